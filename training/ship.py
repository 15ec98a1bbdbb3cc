"""Turn a training checkpoint into the shipped model file (fp16 safetensors inside the package):

    python -m training.ship --ckpt runs/train/last.pt --name small --metrics runs/train/eval.csv

The provenance stored with the weights (steps, image size, data, held-out metrics, command) is what
``pm.load_model(name).provenance`` and docs/models.md report.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import torch

from pointmap.checkpoint import WEIGHTS_DIR, load_state_strict, save_model
from pointmap.model import ModelConfig, PointmapNet
from training.loop import load_checkpoint


def last_eval(path: Path) -> dict:
    if not path.exists():
        return {}
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return {k: float(v) for k, v in rows[-1].items() if isinstance(k, str) and v not in (None, "")} if rows else {}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--name", default="small")
    p.add_argument("--metrics", default=None, help="eval.csv of the run (its last row is recorded)")
    p.add_argument("--note", default="")
    p.add_argument("--out", default=None, help="default: pointmap/weights/NAME.safetensors")
    a = p.parse_args(argv)
    ck = load_checkpoint(Path(a.ckpt))
    if ck.get("kind") != "train":
        print(f"error: {a.ckpt} is a {ck.get('kind')!r} checkpoint; ship a supervised ('train') one", file=sys.stderr)
        return 2
    model = PointmapNet(ModelConfig.from_dict(ck["model_config"]))
    load_state_strict(model, ck["model"], source=a.ckpt)
    cfg = ck["train_config"]
    provenance = {"name": a.name, "image_size": cfg["size"], "steps": ck["step"], "batch_size": cfg["batch_size"],
                  "data": ",".join(Path(r).name for r in cfg["data"].split(",") if r), "eval_data": Path(cfg["eval_data"]).name if cfg["eval_data"] else "",
                  "heldout_metrics": last_eval(Path(a.metrics)) if a.metrics else {}, "note": a.note,
                  "trained_with": "python -m training.train " + " ".join(f"--{k} {v}" for k, v in cfg.items()
                                                                         if k in ("preset", "size", "batch_size", "lr", "steps"))}
    out = Path(a.out) if a.out else WEIGHTS_DIR / f"{a.name}.safetensors"
    path = save_model(model, out, provenance=provenance, dtype=torch.float16)
    print(f"{path} ({path.stat().st_size / 1e6:.1f} MB), step {ck['step']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
