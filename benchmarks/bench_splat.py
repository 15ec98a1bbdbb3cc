"""Gaussian-splatting benchmark: rasterizer speed/memory and the end-to-end fit on a rendered scene.

    .venv/bin/python benchmarks/bench_splat.py                 # both parts
    .venv/bin/python benchmarks/bench_splat.py --part raster   # rasterizer table only
    .venv/bin/python benchmarks/bench_splat.py --part scene --time-budget 120

Part "raster": forward+backward (projection + tiled compositing + L1 loss) at 128x96, 256x192 and
512x384 with 5k/20k/100k Gaussians unprojected from a wavy depth surface (sigma ~ pixel spacing, as a
kNN init gives), opacity 0.5. Reports the best of 3 in CPU seconds and wall seconds, and the peak
resident memory of the process (sampled from /proc/self/statm; it includes the interpreter, torch and
the allocator's cache from earlier rows, so it is an upper bound per row).

Part "scene": the pyrender scene of tests/splat/scene.py (4 training views at 256x192, 3 held-out
views between them), ground-truth depth with 1% noise, training poses 2..4 perturbed by 1 deg and
2 cm (view 0 anchors the gauge), held-out poses perturbed the same way. Runs init + fit with the
automatic CPU budget, aligns each held-out pose (Gaussians frozen), and reports PSNR/SSIM at
256x192, the training-pose errors before/after, and times (CPU and wall: the machine is shared).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

PAGE = os.sysconf("SC_PAGE_SIZE")


class PeakRSS:
    """Samples the resident set size in a thread; ``peak_mb`` is the maximum above the start value."""

    def __enter__(self):
        self.start = self._rss()
        self.peak = self.start
        self.stop = False
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()
        return self

    def _rss(self):
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * PAGE

    def _run(self):
        while not self.stop:
            self.peak = max(self.peak, self._rss())
            time.sleep(0.002)

    def __exit__(self, *a):
        self.stop = True
        self.t.join()
        self.peak_mb = (self.peak - self.start) / 2**20
        self.peak_abs_mb = self.peak / 2**20


def pointmap_like(n, W, H, seed=0):
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * W
    u = torch.rand(n, generator=g) * W
    v = torch.rand(n, generator=g) * H
    z = 4 + 0.5 * torch.sin(u / W * 6) * torch.cos(v / H * 5)
    K = torch.tensor([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1.0]])
    means = torch.stack([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z], -1)
    scales = (z / f * math.sqrt(W * H / n))[:, None].repeat(1, 3)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return means, quats, scales, torch.full((n,), 0.5), torch.rand(n, 3, generator=g), torch.eye(4), K


def bench_raster(sizes, counts, reps=3):
    from pointmap.splat import rasterize

    rows = []
    for W, H in sizes:
        for n in counts:
            sc = pointmap_like(n, W, H)
            target = torch.rand(H, W, 3)
            best_cpu = best_wall = best_fwd = float("inf")
            with PeakRSS() as mem:
                for _ in range(reps):
                    ins = [t.clone().requires_grad_(i < 5) for i, t in enumerate(sc)]
                    c0, w0 = time.process_time(), time.perf_counter()
                    out = rasterize(*ins, W, H)
                    fwd = time.process_time() - c0
                    (out.image - target).abs().mean().backward()
                    best_cpu = min(best_cpu, time.process_time() - c0)
                    best_wall = min(best_wall, time.perf_counter() - w0)
                    best_fwd = min(best_fwd, fwd)
                    del out, ins
            rows.append((f"{W}x{H}", n, best_fwd, best_cpu, best_wall, mem.peak_mb, mem.peak_abs_mb))
            print(f"  {W}x{H} N={n}: fwd {best_fwd:.3f} s, "
                  f"fwd+bwd {best_cpu:.3f} s CPU / {best_wall:.3f} s wall, "
                  f"peak RSS {mem.peak_abs_mb:.0f} MB (+{mem.peak_mb:.0f})", flush=True)
    print("\n| resolution | Gaussians | fwd CPU s | fwd+bwd CPU s | fwd+bwd wall s | peak RSS MB (process) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.3f} | {r[4]:.3f} | {r[6]:.0f} |")
    return rows


def bench_scene(time_budget=None, align_steps=60, seed=0):
    from pointmap.geometry import relative_rotation_error_deg
    from pointmap.splat import auto_budget, fit, init_from
    from pointmap.splat.fit import _ssim, psnr
    from tests.splat.scene import make_benchmark_scene

    d = make_benchmark_scene(seed=seed)
    recon, K = d["recon"], d["K"]
    n, H, W = recon.depth_z.shape
    budget = auto_budget(n, (W, H))
    c0, w0 = time.process_time(), time.perf_counter()
    g = init_from(recon, max_gaussians=budget["max_gaussians"], seed=seed)
    t_init = time.perf_counter() - w0
    remaining = None if time_budget is None else max(1.0, time_budget - t_init)  # as pointmap.splat.run
    res = fit(recon, g, progress=False, time_budget=remaining, seed=seed)
    cpu_fit, wall_fit = time.process_time() - c0, time.perf_counter() - w0

    def pose_err(c2w):
        gt = d["train_c2w_gt"]
        rot = relative_rotation_error_deg(c2w[:, :3, :3], gt[:, :3, :3])
        return rot[1:].mean().item(), (c2w[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1)[1:].mean().item()

    r0, t0 = pose_err(recon.cam2world)
    r1, t1 = pose_err(res.cam2world)
    train_psnr = sum(psnr(res.render(res.cam2world[i], K, W, H), recon.images[i]) for i in range(n)) / n
    c1, w1 = time.process_time(), time.perf_counter()
    rows = []
    for i in range(len(d["test_images"])):
        img = d["test_images"][i]
        p_init = psnr(res.render(d["test_c2w_init"][i], K, W, H), img)
        c2w = res.align_view(img, d["test_c2w_init"][i], K, steps=align_steps)
        r = res.render(c2w, K, W, H)
        rows.append((i, p_init, psnr(r, img), float(_ssim(r, img))))
    cpu_align, wall_align = time.process_time() - c1, time.perf_counter() - w1
    print(f"\nscene: {n} training views {W}x{H}, {len(g)} Gaussians, {res.config['steps_run']}/"
          f"{res.config['steps']} steps at {res.config['levels']}")
    print("| held-out view | PSNR at perturbed pose | PSNR after alignment | SSIM after alignment |")
    print("|---|---|---|---|")
    for i, a, b, s in rows:
        print(f"| {i} | {a:.2f} | {b:.2f} | {s:.3f} |")
    mean_psnr = sum(r[2] for r in rows) / len(rows)
    mean_ssim = sum(r[3] for r in rows) / len(rows)
    print(f"| mean | | **{mean_psnr:.2f}** | **{mean_ssim:.3f}** |")
    print(f"\ntraining-view PSNR (fitted poses): {train_psnr:.2f} dB")
    print(f"training-pose error (views 1..{n - 1}, mean): rotation {r0:.3f} -> {r1:.3f} deg, "
          f"translation {t0 * 100:.2f} -> {t1 * 100:.2f} cm")
    print(f"init {t_init:.1f} s wall; init + fit {cpu_fit:.1f} s CPU / {wall_fit:.1f} s wall; "
          f"alignment of {len(rows)} views x {align_steps} steps "
          f"{cpu_align:.1f} s CPU / {wall_align:.1f} s wall")
    print(f"load average at the end: {os.getloadavg()[0]:.1f} (2 cores, shared)")
    return {"psnr": mean_psnr, "ssim": mean_ssim, "fit_wall": wall_fit, "fit_cpu": cpu_fit,
            "rot": (r0, r1), "trans": (t0, t1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=["raster", "scene", "all"], default="all")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch intra-op threads (1 is best on a loaded box)")
    ap.add_argument("--time-budget", type=float, default=None, help="seconds for init + fit (stops early)")
    ap.add_argument("--align-steps", type=int, default=60)
    ap.add_argument("--quick", action="store_true", help="raster part: 128x96 and 256x192 with 5k/20k only")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"load average {os.getloadavg()[0]:.1f}")
    if args.part in ("raster", "all"):
        print("\nrasterizer forward+backward (best of 3):")
        sizes = [(128, 96), (256, 192)] if args.quick else [(128, 96), (256, 192), (512, 384)]
        counts = [5000, 20000] if args.quick else [5000, 20000, 100000]
        bench_raster(sizes, counts)
    if args.part in ("scene", "all"):
        bench_scene(args.time_budget, args.align_steps)


if __name__ == "__main__":
    main()
