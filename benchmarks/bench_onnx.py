"""Median latency per pair: onnxruntime (fp32, int8, optionally fp16) vs PyTorch eager, in the same run.

    python benchmarks/bench_onnx.py --models small,dust3r_224_linear --res 224 --threads 2
    python benchmarks/bench_onnx.py --quick          # 'small' at 224 only, few repeats

It also times ``load_onnx`` of each export twice, interleaved: as written (every graph and weights file checked
against the SHA-256 its sidecar lists) and from a copy whose sidecar lists no digests (loaded unchecked, as exports
before session 93 are), so the second table's difference is what the check costs a load (``--load-repeats``).

For each model (a shipped model name or preset: random weights when none is shipped; latency does not
depend on the weights) the script exports the single-graph variants into a temp dir, then times one
pair (batch 1, both views at the same resolution) for every backend, interleaving the backends in each
round so machine load affects them alike. Accuracy change of int8/fp16 is measured against fp32 eager
on random images: max |diff| / (1 + max |ref|) over all outputs, and the median / 99th percentile of the
relative error of the points. Prints a markdown table.

With ``--eval-data DIR`` (held-out pairs rendered by ``python -m data.render``) it also reports what
reduced precision does to the task: relative pose (RRA/RTA@15 from the model's own pointmaps), depth
AbsRel and matching precision for eager and every exported variant on the same pairs:

    python benchmarks/bench_onnx.py --models small --variants fp32,int8,fp16 --threads 2 \
        --eval-data ~/.cache/pointmap/data/eval_s424242 --eval-size 160
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from export import export_model, resolve_model  # noqa: E402
from export.parity import compare, random_pair  # noqa: E402
from pointmap.runtime.onnx import SIDECAR, load_onnx  # noqa: E402


def get_model(name: str):
    try:
        return resolve_model(name), "shipped weights"
    except Exception:  # noqa: BLE001 - no shipped weights: the architecture with random weights
        return resolve_model(f"preset:{name}"), "random weights"


def parse_res(text: str) -> list[tuple[int, int]]:
    out = []
    for r in text.split(","):
        h, _, w = r.partition("x")
        out.append((int(h), int(w or h)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="small,dust3r_224_linear")
    ap.add_argument("--res", default="224", help="comma list of H or HxW (e.g. 224,512x384)")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", default="1,2", help="comma list: intra-op threads for both torch and onnxruntime")
    ap.add_argument("--variants", default="fp32,int8", help="comma list from fp32,int8,fp16")
    ap.add_argument("--workdir", default=None, help="where to export (default: a temp dir, removed)")
    ap.add_argument("--quick", action="store_true", help="'small' at 224, 3 repeats")
    ap.add_argument("--eval-data", default=None, help="held-out pair shards: add task metrics per variant")
    ap.add_argument("--eval-size", type=int, default=None, help="eval resolution (default: the model's own)")
    ap.add_argument("--eval-pairs", type=int, default=10_000, help="at most this many held-out pairs")
    ap.add_argument("--load-repeats", type=int, default=5,
                    help="loads timed per export with and without the digest check (0: skip that table)")
    args = ap.parse_args(argv)
    if args.quick:
        args.models, args.res, args.repeats = "small", "224", 3
    variants = args.variants.split(",")
    unknown = sorted(set(variants) - {"fp32", "int8", "fp16"})
    if unknown or args.repeats < 1 or args.load_repeats < 0:
        ap.error(f"--variants expected names from fp32,int8,fp16, --repeats >= 1 and --load-repeats >= 0, got "
                 f"{unknown or variants}, {args.repeats} and {args.load_repeats}")
    tmp = tempfile.TemporaryDirectory() if args.workdir is None else None
    work = Path(args.workdir or tmp.name)
    rows, eval_rows, load_rows = [], [], []
    print(f"torch {torch.__version__}, threads {args.threads}, median of {args.repeats} (after 1 warm-up)", flush=True)
    for name in args.models.split(","):
        model, weights = get_model(name)
        for v in variants:
            t0 = time.perf_counter()
            out = work / f"{name}-{v}"
            if not (out / SIDECAR).exists():
                export_model(model, out, fp16=v == "fp16", quantize="int8" if v == "int8" else None, parity="none")
            print(f"  {name}: {v} export ready ({time.perf_counter() - t0:.0f} s)", flush=True)
        if args.load_repeats:
            load_rows += load_times(name, work, variants, args.load_repeats, int(str(args.threads).split(",")[-1]))
        for threads in [int(t) for t in str(args.threads).split(",")]:
            torch.set_num_threads(threads)
            runners = {v: load_onnx(work / f"{name}-{v}", threads=threads) for v in variants}
            for H, W in parse_res(args.res):
                img1, img2 = random_pair(H, W, H, W, 1, seed=1)
                backends = {"eager": model, **runners}
                times = {k: [] for k in backends}
                with torch.inference_mode():
                    ref = model(img1, img2)  # also the warm-up of eager; the runners warm up below
                    acc = {v: compare(ref, r(img1, img2)) for v, r in runners.items()}
                    for _ in range(args.repeats):  # interleaved, so load changes hit every backend
                        for k, f in backends.items():
                            t0 = time.perf_counter()
                            f(img1, img2)
                            times[k].append(time.perf_counter() - t0)
                med = {k: statistics.median(t) for k, t in times.items()}
                for k in backends:
                    a = acc.get(k)
                    rel = a["outputs"]["pts1_cam1"] if a else None
                    rows.append([name, weights, f"{H}x{W}", str(threads),
                                 "pytorch eager" if k == "eager" else f"onnxruntime {k}",
                                 f"{med[k] * 1000:.0f}", f"{med['eager'] / med[k]:.2f}x",
                                 "-" if a is None else f"{a['worst_ratio'] * 1e-4:.1e}",
                                 "-" if a is None else f"{rel['rel_err_median']:.1e} / {rel['rel_err_p99']:.1e}"])
                print(f"  {name} {H}x{W} {threads} threads: "
                      + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in med.items()), flush=True)
            del runners
        if args.eval_data:
            eval_rows += task_metrics(name, model, {v: load_onnx(work / f"{name}-{v}") for v in variants}, args)
    head = ["model", "weights", "input", "threads", "backend", "median ms/pair", "speed-up vs eager",
            "max err / (1+max|ref|)", "pts rel. err median / p99"]
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")
    if load_rows:
        head = ["model", "backend", "export MB", "load ms, digests checked", "load ms, unchecked", "check cost ms"]
        print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
        for r in load_rows:
            print("| " + " | ".join(r) + " |")
    if eval_rows:
        head = ["model", "backend", "pairs", "RRA@15 %", "RTA@15 %", "rot err med (deg)", "AbsRel", "match prec"]
        print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
        for r in eval_rows:
            print("| " + " | ".join(r) + " |")
    if tmp is not None:
        tmp.cleanup()
    return 0


def load_times(name: str, work: Path, variants: list[str], repeats: int, threads: int) -> list[list[str]]:
    """Median ``load_onnx`` time of each variant's export as written (its files checked against the SHA-256 digests
    its sidecar lists) and of a copy whose sidecar lists none (loaded unchecked), interleaved in each round after one
    warm-up load of each, so the file cache and machine load are the same for both. Rows for the load table."""
    rows = []
    for v in variants:
        folder = work / f"{name}-{v}"
        bare = work / f"{name}-{v}-unchecked"
        shutil.rmtree(bare, ignore_errors=True)  # a copy of this run's export, not an earlier run's
        shutil.copytree(folder, bare)
        meta = json.loads((bare / SIDECAR).read_text())
        if "files" not in meta:
            raise SystemExit(f"{folder}: its sidecar lists no file digests (an export from before session 93?): "
                             "remove it and run again")
        del meta["files"]
        (bare / SIDECAR).write_text(json.dumps(meta, indent=1))
        times = {"checked": [], "unchecked": []}
        for i in range(repeats + 1):
            for k, f in (("checked", folder), ("unchecked", bare)):
                t0 = time.perf_counter()
                load_onnx(f, threads=threads)
                if i:  # the first round warms the file cache and onnxruntime
                    times[k].append(time.perf_counter() - t0)
        med = {k: statistics.median(t) * 1000 for k, t in times.items()}
        mb = sum(p.stat().st_size for p in folder.iterdir() if p.is_file()) / 1e6
        rows.append([name, f"onnxruntime {v}", f"{mb:.1f}", f"{med['checked']:.0f}", f"{med['unchecked']:.0f}",
                     f"{med['checked'] - med['unchecked']:.0f}"])
        print(f"  {name} {v} load: checked {med['checked']:.0f} ms, unchecked {med['unchecked']:.0f} ms", flush=True)
    return rows


def task_metrics(name, model, runners, args) -> list[list[str]]:
    """Held-out pose/depth/matching metrics of eager and each ONNX variant on the same pairs."""
    from data.datasets import PairDataset
    from training.evaluate import evaluate_pairs

    size = args.eval_size or int((getattr(model, "provenance", None) or {}).get("image_size", 224))
    ds = PairDataset(args.eval_data, size=size, augment=False, split="all")
    rows = []
    for k, m in {"pytorch eager": model, **{f"onnxruntime {v}": r for v, r in runners.items()}}.items():
        ev = evaluate_pairs(m, ds, args.eval_pairs)
        rows.append([name, k, f"{ev['pairs']:.0f}", f"{ev['RRA15']:.1f}", f"{ev['RTA15']:.1f}",
                     f"{ev['rot_err_med']:.1f}", f"{ev['AbsRel']:.3f}", f"{ev['match_prec']:.3f}"])
        print(f"  {name} {k}: " + ", ".join(f"{a}={b:.4g}" for a, b in ev.items()), flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
