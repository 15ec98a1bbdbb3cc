"""Turn a training checkpoint into the shipped model file (fp16 or int8 safetensors inside the package):

    python -m training.ship --ckpt runs/train/last.pt --name small --metrics runs/train/eval.csv

Several checkpoints of one run (``--ckpt A.pt B.pt C.pt``) ship their weight average (uniform, in float64):
checkpoint averaging, which evens out the step-to-step wander of a model's answers along the end of a run.
A model file (``.safetensors``, e.g. the shipped model a run was fine-tuned from) may be among them, and
``--weights`` sets each input's share: the weights of a fine-tuned run interpolated towards its start (WiSE-FT,
Wortsman et al. 2022), for instance ``--ckpt small.safetensors decay_*.pt --weights 4 1 1 1 1``.

The provenance stored with the weights (steps, image size, data, held-out metrics, command, licence) is what
``pm.load_model(name).provenance`` and docs/models.md report. The licence is ``--licence`` (Apache-2.0, the
project's) unless an input's lineage records another (an official checkpoint's CC-BY-NC-SA-4.0, carried through
fine-tuning): that one is kept, and a ``--licence`` that contradicts it is refused.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import warnings
from pathlib import Path

import torch

from pointmap.checkpoint import (
    CheckpointError,
    load_own,
    load_state_strict,
    model_licence,
    save_model,
    shipped_file,
)
from pointmap.model import ModelConfig, PointmapNet
from training.loop import load_checkpoint


def eval_row(path: Path, steps: list[int] = ()) -> dict:
    """The row of a run's ``eval.csv`` (as numbers) of the first of ``steps`` it has a row for (the last such row: a
    resumed run may have evaluated a step twice), else its last row. ValueError (one line) for a file that is
    missing, empty or not such a CSV."""
    if not path.is_file():
        raise ValueError(f"--metrics expected a run's eval.csv, got {str(path)!r}, which is not a file")
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or "step" not in rows[-1] or rows[-1]["step"] in (None, ""):
        raise ValueError(f"--metrics {path}: expected an eval.csv with a header and at least one row with its step")
    if {"loss", "grad_norm"} <= set(rows[-1]):  # the run's other log: its losses are no held-out figure
        raise ValueError(f"--metrics {path}: this is a run's train.csv (training losses); expected its eval.csv "
                         "(held-out metrics)")

    def numbers(row):
        try:
            return {k: float(v) for k, v in row.items() if isinstance(k, str) and v not in (None, "")}
        except (TypeError, ValueError) as e:
            raise ValueError(f"--metrics {path}: its row of step {row.get('step')} is not all numbers ({e})") from None

    for step in steps:
        for row in reversed(rows):
            try:
                if float(row.get("step") or "nan") == step:
                    return numbers(row)
            except ValueError:
                continue
    return numbers(rows[-1])


def _load_input(path: Path) -> dict:
    """A training checkpoint as ``load_checkpoint`` reads it, or a model file (``.safetensors``, dequantized to
    float32) in the same shape: ``model``, ``model_config``, ``step`` (its provenance's steps) and ``kind``
    'model'."""
    if path.suffix != ".safetensors":
        return load_checkpoint(path)
    if not path.is_file():
        raise CheckpointError(f"model file not found: {path}")
    model = load_own(path)
    prov = model.provenance if isinstance(model.provenance, dict) else {}
    try:
        step = int(prov.get("steps", 0))
    except (TypeError, ValueError):
        raise CheckpointError(f"{path}: its provenance's steps expected a whole number, got "
                              f"{prov.get('steps')!r}") from None
    licence = model_licence(model)
    return {"model": model.state_dict(), "model_config": model.cfg.to_dict(), "kind": "model", "step": step,
            "extra": {"licence": licence} if licence else {}}


def _config(ck: dict, path: Path) -> ModelConfig:
    try:
        return ModelConfig.from_dict(ck["model_config"])
    except (CheckpointError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path} has a model config that is not one: {e}") from None


def average_checkpoints(paths, weights=None) -> dict:
    """The latest training checkpoint of ``paths`` (the highest step among those with a share) with its model
    weights replaced by the average of all of them (floating tensors averaged in float64 with ``weights``,
    uniform by default, and cast back; any other tensor must be equal in all) and ``averaged_steps`` set to the
    training checkpoints' steps. ``paths`` may include model files (``.safetensors``); ``averaged`` lists every
    input with its share, ``licence`` every licence the inputs with a share record (None: none records one).
    CheckpointError when no training checkpoint has a share, when they are not 'train' checkpoints or model files of
    one architecture with the same tensors, or for weights that are not one non-negative number per input with a
    positive sum."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise CheckpointError("expected at least one checkpoint to average, got none")
    if weights is None:
        weights = [1.0] * len(paths)
    try:
        weights = [float(w) for w in weights]
    except (TypeError, ValueError):
        raise CheckpointError(f"expected one number per checkpoint as weights, got {weights!r}") from None
    if len(weights) != len(paths):
        raise CheckpointError(f"expected one weight per checkpoint ({len(paths)}), got {len(weights)}")
    if not all(math.isfinite(w) and w >= 0 for w in weights) or sum(weights) <= 0:
        raise CheckpointError(f"expected non-negative finite weights with a positive sum, got {weights}")
    cks = [_load_input(p) for p in paths]  # each loader refuses NaN or inf weights, naming its file
    first = _config(cks[0], paths[0]).to_dict()
    for p, ck in zip(paths, cks):
        if ck.get("kind") not in ("train", "model"):
            raise CheckpointError(f"{p} is a {ck.get('kind')!r} checkpoint; expected supervised ('train') ones "
                                  "or model files")
        # compared as ModelConfigs: a model file's config has every field, an older checkpoint's only its own
        here = _config(ck, p).to_dict()
        if here != first:
            raise CheckpointError(f"{p} has another architecture than {paths[0]}: model configs differ in "
                                  f"{sorted(k for k in here if here[k] != first[k])}")
        if set(ck["model"]) != set(cks[0]["model"]):
            raise CheckpointError(f"{p} holds other tensors than {paths[0]}: "
                                  f"{sorted(set(ck['model']) ^ set(cks[0]['model']))[:5]}")
    for j in range(len(cks)):  # a run's last.pt is its last decay_<step>.pt: a glob would weigh that state twice
        for i in range(j):
            if all(torch.equal(cks[i]["model"][k], v) for k, v in cks[j]["model"].items()):
                raise CheckpointError(f"{paths[i]} and {paths[j]} hold the same weights (a run's last.pt is its last "
                                      "checkpoint's state): give one of them, with --weights for a larger share")
    trained = [i for i, ck in enumerate(cks) if ck["kind"] == "train"]
    if not trained:
        raise CheckpointError("expected at least one training checkpoint (.pt) among the inputs, whose run the "
                              f"shipped file records; got only model files: {[str(p) for p in paths]}")
    # the run the file records: the latest training state with a share (not the last argument: a shell sorts
    # decay_10000.pt before decay_9000.pt)
    shared = [i for i in trained if weights[i] > 0]
    if not shared:  # the weights would be the model files' alone, recorded as a run's step (its config, its size)
        raise CheckpointError("expected a training checkpoint (.pt) with a share > 0, whose run the shipped file "
                              f"records; the training checkpoints {[str(paths[i]) for i in trained]} have share 0")
    base = cks[max(shared, key=lambda i: int(cks[i]["step"]))]
    total = sum(weights)
    shares = [w / total for w in weights]
    avg = {}
    for k, last in base["model"].items():
        vals = [ck["model"][k] for ck in cks]
        if any(v.shape != last.shape for v in vals):
            raise CheckpointError(f"tensor {k} has shapes {sorted({tuple(v.shape) for v in vals})} across the "
                                  "checkpoints; expected one")
        if last.is_floating_point():
            avg[k] = sum(s * v.double() for s, v in zip(shares, vals) if s > 0).to(last.dtype)
        elif all(torch.equal(v, last) for v in vals):
            avg[k] = last
        else:
            raise CheckpointError(f"non-floating tensor {k} differs across the checkpoints; cannot average it")
    out = dict(base)
    out["model"] = avg
    # the weights' licence: every licence an input with a share records (an average of official weights is theirs)
    licences = sorted({part for ck, w in zip(cks, weights) if w > 0 and (lic := (ck.get("extra") or {}).get("licence"))
                       for part in lic.split(" AND ")})
    out["licence"] = " AND ".join(licences) if licences else None
    out["averaged_steps"] = [int(cks[i]["step"]) for i in trained if weights[i] > 0]
    out["averaged"] = [{"source": src, "kind": ck["kind"], "step": int(ck["step"]), "share": round(s, 6),
                        **{k: v for k, v in (ck.get("train_config") or {}).items() if k in RUN_KEYS}}
                       for src, ck, s in zip(_sources(paths), cks, shares)]
    runs = {k: sorted({str((cks[i].get("train_config") or {}).get(k)) for i in trained if weights[i] > 0})
            for k in RUN_KEYS}
    differ = {k: v for k, v in runs.items() if len(v) > 1}
    if differ:  # a soup of runs is a choice (fine-tunes of one start); independent starts average to nothing
        warnings.warn(f"the checkpoints come from different runs: their {', '.join(differ)} differ "
                      f"({'; '.join(f'{k}: {v}' for k, v in differ.items())}); the shipped file records "
                      f"step {int(base['step'])}'s run (image size {(base.get('train_config') or {}).get('size')}) "
                      "and each input's own in 'averaged'. Averaging is meaningful only for runs from one start")
    return out


RUN_KEYS = ("seed", "size", "data", "init")  # what tells one training run from another, recorded per input


def _sources(paths) -> list[str]:
    """Each input's name with its parent folder, and as many folders above as tell different files apart (two runs'
    ``train/decay_1100.pt`` are ``run_a/train/decay_1100.pt`` and ``run_b/train/decay_1100.pt``)."""
    parts = [Path(p).resolve().parts for p in paths]
    distinct = len(set(parts))
    for k in range(2, max(len(q) for q in parts) + 1):  # at the longest, the whole paths: distinct as the files
        names = ["/".join(q[-k:]).lstrip("/") for q in parts]
        if len(set(names)) == distinct:
            break
    return names


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.ship", description=__doc__.split("\n\n")[0])
    p.add_argument("--ckpt", required=True, nargs="+",
                   help="a training checkpoint, or several of one run to ship their weight average")
    p.add_argument("--weights", nargs="+", type=float, default=None,
                   help="one non-negative share per --ckpt (normalised to sum 1; default: uniform)")
    p.add_argument("--name", default="small", help="the shipped model's name (a bare name): load_model(NAME)")
    p.add_argument("--metrics", default=None, help="eval.csv of the run (its row of the shipped step is recorded, else its last)")
    p.add_argument("--note", default="")
    p.add_argument("--out", default=None, help="default: pointmap/weights/NAME.safetensors")
    p.add_argument("--licence", default=None,
                   help="the weights' licence (SPDX id) when no input records one (default: the project's)")
    p.add_argument("--dtype", choices=("fp16", "int8"), default="fp16",
                   help="storage: fp16, or int8 weight matrices with per-channel scales (about half of fp16; "
                        "pointmap.checkpoint.save_model)")
    a = p.parse_args(argv)
    try:
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            ck = average_checkpoints(a.ckpt, a.weights)
        for w in said:
            print(f"warning: {w.message}", file=sys.stderr)
        model = PointmapNet(ModelConfig.from_dict(ck["model_config"]))
        load_state_strict(model, ck["model"], source=a.ckpt[-1])
        # the row of the shipped weights' step, else of the latest input that has one, else the last
        inputs = sorted({int(d["step"]) for d in ck.get("averaged", [])}, reverse=True)
        metrics = eval_row(Path(a.metrics), [int(ck["step"]), *inputs]) if a.metrics else {}
        cfg = ck.get("train_config")
        if not isinstance(cfg, dict) or not {"size", "batch_size", "data", "eval_data"} <= set(cfg):
            raise CheckpointError(f"{a.ckpt[-1]}: the run's train_config the shipped file records is missing (size, "
                                  "batch_size, data, eval_data): not a checkpoint written by python -m training.train")
        shipped = shipped_file(a.name)  # a bare name, whatever --out is: load_model(name) reads it
        out = Path(a.out) if a.out else shipped
        if out.is_dir():
            raise ValueError(f"--out expected a file to write the weights to, got the folder {out}")
    except (CheckpointError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    inherited = ck.get("licence")
    if inherited is not None and a.licence not in (None, inherited):
        print(f"error: --licence {a.licence}: the weights derive from ones licensed {inherited}, which they keep",
              file=sys.stderr)
        return 2
    evaluated = None  # for an average: the input whose step the metrics row is
    if metrics and len(a.ckpt) > 1:  # an average was not evaluated: the row is one input's, and recorded as such
        evaluated = next((str(s["source"]) for s in ck["averaged"] if s["step"] == int(metrics["step"])), None)
        print(f"warning: --metrics {a.metrics}: its row is step {int(metrics['step'])}'s"
              f"{f' ({evaluated})' if evaluated else ', none of the inputs'}, not the average's: recorded as "
              "heldout_metrics_of_input", file=sys.stderr)
    elif metrics and int(metrics["step"]) != int(ck["step"]):  # e.g. a run stopped by SIGTERM: not evaluated
        print(f"warning: --metrics {a.metrics}: it has no row of the shipped weights' step {ck['step']}; its last row "
              f"is step {int(metrics['step'])}: the recorded held-out metrics are "
              f"{'an earlier' if metrics['step'] < ck['step'] else 'a later'} state's", file=sys.stderr)
    provenance = {"name": a.name, "image_size": cfg["size"], "steps": ck["step"], "batch_size": cfg["batch_size"],
                  "data": ",".join(Path(r).name for r in cfg["data"].split(",") if r), "eval_data": Path(cfg["eval_data"]).name if cfg["eval_data"] else "",
                  **({"heldout_metrics_of_input": {"source": evaluated, **metrics}} if metrics and len(a.ckpt) > 1
                     else {"heldout_metrics": metrics}), "note": a.note, "licence": inherited or a.licence or "Apache-2.0",
                  **({"averaged_steps": ck["averaged_steps"], "averaged": ck["averaged"]} if len(a.ckpt) > 1 else {}),
                  **({"grown_from": g} if (g := (ck.get("extra") or {}).get("grown_from")) is not None else {}),
                  "trained_with": "python -m training.train " + " ".join(f"--{k} {v}" for k, v in cfg.items()
                                                                         if k in ("preset", "size", "batch_size", "lr", "steps"))}
    path = save_model(model, out, provenance=provenance, dtype=torch.float16 if a.dtype == "fp16" else "int8")
    avg = (", the average of " + ", ".join(f"{d['source']} (step {d['step']}, share {d['share']:.3g})"
                                           for d in ck["averaged"])) if len(a.ckpt) > 1 else ""
    print(f"{path} ({path.stat().st_size / 1e6:.1f} MB), step {ck['step']}{avg}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
