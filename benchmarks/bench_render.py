"""Rendering throughput of the synthetic data engine: pairs/s with full ground truth (RGB, exact depth,
K, poses, overlap, correspondences both ways, PNG/npz encoding, shard writing) at 224 and 512 px, with
1 and 2 worker processes.

    PYOPENGL_PLATFORM=egl python benchmarks/bench_render.py [--scenes 12] [--views 4] [--sizes 224 512]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.generate import GenConfig, generate  # noqa: E402


def run(size, workers, scenes, views, seed):
    with tempfile.TemporaryDirectory() as d:
        cfg = GenConfig(kind="pairs", scenes=scenes, views=views, size=size, shard_size=1, seed=seed)
        t0 = time.perf_counter()
        m = generate(d, cfg, workers=workers, progress=False, log=None)
        dt = time.perf_counter() - t0
        nbytes = sum(s["bytes"] for s in m["shards"])
    return m["pairs"], m["views"], dt, nbytes


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=12)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--sizes", type=int, nargs="+", default=[224, 512])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--seed", type=int, default=1234)
    a = p.parse_args(argv)
    print(f"{'size':>5} {'workers':>7} {'scenes':>6} {'pairs':>6} {'seconds':>8} {'pairs/s':>8} {'views/s':>8} "
          f"{'MB/pair':>8}")
    for size in a.sizes:
        for w in a.workers:
            pairs, views, dt, nbytes = run(size, w, a.scenes, a.views, a.seed)
            print(f"{size:>5} {w:>7} {a.scenes:>6} {pairs:>6} {dt:>8.1f} {pairs / dt:>8.2f} {views / dt:>8.2f} "
                  f"{nbytes / max(pairs, 1) / 1e6:>8.2f}", flush=True)
    print(f"(views per scene: {a.views}; every pair stored with both directions' correspondences; "
          f"cpu count {os.cpu_count()}, load average {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
