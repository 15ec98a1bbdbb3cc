"""Supervised pointmap + matching training: ``python -m training.train --data DIR --eval_data DIR ...``.

``torchrun --nproc_per_node=P -m training.train ...`` runs DDP. See docs/training.md.
"""

from __future__ import annotations

import contextlib
import math
import sys
from pathlib import Path

import torch

from pointmap.checkpoint import (
    HeadlessCheckpointError,
    load_model,
    load_official,
    load_state_strict,
    load_trunk,
    model_licence,
    official_to_ours,
)
from pointmap.errors import CheckpointError, PointmapError
from pointmap.model import PRESETS, PointmapNet
from training.config import TrainConfig, grown_depths
from training.evaluate import evaluate_pairs
from training.grow import is_growth, silent_parameters
from training.loop import TERMINATED_EXIT, error_line, fit, load_checkpoint, step_generator
from training.losses import (
    cell_correspondence_counts,
    cross_attention_loss,
    descriptor_confidence_loss,
    focal_head_loss,
    focal_loss,
    matching_loss,
    patch_matching_loss,
    pose_loss,
    regression_loss,
)
from training.mix import limit_rotation, open_pairs


def _init_state(path: Path):
    """(state dict under our key names, model config, kind, lineage) of any --init source; the lineage holds the
    growth history ``training.grow`` records (``grown_from``, None where the source does not record one) and the
    weights' licence (``licence``, None where none is recorded: an official checkpoint records its own)."""
    if path.suffix == ".pt":  # one of our training checkpoints (pretraining or training)
        from pointmap.model.config import ModelConfig

        ck = load_checkpoint(path)
        extra = ck.get("extra") or {}
        return (official_to_ours(ck["model"]), ModelConfig.from_dict(ck["model_config"]), ck.get("kind"),
                {"grown_from": extra.get("grown_from"), "licence": extra.get("licence")})
    try:
        model = load_model(str(path))
    except HeadlessCheckpointError:  # a CroCo pretraining file: its trunk, the heads start fresh (seeded)
        model = load_official(path, allow_missing_heads=True)
    if not isinstance(model, PointmapNet):
        raise CheckpointError(f"--init {path} is not a PyTorch model")
    prov = getattr(model, "provenance", None) or {}
    return model.state_dict(), model.cfg, "weights", {"grown_from": prov.get("grown_from"),
                                                      "licence": model_licence(model)}


def build_model(cfg: TrainConfig) -> PointmapNet:
    """From scratch, from a cross-view-completion checkpoint (encoder + decoder), or from weights.

    ``--init_heads fresh`` builds ``--preset`` and takes only the trunk (and heads whose shapes match) from
    ``--init``: fine-tuning into a changed head, as MASt3R was trained from DUSt3R. Fresh weights are drawn
    after ``torch.manual_seed(cfg.seed)``: ``--seed`` makes them reproducible."""
    torch.manual_seed(cfg.seed)
    preset = PRESETS[cfg.preset].replace(pose_head=True) if cfg.pose_head else PRESETS[cfg.preset]
    if cfg.focal_head:
        preset = preset.replace(focal_head=True)
    if cfg.desc_stem:
        preset = preset.replace(desc_stem=cfg.desc_stem)
    if not cfg.init:
        model = PointmapNet(preset)
        model.growth = []  # never grown
        model.licence = None  # our own weights: training.ship labels them
        return model
    state, model_cfg, kind, lineage = _init_state(Path(cfg.init))
    if cfg.init_heads == "fresh":
        model = PointmapNet(preset)
        fresh = load_trunk(model, state, source=cfg.init)
        print(f"--init {cfg.init}: trunk loaded; {len(fresh)} head tensors start fresh"
              + (f" (e.g. {fresh[:3]})" if fresh else ""), file=sys.stderr)
    else:
        if cfg.pose_head and not model_cfg.pose_head:
            raise CheckpointError(f"--init {cfg.init} has no pose head: add --init_heads fresh to start one")
        if cfg.desc_stem and model_cfg.desc_stem != cfg.desc_stem:
            raise CheckpointError(f"--init {cfg.init} has desc_stem {model_cfg.desc_stem}, --desc_stem asks for "
                                  f"{cfg.desc_stem}: add --init_heads fresh to start a new one")
        if cfg.focal_head and not model_cfg.focal_head:  # a new focal head on a trained model: it starts fresh
            model_cfg = model_cfg.replace(focal_head=True)  # (returning the pointmap's focal until it trains)
            fresh = {k: v for k, v in PointmapNet(model_cfg).state_dict().items() if k.startswith("focal_head.")}
            state = {**state, **fresh}
            print(f"--init {cfg.init}: a fresh focal head added ({len(fresh)} tensors)", file=sys.stderr)
        model = PointmapNet(model_cfg)
        load_state_strict(model, state, allow_missing_heads=kind == "pretrain", source=cfg.init)
    if cfg.conf_reset:
        reset_confidence(model, cfg.conf_reset)
    model.growth = lineage["grown_from"]  # training.grow's record (None: --init does not say), kept in the run's
    model.licence = lineage["licence"]  # checkpoints, as the licence of the weights it starts from
    return model.train()


def lineage_extra(model: PointmapNet) -> dict | None:
    """What every checkpoint of a run records of the model's lineage (``build_model``'s ``growth`` and ``licence``,
    those known), read back by a later ``--init`` and by ``training.ship``; None when neither is known."""
    return {k: v for k, v in (("grown_from", getattr(model, "growth", None)),
                              ("licence", getattr(model, "licence", None))) if v is not None} or None


def reset_confidence(model: PointmapNet, conf: float) -> None:
    """Restart both heads' pointmap confidence at ``conf`` everywhere (``DownstreamHead.reset_conf``).

    Why: the confidence is ``1 + exp(x)`` and DUSt3R's loss ``conf * err - alpha * log(conf)`` wants it above 1
    only where the normalised error is below alpha (0.2). A young model's error is above that everywhere, so
    x falls; once it is near -13 (as in the shipped v17: every pixel's confidence 1.000) its gradient is
    scaled by e^-13 and the channel stays dead even where the error has since fallen below alpha (a third
    of v17's pixels). A resumed run loads its own weights after this, so only the first start is affected."""
    kind, vmin, vmax = model.cfg.conf_mode
    if not vmin < conf < vmax:
        raise ValueError(f"--conf_reset expected a confidence between the model's floor {vmin} and ceiling "
                         f"{vmax}, got {conf}")
    if kind == "sigmoid":
        u = (conf - vmin) / (vmax - vmin)
        raw = math.log(u / (1 - u))
    else:
        raw = math.log(conf - vmin)
    for head in (model.downstream_head1, model.downstream_head2):
        head.reset_conf(raw)
    print(f"--conf_reset {conf}: confidence channels restart at raw {raw:.3f}", file=sys.stderr)


def collate(items):
    """Stack a list of (view1, view2) dicts into batched dicts (all items share shapes); non-tensor
    fields (scene names, indices) become lists."""
    def one(v):
        return {k: torch.stack([it[v][k] for it in items]) if isinstance(items[0][v][k], torch.Tensor)
                else [it[v][k] for it in items] for k in items[0][v]}

    return one(0), one(1)


class ForwardTaps:
    """Forward hooks that record, only while armed (inside ``recording()``, around a training step's own
    forward pass): the inputs of every decoder cross-attention and the pose head's match scores (for
    ``cross_attention_loss``), and the pose head's transform (for ``pose_loss``). Evaluation, inference and any
    other forward pass record nothing."""

    def __init__(self, model, *, attention: bool, pose: bool) -> None:
        net = getattr(model, "module", model)
        self.armed = False
        self.clear()
        if pose:
            if getattr(net, "pose_head", None) is None:
                raise ValueError("--pose_weight needs a model with a pose head (--pose_head true)")
            net.pose_head.register_forward_hook(self._pose_hook)
        if attention:
            for view, blocks in ((1, net.dec_blocks), (2, net.dec_blocks2)):
                for b in blocks:
                    b.cross_attn.register_forward_hook(self._cross_hook(view))
            if getattr(net, "pose_head", None) is not None:
                net.pose_head.match.register_forward_hook(self._match_hook)

    def _match_hook(self, mod, args, out):
        if self.armed:
            self.match = out

    def _pose_hook(self, mod, args, out):
        if self.armed:
            self.pose = out

    def _cross_hook(self, view):
        def hook(mod, args, out):
            if self.armed:
                self.cross[view].append((mod, args))
        return hook

    @contextlib.contextmanager
    def recording(self):
        self.clear()
        self.armed = True
        try:
            yield self
        finally:
            self.armed = False

    def clear(self) -> None:
        self.cross, self.pose, self.match = {1: [], 2: []}, None, None

    def scores(self, heads: int) -> tuple[list, list]:
        """Logits [B, heads, Nq, Nk] per decoder layer: (view-1 queries over view 2, view-2 queries over view 1)."""
        return tuple([m.scores(*_fp32(args), heads=heads) for m, args in self.cross[v]] for v in (1, 2))


def make_step(cfg: TrainConfig):
    def step_fn(model, batch, step):
        gen = step_generator(cfg.seed, step)  # sampled correspondences: resumable, each rank its own
        view1, view2 = batch
        if step_fn.taps is None:
            step_fn.taps = ForwardTaps(model, attention=cfg.attn_weight > 0, pose=cfg.pose_weight > 0)
        taps = step_fn.taps
        with taps.recording():
            pred = model(view1["img"], view2["img"])
        # under --amp the forward ran in bf16; every loss is computed in float32, outside autocast
        pred = pred.map(_fp32)
        with torch.autocast(pred.pts1_cam1.device.type, enabled=False):
            return _losses(cfg, model, taps, pred, view1, view2, gen)

    step_fn.taps = None  # ForwardTaps, made at the first step (it needs the model)
    return step_fn


def _fp32(x):
    """Floating tensors (also inside tuples and lists) as float32; anything else as it is."""
    if torch.is_tensor(x):
        return x.float() if x.is_floating_point() else x
    if isinstance(x, (tuple, list)):
        return type(x)(_fp32(v) for v in x)
    return x


def _losses(cfg: TrainConfig, model, taps: ForwardTaps, pred, view1, view2, gen):
    """The step's total loss and its logged details, from a float32 prediction and the recorded taps."""
    loss, details = regression_loss(pred, view1, view2, alpha=cfg.alpha, metric=cfg.metric)
    if pred.has_desc and cfg.match_weight > 0:
        lm, acc = matching_loss(pred.desc1, pred.desc2, view1["corr"], cfg.n_corr, cfg.temperature, gen)
        loss = loss + cfg.match_weight * lm
        details.update(match_loss=float(lm.detach()), match_acc=acc)
    if pred.has_desc and cfg.desc_conf_weight > 0:  # after matching_loss: its draws from gen stay as they were
        # (a model without its own descriptor confidence is refused by check_model_options)
        ld, mean_c = descriptor_confidence_loss(pred.desc1, pred.desc2, pred.desc_conf1, pred.desc_conf2,
                                                view1["corr"], cfg.n_corr, cfg.temperature, cfg.desc_conf_alpha, gen)
        loss = loss + cfg.desc_conf_weight * ld
        details.update(desc_conf_loss=float(ld.detach()), desc_conf=mean_c)
    if pred.has_desc and cfg.coarse_weight > 0:
        patch = getattr(model, "module", model).cfg.patch_size
        lc, acc = patch_matching_loss(pred.desc1, pred.desc2, view1["corr"], patch, cfg.coarse_temperature)
        loss = loss + cfg.coarse_weight * lc
        details.update(coarse_loss=float(lc.detach()), coarse_acc=acc)
    if cfg.pose_weight > 0:
        lp, d = pose_loss(_fp32(taps.pose), pred, view1, view2, metric=cfg.metric, dir_weight=cfg.pose_dir_weight)
        loss = loss + cfg.pose_weight * lp
        details.update(pose_loss=float(lp.detach()), **d)
    if cfg.focal_weight > 0:
        lf, d = focal_loss(pred.pts1_cam1, view1["K"], view1["valid"])
        loss = loss + cfg.focal_weight * lf
        details.update(focal_loss=float(lf.detach()), **d)
    if cfg.focal_head_weight > 0:
        lh, d = focal_head_loss(pred, view1["K"], view2["K"])
        loss = loss + cfg.focal_head_weight * lh
        details.update(focal_head_loss=float(lh.detach()), **d)
    if cfg.attn_weight > 0:
        net = getattr(model, "module", model)
        counts = cell_correspondence_counts(view1["corr"], net.cfg.patch_size, view2["img"].shape[-2:])
        min_px = net.cfg.patch_size ** 2 // 8  # a token takes part when >= 1/8 of its pixels are co-visible
        s12, s21 = taps.scores(cfg.attn_heads)
        la, acc = cross_attention_loss(s12, s21, counts, min_pixels=min_px)
        loss = loss + cfg.attn_weight * la
        details.update(attn_loss=float(la.detach()), attn_acc=acc)
        if taps.match is not None:  # the pose head's own correspondence field, supervised the same way
            lm2, acc2 = cross_attention_loss([_fp32(taps.match)[:, None]], [], counts, min_pixels=min_px)
            loss = loss + cfg.attn_weight * lm2
            details.update(pose_match_loss=float(lm2.detach()), pose_match_acc=acc2)
    taps.clear()
    return loss, details


def grown_lr_scale(cfg: TrainConfig, model: PointmapNet) -> dict[str, float]:
    """``--grown_from`` / ``--grown_lr``: the learning-rate multiplier of each parameter the model's last growth
    zeroed (``training.grow.silent_parameters``); {} without ``--grown_from`` or at ``--grown_lr 1``. ValueError
    (one line) when the model cannot have grown from ``--grown_from``: depths that are not fewer, or a growth
    history (``model.growth``, from ``--init``) whose last entry is other depths. A model whose history is
    unknown (None: a checkpoint written before runs recorded it) takes ``--grown_from`` as its history, with a
    warning."""
    if not cfg.grown_from:
        return {}
    enc, dec = grown_depths(cfg.grown_from)
    have = (model.cfg.enc_depth, model.cfg.dec_depth)
    if not is_growth((enc, dec), have):
        raise ValueError(f"--grown_from {cfg.grown_from}: the model has {have[0]} encoder and {have[1]} decoder "
                         "blocks, so it was not grown from those depths (expected fewer blocks in at least one)")
    growth = getattr(model, "growth", None)
    if growth is None:
        print(f"warning: --init {cfg.init} records no growth history; taking --grown_from {cfg.grown_from} as "
              "its last growth", file=sys.stderr)
        model.growth = [{"enc_depth": enc, "dec_depth": dec}]
    elif not growth:
        raise ValueError(f"--grown_from {cfg.grown_from}: the model ({cfg.init or 'built from scratch'}) was "
                         "never grown (training.grow records each growth in the provenance's grown_from)")
    elif (growth[-1]["enc_depth"], growth[-1]["dec_depth"]) != (enc, dec):
        raise ValueError(f"--grown_from {cfg.grown_from}: the --init model's last growth was from "
                         f"{growth[-1]['enc_depth']},{growth[-1]['dec_depth']} (its grown_from record: {growth})")
    if cfg.grown_lr == 1:
        return {}
    names = silent_parameters([n for n, _ in model.named_parameters()], enc, dec, *have)
    return {n: cfg.grown_lr for n in names}


def freeze_except(model: PointmapNet, train_only: str) -> int:
    """``--train_only``: parameters whose names start with none of the comma-separated prefixes stop requiring
    gradients (the optimizer leaves them out, autograd stops before them). Returns how many tensors train after
    it; "" changes no flag and returns the count of all parameter tensors. ValueError (one line) for an empty
    prefix or one that names no parameter."""
    if not train_only:
        return sum(1 for _ in model.parameters())
    prefixes = [p.strip() for p in train_only.split(",")]
    names = [n for n, _ in model.named_parameters()]
    for pre in prefixes:
        if not pre or not any(n.startswith(pre) for n in names):
            raise ValueError(f"--train_only {train_only!r}: {pre!r} names no parameter of this model (prefixes of "
                             f"names such as {names[0]!r} or {names[-1]!r})")
    kept = 0
    for n, p in model.named_parameters():
        p.requires_grad_(n.startswith(tuple(prefixes)))
        kept += p.requires_grad
    return kept


def idle_parameters(cfg: TrainConfig, model: PointmapNet) -> list[str]:
    """Names of the parameters no loss of this run reaches: a focal head's at --focal_head_weight 0 (every other
    module feeds the pointmap loss: descriptors at matching weights 0 still get gradients, through the confidence
    and the pose head). They get no gradient: ``freeze_idle`` freezes them, so the optimizer leaves them out and
    DDP, which waits for a gradient of every trainable parameter, does not stop the run at its second step (its search
    for unused parameters does not find outputs that no loss reads)."""
    return [n for n, _ in model.named_parameters() if n.startswith("focal_head.") and cfg.focal_head_weight <= 0]


def freeze_idle(cfg: TrainConfig, model: PointmapNet) -> list[str]:
    """Freeze ``idle_parameters`` (after ``freeze_except``: it only ever turns gradients off). Returns their names.
    ValueError when nothing would be left to train."""
    idle = set(idle_parameters(cfg, model))
    for n, p in model.named_parameters():
        if n in idle:
            p.requires_grad_(False)
    if not any(p.requires_grad for p in model.parameters()):
        raise ValueError(f"nothing to train: every parameter {'--train_only ' + cfg.train_only + ' keeps' if cfg.train_only else ''}"
                         " is one no loss reaches (a focal head needs --focal_head_weight > 0)")
    return sorted(idle)


def check_model_options(cfg: TrainConfig, model: PointmapNet) -> None:
    """Options that depend on the architecture, checked before any data is opened."""
    if cfg.attn_weight > 0 and cfg.attn_heads > model.cfg.dec_heads:
        raise ValueError(f"--attn_heads {cfg.attn_heads} exceeds the decoder's {model.cfg.dec_heads} heads")
    if cfg.pose_weight > 0 and not model.cfg.pose_head:
        raise ValueError("--pose_weight needs a model with a pose head (--pose_head true)")
    if cfg.pose_dir_weight > 0 and cfg.pose_weight <= 0:
        raise ValueError("--pose_dir_weight weighs a term of the pose loss: it needs --pose_weight > 0")
    focal_only = bool(cfg.train_only) and all(p.strip().startswith("focal_head") for p in cfg.train_only.split(","))
    if model.cfg.pose_head and cfg.pose_weight <= 0 and cfg.task == "train" and not focal_only:
        # pts2_cam1 = T * head2: any rigid motion can move between the two without changing the regression loss,
        # so only a loss on T pins head 2 to view 2's own frame
        raise ValueError("a model with a pose head needs --pose_weight > 0 (the pointmap loss alone does not fix "
                         "which frame view 2's head predicts in; unless only the focal head trains)")
    if cfg.focal_head_weight > 0 and not model.cfg.focal_head:
        raise ValueError("--focal_head_weight needs a model with a focal head (--focal_head true)")
    if not model.cfg.has_desc:  # (match_weight's default stays allowed: a DUSt3R-style model trains with defaults)
        matching = [f"--{k} {getattr(cfg, k)}" for k in ("match_weight", "coarse_weight", "desc_conf_weight")
                    if getattr(cfg, k) > 0 and getattr(cfg, k) != getattr(TrainConfig, k)]
        if matching:
            raise ValueError(f"{', '.join(matching)} train descriptors, which this model does not have (head "
                             f"{model.cfg.head!r}): set them to 0, or use a model with a descriptor head")
    if cfg.desc_conf_weight > 0 and not model.cfg.two_confs:
        raise ValueError("--desc_conf_weight needs a model whose descriptor head predicts its own confidence "
                         "(two_confs); this one's descriptor confidence is the pointmap's")


def main(argv=None) -> int:
    cfg = TrainConfig.from_args(argv, prog="python -m training.train")
    if cfg.task != "train":
        print("error: --task pretrain is python -m training.pretrain's (cross-view completion); training.train "
              "trains pointmaps + matching", file=sys.stderr)
        return 2
    if cfg.mask_ratio != TrainConfig.mask_ratio:  # pretraining's setting (as pretrain refuses training's)
        print(f"error: --mask_ratio sets cross-view completion pretraining (python -m training.pretrain); "
              f"training.train masks nothing and would ignore it (got {cfg.mask_ratio})", file=sys.stderr)
        return 2
    try:
        model = build_model(cfg)
        check_model_options(cfg, model)
        lr_scale = grown_lr_scale(cfg, model)
        trainable = freeze_except(model, cfg.train_only)
        idle = freeze_idle(cfg, model)
        train_set = limit_rotation(open_pairs(cfg.data, size=cfg.size, augment=True, split="train",
                                              crop_link=cfg.crop_link, grey_p=cfg.grey_p, flip_p=cfg.flip_p,
                                              pad_p=cfg.pad_p),
                                 cfg.max_rotation)
        eval_set = open_pairs(cfg.eval_data, size=cfg.size, augment=False, split="all") if cfg.eval_data else None
    except (ValueError, OSError, PointmapError) as e:  # bad flags, --init or --data: one line, before any step
        print(f"error: {e}", file=sys.stderr)
        return 2
    eval_fn = None
    if eval_set is not None:
        eval_fn = lambda m: evaluate_pairs(m, eval_set, cfg.eval_pairs)  # noqa: E731
    if lr_scale:
        print(f"--grown_lr {cfg.grown_lr}: {len(lr_scale)} tensors (the output projections of the blocks grown from "
              f"{cfg.grown_from})", file=sys.stderr)
    if cfg.train_only:
        print(f"--train_only {cfg.train_only}: {trainable} parameter tensors train, the rest is frozen", file=sys.stderr)
    if idle:
        print(f"the focal head's {len(idle)} parameter tensors are frozen: no loss reaches them (--focal_head_weight "
              "trains them)", file=sys.stderr)
    extra = lineage_extra(model)
    try:
        result = fit(cfg, model, train_set, collate, make_step(cfg), eval_fn, lr_scale=lr_scale, extra=extra)
    except (PointmapError, FloatingPointError, OSError) as e:  # a resume that does not fit, a shard that cannot be
        print(f"error: {error_line(e)}", file=sys.stderr)      # read, a loss gone NaN, a full disk: one line
        return 2
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()})
    return TERMINATED_EXIT if result.get("terminated") else 0  # a chained `&& ship` must not take it as finished


if __name__ == "__main__":
    sys.exit(main())
