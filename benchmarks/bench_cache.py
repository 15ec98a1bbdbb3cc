"""What the prediction cache (``reconstruct(cache=DIR)``, ``--cache DIR``) costs and saves: one rendered scene
reconstructed without a cache (the baseline), then twice with a float32 cache and twice with a float16 one
(``--cache-half``), each in a new empty folder, in the same run. Per run: the wall time, the inference stage's
(``info["pipeline"]["seconds"]``), the pairs read and predicted, the cache's size on disk (files written
atomically and synced, as ``put`` always does), and the largest camera rotation difference from the run without a
cache (a float32 cache reads back bit for bit: 0; float16 may differ slightly). The five runs are repeated in turn
(``--repeats``) and each figure is the median (min-max) over the repeats.

    nice .venv/bin/python benchmarks/bench_cache.py --model small --views 9 --threads 2
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pointmap as pm  # noqa: E402
from benchmarks.bench_inference import load_models  # noqa: E402
from benchmarks.bench_pipeline import KINDS, render_views  # noqa: E402
from pointmap.cache import PredictionCache  # noqa: E402
from pointmap.geometry.rotations import relative_rotation_error_deg  # noqa: E402


def folder_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def spread(xs: list) -> str:
    """'median (min-max)' of a list of seconds; the value alone for one."""
    med = statistics.median(xs)
    return f"{med:.1f}" if len(xs) == 1 else f"{med:.1f} ({min(xs):.1f}-{max(xs):.1f})"


def rotation_gap_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest angle (degrees) between the same camera's rotations in two reconstructions (both anchored alike);
    ``relative_rotation_error_deg``'s atan2 form reads 0 for equal matrices, where arccos of the trace of a float32
    rotation that is not quite orthonormal reads ~0.02 degrees."""
    ra, rb = (torch.as_tensor(c)[:, :3, :3].double() for c in (a, b))
    return float(relative_rotation_error_deg(ra, rb).max())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="small", help="a shipped model's name or a model file")
    p.add_argument("--views", type=int, default=9, help="rendered views of the scene (>= 2); graph complete")
    p.add_argument("--kind", choices=KINDS, default="room")
    p.add_argument("--render-size", type=int, default=320)
    p.add_argument("--size", type=int, default=224, help="network input size")
    p.add_argument("--niter", type=int, default=300, help="alignment iterations")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3, help="times the five runs are made, in turn (median reported)")
    p.add_argument("--dir", default=None, help="where the caches are made (default: a temporary folder, removed)")
    a = p.parse_args(argv)
    if a.views < 2 or min(a.threads, a.niter, a.repeats) < 1:
        p.error(f"--views expected >= 2, --threads, --niter and --repeats >= 1, got {a.views}, {a.threads}, "
                f"{a.niter} and {a.repeats}")
    try:
        model = load_models([a.model])[a.model]
    except pm.CheckpointError as e:
        p.error(str(e))
    torch.set_num_threads(a.threads)
    images, _ = render_views(a.views, a.kind, a.render_size)
    root = Path(tempfile.mkdtemp(prefix="bench_cache_", dir=a.dir))
    kw = dict(size=a.size, graph="complete", quiet=True, align=pm.AlignConfig(niter=a.niter, quiet=True))
    runs = [("no cache (baseline)", None, None), ("float32 cache, first run", "f32", torch.float32),
            ("float32 cache, second run", "f32", torch.float32), ("float16 cache, first run", "f16", torch.float16),
            ("float16 cache, second run", "f16", torch.float16)]
    print(f"model {a.model}; {a.views} views of a {a.kind} at {a.size} px, graph complete "
          f"({a.views * (a.views - 1)} directed pairs); {a.threads} threads\n")
    print(f"median (min-max) of {a.repeats} repeats; the second runs read what the first just wrote "
          "(warm page cache)\n")
    print("| run | wall s | inference s | pairs read / predicted | cache MB | max rotation gap to baseline (deg) |")
    print("|---|---|---|---|---|---|")
    pm.reconstruct(model, images[:2], **kw)  # untimed warm-up: first-call costs (imports, allocator) out of the table
    walls, infers, counts, sizes, gaps = ({name: [] for name, _, _ in runs} for _ in range(5))
    try:
        for rep in range(a.repeats):  # the five runs in turn, each repeat in new folders: drift hits them alike
            base = None
            for name, sub, dtype in runs:
                t0 = time.perf_counter()  # the cache's own weight hash (--cache DIR makes one) inside the timing
                cache = None if sub is None else PredictionCache(root / f"r{rep}" / sub, model, dtype)
                recon = pm.reconstruct(model, images, cache=cache, **kw)
                walls[name].append(time.perf_counter() - t0)
                info = recon.info["pipeline"]
                infers[name].append(info["seconds"]["inference"])
                base = recon.cam2world if base is None else base
                gaps[name].append(rotation_gap_deg(base, recon.cam2world))
                if cache is not None:
                    counts[name].append(f"{info['cache']['hits']} / {info['cache']['misses']}")
                    sizes[name].append(folder_mb(root / f"r{rep}" / sub))
    finally:
        if a.dir is None:
            shutil.rmtree(root, ignore_errors=True)
    for name, _, _ in runs:
        c = " or ".join(sorted(set(counts[name]))) or "-"
        size = f"{max(sizes[name]):.0f}" if sizes[name] else "-"
        print(f"| {name} | {spread(walls[name])} | {spread(infers[name])} | {c} | {size} | {max(gaps[name]):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
