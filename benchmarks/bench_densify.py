"""Densification's effect on a fit: held-out PSNR with and without ``densify=True``, in one run.

    .venv/bin/python benchmarks/bench_densify.py                      # 96 x 72, 150 steps, densify every 20
    .venv/bin/python benchmarks/bench_densify.py --size 128 96 --steps 300 --every 50

The pyrender scene of tests/splat/scene.py (``make_benchmark_scene``: training views with 1% depth noise and
perturbed poses, held-out views between them), the same init for both rows, the same seed; held-out views
rendered from their true poses (no test-time alignment, so the figure is the Gaussians' alone)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, nargs=2, default=(96, 72), metavar=("W", "H"))
    ap.add_argument("--train", type=int, default=3, help="training views (default 3)")
    ap.add_argument("--test", type=int, default=2, help="held-out views (default 2)")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--every", type=int, default=20, help="densify_every (default 20)")
    ap.add_argument("--grad", type=float, default=2e-4, help="densify_grad (default 2e-4, 3DGS's)")
    ap.add_argument("--max-gaussians", type=int, default=1500)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    if min(a.size) < 16 or a.train < 2 or a.test < 1 or a.steps < 1 or a.every < 1 or a.grad <= 0:
        ap.error(f"expected --size >= 16, --train >= 2, --test >= 1, --steps, --every >= 1 and --grad > 0, got "
                 f"{a.size}, {a.train}, {a.test}, {a.steps}, {a.every}, {a.grad}")
    import torch

    from pointmap.splat import fit, init_from
    from pointmap.splat.outputs import evaluate_views
    from tests.splat.scene import make_benchmark_scene

    torch.set_num_threads(a.threads)
    d = make_benchmark_scene(width=a.size[0], height=a.size[1], n_train=a.train, n_test=a.test, seed=a.seed)
    g = init_from(d["recon"], max_gaussians=a.max_gaussians)
    K = torch.as_tensor(d["K"], dtype=torch.float32).expand(a.test, 3, 3)
    print("| densify | Gaussians | train PSNR | held-out PSNR | held-out SSIM | fit s |\n|---|---|---|---|---|---|")
    for densify in (False, True):
        torch.manual_seed(a.seed)
        t = time.perf_counter()
        res = fit(d["recon"], g, steps=a.steps, max_side=max(a.size), coarse_frac=0.0, progress=False,
                  densify=densify, densify_every=a.every, densify_grad=a.grad)
        seconds = time.perf_counter() - t
        ev = evaluate_views(res, d["test_images"], d["test_c2w_gt"], K, align_steps=0, quiet=True)
        print(f"| {'on' if densify else 'off'} | {len(g)} -> {len(res.gaussians)} | {res.history[-1]['psnr']:.2f} | "
              f"{ev['psnr']:.2f} | {ev['ssim']:.3f} | {seconds:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
