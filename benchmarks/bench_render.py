"""Rendering throughput of the synthetic data engine: pairs/s with full ground truth (RGB, exact depth,
K, poses, overlap, correspondences both ways, PNG/npz encoding, shard writing) at 224 and 512 px, with
1 and 2 worker processes.

    PYOPENGL_PLATFORM=egl python benchmarks/bench_render.py [--scenes 12] [--views 4] [--sizes 224 512] [--versions 2 3]

``--versions`` renders the same seeds with each generator version (data.generate.GENERATOR_VERSION by default):
a new version's cost against the one before it, in the same minutes.

Each configuration runs in a fresh Python process, as `python -m data.render` would (so worker start-up
is what a real run pays, and no configuration inherits another's GL context). ``cpu s`` is the CPU time
of that process and its workers (GL rasterisation threads included): on a shared machine, where wall
time depends on the other jobs, ``pairs per cpu s`` is the steadier measure of the engine's own cost.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(size, workers, scenes, views, seed, version):
    """One configuration in this process: (pairs, views, wall seconds, cpu seconds, bytes, the generator version
    the dataset records)."""
    import resource

    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from data.generate import GenConfig, generate

    def cpu():
        a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime

    with tempfile.TemporaryDirectory() as d:
        cfg = GenConfig(kind="pairs", scenes=scenes, views=views, size=size, shard_size=1, seed=seed, version=version)
        t0, c0 = time.perf_counter(), cpu()
        m = generate(d, cfg, workers=workers, progress=False, log=None)
        dt, dc = time.perf_counter() - t0, cpu() - c0
        nbytes = sum(s["bytes"] for s in m["shards"])
        recorded = json.loads((Path(d) / "config.json").read_text())["version"]
    return m["pairs"], m["views"], dt, dc, nbytes, recorded


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=12)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--sizes", type=int, nargs="+", default=[224, 512])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--seed", type=int, default=1234)
    p.add_argument("--versions", type=int, nargs="+", default=None,
                   help="generator versions to render the same seeds with (default: the latest)")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # internal: one configuration, JSON out
    a = p.parse_args(argv)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    # numpy and trimesh only: the renderer and torch load in each configuration's own process
    from data.scene import SCENE_VERSIONS

    versions = a.versions or [SCENE_VERSIONS[-1]]  # data.generate.GENERATOR_VERSION
    if not set(versions) <= set(SCENE_VERSIONS):
        p.error(f"--versions expected generator versions of {SCENE_VERSIONS}, got {versions}")
    if a.one:
        print(json.dumps(run(a.sizes[0], a.workers[0], a.scenes, a.views, a.seed, versions[0])))
        return
    print(f"{'size':>5} {'workers':>7} {'version':>7} {'scenes':>6} {'pairs':>6} {'seconds':>8} {'pairs/s':>8} "
          f"{'views/s':>8} {'cpu s':>7} {'pairs/cpu s':>11} {'MB/pair':>8}")
    env = dict(os.environ)
    env.setdefault("PYOPENGL_PLATFORM", "egl")
    for size in a.sizes:
        for w in a.workers:
            for v in versions:
                cmd = [sys.executable, __file__, "--one", "--sizes", str(size), "--workers", str(w), "--scenes",
                       str(a.scenes), "--views", str(a.views), "--seed", str(a.seed), "--versions", str(v)]
                out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
                if out.returncode != 0:
                    sys.exit(f"size {size}, {w} workers, version {v} failed:\n{out.stderr}")
                pairs, views, dt, dc, nbytes, recorded = json.loads(out.stdout.strip().splitlines()[-1])
                if recorded != v:
                    sys.exit(f"version {v} asked for, the dataset records version {recorded}")
                print(f"{size:>5} {w:>7} {v:>7} {a.scenes:>6} {pairs:>6} {dt:>8.1f} {pairs / dt:>8.2f} "
                      f"{views / dt:>8.2f} {dc:>7.1f} {pairs / max(dc, 1e-9):>11.2f} "
                      f"{nbytes / max(pairs, 1) / 1e6:>8.2f}", flush=True)
    print(f"(views per scene: {a.views}; every pair stored with both directions' correspondences; "
          f"cpu count {os.cpu_count()}, load average {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
