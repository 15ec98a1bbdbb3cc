"""Sparse refinement on matches (bundle adjustment in the spirit of MASt3R's second stage).

Each match (xy_i in image i, xy_j in image j, map pixels) defines a 3D point on image i's ray at xy_i,
its depth d = d0 exp(s_i + delta) starting from the dense depth: s_i one log-scale per image (MASt3R's per-image
depth scale: a view whose whole depth map is off in scale moves as one, instead of through thousands of per-match
deltas each holding 1/M of the gradient, which left the poses and focals to absorb the error), delta per match.
Poses (cam2world = base @ se3_exp(xi)), focal (one log-factor per image, fx and fy scaled together) and optionally
the principal point are optimised with the depths on the robust (Cauchy) reprojection error of the points into
image j, plus a weak prior (s_i + delta)^2 that fixes the scale gauge. LBFGS with a strong-Wolfe line
search. The objective is the one of per-match offsets alone: the per-image scale changes how fast LBFGS gets there,
not where. The dense depth maps are then rescaled per image by the median depth change of their matches (an image
with none of its own by the scene's).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import torch
from tqdm import tqdm

from pointmap.align.gauge import anchor_to_first
from pointmap.align.inputs import camera_index
from pointmap.errors import ShapeError, is_int, is_number
from pointmap.geometry.rotations import se3_exp
from pointmap.reconstruction import K_to_original, Reconstruction


@dataclass(frozen=True)
class SparseConfig:
    """niter: LBFGS iterations; robust_px: Cauchy scale in map pixels (None: min(2, max(h, w) / 100));
    depth_prior: weight of each match's squared log-depth change (s_i + delta)^2 (in px^2 per unit log-depth^2);
    optimize_focal / optimize_pp: which intrinsics move; min_score: matches with a score at or below it are dropped;
    max_matches_per_pair: random subsample cap; quiet: no progress bar (over the fit's loss evaluations)."""

    niter: int = 100
    robust_px: float | None = None
    depth_prior: float = 0.01
    optimize_focal: bool = True
    optimize_pp: bool = False
    min_score: float = 0.0
    max_matches_per_pair: int = 4096
    quiet: bool = False

    def __post_init__(self) -> None:
        bad = []
        if not (is_int(self.niter) and self.niter >= 1):
            bad.append(f"niter expected an int >= 1, got {self.niter!r}")
        if self.robust_px is not None and not (is_number(self.robust_px) and 0 < self.robust_px < math.inf):
            bad.append(f"robust_px expected pixels > 0 (None: automatic), got {self.robust_px!r}")
        if not (is_number(self.depth_prior) and 0 <= self.depth_prior < math.inf):
            bad.append(f"depth_prior expected a weight >= 0, got {self.depth_prior!r}")
        if not (is_number(self.min_score) and math.isfinite(self.min_score)):
            bad.append(f"min_score expected a finite score, got {self.min_score!r}")
        if not (is_int(self.max_matches_per_pair) and self.max_matches_per_pair >= 1):
            bad.append(f"max_matches_per_pair expected an int >= 1, got {self.max_matches_per_pair!r}")
        for name in ("optimize_focal", "optimize_pp", "quiet"):  # "no" is truthy: it would move what it names
            if not isinstance(getattr(self, name), bool):
                bad.append(f"{name} expected True or False, got {getattr(self, name)!r}")
        if bad:
            raise ShapeError("SparseConfig: " + "; ".join(bad))


MAX_FOCAL_CHANGE = 4.0  # a sparse fit that scales a focal beyond this either way is refused (degenerate)


def _unpack(m, key=None):
    """(xy1 [M, 2], xy2 [M, 2], score [M]) float64 of a pair's matches: a Matches or an (xy1, xy2[, score]) tuple.
    ShapeError naming the pair ``key`` for anything else, e.g. xy given as [2, M] (a reshape would pair the wrong
    coordinates)."""
    expected = f"matches[{key!r}] expected a Matches or (xy1 [M, 2], xy2 [M, 2][, score [M]])"
    if isinstance(m, (tuple, list)) and len(m) in (2, 3):
        xy1, xy2, score = m[0], m[1], m[2] if len(m) > 2 else None
    elif all(hasattr(m, a) for a in ("xy1", "xy2")):
        xy1, xy2, score = m.xy1, m.xy2, getattr(m, "score", None)
    else:
        raise ShapeError(f"{expected}, got {type(m).__name__}{f' of {len(m)}' if isinstance(m, (tuple, list)) else ''}")
    try:
        xy1, xy2 = (torch.as_tensor(x, dtype=torch.float64) for x in (xy1, xy2))
        score = torch.ones(len(xy1), dtype=torch.float64) if score is None else \
            torch.as_tensor(score, dtype=torch.float64).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ShapeError(f"{expected} of numbers, got {e}") from None
    if xy1.ndim != 2 or xy1.shape[1] != 2 or xy2.ndim != 2 or xy2.shape[1] != 2 \
            or not (len(xy1) == len(xy2) == len(score)):
        raise ShapeError(f"{expected}, got xy1 {list(xy1.shape)}, xy2 {list(xy2.shape)}, score {list(score.shape)}")
    return xy1, xy2, score


def gather_matches(recon: Reconstruction, matches: dict, cfg: SparseConfig, seed: int = 0):
    """Flatten {(i, j): matches} into tensors, keeping matches inside both images with depth at xy_i."""
    n = len(recon)
    if not isinstance(matches, dict):
        raise ShapeError(f"matches expected a dict {{(i, j): matches}}, got {type(matches).__name__}")
    for key in matches:
        if not (isinstance(key, tuple) and len(key) == 2 and all(is_int(k) and 0 <= k < n for k in key)):
            raise ShapeError(f"matches keys expected (i, j) image indices in 0..{n - 1}, got {key!r}")
    g = torch.Generator().manual_seed(seed)
    I, J, A, B, S = [], [], [], [], []
    given = low_score = outside = no_depth = 0
    for (i, j), m in matches.items():
        if i == j:
            continue
        xy1, xy2, score = _unpack(m, (i, j))
        good_score = (score > cfg.min_score) & torch.isfinite(score)
        keep = good_score & torch.isfinite(xy1).all(1) & torch.isfinite(xy2).all(1)
        given += len(score)
        low_score += int((~good_score).sum())
        for xy, (w, h) in ((xy1, recon.map_sizes[i]), (xy2, recon.map_sizes[j])):  # inside each view's own map
            keep &= (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
        outside += int(good_score.sum()) - int(keep.sum())
        idx = keep.nonzero()[:, 0]
        if len(idx) > cfg.max_matches_per_pair:
            idx = idx[torch.randperm(len(idx), generator=g)[: cfg.max_matches_per_pair]]
        u = xy1[idx, 0].round().long()
        v = xy1[idx, 1].round().long()
        d0 = recon.depth_z[i].double()[v, u]
        ok = d0 > 0
        no_depth += int((~ok).sum())
        idx = idx[ok]
        I.append(torch.full((len(idx),), i))
        J.append(torch.full((len(idx),), j))
        A.append(xy1[idx])
        B.append(xy2[idx])
        S.append(score[idx].clamp_min(0))
    if not I or sum(len(x) for x in I) == 0:
        raise ShapeError(f"refine_matches: no usable matches of {given} given: {low_score} scored at or below "
                         f"min_score={cfg.min_score}, {outside} outside image i or j (or not finite), {no_depth} "
                         f"without depth at xy1 (expected matches in map pixels, score > min_score, inside both "
                         f"images, with depth at xy1)")
    return torch.cat(I), torch.cat(J), torch.cat(A), torch.cat(B), torch.cat(S)


def refine_matches(recon: Reconstruction, matches: dict, *, config: SparseConfig | None = None,
                   fixed_poses=None, fixed_intrinsics=None) -> Reconstruction:
    """Refine poses and intrinsics of ``recon`` on 2D matches; returns a new Reconstruction.

    matches: {(i, j): (xy_i [M, 2], xy_j [M, 2], score [M])} in MAP pixels (the network input, as
        ``pm.match`` returns), or objects with ``xy1``, ``xy2``, ``score``.
    fixed_poses: indices (or True for all) whose cam2world stays bit-identical; None (default): the poses the
        alignment was given (``recon.info["align"]["known_pose_indices"]``). If none is held, the image with the
        most matches is held fixed to pin the frame, and the result then moved rigidly so that image 0's pose is
        the one given: the world stays where it was. fixed_intrinsics: indices (or True for all) with K kept as
        is; None (default): the intrinsics the alignment was given, and those of every camera it shared a focal over.
    """
    cfg = config or SparseConfig()
    if not isinstance(recon, Reconstruction) or not isinstance(cfg, SparseConfig):
        raise ShapeError(f"refine_matches expected a Reconstruction and a SparseConfig, got {type(recon).__name__} "
                         f"and {type(cfg).__name__}")
    t0 = time.perf_counter()
    n = len(recon)
    aligned = recon.info.get("align", {}) if isinstance(recon.info, dict) else {}
    if fixed_poses is None:
        fixed_poses = aligned.get("known_pose_indices", [])
    if fixed_intrinsics is None:
        camera = camera_index(aligned.get("config", {}).get("shared_focal", False), n)  # shared focals stay
        fixed_intrinsics = sorted(set(aligned.get("known_K_indices", [])) |
                                  {k for k in range(n) if int((camera == camera[k]).sum()) > 1})
    if hasattr(fixed_poses, "tolist"):  # a numpy array or tensor of indices
        fixed_poses = fixed_poses.tolist()
    if hasattr(fixed_intrinsics, "tolist"):
        fixed_intrinsics = fixed_intrinsics.tolist()
    for name, idx in (("fixed_poses", fixed_poses), ("fixed_intrinsics", fixed_intrinsics)):
        if idx is True:
            continue
        if not isinstance(idx, (list, tuple, set, range)) or not all(is_int(i) for i in idx):
            raise ShapeError(f"{name} expected image indices (integers) or True for all, got {idx!r}")
        out_of_range = [i for i in idx if not 0 <= i < n]
        if out_of_range:
            raise ShapeError(f"{name} expected image indices in 0..{n - 1}, got {out_of_range}")
    if fixed_poses is True:
        fixed_poses = range(n)
    I, J, xy_i, xy_j, score = gather_matches(recon, matches, cfg)
    fixed_poses = sorted(int(i) for i in fixed_poses)
    anchor = not fixed_poses  # then image 0 is put back where it was given (global_align's world: its frame)
    user_fixed = list(fixed_poses)
    if not fixed_poses:  # the gauge: the most-matched image is held during the optimisation, then moved back
        fixed_poses = [int(torch.bincount(torch.cat([I, J]), minlength=n).argmax())]
    fixed_K = set(range(n)) if fixed_intrinsics is True else {int(i) for i in fixed_intrinsics}
    K0 = recon.K_map.double()
    unit = float(recon.depth_z[(recon.depth_z > 0) & recon.regions].double().median())
    base = recon.cam2world.double().clone()
    base[:, :3, 3] /= unit
    d0 = recon.depth_z.double()[I, xy_i[:, 1].round().long(), xy_i[:, 0].round().long()] / unit
    pose_free = torch.tensor([k not in fixed_poses for k in range(n)], dtype=torch.float64)[:, None]
    f_free = torch.tensor([cfg.optimize_focal and k not in fixed_K for k in range(n)], dtype=torch.float64)
    pp_free = torch.tensor([cfg.optimize_pp and k not in fixed_K for k in range(n)], dtype=torch.float64)[:, None]
    size = torch.tensor(recon.map_sizes, dtype=torch.float64)  # [N, 2] (w, h): a principal-point step is 1% of it
    xi = torch.zeros(n, 6, dtype=torch.float64, requires_grad=True)
    dlf = torch.zeros(n, dtype=torch.float64, requires_grad=True)
    dpp = torch.zeros(n, 2, dtype=torch.float64, requires_grad=True)
    log_scale = torch.zeros(n, dtype=torch.float64, requires_grad=True)
    delta = torch.zeros(len(I), dtype=torch.float64, requires_grad=True)
    wts = score / score.mean().clamp_min(1e-12)
    h, w = recon.depth_z.shape[1:]
    sig2 = (cfg.robust_px if cfg.robust_px else min(2.0, max(h, w) / 100)) ** 2

    def state():
        c2w = base @ se3_exp(xi * pose_free)
        scale = torch.exp(dlf * f_free)
        fx, fy = K0[:, 0, 0] * scale, K0[:, 1, 1] * scale
        pp = K0[:, :2, 2] + dpp * pp_free * size / 100
        return c2w, fx, fy, pp

    def residuals():
        c2w, fx, fy, pp = state()
        d = d0 * torch.exp(log_scale[I] + delta)
        ray = torch.stack([(xy_i[:, 0] - pp[I, 0]) / fx[I], (xy_i[:, 1] - pp[I, 1]) / fy[I], torch.ones_like(d)], -1)
        pw = (c2w[I, :3, :3] @ (d[:, None] * ray)[..., None])[..., 0] + c2w[I, :3, 3]
        Rj = c2w[J, :3, :3]
        pc = (Rj.transpose(-1, -2) @ (pw - c2w[J, :3, 3])[..., None])[..., 0]
        z = pc[:, 2].clamp_min(1e-6)
        uv = torch.stack([fx[J] * pc[:, 0] / z + pp[J, 0], fy[J] * pc[:, 1] / z + pp[J, 1]], -1)
        return (uv - xy_j).norm(dim=-1), pc[:, 2]

    def loss_fn():
        r, _ = residuals()
        robust = sig2 * torch.log1p(r * r / sig2)
        change = log_scale[I] + delta  # each match's log-depth change, held near 0 by the prior
        return (wts * robust).mean() + cfg.depth_prior * (change * change).mean()

    with torch.no_grad():
        r0, _ = residuals()
    max_eval = cfg.niter * 2  # the loss evaluations LBFGS may spend, line searches included: the bar's length
    opt = torch.optim.LBFGS([xi, dlf, dpp, log_scale, delta], lr=1.0, max_iter=cfg.niter, max_eval=max_eval,
                            history_size=20, line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-14)
    evals = [0]
    bar = tqdm(total=max_eval, desc="sparse refinement", unit="eval", disable=cfg.quiet, leave=False)

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        evals[0] += 1
        bar.update()
        return loss

    loss0 = float(loss_fn().detach())
    try:
        opt.step(closure)
    finally:
        bar.close()
    with torch.no_grad():
        final = float(loss_fn())
        r1, z1 = residuals()
        c2w, fx, fy, pp = state()

    def refused(reason):  # the input unchanged, with why
        return replace(recon, info={**recon.info, "sparse": {"applied": False, "reason": reason, "init_loss": loss0,
                                                             "final_loss": final}})

    if not (math.isfinite(final) and torch.isfinite(c2w).all() and torch.isfinite(fx).all()):
        return refused("the fit diverged (a non-finite loss, pose or focal): degenerate; the aligned result is kept")
    if final > loss0:
        return refused("did not improve")
    change = fx / K0[:, 0, 0]
    moved = [k for k in range(n) if not 1 / MAX_FOCAL_CHANGE <= float(change[k]) <= MAX_FOCAL_CHANGE]
    if moved:  # matches that fit anything (few, or wrong) let a focal run to 0: a degenerate fit, not an answer
        return refused(f"the fit scaled the focal of image(s) {moved} by {[round(float(change[k]), 4) for k in moved]} "
                       f"(beyond {MAX_FOCAL_CHANGE:g}x either way): degenerate; the aligned result is kept")
    cam2world = c2w.clone()
    cam2world[:, :3, 3] *= unit
    cam2world = cam2world.float()
    for k in fixed_poses:
        cam2world[k] = recon.cam2world[k]
    if anchor:
        cam2world = anchor_to_first(cam2world, recon.cam2world[0]).float()
    K_map = K0.clone()
    K_map[:, 0, 0], K_map[:, 1, 1], K_map[:, :2, 2] = fx, fy, pp
    K = K_to_original(K_map, recon.map_from_original.double()).float()
    for k in fixed_K:
        K[k] = recon.K[k]
    # each dense depth map follows its matches' median depth change; an image with no match of its own (only ever
    # the second image of its pairs) follows the scene's, which the poses' scale followed: depth and poses agree
    ratio = torch.exp(log_scale.detach()[I] + delta.detach())
    own = [bool((I == k).any()) for k in range(n)]
    depth_scale = [float(ratio[I == k].median() if own[k] else ratio.median()) for k in range(n)]
    depth = recon.depth_z * torch.tensor(depth_scale, dtype=recon.depth_z.dtype)[:, None, None]
    report = {"applied": True, "num_matches": int(len(I)), "evaluations": evals[0], "init_loss": loss0,
              "final_loss": final, "median_reproj_px_before": float(r0.median()),
              "median_reproj_px_after": float(r1.median()), "fixed_poses": user_fixed,
              "held_during_optimisation": fixed_poses, "depth_scale": depth_scale,
              "depth_scale_from_scene": [k for k in range(n) if not own[k]],
              "seconds": time.perf_counter() - t0, "config": asdict(cfg)}
    return replace(recon, cam2world=cam2world, K=K, depth_z=depth, info={**recon.info, "sparse": report})
