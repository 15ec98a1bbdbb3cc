"""Held-out evaluation of a pair model: relative pose (RRA/RTA@15), depth AbsRel, matching precision."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from pointmap.align.edges import AUTO_SPREAD_CONF
from pointmap.geometry.cameras import invert_rigid, transform_points
from pointmap.geometry.focal import focal_from_pointmap
from pointmap.geometry.rotations import relative_rotation_error_deg, rotation_angle, translation_angle_deg
from pointmap.matching import match, match_coarse
from pointmap.pose import focal_from_prediction, pair_pose, refine_pose_with_matches, relative_pose
from training.losses import patch_matching_loss


def _depth_scale(p: torch.Tensor, g: torch.Tensor):
    """The median ratio true / predicted depth over the pixels predicted in front (p, g: valid pixels, float64)
    that puts a scale-free prediction in the truth's units, or None when no pixel is predicted in front."""
    front = p > 0
    return torch.median(g[front] / p[front]) if bool(front.any()) else None


class PairResult(NamedTuple):
    """One pair's two-view pose result: its index in the held-out set, the rotation error and the translation
    direction error of the pose from the model's pointmaps (degrees; a pose not found counts 180 for both, a
    zero translation, predicted or true, 90: ``translation_angle_deg``), the true rotation angle between the two cameras (degrees; NaN when unknown),
    and the same two errors of the pose the pipeline reports (``pointmap.pose.pair_pose``: refined on the
    model's own matches; NaN for a model without descriptors or a tool that does not compute it)."""
    pair: int
    rot_err: float
    dir_err: float
    true_rot: float
    pair_rot_err: float = float("nan")
    pair_dir_err: float = float("nan")


PER_PAIR_HEADER = ("set", "pair", "rot_err", "dir_err", "true_rot", "pair_rot_err", "pair_dir_err")
PER_PAIR_HEADER_V1 = PER_PAIR_HEADER[:5]  # files written before session 42 (no pipeline pose): read as NaN


CONDITIONS_TAG = "# conditions"  # a per-pair CSV's rows of that first field: (tag, set, measurement_conditions())
CONDITIONS_PACKAGES = ("torch", "numpy", "opencv-contrib-python-headless", "kornia", "scipy")


def measurement_conditions() -> str:
    """What a pair's errors depend on besides the model and the pair, as ``key=value`` fields joined by ``;``:
    torch's thread count and the versions of Python and of the packages that compute them. The same model on the
    same renders gives other pipeline poses and global alignments at another thread count (session 89: at 1 thread
    against the baseline's 2, 21 of ``eval_s424242``'s 139 pipeline directions moved, by up to 19 degrees; global
    alignment at 1 thread moved 9 of the baseline's 1,008 camera pairs, by up to 71), so a comparison must be
    between files written under the same conditions."""
    import importlib.metadata
    import platform

    fields = [f"threads={torch.get_num_threads()}", f"python={platform.python_version()}"]
    for name in CONDITIONS_PACKAGES:
        try:
            fields.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            fields.append(f"{name}=none")
    return ";".join(fields)


def read_per_pair_csv(path) -> tuple[int, list, dict]:
    """(the number of columns of the file's header, its data rows as lists of strings, {set: the conditions it
    was measured under}) of a per-pair CSV written by ``write_per_pair``, this version's or one before session 42
    (without the pipeline's two columns; files before session 89 record no conditions); OSError when it cannot
    be read, ValueError naming the header otherwise."""
    import csv

    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) not in (PER_PAIR_HEADER, PER_PAIR_HEADER_V1):
        raise ValueError(f"{path}: expected the header {','.join(PER_PAIR_HEADER)} (or, before session 42, "
                         f"{','.join(PER_PAIR_HEADER_V1)}), got {','.join(rows[0]) if rows else 'an empty file'}")
    conditions = {r[1]: r[2] for r in rows[1:] if r and r[0] == CONDITIONS_TAG and len(r) == 3}
    return len(rows[0]), [r for r in rows[1:] if not (r and r[0] == CONDITIONS_TAG)], conditions


def _per_pair_rows_kept(path, set_name: str) -> tuple[list, dict]:
    """The rows of other sets in an existing per-pair CSV at ``path`` and their conditions (([], {}) when there
    is none), after checking ``set_name`` and that the file is a per-pair CSV; ValueError otherwise (nothing
    written)."""
    from pathlib import Path

    if not set_name or set_name == "all" or set_name == CONDITIONS_TAG or any(c in set_name for c in ',"\n\r'):
        raise ValueError(f"set_name expected a non-empty name without commas, quotes or newlines, other than 'all' "
                         f"(paired.py's pooled row) and {CONDITIONS_TAG!r}, got {set_name!r}")
    path = Path(path)
    if not path.exists():
        return [], {}
    try:
        width, old, conditions = read_per_pair_csv(path)
    except ValueError as e:
        raise ValueError(f"{e}; refusing to overwrite it") from None
    pad = ["nan"] * (len(PER_PAIR_HEADER) - width)  # an older file's rows gain the pipeline's columns
    return [r + pad for r in old if r and r[0] != set_name], {k: v for k, v in conditions.items() if k != set_name}


def check_per_pair(path, set_name: str) -> None:
    """Raise ValueError now if ``write_per_pair(path, set_name, ...)`` would refuse later (a command checks
    this before a long evaluation)."""
    _per_pair_rows_kept(path, set_name)


def write_per_pair(path, set_name: str, rows) -> None:
    """Save per-pair results (``PairResult`` rows of one held-out set) as CSV, atomically; the file
    ``benchmarks/paired.py`` reads. Several sets may share a file (the ``set`` column tells them apart):
    ``rows`` are appended to the file's existing rows of other sets, and replace its rows of ``set_name``.
    Errors are written at full precision (a 14.99996 stays under 15, as the card counted it). Each set's
    ``measurement_conditions()`` at the time it is written close the file, one ``# conditions`` row per set."""
    import csv
    import io

    from pointmap.atomic import atomic_open

    rows = list(rows)
    for r in rows:
        if not isinstance(r, PairResult):
            raise ValueError(f"write_per_pair expected PairResult rows, got {type(r).__name__} {r!r}")
    kept, conditions = _per_pair_rows_kept(path, set_name)
    conditions[set_name] = measurement_conditions()
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(PER_PAIR_HEADER)
    w.writerows(kept)
    w.writerows([set_name, int(r.pair), *(repr(float(v)) for v in r[1:])] for r in rows)
    w.writerows([CONDITIONS_TAG, s, c] for s, c in conditions.items())
    with atomic_open(path, "w") as f:
        f.write(buf.getvalue())


def _pose_errors(est: torch.Tensor, gt: torch.Tensor) -> tuple[float, float]:
    """(rotation error, translation direction error) in degrees of a cam2world [4, 4] against the truth; a pose
    that was not found (any NaN) counts 180 for both."""
    if not bool(torch.isfinite(est).all()):
        return 180.0, 180.0
    return (float(relative_rotation_error_deg(est[:3, :3].double(), gt[:3, :3].double())),
            float(translation_angle_deg(est[:3, 3].double(), gt[:3, 3].double())))


def depth_rel_errors(pred_z: torch.Tensor, gt_z: torch.Tensor, valid: torch.Tensor) -> torch.Tensor | None:
    """|scale * pred - gt| / gt per valid pixel (float64, in ``valid``'s order) after the median scale alignment of
    ``_depth_scale`` (the prediction is scale-free); pixels predicted behind the camera count with their full
    relative error. Empty when no pixel is valid; None when no pixel is predicted in front (no scale)."""
    p, g = pred_z[valid].double(), gt_z[valid].double()
    if p.numel() == 0:
        return p
    scale = _depth_scale(p, g)
    if scale is None:
        return None
    return (p.clamp_min(0) * scale - g).abs() / g


def abs_rel(pred_z: torch.Tensor, gt_z: torch.Tensor, valid: torch.Tensor) -> float:
    """AbsRel of a depth map after median scale alignment (``depth_rel_errors``): NaN without valid pixels, 1
    when no pixel is predicted in front."""
    err = depth_rel_errors(pred_z, gt_z, valid)
    if err is None:
        return 1.0
    return float(err.mean()) if err.numel() else float("nan")


def confidence_order(conf: torch.Tensor, pred_z: torch.Tensor, gt_z: torch.Tensor, valid: torch.Tensor,
                     floor: float = AUTO_SPREAD_CONF) -> tuple[float, float]:
    """(share of the valid pixels whose confidence is ``floor`` or more, the AbsRel of the more confident half of
    the valid pixels divided by the AbsRel of all of them): the first says whether the confidence has left its
    floor of 1 (``pointmap.align.edges.AUTO_SPREAD_CONF``), the second whether it orders the errors (below 1:
    the confident half is the more accurate; 1 for a flat confidence). The half is the pixels at or above the
    median confidence (the lower middle value for an even count: n - (n - 1) // 2 pixels); pixels tied at the
    half's lowest confidence count at the share of them the half needs (the mean over the ways to break the tie),
    so a confidence left at its floor on just over half the pixels still ranks the rest (taking every tied pixel
    made such a "half" every pixel, and the ratio 1). One median scale alignment over all valid pixels
    (``depth_rel_errors``, as ``abs_rel``)."""
    c = conf[valid].double()
    if c.numel() == 0:
        return float("nan"), float("nan")
    spread = float((c >= floor).double().mean())
    err = depth_rel_errors(pred_z, gt_z, valid)
    if err is None:
        return spread, float("nan")
    m = c.numel() - (c.numel() - 1) // 2  # how many c >= c.median() selects when no two confidences are equal
    t = torch.sort(c, descending=True).values[m - 1]
    above, tied = c > t, c == t
    top = (err[above].sum() + (m - int(above.sum())) * err[tied].mean()) / m
    return spread, float(top / err.mean().clamp_min(1e-12))


def baseline_ratio(t_pred: torch.Tensor, pred_z: torch.Tensor, t_gt: torch.Tensor, gt_z: torch.Tensor,
                   valid: torch.Tensor, min_baseline: float = 0.01) -> float:
    """Length of the predicted baseline over the true one, after the median depth alignment of ``abs_rel`` (the
    prediction's units are its own): 1 is the right length, < 1 a camera placed too close to the first. NaN when
    the true baseline is under ``min_baseline`` of the median depth (no direction to get right) or the
    prediction has no usable depth or translation."""
    p, g = pred_z[valid].double(), gt_z[valid].double()
    scale = _depth_scale(p, g)
    if scale is None or not bool(torch.isfinite(t_pred).all()):
        return float("nan")
    if float(t_gt.double().norm()) < min_baseline * float(g.median()):
        return float("nan")
    return float(t_pred.double().norm() * scale / t_gt.double().norm())


def depth_ratio(pred_z1: torch.Tensor, gt_z1: torch.Tensor, valid1: torch.Tensor, pred_z2: torch.Tensor,
                gt_z2: torch.Tensor, valid2: torch.Tensor) -> float:
    """How much deeper one prediction places view 2's scene, relative to view 1's, than the truth has it: the
    median depth scale of view 1 (``abs_rel``'s true / predicted) over view 2's, both views' depths taken in
    their own camera frames from the same prediction. 1 is right; 1.2 puts view 2's scene 20% too far
    relative to view 1's. A camera's forward motion is the difference of the two views' depths, so an error
    here is an error in the translation's forward component of about ``|log ratio|`` x the depth
    (docs/models.md). NaN when either view has no valid pixel predicted in front."""
    scales = []
    for p, g, v in ((pred_z1, gt_z1, valid1), (pred_z2, gt_z2, valid2)):
        scale = _depth_scale(p[v].double(), g[v].double())
        if scale is None or not bool(torch.isfinite(scale)):
            return float("nan")
        scales.append(scale)
    return float(scales[0] / scales[1])


def forward_agreement(t_pred: torch.Tensor, t_gt: torch.Tensor, min_forward: float = 0.2) -> tuple[float, float]:
    """How well predicted translation directions [N, 3] get the forward (z) component of the true ones [N, 3]
    (camera 2's centre in camera 1's frame, any units): (Pearson correlation of the unit directions' z over the
    pairs with a finite prediction and a true baseline, share of pairs whose true direction has |z| >=
    ``min_forward`` with the predicted z of the same sign). A model that reads sideways motion but not depth
    change has a correlation near 0 and a sign share near 0.5 (docs/models.md, What limits it). NaN for what
    has no pair to count."""
    tp, tg = t_pred.double(), t_gt.double()
    ok = torch.isfinite(tp).all(-1) & (tp.norm(dim=-1) > 0) & (tg.norm(dim=-1) > 0)
    zp = (tp[ok] / tp[ok].norm(dim=-1, keepdim=True))[:, 2]
    zg = (tg[ok] / tg[ok].norm(dim=-1, keepdim=True))[:, 2]
    corr = float("nan")
    if len(zp) >= 3 and float(zp.std()) > 0 and float(zg.std()) > 0:
        corr = float(torch.corrcoef(torch.stack([zp, zg]))[0, 1])
    clear = zg.abs() >= min_forward
    sign = float("nan")
    if bool(clear.any()):
        sign = float((torch.sign(zp[clear]) == torch.sign(zg[clear])).double().mean())
    return corr, sign


def rra_by_angle(rot_err: torch.Tensor, angle_gt: torch.Tensor) -> tuple[float, float]:
    """RRA@15 (%) over the pairs whose cameras are rotated less than 30 degrees apart, and over those rotated 45
    degrees or more (``rot_err`` and ``angle_gt`` [N], degrees); NaN for a group without pairs. The held-out sets
    hold 30-36% of pairs at 45 degrees or more (``python -m data.stats``), where rotation is hardest."""
    if rot_err.shape != angle_gt.shape:
        raise ValueError(f"rot_err and angle_gt expected the same shape, got {list(rot_err.shape)} and "
                         f"{list(angle_gt.shape)}")
    out = []
    for group in (angle_gt < 30, angle_gt >= 45):
        out.append(float((rot_err[group] < 15).double().mean() * 100) if group.any() else math.nan)
    return out[0], out[1]


def focal_error(pts_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """[B] relative error |f / f_true - 1| of the focal recovered from camera-frame pointmaps [B, H, W, 3] (a view's
    pointmap in its own frame; ``pointmap.geometry.focal_from_pointmap``, the estimate ``pointmap demo`` and the
    global aligner start from) against the true intrinsics K [B, 3, 3] (fx). 0.25: 25% too long or too short."""
    if pts_cam.ndim != 4 or pts_cam.shape[-1] != 3 or K.shape != (pts_cam.shape[0], 3, 3):
        raise ValueError(f"pts_cam [B, H, W, 3] and K [B, 3, 3] expected, got {list(pts_cam.shape)} and "
                         f"{list(K.shape)}")
    return _focal_rel_error(focal_from_pointmap(pts_cam.float()), K[:, 0, 0])


def _focal_rel_error(f: torch.Tensor, f_true: torch.Tensor) -> torch.Tensor:
    """|f / f_true - 1|, float64; no estimate (NaN) counts as a 100% error."""
    return (f.double().nan_to_num(0.0) / f_true.double() - 1).abs()


def focal_slope(f_est, f_true) -> float:
    """Least-squares slope of log(estimated focal) on log(true focal) over views (sequences of pixels): 1 when the
    estimates follow the truth (or a constant factor of it), 0 when they are one focal whatever the image (session
    55: v54h 0.07-0.17). Views without a positive finite estimate are left out; NaN when fewer than two remain or
    the true focals are all equal."""
    e, t = torch.as_tensor(f_est, dtype=torch.float64), torch.as_tensor(f_true, dtype=torch.float64)
    if e.shape != t.shape or e.ndim != 1:
        raise ValueError(f"f_est and f_true expected two [N] sequences, got {list(e.shape)} and {list(t.shape)}")
    ok = torch.isfinite(e) & (e > 0) & torch.isfinite(t) & (t > 0)
    x, y = t[ok].log(), e[ok].log()
    if len(x) < 2 or float((x - x.mean()).square().sum()) == 0:
        return float("nan")
    return float(((x - x.mean()) * (y - y.mean())).sum() / (x - x.mean()).square().sum())


def match_precision(pred, corr: torch.Tensor, tol: float = 3.0) -> float:
    """Fraction of reciprocal matches whose view-2 pixel is within ``tol`` px of the GT correspondence
    (only matches whose view-1 pixel has a GT correspondence count). A pair without any
    match scores 0 (it found nothing right); NaN only when it cannot be judged (no descriptors, or no match
    lands where the ground truth has a correspondence)."""
    if not pred.has_desc:
        return float("nan")
    m = match(pred)
    if len(m) == 0:
        return 0.0
    u, v = m.xy1[:, 0].long(), m.xy1[:, 1].long()
    gt = corr[v, u]
    ok = torch.isfinite(gt).all(-1)
    if ok.sum() == 0:
        return float("nan")
    err = (gt[ok] - m.xy2[ok]).norm(dim=-1)
    return float((err < tol).float().mean())


def _median(values) -> float:
    """The median of ``values`` (a list or tensor), NaN left out, the mean of the two middle values for an even
    count (torch's median takes the lower one); NaN when nothing is left."""
    import numpy as np

    x = np.asarray(torch.as_tensor(values, dtype=torch.float64).reshape(-1))
    x = x[~np.isnan(x)]
    return float(np.median(x)) if x.size else float("nan")


def within_pair_auc(scores: list, labels: list) -> float:
    """The mean over pairs of ``score_auc`` of each pair's ``scores`` and ``labels`` (pairs with right and wrong
    matches only): how well the score ranks one pair's matches, whatever it says about pairs against each other."""
    aucs = [a for a in (score_auc(s, y) for s, y in zip(scores, labels)) if not math.isnan(a)]
    return sum(aucs) / len(aucs) if aucs else float("nan")


def coarse_match_labels(m, corr: torch.Tensor, valid: torch.Tensor, tol: float) -> torch.Tensor:
    """[M] labels of the matches ``m`` (xy1 in view 1's pixels) against view 1's ground truth: 1.0 where the true
    correspondence of xy1 is within ``tol`` px of xy2, 0.0 where it is farther or where xy1 has valid depth but no
    correspondence (a cell view 2 does not see), NaN where xy1 has no valid depth (cannot be judged)."""
    u, v = m.xy1[:, 0].long(), m.xy1[:, 1].long()
    gt = corr[v, u].float()
    seen = torch.isfinite(gt).all(-1)
    err = (gt - m.xy2.float()).norm(dim=-1)
    lab = torch.where(seen & (err < tol), 1.0, 0.0)
    return torch.where(seen | valid[v, u].bool(), lab, torch.full_like(lab, float("nan")))


def score_auc(scores, labels) -> float:
    """Area under the ROC curve of ``scores`` separating labels 1 from labels 0 (NaN labels left out): the chance
    that a random right match scores above a random wrong one, ties counting half (Mann-Whitney). 0.5 is a score
    that carries no information; NaN without both kinds."""
    s, y = torch.as_tensor(scores, dtype=torch.float64).reshape(-1), torch.as_tensor(labels, dtype=torch.float64).reshape(-1)
    if s.shape != y.shape:
        raise ValueError(f"score_auc expected scores and labels of one length, got {s.numel()} and {y.numel()}")
    keep = torch.isfinite(y) & torch.isfinite(s)
    s, y = s[keep], y[keep]
    n1, n0 = int((y == 1).sum()), int((y == 0).sum())
    if n1 + n0 != len(y):
        raise ValueError("score_auc expected labels 0, 1 or NaN")
    if n1 == 0 or n0 == 0:
        return float("nan")
    _, inv, counts = torch.unique(s, return_inverse=True, return_counts=True)
    first = torch.cumsum(counts, 0) - counts  # ranks 1..n, tied values sharing their mean rank
    ranks = (first.double() + (counts.double() + 1) / 2)[inv]
    return float((ranks[y == 1].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def weights_device(model) -> torch.device:
    """The device a torch model's weights are on (a DDP wrapper's or a compiled model's too); the CPU for a model
    without parameters (an ONNX session's wrapper)."""
    params = getattr(model, "parameters", None)
    p = next(params(), None) if callable(params) else None
    return p.device if p is not None else torch.device("cpu")


@torch.inference_mode()
def evaluate_pairs(model, dataset, n_pairs: int = 64, batch_size: int = 8, per_pair: list | None = None) -> dict:
    """Metrics over the first ``n_pairs`` items of a held-out PairDataset (both orders inferred).
    ``per_pair`` (a list) given: one ``PairResult`` per pair is appended to it, in dataset order (the rows
    ``write_per_pair`` saves and ``benchmarks/paired.py`` compares between two models).
    ``baseline_ratio``: median of ``baseline_ratio`` (< 1: camera 2 placed too close to camera 1);
    ``depth_ratio_err``: median over pairs of |log ``depth_ratio``|, view 2's depth in its own frame taken
    from the forward pass's ``pts2_cam1`` through the estimated pose (0: the two views' depths agree in
    scale); ``coarse_acc``: top-1 accuracy of the patch-level matching (``losses.patch_matching_loss``),
    chance is 1 / patches;
    ``conf_spread`` / ``conf_order``: mean / median over pairs of ``confidence_order`` (view 1);
    ``focal_err``: median over both views of ``focal_error`` (each view's focal from its own-frame pointmap);
    ``focal_slope``: ``focal_slope`` of those focals against the true ones (1: they follow the image);
    ``fwd_corr``/``fwd_sign``: ``forward_agreement`` of the estimated translation directions (the forward
    component, which per-view focal lengths had hidden from training);
    ``match_score_auc``: ``score_auc`` of the coarse matches' scores (the descriptor confidence) for right (true
    correspondence within half a patch) against wrong ones (farther, or a cell view 2 does not see), pooled over
    the pairs: 0.5 when the score says nothing about a match; ``match_score_auc_within``: the mean over pairs of
    each pair's own AUC (pairs with right and wrong matches): whether the score ranks the matches of one pair, what
    a filter of matches needs (a pooled AUC also rises when the score merely tells easy pairs from hard ones);
    ``RRA15_matches``/``RTA15_matches``: pose from the model's own matches (``match_coarse``) lifted by view 1's
    pointmap, PnP with the true K (MASt3R-style; models with descriptors); ``RRA15_refined``/``RTA15_refined``: the
    model's pose refined on the same matches with the true K (``pointmap.pose.refine_pose_with_matches``; a pair
    whose matches give no direction keeps the model's pose); ``RRA15_pair``/``RTA15_pair``: the pose the pipeline
    reports (``pointmap.pose.pair_pose``: the same refinement with each view's focal from its own pointmap, no K)."""
    rot_err, tr_err, rels, precs, coarse, ratios, dratios = [], [], [], [], [], [], []
    spreads, orders = [], []  # confidence_order of view 1's confidence (forward pass)
    t_pred, t_true = [], []  # camera 2's centre in camera 1's frame, estimated and true (forward_agreement)
    angle_gt = []  # the true rotation between the two cameras, degrees (RRA15_under30 / RRA15_over45)
    rot_m, tr_m = [], []  # pose from the model's matches (match_coarse) + PnP with the true K
    rot_r, tr_r = [], []  # the model's pose refined on its matches (true K)
    m_scores, m_labels = [], []  # coarse matches' scores and right/wrong labels (match_score_auc)
    rot_p, tr_p = {}, {}  # pair_pose: refined on its matches with its own focals (what the pipeline reports), by index
    order = []  # the dataset index of each entry of rot_err / tr_err / angle_gt (batches regroup by shape)
    focal_errs = []  # each view's focal from its own-frame pointmap (forward pass: view 1, reverse: view 2)
    focal_est, focal_true = [], []  # the same focals and the true ones (focal_slope)
    n = min(n_pairs, len(dataset))
    dev = weights_device(model)
    for s in range(0, n, batch_size):
        groups: dict = {}
        for k in range(s, min(s + batch_size, n)):  # batch items of equal shapes together
            it = dataset[k]
            key = (tuple(it[0]["img"].shape), tuple(it[1]["img"].shape))
            groups.setdefault(key, []).append((k, it))
        for group in groups.values():
            order += [k for k, _ in group]
            its = [it for _, it in group]
            v1 = {k: torch.stack([it[0][k] for it in its]) for k in ("img", "K", "cam2world", "depth_z", "valid", "corr")}
            v2 = {k: torch.stack([it[1][k] for it in its]) for k in ("img", "K", "cam2world", "depth_z", "valid")}
            # the model where its weights are (a GPU run's evaluation), the metrics on the CPU beside the truth
            pred = model(v1["img"].to(dev), v2["img"].to(dev)).to("cpu")
            pred_rev = model(v2["img"].to(dev), v1["img"].to(dev)).to("cpu")
            cam2world_pred = relative_pose(pred, pred_reverse=pred_rev)
            cam2world_gt = invert_rigid(v1["cam2world"].double()) @ v2["cam2world"].double()
            ok = torch.isfinite(cam2world_pred).all(-1).all(-1)
            re = relative_rotation_error_deg(cam2world_pred[..., :3, :3].double(), cam2world_gt[..., :3, :3])
            te = translation_angle_deg(cam2world_pred[..., :3, 3].double(), cam2world_gt[..., :3, 3])
            # view 2's depth in its own frame, through the estimated pose (depth_ratio)
            own2_z = transform_points(invert_rigid(cam2world_pred.double()), pred.pts2_cam1.double())[..., 2]
            for own, v in ((pred, v1), (pred_rev, v2)):  # each view's focal once (focal_error's estimate)
                f = focal_from_prediction(own)  # the focal the pipeline uses (a focal head's, if any)
                focal_errs += _focal_rel_error(f, v["K"][:, 0, 0]).tolist()
                focal_est += f.tolist()
                focal_true += v["K"][:, 0, 0].tolist()
            angle_gt += torch.rad2deg(rotation_angle(cam2world_gt[..., :3, :3])).tolist()
            t_pred.append(cam2world_pred[..., :3, 3].double())
            t_true.append(cam2world_gt[..., :3, 3])
            rot_err += torch.where(ok, re, torch.full_like(re, 180.0)).tolist()
            tr_err += torch.where(ok, te, torch.full_like(te, 180.0)).tolist()
            for b in range(len(its)):
                rels.append(abs_rel(pred.pts1_cam1[b, ..., 2], v1["depth_z"][b], v1["valid"][b]))
                sp, co = confidence_order(pred.conf1[b], pred.pts1_cam1[b, ..., 2], v1["depth_z"][b], v1["valid"][b])
                spreads.append(sp)
                orders.append(co)
                ratios.append(baseline_ratio(cam2world_pred[b, :3, 3], pred.pts1_cam1[b, ..., 2],
                                             cam2world_gt[b, :3, 3], v1["depth_z"][b], v1["valid"][b]))
                dr = depth_ratio(pred.pts1_cam1[b, ..., 2], v1["depth_z"][b], v1["valid"][b], own2_z[b],
                                 v2["depth_z"][b], v2["valid"][b])
                if math.isfinite(dr) and dr > 0:
                    dratios.append(abs(math.log(dr)))
                p = match_precision(pred[b], v1["corr"][b])
                if not math.isnan(p):  # a pair without matches counts, as 0
                    precs.append(p)
            if pred.has_desc:
                patch = getattr(model, "module", model).cfg.patch_size
                for b in range(len(its)):  # pairs without >= 4 co-visible cells are left out (NaN)
                    acc = patch_matching_loss(pred.desc1[b:b + 1], pred.desc2[b:b + 1], v1["corr"][b:b + 1], patch)[1]
                    if not math.isnan(acc):
                        coarse.append(acc)
                    m = match_coarse(pred[b], patch)
                    m_scores.append(m.score.float())
                    m_labels.append(coarse_match_labels(m, v1["corr"][b], v1["valid"][b], patch / 2))
                    est = relative_pose(pred[b], K2=v2["K"][b].double(), matches=[m])[0]
                    r, t = _pose_errors(est, cam2world_gt[b])
                    rot_m.append(r)
                    tr_m.append(t)
                    refined = refine_pose_with_matches(cam2world_pred[b], m, v1["K"][b], v2["K"][b])
                    r, t = _pose_errors(refined, cam2world_gt[b])
                    rot_r.append(r)
                    tr_r.append(t)
                    r, t = _pose_errors(pair_pose(pred[b], pred_rev[b], patch=patch, pose=cam2world_pred[b:b + 1], matches=[m])[0], cam2world_gt[b])
                    rot_p[group[b][0]], tr_p[group[b][0]] = r, t
    if per_pair is not None:
        nan = float("nan")
        per_pair += sorted(PairResult(k, r, t, a, rot_p.get(k, nan), tr_p.get(k, nan))
                           for k, r, t, a in zip(order, rot_err, tr_err, angle_gt))
    rot, tr = torch.tensor(rot_err, dtype=torch.float64), torch.tensor(tr_err, dtype=torch.float64)  # as the per-pair file
    rels_t = torch.tensor([r for r in rels if not math.isnan(r)])
    ratios_t = torch.tensor([r for r in ratios if not math.isnan(r)])
    fwd_corr, fwd_sign = forward_agreement(torch.cat(t_pred), torch.cat(t_true)) if t_pred else (math.nan,) * 2
    under30, over45 = rra_by_angle(rot, torch.tensor(angle_gt, dtype=torch.float64))
    return {"RRA15": float((rot < 15).float().mean() * 100), "RTA15": float((tr < 15).float().mean() * 100),
            "rot_err_med": _median(rot), "trans_err_med": _median(tr),
            "AbsRel": float(rels_t.mean()) if rels_t.numel() else float("nan"),
            "baseline_ratio": _median(ratios_t),
            "depth_ratio_err": _median(dratios),
            "fwd_corr": fwd_corr, "fwd_sign": fwd_sign, "RRA15_under30": under30, "RRA15_over45": over45,
            "focal_err": _median(focal_errs),
            "focal_slope": focal_slope(focal_est, focal_true) if focal_est else float("nan"),
            "match_prec": float(torch.tensor(precs).mean()) if precs else float("nan"),
            "coarse_acc": sum(coarse) / len(coarse) if coarse else float("nan"),
            "match_score_auc": score_auc(torch.cat(m_scores), torch.cat(m_labels)) if m_scores else float("nan"),
            "match_score_auc_within": within_pair_auc(m_scores, m_labels),
            "conf_spread": float(torch.tensor(spreads).nanmean()) if spreads else float("nan"),
            "conf_order": _median(orders),
            **({"RRA15_matches": 100 * sum(r < 15 for r in rot_m) / len(rot_m),
                "RTA15_matches": 100 * sum(t < 15 for t in tr_m) / len(tr_m),
                "RRA15_refined": 100 * sum(r < 15 for r in rot_r) / len(rot_r),
                "RTA15_refined": 100 * sum(t < 15 for t in tr_r) / len(tr_r),
                "RRA15_pair": 100 * sum(r < 15 for r in rot_p.values()) / len(rot_p),
                "RTA15_pair": 100 * sum(t < 15 for t in tr_p.values()) / len(tr_p)} if rot_m else {}),
            "pairs": float(len(rot))}


SOURCE_ROWS = ("model matches + model depth", "model matches + true depth", "true matches + model depth",
               "true matches + true depth", "model matches, essential matrix (no depth)")
# pm.pair_pose (what `pointmap pair`, the demo and the card report) fed each combination of matches and intrinsics
PIPELINE_ROWS = ("pipeline: model matches + model focals", "pipeline: true matches + model focals",
                 "pipeline: model matches + true intrinsics", "pipeline: true matches + true intrinsics")


@torch.inference_mode()
def pose_error_sources(model, dataset, n_pairs: int = 64, n_true: int = 300, seed: int = 0,
                       pipeline: bool = True) -> dict:
    """Where the two-view pose error comes from. The pose of view 2 by PnP-RANSAC with its true K, from each
    combination of correspondences (the model's ``match_coarse``, or ``n_true`` true ones drawn per pair from the
    ground-truth correspondences) and view-1 geometry (the model's own pointmap, or the true depth
    unprojected with the true K), plus the model's matches through the essential matrix (true K1, K2; no depth).
    With ``pipeline`` (default), also the pose the pipeline reports (``pair_pose``: ``relative_pose`` of both
    passes, refined on matches) fed the model's or the same true matches, with each view's focal from its own
    pointmap or both true intrinsics (``PIPELINE_ROWS``; one more forward pass per pair, the reverse one): how far
    better matches, or a better focal, would take the reported pose.
    Returns {row of ``SOURCE_ROWS`` (+ ``PIPELINE_ROWS``): {"RRA15", "RTA15", "rot_err_med", "trans_err_med",
    "pairs"}} over the first ``n_pairs`` pairs (pairs with fewer than 20 true correspondences left out); a failed
    pose counts 180 deg. "true matches + true depth" is the check of the method itself (~100 %)."""
    from dataclasses import replace

    import numpy as np

    from pointmap.geometry import depth_to_points_cam
    from pointmap.matching import Matches
    from pointmap.pose import pose_from_essential

    cfg = getattr(getattr(model, "module", model), "cfg", None)
    if cfg is None or not cfg.desc_dim:
        raise ValueError("pose_error_sources needs a model with a descriptor head (its matches are one source), "
                         f"got {'no model config' if cfg is None else 'desc_dim 0'}")
    patch = cfg.patch_size
    errs: dict = {k: [] for k in SOURCE_ROWS + (PIPELINE_ROWS if pipeline else ())}
    for i in range(min(n_pairs, len(dataset))):
        a, b = dataset[i]
        corr = a["corr"]
        v, u = torch.isfinite(corr).all(-1).nonzero(as_tuple=True)
        if len(v) < 20:
            continue
        pick = torch.from_numpy(np.random.default_rng(seed + i).choice(len(v), min(n_true, len(v)), replace=False))
        xy1 = torch.stack([u[pick], v[pick]], -1).float()
        true_m = Matches(xy1, corr[v[pick], u[pick]].float(), torch.ones(len(pick)))
        pred = model(a["img"][None], b["img"][None])
        model_m = match_coarse(pred, patch)
        true_pts = depth_to_points_cam(a["depth_z"].double(), a["K"].double()).float()
        true_pts[~a["valid"]] = float("nan")
        with_true = replace(pred, pts1_cam1=true_pts[None])
        gt = invert_rigid(a["cam2world"].double()) @ b["cam2world"].double()
        K2 = b["K"].double()
        ests = [relative_pose(pr, K2=K2, matches=[m])[0] for pr, m in
                ((pred, model_m), (with_true, model_m), (pred, true_m), (with_true, true_m))]
        e = pose_from_essential(model_m.xy1.numpy(), model_m.xy2.numpy(), a["K"].double().numpy(), K2.numpy(),
                                threshold_px=0.02 * max(a["img"].shape[-2:]))  # cell-quantised matches: loose
        ests.append(torch.full((4, 4), float("nan")) if e is None else torch.from_numpy(e))
        if pipeline:
            rev = model(b["img"][None], a["img"][None])
            pose = relative_pose(pred, pred_reverse=rev)  # the pointmaps' pose, once for the four rows
            Ks = {"K1": a["K"].double(), "K2": K2}
            ests += [pair_pose(pred, rev, patch=patch, pose=pose, matches=[m], **kw)[0]
                     for m, kw in ((model_m, {}), (true_m, {}), (model_m, Ks), (true_m, Ks))]
        for name, est in zip(errs, ests):
            errs[name].append(_pose_errors(est, gt))
    out = {}
    for name, v in errs.items():
        t = torch.tensor(v, dtype=torch.float64).reshape(-1, 2)
        if len(t) == 0:
            continue
        out[name] = {"RRA15": float((t[:, 0] < 15).double().mean() * 100),
                     "RTA15": float((t[:, 1] < 15).double().mean() * 100),
                     "rot_err_med": _median(t[:, 0]), "trans_err_med": _median(t[:, 1]),
                     "pairs": len(t)}
    return out


def main(argv=None) -> int:
    """``python -m training.evaluate --model M --data HELDOUT [--size S] [--pairs N]``: the held-out metrics of
    a training checkpoint (``.pt``) or of model weights (a name or a file ``pm.load_model`` takes)."""
    import argparse
    import json
    import sys
    from pathlib import Path

    import pointmap as pm
    from pointmap.images import INPUT_SIZE_RULE, is_input_size
    from training.mix import open_pairs

    p = argparse.ArgumentParser(prog="python -m training.evaluate", description=main.__doc__)
    p.add_argument("--model", required=True)
    p.add_argument("--data", required=True, help="held-out shards (never trained on)")
    p.add_argument("--size", type=int, default=None,
                   help="input size, a multiple of 16 (default: the size the model was trained at)")
    p.add_argument("--pairs", type=int, default=139, help="the first N held-out pairs")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--sources", action="store_true",
                   help="also print where the pose error comes from (pose_error_sources: model vs true matches, "
                        "depth and intrinsics, for PnP and for the pipeline's pair_pose), a markdown table "
                        "before the JSON line")
    p.add_argument("--per-pair", type=Path, default=None, metavar="CSV",
                   help="also save each pair's rotation / direction error to this CSV (its rows for this set "
                        "replaced, other sets' kept), for benchmarks/paired.py")
    p.add_argument("--set", default=None, help="the set's name in --per-pair (default: the --data folder's name)")
    a = p.parse_args(argv)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    if a.pairs < 1:
        p.error(f"--pairs expected >= 1, got {a.pairs}")
    if a.size is not None and not is_input_size(a.size):
        p.error(f"--size expected {INPUT_SIZE_RULE}, got {a.size}")
    set_name = a.set or Path(a.data).resolve().name
    if a.per_pair is not None:
        if a.set is None and "," in a.data:
            p.error("--per-pair with several --data folders expected a --set name for their pairs together")
        try:
            check_per_pair(a.per_pair, set_name)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    try:
        if a.model.endswith(".pt"):  # a training checkpoint: architecture, weights and training size inside
            from pointmap.checkpoint import load_state_strict, official_to_ours
            from training.loop import load_checkpoint

            ck = load_checkpoint(Path(a.model))
            if ck.get("kind") != "train":
                raise pm.CheckpointError(f"{a.model} is a {ck.get('kind')!r} checkpoint; evaluate a 'train' one")
            missing = [k for k in ("model_config", "model", "train_config") if k not in ck]
            if missing:
                raise pm.CheckpointError(f"{a.model} is not a complete training checkpoint (missing {missing})")
            model = pm.PointmapNet(pm.ModelConfig.from_dict(ck["model_config"]))
            load_state_strict(model, official_to_ours(ck["model"]), source=a.model)
            size = a.size or int(ck["train_config"]["size"])
        else:
            model = pm.load_model(a.model)
            size = a.size or int((getattr(model, "provenance", None) or {}).get("image_size", 224))
        ds = open_pairs(a.data, size=size, augment=False, split="all")
    except (pm.PointmapError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.sources:
        try:
            src = pose_error_sources(model.eval(), ds, a.pairs)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print("| correspondences + view-1 geometry (PnP, true K), or what the pipeline (pair_pose) is fed | pairs | "
              "RRA@15 | RTA@15 | median rot err | median dir err |\n|---|---|---|---|---|---|")
        for name, r in src.items():
            print(f"| {name} | {r['pairs']} | {r['RRA15']:.1f}% | {r['RTA15']:.1f}% | {r['rot_err_med']:.1f} | "
                  f"{r['trans_err_med']:.1f} |")
    rows = []
    res = evaluate_pairs(model.eval(), ds, a.pairs, per_pair=rows)
    if a.per_pair is not None:
        try:
            write_per_pair(a.per_pair, set_name, rows)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    print(json.dumps({"model": a.model, "size": size, **{k: round(v, 4) for k, v in res.items()}}))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
