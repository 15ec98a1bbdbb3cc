"""Supervised pointmap + matching training: ``python -m training.train --data DIR --eval_data DIR ...``.

``torchrun --nproc_per_node=P -m training.train ...`` runs DDP. See docs/training.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from pointmap.checkpoint import load_model, load_state_strict, official_to_ours
from pointmap.errors import CheckpointError
from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig
from training.evaluate import evaluate_pairs
from training.loop import fit, load_checkpoint
from training.losses import matching_loss, regression_loss


def build_model(cfg: TrainConfig) -> PointmapNet:
    """From scratch, from a cross-view-completion checkpoint (encoder + decoder), or from weights."""
    if not cfg.init:
        return PointmapNet(PRESETS[cfg.preset])
    path = Path(cfg.init)
    if path.suffix == ".pt":  # one of our training checkpoints (pretraining or training)
        ck = load_checkpoint(path)
        from pointmap.model.config import ModelConfig

        model = PointmapNet(ModelConfig.from_dict(ck["model_config"]))
        load_state_strict(model, official_to_ours(ck["model"]), allow_missing_heads=ck.get("kind") == "pretrain",
                          source=str(path))
        return model
    model = load_model(cfg.init)
    if not isinstance(model, PointmapNet):
        raise CheckpointError(f"--init {cfg.init} is not a PyTorch model")
    return model.train()


def collate(items):
    """Stack a list of (view1, view2) dicts into batched dicts (all items share shapes); non-tensor
    fields (scene names, indices) become lists."""
    def one(v):
        return {k: torch.stack([it[v][k] for it in items]) if isinstance(items[0][v][k], torch.Tensor)
                else [it[v][k] for it in items] for k in items[0][v]}

    return one(0), one(1)


def make_step(cfg: TrainConfig):
    def step_fn(model, batch, step):
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)  # a function of the step: resumable
        view1, view2 = batch
        pred = model(view1["img"], view2["img"])
        loss, details = regression_loss(pred, view1, view2, alpha=cfg.alpha, metric=cfg.metric)
        if pred.has_desc and cfg.match_weight > 0:
            lm, acc = matching_loss(pred.desc1, pred.desc2, view1["corr"], cfg.n_corr, cfg.temperature, gen)
            loss = loss + cfg.match_weight * lm
            details.update(match_loss=float(lm.detach()), match_acc=acc)
        return loss, details

    return step_fn


def main(argv=None) -> int:
    from data.datasets import PairDataset

    cfg = TrainConfig.from_args(argv)
    model = build_model(cfg)
    train_set = PairDataset(cfg.data, size=cfg.size, augment=True, split="train")
    eval_fn = None
    if cfg.eval_data:
        eval_set = PairDataset(cfg.eval_data, size=cfg.size, augment=False, split="all")
        eval_fn = lambda m: evaluate_pairs(m, eval_set, cfg.eval_pairs)  # noqa: E731
    result = fit(cfg, model, train_set, collate, make_step(cfg), eval_fn)
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
