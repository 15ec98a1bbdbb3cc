"""Turn a training checkpoint into the shipped model file (fp16 or int8 safetensors inside the package):

    python -m training.ship --ckpt runs/train/last.pt --name small --metrics runs/train/eval.csv

Several checkpoints of one run (``--ckpt A.pt B.pt C.pt``) ship their weight average (uniform, in float64):
checkpoint averaging, which evens out the step-to-step wander of a model's answers along the end of a run.

The provenance stored with the weights (steps, image size, data, held-out metrics, command) is what
``pm.load_model(name).provenance`` and docs/models.md report.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import torch

from pointmap.checkpoint import WEIGHTS_DIR, CheckpointError, load_state_strict, save_model
from pointmap.model import ModelConfig, PointmapNet
from training.loop import load_checkpoint


def last_eval(path: Path) -> dict:
    """The last row of a run's ``eval.csv`` as numbers; ValueError (one line) for a file that is missing, empty or
    not such a CSV."""
    if not path.is_file():
        raise ValueError(f"--metrics expected a run's eval.csv, got {str(path)!r}, which is not a file")
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or "step" not in rows[-1]:
        raise ValueError(f"--metrics {path}: expected an eval.csv with a header and at least one row")
    try:
        return {k: float(v) for k, v in rows[-1].items() if isinstance(k, str) and v not in (None, "")}
    except (TypeError, ValueError) as e:
        raise ValueError(f"--metrics {path}: its last row is not all numbers ({e})") from None


def average_checkpoints(paths) -> dict:
    """The last of ``paths``'s training checkpoints with its model weights replaced by the uniform average of all
    of them (floating tensors averaged in float64 and cast back; any other tensor must be equal in all) and
    ``averaged_steps`` set to their steps. CheckpointError when they are not 'train' checkpoints of one
    architecture with the same tensors."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise CheckpointError("expected at least one checkpoint to average, got none")
    cks = [load_checkpoint(p) for p in paths]
    for p, ck in zip(paths, cks):
        if ck.get("kind") != "train":
            raise CheckpointError(f"{p} is a {ck.get('kind')!r} checkpoint; expected supervised ('train') ones")
        if ck["model_config"] != cks[0]["model_config"]:
            raise CheckpointError(f"{p} has another architecture than {paths[0]}: model configs differ in "
                                  f"{sorted(k for k in ck['model_config'] if ck['model_config'][k] != cks[0]['model_config'].get(k))}")
        if set(ck["model"]) != set(cks[0]["model"]):
            raise CheckpointError(f"{p} holds other tensors than {paths[0]}: "
                                  f"{sorted(set(ck['model']) ^ set(cks[0]['model']))[:5]}")
    out = dict(cks[-1])
    avg = {}
    for k, last in cks[-1]["model"].items():
        vals = [ck["model"][k] for ck in cks]
        if any(v.shape != last.shape for v in vals):
            raise CheckpointError(f"tensor {k} has shapes {sorted({tuple(v.shape) for v in vals})} across the "
                                  "checkpoints; expected one")
        if last.is_floating_point():
            avg[k] = (sum(v.double() for v in vals) / len(vals)).to(last.dtype)
        elif all(torch.equal(v, last) for v in vals):
            avg[k] = last
        else:
            raise CheckpointError(f"non-floating tensor {k} differs across the checkpoints; cannot average it")
    out["model"] = avg
    out["averaged_steps"] = [int(ck["step"]) for ck in cks]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", required=True, nargs="+",
                   help="a training checkpoint, or several of one run to ship their weight average")
    p.add_argument("--name", default="small")
    p.add_argument("--metrics", default=None, help="eval.csv of the run (its last row is recorded)")
    p.add_argument("--note", default="")
    p.add_argument("--out", default=None, help="default: pointmap/weights/NAME.safetensors")
    p.add_argument("--dtype", choices=("fp16", "int8"), default="fp16",
                   help="storage: fp16, or int8 weight matrices with per-channel scales (about half of fp16; "
                        "pointmap.checkpoint.save_model)")
    a = p.parse_args(argv)
    try:
        ck = average_checkpoints(a.ckpt)
        model = PointmapNet(ModelConfig.from_dict(ck["model_config"]))
        load_state_strict(model, ck["model"], source=a.ckpt[-1])
        metrics = last_eval(Path(a.metrics)) if a.metrics else {}
    except (CheckpointError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cfg = ck["train_config"]
    provenance = {"name": a.name, "image_size": cfg["size"], "steps": ck["step"], "batch_size": cfg["batch_size"],
                  "data": ",".join(Path(r).name for r in cfg["data"].split(",") if r), "eval_data": Path(cfg["eval_data"]).name if cfg["eval_data"] else "",
                  "heldout_metrics": metrics, "note": a.note,
                  **({"averaged_steps": ck["averaged_steps"]} if len(a.ckpt) > 1 else {}),
                  **({"grown_from": g} if (g := (ck.get("extra") or {}).get("grown_from")) is not None else {}),
                  "trained_with": "python -m training.train " + " ".join(f"--{k} {v}" for k, v in cfg.items()
                                                                         if k in ("preset", "size", "batch_size", "lr", "steps"))}
    out = Path(a.out) if a.out else WEIGHTS_DIR / f"{a.name}.safetensors"
    path = save_model(model, out, provenance=provenance, dtype=torch.float16 if a.dtype == "fp16" else "int8")
    avg = f", the average of steps {ck['averaged_steps']}" if len(a.ckpt) > 1 else ""
    print(f"{path} ({path.stat().st_size / 1e6:.1f} MB), step {ck['step']}{avg}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
