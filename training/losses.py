"""Training losses: cross-view completion (CroCo), confidence-aware pointmap regression (DUSt3R),
InfoNCE matching on descriptors (MASt3R). Pure functions of tensors; batches are the items of data/datasets.py (docs/data.md)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from pointmap.errors import ShapeError, is_int
from pointmap.geometry.cameras import depth_to_points_cam, invert_rigid, transform_points
from pointmap.matching import cell_descriptors


def _check_descriptors(desc1, desc2, corr, temperature: float, name: str) -> None:
    """ShapeError unless desc1 [B, H1, W1, D], desc2 [B, H2, W2, D], corr [B, H1, W1, 2] and temperature > 0."""
    if desc1.ndim != 4 or desc2.ndim != 4 or desc1.shape[0] != desc2.shape[0] or desc1.shape[-1] != desc2.shape[-1]:
        raise ShapeError(f"{name} expected desc1 [B, H1, W1, D] and desc2 [B, H2, W2, D], got {list(desc1.shape)} "
                         f"and {list(desc2.shape)}")
    if tuple(corr.shape) != (*desc1.shape[:3], 2):
        raise ShapeError(f"{name} expected corr {[*desc1.shape[:3], 2]} (view 1's grid), got {list(corr.shape)}")
    if not 0 < temperature < math.inf:
        raise ShapeError(f"{name} expected a temperature > 0, got {temperature}")


def patchify(img: torch.Tensor, patch: int) -> torch.Tensor:
    """[B, 3, H, W] -> [B, N, patch*patch*3] in row-major patch order (matches the token order)."""
    if img.ndim != 4 or img.shape[2] % patch or img.shape[3] % patch:
        raise ShapeError(f"patchify expected [B, C, H, W] with H and W multiples of {patch}, got {list(img.shape)}")
    B, C, H, W = img.shape
    x = img.reshape(B, C, H // patch, patch, W // patch, patch)
    return x.permute(0, 2, 4, 3, 5, 1).reshape(B, (H // patch) * (W // patch), patch * patch * C)


def completion_loss(pred_patches: torch.Tensor, img: torch.Tensor, mask: torch.Tensor, patch: int,
                    eps: float = 1e-6) -> torch.Tensor:
    """CroCo loss: MSE on per-patch normalised pixels of the MASKED patches only.

    pred_patches [B, N, p*p*3]; img [B, 3, H, W]; mask [B, N] bool, True = masked (to reconstruct).
    """
    target = patchify(img, patch)
    if tuple(pred_patches.shape) != tuple(target.shape) or tuple(mask.shape) != tuple(target.shape[:2]):
        raise ShapeError(f"completion_loss expected pred_patches {list(target.shape)} and mask "
                         f"{list(target.shape[:2])} for img {list(img.shape)}, got {list(pred_patches.shape)} and "
                         f"{list(mask.shape)}")
    mean = target.mean(-1, keepdim=True)
    var = target.var(-1, keepdim=True)
    target = (target - mean) / (var + eps).sqrt()
    per_patch = ((pred_patches - target) ** 2).mean(-1)
    m = mask.float()
    return (per_patch * m).sum() / m.sum().clamp_min(1)


def gt_cam2_to_cam1(view1: dict, view2: dict) -> torch.Tensor:
    """Ground-truth transform [B, 4, 4] from view 2's camera frame to view 1's."""
    return invert_rigid(view1["cam2world"]) @ view2["cam2world"]


def gt_points_cam1(view1: dict, view2: dict):
    """Ground-truth pointmaps of both views in view 1's camera frame: ([B,H1,W1,3], [B,H2,W2,3])."""
    p1 = depth_to_points_cam(view1["depth_z"], view1["K"])
    p2_cam2 = depth_to_points_cam(view2["depth_z"], view2["K"])
    return p1, transform_points(gt_cam2_to_cam1(view1, view2), p2_cam2)


def _mean_dist(p1, p2, v1, v2):
    """Mean distance to the origin over the valid pixels of both views, [B]."""
    d = (p1.norm(dim=-1) * v1).flatten(1).sum(1) + (p2.norm(dim=-1) * v2).flatten(1).sum(1)
    n = v1.flatten(1).sum(1) + v2.flatten(1).sum(1)
    return d / n.clamp_min(1)


def _scales(pred, view1: dict, view2: dict, metric: bool):
    """(GT points of both views in view 1's frame, valid masks, GT scale [B], prediction scale [B]): each scale
    the mean distance of its own pointmaps over both views' valid pixels; metric mode uses the GT's for both."""
    gt1, gt2 = gt_points_cam1(view1, view2)
    v1, v2 = view1["valid"].float(), view2["valid"].float()
    s_gt = _mean_dist(gt1, gt2, v1, v2).clamp_min(1e-8)
    s_pr = s_gt if metric else _mean_dist(pred.pts1_cam1.float(), pred.pts2_cam1.float(), v1, v2).clamp_min(1e-8)
    return (gt1, gt2), (v1, v2), s_gt, s_pr


def regression_loss(pred, view1: dict, view2: dict, alpha: float = 0.2, metric: bool = False):
    """DUSt3R confidence-aware regression: per view, mean over valid pixels of conf*||P - X|| - alpha*log conf.

    P and X are the predicted and GT pointmaps in view 1's frame, each divided by its own mean distance over
    both views' valid pixels (metric mode: the GT scale is used for both). Returns (loss, details dict).
    """
    (gt1, gt2), (v1, v2), s_gt, s_pr = _scales(pred, view1, view2, metric)
    pr1, pr2 = pred.pts1_cam1.float(), pred.pts2_cam1.float()
    s_gt, s_pr = s_gt[:, None, None, None], s_pr[:, None, None, None]
    total, details = 0.0, {}
    for name, pr, gt, v, conf in (("1", pr1, gt1, v1, pred.conf1), ("2", pr2, gt2, v2, pred.conf2)):
        err = (pr / s_pr - gt / s_gt).norm(dim=-1)
        conf = conf.float()
        per_px = conf * err - alpha * torch.log(conf)
        n = v.sum().clamp_min(1)
        total = total + (per_px * v).sum() / n
        details[f"regr{name}"] = float(((err * v).sum() / n).detach())
    return total, details


MIN_BASELINE = 0.01  # translations shorter than this (in mean point distances) have no direction to learn
DIR_EPS = 0.05       # smoothing of the predicted translation's norm in the direction term (mean point distances)


def pose_loss(T: torch.Tensor, pred, view1: dict, view2: dict, metric: bool = False, dir_weight: float = 0.0):
    """Direct loss on a predicted cam2 -> cam1 transform T [B, 4, 4] (``model.heads.PoseHead``): Frobenius
    distance of the rotations (2 sqrt(2) sin(angle / 2) for an error of ``angle``) plus the distance of the
    translations, each divided by the mean distance of its own pointmaps as in ``regression_loss`` (the GT
    scale for both in metric mode).

    ``dir_weight`` > 0 adds the chord distance of the translation directions (2 sin(angle / 2), like the
    rotation term; each translation divided by sqrt(|t|^2 + DIR_EPS^2) rather than |t|, which bounds the gradient
    at t = 0) over pairs whose true baseline is at least ``MIN_BASELINE``: the distance of the
    translations is small for short baselines whatever their direction, this term is not. Returns (loss,
    details with the mean rotation error in degrees and, with ``dir_weight``, the mean direction error)."""
    _, (v1, v2), s_gt, s_pr = _scales(pred, view1, view2, metric)
    gt = gt_cam2_to_cam1(view1, view2).float()
    T = T.float()
    rot = (T[:, :3, :3] - gt[:, :3, :3]).flatten(1).norm(dim=1)
    t_pr, t_gt = T[:, :3, 3] / s_pr[:, None], gt[:, :3, 3] / s_gt[:, None]
    tr = (t_pr - t_gt).norm(dim=1)
    # a pair without a valid pixel has no scale (the clamp's 1e-8: a true baseline of 5e7 and a gradient of 5e8
    # that clipping then let drive the whole update): its rotation counts, its translation does not
    scaled = (v1.flatten(1).sum(1) + v2.flatten(1).sum(1)) > 0
    trans = (tr * scaled).sum() / scaled.sum().clamp_min(1)
    loss = rot.mean() + trans
    with torch.no_grad():
        deg = torch.rad2deg(2 * torch.asin((rot / (2 * 2 ** 0.5)).clamp(max=1)))
    details = {"pose_rot_deg": float(deg.mean()),  # the translation error of the pairs the loss counts
               "pose_trans": float(trans.detach()) if bool(scaled.any()) else math.nan}
    if dir_weight > 0:
        ok = (t_gt.norm(dim=1) >= MIN_BASELINE) & scaled
        # directions with a smooth norm t / sqrt(|t|^2 + DIR_EPS^2), the same for both (zero at the truth): the
        # gradient stays below ~1/DIR_EPS near t = 0 (a fresh head predicts exactly 0), where plain normalisation
        # would swamp every other loss after clipping
        def soft_unit(t):
            return t / (t.square().sum(1, keepdim=True) + DIR_EPS ** 2).sqrt()

        chord = (soft_unit(t_pr) - soft_unit(t_gt)).norm(dim=1)
        if bool(ok.any()):
            loss = loss + dir_weight * chord[ok].mean()  # over the pairs it covers (the docs' formula)
            with torch.no_grad():
                cos = (F.normalize(t_pr[ok], dim=1, eps=1e-8) * F.normalize(t_gt[ok], dim=1, eps=1e-8)).sum(1)
                angle = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
            details["pose_dir_deg"] = float(angle.mean())
    return loss, details


def focal_loss(pts_cam: torch.Tensor, K: torch.Tensor, valid: torch.Tensor, iters: int = 3):
    """Mean |log(f / f_true)| over the images used, f the focal a view's own-frame pointmap [B, H, W, 3] implies (the
    estimator the pipeline uses on it, ``pointmap.geometry.focal.focal_from_pointmap``, at the true principal point
    of ``K`` [B, 3, 3], over ``valid`` [B, H, W] pixels), f_true ``K``'s fx. The Weiszfeld weights of the L1
    estimate are computed without gradient and the focal is their weighted least-squares solution, so the loss is
    smooth in the points. The regression loss measures a pointmap's shape only after normalising its scale, where
    a field of view off by 20% costs little beside depth errors; the model learns to predict nearly one focal for
    every image (session 55: slope 0.14 of log predicted on log true focal); this term asks for the image's own.
    Images without a usable pixel are left out; (zero, details) when none is usable. Returns (loss, details with
    the mean |log ratio|)."""
    from pointmap.geometry.focal import focal_rays, solve_focal

    f_true = K[:, 0, 0].to(pts_cam.dtype)
    p, r, ok = focal_rays(pts_cam, valid, K[:, :2, 2].to(pts_cam.dtype))
    with torch.no_grad():  # the L1 estimate and its weights at its solution (1 / pixel residual)
        w0 = ok.to(p.dtype)
        f0 = solve_focal(p, r.detach(), w0, iters)
        w = w0 / (p - f0.nan_to_num(1.0)[:, None, None] * r.detach()).norm(dim=-1).clamp_min(1e-3)
    f = solve_focal(p, r, w, 0)
    use = torch.isfinite(f0) & (f > 0) & (f_true > 0)
    if not bool(use.any()):
        return pts_cam.sum() * 0.0, {"focal_log_err": float("nan")}
    err = (f[use].log() - f_true[use].log()).abs()
    return err.mean(), {"focal_log_err": float(err.detach().mean())}


def focal_head_loss(pred, K1: torch.Tensor, K2: torch.Tensor):
    """Mean |log(f / f_true)| of a focal head's estimates (``pred.focal1``, ``pred.focal2`` [B], pixels of each
    view's pointmap) against the true intrinsics ``K1``, ``K2`` [B, 3, 3] (fx), over both views. Returns (loss,
    details with the mean |log ratio| of each view). ShapeError for a prediction without focals."""
    if pred.focal1 is None or pred.focal2 is None:
        raise ShapeError("focal_head_loss needs a model with a focal head (PairPrediction.focal1 / focal2 are None)")
    B = pred.batch_size
    for name, K in (("K1", K1), ("K2", K2)):
        if tuple(K.shape) != (B, 3, 3):
            raise ShapeError(f"focal_head_loss expected {name} [{B}, 3, 3], got {list(K.shape)}")
    e1 = (pred.focal1.clamp_min(1e-6).log() - K1[:, 0, 0].to(pred.focal1.dtype).log()).abs()
    e2 = (pred.focal2.clamp_min(1e-6).log() - K2[:, 0, 0].to(pred.focal2.dtype).log()).abs()
    return (e1.mean() + e2.mean()) / 2, {"focal_head_err1": float(e1.detach().mean()),
                                         "focal_head_err2": float(e2.detach().mean())}


def matching_loss(desc1: torch.Tensor, desc2: torch.Tensor, corr: torch.Tensor, n_corr: int = 2048,
                  temperature: float = 0.05, generator: torch.Generator | None = None):
    """InfoNCE in both directions on descriptors of corresponding pixels (MASt3R).

    desc1 [B, H1, W1, D], desc2 [B, H2, W2, D] unit descriptors; corr [B, H1, W1, 2] (u, v) pixel of
    each view-1 pixel in view 2, NaN where not co-visible. Up to ``n_corr`` correspondences per pair.
    Returns (loss, accuracy of the argmax match) averaged over pairs that have >= 8 correspondences (a differentiable
    zero and a NaN accuracy without one).
    """
    _check_descriptors(desc1, desc2, corr, temperature, "matching_loss")
    if not (is_int(n_corr) and n_corr >= 1):
        raise ShapeError(f"matching_loss expected n_corr >= 1, got {n_corr!r}")
    sel1, sel2, counts = _sampled_correspondences(desc1.shape, desc2.shape, corr, n_corr, generator)
    losses, accs = [], []
    for d1, d2 in zip(*_sampled_rows(desc1, desc2, sel1, sel2, counts)):
        logits = d1 @ d2.T / temperature
        target = torch.arange(len(d1), device=logits.device)
        losses.append(0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target)))
        accs.append((logits.argmax(1) == target).float().mean())
    if not losses:  # a zero that still reaches both heads (DDP expects every parameter to get a gradient); no
        return (desc1.sum() + desc2.sum()) * 0, float("nan")  # accuracy to average (a 0 would read as all wrong)
    return torch.stack(losses).mean(), float(torch.stack(accs).mean())


def descriptor_confidence_loss(desc1: torch.Tensor, desc2: torch.Tensor, conf1: torch.Tensor, conf2: torch.Tensor,
                               corr: torch.Tensor, n_corr: int = 2048, temperature: float = 0.05,
                               alpha: float = 10.0, generator: torch.Generator | None = None):
    """MASt3R's ConfMatchingLoss for the descriptor confidence alone: over sampled correspondences (as
    ``matching_loss`` samples them), the mean of l_i c_i - alpha log c_i, with c_i = (conf1 at the view-1 pixel +
    conf2 at the view-2 pixel) / 2 and l_i the correspondence's InfoNCE (the mean of both directions, as
    ``matching_loss``) computed WITHOUT gradient: the descriptors' objective stays ``matching_loss``'s, and the
    confidence learns alpha / l_i, high where a match is easy (MASt3R also lets c_i weigh the descriptors' loss).
    conf1 [B, H1, W1], conf2 [B, H2, W2] > 0. Returns (loss averaged over pairs with >= 8 correspondences, mean
    c_i); a differentiable zero (and NaN) without correspondences."""
    _check_descriptors(desc1, desc2, corr, temperature, "descriptor_confidence_loss")
    for name, c, d in (("conf1", conf1, desc1), ("conf2", conf2, desc2)):
        if not isinstance(c, torch.Tensor) or tuple(c.shape) != tuple(d.shape[:3]):
            got = list(c.shape) if isinstance(c, torch.Tensor) else type(c).__name__
            raise ShapeError(f"descriptor_confidence_loss expected {name} {list(d.shape[:3])}, got {got}")
    if not (is_int(n_corr) and n_corr >= 1) or not 0 < alpha < math.inf:
        raise ShapeError(f"descriptor_confidence_loss expected n_corr >= 1 and a finite alpha > 0, got {n_corr!r}, "
                         f"{alpha!r}")
    sel1, sel2, counts = _sampled_correspondences(desc1.shape, desc2.shape, corr, n_corr, generator)
    if not counts:
        return (conf1.sum() + conf2.sum()) * 0, float("nan")
    with torch.no_grad():
        rows1, rows2 = _sampled_rows(desc1, desc2, sel1, sel2, counts)
    i1, i2 = torch.cat(sel1).to(conf1.device), torch.cat(sel2).to(conf2.device)
    c = (0.5 * (conf1.reshape(-1)[i1].float() + conf2.reshape(-1)[i2].float())).split(counts)
    losses = []
    for d1, d2, ci in zip(rows1, rows2, c):
        with torch.no_grad():
            logits = d1 @ d2.T / temperature
            target = torch.arange(len(d1), device=logits.device)
            li = 0.5 * (F.cross_entropy(logits, target, reduction="none")
                        + F.cross_entropy(logits.T, target, reduction="none"))
        losses.append((li * ci - alpha * torch.log(ci)).mean())
    return torch.stack(losses).mean(), float(torch.cat(c).detach().mean())


def _sampled_rows(desc1: torch.Tensor, desc2: torch.Tensor, sel1: list, sel2: list, counts: list) -> tuple:
    """Each pair's descriptors at its sampled correspondences (``_sampled_correspondences``), float32: (view 1's
    [count, D] per pair, view 2's). One gather per view for the whole batch: indexing pair by pair would zero-fill
    a gradient buffer of the whole descriptor batch for every pair in the backward pass."""
    if not counts:
        return (), ()
    D = desc1.shape[-1]
    rows1 = desc1.reshape(-1, D)[torch.cat(sel1).to(desc1.device)].float().split(counts)
    rows2 = desc2.reshape(-1, D)[torch.cat(sel2).to(desc2.device)].float().split(counts)
    return rows1, rows2


def _sampled_correspondences(shape1, shape2, corr: torch.Tensor, n_corr: int, generator):
    """The correspondences the matching losses use: per pair, up to ``n_corr`` view-1 pixels whose correspondence
    lands inside view 2 (a random subset when more), each view-2 pixel kept once (its first), pairs left with
    fewer than 8 left out. Returns (rows of view 1, rows of view 2, counts): indices into each view's flattened
    batch (pair b's pixels are b * H * W + index) and the number of each pair's correspondences."""
    B, H1, W1 = shape1[:3]
    H2, W2 = shape2[1:3]
    sel1, sel2, counts = [], [], []
    for b in range(B):
        c = corr[b].reshape(-1, 2)
        ok = torch.isfinite(c).all(-1)
        u2, v2 = c[:, 0].round(), c[:, 1].round()
        ok &= (u2 >= 0) & (u2 < W2) & (v2 >= 0) & (v2 < H2)
        idx1 = ok.nonzero()[:, 0]
        if idx1.numel() < 8:
            continue
        if idx1.numel() > n_corr:
            idx1 = idx1[torch.randperm(idx1.numel(), generator=generator)[:n_corr]]
        idx2 = (v2[idx1] * W2 + u2[idx1]).long()
        # one view-2 pixel may be hit twice: keep the first, so that targets are unique
        idx2, first = _unique_first(idx2)
        if idx2.numel() < 8:  # eight pixels all landing on one: a "pair" of one correspondence, loss 0, accuracy 1
            continue
        sel1.append(b * H1 * W1 + idx1[first])
        sel2.append(b * H2 * W2 + idx2)
        counts.append(len(idx2))
    return sel1, sel2, counts


def _unique_first(x: torch.Tensor):
    """Unique values of x and the index of their first occurrence."""
    uniq, inv = torch.unique(x, return_inverse=True)
    first = torch.full((uniq.numel(),), x.numel(), dtype=torch.long, device=x.device)
    first.scatter_reduce_(0, inv, torch.arange(x.numel(), device=x.device), reduce="amin")
    return x[first], first


def patch_matching_loss(desc1: torch.Tensor, desc2: torch.Tensor, corr: torch.Tensor, patch: int = 16,
                        temperature: float = 0.1):
    """Coarse (patch-level) InfoNCE: each co-visible patch of view 1 against ALL patches of view 2, and back.

    Descriptors are averaged over each ``patch`` x ``patch`` cell and re-normalised; the positive of a view-1
    cell is the view-2 cell that holds the correspondence of its centre pixel. Unlike the pixel loss, the
    classification is over the ~100 cells of the other view (chance is ln N, not ln n_corr), and the pooled
    descriptor is ONE linear read-out of the decoder token (the mean of the head's per-sub-pixel
    projections), so a pixel and its match start correlated: this is the signal that teaches the trunk to
    find the other view's content (LoFTR's coarse level; MASt3R gets it from DUSt3R's pretraining instead).

    desc1 [B, H1, W1, D], desc2 [B, H2, W2, D]; corr [B, H1, W1, 2] (u, v) in view 2, NaN where not
    co-visible (pixel centres at integer coordinates). Several view-1 cells may fall in one view-2 cell (a
    change of scale): backwards, each hit view-2 cell has all of them as positives (multi-positive InfoNCE).
    Returns (loss, top-1 accuracy of the forward direction) over pairs with >= 4 co-visible cells; the
    accuracy is NaN when no pair has them.
    """
    _check_descriptors(desc1, desc2, corr, temperature, "patch_matching_loss")
    B, H1, W1, D = desc1.shape
    H2, W2 = desc2.shape[1:3]
    if H1 % patch or W1 % patch or H2 % patch or W2 % patch:
        raise ValueError(f"descriptor maps {H1}x{W1}, {H2}x{W2} are not multiples of the patch size {patch}")
    h1, w1, w2 = H1 // patch, W1 // patch, W2 // patch
    c1, c2 = cell_descriptors(desc1, patch), cell_descriptors(desc2, patch)
    centre = corr[:, patch // 2::patch, patch // 2::patch].reshape(B, h1 * w1, 2)  # corr of each cell's centre
    losses, accs = [], []
    for b in range(B):
        u, v = centre[b, :, 0], centre[b, :, 1]
        ok = torch.isfinite(u) & torch.isfinite(v) & (u > -0.5) & (u < W2 - 0.5) & (v > -0.5) & (v < H2 - 0.5)
        idx1 = ok.nonzero()[:, 0]
        if idx1.numel() < 4:
            continue
        col = torch.div(u[idx1] + 0.5, patch, rounding_mode="floor").long()  # the cell of the nearest pixel
        row = torch.div(v[idx1] + 0.5, patch, rounding_mode="floor").long()
        idx2 = row * w2 + col
        logits = c1[b, idx1] @ c2[b].T / temperature  # [n, h2*w2]
        fwd = F.cross_entropy(logits, idx2)
        idx2u, inv = torch.unique(idx2, return_inverse=True)  # backwards: each hit view-2 cell vs all view-1 cells
        back_logits = c2[b, idx2u] @ c1[b].T / temperature  # [U, h1*w1]
        pos = torch.zeros_like(back_logits, dtype=torch.bool)
        pos[inv, idx1] = True
        back = (back_logits.logsumexp(1) - back_logits.masked_fill(~pos, float("-inf")).logsumexp(1)).mean()
        losses.append(0.5 * (fwd + back))
        accs.append((logits.argmax(1) == idx2).float().mean())
    if not losses:  # a zero that still reaches both heads (DDP expects every parameter to get a gradient)
        return (desc1.sum() + desc2.sum()) * 0, float("nan")
    return torch.stack(losses).mean(), float(torch.stack(accs).mean())


def cell_correspondence_counts(corr: torch.Tensor, patch: int, hw2: tuple) -> torch.Tensor:
    """How many pixels of each view-1 patch cell land in each view-2 patch cell: [B, N1, N2] float.

    corr [B, H1, W1, 2] (u, v) in an H2 x W2 view 2, NaN where not co-visible; cells are row-major
    ``patch`` x ``patch`` blocks (the token order). Row i normalised is where view-1 token i's content lies
    among view 2's tokens; column j normalised, where view-2 token j's content lies among view 1's."""
    B, H1, W1, _ = corr.shape
    H2, W2 = hw2
    if H1 % patch or W1 % patch or H2 % patch or W2 % patch:
        raise ValueError(f"images {H1}x{W1}, {H2}x{W2} are not multiples of the patch size {patch}")
    n1, n2 = (H1 // patch) * (W1 // patch), (H2 // patch) * (W2 // patch)
    u, v = corr[..., 0], corr[..., 1]
    ok = torch.isfinite(u) & torch.isfinite(v) & (u > -0.5) & (u < W2 - 0.5) & (v > -0.5) & (v < H2 - 0.5)
    dev = corr.device
    ys, xs = torch.meshgrid(torch.arange(H1, device=dev), torch.arange(W1, device=dev), indexing="ij")
    cell1 = ((ys // patch) * (W1 // patch) + xs // patch).expand(B, H1, W1)
    ui = torch.nan_to_num(u + 0.5).floor().long().clamp(0, W2 - 1)  # the nearest pixel, then its cell
    vi = torch.nan_to_num(v + 0.5).floor().long().clamp(0, H2 - 1)
    cell2 = (vi // patch) * (W2 // patch) + ui // patch
    b = torch.arange(B, device=dev).view(B, 1, 1).expand(B, H1, W1)
    flat = (b * n1 + cell1) * n2 + cell2
    counts = torch.bincount(flat[ok], minlength=B * n1 * n2)
    return counts.view(B, n1, n2).float()


def _soft_ce(scores: torch.Tensor, target: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """KL(target || softmax(scores)) averaged over heads and the selected rows; scores [B, h, N, M],
    target [B, N, M] (rows sum to 1 where selected), rows [B, N] bool."""
    logp = torch.log_softmax(scores.float(), dim=-1)
    t = target[:, None]
    kl = (t * (torch.log(t.clamp_min(1e-12)) - logp)).sum(-1)  # [B, h, N]
    w = rows[:, None].float().expand_as(kl)
    return (kl * w).sum() / w.sum().clamp_min(1)


def cross_attention_loss(scores12: list, scores21: list, counts: torch.Tensor, min_pixels: int = 32):
    """Supervise where the decoders' cross-attention looks: the attention of each view-1 token over view 2's
    tokens should follow where that token's pixels land in view 2 (and back), as the ground truth says.

    scores12: per supervised layer, [B, h, N1, N2] pre-softmax logits of view-1 queries over view-2 keys
    (``CrossAttention.scores``); scores21 likewise [B, h, N2, N1]; counts [B, N1, N2] from
    ``cell_correspondence_counts``. Only tokens with >= ``min_pixels`` co-visible pixels take part. The loss is
    the KL divergence from the correspondence distribution (0 when attention matches it). Returns (loss,
    top-1 accuracy of the last supervised view-1 layer, averaged over its heads; NaN when no token takes part).

    Why: DUSt3R's second head must express view 2's points in view 1's frame, which the network learns by
    attending to the corresponding view-1 tokens; with millions of pairs that emerges from the regression
    loss alone, with the few thousand a CPU affords it does not (the decoders ignored the other view). This
    gives the attention its answer directly, the way LoFTR-style matchers supervise their coarse level.
    """
    if not scores12 and not scores21:
        raise ValueError("cross_attention_loss expected at least one layer of scores, got none")
    rows1 = counts.sum(2) >= min_pixels
    rows2 = counts.sum(1) >= min_pixels
    t12 = counts / counts.sum(2, keepdim=True).clamp_min(1)
    ct = counts.transpose(1, 2)
    t21 = ct / ct.sum(2, keepdim=True).clamp_min(1)
    terms = [_soft_ce(s, t12, rows1) for s in scores12] + [_soft_ce(s, t21, rows2) for s in scores21]
    loss = torch.stack(terms).mean()
    acc = float("nan")
    if scores12 and rows1.any():
        hit = scores12[-1].argmax(-1) == t12.argmax(-1)[:, None]  # [B, h, N1]
        acc = float(hit.float().mean(1)[rows1].mean())
    return loss, acc
