"""Cross-view completion pretraining (CroCo): ``python -m training.pretrain --data DIR ...``.

The checkpoint (out/last.pt) initialises supervised training: ``python -m training.train --init out/last.pt``.
"""

from __future__ import annotations

import sys

import torch

from pointmap.errors import PointmapError
from pointmap.model import PRESETS
from pointmap.model.pretrain import CrossViewCompletion
from training.config import TrainConfig
from training.evaluate import weights_device
from training.loop import TERMINATED_EXIT, error_line, fit, step_generator
from training.losses import completion_loss
from training.mix import open_pairs
from training.train import collate


def make_step(cfg: TrainConfig):
    def step_fn(model, batch, step):
        view1, view2 = batch
        g = step_generator(cfg.seed, step)  # the masks: a resumed run draws the same ones, each rank its own
        net = getattr(model, "module", model)  # DDP's model (torch.compile's wrapper forwards attributes itself)
        p = net.cfg.patch_size
        B, N = view1["img"].shape[0], (view1["img"].shape[-2] // p) * (view1["img"].shape[-1] // p)
        mask = net.random_mask(B, N, generator=g, device=view1["img"].device)
        pred, mask = model(view1["img"], view2["img"], mask)
        with torch.autocast(pred.device.type, enabled=False):  # under --amp the forward ran in bf16; the loss not
            loss = completion_loss(pred.float(), view1["img"], mask, PRESETS[cfg.preset].patch_size)
        return loss, {}

    return step_fn


@torch.inference_mode()
def completion_eval(model, dataset, n: int = 32) -> dict:
    """Held-out completion loss with fixed masks."""
    g = torch.Generator().manual_seed(0)
    losses = []
    dev = weights_device(model)
    for k in range(min(n, len(dataset))):
        v1, v2 = dataset[k]
        img1, img2 = v1["img"][None], v2["img"][None]
        N = (img1.shape[-2] // model.cfg.patch_size) * (img1.shape[-1] // model.cfg.patch_size)
        mask = model.random_mask(1, N, generator=g)
        pred, mask = model(img1.to(dev), img2.to(dev), mask.to(dev))  # where the weights are (a GPU run)
        losses.append(float(completion_loss(pred.cpu(), img1, mask.cpu(), model.cfg.patch_size)))
    return {"completion_loss": sum(losses) / max(len(losses), 1)}


# settings of pointmap training that pretraining would ignore: refused when set, rather than dropped silently
TRAIN_ONLY = ("init", "init_heads", "conf_reset", "metric", "match_weight", "n_corr", "max_rotation", "grey_p",
              "flip_p", "pad_p", "temperature", "coarse_weight", "coarse_temperature", "attn_weight", "pose_head", "desc_stem",
              "pose_weight", "pose_dir_weight", "focal_weight", "attn_heads", "alpha", "focal_head", "focal_head_weight",
              "train_only", "desc_conf_weight", "desc_conf_alpha")


def main(argv=None) -> int:
    cfg = TrainConfig.from_args(["--task", "pretrain", *(argv if argv is not None else sys.argv[1:])],
                                prog="python -m training.pretrain")
    if cfg.task != "pretrain":
        print(f"error: --task {cfg.task} is python -m training.train's; training.pretrain runs cross-view completion",
              file=sys.stderr)
        return 2
    ignored = [f"--{k}" for k in TRAIN_ONLY if getattr(cfg, k) != getattr(TrainConfig, k)]
    if ignored:
        print(f"error: {', '.join(ignored)} set pointmap training (python -m training.train); cross-view completion "
              "pretraining starts from scratch and would ignore them", file=sys.stderr)
        return 2
    try:
        torch.manual_seed(cfg.seed)  # --seed seeds the initial weights too
        model = CrossViewCompletion(PRESETS[cfg.preset], mask_ratio=cfg.mask_ratio)
        train_set = open_pairs(cfg.data, size=cfg.size, augment=True, split="train", crop_link=cfg.crop_link)
        eval_set = open_pairs(cfg.eval_data, size=cfg.size, augment=False, split="all") if cfg.eval_data else None
        eval_fn = None
        if eval_set is not None:
            eval_fn = lambda m: completion_eval(m, eval_set, cfg.eval_pairs)  # noqa: E731
        result = fit(cfg, model, train_set, collate, make_step(cfg), eval_fn)
    except (ValueError, OSError, PointmapError, FloatingPointError) as e:
        print(f"error: {error_line(e)}", file=sys.stderr)
        return 2
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()})
    return TERMINATED_EXIT if result.get("terminated") else 0  # a chained `&& ship` must not take it as finished


if __name__ == "__main__":
    sys.exit(main())
