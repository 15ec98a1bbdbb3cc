"""Multi-view pose refinement on the model's matches (epipolar): the aligned scene's rotations and camera centres
refined jointly on the coarse matches of every pair, then the dense depths re-fitted with those poses held.

Why: dense alignment takes the camera centres from the pointmaps' geometry, whose depth and focal errors bend the
baselines; the matches' epipolar geometry gives better directions (``pm.pair_pose`` on one pair). Translation
averaging of pair_pose directions on the aligned rotations was measured too and is worse than this joint fit
(docs/alignment.md, "Pose refinement on the model's matches").

The fit: for each match (ray r_i in image i, ray r_j in image j) the residual is the signed sine of the angle
between r_i and the epipolar plane spanned by the direction of camera j's centre and the rotated ray
R_i^T R_j r_j, both in camera i's frame (``pointmap.pose._epipolar_residuals``, here vectorised over all pairs).
Robust least squares (Cauchy, scale ``threshold_px`` over the focal) over the matches within 3 scales of the
current poses (the gate is re-drawn after each solve), plus a Cauchy prior of width ``rotation_prior_deg`` per
rotation-vector component keeping each rotation near the aligned one. Rotations move as R_k = exp(w_k) R_k0 in
the world frame; the Jacobian is analytic (``_residual_jacobian``). Gauge: known poses are held (else image 0's);
without two known centres the mean distance of the free cameras from the first held one keeps its aligned value.
Intrinsics: known ones as given; otherwise each image's focal is the median of the Weiszfeld focals of its
own-frame pointmaps (one per pass in which it is the first view), with the principal point as aligned;
``shared_focal``: the median over each camera's images.

Cheirality (sessions 33-34): the residuals cannot tell a direction from its opposite, so a camera could slide
through its neighbour at no cost to that pair. Each gated match also has two residuals that are zero while its pair's
matches meet in front of both cameras on average and grow with how far behind they meet: the pair's mean
``cheirality_margins`` over the scale (session 33 charged each match's own margins; the random matches that met behind
a camera then pulled the fit, and a camera turned until a pair's rays were parallel escaped the charge). Only pairs
whose points met mostly in front at the start are charged. The charge is a wall, and a camera whose way to the
matches' optimum crosses it stops there (session 33's 100-view ring: a camera left 27 degrees off); a second descent,
uncharged then charged, crosses it, and is kept where its charged cost is lower and it reverses no pair. The mirror
check stays as the safety net.

Mirror check: after the fit each camera pair's gated
matches are triangulated under the start and the fitted poses (``in_front_share``); a pair whose points moved from in
front of its cameras to behind them was reversed (``mirrored_pairs``), and so is, for this check, a pair whose centres
the fit brought together (``collapsed_pairs``: under a fifth of their aligned distance, where the pair's residuals
vanish; listed in the report's ``collapsed_pairs`` too). The fit is then run once more with the
cameras touching those pairs held at their aligned poses (``pinned_cameras``; the gauge as in the first fit), and
the aligned poses are kept when that reverses a pair too, or when every camera would be held.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass, replace
from functools import partial

import numpy as np
import torch

from pointmap.align.selfcal import calibrate_focals, fundamental_matrices
from pointmap.errors import ShapeError, is_int, is_number
from pointmap.pose import _bearings
from pointmap.reconstruction import K_to_original, Reconstruction

# lsmr's default tolerances stop its steps early: hundreds of slow iterations, ending 1 degree off
LSMR_TIGHT = {"atol": 1e-12, "btol": 1e-12, "regularize": False}
SELFCAL_THRESHOLD = 1 / 224  # the fundamental matrices' RANSAC threshold over the map's longer side (1 px at 224)
MIN_PARALLAX_DEG = 0.5  # in_front_share: rays closer to parallel than this do not count


@dataclass(frozen=True)
class EpipolarConfig:
    """rotation_prior_deg: Cauchy width of the prior keeping each rotation near the aligned one;
    threshold_px: Cauchy scale of the epipolar residual in map pixels (None: max(h, w) / 56, 4 px at 224);
    rounds: least-squares solves with a re-drawn inlier gate; max_evals: function evaluations per solve;
    patch: cell size of the coarse matches (the model's patch size); refit_depth: re-run dense alignment with
    the refined poses and intrinsics held, so the depths agree with them (else the depths stay as aligned);
    cheirality: the fit also pays for matched points moved behind a camera (``solve_poses``; False: the epipolar
    residuals alone, the stage before session 33); second_descent: with cheirality, a second descent (uncharged,
    then charged) that can cross where the charge stops the first (``solve_poses``; False: one descent, session
    33's stage); self_calibrate: unknown focals start from the matches' (``pointmap.align.selfcal``: each pair's
    fundamental matrix, one focal per camera, held near the network's) instead of the network's own."""

    rotation_prior_deg: float = 3.0
    threshold_px: float | None = None
    rounds: int = 3
    max_evals: int = 200
    patch: int = 16
    refit_depth: bool = True
    cheirality: bool = True
    second_descent: bool = True
    self_calibrate: bool = False

    def __post_init__(self):
        ints = (self.rounds, self.max_evals, self.patch)
        # numbers, not strings (a raw TypeError from the comparison) nor bools; switches True or False, not strings
        # ("no" is truthy and would have run the stage it names)
        if not all(is_int(v) for v in ints) or min(ints) < 1 \
                or not (is_number(self.rotation_prior_deg) and self.rotation_prior_deg > 0) \
                or (self.threshold_px is not None and not (is_number(self.threshold_px)
                                                          and 0 < self.threshold_px < math.inf)):
            raise ShapeError(f"EpipolarConfig expected rotation_prior_deg > 0, threshold_px > 0 (finite) or None, rounds, "
                             f"max_evals and patch ints >= 1; got {self}")
        for name in ("refit_depth", "cheirality", "second_descent", "self_calibrate"):
            if not isinstance(getattr(self, name), bool):
                raise ShapeError(f"EpipolarConfig.{name} expected True or False, got {getattr(self, name)!r}")


def epipolar_residuals(R: np.ndarray, C: np.ndarray, I: np.ndarray, J: np.ndarray, r1: np.ndarray,
                       r2: np.ndarray) -> np.ndarray:
    """[M] signed sine between each ray r1 [M, 3] (camera I[m]'s frame) and the epipolar plane of camera J[m]'s
    centre and ray r2 [M, 3] (camera J[m]'s frame), for cam2world rotations R [N, 3, 3] and centres C [N, 3]."""
    pairs, pid = np.unique(np.stack([I, J], 1), axis=0, return_inverse=True)
    return _residuals_by_pair(R, C, pairs[:, 0], pairs[:, 1], pid.reshape(-1), r1, r2)


def _residuals_by_pair(R, C, PI, PJ, pid, r1, r2):
    """``epipolar_residuals`` with the relative poses computed once per camera pair (PI[p], PJ[p]); ``pid`` [M]: each
    match's pair. The fit evaluates this thousands of times: per match only a rotation, a cross and a dot remain."""
    RiT = R[PI].transpose(0, 2, 1)
    Rij = RiT @ R[PJ]                                        # R_i^T R_j per pair
    t = (RiT @ (C[PJ] - C[PI])[..., None])[..., 0]           # camera j's centre in camera i's frame
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    v = np.einsum("mab,mb->ma", Rij[pid], r2)
    n = np.cross(t[pid], v)
    return (n * r1).sum(1) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)


def in_front_share(R: np.ndarray, C: np.ndarray, I: np.ndarray, J: np.ndarray, r1: np.ndarray, r2: np.ndarray,
                   n_pairs: int, pid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per camera pair (``pid`` [M] in [0, n_pairs)): the share of its matches whose two rays meet (closest points)
    in front of both cameras, and how many matches counted: those whose rays are at least ``MIN_PARALLAX_DEG`` apart
    (closer to parallel, the meeting point's side is noise). The epipolar residuals cannot tell a direction from its
    opposite; this can: mirrored, the points land behind both cameras."""
    pid = np.asarray(pid)
    if len(pid) != len(I) or (len(pid) and not 0 <= pid.min() <= pid.max() < n_pairs):
        raise ShapeError(f"in_front_share expected one pair index in [0, {n_pairs}) per match ({len(I)}), got "
                         f"{len(pid)} in [{pid.min() if len(pid) else '-'}, {pid.max() if len(pid) else '-'}]")
    return _shares(*_counted_and_in_front(R, C, I, J, r1, r2), pid, n_pairs)


def _shares(ok, front, pid, n_pairs):
    """Per pair: the share of its counted matches (``ok`` [M]) that are ``front`` [M], and how many were counted."""
    n_ok = np.bincount(pid[ok], minlength=n_pairs)
    return np.bincount(pid[front], minlength=n_pairs) / np.maximum(n_ok, 1), n_ok


def _counted_and_in_front(R, C, I, J, r1, r2):
    """[M] bools: the match's rays are at least ``MIN_PARALLAX_DEG`` apart; and they also meet in front of both."""
    a, b = _world_rays(R, I, J, r1, r2)
    ok = 1.0 - (a * b).sum(1) ** 2 > math.sin(math.radians(MIN_PARALLAX_DEG)) ** 2  # sin^2 between the rays
    return ok, ok & (_margins(a, b, C[J] - C[I]) > 0).all(1)  # both meeting depths positive


def mirrored_pairs(R0, C0, R, C, I, J, r1, r2, *, min_matches: int = 10, was: float = 0.7,
                   now: float = 0.3, parallel_is_behind: bool = False) -> list:
    """Camera pairs [i, j] whose matches met in front of both cameras at the start (share > ``was``) and no longer do
    after a fit (share < ``now``): a reversed direction, which the epipolar residuals cannot see. The margins keep
    short baselines, whose meeting points are ill-conditioned, from being called mirrored by chance; a pair needs
    ``min_matches`` counted matches before and after. ``parallel_is_behind``: the share after is over the matches
    counted before, and one whose rays the fit made parallel counts as behind (a fit paying for points behind a
    camera can escape by turning it until its pair's rays are parallel: nothing is counted after, nothing flagged)."""
    if not (0 <= now < was <= 1) or min_matches < 1:
        raise ValueError(f"mirrored_pairs expected 0 <= now < was <= 1 and min_matches >= 1, got now={now}, "
                         f"was={was}, min_matches={min_matches}")
    if len(I) == 0:
        return []
    pairs, pid = np.unique(np.stack([I, J], 1), axis=0, return_inverse=True)
    pid = pid.reshape(-1)
    ok0, front0 = _counted_and_in_front(R0, C0, I, J, r1, r2)
    ok, front = _counted_and_in_front(R, C, I, J, r1, r2)
    if parallel_is_behind:  # over the matches counted before; one no longer counted is not in front
        ok, front = ok0, front & ok0
    before, counted_before = _shares(ok0, front0, pid, len(pairs))
    after, counted = _shares(ok, front, pid, len(pairs))
    flag = (counted_before >= min_matches) & (counted >= min_matches) & (before > was) & (after < now)
    return [[int(i), int(j)] for i, j in pairs[flag]]


def collapsed_pairs(C0, C, I, J, ratio: float = 0.2) -> list:
    """Camera pairs [i, j] (among the matched pairs I, J) whose centres the fit brought closer than ``ratio`` of
    their aligned distance: the epipolar residuals of a pair vanish when its two centres meet (no baseline, no
    epipolar plane), so a fit can settle two cameras onto one point at no cost (found on three chessboard photos,
    session 73)."""
    if len(I) == 0:
        return []
    pairs = np.unique(np.stack([I, J], 1), axis=0)
    C0, C = np.asarray(C0, dtype=np.float64), np.asarray(C, dtype=np.float64)
    b0 = np.linalg.norm(C0[pairs[:, 0]] - C0[pairs[:, 1]], axis=1)
    b = np.linalg.norm(C[pairs[:, 0]] - C[pairs[:, 1]], axis=1)
    flag = (b0 > 0) & ~(b >= ratio * b0)  # NaN counts as collapsed
    return [[int(i), int(j)] for i, j in pairs[flag]]


def pinned_cameras(pairs: list, held=()) -> list:
    """Few cameras, none of ``held``, that touch every pair in ``pairs`` (greedy: the camera in most of the pairs
    left, until none is left): where a fit reversed several pairs of one camera, that camera is the one that passed
    through the others; a pair with a held camera has its other camera pinned."""
    held = set(held)
    left, out = [tuple(k for k in p if k not in held) for p in pairs], []
    left = [p for p in left if p]
    while left:
        counts: dict = {}
        for p in left:
            for k in p:
                counts[k] = counts.get(k, 0) + 1
        k = max(sorted(counts), key=counts.get)
        out.append(int(k))
        left = [p for p in left if k not in p]
    return sorted(out)


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


def _skew(v: np.ndarray) -> np.ndarray:
    """[..., 3, 3] cross-product matrices of v [..., 3]."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """[N, 3, 3] left Jacobians of SO(3) at rotation vectors w [N, 3]: exp(w + d) = exp(J_l(w) d) exp(w) to first
    order, so a derivative by a left perturbation of exp(w) R0, times J_l(w), is the derivative by w."""
    th = np.linalg.norm(w, axis=1)[:, None, None]
    W = _skew(w)
    small = th < 1e-4
    t = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(t)) / t ** 2)
    b = np.where(small, 1 / 6 - th ** 2 / 120, (t - np.sin(t)) / t ** 3)
    return np.eye(3) + a * W + b * (W @ W)


def _residual_jacobian(R, C, I, J, r1, r2):
    """Derivatives of ``_residuals_by_pair``'s residuals [M] by a left rotation perturbation of each match's two
    cameras (R_k -> exp(phi_k) R_k) and by their centres: (d_phi_i, d_phi_j, d_C_i, d_C_j), each [M, 3].

    In the world frame the residual is e = (d x b) . a / |d x b| with a = R_i r1, b = R_j r2, d = C_j - C_i (camera
    j's centre direction; the length cancels). With N = d x b, q = |N|, s = N . a and g = de/dN = a / q - s N / q^3:
    de/dphi_i = a x N / q, de/dphi_j = b x (g x d), de/dC_j = b x g = -de/dC_i."""
    a = np.einsum("mab,mb->ma", R[I], r1)
    b = np.einsum("mab,mb->ma", R[J], r2)
    d = C[J] - C[I]
    N = np.cross(d, b)
    q = np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    s = (N * a).sum(1, keepdims=True)
    g = a / q - s * N / q ** 3
    dC = np.cross(b, g)
    return np.cross(a, N) / q, np.cross(b, np.cross(g, d)), -dC, dC


def cheirality_margins(R: np.ndarray, C: np.ndarray, I: np.ndarray, J: np.ndarray, r1: np.ndarray,
                       r2: np.ndarray) -> np.ndarray:
    """[M, 2] per match, the signs of the depths at which its two rays (r1 in camera I[m]'s frame, r2 in camera
    J[m]'s) pass closest, along ray 1 and along ray 2, as bounded margins: with a = R_i r1, b = R_j r2 (unit) and d
    the unit direction from camera i's centre to camera j's, d . (a - (a.b) b) and -d . (b - (a.b) a). Each is the
    numerator of that depth (``in_front_share``'s lambda, mu) over the baseline, so it has the depth's sign; it is at
    most the sine of the angle between the rays, so near-parallel rays, whose meeting side is noise, weigh little."""
    return _margins(*_world_rays(R, I, J, r1, r2), C[J] - C[I])


def _world_rays(R, I, J, r1, r2):
    """Each match's two rays in the world, unit [M, 3]: a = R_i r1, b = R_j r2."""
    a = np.einsum("mab,mb->ma", R[I], r1)
    b = np.einsum("mab,mb->ma", R[J], r2)
    return (a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12),
            b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12))


def _margins(a, b, D):
    """``cheirality_margins`` [M, 2] of unit world rays a, b [M, 3] and baselines D = C_j - C_i [M, 3]: the
    numerators of the meeting depths lambda = (a.D - (a.b)(b.D)) / (1 - (a.b)^2) along a and mu along b, over |D|."""
    d = D / np.maximum(np.linalg.norm(D, axis=1, keepdims=True), 1e-12)
    ab = (a * b).sum(1, keepdims=True)
    return np.stack([(d * (a - ab * b)).sum(1), -(d * (b - ab * a)).sum(1)], 1)


def _cheirality_jacobian(R, C, I, J, r1, r2):
    """Derivatives of ``cheirality_margins`` [M, 2] by a left rotation perturbation of each match's two cameras and
    by their centres: (d_phi_i, d_phi_j, d_C_i, d_C_j), each [M, 2, 3] (rays r1, r2 unit). With u = a.b and the
    gradients g_a, g_b, g_d of a margin by a, b and the unit baseline direction d: de/dphi_i = a x g_a,
    de/dphi_j = b x g_b, de/dC_j = (I - d d^T) g_d / |d| = -de/dC_i."""
    a, b = _world_rays(R, I, J, r1, r2)
    D = C[J] - C[I]
    L = np.maximum(np.linalg.norm(D, axis=1, keepdims=True), 1e-12)
    d = D / L
    u = (a * b).sum(1, keepdims=True)
    ad, bd = (a * d).sum(1, keepdims=True), (b * d).sum(1, keepdims=True)
    # margin 1: d.a - u (b.d); margin 2: u (a.d) - b.d
    g_a = np.stack([d - bd * b, ad * b + u * d], 1)
    g_b = np.stack([-u * d - bd * a, ad * a - d], 1)
    g_d = np.stack([a - u * b, u * a - b], 1)
    d_phi_i = np.cross(a[:, None], g_a)
    d_phi_j = np.cross(b[:, None], g_b)
    d_Cj = (g_d - (g_d * d[:, None]).sum(2, keepdims=True) * d[:, None]) / L[:, None]
    return d_phi_i, d_phi_j, -d_Cj, d_Cj


def _pair_means(v, ps, n_pairs):
    """Per pair (``ps`` [M]: each row's pair): how many rows of v [M, ...] it has [P], and their mean [P, ...] (0
    where none)."""
    cnt = np.bincount(ps, minlength=n_pairs).astype(float)
    out = np.zeros((n_pairs,) + v.shape[1:])
    np.add.at(out, ps, v)
    return cnt, out / np.maximum(cnt, 1).reshape((-1,) + (1,) * (v.ndim - 1))


def solve_poses(R0: np.ndarray, C0: np.ndarray, I: np.ndarray, J: np.ndarray, r1: np.ndarray, r2: np.ndarray,
                scale: np.ndarray, *, held, keep_scale: bool, prior_deg: float = 3.0, rounds: int = 3,
                max_evals: int = 200, sparse: bool | None = None, jac: str = "analytic", anchor: int | None = None,
                cheirality: bool = True, second_descent: bool = True):
    """Rotations [N, 3, 3] and centres [N, 3] refined on matches (the module's fit). ``scale`` [M]: each match's
    Cauchy scale (threshold over the focal of its camera I); ``held``: indices kept as given (at least one);
    ``keep_scale``: the mean distance of the free cameras from ``anchor`` (a held camera; default the first held one)
    stays as given, by a residual (restoring it after each solve instead was 5 times faster with finite differences on
    100 views, but it let the demo room's cameras pass through each other, their directions mirrored, 159 degrees off);
    ``jac``: "analytic" (``_residual_jacobian``, one evaluation per Jacobian) or "2-point" (scipy's finite
    differences, by column groups of cameras that share no pair when sparse: the scale row, which joins every centre,
    makes them cost one evaluation per centre coordinate; kept as the reference ``benchmarks/bench_epipolar.py``
    compares against); ``sparse``: a sparse Jacobian solved by ``lsmr`` (many cameras) or a dense one (few); None:
    sparse beyond 8 free cameras; ``cheirality``: two more residuals per gated match, its pair's mean
    ``cheirality_margins`` over the scale where negative (zero where positive), so the fit pays for a pair's points
    moved behind a camera, which the epipolar residuals cannot see (their square is the same for a direction and its
    opposite); the mean leaves the few random matches that meet behind uncharged, where each match's own margin made
    them pull (worst rotation 1.2-1.6 against 0.1-0.3 degrees on 8-view rings started 15 degrees off with 10% random
    matches, docs/alignment.md). Only pairs whose points met mostly in front of both cameras at the start
    (``in_front_share`` > 0.5) are charged: from a start with a camera already passed through another, charging its
    pairs too turned cameras by 56-180 degrees in 5 of 8 such starts on the analytic scene. ``second_descent`` (with
    cheirality): the charge is a wall that can stop a camera short of the matches' optimum, so a second descent runs
    uncharged, then charged from where it ended; it is kept when its charged cost over every match is lower and it
    reverses no camera pair (``mirrored_pairs`` with ``parallel_is_behind``, over the matches gated at the start or at
    its end: the robust loss caps what passing through a neighbour costs, and turning a camera until a pair's rays
    are parallel hides it); the report's ``descent`` says which was kept ("aligned" or "uncharged first").
    The report's ``mirrored_pairs`` (``mirrored_pairs`` on the final gate's matches)
    lists camera pairs whose direction the fit reversed. The fit limits BLAS to one thread while it runs
    (``threadpoolctl``, process-wide: other threads of the caller get one BLAS thread meanwhile).
    Returns (R, C, report)."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix
    from threadpoolctl import threadpool_limits

    if jac not in ("analytic", "2-point"):
        raise ValueError(f"jac expected 'analytic' or '2-point', got {jac!r}")
    n = len(R0)
    held = sorted(set(int(k) for k in held))
    if not held:
        raise ShapeError("solve_poses expected at least one held camera (the gauge)")
    if anchor is None:
        anchor = held[0]
    elif anchor not in held:
        raise ShapeError(f"solve_poses expected the anchor ({anchor}) among the held cameras {held}")
    free = [k for k in range(n) if k not in held]
    slot = {k: s for s, k in enumerate(free)}
    nf = len(free)
    d0 = float(np.linalg.norm(C0[free] - C0[anchor], axis=1).mean()) if nf else 1.0
    unit = d0 if d0 > 0 else 1.0
    prior = math.radians(prior_deg)
    pairs, pid = np.unique(np.stack([I, J], 1), axis=0, return_inverse=True)
    PI, PJ, pid = pairs[:, 0], pairs[:, 1], pid.reshape(-1)

    def unpack(x):  # x: rotation vectors and centre offsets (over unit) of the free cameras, both from the start
        R, C = R0.copy(), C0 / unit
        if nf:
            w = x[:3 * nf].reshape(nf, 3)
            R[free] = _rotvec_to_matrix(w) @ R0[free]
            C[free] += x[3 * nf:].reshape(nf, 3)
        return R, C

    def all_residuals(x):
        R, C = unpack(x)
        return _residuals_by_pair(R, C, PI, PJ, pid, r1, r2) / scale

    slots = np.array([slot.get(k, -1) for k in range(n)])

    def sparse_opts(x, sel, charged):  # scipy's differences by column groups, on the analytic Jacobian's pattern
        return {"jac_sparsity": jacobian(x, sel, pattern=True, charged=charged), "tr_solver": "lsmr",
                "tr_options": LSMR_TIGHT}

    def jacobian(x, sel, dense=False, pattern=False, charged=True):
        """The rows of ``fun`` by the parameters (w, C) of the free cameras, analytic (``_residual_jacobian``); with
        ``pattern``, which entries can be nonzero (ones): a match (and its two cheirality rows, which are zero while
        its pair's mean margin is positive) on its two cameras' rotation and centre (held cameras have none), a prior
        row on its camera's rotation, the scale row on every centre."""
        R, C = unpack(x)
        Is, Js, m = I[sel], J[sel], int(sel.sum())
        Jl = _left_jacobian(x[:3 * nf].reshape(nf, 3)) if nf else np.zeros((0, 3, 3))
        rows, cols, vals = [], [], []
        # row blocks (first row, derivatives, each row's factor): the epipolar residuals (rows 0..m), then with
        # cheirality margin 1 and margin 2 of each match's pair (mean), where charged (the mean negative, and the
        # pair's points mostly in front at the start)
        inv = 1.0 / scale[sel]
        blocks = [(0, _residual_jacobian(R, C, Is, Js, r1[sel], r2[sel]), inv)]
        if charged:  # each match's rows: its pair's mean margin, so its derivatives are the pair's mean ones
            ps = pid[sel]
            _, mean = _pair_means(cheirality_margins(R, C, Is, Js, r1[sel], r2[sel]) * inv[:, None], ps, len(pairs))
            slope = ((mean[ps] < 0) & front0p[ps, None]).astype(float)
            ch = [_pair_means(p * inv[:, None, None], ps, len(pairs))[1][ps]
                  for p in _cheirality_jacobian(R, C, Is, Js, r1[sel], r2[sel])]
            blocks += [(m * (1 + k), [p[:, k] for p in ch], slope[:, k]) for k in range(2)]
        for start, parts, gain in blocks:
            for cams, d_phi, d_C in ((Is, parts[0], parts[2]), (Js, parts[1], parts[3])):
                s_ = slots[cams]
                r = np.nonzero((s_ >= 0) & ((gain != 0) | pattern))[0]
                f = gain[r, None]
                d_w = np.einsum("ma,mab->mb", d_phi[r], Jl[s_[r]]) * f
                d_c = d_C[r] * f
                for off, dv in ((0, d_w), (3 * nf, d_c)):
                    for c in range(3):
                        rows.append(start + r)
                        cols.append(off + 3 * s_[r] + c)
                        vals.append(dv[:, c])
        m = m * (3 if charged else 1)  # the prior and scale rows follow the match rows
        rows.append(m + np.arange(3 * nf))
        cols.append(np.arange(3 * nf))
        vals.append(np.full(3 * nf, 1.0 / prior))
        if keep_scale:
            diff = C[free] - C[anchor]
            unit_dirs = diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-12)
            rows.append(np.full(3 * nf, m + 3 * nf))
            cols.append(3 * nf + np.arange(3 * nf))
            vals.append((10.0 / nf) * unit_dirs.ravel())
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        vals = np.ones(len(rows), np.int8) if pattern else np.concatenate(vals)
        out = coo_matrix((vals, (rows, cols)), shape=(m + 3 * nf + (1 if keep_scale else 0), 6 * nf)).tocsr()
        return out.toarray() if dense else out

    # the start is x = 0: scipy's first trust region is the norm of x0 (1 when zero), and with the centres themselves
    # as parameters it was that of every free centre, 10.7 units on the 100-view ring against a camera spacing of
    # 0.12: the first accepted step could carry a camera through its neighbours (docs/alignment.md)
    x0 = np.zeros(6 * nf)
    e0 = all_residuals(x0)
    front0p = None
    if cheirality:  # [P]: charged pairs, those whose points met mostly in front at the start
        share0, _ = in_front_share(R0, C0, I, J, r1, r2, len(pairs), pid)
        front0p = share0 > 0.5

    def residuals(x, sel, charged):
        R, C = unpack(x)
        e = _residuals_by_pair(R, C, PI, PJ, pid[sel], r1[sel], r2[sel]) / scale[sel]
        out = [e]
        if charged:
            u = cheirality_margins(R, C, I[sel], J[sel], r1[sel], r2[sel]) / scale[sel, None]
            ps = pid[sel]
            charge = np.minimum(_pair_means(u, ps, len(pairs))[1][ps], 0.0) * front0p[ps, None]
            out += [charge[:, 0], charge[:, 1]]
        out.append(x[:3 * nf] / prior)
        if keep_scale:
            dist = np.linalg.norm(C[free] - C[anchor], axis=1).mean()
            out.append([10.0 * (dist - 1.0)])
        return np.concatenate(out)

    def descend(x, charged):
        """Rounds of robust least squares from x, the gate re-drawn after each: (x, solves, evaluations)."""
        gate = np.abs(all_residuals(x)) < 3
        solves = evals = 0
        for _ in range(rounds if nf else 0):
            if gate.sum() < 5:
                break
            sel = gate.copy()
            use_sparse = nf > 8 if sparse is None else sparse
            if jac == "analytic":
                jac_fn = partial(jacobian, sel=sel, dense=not use_sparse, charged=charged)
                opts = {"jac": jac_fn, **({"tr_solver": "lsmr", "tr_options": LSMR_TIGHT} if use_sparse else {})}
            else:  # column groups pay off once cameras touch few pairs; for a handful the dense difference is cheaper
                opts = sparse_opts(x, sel, charged) if use_sparse else {}
            sol = least_squares(partial(residuals, sel=sel, charged=charged), x, loss="cauchy", f_scale=1.0,
                                max_nfev=max_evals, ftol=1e-6, xtol=1e-6, **opts)
            x, evals = sol.x, evals + sol.nfev
            solves += 1
            new = np.abs(all_residuals(x)) < 3
            if np.array_equal(new, gate):
                break
            gate = new
        return x, solves, evals

    def objective(x):  # the charged fit's robust cost over every match (no gate), to compare its two descents
        return float(np.log1p(residuals(x, np.ones(len(I), bool), True) ** 2).sum())

    def reverses(x):  # camera pairs whose matches (gated at the start or at x) x moves from in front to behind
        g = (np.abs(e0) < 3) | (np.abs(all_residuals(x)) < 3)
        return mirrored_pairs(R0, C0 / unit, *unpack(x), I[g], J[g], r1[g], r2[g], parallel_is_behind=True)

    # one BLAS thread: lsmr's products are of vectors of a few 10^4 entries, where OpenBLAS's threads only wait
    # for each other, and on a busy machine (training beside it) they made the fit 10 times slower
    with threadpool_limits(1, user_api="blas"):
        x, solves, evals = descend(x0, cheirality)
        descent = "aligned"
        if cheirality and second_descent and nf:
            # the charge is a wall: a camera whose path to the matches' optimum passes where some points meet
            # behind it can stop at the wall. The second descent crosses it uncharged, then settles charged; it is
            # taken where it costs less and reverses no camera pair (the uncharged path can slide a camera through
            # a neighbour, and the robust loss caps what the charge makes that cost)
            xb, sb, eb = descend(x0, False)
            xb, sc_, ec = descend(xb, True)
            solves, evals = solves + sb + sc_, evals + eb + ec
            if objective(xb) < objective(x) and not reverses(xb):
                x, descent = xb, "uncharged first"
    R, C = unpack(x)
    C = C * unit
    C[held] = C0[held]
    e1 = all_residuals(x)
    g = np.abs(e1) < 3
    mirrored = mirrored_pairs(R0, C0, R, C, I[g], J[g], r1[g], r2[g])
    report = {"matches": int(len(I)), "inliers_before": int((np.abs(e0) < 1).sum()),
              "inliers_after": int((np.abs(e1) < 1).sum()), "median_residual_before": float(np.median(np.abs(e0))),
              "median_residual_after": float(np.median(np.abs(e1))), "solves": solves, "evaluations": evals,
              "held": held, "mirrored_pairs": mirrored, **({"descent": descent} if cheirality else {})}
    return R, C, report


def _pair_list(preds: dict) -> list:
    """One direction per unordered pair: (i, j) with i < j when present, else the order given."""
    out = []
    for i, j in preds:
        if i == j:
            continue
        if (i, j) == (min(i, j), max(i, j)) or (min(i, j), max(i, j)) not in preds:
            out.append((i, j))
    return sorted(out)


def own_focals(preds: dict, n: int) -> np.ndarray:
    """[N] per image: the median of its focals over the pairs it leads (``focal_from_prediction``: a focal head's,
    else the Weiszfeld focal of its own-frame pointmap's unmasked pixels; NaN when it has none)."""
    from pointmap.pose import focal_from_prediction

    per = [[] for _ in range(n)]
    for (i, j), p in preds.items():
        if i != j:
            f = float(focal_from_prediction(p)[0])
            if math.isfinite(f) and f > 0:
                per[i].append(f)
    return np.array([float(np.median(v)) if v else math.nan for v in per])


def refine_epipolar(views, preds: dict, recon, *, config: EpipolarConfig | None = None, align=None):
    """The aligned ``recon`` (``global_align(views, preds, ...)``) with poses (and unknown focals) refined on the
    model's coarse matches of every pair in ``preds``, then, with ``config.refit_depth``, its depths re-fitted by
    ``global_align`` with those poses and intrinsics held (``align``: its AlignConfig; default the one recon was
    aligned with). Known poses and intrinsics (recon.info["align"]) stay as given. Returns a new Reconstruction;
    ``recon.info["epipolar"]`` reports the fit, or why it was skipped (a model without descriptors, every pose
    known, too few matches)."""
    cfg = config or EpipolarConfig()
    if not isinstance(recon, Reconstruction) or not isinstance(cfg, EpipolarConfig) or not isinstance(preds, dict) \
            or not all(isinstance(k, tuple) and len(k) == 2 and all(is_int(x) for x in k) for k in preds):
        raise ShapeError(f"refine_epipolar expected a Reconstruction, preds {{(i, j): PairPrediction}} with integer "
                         f"indices and an EpipolarConfig, got {type(recon).__name__}, {type(preds).__name__} "
                         f"{list(preds)[:3] if isinstance(preds, dict) else ''} and {type(cfg).__name__}")
    t0 = time.perf_counter()
    n = len(recon)
    rep = recon.info.get("align", {})
    known_poses = list(rep.get("known_pose_indices", []))
    known_K = set(rep.get("known_K_indices", []))

    def skipped(reason):
        return replace(recon, info={**recon.info, "epipolar": {"applied": False, "reason": reason, "config": asdict(cfg)}})

    if any(not (0 <= i < n and 0 <= j < n) for i, j in preds):
        raise ShapeError(f"preds expected pairs of indices below {n} (the reconstruction's images), got "
                         f"{sorted(preds)[:5]}")
    if not all(p.has_desc for p in preds.values()):
        return skipped("the model has no descriptor head (no matches)")
    if len(known_poses) == n:
        return skipped("every pose is known")
    from pointmap.align.inputs import camera_index
    from pointmap.align.optimize import AlignConfig, global_align
    from pointmap.geometry.cameras import intrinsics
    from pointmap.matching import match_coarse

    h, w = recon.depth_z.shape[1:]
    matches = {}
    for i, j in _pair_list(preds):
        m = match_coarse(preds[(i, j)], cfg.patch)
        keep = (m.score > 0).numpy()  # cells of zero descriptor confidence (masked pixels) match nothing
        if keep.any():
            matches[(i, j)] = (m.xy1.double().numpy()[keep], m.xy2.double().numpy()[keep])
    K_map = recon.K_map.double().clone()
    calibration = None
    if len(known_K) < n:
        f_own = own_focals(preds, n)
        camera = camera_index(rep.get("config", {}).get("shared_focal", False), n).numpy()
        for c in np.unique(camera):  # one focal per camera: the median of its images' own
            one = camera == c
            if one.sum() > 1 and np.isfinite(f_own[one]).any():
                f_own[one] = float(np.nanmedian(f_own[one]))
        if cfg.self_calibrate and np.isfinite(f_own).all():
            Fs = fundamental_matrices(matches, SELFCAL_THRESHOLD * max(h, w))
            f_cal = calibrate_focals(Fs, f_own, K_map[:, :2, 2].numpy(), camera, sorted(known_K))
            calibration = {"pairs": len(Fs), "focals_own": f_own.tolist(), "focals": f_cal.tolist()}
            f_own = f_cal
        for k in range(n):
            if k not in known_K and math.isfinite(f_own[k]):
                K_map[k] = intrinsics(float(f_own[k]), float(K_map[k, 0, 2]), float(K_map[k, 1, 2]),
                                      dtype=torch.float64)
    thr = cfg.threshold_px if cfg.threshold_px is not None else max(h, w) / 56
    I, J, r1, r2, s = [], [], [], [], []
    Kn = K_map.numpy()
    for (i, j), (xy1, xy2) in matches.items():
        I.append(np.full(len(xy1), i))
        J.append(np.full(len(xy1), j))
        r1.append(_bearings(xy1, Kn[i]))
        r2.append(_bearings(xy2, Kn[j]))
        s.append(np.full(len(xy1), thr / Kn[i, 0, 0]))
    if sum(len(x) for x in I) < 5 * max(1, n - 1):
        return skipped(f"too few matches ({sum(len(x) for x in I)}) for {n} images")
    I, J, r1, r2, s = (np.concatenate(x) for x in (I, J, r1, r2, s))
    c2w = recon.cam2world.double().numpy()
    held = known_poses or [0]
    keep_scale, anchor = len(known_poses) < 2, min(held)  # the first fit's gauge, kept by the re-fit

    def fit_with(held):
        R, C, fit = solve_poses(c2w[:, :3, :3], c2w[:, :3, 3], I, J, r1, r2, s, held=held, keep_scale=keep_scale,
                                anchor=anchor, prior_deg=cfg.rotation_prior_deg, rounds=cfg.rounds,
                                max_evals=cfg.max_evals, cheirality=cfg.cheirality, second_descent=cfg.second_descent)
        collapsed = [p for p in collapsed_pairs(c2w[:, :3, 3], C, I, J) if p not in fit["mirrored_pairs"]]
        return R, C, {**fit, "mirrored_pairs": fit["mirrored_pairs"] + collapsed, "collapsed_pairs": collapsed}

    R, C, fit = fit_with(held)
    if fit["mirrored_pairs"]:  # once more with the cameras at the reversed pairs held where they were aligned
        first = {"mirrored_pairs": fit["mirrored_pairs"], "collapsed_pairs": fit["collapsed_pairs"],
                 "evaluations": fit["evaluations"]}
        pinned = pinned_cameras(fit["mirrored_pairs"], held)
        held = sorted(held + pinned)

        def kept(why):
            return replace(recon, info={**recon.info, "epipolar": {
                "applied": False, "reason": f"the fit reversed the direction of camera pair(s) {first['mirrored_pairs']}"
                f" (their matches' points moved behind the cameras, or their centres met){why}: the aligned poses are "
                "kept", **fit,
                "first_fit": first, "pinned": pinned, "config": asdict(cfg)}})

        if len(held) == n:
            return kept(", and holding their cameras would hold every camera")
        R, C, fit = fit_with(held)
        fit = {**fit, "pinned": pinned, "first_fit": first, "evaluations": first["evaluations"] + fit["evaluations"]}
        if fit["mirrored_pairs"]:
            return kept(f", and the re-fit with cameras {pinned} held reversed {fit['mirrored_pairs']}")
    new = recon.cam2world.double().clone()
    new[:, :3, :3] = torch.from_numpy(R)
    new[:, :3, 3] = torch.from_numpy(C)
    new[held] = recon.cam2world[held].double()
    if not bool(torch.isfinite(new).all()):
        return skipped("the fit did not give finite poses")
    K = K_to_original(K_map, recon.map_from_original.double()).float()
    for k in known_K:
        K[k] = recon.K[k]
    report = {"applied": True, **fit, "threshold_px": thr, "config": asdict(cfg), "self_calibration": calibration,
              "fit_seconds": time.perf_counter() - t0}  # matching and the pose fit, before the depth re-fit
    if cfg.refit_depth:
        acfg = align or AlignConfig(**{**rep.get("config", {}), "quiet": True})
        with warnings.catch_warnings():  # the views' warnings were given by the first alignment: not twice
            warnings.filterwarnings("ignore", message="(identical images|duplicate image names) ")
            out = global_align(views, preds, K=K, cam2world=new.float(), config=acfg)
        report["seconds"] = time.perf_counter() - t0
        return replace(out, info={**recon.info, "align_refit": out.info["align"], "epipolar": report})
    report["seconds"] = time.perf_counter() - t0
    return replace(recon, cam2world=new.float(), K=K, info={**recon.info, "epipolar": report})
