"""Two-view relative pose from a pair prediction: PnP-RANSAC (OpenCV) or weighted Procrustes; from pixel
correspondences alone: the essential matrix (OpenCV), or the translation direction given the rotation."""

from __future__ import annotations

import math

import numpy as np
import torch

from pointmap.errors import ShapeError, check_seed, is_int, is_number
from pointmap.geometry.cameras import K_LAYOUT, head_translation, invert_rigid, is_pinhole_K, transform_points
from pointmap.geometry.focal import focal_from_pointmap
from pointmap.geometry.procrustes import weighted_procrustes
from pointmap.geometry.rotations import project_to_rotation
from pointmap.prediction import PairPrediction, check_prediction


def _conf_mask(conf: torch.Tensor, pts: torch.Tensor, keep: float) -> torch.Tensor:
    ok = torch.isfinite(pts).all(-1) & torch.isfinite(conf)
    if ok.sum() == 0:
        return ok
    thr = torch.quantile(conf[ok].float(), 1 - keep)
    return ok & (conf >= thr)


def _pnp(pts_cam1: np.ndarray, uv: np.ndarray, K: np.ndarray, iters: int, reproj: float):
    import cv2

    if len(pts_cam1) < 6:
        return None, 0
    # the pose does not depend on the points' units, but OpenCV's solvers have absolute tolerances (SQPnP found
    # nothing for a scene 1e-6 across): solved in units of the points' median distance, the translation scaled back
    unit = float(np.median(np.linalg.norm(pts_cam1, axis=1)))
    if not (np.isfinite(unit) and unit > 0):
        unit = 1.0
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            pts_cam1.astype(np.float64) / unit, uv.astype(np.float64), K.astype(np.float64), None,
            iterationsCount=iters, reprojectionError=reproj, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:  # SQPnP asserts on degenerate samples (e.g. every pixel the same): no pose, as below
        return None, 0
    if not ok or inliers is None:
        return None, 0
    R, _ = cv2.Rodrigues(rvec)
    world2cam = np.eye(4)
    world2cam[:3, :3], world2cam[:3, 3] = R, tvec[:, 0] * unit
    return np.linalg.inv(world2cam), len(inliers)


def _pose_pnp(pts2_cam1, conf2, K2, keep, rng):
    """PnP of view 2's most confident pixels against their points in view 1's frame (DUSt3R)."""
    H, W = pts2_cam1.shape[:2]
    mask = _conf_mask(conf2, pts2_cam1, keep).numpy()
    v, u = np.nonzero(mask)
    pts = pts2_cam1.numpy()[v, u]
    uv = np.stack([u, v], -1).astype(np.float64)
    if len(pts) > 4000:
        sel = rng.choice(len(pts), 4000, replace=False)
        pts, uv = pts[sel], uv[sel]
    return _pnp_any_focal(pts, uv, K2, H, W)


def _pnp_any_focal(pts, uv, K2, H, W, reproj_frac: float = 0.01):
    """cam2world of the camera seeing 3D points ``pts`` (view 1's frame) at pixels ``uv`` of an H x W image:
    PnP-RANSAC with ``K2``, or, when K2 is None, with the focal that explains the points best. Inlier
    threshold: ``reproj_frac`` of the long side (at least 2 px)."""
    reproj = max(2.0, reproj_frac * max(H, W))
    if K2 is not None:
        return _pnp(pts, uv, K2, 1000, reproj)[0]
    # unknown focal: sweep 21 focals (as the official MST init), score each pose by a truncated quadratic
    # reprojection cost over all points, then refine the focal by golden-section search around the best.
    S = max(H, W)

    def cost_at(f, iters=100):
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
        pose, _ = _pnp(pts, uv, K, iters, reproj)
        if pose is None:
            return np.inf, None
        world2cam = np.linalg.inv(pose)
        Xc = pts @ world2cam[:3, :3].T + world2cam[:3, 3]
        z = np.maximum(Xc[:, 2], 1e-9)
        proj = Xc[:, :2] / z[:, None] * f + K[:2, 2]
        err = np.linalg.norm(proj - uv, axis=1)
        err[Xc[:, 2] <= 0] = reproj
        return float(np.mean(np.minimum(err, reproj) ** 2)), pose

    grid = np.geomspace(S / 2, 3 * S, 21)
    costs = [cost_at(f)[0] for f in grid]
    k = int(np.argmin(costs))
    if not np.isfinite(costs[k]):
        return None
    lo, hi = np.log(grid[max(k - 1, 0)]), np.log(grid[min(k + 1, len(grid) - 1)])
    g = (np.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    ca, cb = cost_at(np.exp(a))[0], cost_at(np.exp(b))[0]
    for _ in range(12):
        if ca < cb:
            hi, b, cb = b, a, ca
            a = hi - g * (hi - lo)
            ca = cost_at(np.exp(a))[0]
        else:
            lo, a, ca = a, b, cb
            b = lo + g * (hi - lo)
            cb = cost_at(np.exp(b))[0]
    return cost_at(np.exp((lo + hi) / 2), iters=1000)[1]


def relative_pose(pred: PairPrediction, K1=None, K2=None, *, pred_reverse: PairPrediction | None = None,
                  matches: list | None = None, keep: float = 0.7, seed: int = 0) -> torch.Tensor:
    """View 2's cam2world in view 1's camera frame, [B, 4, 4] (translation in the prediction's units).

    - ``pred_reverse`` (the prediction of (view 2, view 1)) given, for a model with a pose head (both passes
      carry ``cam2_to_cam1``): the head's transforms of both passes, averaged: the forward one and the reverse
      one inverted, its translation brought to the forward pass's units by the ratio of view 1's own-frame
      pointmaps in the two passes (mean distance to camera 1); the translation keeps the heads' direction and
      takes the length of the pointmaps' (below), as the head's baselines come out short. Otherwise
      confidence-weighted Procrustes both ways, averaged: view 2's own-frame pointmap (reverse pass) onto its
      pointmap in view 1's frame (forward pass), and view 1's own-frame pointmap (forward) onto its pointmap in
      view 2's frame (reverse), inverted. Either way the rotation is the chordal mean of the two, the
      translation (camera 2's centre, in the forward pass's units) their mean (one way alone when the other is
      missing: fewer than 3 usable pixels, or a non-finite transform). Its rotation is the inverse of
      ``relative_pose(pred_reverse, pred_reverse=pred)``'s. No intrinsics needed. On held-out pairs the average
      beats either direction alone, and the pose head's beats the Procrustes of its pointmaps, which compares
      view 2's own-frame points of two passes whose small disagreements turn short baselines (docs/models.md).
    - else PnP-RANSAC (OpenCV SQPNP) of view-2 pixels against ``pts2_cam1`` with ``K2`` [3, 3] or [B, 3, 3]
      (pixels of the prediction's resolution); when K2 is None, K1 is used for view 2 too (a shared
      camera; the views must then have one size) if given, else the focal is found by a sweep over focals
      keeping the lowest truncated reprojection cost, then a golden-section search (``_pnp_any_focal``).
    - ``matches`` (one ``pointmap.matching.Matches`` per batch item, e.g. from ``match`` or ``match_coarse``)
      given: PnP-RANSAC of the matched view-2 pixels against view 1's OWN pointmap at the matched view-1
      pixels (MASt3R-style: needs good matches and view 1's geometry, not the cross-view regression),
      with ``K2`` or the focal sweep described above.
    ``keep``: fraction of most confident pixels used (dense paths). A pose that cannot be found is NaN (never raises
    for degenerate content; raises ShapeError for wrong inputs).
    """
    check_prediction(pred)
    if pred_reverse is not None:
        check_prediction(pred_reverse, "pred_reverse")
    B = pred.batch_size

    def batch_of_K(name, K):
        K = torch.as_tensor(K, dtype=torch.float64).detach().cpu()
        K = K.expand(B, 3, 3) if K.shape == (3, 3) else K
        if tuple(K.shape) != (B, 3, 3):
            raise ShapeError(f"{name} expected [3, 3] or [{B}, 3, 3], got {list(K.shape)}")
        _check_focals(name, K)
        return K

    if K1 is not None:
        K1 = batch_of_K("K1", K1)
        if K2 is None and pred_reverse is None and tuple(pred.pts1_cam1.shape[1:3]) != tuple(pred.pts2_cam1.shape[1:3]):
            raise ShapeError(f"K1 stands for view 2's intrinsics only when the views have one size; got views "
                             f"{list(pred.pts1_cam1.shape[1:3])} and {list(pred.pts2_cam1.shape[1:3])}: give K2")
    if K2 is None and K1 is not None and pred_reverse is None:  # the two-pass path reads no intrinsics
        K2 = K1
    elif K2 is not None:
        K2 = batch_of_K("K2", K2)
    if pred_reverse is not None and pred_reverse.batch_size != B:
        raise ShapeError(f"pred_reverse batch size {pred_reverse.batch_size} differs from pred's {B}")
    if matches is not None and (pred_reverse is not None or not isinstance(matches, (list, tuple))
                                or len(matches) != B):
        raise ShapeError(f"matches expected a list of {B} Matches (and no pred_reverse), got "
                         f"{type(matches).__name__} of {len(matches) if hasattr(matches, '__len__') else '?'}")
    if not 0 < keep <= 1:
        raise ShapeError(f"keep expected in (0, 1], got {keep}")
    out = torch.full((B, 4, 4), float("nan"), dtype=torch.float32)
    seed = check_seed(seed)
    for b in range(B):
        pts2 = pred.pts2_cam1[b].detach().float().cpu()
        conf2 = pred.conf2[b].detach().float().cpu()
        if matches is not None:
            pose = _pose_from_matches(pred.pts1_cam1[b].detach().float().cpu(), matches[b], pts2.shape[:2],
                                      None if K2 is None else K2[b].numpy())
            if pose is not None:
                out[b] = torch.from_numpy(pose).float()
        elif pred_reverse is not None:
            own2 = pred_reverse.pts1_cam1[b].detach().float().cpu()
            if own2.shape != pts2.shape or pred_reverse.pts2_cam1[b].shape != pred.pts1_cam1[b].shape:
                raise ShapeError(f"pred_reverse's pointmaps {list(own2.shape)}, {list(pred_reverse.pts2_cam1[b].shape)}"
                                 f" must match pred's view 2, view 1: {list(pts2.shape)}, "
                                 f"{list(pred.pts1_cam1[b].shape)}")
            fwd = _own_onto_other(own2, pred_reverse.conf1[b], pts2, conf2, keep)
            bwd = _own_onto_other(pred.pts1_cam1[b].detach().float().cpu(), pred.conf1[b],
                                  pred_reverse.pts2_cam1[b].detach().float().cpu(), pred_reverse.conf2[b], keep)
            # bwd maps view 1's own frame (forward units) into camera 2's frame (reverse units): inverted,
            # camera 2's centre in camera 1's frame is -R_b^T t_b / s_b (forward units), its orientation R_b^T
            estimates = ([] if fwd is None else [(fwd[1], fwd[2])]) + \
                        ([] if bwd is None else [(bwd[1].T, -bwd[1].T @ bwd[2] / bwd[0])])
            heads = []
            if pred.cam2_to_cam1 is not None and pred_reverse.cam2_to_cam1 is not None:
                heads = _head_estimates(pred.cam2_to_cam1[b], pred_reverse.cam2_to_cam1[b],
                                        pred.pts1_cam1[b], pred_reverse.pts2_cam1[b])
            if not (estimates or heads):
                continue
            R, t = _mean_motion(heads or estimates)
            if heads and estimates:  # the head's direction, the points' baseline
                t = head_translation(t, _mean_motion(estimates)[1])
            out[b] = torch.eye(4)
            out[b, :3, :3] = R.float()
            out[b, :3, 3] = t.float()
        else:
            # a generator per pair: its subsample, so its pose, is the same alone and in any batch
            pose = _pose_pnp(pts2, conf2, None if K2 is None else K2[b].numpy(), keep, np.random.default_rng(seed))
            if pose is not None:
                out[b] = torch.from_numpy(pose).float()
    return out


def _mean_motion(estimates: list):
    """(chordal mean rotation, mean translation) of a non-empty list of (R, t)."""
    return project_to_rotation(sum(R for R, _ in estimates)), sum(t for _, t in estimates) / len(estimates)


def _head_estimates(T_fwd: torch.Tensor, T_rev: torch.Tensor, own1_fwd: torch.Tensor, pts1_rev: torch.Tensor) -> list:
    """[(R, t)] float64 of camera 2 in camera 1's frame from a pose head's transforms of both passes: ``T_fwd``
    (cam2 -> cam1, forward units) and ``T_rev`` (cam1 -> cam2, reverse units) inverted, its translation scaled
    by the mean distance to camera 1 of view 1's own-frame points in the forward pass (``own1_fwd``) over the
    reverse pass's (``pts1_rev``, view 1's points in camera 2's frame, moved back by the inverted ``T_rev``).
    A transform or scale that is not finite is left out (an empty list when neither is usable)."""
    out = []
    T_fwd, T_rev = T_fwd.detach().double().cpu(), T_rev.detach().double().cpu()
    if bool(torch.isfinite(T_fwd).all()):
        out.append((T_fwd[:3, :3], T_fwd[:3, 3]))
    if bool(torch.isfinite(T_rev).all()):
        T_inv = invert_rigid(T_rev)
        own1_rev = transform_points(T_inv, pts1_rev.detach().double().cpu())
        own1_fwd = own1_fwd.detach().double().cpu()
        ok = torch.isfinite(own1_rev).all(-1) & torch.isfinite(own1_fwd).all(-1)
        if bool(ok.any()):
            scale = own1_fwd[ok].norm(dim=-1).mean() / own1_rev[ok].norm(dim=-1).mean()
            if bool(torch.isfinite(scale)) and scale > 0:
                out.append((T_inv[:3, :3], T_inv[:3, 3] * scale))
    return out


def _own_onto_other(own, conf_own, other, conf_other, keep: float):
    """(s, R, t) float64 of the confidence-weighted Procrustes taking a view's own-frame pointmap onto its
    pointmap in the other camera's frame (same pixels), or None with fewer than 3 usable pixels (or no weight)."""
    w = conf_other.detach().float().cpu() * conf_own.detach().float().cpu()
    mask = _conf_mask(w, other, keep) & torch.isfinite(own).all(-1)
    if mask.sum() < 3 or not bool(w[mask].sum() > 0):
        return None
    s, R, t = weighted_procrustes(own[mask].double(), other[mask].double(), w[mask].double())
    if not (bool(torch.isfinite(s)) and float(s) > 1e-12 and bool(torch.isfinite(R).all())
            and bool(torch.isfinite(t).all())):
        return None  # a collapsed pointmap (all its points at one place) has no scale to invert
    return s, R, t


def _pose_from_matches(pts1_cam1: torch.Tensor, m, hw2, K2):
    H1, W1 = pts1_cam1.shape[:2]
    xy1 = m.xy1.round().long().cpu()
    ok = (xy1[:, 0] >= 0) & (xy1[:, 0] < W1) & (xy1[:, 1] >= 0) & (xy1[:, 1] < H1)
    xy1, xy2 = xy1[ok], m.xy2.cpu()[ok]
    pts = pts1_cam1[xy1[:, 1], xy1[:, 0]]
    fin = torch.isfinite(pts).all(-1) & torch.isfinite(xy2).all(-1)
    # matches may be quantised to patch cells (match_coarse): a looser inlier threshold than dense PnP
    return _pnp_any_focal(pts[fin].double().numpy(), xy2[fin].double().numpy(), K2, *hw2, reproj_frac=0.04)


def pose_from_essential(xy1, xy2, K1, K2, threshold_px: float = 1.0, prob: float = 0.999) -> np.ndarray | None:
    """View 2's cam2world [4, 4] float64 in view 1's frame (unit translation) from pixel correspondences
    ``xy1``, ``xy2`` [M, 2] (u, v) and the intrinsics [3, 3] of each view: five-point essential matrix in
    RANSAC (OpenCV) on normalised coordinates, inlier threshold ``threshold_px`` pixels of view 1, then the
    cheirality test. Needs no depth at all (the classical two-view pipeline). None with fewer than 5
    correspondences or no solution with at least 5 inliers in front of both cameras (e.g. no motion), or when
    several solutions explain equally many (exactly five correspondences often fit more than one essential
    matrix); ShapeError for wrong inputs."""
    import cv2

    if not 0 < prob < 1:
        raise ShapeError(f"prob expected in (0, 1), got {prob}")
    xy1, xy2, K1, K2 = _checked_pixels(xy1, xy2, K1, K2, threshold_px)
    if len(xy1) < 5:
        return None
    n1 = cv2.undistortPoints(xy1[:, None], K1, None)[:, 0]
    n2 = cv2.undistortPoints(xy2[:, None], K2, None)[:, 0]
    try:
        E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), method=cv2.RANSAC, prob=prob,
                                       threshold=threshold_px / K1[0, 0])
    except cv2.error:
        # The inputs were checked above, so OpenCV's errors here are its solver's: OpenCV 5.1 asserts inside the
        # five-point polynomial solve (solvePoly) on degenerate samples, e.g. no motion, where 4.x and 5.0 return
        # no solution. Both mean the same thing.
        return None
    if E is None or E.ndim != 2 or E.shape[1] != 3 or E.shape[0] % 3 or E.shape[0] == 0:
        return None
    # from exactly five correspondences OpenCV returns every five-point solution stacked ([3k, 3]): the pose is
    # the one with the most points in front of both cameras, if no other solution explains as many
    sols = [cv2.recoverPose(e, n1, n2, np.eye(3), mask=mask.copy())[:3] for e in E.reshape(-1, 3, 3)]
    n_front, R, t = max(sols, key=lambda x: x[0])
    if n_front < 5 or sum(n == n_front for n, _, _ in sols) > 1:
        return None
    world2cam2 = np.eye(4)
    world2cam2[:3, :3], world2cam2[:3, 3] = R, t[:, 0]
    return np.linalg.inv(world2cam2)


def _check_focals(name: str, K: torch.Tensor) -> None:
    """ShapeError unless every [3, 3] of ``K`` [B, 3, 3] is finite pinhole intrinsics with positive focals (a user's
    intrinsics)."""
    ok = is_pinhole_K(K)
    if not bool(ok.all()):
        b = int((~ok).nonzero()[0])
        raise ShapeError(f"{name} expected finite intrinsics with positive focals ({K_LAYOUT}), got {K[b].tolist()}"
                         f"{f' (batch item {b})' if K.shape[0] > 1 else ''}")


def _checked_pixels(xy1, xy2, K1, K2, threshold_px):
    """float64 (xy1, xy2, K1, K2) of the correspondence solvers, rows with a non-finite value dropped;
    ShapeError for wrong shapes, intrinsics or threshold."""
    xy1, xy2 = np.asarray(xy1, dtype=np.float64), np.asarray(xy2, dtype=np.float64)
    K1, K2 = np.asarray(K1, dtype=np.float64), np.asarray(K2, dtype=np.float64)
    if xy1.ndim != 2 or xy1.shape[1:] != (2,) or xy1.shape != xy2.shape:
        raise ShapeError(f"xy1, xy2 expected matching [M, 2] pixel arrays, got {list(xy1.shape)} and {list(xy2.shape)}")
    for name, K in (("K1", K1), ("K2", K2)):
        if K.shape != (3, 3) or not bool(is_pinhole_K(K)):
            raise ShapeError(f"{name} expected finite [3, 3] pinhole intrinsics with positive focals ({K_LAYOUT}), got "
                             f"{K.tolist() if K.size <= 9 else list(K.shape)}")
    if not threshold_px > 0:
        raise ShapeError(f"threshold_px expected > 0, got {threshold_px}")
    keep = np.isfinite(xy1).all(1) & np.isfinite(xy2).all(1)
    return xy1[keep], xy2[keep], K1, K2


def _bearings(xy, K):
    """Unit viewing rays [M, 3] of pixels (u, v) through intrinsics K."""
    r = np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def translation_from_matches(R, xy1, xy2, K1, K2, threshold_px: float = 2.0, prob: float = 0.999,
                             max_iters: int = 1000, seed: int = 0) -> np.ndarray | None:
    """Direction [3] float64 (unit) of camera 2's centre in view 1's frame, given the relative rotation ``R``
    (view 2's cam2world rotation in view 1's frame, e.g. the model's) and pixel correspondences ``xy1``, ``xy2``
    [M, 2] with each view's intrinsics [3, 3].

    With the rotation known, the epipolar constraint is linear in t: t . (R r2 x r1) = 0 for the rays r1, r2 of
    a correspondence, so two correspondences fix the direction (their cross product). Two-point RANSAC
    (adaptive: stops once ``prob`` says an all-inlier sample was drawn, at most ``max_iters`` samples, fixed
    ``seed``) with the angular distance of r1 from the epipolar plane of (t, R r2), inlier within
    ``threshold_px`` / focal of view 1; then least squares over the inliers and the sign that puts the most
    inliers in front of both cameras. Depth-free, so a pointmap model's rotation plus its own matches gives a
    translation direction that does not inherit the errors of its depth or baseline. None with fewer than 5
    inliers; ShapeError for wrong inputs (R must be a rotation)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(R) < 0:
        raise ShapeError(f"R expected a [3, 3] rotation matrix, got {R.tolist() if R.size <= 9 else list(R.shape)}")
    if not (0 < prob < 1 and max_iters >= 1):
        raise ShapeError(f"prob expected in (0, 1) and max_iters >= 1, got {prob} and {max_iters}")
    seed = check_seed(seed)
    xy1, xy2, K1, K2 = _checked_pixels(xy1, xy2, K1, K2, threshold_px)
    if len(xy1) < 5:
        return None
    r1, r2 = _bearings(xy1, K1), _bearings(xy2, K2) @ R.T  # both in view 1's frame
    A = np.cross(r2, r1)  # t . A_i = 0 for the true t

    def residual(t):  # [..., M] |sin| of the angle between r1 and the plane spanned by t and R r2
        n = np.cross(t[..., None, :], r2)
        return np.abs((n * r1).sum(-1)) / np.maximum(np.linalg.norm(n, axis=-1), 1e-12)

    thr = threshold_px / K1[0, 0]
    rng = np.random.default_rng(seed)
    best, n_best, iters, done = None, 0, max_iters, 0
    while done < iters:
        k = min(max(1, 2_000_000 // len(A)), 256, iters - done)  # hypotheses per batch: bounded memory
        i = rng.integers(0, len(A), size=(k, 2))
        t = np.cross(A[i[:, 0]], A[i[:, 1]])
        norm = np.linalg.norm(t, axis=1)
        t = t[norm > 1e-12] / norm[norm > 1e-12, None]
        done += k
        if len(t) == 0:
            continue
        inl = residual(t) < thr  # [k, M]
        j = int(inl.sum(1).argmax())
        if inl[j].sum() > n_best:
            best, n_best = inl[j], int(inl[j].sum())
            w = n_best / len(A)
            iters = min(max_iters, int(np.ceil(np.log(1 - prob) / np.log(max(1 - w * w, 1e-12)))))
    if n_best < 5:
        return None
    t = np.linalg.svd(A[best] / np.linalg.norm(A[best], axis=1, keepdims=True).clip(1e-12))[2][-1]
    # cheirality: a r1 = b R r2 + t with a, b > 0 for a point in front of both cameras (2 x 2 normal equations)
    a11, a12, a22 = (r1[best] ** 2).sum(1), -(r1[best] * r2[best]).sum(1), (r2[best] ** 2).sum(1)
    det = np.maximum(a11 * a22 - a12 ** 2, 1e-12)
    b1, b2 = r1[best] @ t, -(r2[best] @ t)
    a = (a22 * b1 - a12 * b2) / det
    b = (a11 * b2 - a12 * b1) / det
    front = ((a > 0) & (b > 0)).sum(), ((a < 0) & (b < 0)).sum()  # -t flips both signs
    return t if front[0] >= front[1] else -t


def refine_pose_with_matches(cam2world: torch.Tensor, m, K1, K2, *, threshold_px: float = 8.0,
                             rotation_prior_deg: float = 10.0, max_evals: int = 200) -> torch.Tensor:
    """A pose [4, 4] (view 2's cam2world in view 1's frame, e.g. the model's from ``relative_pose``) refined on
    pixel matches ``m`` (``pointmap.matching.Matches``) with each view's intrinsics [3, 3]; the baseline length is
    kept (matches fix only the direction).

    The model's pose is a prior, the matches are evidence: the translation direction starts from
    ``translation_from_matches`` given the model's rotation (two-point RANSAC, ``threshold_px``), then rotation and
    direction are refined together by robust least squares (Cauchy, scale ``threshold_px`` / focal of view 1) on
    the angular distance of each view-1 ray from its epipolar plane, plus a Cauchy-robust prior of width
    ``rotation_prior_deg`` keeping the rotation near the model's (``math.inf``: no prior; ``0``: the rotation is
    kept and only the direction is estimated). The pose is returned unchanged when it is not finite or the
    matches give no direction (fewer than 5 RANSAC inliers); a zero baseline gets unit length. ShapeError for
    wrong inputs."""
    if not isinstance(cam2world, torch.Tensor) or tuple(cam2world.shape) != (4, 4):
        raise ShapeError(f"cam2world expected a [4, 4] tensor, got "
                         f"{list(cam2world.shape) if hasattr(cam2world, 'shape') else type(cam2world).__name__}")
    if not rotation_prior_deg >= 0 or not is_int(max_evals) or max_evals < 1:  # NaN fails too
        raise ShapeError(f"rotation_prior_deg expected >= 0 (math.inf: no prior) and max_evals an int >= 1, got "
                         f"{rotation_prior_deg} and {max_evals}")
    if not bool(torch.isfinite(cam2world).all()):
        return cam2world
    R0 = cam2world[:3, :3].detach().double().cpu().numpy()
    xy1, xy2, K1, K2 = _checked_pixels(m.xy1.detach().double().cpu().numpy(), m.xy2.detach().double().cpu().numpy(),
                                       K1, K2, threshold_px)
    t = translation_from_matches(R0, xy1, xy2, K1, K2, threshold_px=threshold_px)
    if t is None:
        return cam2world
    R = R0
    if rotation_prior_deg > 0:
        R, t = _refine_rt(R0, t, _bearings(xy1, K1), _bearings(xy2, K2), threshold_px / K1[0, 0],
                          math.radians(rotation_prior_deg), max_evals)
    out = cam2world.clone()
    length = float(cam2world[:3, 3].norm())
    out[:3, :3] = torch.from_numpy(R).to(out.dtype)
    out[:3, 3] = torch.from_numpy(t).to(out.dtype) * (length if length > 0 else 1.0)
    return out


def _epipolar_residuals(R, t, r1, r2):
    """Signed sine of the angle between each ray r1 and the plane spanned by t and R r2 (rays [M, 3], t unit)."""
    n = np.cross(t[None], r2 @ R.T)
    return (n * r1).sum(1) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)


def _refine_rt(R0, t0, r1, r2, scale: float, prior: float, max_evals: int, rounds: int = 4):
    """argmin over (w, t) of sum_i Cauchy(e_i / scale) + sum_k Cauchy(w_k / prior), R = exp(w) R0, |t| = 1, e_i the
    angular epipolar residuals (``_epipolar_residuals``) of the matches within 3 ``scale`` of the current pose: a
    Cauchy loss alone still lets many far outliers pull the pose (a 40% share biased it by 1 degree), so the sum
    runs over that gate, re-drawn after each solve until it settles (at most ``rounds`` solves; scipy's
    trust-region least squares)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def pose(x):
        return Rotation.from_rotvec(x[:3]).as_matrix() @ R0, x[3:] / max(np.linalg.norm(x[3:]), 1e-12)

    x = np.r_[np.zeros(3), t0]
    gate = np.abs(_epipolar_residuals(R0, t0, r1, r2)) < 3 * scale
    for _ in range(rounds):
        if gate.sum() < 5:
            break
        a, b = r1[gate], r2[gate]

        def residuals(x):
            e = _epipolar_residuals(*pose(x), a, b)
            return e if math.isinf(prior) else np.r_[e, scale * x[:3] / prior]

        x = least_squares(residuals, x, loss="cauchy", f_scale=scale, max_nfev=max_evals).x
        new = np.abs(_epipolar_residuals(*pose(x), r1, r2)) < 3 * scale
        if np.array_equal(new, gate):
            break
        gate = new
    return pose(x)


def focal_from_prediction(pred: PairPrediction, view: int = 1) -> torch.Tensor:
    """[B] focal of view ``view`` in pixels of its pointmap (principal point at the centre): the focal head's
    (``pred.focal1`` / ``focal2``) for a model with one (view 1's where it gave none: NaN, zero or negative), else
    view 1's own-frame pointmap's (Weiszfeld) over its
    pixels of positive confidence (a mask's zeroed pixels left out, as global alignment's start leaves them; the
    network's confidences are all positive); view 2 of a model without a focal head needs the reverse prediction."""
    check_prediction(pred)
    if view not in (1, 2):
        raise ShapeError(f"view expected 1 or 2, got {view!r}")
    head = pred.focal1 if view == 1 else pred.focal2
    if head is not None:
        head = head.detach().float()
        if view == 2 or bool((torch.isfinite(head) & (head > 0)).all()):
            return head
    if view != 1:
        raise ShapeError("only view 1's pointmap is in its own frame; run the reverse pair for view 2")
    own = focal_from_pointmap(pred.pts1_cam1.float(), valid=torch.nan_to_num(pred.conf1.float(), nan=0.0) > 0)
    # a head that gave no focal (NaN, zero or negative) is read off the pointmap instead, as the alignment's start
    return own if head is None else torch.where(torch.isfinite(head) & (head > 0), head, own)


def pair_pose(pred: PairPrediction, pred_reverse: PairPrediction, K1=None, K2=None, *, patch: int = 16,
              rotation_prior_deg: float | None = None, threshold_px: float = 8.0, pose: torch.Tensor | None = None,
              matches: list | None = None) -> torch.Tensor:
    """The model's two-view pose, [B, 4, 4] (view 2's cam2world in view 1's frame, translation in the forward
    pass's units): what ``pointmap pair``, ``pointmap demo`` and the model card report.

    ``relative_pose(pred, pred_reverse=pred_reverse)`` (the pose head's transforms of both passes, or the
    Procrustes of the pointmaps both ways for a model without one), then, for a model
    with descriptors, ``refine_pose_with_matches`` on its own coarse matches (``match_coarse(pred[b], patch)``)
    with each view's intrinsics: ``K1`` / ``K2`` [3, 3] or [B, 3, 3] when known (pixels of the prediction), else
    a focal from that view's own-frame pointmap (``focal_from_prediction`` of its pass) and the image centre.
    The pointmaps' rotation is the better estimate and the matches' epipolar geometry the better translation
    direction (docs/models.md), so ``rotation_prior_deg`` keeps the rotation near the pointmaps': default 3
    degrees when a focal is estimated (its error would otherwise pull the rotation), 1 with both intrinsics known
    (session 77, v76a on the 617 card pairs with their true K: rotations / directions within 15 degrees 438 / 211
    at 1 degree, 423 / 218 at 3, 415 / 214 at 10, 437 / 150 at 0; the pose head's rotation is the better one).
    The direction keeps the side of camera 1 the pointmaps put camera 2 on (the epipolar residuals are blind to
    its sign; a wrong rotation or focal can fool the matches' cheirality test: on 556 held-out pairs of v26a, 97
    directions within 15 degrees against 92 without this, 18 flipped against 26). A pair whose matches give no
    direction keeps its pointmap pose; a pose that cannot be found is NaN. Models
    without descriptors get ``relative_pose`` alone. ``pose`` ([B, 4, 4], that ``relative_pose``) and ``matches``
    (B ``Matches``, those ``match_coarse``) reuse what a caller already computed. ShapeError for wrong inputs."""
    from pointmap.geometry.cameras import intrinsics
    from pointmap.matching import match_coarse

    check_prediction(pred)
    if not isinstance(pred_reverse, PairPrediction):
        raise ShapeError(f"pred_reverse expected the PairPrediction of (view 2, view 1), got "
                         f"{type(pred_reverse).__name__}")
    B = pred.batch_size
    # the settings are checked whether or not a pair gets refined (one without a usable focal skips it)
    if not (is_int(patch) and patch >= 1):
        raise ShapeError(f"patch expected an int >= 1, got {patch!r}")
    if not (is_number(threshold_px) and 0 < threshold_px < math.inf):
        raise ShapeError(f"threshold_px expected a finite number > 0, got {threshold_px!r}")
    if rotation_prior_deg is not None and not (is_number(rotation_prior_deg) and rotation_prior_deg >= 0):
        raise ShapeError(f"rotation_prior_deg expected None or a number >= 0 (math.inf: no prior), got "
                         f"{rotation_prior_deg!r}")
    if pose is not None:
        pose = torch.as_tensor(pose)
        if tuple(pose.shape) != (B, 4, 4):
            raise ShapeError(f"pose expected relative_pose's [{B}, 4, 4], got {list(pose.shape)}")
    if matches is not None and (not isinstance(matches, (list, tuple)) or len(matches) != B):
        raise ShapeError(f"matches expected a list of {B} Matches, got {type(matches).__name__}")
    given = {}
    for name, K in (("K1", K1), ("K2", K2)):  # the user's intrinsics, checked whether or not they get used
        if K is not None:
            K = torch.as_tensor(K, dtype=torch.float64)
            K = K.expand(B, 3, 3) if K.shape == (3, 3) else K
            if tuple(K.shape) != (B, 3, 3):
                raise ShapeError(f"{name} expected [3, 3] or [{B}, 3, 3], got {list(K.shape)}")
            _check_focals(name, K)
            given[name] = K
    out = relative_pose(pred, pred_reverse=pred_reverse) if pose is None else pose.float().clone()
    if not pred.has_desc:
        return out
    Ks = []
    for name, own in (("K1", pred), ("K2", pred_reverse)):
        K = given.get(name)
        if K is None:  # the view's focal from its own-frame pointmap, the principal point at the centre
            H, W = own.pts1_cam1.shape[1:3]
            K = torch.stack([intrinsics(float(f), (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
                             for f in focal_from_prediction(own)])
        Ks.append(K)
    prior = (1.0 if K1 is not None and K2 is not None else 3.0) if rotation_prior_deg is None else rotation_prior_deg
    for b in range(B):
        usable = all(bool(torch.isfinite(K[b]).all()) and float(K[b, 0, 0]) > 0 for K in Ks)
        if not usable or not bool(torch.isfinite(out[b]).all()):
            continue  # no pointmap pose, or no usable focal (a degenerate pointmap): nothing to refine
        m = match_coarse(pred[b], patch) if matches is None else matches[b]
        refined = refine_pose_with_matches(out[b], m, Ks[0][b].detach().cpu().numpy(), Ks[1][b].detach().cpu().numpy(),
                                           threshold_px=threshold_px, rotation_prior_deg=prior)
        if float(refined[:3, 3] @ out[b, :3, 3]) < 0:  # the side the pointmaps put camera 2 on: a sign the
            refined[:3, 3] = -refined[:3, 3]  # epipolar fit does not see (its cheirality test can be fooled)
        out[b] = refined
    return out
