"""Training configuration: a dataclass, filled from defaults, an optional JSON file, then CLI overrides."""

from __future__ import annotations

import argparse
import inspect
import io
import json
import math
import os
import sys
import tokenize
from dataclasses import MISSING, asdict, dataclass, fields


@dataclass
class TrainConfig:
    task: str = "train"            # "train" (pointmaps + matching) or "pretrain" (cross-view completion)
    data: str = ""                 # shard root of training pairs (python -m data.render --kind pairs)
    eval_data: str = ""            # shard root of the held-out pairs (never trained on)
    out: str = "runs/train"        # checkpoints, logs
    preset: str = "small"          # model preset (pointmap.model.PRESETS)
    init: str = ""                 # "", a pretraining checkpoint, our .safetensors, or an official .pth
    init_heads: str = "strict"     # "strict": --init's architecture as is; "fresh": --preset's architecture,
                                   # trunk from --init, heads from --init where their shapes match
    resume: bool = True            # continue from out/last.pt when it exists
    size: int = 224                # training resolution (long side)
    batch_size: int = 8            # per process
    steps: int = 20000             # optimizer steps in all (the schedule's length)
    lr: float = 2e-4               # AdamW's peak learning rate (after warmup)
    min_lr: float = 1e-6           # the learning rate at the schedule's end
    warmup: int = 500              # steps of linear warmup from 0 to --lr
    schedule: str = "cosine"       # after warmup: "cosine" to min_lr at --steps, or "wsd" (warmup-stable-decay):
                                   # constant lr, then the last --decay_steps fall to min_lr (1 - sqrt shape)
    decay_steps: int = 0           # wsd: length of the final decay (its first step also saves out/stable_<step>.pt)
    weight_decay: float = 0.05     # AdamW's (betas 0.9, 0.95)
    clip: float = 1.0              # the gradient's global norm is clipped to this
    alpha: float = 0.2             # confidence regulariser of the regression loss
    conf_reset: float = 0.0        # > 0: restart both heads' confidence channel at this confidence everywhere
                                   # (weights 0, bias set; must be above the floor of 1) before training from
                                   # --init, for a channel that collapsed to its floor (train.reset_confidence)
    metric: bool = False           # metric regression (GT scale for both)
    match_weight: float = 0.075    # weight of the InfoNCE matching loss
    n_corr: int = 1024             # correspondences per pair for the matching loss
    desc_conf_weight: float = 0.0  # weight of the descriptor confidence's loss (losses.descriptor_confidence_loss:
                                   # MASt3R's ConfMatchingLoss with the InfoNCE held fixed; 0 = off, the confidence
                                   # untrained, as in every model up to v72x)
    desc_conf_alpha: float = 10.0  # its -alpha log c term: the confidence learns alpha / (the match's InfoNCE)
    max_rotation: float = 0.0      # curriculum: train only on pairs whose cameras differ by <= this (deg; 0 = all)
    crop_link: float = 1.0         # probability that view 2's random crop has view 1's scale
                                   # (data.PairDataset): the pair keeps its rendered focal ratio, so
                                   # magnification means motion
    grey_p: float = 0.0            # probability that a training pair is turned grey (both views; a monochrome
                                   # camera, as OpenCV's stereo sample: data.PairDataset)
    flip_p: float = 0.0            # probability that a training pair is mirrored left-right (a mirrored scene seen
                                   # by mirrored cameras: data.PairDataset; 0 replays earlier recipes exactly)
    pad_p: float = 0.0             # probability that each view of a training pair is letterboxed (a band at two
                                   # edges flat grey and invalid: data.PairDataset; 0 replays earlier recipes)
    temperature: float = 0.05      # InfoNCE temperature of the pixel matching loss
    coarse_weight: float = 0.0     # weight of the patch-level InfoNCE (losses.patch_matching_loss; 0 = off)
    coarse_temperature: float = 0.1  # InfoNCE temperature of the patch-level matching loss
    attn_weight: float = 0.0       # weight of the cross-attention supervision (losses.cross_attention_loss; 0 = off)
    pose_head: bool = False        # build --preset with a pose head (model.heads.PoseHead): rigid view-2 points
    desc_stem: int = 0             # > 0: build --preset with a descriptor stem of this many channels (DescStem)
    pose_weight: float = 0.0       # weight of the direct loss on the pose head's transform (losses.pose_loss)
    pose_dir_weight: float = 0.0   # within the pose loss: weight of the translation-direction term (0 = off)
    focal_weight: float = 0.0      # weight of |log focal error| of view 1's own-frame pointmap (losses.focal_loss;
                                   # 0 = off, which replays earlier recipes exactly)
    focal_head: bool = False       # build the model with a focal head (model.heads.FocalHead; needs --pose_head or
                                   # an --init with one); an --init without one starts it fresh, where it returns
                                   # the pointmap's own focal (its read-out starts at zero)
    focal_head_weight: float = 0.0  # weight of the focal head's |log focal error|, both views (losses.focal_head_loss)
    attn_heads: int = 1            # supervised heads per decoder layer (the first ones; the rest stay free)
    grown_from: str = ""           # "ENC,DEC": the --init model's last growth (training.grow) was from these depths
    grown_lr: float = 1.0          # ... and the output projections that growth zeroed train at this multiple of
                                   # --lr, weight decay included (they start at 0; AdamW moves every weight by
                                   # about the same step, so at 1 they stay near 0 for thousands of steps:
                                   # docs/training.md, Growing a model)
    train_only: str = ""           # "PREFIX[,PREFIX...]": only parameters whose names start with one of these train
                                   # (e.g. "pose_head"); the rest is frozen (unchanged, no gradient computed)
    mask_ratio: float = 0.9        # pretraining
    ckpt_every: int = 200          # write out/last.pt (atomically, resumable) every this many steps
    ckpt_minutes: float = 10.0     # also checkpoint when this much wall time passed since the last one (0: off), so
                                   # a slow run killed outright loses minutes, not ckpt_every steps; SIGTERM itself
                                   # checkpoints the current step and stops (resume with the same command)
    eval_every: int = 1000         # evaluate on --eval_data every this many steps
    eval_pairs: int = 64           # held-out pairs per evaluation
    log_every: int = 10            # a row of train.csv and TensorBoard every this many steps
    seed: int = 0                  # seeds initialisation, data order and augmentation
    workers: int = 1               # data-loading processes
    threads: int = 0               # torch threads (0: torch default)
    max_minutes: float = 0.0       # stop (after a checkpoint) when this wall time is spent; 0 = no limit
    decay_by_time: bool = False    # wsd + --max_minutes: the stable phase ends when the minutes left fit just the
                                   # decay at the pace measured so far (--steps is then an upper bound)
    decay_ckpts: bool = False      # wsd: also keep each checkpoint written inside the decay as out/decay_<step>.pt
                                   # (full, resumable checkpoints; `training.ship --ckpt` averages them)
    keep_decay: bool = True        # resuming a --decay_by_time run: finish the decay a previous leg placed (false:
                                   # forget it and place a new one, e.g. when that leg measured its pace while
                                   # other jobs loaded the machine and so started the decay too early)
    amp: str = "auto"              # bf16 autocast of the network's forward: "auto" (GPUs that support it), "bf16"
                                   # (any device; no gain for `small` on this CPU, docs/training.md), "off";
                                   # losses are always computed in float32
    compile: bool = False          # torch.compile the training forward/backward (1.24x on 2 CPU threads; ~2 min
                                   # of compilation per image shape, docs/benchmarks.md); evaluation stays eager
    quiet: bool = False            # no progress bar

    @classmethod
    def from_args(cls, argv=None, prog: str | None = None) -> TrainConfig:
        p = argparse.ArgumentParser(prog=prog, description="pointmap training (see docs/training.md)")
        p.add_argument("--config", default=None, help="JSON file with config values (CLI flags override it)")
        notes = field_comments(cls)
        for f in fields(cls):
            default = f.default if f.default is not MISSING else None
            text = f"{notes[f.name]} " if f.name in notes else ""
            text = (text + f"(default: {default!r})").replace("%", "%%")
            if isinstance(default, bool):
                p.add_argument(f"--{f.name}", type=_bool, default=None, metavar="BOOL", help=text)
            else:
                p.add_argument(f"--{f.name}", type=type(default), default=None, help=text)
        ns = p.parse_args(argv)
        values = {}
        if ns.config:
            try:
                with open(ns.config) as fh:
                    loaded = json.load(fh)
            except (OSError, ValueError) as e:  # ValueError: JSONDecodeError, or UnicodeDecodeError (a binary file)
                p.error(f"--config {ns.config}: not a readable JSON file ({e})")
            if not isinstance(loaded, dict):
                p.error(f"--config {ns.config} expected a JSON object of config values, got {type(loaded).__name__}")
            unknown = set(loaded) - {f.name for f in fields(cls)}
            if unknown:
                p.error(f"unknown keys in {ns.config}: {sorted(unknown)}")
            for f in fields(cls):  # the file's values get the CLI's types: "false" is False, "100" is 100
                if f.name in loaded:
                    try:
                        values[f.name] = _typed(f.default, loaded[f.name])
                    except (TypeError, ValueError, argparse.ArgumentTypeError):
                        p.error(f"--config {ns.config}: {f.name} expected {type(f.default).__name__}, got "
                                f"{loaded[f.name]!r}")
        values.update({k: v for k, v in vars(ns).items() if k != "config" and v is not None})
        cfg = cls(**values)
        if cfg.task not in ("train", "pretrain"):
            p.error(f"--task expected 'train' or 'pretrain', got {cfg.task!r}")
        bad = range_errors(cfg)
        if bad:
            p.error("; ".join(bad))
        if cfg.warmup >= cfg.steps:
            print(f"warning: --warmup {cfg.warmup} >= --steps {cfg.steps}: the learning rate never reaches --lr",
                  file=sys.stderr)
        given = [f"--{k} {getattr(cfg, k)}" for k in ("eval_every", "eval_pairs") if getattr(cfg, k) != getattr(cls, k)]
        if given and not cfg.eval_data:  # a warning, not an error: "--eval_every 100000" is how runs say "never"
            print(f"warning: {' and '.join(given)} without --eval_data: the run evaluates nothing", file=sys.stderr)
        from training.loop import check_loop_options

        try:
            check_loop_options(cfg)
        except ValueError as e:
            p.error(str(e))
        for f in fields(cls):  # NaN passes the plain range checks below (each comparison is False) and inf overflows
            value = getattr(cfg, f.name)
            if isinstance(f.default, float) and not math.isfinite(value):
                p.error(f"--{f.name} expected a finite number, got {value}")
        if cfg.init_heads not in ("strict", "fresh"):
            p.error(f"--init_heads expected 'strict' or 'fresh', got {cfg.init_heads!r}")
        if cfg.init_heads == "fresh" and not cfg.init:
            p.error("--init_heads fresh needs --init (the checkpoint whose encoder/decoder to start from)")
        if cfg.conf_reset and not cfg.init:
            p.error("--conf_reset restarts the confidence of an --init model; a model from scratch starts fresh anyway")
        for name in ("match_weight", "coarse_weight", "attn_weight", "pose_weight", "pose_dir_weight", "focal_weight",
                     "focal_head_weight", "conf_reset", "desc_conf_weight"):
            if getattr(cfg, name) < 0:
                p.error(f"--{name} expected >= 0 (a negative weight would maximise its loss), got {getattr(cfg, name)}")
        if cfg.grown_lr <= 0:
            p.error(f"--grown_lr expected a learning-rate multiplier > 0, got {cfg.grown_lr}")
        if cfg.task == "pretrain" and (cfg.grown_from or cfg.grown_lr != 1):
            p.error("--grown_from / --grown_lr are for training a grown model (task train), not pretraining")
        if cfg.grown_from and not cfg.init:
            p.error("--grown_from needs --init (the grown model: training.grow's output, or a checkpoint of its run)")
        if cfg.grown_from:
            try:
                grown_depths(cfg.grown_from)
            except ValueError as e:
                p.error(str(e))
        elif cfg.grown_lr != 1:
            p.error("--grown_lr needs --grown_from ENC,DEC (the depths training.grow grew the --init model from)")
        if cfg.attn_heads < 1:
            p.error(f"--attn_heads expected >= 1 (supervised heads per decoder layer), got {cfg.attn_heads}")
        if not cfg.data:
            p.error("--data is required (a directory of shards written by python -m data.render)")
        trained = {os.path.realpath(r) for r in cfg.data.split(",") if r}
        both = [r for r in cfg.eval_data.split(",") if r and os.path.realpath(r) in trained]
        if both:  # its held-out metrics would be measured on pairs the run trains on
            p.error(f"--eval_data expected held-out shards (never trained on), got {', '.join(both)}, which --data "
                    "trains on")
        return cfg

    def to_dict(self) -> dict:
        return asdict(self)


def _typed(default, value):
    """A config file's ``value`` as the type of the field whose default is ``default`` (as the CLI parses it)."""
    if isinstance(default, bool):
        return value if isinstance(value, bool) else _bool(str(value))
    if isinstance(default, int):
        if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
            raise ValueError(value)
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool):
            raise ValueError(value)
        return float(value)
    if not isinstance(value, str):
        raise TypeError(value)
    return value


def range_errors(cfg: TrainConfig) -> list[str]:
    """One message per setting out of its range (types are the CLI's; the schedule's own checks are
    ``training.loop.check_loop_options``)."""
    from pointmap.images import INPUT_SIZE_RULE, is_input_size
    from pointmap.model import PRESETS

    out = []
    if cfg.preset not in PRESETS:
        out.append(f"--preset expected one of {sorted(PRESETS)}, got {cfg.preset!r}")
    at_least = {"batch_size": 1, "steps": 1, "log_every": 1, "ckpt_every": 1, "eval_every": 1, "eval_pairs": 1,
                "warmup": 0, "decay_steps": 0, "workers": 0, "threads": 0, "desc_stem": 0}
    out += [f"--{k} expected >= {v}, got {getattr(cfg, k)}" for k, v in at_least.items() if getattr(cfg, k) < v]
    if not is_input_size(cfg.size):
        out.append(f"--size expected {INPUT_SIZE_RULE}, got {cfg.size}")
    positive = ("lr", "clip", "alpha", "temperature", "coarse_temperature", "desc_conf_alpha")
    out += [f"--{k} expected a finite value > 0, got {getattr(cfg, k)}" for k in positive
            if not 0 < getattr(cfg, k) < math.inf]
    nonneg = ("min_lr", "weight_decay", "max_rotation", "max_minutes", "ckpt_minutes")
    out += [f"--{k} expected a finite value >= 0, got {getattr(cfg, k)}" for k in nonneg
            if not 0 <= getattr(cfg, k) < math.inf]
    if cfg.n_corr < 8:  # a pair with fewer than 8 correspondences is left out of the matching losses
        out.append(f"--n_corr expected >= 8 (the matching losses leave out a pair with fewer correspondences: fewer "
                   f"would train nothing), got {cfg.n_corr}")
    if not 0 <= cfg.seed < 2 ** 31:  # numpy takes seeds below 2**32, and each rank adds its own
        out.append(f"--seed expected an int in [0, 2**31), got {cfg.seed}")
    # a setting of a loss or schedule that is off would be ignored: a given value means the user expects it to act
    owners = (("coarse_temperature", "coarse_weight"), ("attn_heads", "attn_weight"),
              ("desc_conf_alpha", "desc_conf_weight"), ("temperature", "match_weight"))
    out += [f"--{k} {getattr(cfg, k)} sets a loss that is off: it needs --{w} > 0" for k, w in owners
            if getattr(cfg, k) != getattr(TrainConfig, k) and getattr(cfg, w) <= 0]
    if cfg.n_corr != TrainConfig.n_corr and cfg.match_weight <= 0 and cfg.desc_conf_weight <= 0:
        out.append(f"--n_corr {cfg.n_corr} sets the matching losses, which are off: it needs --match_weight or "
                   "--desc_conf_weight > 0")
    if cfg.keep_decay != TrainConfig.keep_decay and not cfg.decay_by_time:
        out.append("--keep_decay false acts on resuming a --decay_by_time run: it needs --decay_by_time true")
    if cfg.min_lr > cfg.lr:
        out.append(f"--min_lr expected <= --lr ({cfg.lr}), got {cfg.min_lr}")
    if not 0 < cfg.mask_ratio < 1:
        out.append(f"--mask_ratio expected a fraction in (0, 1), got {cfg.mask_ratio}")
    return out


def field_comments(cls) -> dict[str, str]:
    """Each dataclass field's comment in ``cls``'s source (the one on its line and the comment-only lines under
    it), joined into one line: the ``--help`` text of its flag. {} when the source cannot be read."""
    try:
        lines = inspect.getsource(cls).splitlines(keepends=True)
    except (OSError, TypeError):
        return {}
    comments = {t.start[0]: t.string.lstrip("#").strip()
                for t in tokenize.generate_tokens(io.StringIO("".join(lines)).readline) if t.type == tokenize.COMMENT}
    names = {f.name for f in fields(cls)}
    notes, current = {}, None
    for row, line in enumerate(lines, start=1):
        head = line.split(":", 1)[0].strip()
        if head in names and line.startswith("    ") and not line.startswith("     "):
            current = head
            if row in comments:
                notes[current] = comments[row]
        elif current is not None and line.strip().startswith("#") and row in comments:
            notes[current] = f"{notes.get(current, '')} {comments[row]}".strip()
        else:
            current = None
    return notes


def _bool(s: str) -> bool:
    if s.lower() in ("1", "true", "yes", "on"):
        return True
    if s.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean, got {s!r}")


def grown_depths(text: str) -> tuple[int, int]:
    """``--grown_from "ENC,DEC"`` as two ints >= 1; ValueError (one line) otherwise."""
    parts = text.split(",")
    try:
        enc, dec = (int(x) for x in parts)
    except ValueError:
        raise ValueError(f"--grown_from expected ENC,DEC (two block counts, e.g. 6,4), got {text!r}") from None
    if enc < 1 or dec < 1:
        raise ValueError(f"--grown_from expected block counts >= 1, got {text!r}")
    return enc, dec
