"""Time and peak memory of global alignment against the number of images (alignment only).

Predictions are ground-truth pointmaps of the analytic test scene (tests/align/align_scene.py) with 1%
depth noise, 2% outliers, ``--pose-noise`` degrees of per-pair pose noise (default 0.3) and a random scale per
pair, on a sparse cyclic sliding-window graph (every image paired with its next ``--window`` images). Each image
count (and start, ``--init``) runs in a fresh subprocess so the peak RSS is its own. Writes a table (stdout,
markdown) and a PNG plot of the first start.

    nice .venv/bin/python benchmarks/bench_align.py --sizes 10 25 50 100 --hw 384 512 --png bench_align.png
    nice .venv/bin/python benchmarks/bench_align.py --sizes 10 40 100 --hw 64 96 --window 3 --pose-noise 8 \
        --init mst averaging   # the two starts on the same predictions

``--official PATH`` additionally runs the official DUSt3R PointCloudOptimizer (needs a checkout with
croco, and the ``roma`` and ``einops`` packages) on the same predictions for the smaller sizes.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pointmap.align.optimize import INITS  # noqa: E402


def make_inputs(n: int, h: int, w: int, window: int, seed: int = 0, pose_noise: float = 0.3):
    import numpy as np
    import torch

    sys.path.insert(0, str(ROOT / "tests" / "align"))
    from align_scene import gt_preds, make_scene, views_of

    from pointmap.pairs import make_pairs

    f = 0.85 * w
    sc = make_scene(n, h, w, seed=seed, focal_range=(f * 0.9, f * 1.1))
    pairs = sorted(make_pairs(n, f"swin-{window}"))  # cyclic sliding window
    preds = gt_preds(sc, pairs, seed=seed, noise=0.01, outliers=0.02, pair_rot_deg=pose_noise)
    del sc["pts_world"]
    return sc, views_of(sc), preds, pairs, np, torch


def run_one(n: int, h: int, w: int, window: int, official: str | None, niter: int, init: str = "averaging",
            pose_noise: float = 0.3) -> dict:
    sc, views, preds, pairs, np, torch = make_inputs(n, h, w, window, pose_noise=pose_noise)
    sys.path.insert(0, str(ROOT / "tests" / "align"))
    from align_scene import pose_errors

    from pointmap.align import AlignConfig, global_align

    torch.set_num_threads(1)
    rss_inputs = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    out = {"n": n, "pairs": len(pairs), "directed": len(preds), "hw": [h, w], "init": init}
    if official:
        out.update(run_official(official, views, preds, sc, niter))
        return out
    t = time.perf_counter()
    recon = global_align(views, preds, config=AlignConfig(quiet=True, niter=niter, init=init))
    out["seconds"] = time.perf_counter() - t
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    out["inputs_rss_gb"] = rss_inputs
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    out["rot_err_deg"], out["centre_err"] = rot, centre
    start = global_align(views, preds, config=AlignConfig(quiet=True, optimizer="none", init=init))  # after timing
    out["start_rot_err_deg"] = pose_errors(start.cam2world.numpy(), sc["cam2world"])[0]
    rep = recon.info["align"]
    out.update({k: rep[k] for k in ("iterations", "stop_reason", "stride", "opt_pixels_per_image")})
    out["seconds_optimise"] = rep["seconds"]
    return out


def run_official(path: str, views, preds, sc, niter: int) -> dict:
    """The official PointCloudOptimizer on the same predictions (both orders, as its loader expects)."""
    import torch

    sys.path.insert(0, path)
    _stub_torchvision()
    from dust3r.cloud_opt import GlobalAlignerMode, global_aligner  # noqa: E402  (official, run only)

    sys.path.insert(0, str(ROOT / "tests" / "align"))
    from align_scene import pose_errors

    keys = sorted(preds)
    view1 = {"idx": [i for i, _ in keys], "instance": [str(i) for i, _ in keys],
             "img": torch.stack([views[i].img * 2 - 1 for i, _ in keys])}
    view2 = {"idx": [j for _, j in keys], "instance": [str(j) for _, j in keys],
             "img": torch.stack([views[j].img * 2 - 1 for _, j in keys])}
    pred1 = {"pts3d": torch.cat([preds[k].pts1_cam1 for k in keys]), "conf": torch.cat([preds[k].conf1 for k in keys])}
    pred2 = {"pts3d_in_other_view": torch.cat([preds[k].pts2_cam1 for k in keys]),
             "conf": torch.cat([preds[k].conf2 for k in keys])}
    t = time.perf_counter()
    scene = global_aligner({"view1": view1, "view2": view2, "pred1": pred1, "pred2": pred2}, device="cpu",
                           mode=GlobalAlignerMode.PointCloudOptimizer, verbose=False)
    scene.compute_global_alignment(init="mst", niter=niter, schedule="cosine", lr=0.01)
    secs = time.perf_counter() - t
    c2w = scene.get_im_poses().detach().double().numpy()
    rot, centre, _ = pose_errors(c2w, sc["cam2world"])
    return {"official_seconds": secs, "official_peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
            "official_rot_err_deg": rot, "official_centre_err": centre}


def _stub_torchvision() -> None:
    """The official package imports torchvision.transforms at module level for image loading only (not
    used by the optimiser). If torchvision is absent, register an empty stand-in so the import works."""
    import importlib.util
    import types

    if importlib.util.find_spec("torchvision") is not None:
        return
    tv = types.ModuleType("torchvision")
    tf = types.ModuleType("torchvision.transforms")

    class _Unused:
        def __init__(self, *a, **k):
            pass

        def __call__(self, *a, **k):
            raise RuntimeError("torchvision stand-in: not available in this benchmark")

    tf.Compose = tf.ToTensor = tf.Normalize = tf.ColorJitter = _Unused
    tv.transforms = tf
    sys.modules["torchvision"] = tv
    sys.modules["torchvision.transforms"] = tf


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 25, 50, 100])
    ap.add_argument("--hw", type=int, nargs=2, default=[384, 512], metavar=("H", "W"))
    ap.add_argument("--window", type=int, default=2)
    ap.add_argument("--niter", type=int, default=100)
    ap.add_argument("--init", nargs="+", default=["averaging"], choices=INITS,
                    help="the alignment's start(s), each run on the same predictions (AlignConfig.init)")
    ap.add_argument("--pose-noise", dest="pose_noise", type=float, default=0.3,
                    help="per-pair pose noise of the predictions, degrees")
    ap.add_argument("--png", default="bench_align.png")
    ap.add_argument("--official", default=None, help="path to an official dust3r checkout (with croco)")
    ap.add_argument("--official-max", type=int, default=25, help="largest image count run with --official")
    ap.add_argument("--official-niter", type=int, default=300, help="iterations of the official optimiser "
                    "(its default is 300)")
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--as-official", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    h, w = args.hw
    if args.one is not None:
        res = run_one(args.one, h, w, args.window, args.official if args.as_official else None, args.niter,
                      args.init[0], args.pose_noise)
        print("RESULT " + json.dumps(res))
        return
    rows = []
    inits = list(dict.fromkeys(args.init))
    for n in args.sizes:
        for k, init in enumerate(inits):  # the official optimiser (its own MST start) runs once, beside the first
            modes = [False] + ([True] if args.official and n <= args.official_max and k == 0 else [])
            row = {}
            for as_off in modes:
                cmd = [sys.executable, __file__, "--one", str(n), "--hw", str(h), str(w), "--window", str(args.window),
                       "--niter", str(args.official_niter if as_off else args.niter), "--init", init,
                       "--pose-noise", str(args.pose_noise)] + (["--official", args.official, "--as-official"] if as_off else [])
                proc = subprocess.run(cmd, capture_output=True, text=True)
                line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if not line:
                    print(f"n={n} init={init} official={as_off} failed:\n{proc.stderr[-2000:]}", file=sys.stderr)
                    continue
                row.update(json.loads(line[0][7:]))
            if row:
                rows.append(row)
                print(json.dumps(row), file=sys.stderr)
    print(f"\nmaps {h}x{w}, cyclic sliding window {args.window}, niter {args.niter}, per-pair pose noise "
          f"{args.pose_noise} deg; errors: the worst camera after a similarity fit (start = before optimising)\n")
    print("| images | pairs | init | time (s) | optimise (s) | peak RSS (GB) | inputs RSS (GB) | start rot err (deg) | rot err (deg) | centre err |"
          + (" official time (s) | official RSS (GB) | official rot err |" if args.official else ""))
    print("|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.official else ""))
    for r in rows:
        line = (f"| {r['n']} | {r['pairs']} | {r.get('init', '-')} | {r.get('seconds', float('nan')):.1f} | {r.get('seconds_optimise', float('nan')):.1f} | "
                f"{r.get('peak_rss_gb', float('nan')):.2f} | {r.get('inputs_rss_gb', float('nan')):.2f} | "
                f"{r.get('start_rot_err_deg', float('nan')):.3f} | "
                f"{r.get('rot_err_deg', float('nan')):.3f} | {r.get('centre_err', float('nan')):.4f} |")
        if args.official:
            line += (f" {r.get('official_seconds', float('nan')):.1f} | {r.get('official_peak_rss_gb', float('nan')):.2f} |"
                     f" {r.get('official_rot_err_deg', float('nan')):.3f} |")
        print(line)
    if rows:
        plot([r for r in rows if r.get("init") == inits[0]], args.png, f"{h}x{w}, window {args.window}, {inits[0]} start")


def plot(rows, png, title):
    """Two panels (time, peak RSS vs images) drawn with OpenCV (matplotlib is not a dependency)."""
    import cv2
    import numpy as np

    W, H, m = 460, 340, 55
    img = np.full((H, 2 * W, 3), 255, np.uint8)
    series = [("pointmap", "seconds", "peak_rss_gb", (200, 80, 20)),
              ("official", "official_seconds", "official_peak_rss_gb", (20, 20, 200))]
    for panel, (ylabel, key_idx) in enumerate((("alignment time (s)", 1), ("peak RSS (GB)", 2))):
        x0 = panel * W
        pts_all = [(r["n"], r[s[key_idx]]) for s in series for r in rows if s[key_idx] in r]
        if not pts_all:
            continue
        xmax = max(p[0] for p in pts_all) * 1.05
        ymax = max(p[1] for p in pts_all) * 1.15
        def to_px(x, y):
            return int(x0 + m + (W - 1.5 * m) * x / xmax), int(H - m - (H - 1.6 * m) * y / ymax)
        cv2.line(img, to_px(0, 0), to_px(xmax, 0), (0, 0, 0), 1)
        cv2.line(img, to_px(0, 0), to_px(0, ymax), (0, 0, 0), 1)
        for k in range(5):
            y = ymax * k / 5
            cv2.putText(img, f"{y:.3g}", (x0 + 5, to_px(0, y)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        for r in rows:
            cv2.putText(img, str(r["n"]), (to_px(r["n"], 0)[0] - 8, H - m + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        cv2.putText(img, ylabel + " vs images", (x0 + m, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        for li, (name, *keys, colour) in enumerate(series):
            pts = [to_px(r["n"], r[keys[key_idx - 1]]) for r in rows if keys[key_idx - 1] in r]
            for a_, b_ in zip(pts, pts[1:]):
                cv2.line(img, a_, b_, colour, 2)
            for p in pts:
                cv2.circle(img, p, 4, colour, -1)
            if pts:
                cv2.putText(img, name, (x0 + m + 10, 40 + 16 * li), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    cv2.putText(img, title, (W - 80, H - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (80, 80, 80), 1)
    from pointmap.io_pair import write_png

    print(f"\nplot: {write_png(png, img[..., ::-1])}")  # atomic; raises if the file cannot be written


if __name__ == "__main__":
    main()
