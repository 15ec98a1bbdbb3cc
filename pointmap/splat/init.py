"""InstantSplat-style initialisation of Gaussians from a Reconstruction.

1. Confidence ranking: views sorted by mean confidence of their valid pixels, most confident first.
2. Co-visibility pruning: in ranked order, the points of all earlier views are projected into view i;
   a pixel of view i whose depth agrees with a projected point (relative difference < ``covis_tol``)
   is already explained and its point is dropped. The first view keeps every valid pixel.
3. Confidence threshold (``min_conf``) and user masks (``Reconstruction.valid``).
4. Downsampling to ``max_gaussians``: a voxel grid keeping the most confident point per voxel (the
   voxel size found by bisection), or confidence-weighted random sampling.
5. Gaussians: colour from the pixel, isotropic scale sqrt(mean squared distance to the 3 nearest
   neighbours), identity rotation, opacity ``opacity`` (0.1 as InstantSplat).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pointmap.errors import ShapeError, check_seed, is_int, is_number
from pointmap.geometry.cameras import invert_rigid, transform_points
from pointmap.reconstruction import Reconstruction
from pointmap.splat.gaussians import Gaussians


def covisibility_keep(recon: Reconstruction, valid: torch.Tensor, order, covis_tol: float = 0.01,
                      max_src_points: int = 400_000) -> torch.Tensor:
    """[N, h, w] bool: valid pixels not already explained by an earlier view in ``order``."""
    n, h, w = recon.depth_z.shape
    keep = valid.clone()
    pts = recon.pts_world.float()
    K = recon.K_map.float()
    w2c = invert_rigid(recon.cam2world.float())
    gen = torch.Generator().manual_seed(0)
    for k in range(1, len(order)):
        i = order[k]
        src = torch.cat([pts[j][valid[j]] for j in order[:k]])
        if src.shape[0] > max_src_points:  # a random subset is enough to mark covered pixels
            src = src[torch.randperm(src.shape[0], generator=gen)[:max_src_points]]
        pc = transform_points(w2c[i], src)
        z = pc[:, 2]
        front = z > 1e-6
        pc, z = pc[front], z[front]
        u = torch.round(K[i, 0, 0] * pc[:, 0] / z + K[i, 0, 2]).long()
        v = torch.round(K[i, 1, 1] * pc[:, 1] / z + K[i, 1, 2]).long()
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, z = u[inside], v[inside], z[inside]
        d = recon.depth_z[i].float()[v, u]
        hit = valid[i][v, u] & ((z - d).abs() < covis_tol * d)
        keep[i][v[hit], u[hit]] = False
    return keep


def _voxel_downsample(points: np.ndarray, score: np.ndarray, budget: int) -> np.ndarray:
    """Indices of at most ``budget`` points: the best-scoring point of each voxel, voxel size by bisection. The
    search starts from a voxel holding every point (in float64: float32 coordinates divided by their own extent
    put the far corner in a second voxel, and budget 1 gave 2 points)."""
    pos = points.astype(np.float64) - points.min(0).astype(np.float64)
    extent = float(pos.max()) * (1 + 1e-6) + 1e-9

    def pick(size):
        key = np.floor(pos / size).astype(np.int64)
        dims = key.max(0) + 1
        flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        order = np.lexsort((-score, flat))            # by voxel, best score first
        first = np.ones(len(order), dtype=bool)
        first[1:] = flat[order][1:] != flat[order][:-1]
        return order[first]

    lo, hi = extent * 1e-5, extent
    best = pick(hi)
    for _ in range(30):
        mid = np.sqrt(lo * hi)
        sel = pick(mid)
        if len(sel) > budget:
            lo = mid
        else:
            hi, best = mid, sel
        if hi / lo < 1.02:
            break
    return np.sort(best)


def knn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:
    """sqrt(mean squared distance to the ``k`` nearest neighbours) per point."""
    from scipy.spatial import cKDTree

    if len(points) <= 1:
        return np.full(len(points), 0.01, dtype=np.float32)
    kk = min(k, len(points) - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    d2 = (dist[:, 1:] ** 2).mean(1)
    d = np.sqrt(d2)
    floor = max(float(np.median(d)) * 0.05, 1e-7)
    return np.maximum(d, floor).astype(np.float32)


def check_has_points(recon: Reconstruction, min_conf: float = 0.0) -> None:
    """ShapeError, saying which filter emptied it, unless some pixel has depth, confidence above ``min_conf`` and is
    inside the reconstruction's masks: the Gaussians start from those points."""
    if recon.valid(min_conf).any():
        return
    if not recon.valid(min_conf, masked=False).any():
        raise ShapeError(f"no pixel of the reconstruction has depth > 0 and confidence > {min_conf}: nothing to start "
                         "Gaussians from")
    raise ShapeError("the reconstruction's masks (recon.masks) keep none of its pixels with depth: nothing to start "
                     "Gaussians from (a confidence filter at reconstruct, --min-conf / --conf-percentile, or user "
                     "masks removed every point; reconstruct again with a lower one)")


def init_from(recon: Reconstruction, max_gaussians: int | None = 20_000, *, min_conf: float = 0.0,
              covisibility: bool = True, covis_tol: float = 0.01, rank_by_conf: bool = True,
              downsample: str = "voxel", opacity: float = 0.1, seed: int = 0) -> Gaussians:
    """Initial Gaussians from a Reconstruction (see the module docstring).

    ``max_gaussians`` None keeps every surviving point (InstantSplat); the fitter's CPU budget uses a
    few tens of thousands. ``downsample``: "voxel" (even coverage) or "conf" (confidence-weighted
    random choice, InstantSplat's). Points keep their confidence in ``Gaussians.conf``.
    """
    if not isinstance(recon, Reconstruction):
        raise ShapeError(f"init_from expects a pointmap Reconstruction, got {type(recon).__name__}")
    if downsample not in ("voxel", "conf"):
        raise ShapeError(f"downsample must be 'voxel' or 'conf', got {downsample!r}")
    if max_gaussians is not None and not (is_int(max_gaussians) and max_gaussians >= 1):
        raise ShapeError(f"max_gaussians expected an int >= 1 or None, got {max_gaussians!r}")
    if not (is_number(opacity) and 0.0 < opacity < 1.0):
        raise ShapeError(f"opacity must be a number in (0, 1), got {opacity!r}")
    if not (is_number(min_conf) and math.isfinite(min_conf)):
        raise ShapeError(f"min_conf expected a finite confidence, got {min_conf!r}")
    if not (is_number(covis_tol) and 0 < covis_tol < math.inf):
        raise ShapeError(f"covis_tol expected a finite relative depth tolerance > 0, got {covis_tol!r}")
    for name, flag in (("covisibility", covisibility), ("rank_by_conf", rank_by_conf)):
        if not isinstance(flag, bool):  # "no" is truthy: it would prune or rank what the caller meant to leave alone
            raise ShapeError(f"{name} expected True or False, got {flag!r}")
    seed = check_seed(seed)
    check_has_points(recon, min_conf)
    valid = recon.valid(min_conf)
    n = len(recon)
    if rank_by_conf:
        mean_conf = torch.stack([recon.conf[i][valid[i]].float().mean() if valid[i].any() else
                                 torch.tensor(-1.0) for i in range(n)])
        order = torch.argsort(-mean_conf, stable=True).tolist()
    else:
        order = list(range(n))
    keep = covisibility_keep(recon, valid, order, covis_tol) if covisibility and n > 1 else valid
    pts = recon.pts_world.float()[keep].numpy()
    rgb = recon.images.float()[keep].clamp(0, 1).numpy()
    conf = recon.conf.float()[keep].numpy()
    finite = np.isfinite(pts).all(1)
    pts, rgb, conf = pts[finite], rgb[finite], conf[finite]
    if max_gaussians is not None and len(pts) > max_gaussians:
        if downsample == "voxel":
            rng = np.random.default_rng(seed)
            idx = _voxel_downsample(pts, conf + 1e-6 * rng.random(len(conf)), max_gaussians)
        else:
            g = torch.Generator().manual_seed(seed)
            wts = torch.as_tensor(conf, dtype=torch.float64).clamp_min(1e-12)
            idx = torch.multinomial(wts, max_gaussians, replacement=False, generator=g).sort().values.numpy()
        pts, rgb, conf = pts[idx], rgb[idx], conf[idx]
    scale = knn_scale(pts)
    g = Gaussians.from_points(torch.from_numpy(pts), torch.from_numpy(rgb), torch.from_numpy(scale),
                              opacity=opacity, conf=torch.from_numpy(conf))
    g.info = {"view_order": order, "points_after_covisibility": int(keep.sum()),
              "points_valid": int(valid.sum())}
    return g
