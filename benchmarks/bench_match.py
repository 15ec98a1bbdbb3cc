"""Reciprocal matching (``pm.match``): time and peak memory per image size, the similarity blocks sized by
``pointmap.matching.BLOCK_ENTRIES`` (since session 81) against a fixed number of query rows per block (4,096
before it), in the same run.

The shipped model predicts the demo room pair once per size; each row then matches that prediction in a fresh
process that loads only the prediction, so the peak resident memory it reports (``ru_maxrss``) is the matching's,
not the network's (Linux: ``VmHWM``). Every row must find the same matches as the first row of its size ("same").

    python benchmarks/bench_match.py --sizes 224 512 --blocks budget 4096
    python benchmarks/bench_match.py --sizes 512 1024 --blocks budget     # 1024: the fixed rows need ~13 GB
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import fields
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pointmap as pm  # noqa: E402
import pointmap.matching as matching  # noqa: E402

PAIR = [ROOT / "pointmap" / "demo_scenes" / "room" / f"view-{i}.png" for i in (0, 1)]


def peak_rss_gb() -> float:
    """This process's peak resident memory: VmHWM, which starts afresh at exec (``ru_maxrss`` keeps the forking
    parent's peak across it)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1e6  # kB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # not Linux: kilobytes on most systems


def child(path: str, blocks: str, subsample: int, threads: int) -> None:
    """Match one saved prediction; print one JSON line."""
    torch.set_num_threads(threads)
    saved = torch.load(path, weights_only=True)
    pred = pm.PairPrediction(**saved)
    if blocks != "budget":
        rows = int(blocks)
        matching.block_rows = lambda n_db, chunk=None: chunk if chunk is not None else rows
    n_db = pred.desc2.shape[1] * pred.desc2.shape[2]
    before = peak_rss_gb()
    t = time.perf_counter()
    m = pm.match(pred, subsample=subsample)
    seconds = time.perf_counter() - t
    digest = hashlib.sha256(torch.cat([m.xy1, m.xy2], 1).numpy().tobytes()).hexdigest()[:12]
    print(json.dumps({"rows": matching.block_rows(n_db), "matches": len(m), "seconds": seconds,
                      "before_gb": before, "peak_gb": peak_rss_gb(), "digest": digest}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="small", help="model name or file (needs a descriptor head)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[224, 512], help="load_images size (long side)")
    ap.add_argument("--blocks", nargs="+", default=["budget", "4096"],
                    help="'budget' (BLOCK_ENTRIES) or a fixed number of query rows per block")
    ap.add_argument("--subsample", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.blocks[0], args.subsample, args.threads)
        return 0
    for b in args.blocks:
        if b != "budget" and not (b.isdigit() and int(b) > 0):
            ap.error(f"--blocks expected 'budget' or a positive row count, got {b!r}")
    if any(s < 16 for s in args.sizes):
        ap.error(f"--sizes expected sizes >= 16, got {args.sizes}")
    if args.subsample < 1 or args.threads < 1:
        ap.error(f"--subsample and --threads expected >= 1, got {args.subsample} and {args.threads}")
    torch.set_num_threads(args.threads)
    try:
        model = pm.load_model(args.model)
    except pm.PointmapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"pm.match on the demo room pair, model {args.model}, subsample {args.subsample}, "
          f"{args.threads} threads, BLOCK_ENTRIES {matching.BLOCK_ENTRIES:,}\n")
    print("| size | views | blocks | rows per block | matches | seconds | peak RSS GB (prediction loaded) | same |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            views = pm.load_images([str(p) for p in PAIR], size=size)
            pred = pm.predict_pairs(model, views, [(0, 1)], quiet=True)[(0, 1)]
            if not pred.has_desc:
                print(f"model {args.model} has no descriptor head; pm.match would match pointmaps", file=sys.stderr)
                return 2
            path = f"{tmp}/pred_{size}.pt"
            torch.save({f.name: getattr(pred, f.name).clone() for f in fields(pred)  # a view saves its whole storage
                        if getattr(pred, f.name) is not None}, path)
            H, W = pred.desc1.shape[1:3]
            ref = None
            for blocks in args.blocks:
                run = subprocess.run([sys.executable, __file__, "--child", path, "--blocks", blocks,
                                      "--subsample", str(args.subsample), "--threads", str(args.threads)],
                                     capture_output=True, text=True)
                if run.returncode != 0:
                    last = (run.stderr.strip().splitlines() or ["(no message)"])[-1]
                    print(f"| {size} | {W}x{H} | {blocks} | - | - | - | failed: {last} | - |")
                    continue
                r = json.loads(run.stdout.strip().splitlines()[-1])
                ref = ref or r["digest"]
                print(f"| {size} | {W}x{H} | {blocks} | {r['rows']:,} | {r['matches']:,} | {r['seconds']:.2f} | "
                      f"{r['peak_gb']:.2f} ({r['before_gb']:.2f}) | {'yes' if r['digest'] == ref else 'NO'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
