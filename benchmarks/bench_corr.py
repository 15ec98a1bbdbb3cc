"""Training correspondences after augmentation: the geometric field (``data.datasets._geometric_corr``, since
session 72) against the stored field resampled with each crop (what every model up to v72x trained on).

Each row serves the same augmented pairs (same seeds, colour jitter off so that both views keep the rendered
colours) and measures, over the correspondences the field keeps:
- how far each lies from the geometry: the projection into view 2 of view 1's pointmap target at its pixel (the
  point the regression loss supervises), in pixels (median, 99th percentile, max);
- the share whose rounded landing pixel differs from the geometry's (the pixel matching loss's targets);
- independently of the depth, the colour agreement at the matches: mean |view 1 - view 2 (bilinear) at the match|
  over view 1's textured pixels (the 30% of largest Sobel gradient), lower is better.

    python benchmarks/bench_corr.py --data TRAIN_SHARDS [--pairs 40] [--size 224] [--seed 0]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import data.datasets as dsm  # noqa: E402


def resampled_corr(corr, d1, K1, T1, d2, K2, T2):
    """``_geometric_corr``'s stand-in for the field as it was before session 72: the stored correspondences
    resampled with the crop, kept where they land inside view 2 on a pixel with depth from a pixel with depth."""
    h2, w2 = d2.shape
    u, v = corr[..., 0], corr[..., 1]
    with np.errstate(invalid="ignore"):
        keep = (u > -0.5) & (u < w2 - 0.5) & (v > -0.5) & (v < h2 - 0.5) & (d1 > 0)
    ui, vi = dsm._landing_pixel(corr, w2, h2)
    out = corr.copy()
    out[~(keep & (d2[vi, ui] > 0))] = np.nan
    return out


@contextlib.contextmanager
def resampled_field():
    """PairDataset serving the field as it was before session 72 (``resampled_corr``)."""
    keep = dsm._geometric_corr
    dsm._geometric_corr = resampled_corr
    try:
        yield
    finally:
        dsm._geometric_corr = keep


def pair_figures(v1: dict, v2: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(distance to the geometry [M], landing pixel differs [M] bool, colour error [T]) of one served pair."""
    corr = v1["corr"].numpy().astype(np.float64)
    ok = np.isfinite(corr).all(-1)
    T = np.linalg.inv(v2["cam2world"].double().numpy()) @ v1["cam2world"].double().numpy()
    p = v1["pts_cam1"].double().numpy()[ok] @ T[:3, :3].T + T[:3, 3]
    K = v2["K"].double().numpy()
    geo = np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], -1)
    dist = np.linalg.norm(geo - corr[ok], axis=-1)
    moved = (np.rint(geo) != np.rint(corr[ok])).any(-1)
    i1, i2 = v1["img"].permute(1, 2, 0).numpy(), v2["img"].permute(1, 2, 0).numpy()
    grey = np.ascontiguousarray(i1.mean(-1))
    grad = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0)) + np.abs(cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    textured = ok & (grad > np.quantile(grad, 0.7))
    c = np.nan_to_num(corr).astype(np.float32)
    seen = cv2.remap(i2, np.ascontiguousarray(c[..., 0]), np.ascontiguousarray(c[..., 1]), cv2.INTER_LINEAR)
    return dist, moved, np.abs(seen[textured] - i1[textured]).reshape(-1)


def measure(root, pairs: int, size: int, seed: int) -> dict:
    """{field name: figures} over the same ``pairs`` augmented pairs (seeded) for both fields."""
    out = {}
    for name, ctx in (("resampled stored field (up to v72x)", resampled_field), ("geometric (session 72)",
                                                                                   contextlib.nullcontext)):
        with ctx(), _no_colour_jitter():
            ds = dsm.PairDataset(root, size=size, augment=True, split="all")
            dists, moved, colour = [], [], []
            for k in range(pairs):
                torch.manual_seed(seed * 100_003 + k)
                v1, v2 = ds[((k * 37) % len(ds), k % len(ds.aspects))]
                d, m, c = pair_figures(v1, v2)
                dists.append(d)
                moved.append(m)
                colour.append(c)
        d, m, c = np.concatenate(dists), np.concatenate(moved), np.concatenate(colour)
        out[name] = {"matches": len(d), "median": float(np.median(d)) if len(d) else float("nan"),
                     "p99": float(np.quantile(d, 0.99)) if len(d) else float("nan"),
                     "max": float(d.max()) if len(d) else float("nan"), "moved": float(m.mean()) if len(m) else 0.0,
                     "colour": float(c.mean()) if len(c) else float("nan")}
    return out


@contextlib.contextmanager
def _no_colour_jitter():
    keep = dsm._photometric
    dsm._photometric = lambda rng, rgb: rgb.astype(np.float32) / 255.0
    try:
        yield
    finally:
        dsm._photometric = keep


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="a pair set rendered with --kind pairs")
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--size", type=int, default=224)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.pairs < 1:
        p.error(f"--pairs expected >= 1, got {a.pairs}")
    try:
        res = measure(a.data, a.pairs, a.size, a.seed)
    except (dsm.ShardError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"| field ({a.pairs} augmented pairs at {a.size}) | matches | px off the geometry: median / p99 / max | "
          "landing pixel differs | colour error at the matches |")
    print("|---|---|---|---|---|")
    for name, r in res.items():
        print(f"| {name} | {r['matches']} | {r['median']:.3f} / {r['p99']:.3f} / {r['max']:.3f} | "
              f"{100 * r['moved']:.1f}% | {r['colour']:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
