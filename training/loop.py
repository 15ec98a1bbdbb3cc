"""The training loop shared by pretraining and supervised training.

Resumable exactly: a checkpoint holds model, optimiser, scheduler, RNG states and the step; the data
order is a pure function of (seed, step, rank), so a resumed run sees the batches it would have seen.
Runs single-process or under ``torchrun`` (DDP: gloo on CPU, nccl on GPU).
"""

from __future__ import annotations

import collections
import contextlib
import csv
import dataclasses
import io
import math
import os
import random
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from tqdm.auto import tqdm

from pointmap.atomic import atomic_open, atomic_path
from pointmap.checkpoint import check_state
from pointmap.errors import CheckpointError
from training.config import TrainConfig


# -- distributed ----------------------------------------------------------------------------------
def setup_distributed():
    """(rank, world, device); initialises the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world > 1 and not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
    device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu")
    return rank, world, device


# -- data order -----------------------------------------------------------------------------------
def batch_indices(step: int, rank: int, world: int, batch: int, n: int, seed: int) -> list[int]:
    """Dataset indices of (step, rank): consecutive slices of per-epoch permutations (a pure function)."""
    per_step = batch * world
    start = step * per_step + rank * batch
    out = []
    for k in range(start, start + batch):
        epoch, pos = divmod(k, n)
        g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
        out.append(int(torch.randperm(n, generator=g)[pos]))
    return out


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator of the random draws a training step makes itself (pretraining's masks, the losses' sampled
    correspondences): a function of (seed, step, this process's rank), so a resumed run draws what the
    uninterrupted one did and no two ranks draw the same (equal-sized pairs would sample the same pixels)."""
    rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
    return torch.Generator().manual_seed((seed * 1_000_003 + step) * 1024 + rank)


class StepBatches(torch.utils.data.Sampler):
    """Batch sampler from ``start_step`` to ``steps`` following ``batch_indices``. With ``item_seeds`` (a dataset
    that takes them: ``PairDataset``) each item is ``(index, aspect, (seed, step, k))``, ``k`` the sample's place in
    the whole run's order: the dataset draws its augmentation from that seed, so every sample's augmentation is a
    function of the run's seed and step, whichever worker loads it and however often the run was resumed."""

    def __init__(self, n, batch, steps, start_step, rank, world, seed, n_aspects: int = 1, item_seeds: bool = False):
        self.args = (n, batch, steps, start_step, rank, world, seed)
        self.n_aspects = n_aspects
        self.item_seeds = item_seeds
        self._perm_cache = {}

    def __iter__(self):
        n, batch, steps, start, rank, world, seed = self.args
        for step in range(start, steps):
            per_step = batch * world
            first = step * per_step + rank * batch
            idx = []
            for k in range(first, first + batch):
                epoch, pos = divmod(k, n)
                if epoch not in self._perm_cache:
                    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
                    self._perm_cache = {epoch: torch.randperm(n, generator=g)}
                idx.append(int(self._perm_cache[epoch][pos]))
            aspect = 0
            if self.n_aspects > 1:  # one aspect ratio per step (same on every rank), a function of the step
                g = torch.Generator().manual_seed(seed * 7_919 + step)
                aspect = int(torch.randint(self.n_aspects, (), generator=g))
            if self.item_seeds:
                idx = [(i, aspect, (seed % 2**63, step, first + b)) for b, i in enumerate(idx)]
            elif self.n_aspects > 1:
                idx = [(i, aspect) for i in idx]
            yield idx

    def __len__(self):
        return max(self.args[2] - self.args[3], 0)


# -- optimisation ---------------------------------------------------------------------------------
NO_DECAY_SUFFIXES = ("pose_head.query", "focal_head.query")  # learned embeddings, like tokens


def make_optimizer(model: torch.nn.Module, cfg: TrainConfig, lr_scale: dict[str, float] | None = None
                   ) -> torch.optim.Optimizer:
    """AdamW (0.9, 0.95); no weight decay on biases, norms, tokens and learned embeddings. ``lr_scale`` maps
    parameter names to a multiplier of the learning rate (e.g. ``--grown_lr``); each group records its
    multiplier as ``lr_scale``, which the schedule keeps."""
    lr_scale = lr_scale or {}
    unknown = set(lr_scale) - {name for name, _ in model.named_parameters()}
    if unknown:
        raise ValueError(f"lr_scale names parameters the model does not have: {sorted(unknown)[:3]}")
    groups: dict[tuple[bool, float], list] = {}
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        decay = not (p.ndim < 2 or "token" in name or name.endswith(NO_DECAY_SUFFIXES))
        groups.setdefault((decay, float(lr_scale.get(name, 1.0))), []).append(p)
    # the unscaled groups first, in the order earlier checkpoints hold them (decay, then no decay)
    order = sorted(groups, key=lambda k: (k[1] != 1.0, k[1], not k[0]))
    return torch.optim.AdamW([{"params": groups[k], "weight_decay": cfg.weight_decay if k[0] else 0.0,
                               "lr": cfg.lr * k[1], "lr_scale": k[1]} for k in order], lr=cfg.lr, betas=(0.9, 0.95))


def check_loop_options(cfg: TrainConfig) -> None:
    """ValueError (one line) for a schedule, ``--decay_by_time``, ``--decay_ckpts``, ``--amp``, ``--crop_link``,
    ``--grey_p``, ``--flip_p`` or ``--pad_p`` that cannot run as configured."""
    if cfg.schedule not in ("cosine", "wsd"):
        raise ValueError(f"--schedule expected 'cosine' or 'wsd', got {cfg.schedule!r}")
    if cfg.schedule == "wsd" and not 0 < cfg.decay_steps <= cfg.steps - cfg.warmup:
        raise ValueError(f"--schedule wsd needs 0 < --decay_steps <= --steps - --warmup "
                         f"({cfg.steps} - {cfg.warmup}), got {cfg.decay_steps}")
    if cfg.schedule == "cosine" and cfg.decay_steps:
        raise ValueError(f"--decay_steps {cfg.decay_steps} is for --schedule wsd (cosine decays over --steps)")
    if cfg.decay_by_time and (cfg.schedule != "wsd" or cfg.max_minutes <= 0):
        raise ValueError("--decay_by_time true needs --schedule wsd and --max_minutes > 0 (the decay is placed so "
                         f"that it ends when the minutes run out), got --schedule {cfg.schedule} "
                         f"--max_minutes {cfg.max_minutes}")
    if cfg.decay_ckpts and cfg.schedule != "wsd":
        raise ValueError(f"--decay_ckpts true keeps the checkpoints of a wsd decay; it needs --schedule wsd, got "
                         f"--schedule {cfg.schedule}")
    if not 0 <= cfg.crop_link <= 1:
        raise ValueError(f"--crop_link expected a probability in [0, 1], got {cfg.crop_link}")
    if not 0 <= cfg.grey_p <= 1:
        raise ValueError(f"--grey_p expected a probability in [0, 1], got {cfg.grey_p}")
    if not 0 <= cfg.flip_p <= 1:
        raise ValueError(f"--flip_p expected a probability in [0, 1], got {cfg.flip_p}")
    if not 0 <= cfg.pad_p <= 1:
        raise ValueError(f"--pad_p expected a probability in [0, 1], got {cfg.pad_p}")
    if cfg.amp not in ("auto", "bf16", "off"):
        raise ValueError(f"--amp expected 'auto', 'bf16' or 'off', got {cfg.amp!r}")


def lr_factor(step: int, cfg: TrainConfig) -> float:
    """The learning rate at ``step`` as a factor of ``cfg.lr``: linear warmup, then either cosine decay to
    min_lr at ``cfg.steps``, or (``schedule="wsd"``) constant until the last ``decay_steps`` steps, which fall to
    min_lr as 1 - sqrt(t) (Hägele et al. 2024, "Scaling laws and compute-optimal training beyond fixed training
    durations"). The schedule is a function of the step and the current config only, so a resumed run may
    change it (e.g. lengthen ``--steps`` of a wsd run resumed from its stable checkpoint)."""
    if step < cfg.warmup:
        return (step + 1) / cfg.warmup
    floor = cfg.min_lr / cfg.lr
    if cfg.schedule == "wsd":
        start = cfg.steps - cfg.decay_steps
        if step < start:
            return 1.0
        t = min((step - start + 1) / max(cfg.decay_steps, 1), 1.0)  # update steps-1 runs at min_lr
        return floor + (1.0 - floor) * (1.0 - math.sqrt(t))
    t = min((step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1), 1.0)
    return floor + (1.0 - floor) * 0.5 * (1 + math.cos(math.pi * t))


class DecayByTime:
    """``--decay_by_time``: places a wsd run's end (``cfg.steps``) so that its decay ends as ``--max_minutes`` runs
    out. The stable phase has a constant learning rate, so where it ends is free until the decay starts: at every
    step after warmup the decay starts when the seconds left (less ``reserve``: the last evaluation's and
    checkpoint's durations) fit no more than ``decay_steps`` * (1 + ``margin``) + 2 steps at the pace of this process
    (the margin: session 85's decay steps ran 4.2 s against the 3.8 s measured before them, and ``--max_minutes`` cut
    its last 18 steps; sessions 26 and 85 both ended short that way). The pace is the
    mean duration of the last ``window`` steps (from its ``warm``-th step on, so compilation is excluded;
    evaluations and checkpoints included), each counted as at most 4 times their median, and it is read only once
    ``min_steps`` durations are in: a stall of the process (``kill -STOP``, a suspended machine) is one long step,
    which, read alone as the pace, once started a 105-minute leg's decay at its 21st step (session 41). From then
    on the end is fixed, and saved with every checkpoint, so a resumed run finishes the same decay. ``--steps``
    stays an upper bound."""

    def __init__(self, cfg: TrainConfig, start: int, t0: float, warm: int = 20, window: int = 200,
                 min_steps: int = 5, margin: float = 0.1) -> None:
        self.cfg, self.start, self.t0, self.warm, self.min_steps, self.margin = cfg, start, t0, warm, min_steps, margin
        self.times = collections.deque(maxlen=window + 1)  # the clock at the last window + 1 updates since warm

    def decaying(self, step: int) -> bool:
        return step >= self.cfg.steps - self.cfg.decay_steps

    def pace(self) -> float:
        """Seconds per step: the window's mean step, each step counted as at most 4 times the median one."""
        steps = np.diff(np.asarray(self.times, dtype=np.float64))
        return float(np.minimum(steps, 4.0 * np.median(steps)).mean())

    def update(self, step: int, now: float, reserve: float = 0.0) -> bool:
        """Move the end for the state after ``step`` updates; True when the decay starts at this call."""
        if self.decaying(step) or step < self.cfg.warmup or step - self.start < self.warm:
            return False
        self.times.append(now)
        if len(self.times) <= self.min_steps:
            return False
        left = self.cfg.max_minutes * 60 - (now - self.t0) - reserve
        if left > (self.cfg.decay_steps * (1 + self.margin) + 2) * self.pace():
            return False
        self.cfg.steps = step + self.cfg.decay_steps
        return True


# -- checkpoints ----------------------------------------------------------------------------------
def _rng_state() -> dict:
    np_state = np.random.get_state()
    py = random.getstate()
    return {"torch": torch.get_rng_state(), "numpy_keys": torch.from_numpy(np_state[1].astype(np.int64)),
            "numpy_pos": int(np_state[2]), "py_version": py[0], "py_internal": torch.tensor(py[1], dtype=torch.int64),
            "py_gauss": py[2]}


def _set_rng_state(s: dict) -> None:
    torch.set_rng_state(s["torch"])
    np.random.set_state(("MT19937", s["numpy_keys"].numpy().astype(np.uint32), s["numpy_pos"], 0, 0.0))
    random.setstate((s["py_version"], tuple(int(v) for v in s["py_internal"].tolist()), s["py_gauss"]))


def _group_names(model, optimizer) -> list[list[str]]:
    """The parameter names of each of ``optimizer``'s groups, in its order."""
    names = {id(p): n for n, p in _unwrap(model).named_parameters()}
    return [[names[id(p)] for p in g["params"]] for g in optimizer.param_groups]


def _regroup(saved: dict, saved_names: list[list[str]], optimizer, model) -> dict:
    """``saved`` (an optimizer state dict whose groups hold ``saved_names``) re-keyed by parameter name for
    ``optimizer``'s groups, whose own hyperparameters it takes. CheckpointError when the names differ."""
    by_name = {}
    for group, names in zip(saved["param_groups"], saved_names):
        if len(group["params"]) != len(names):
            raise CheckpointError(f"the checkpoint names {len(names)} parameters for a group of {len(group['params'])}")
        by_name.update({n: saved["state"][i] for i, n in zip(group["params"], names) if i in saved["state"]})
    now, current = optimizer.state_dict(), _group_names(model, optimizer)
    if sorted(n for g in saved_names for n in g) != sorted(n for g in current for n in g):
        raise CheckpointError("the checkpoint's optimizer holds other parameters than this model's")
    state = {i: by_name[n] for group, names in zip(now["param_groups"], current)
             for i, n in zip(group["params"], names) if n in by_name}
    return {"state": state, "param_groups": now["param_groups"]}


def save_checkpoint(path: Path, model, optimizer, scheduler, step: int, cfg: TrainConfig, extra=None) -> None:
    """Atomic write (temp file + rename) of everything needed to resume exactly; the optimizer's groups are saved
    with their parameters' names (``optimizer_names``), so a resume with other groups can regroup its state."""
    state = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
             "optimizer_names": _group_names(model, optimizer),
             "step": step, "rng": _rng_state(), "train_config": cfg.to_dict(),
             "model_config": _unwrap(model).cfg.to_dict(), "kind": cfg.task, "extra": extra or {}}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    """A training checkpoint (``save_checkpoint``), loaded with ``weights_only=True``; CheckpointError (one line)
    when the file is not one."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - torch reports corrupt or foreign files through many types
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path} is not a readable training checkpoint: {first}") from e
    if not isinstance(ck, dict) or not {"model", "model_config", "step"} <= set(ck):
        raise CheckpointError(f"{path} is not a pointmap training checkpoint (expected keys model, model_config, "
                              f"step; got {sorted(ck) if isinstance(ck, dict) else type(ck).__name__})")
    if not (isinstance(ck["step"], int) and not isinstance(ck["step"], bool) and ck["step"] >= 0):
        raise CheckpointError(f"{path}: its step expected an int >= 0, got {ck['step']!r}")
    check_state(ck["model"], path)  # named tensors, all finite: a NaN state would train or ship NaN
    return ck


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


# -- logging --------------------------------------------------------------------------------------
class Logger:
    """CSV (always) and TensorBoard (when installed) on rank 0."""

    def __init__(self, out: Path, enabled: bool) -> None:
        self.enabled, self.out = enabled, out
        self.tb = None
        self._fields: dict[str, list] = {}  # the header each CSV has on disk, once known
        if enabled:
            out.mkdir(parents=True, exist_ok=True)
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tb = SummaryWriter(str(out / "tb"))
            except Exception:  # noqa: BLE001 - TensorBoard is optional
                self.tb = None

    def has_eval(self, step: int) -> bool:
        """Whether ``eval.csv`` already holds a row for ``step``."""
        path = self.out / "eval.csv"
        return path.exists() and any(row.get("step") == str(step) for row in _whole_rows(path)[1])

    def log(self, kind: str, step: int, values: dict) -> None:
        if not self.enabled:
            return
        path = self.out / f"{kind}.csv"
        fields = ["step", "time", *values.keys()]
        row = {"step": step, "time": round(time.time(), 1), **values}
        known = self._fields.get(kind)
        if known is not None and set(fields) <= set(known):
            fields = known
        elif path.exists():
            header, rows = _whole_rows(path)
            if header != fields:  # columns changed (e.g. a resumed run with new metrics): one header for all rows
                fields = header + [f for f in fields if f not in header]
                with atomic_open(path, "w") as fh:
                    w = csv.DictWriter(fh, fieldnames=fields)
                    w.writeheader()
                    w.writerows(rows)
        self._fields[kind] = fields
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=fields)
        if not path.exists():
            w.writeheader()
        w.writerow(row)
        append_line(path, buf.getvalue().encode())
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(f"{kind}/{k}", v, step)
            self.tb.flush()


def _whole_rows(path: Path) -> tuple[list, list]:
    """(header, rows as dicts) of a CSV log, without a last row torn by a kill (no newline), which
    ``append_line`` would cut before its next write."""
    text = path.read_bytes().decode()
    reader = csv.DictReader(io.StringIO(text[: text.rfind("\n") + 1], newline=""))
    return list(reader.fieldnames or []), list(reader)


def append_line(path: Path, data: bytes) -> None:
    """Append ``data`` (whole lines) to ``path`` in one write, after cutting a torn last line a killed run may
    have left (a CSV row without its newline), so every line in the file is one that was written whole."""
    with open(path, "ab+") as fh:
        size = fh.seek(0, os.SEEK_END)
        if size:
            fh.seek(max(0, size - 65536))
            tail = fh.read()
            if not tail.endswith(b"\n"):
                cut = tail.rfind(b"\n")
                fh.truncate(size - len(tail) + cut + 1 if cut >= 0 else (0 if size <= 65536 else size))
        fh.write(data)


# -- the loop -------------------------------------------------------------------------------------
def fit(cfg: TrainConfig, model: torch.nn.Module, dataset, collate, step_fn, eval_fn=None,
        lr_scale: dict[str, float] | None = None, extra: dict | None = None) -> dict:
    """Train ``model`` with ``step_fn(model, batch, step) -> (loss, metrics dict)`` (``lr_scale``:
    ``make_optimizer``; ``extra``: recorded in every checkpoint, e.g. the model's growth history).

    Evaluates with ``eval_fn(model) -> metrics dict`` every ``eval_every`` steps (rank 0) and checkpoints
    every ``ckpt_every`` steps and every ``ckpt_minutes`` of wall time to ``out/last.pt``; both also at the last
    step, whether ``--steps`` or ``--max_minutes`` ended the run (eval.csv's last row, which training.ship records,
    is then the saved state's). SIGTERM (on any rank) ends the run after the current step with a checkpoint and no
    evaluation. Returns the last metrics with ``step`` and ``terminated`` (True after a SIGTERM).
    """
    check_loop_options(cfg)
    cfg = dataclasses.replace(cfg)  # --decay_by_time moves cfg.steps: the caller's config stays as given
    rank, world, device = setup_distributed()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    torch.manual_seed(cfg.seed + rank)
    np.random.seed(cfg.seed + rank)
    random.seed(cfg.seed + rank)
    model.to(device)
    optimizer = make_optimizer(model, cfg, lr_scale)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, cfg))
    start = 0
    last = out / "last.pt"
    if cfg.resume and last.exists():
        ck = load_checkpoint(last)
        lost = sorted({"optimizer", "scheduler", "rng"} - set(ck))
        if lost:
            raise CheckpointError(f"{last} cannot be resumed: it has no {', '.join(lost)} (a weights-only file?); "
                                  f"use a new --out with --init {last}, or --resume false to start over in this one")
        if ck.get("kind") not in (None, cfg.task):
            raise CheckpointError(f"{last} is a {ck.get('kind')!r} checkpoint and this run is {cfg.task!r}: use a new "
                                  "--out, or --resume false to start over in this one")
        try:
            model.load_state_dict(ck["model"])
        except RuntimeError as e:  # torch lists every missing / unexpected / mis-shaped key
            first = str(e).strip().splitlines()[0]
            raise CheckpointError(f"{last} holds another architecture than this run's ({first[:160]}): use a new "
                                  "--out, or --resume false to start over in this one") from None
        saved_names = ck.get("optimizer_names")
        if saved_names is not None and saved_names != _group_names(model, optimizer):
            # other groups (e.g. --grown_lr turned on or off): Adam's moments follow their parameters by name
            try:
                optimizer.load_state_dict(_regroup(ck["optimizer"], saved_names, optimizer, model))
            except CheckpointError as e:
                raise CheckpointError(f"{last}: {e}") from None
        else:
            try:
                optimizer.load_state_dict(ck["optimizer"])
            except ValueError:  # torch: "loaded state dict has a different number of parameter groups", ...
                def groups(gs):
                    return (f"{len(gs)} parameter groups (learning-rate multipliers "
                            f"{sorted({g.get('lr_scale', 1.0) for g in gs})})")
                raise CheckpointError(
                    f"{last}: its optimizer holds {groups(ck['optimizer']['param_groups'])}, this run "
                    f"{groups(optimizer.param_groups)}, and it does not name their parameters (written before "
                    f"checkpoints did), so its state cannot be regrouped: start a new --out with --init {last} "
                    "(its weights; the optimizer starts fresh)") from None
        scheduler.load_state_dict(ck["scheduler"])
        start = int(ck["step"])
        saved = ck.get("train_config", {})
        kept_decay = (cfg.decay_by_time and cfg.keep_decay and saved.get("decay_by_time")
                      and start > saved["steps"] - saved["decay_steps"])
        if kept_decay:
            placed_end = saved["steps"] - saved["decay_steps"] + cfg.decay_steps
            if cfg.steps < placed_end:  # lr_factor places the decay from --steps: a shorter run would move it
                raise CheckpointError(f"{last}: its decay by time runs from step {saved['steps'] - saved['decay_steps']}"
                                      f" to {placed_end}, and --steps {cfg.steps} ends inside it (the decay would "
                                      f"start over at step {cfg.steps - cfg.decay_steps}): pass --steps "
                                      f"{placed_end} or more, or --keep_decay false")
            cfg.steps = placed_end  # the same decay
        if start >= cfg.steps and rank == 0:
            go_on = (f"its decay by time ended at step {cfg.steps}; to train on, resume stable_"
                     f"{saved['steps'] - saved['decay_steps']}.pt (or pass --keep_decay false)" if kept_decay
                     else "raise --steps to go on")
            print(f"warning: {last} is at step {start}, the run's end is step {cfg.steps}: nothing left to train, "
                  f"only the final evaluation runs if it is owed ({go_on})", file=sys.stderr)
        # the schedule and weight decay are the current config's, not the ones the checkpoint was written with
        fresh_groups = make_optimizer(model, cfg, lr_scale).param_groups
        for group, fresh in zip(optimizer.param_groups, fresh_groups):
            base = cfg.lr * fresh["lr_scale"]
            group["lr"], group["initial_lr"], group["lr_scale"] = base * lr_factor(start, cfg), base, fresh["lr_scale"]
            group["weight_decay"] = fresh["weight_decay"]
        scheduler.base_lrs = [g["initial_lr"] for g in optimizer.param_groups]
        scheduler._last_lr = [g["lr"] for g in optimizer.param_groups]
        if world == 1:
            _set_rng_state(ck["rng"])
    ddp_model = model
    if world > 1:
        # the DPT's last fusion block has an unused lateral unit (kept for official-key compatibility)
        ddp_model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            find_unused_parameters=any("dpt" in n for n, _ in model.named_parameters()))
    # static shapes: one compilation per aspect ratio (three at most in our datasets); the dynamic-shape graph
    # of a model with a descriptor stem fails to compile in torch 2.13's inductor (symbolic stride order)
    step_model = torch.compile(ddp_model, dynamic=False) if cfg.compile else ddp_model
    logger = Logger(out, rank == 0)
    n_aspects = len(getattr(dataset, "aspects", [None]))
    sampler = StepBatches(len(dataset), cfg.batch_size, cfg.steps, start, rank, world, cfg.seed, n_aspects,
                          item_seeds=bool(getattr(dataset, "item_seeds", False)))
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=sampler, collate_fn=collate,
                                         num_workers=cfg.workers, persistent_workers=False,
                                         worker_init_fn=_leave_sigterm_to_the_main_process,
                                         prefetch_factor=4 if cfg.workers > 0 else None)
    bar = tqdm(total=cfg.steps, initial=start, desc=cfg.task, disable=cfg.quiet or rank != 0, dynamic_ncols=True)
    t0, seen, metrics = time.time(), 0, {}
    last_ckpt_time = t0
    step = start
    by_time = DecayByTime(cfg, start, t0) if cfg.decay_by_time else None
    eval_seconds = ckpt_seconds = 0.0  # the last evaluation's and checkpoint's durations (--decay_by_time)
    use_bf16 = use_autocast(cfg, device)
    model.train()
    def evaluate() -> float:
        """Evaluate (rank 0), log eval.csv's row, add it to ``metrics``; returns the seconds it took."""
        model.eval()
        t_eval = time.time()
        ev = eval_fn(model)
        seconds = time.time() - t_eval
        model.train()
        logger.log("eval", step, ev)
        metrics.update({f"eval_{k}": v for k, v in ev.items()})
        tqdm.write(f"[eval step {step}] " + ", ".join(f"{k}={v:.4g}" for k, v in ev.items()))
        return seconds

    killed = False
    with sigterm_flag() as terminated:
        torch_state = torch.get_rng_state()  # the loader draws its workers' base seed from the global generator
        batches = iter(loader)
        torch.set_rng_state(torch_state)
        try:
            for batch in batches:
                batch = _to(batch, device)
                with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
                    loss, metrics = step_fn(step_model, batch, step)
                loss_value = float(loss.detach())
                if not math.isfinite(loss_value):
                    raise FloatingPointError(f"loss is {loss_value} at step {step}: lower --lr or check the data")
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip)
                if not math.isfinite(float(gnorm)):  # clipping by a NaN norm turns every gradient NaN: the step
                    # would write NaN weights, and a checkpoint at this step would keep them
                    raise FloatingPointError(f"gradient norm is {float(gnorm)} at step {step} (the loss, "
                                             f"{loss_value:.4g}, is finite): lower --lr or check the data")
                optimizer.step()
                scheduler.step()
                step += 1
                seen += cfg.batch_size * world
                now = time.time()
                stop = cfg.max_minutes > 0 and (now - t0) / 60 > cfg.max_minutes
                killed = bool(terminated)
                moved = by_time is not None and rank == 0 and by_time.update(step, now, reserve=eval_seconds + ckpt_seconds)
                if world > 1:
                    # every rank follows rank 0's clock (one end and one stop for all: a rank stopping alone would
                    # hang), and a SIGTERM that reached any rank stops them all
                    shared = torch.tensor([cfg.steps, int(stop)], dtype=torch.int64, device=device)
                    dist.broadcast(shared, 0)
                    moved, cfg.steps, stop = moved or int(shared[0]) != cfg.steps, int(shared[0]), bool(shared[1])
                    signalled = torch.tensor([int(killed)], dtype=torch.int64, device=device)
                    dist.all_reduce(signalled, op=dist.ReduceOp.MAX)
                    killed = bool(signalled[0])
                if moved:  # the next update already runs at the first decay step's rate
                    for group in optimizer.param_groups:
                        group["lr"] = group["initial_lr"] * lr_factor(step, cfg)  # as LambdaLR computes it
                    scheduler._last_lr = [g["lr"] for g in optimizer.param_groups]
                    bar.total = cfg.steps
                    if rank == 0:
                        tqdm.write(f"[step {step}] --decay_by_time: the decay starts, the run ends at step {cfg.steps}")
                rate = seen / max(now - t0, 1e-9)
                metrics = {"loss": loss_value, "grad_norm": float(gnorm), "lr": scheduler.get_last_lr()[0],
                           "pairs_per_s": rate, **metrics}
                bar.update(1)
                bar.set_postfix(loss=f"{loss_value:.4f}", pairs_s=f"{rate:.2f}")
                if step % cfg.log_every == 0:
                    logger.log("train", step, metrics)
                if rank == 0 and cfg.schedule == "wsd" and step == cfg.steps - cfg.decay_steps:
                    # the end of the stable phase: a longer run resumes from here (docs/training.md, "Schedules")
                    save_checkpoint(out / f"stable_{step}.pt", model, optimizer, scheduler, step, cfg, extra)
                ending = stop or killed or step >= cfg.steps  # the last update: checkpointed, whatever ended it
                due = cfg.ckpt_minutes > 0 and now - last_ckpt_time >= cfg.ckpt_minutes * 60
                if rank == 0 and (step % cfg.ckpt_every == 0 or ending or due):
                    t_ckpt = last_ckpt_time = time.time()
                    save_checkpoint(last, model, optimizer, scheduler, step, cfg, extra)
                    # the decay's keepsakes on the --ckpt_every grid and at the run's real end only: a checkpoint by
                    # the clock or a signal would add an irregular one to what training.ship averages
                    if cfg.decay_ckpts and step > cfg.steps - cfg.decay_steps and (
                            step % cfg.ckpt_every == 0 or step >= cfg.steps or (stop and not killed)):  # wsd only
                        save_checkpoint(out / f"decay_{step}.pt", model, optimizer, scheduler, step, cfg, extra)
                    ckpt_seconds = time.time() - t_ckpt
                if killed:  # no evaluation: the process is asked to end now (eval.csv's last row is an earlier state's)
                    if rank == 0:
                        tqdm.write(f"[step {step}] SIGTERM: checkpointed {last}; the same command resumes from it")
                    break
                if eval_fn is not None and rank == 0 and (step % cfg.eval_every == 0 or ending):
                    eval_seconds = evaluate()
                if ending:
                    break
        finally:  # workers shut down now, also on an error: left to the interpreter's exit, they hung it
            shutdown = getattr(batches, "_shutdown_workers", None)
            if shutdown is not None:
                shutdown()

    bar.close()
    if step == start >= cfg.steps and eval_fn is not None and rank == 0 and not logger.has_eval(step):
        evaluate()  # resumed at the end (e.g. a SIGTERM during the last update): the final evaluation the run owes
    if world > 1:
        dist.barrier()
    return {"step": step, "terminated": killed, **metrics}


@contextlib.contextmanager
def sigterm_flag():
    """While inside: SIGTERM appends to the yielded list instead of killing the process, so the loop can checkpoint
    the step it is on and stop (what a job scheduler or a session's end sends; SIGKILL cannot be caught, which
    ``--ckpt_minutes`` bounds); a second SIGTERM kills the process as the first would have. The previous handler
    is restored on the way out. Off the main thread (where Python cannot set handlers) the list stays empty."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def on_sigterm(signum, frame):
        received.append(signum)
        if len(received) > 1:  # asked twice (e.g. a run stuck waiting for data): die as SIGTERM would
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        yield received
    finally:  # None: a handler set outside Python, which cannot be restored; the default then
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


TERMINATED_EXIT = 128 + signal.SIGTERM  # training.train / pretrain exit with it after a SIGTERM, as a shell reports


def error_line(e: BaseException) -> str:
    """The one line a CLI prints for ``e``: a DataLoader re-raises a worker's error with the worker's traceback in
    its message, of which the last line is the error itself."""
    text = str(e)
    if "Original Traceback" in text:
        last = next((ln for ln in reversed(text.splitlines()) if ln.strip()), text)
        kind, sep, message = last.partition(": ")  # "data.shards.ShardError: <message>"
        text = message if sep and kind.replace(".", "").isidentifier() else last
    return text


def _leave_sigterm_to_the_main_process(worker_id: int) -> None:
    """DataLoader workers ignore SIGTERM (a group-wide signal reaches them too): the main process checkpoints and
    then shuts them down; a worker dying first would end the run with a DataLoader error instead (as would one
    dying later on a timer: the loader raises wherever the main process is). A worker whose parent is gone exits
    by itself (PyTorch's worker watchdog)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def use_autocast(cfg: TrainConfig, device: torch.device) -> bool:
    """Whether the training step runs under bf16 autocast (``--amp``). The step functions keep their losses in
    float32 (training.train casts the network's outputs back before any loss)."""
    if cfg.amp == "bf16":
        return True
    return cfg.amp == "auto" and device.type == "cuda" and torch.cuda.is_bf16_supported()


def _to(batch, device):
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return {k: _to(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to(v, device) for v in batch)
    return batch
