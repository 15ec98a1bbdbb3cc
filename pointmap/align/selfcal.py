"""Focals from the model's matches (self-calibration), for the epipolar stage's start.

Why: the network's own focal hardly follows the image (log focal against log true focal has slope 0.1-0.2 on the
held-out sets, docs/training-log.md sessions 55-56; v79a's model card: 0.10-0.16, median errors 21-28%). The matches carry the focal the pointmaps lack: for a pair's fundamental matrix F
(image i to image j, x_j^T F x_i = 0) the essential matrix E = K_j^T F K_i of the right intrinsics has two equal
singular values (Hartley and Zisserman, 9.6.1; Mendonca and Cipolla's self-calibration). Each pair's cost

    c_ij(f_i, f_j) = (s1 - s2) / (s1 + s2)   of E(f_i, f_j), its singular values s1 >= s2 (>= s3 = 0)

is zero at the true focals for exact matches. One pair's cost does not pin two focals (a whole curve of them
makes it zero), and motions whose optical axes meet, as an orbit's do, make it flat (Sturm's critical motions),
so the fit sums it over every pair, with one focal per camera (``AlignConfig.shared_focal``'s labels), plus a
prior that keeps each focal near the network's: ``prior`` x (pairs of the camera) x log(f / f_start)^2, searched
on a grid of ``span`` times either side of the start, one camera at a time for a few sweeps (coordinate descent:
a camera's cost is one-dimensional with the others held).

Measured and not adopted (session 80, docs/alignment.md, "Focals from the matches"): with v79a's coarse matches
(about 80 per pair at 224 px) the focal error falls little (18.1 -> 16.5% per image on the tuning set, 27.0 -> 21.3%
one camera per scene on `eval_cam_s464646`) and the poses do not gain (per image, aligned rotations within 15
degrees 252 -> 233 of 288, McNemar p 0.003; one camera level). So ``EpipolarConfig.self_calibrate`` is off by
default; ``benchmarks/bench_ga.py`` '+C' measures it again for a model whose matches are better.
"""

from __future__ import annotations

import math

import numpy as np

from pointmap.errors import ShapeError, is_number

MIN_INLIERS = 15  # a pair's F with fewer RANSAC inliers says nothing


def fundamental_matrices(matches: dict, threshold_px: float, min_inliers: int = MIN_INLIERS) -> dict:
    """{(i, j): F [3, 3]} (x_j^T F x_i = 0, pixels) from each pair's matches ``{(i, j): (xy_i [M, 2], xy_j [M,
    2])}`` by OpenCV's MAGSAC++ at ``threshold_px``; pairs with fewer than ``min_inliers`` inliers are left out."""
    import cv2

    out = {}
    for key, (xy1, xy2) in matches.items():
        xy1, xy2 = np.asarray(xy1, np.float64), np.asarray(xy2, np.float64)
        if len(xy1) < max(min_inliers, 8):
            continue
        F, mask = cv2.findFundamentalMat(xy1, xy2, cv2.USAC_MAGSAC, threshold_px, 0.999, 10000)
        if F is not None and F.shape == (3, 3) and np.isfinite(F).all() and int(mask.sum()) >= min_inliers:
            out[key] = F
    return out


def _intrinsics(f: np.ndarray, c: np.ndarray) -> np.ndarray:
    """[len(f), 3, 3] intrinsics of focals ``f`` and principal point(s) ``c`` ([2] or [len(f), 2])."""
    K = np.zeros((len(f), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = f
    K[:, :2, 2] = c
    K[:, 2, 2] = 1.0
    return K


def essential_cost(F: np.ndarray, fi: np.ndarray, fj: np.ndarray, ci, cj) -> np.ndarray:
    """[len(fi), len(fj)] (s1 - s2) / (s1 + s2) of E = K_j^T F K_i for every focal fi of image i and fj of image j
    (principal points ``ci``, ``cj``): 0 when E is an essential matrix."""
    Ki = _intrinsics(np.asarray(fi, np.float64), np.asarray(ci, np.float64))
    Kj = _intrinsics(np.asarray(fj, np.float64), np.asarray(cj, np.float64))
    return _gap(np.einsum("bxi,xy,ayl->abil", Kj, F, Ki))  # E [fi, fj, 3, 3] = Kj^T F Ki


def _gap(E: np.ndarray) -> np.ndarray:
    """[...] (s1 - s2) / (s1 + s2) of each [..., 3, 3] matrix, s1 >= s2 its two largest singular values."""
    s = np.linalg.svd(E, compute_uv=False)
    return (s[..., 0] - s[..., 1]) / np.maximum(s[..., 0] + s[..., 1], 1e-300)


def calibrate_focals(Fs: dict, f_start, centres, camera=None, fixed=(), *, prior: float = 0.1, span: float = 2.0,
                     steps: int = 121, sweeps: int = 6) -> np.ndarray:
    """[N] focals (pixels) from the pairs' fundamental matrices ``Fs`` ({(i, j): F}, ``fundamental_matrices``),
    started at ``f_start`` [N] (the network's; one value per camera), principal points ``centres`` [N, 2]; images of
    one ``camera`` label [N] share a focal (default one per image); cameras with an image in ``fixed`` (known K)
    keep their start, as do cameras that no pair in ``Fs`` touches. Module docstring for the cost."""
    f0 = np.asarray(f_start, np.float64)
    n = len(f0)
    cams = np.arange(n) if camera is None else np.asarray(camera)
    cen = np.asarray(centres, np.float64)
    if cams.shape != (n,) or cen.shape != (n, 2) or not (np.isfinite(f0).all() and (f0 > 0).all()) \
            or not (is_number(prior) and prior >= 0 and is_number(span) and span > 1) or steps < 3 or sweeps < 1:
        raise ShapeError(f"calibrate_focals expected f_start [N] positive, centres [N, 2], camera [N], prior >= 0, "
                         f"span > 1; got {f0.shape}, {cen.shape}, {cams.shape}, prior {prior}, span {span}")
    for c in np.unique(cams):
        if np.ptp(f0[cams == c]) > 1e-9 * f0[cams == c].max():
            raise ShapeError(f"calibrate_focals expected one start focal per camera, got {f0[cams == c]} for camera {c}")
    held = {int(cams[k]) for k in fixed}
    f = f0.copy()
    ratios = np.exp(np.linspace(-math.log(span), math.log(span), steps))
    free = [c for c in np.unique(cams) if int(c) not in held]
    for _ in range(sweeps):
        for c in free:
            one = cams == c
            grid = f0[one][0] * ratios
            total, used = np.zeros(steps), 0
            for (i, j), F in Fs.items():
                if one[i] and one[j]:  # both images of this camera: one focal on both sides
                    total += np.diagonal(essential_cost(F, grid, grid, cen[i], cen[j]))
                elif one[i]:
                    total += essential_cost(F, grid, f[j:j + 1], cen[i], cen[j])[:, 0]
                elif one[j]:
                    total += essential_cost(F, f[i:i + 1], grid, cen[i], cen[j])[0]
                else:
                    continue
                used += 1
            if used:
                f[one] = grid[int(np.argmin(total + prior * used * np.log(ratios) ** 2))]
    return _polish(Fs, f, f0, cen, cams, free, prior, span)


def _polish(Fs, f, f0, cen, cams, free, prior, span) -> np.ndarray:
    """The grid's focals refined jointly (Powell on log focals, within ``span`` of the start): a grid point can
    sit beside a valley that runs diagonally across the cameras (all focals a little short), which moving one
    camera at a time cannot follow. The cost is the grid's: every pair's ``_gap`` at once, plus each camera's prior
    weighted by its pairs."""
    from scipy.optimize import minimize

    I, J = (np.array([key[side] for key in Fs]) for side in (0, 1))
    F = np.stack(list(Fs.values()))
    ones = [cams == c for c in free]
    used = np.array([np.sum(one[I] | one[J]) for one in ones])
    touched = [k for k, n in enumerate(used) if n]  # cameras no pair touches keep their start
    if not touched:
        return f
    ones, used = [ones[k] for k in touched], used[touched]
    log_f0 = np.array([math.log(f0[one][0]) for one in ones])

    def at(x):
        g = f.copy()
        for one, v in zip(ones, x):
            g[one] = math.exp(v)
        return g

    def cost(x):
        g = at(x)
        E = np.swapaxes(_intrinsics(g[J], cen[J]), 1, 2) @ F @ _intrinsics(g[I], cen[I])
        return float(_gap(E).sum() + prior * np.sum(used * (x - log_f0) ** 2))

    start = np.array([math.log(f[one][0]) for one in ones])
    res = minimize(cost, start, method="Powell", bounds=list(zip(log_f0 - math.log(span), log_f0 + math.log(span))),
                   options={"xtol": 1e-6, "ftol": 1e-12})
    return at(res.x) if res.fun <= cost(start) and np.isfinite(res.x).all() else f
