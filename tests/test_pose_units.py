"""Unit checks of pointmap.pose on the exact plane scene of test_pose_and_matching: the confidence mask, PnP's
inlier count and thresholds, the intrinsics each path reads, the two-pass and pose-head averages, the inputs each
correspondence solver drops or refuses, the refinement's settings and pair_pose's focals."""

import math

import numpy as np
import pytest
import torch

import pointmap as pm
import pointmap.pose as pose_mod
from pointmap.geometry import depth_to_points_cam, invert_rigid, transform_points
from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg
from pointmap.pose import _conf_mask, _pnp, _pnp_any_focal, focal_from_prediction
from tests.test_pose_and_matching import (
    H,
    K,
    W,
    _described,
    _perturbed_start,
    _scene_pixels,
    _with_head,
    as_pred,
    pose_errors,
    reverse_pass,
    true_matches,
    two_views,
)


def _with_conf(pred, conf1=None, conf2=None):
    return pm.PairPrediction(pred.pts1_cam1, pred.pts2_cam1, pred.conf1 if conf1 is None else conf1[None].float(),
                             pred.conf2 if conf2 is None else conf2[None].float())


# --- the confidence mask ---------------------------------------------------------------------------------------

def test_the_confidence_mask_keeps_exactly_the_most_confident_share_of_finite_pixels():
    conf = torch.arange(1.0, 101.0).reshape(10, 10)
    pts = torch.zeros(10, 10, 3)
    mask = _conf_mask(conf, pts, 0.3)
    assert int(mask.sum()) == 30 and bool(mask.view(-1)[70:].all())  # the 30 most confident, nothing else
    assert bool(_conf_mask(conf, pts, 1.0).all())
    conf_nan = conf.clone()
    conf_nan[9, 9] = float("nan")  # a NaN confidence is left out, it does not poison the quantile
    mask = _conf_mask(conf_nan, pts, 0.3)
    assert not bool(mask[9, 9]) and int(mask.sum()) == 30
    pts_nan = pts.clone()
    pts_nan[9, 8] = float("nan")
    assert not bool(_conf_mask(conf, pts_nan, 0.3)[9, 8])
    assert not bool(_conf_mask(conf, pts * float("nan"), 0.3).any())  # nothing finite: an empty mask, no error


def test_the_pnp_pose_is_found_through_nan_confidences_and_is_nan_for_a_pointmap_with_no_finite_point():
    p1, p2, _, _, gt = two_views()
    conf = torch.full((H, W), 2.0)
    conf[:5] = float("nan")
    est = pm.relative_pose(_with_conf(as_pred(p1, p2), conf2=conf), K2=K)[0]
    assert max(pose_errors(est, gt)) < 0.2
    blind = pm.relative_pose(as_pred(p1, p2 * float("nan")), K2=K)
    assert torch.isnan(blind).all()


def test_the_pnp_pose_reads_view_twos_confidence_not_view_ones():
    p1, p2, _, _, gt = two_views()
    wrong = p2.clone()
    wrong[: H // 2] = wrong[: H // 2] * 1.3  # the top half of view 2's pointmap 30% too deep ...
    low = torch.full((H, W), 3.0)
    low[: H // 2] = 1.0  # ... and known to be unsure: keep=0.5 leaves it out
    est = pm.relative_pose(_with_conf(as_pred(p1, wrong), conf1=torch.full((H, W), 2.0), conf2=low), K2=K,
                           keep=0.5)[0]
    assert max(pose_errors(est, gt)) < 0.2
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)


def test_keep_must_lie_in_zero_to_one_with_one_keeping_every_pixel():
    p1, p2, _, _, gt = two_views()
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(pm.ShapeError, match="keep expected in"):
            pm.relative_pose(as_pred(p1, p2), K2=K, keep=bad)
    assert max(pose_errors(pm.relative_pose(as_pred(p1, p2), K2=K, keep=1.0)[0], gt)) < 0.2


# --- PnP -------------------------------------------------------------------------------------------------------

def _cloud(n=20, depth=10.0, seed=0):
    pts = np.random.default_rng(seed).uniform(-3, 3, (n, 3)) + [0, 0, depth]
    Kn = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    return pts, pts[:, :2] / pts[:, 2:] * 100 + 50, Kn


def test_pnp_counts_as_inliers_the_points_within_the_pixel_threshold_whatever_the_scenes_units():
    pts, uv, Kn = _cloud(depth=10.0)  # points ~10 units away: a threshold read in those units would be 0.2 px
    offsets = np.tile([[0.8, -0.6], [-0.6, 0.8]], (10, 1))  # every pixel 1 px off: inside a 2 px threshold
    uv = uv + offsets
    uv[:5] += 25.0  # five far outliers
    c2w, n = _pnp(pts, uv, Kn, 200, 2.0)
    assert n == 15
    assert np.allclose(c2w[:3, :3], np.eye(3), atol=0.02)


def test_pnp_needs_six_points_and_solves_exactly_six():
    pts, uv, Kn = _cloud(n=6, depth=5.0, seed=1)
    c2w, n = _pnp(pts, uv, Kn, 100, 2.0)
    assert n == 6 and np.allclose(c2w, np.eye(4), atol=1e-5)
    assert _pnp(pts[:5], uv[:5], Kn, 100, 2.0) == (None, 0)


def test_pnp_with_an_unknown_focal_recovers_the_pose_of_exact_pointmaps_almost_exactly():
    p1, p2, _, _, gt = two_views()
    est = pm.relative_pose(as_pred(p1, p2))[0]  # dense, focal swept then refined by golden-section search
    r, t = pose_errors(est, gt)
    assert r < 0.02 and t < 0.1
    m = true_matches(p1, gt, outliers=0.3)  # matches with 30% outliers, focal unknown
    r, t = pose_errors(pm.relative_pose(as_pred(p1, torch.zeros_like(p1)), matches=[m])[0], gt)
    assert r < 0.02 and t < 0.1


def _spy(monkeypatch, name, result=None):
    calls = []

    def spy(*args, **kwargs):
        calls.append((args, kwargs))
        return result

    monkeypatch.setattr(pose_mod, name, spy)
    return calls


def test_the_pnp_inlier_threshold_is_a_share_of_the_long_side_and_never_below_two_pixels(monkeypatch):
    pts, uv, Kn = _cloud()
    calls = _spy(monkeypatch, "_pnp", (None, 0))
    _pnp_any_focal(pts, uv, Kn, 300, 1000)
    _pnp_any_focal(pts, uv, Kn, 1000, 300)
    _pnp_any_focal(pts, uv, Kn, 48, 64)
    _pnp_any_focal(pts, uv, Kn, 300, 1000, reproj_frac=0.04)
    assert [args[4] for args, _ in calls] == [10.0, 10.0, 2.0, 40.0]
    calls.clear()
    _pnp_any_focal(pts, uv, None, 100, 200)  # unknown focal: each swept K has its centre at the image's
    Ks = [args[2] for args, _ in calls]
    assert len(Ks) > 20 and all(k[0, 2] == 99.5 and k[1, 2] == 49.5 and k[0, 0] == k[1, 1] for k in Ks)


def test_the_matches_path_hands_pnp_view_ones_points_at_the_rounded_pixels_of_matches_inside_view_one(monkeypatch):
    p1, _, _, _, gt = two_views()
    m = true_matches(p1, gt, step=8)
    xy1, xy2 = m.xy1.clone(), m.xy2.clone()
    xy1[:, 0] += torch.where(torch.arange(len(xy1)) % 2 == 0, 0.4, -0.4)  # sub-pixel: rounded to the grid pixel
    xy1[0] = torch.tensor([-0.6, 5.0])  # rounds to -1: outside view 1
    xy1[1] = torch.tensor([W - 0.4, 5.0])  # rounds to W: outside
    xy1[2] = torch.tensor([5.0, -0.6])
    xy2[3] = float("nan")  # not finite
    calls = _spy(monkeypatch, "_pnp_any_focal")
    small2 = pm.PairPrediction(p1[None].float(), torch.zeros(1, 2 * H, 3 * W, 3), torch.ones(1, H, W),
                               torch.ones(1, 2 * H, 3 * W))  # view 2 of another size than view 1
    pm.relative_pose(small2, K2=K, matches=[pm.Matches(xy1, xy2, torch.ones(len(xy1)))])
    (pts, uv, K2, h2, w2), kw = calls[0]
    kept = torch.arange(4, len(xy1))
    assert np.allclose(pts, p1.float()[m.xy1[kept, 1].long(), m.xy1[kept, 0].long()].double().numpy())
    assert np.array_equal(uv, xy2[kept].double().numpy())
    assert np.array_equal(K2, K.numpy()) and (h2, w2) == (2 * H, 3 * W) and kw == {"reproj_frac": 0.04}


# --- the intrinsics and inputs of relative_pose -----------------------------------------------------------------

def test_each_pair_of_a_batch_is_solved_with_its_own_intrinsics_and_matches():
    p1, p2, _, _, gt = two_views()
    batch = pm.PairPrediction.cat([as_pred(p1, p2), as_pred(p1, p2)])
    K_other = K.clone()
    K_other[0, 0] = K_other[1, 1] = 75.0
    Ks = torch.stack([K, K_other])
    together = pm.relative_pose(batch, K2=Ks)
    assert max(pose_errors(together[0], gt)) < 0.2
    assert torch.equal(together[1], pm.relative_pose(batch[1], K2=K_other)[0])
    assert max(pose_errors(together[1], gt)) > 1  # the other focal, another pose: not the first pair's
    m = true_matches(p1, gt)
    by_matches = pm.relative_pose(batch, K2=Ks, matches=[m, m])
    assert torch.allclose(by_matches[1], pm.relative_pose(batch[1], K2=K_other, matches=[m])[0], atol=1e-5)
    assert max(pose_errors(by_matches[1], gt)) > 1


def test_the_seed_chooses_the_pnp_subsample_of_a_large_pointmap():
    p1, p2, *_ = two_views()
    g = torch.Generator().manual_seed(1)
    big = [torch.nn.functional.interpolate(p.permute(2, 0, 1)[None], scale_factor=2, mode="bilinear")[0]
           .permute(1, 2, 0) for p in (p1, p2)]  # 6,144 pixels: 4,000 are drawn
    big = [p + 0.01 * torch.randn(p.shape, generator=g, dtype=p.dtype) for p in big]
    pred = pm.PairPrediction(big[0][None].float(), big[1][None].float(), torch.ones(1, 2 * H, 2 * W),
                             torch.ones(1, 2 * H, 2 * W))
    K_big = torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=K.dtype)) @ K
    a, b = (pm.relative_pose(pred, K2=K_big, seed=s) for s in (0, 1))
    assert torch.equal(a, pm.relative_pose(pred, K2=K_big, seed=0)) and not torch.equal(a, b)
    for bad in (-1, 1.5, "0"):
        with pytest.raises(pm.ShapeError, match="seed expected"):
            pm.relative_pose(pred, K2=K_big, seed=bad)


def test_relative_pose_refuses_a_reverse_prediction_of_another_batch_or_size_and_matches_beside_it():
    p1, p2, _, d2, gt = two_views()
    fwd, rev = as_pred(p1, p2), reverse_pass(p1, d2, gt)
    with pytest.raises(pm.ShapeError, match="pred_reverse batch size 2 differs from pred's 1"):
        pm.relative_pose(fwd, pred_reverse=pm.PairPrediction.cat([rev, rev]))
    with pytest.raises(pm.ShapeError, match="and no pred_reverse"):
        pm.relative_pose(fwd, pred_reverse=rev, matches=[true_matches(p1, gt)])
    cropped = pm.PairPrediction(rev.pts1_cam1[:, :, :32], rev.pts2_cam1, rev.conf1[:, :, :32], rev.conf2)
    with pytest.raises(pm.ShapeError, match="pred_reverse's pointmaps"):
        pm.relative_pose(fwd, pred_reverse=cropped)


# --- the two-pass pose -------------------------------------------------------------------------------------------

def test_the_two_pass_pose_leaves_out_pixels_either_pass_is_unsure_of():
    p1, p2, _, d2, gt = two_views()
    rev = reverse_pass(p1, d2, gt)
    warped = rev.pts1_cam1.clone()
    warped[:, : H // 5] *= 1.5  # the top rows of the reverse pass's own view 2 are wrong ...
    unsure = torch.full((H, W), 2.0)
    unsure[: H // 5] = 1.0  # ... and that pass says so (its view-1 confidence, of view 2's pixels)
    bad_rev = pm.PairPrediction(warped, rev.pts2_cam1, unsure[None], rev.conf2)
    est = pm.relative_pose(as_pred(p1, p2), pred_reverse=bad_rev)[0]
    r, t = pose_errors(est, gt)
    assert r < 1e-3 and t < 1e-2
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)


def test_the_two_pass_pose_from_one_direction_alone_keeps_the_full_baseline():
    p1, p2, _, d2, gt = two_views()
    rev = reverse_pass(p1, d2, gt)
    blind = as_pred(p1 * float("nan"), p2)  # view 1's own pointmap unusable: the reverse direction is dropped
    est = pm.relative_pose(blind, pred_reverse=rev)[0]
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)


def test_the_two_pass_pose_leaves_out_pixels_without_a_finite_own_frame_point():
    p1, p2, _, d2, gt = two_views()
    rev = reverse_pass(p1, d2, gt)
    holes1, holes2 = p1.clone(), rev.pts1_cam1[0].clone()
    holes1[3:6, 10:20] = float("nan")
    holes2[30:33, 5:9] = float("inf")
    est = pm.relative_pose(as_pred(holes1, p2), pred_reverse=as_pred(holes2, rev.pts2_cam1[0]))[0]
    r, t = pose_errors(est, gt)
    assert r < 1e-3 and t < 1e-2
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)


def test_the_reverse_pose_heads_translation_is_brought_to_the_forward_units_before_averaging():
    p1, p2, _, d2, gt = two_views()
    rev = reverse_pass(p1, d2, gt, scale=0.5)
    other = gt.clone()
    other[:3, 3] = torch.tensor([0.1, 0.5, 0.3], dtype=torch.float64)  # the reverse head sees another direction
    rev_T = invert_rigid(other)
    rev_T[:3, 3] *= 0.5  # in the reverse pass's units
    fwd = _with_head(as_pred(p1, p2), gt)
    est = pm.relative_pose(fwd, pred_reverse=_with_head(rev, rev_T))[0].double()
    # the rule: the reverse head inverted, its translation times mean |view 1's own points| over mean |view 1's
    # points of the reverse pass moved back into camera 1|; the mean with the forward head gives the direction
    back = transform_points(invert_rigid(rev_T), rev.pts2_cam1[0].double())
    scale = p1.float().double().norm(dim=-1).mean() / back.norm(dim=-1).mean()
    assert abs(float(scale) - 2.0) < 0.5
    direction = gt[:3, 3] + invert_rigid(rev_T)[:3, 3] * scale
    assert float(translation_angle_deg(est[:3, 3], direction)) < 0.01
    assert float(relative_rotation_error_deg(est[:3, :3], gt[:3, :3])) < 1e-3


# --- the correspondence solvers -----------------------------------------------------------------------------------

def test_the_correspondence_solvers_drop_rows_with_a_nan_in_view_twos_pixels():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, _ = _scene_pixels(gt)
    holes = uv2.clone()
    holes[:40, 1] = float("nan")
    k1, k2 = K1.numpy(), K2.numpy()
    est = pm.pose_from_essential(uv1.numpy(), holes.numpy(), k1, k2)
    assert est is not None and max(pose_errors(torch.from_numpy(est), gt)) < 0.5
    t = pm.translation_from_matches(gt[:3, :3].numpy(), uv1.numpy(), holes.numpy(), k1, k2)
    assert t is not None and float(translation_angle_deg(torch.from_numpy(t), gt[:3, 3])) < 0.01


def test_the_translation_direction_reads_its_pixel_threshold_in_view_ones_pixels():
    # view 2 a narrow telephoto (focal 10x view 1's): every match 1 px off in view 1, a 3 px threshold keeps them all,
    # so the direction is the least-squares one over all matches (a threshold over view 2's focal would keep a few)
    _, _, _, _, gt = two_views(angle_deg=10.0, t=(0.2, -0.4, 0.5))
    uv1, uv2, K1, _, g = _scene_pixels(gt, n=120, seed=7)
    K2 = K1.clone()
    K2[0, 0] = K2[1, 1] = 5000.0
    X2 = transform_points(invert_rigid(gt), torch.cat([uv1, torch.ones(len(uv1), 1, dtype=torch.float64)], 1)
                          @ torch.linalg.inv(K1).T * 4.0)
    uv2 = ((X2 / X2[:, 2:]) @ K2.T)[:, :2]
    angle = torch.rand(len(uv1), generator=g, dtype=torch.float64) * 2 * math.pi
    noisy1 = uv1 + torch.stack([angle.cos(), angle.sin()], 1)
    R = gt[:3, :3].numpy()
    est = pm.translation_from_matches(R, noisy1.numpy(), uv2.numpy(), K1.numpy(), K2.numpy(), threshold_px=3.0)
    r1 = pose_mod._bearings(noisy1.numpy(), K1.numpy())
    r2 = pose_mod._bearings(uv2.numpy(), K2.numpy()) @ R.T
    A = np.cross(r2, r1)
    ref = np.linalg.svd(A / np.linalg.norm(A, axis=1, keepdims=True))[2][-1]  # all matches, sign from the truth
    ref = ref if ref @ gt[:3, 3].numpy() > 0 else -ref
    assert float(translation_angle_deg(torch.from_numpy(est), torch.from_numpy(ref))) < 1e-6


def test_the_translation_direction_refuses_a_probability_outside_zero_to_one_and_a_bad_seed():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, _ = _scene_pixels(gt)
    args = (gt[:3, :3].numpy(), uv1.numpy(), uv2.numpy(), K1.numpy(), K2.numpy())
    for prob in (0.0, 1.0, 1.5):
        with pytest.raises(pm.ShapeError, match="prob expected in"):
            pm.translation_from_matches(*args, prob=prob)
    with pytest.raises(pm.ShapeError, match="seed expected"):
        pm.translation_from_matches(*args, seed=-1)


def test_the_translation_direction_needs_five_inliers_and_a_pair_of_unrelated_pixels_has_two():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    _, _, K1, K2, g = _scene_pixels(gt)
    noise = torch.rand(12, 2, generator=g, dtype=torch.float64) * 600
    assert pm.translation_from_matches(gt[:3, :3].numpy(), noise[:6].numpy(), noise[6:].numpy(), K1.numpy(),
                                       K2.numpy(), threshold_px=0.01) is None


# --- the refinement ------------------------------------------------------------------------------------------------

def test_a_refined_pose_with_a_zero_baseline_gets_a_unit_one():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, _ = _scene_pixels(gt)
    still = gt.clone()
    still[:3, 3] = 0.0
    out = pm.refine_pose_with_matches(still, pm.Matches(uv1, uv2, torch.ones(len(uv1))), K1.numpy(), K2.numpy(),
                                      rotation_prior_deg=0)
    assert abs(float(out[:3, 3].norm()) - 1.0) < 1e-9
    assert float(translation_angle_deg(out[:3, 3], gt[:3, 3])) < 0.1


def test_the_rotation_prior_is_read_in_degrees():
    # a start 6 degrees off, exact matches: without a prior the rotation comes back exactly, a 1-degree prior holds it
    # a hundredth of a degree short (a prior of 1 radian would hold it a hundred times less)
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, _ = _scene_pixels(gt)
    m = pm.Matches(uv1, uv2, torch.ones(len(uv1)))
    start = _perturbed_start(gt, deg=6.0)
    free = pm.refine_pose_with_matches(start, m, K1.numpy(), K2.numpy(), threshold_px=2.0, rotation_prior_deg=math.inf)
    assert float(relative_rotation_error_deg(free[:3, :3], gt[:3, :3])) < 1e-4
    held = pm.refine_pose_with_matches(start, m, K1.numpy(), K2.numpy(), threshold_px=2.0, rotation_prior_deg=1.0)
    assert 0.008 < float(relative_rotation_error_deg(held[:3, :3], gt[:3, :3])) < 0.1


# --- focal_from_prediction and pair_pose -------------------------------------------------------------------------

def test_a_focal_heads_view_two_focal_is_returned_as_given_and_view_ones_missing_ones_come_from_the_pointmap():
    from pointmap.geometry.focal import focal_from_pointmap

    p1, p2, *_ = two_views()
    pts = (p1[None].float().expand(2, -1, -1, -1), p2[None].float().expand(2, -1, -1, -1), torch.ones(2, H, W),
           torch.ones(2, H, W))
    pred = pm.PairPrediction(*pts, focal1=torch.tensor([100.0, float("nan")]), focal2=torch.tensor([0.0, 130.0]))
    own = focal_from_pointmap(pts[0])
    assert torch.equal(focal_from_prediction(pred), torch.stack([torch.tensor(100.0), own[1]]))
    assert torch.equal(focal_from_prediction(pred, view=2), torch.tensor([0.0, 130.0]))
    for view in (0, 3, "1"):
        with pytest.raises(pm.ShapeError, match="view expected 1 or 2"):
            focal_from_prediction(pm.PairPrediction(*pts), view=view)


def test_the_pointmap_focal_leaves_out_pixels_of_zero_confidence():
    p1, p2, *_ = two_views()
    junk = p1.clone()
    junk[:, :20] = torch.tensor([5.0, -3.0, 0.2], dtype=junk.dtype)  # a masked-out band with garbage points
    conf = torch.ones(1, H, W)
    conf[:, :, :20] = 0.0
    pred = pm.PairPrediction(junk[None].float(), p2[None].float(), conf, torch.ones(1, H, W))
    assert abs(float(focal_from_prediction(pred)[0]) - 60.0) < 0.5


def _pair_with_view_two_focal(f2):
    """The described pair of test_pose_and_matching, with the reverse pass's own-frame view 2 as a camera of focal
    ``f2`` would see it (only the focal read from it changes)."""
    p1, p2, d1, d2, gt = two_views(angle_deg=10.0)
    K2 = K.clone()
    K2[0, 0] = K2[1, 1] = f2
    return _described(p1, p2, depth_to_points_cam(d2, K2), transform_points(invert_rigid(gt), p1), gt)


def test_pair_pose_refines_with_each_views_focal_from_its_own_pass_and_the_image_centre(monkeypatch):
    fwd, rev = _pair_with_view_two_focal(90.0)
    calls = _spy(monkeypatch, "refine_pose_with_matches", torch.eye(4))
    pm.pair_pose(fwd, rev, patch=8, threshold_px=5.0)
    (_, _, k1, k2), kw = calls[0]
    assert abs(k1[0, 0] - 60.0) < 0.1 and abs(k2[0, 0] - 90.0) < 0.1 and k1[0, 0] == k1[1, 1]
    assert (k1[0, 2], k1[1, 2], k2[0, 2], k2[1, 2]) == ((W - 1) / 2, (H - 1) / 2, (W - 1) / 2, (H - 1) / 2)
    assert kw == {"threshold_px": 5.0, "rotation_prior_deg": 3.0}  # a focal estimated: the 3-degree prior
    K_known = K.clone()
    K_known[0, 0] = K_known[1, 1] = 70.0
    calls.clear()
    pm.pair_pose(fwd, rev, K_known, patch=8)  # view 1 known, view 2 still estimated: still 3 degrees
    (_, _, k1, k2), kw = calls[0]
    assert np.array_equal(k1, K_known.numpy()) and abs(k2[0, 0] - 90.0) < 0.1 and kw["rotation_prior_deg"] == 3.0
    calls.clear()
    pm.pair_pose(fwd, rev, None, K_known, patch=8)
    (_, _, k1, k2), kw = calls[0]
    assert abs(k1[0, 0] - 60.0) < 0.1 and np.array_equal(k2, K_known.numpy()) and kw["rotation_prior_deg"] == 3.0


def test_pair_pose_keeps_the_pointmap_pose_of_a_pass_whose_focal_cannot_be_read():
    fwd, rev = _pair_with_view_two_focal(60.0)
    flat = pm.PairPrediction(torch.zeros_like(rev.pts1_cam1), rev.pts2_cam1, rev.conf1, rev.conf2, desc1=rev.desc1,
                             desc2=rev.desc2, desc_conf1=rev.desc_conf1, desc_conf2=rev.desc_conf2)
    assert bool(torch.isnan(focal_from_prediction(flat)).all())  # view 2's own pointmap at one point: no focal
    plain = pm.relative_pose(fwd, pred_reverse=flat)
    assert bool(torch.isfinite(plain).all())
    assert torch.equal(pm.pair_pose(fwd, flat, patch=8), plain)


def test_pair_pose_turns_a_refined_direction_that_points_away_from_the_pointmaps_side(monkeypatch):
    fwd, rev = _pair_with_view_two_focal(60.0)
    plain = pm.relative_pose(fwd, pred_reverse=rev)[0]
    flipped = plain.clone()
    flipped[:3, 3] = -flipped[:3, 3]
    _spy(monkeypatch, "refine_pose_with_matches", flipped)
    assert torch.allclose(pm.pair_pose(fwd, rev, patch=8)[0], plain)


def test_a_swept_focal_whose_pose_puts_the_points_behind_the_camera_scores_worst(monkeypatch):
    pts, uv, Kn = _cloud(depth=5.0)  # seen by the identity camera with focal 100, principal point (50, 50)
    behind = np.diag([-1.0, 1.0, -1.0, 1.0])  # turned half a turn about y: every point behind it

    def pnp(p, q, K, iters, reproj):  # long focals "find" the half-turned camera, which lands near the pixels' mirror
        return (behind, len(p)) if K[0, 0] > 150 else (np.eye(4), len(p))

    monkeypatch.setattr(pose_mod, "_pnp", pnp)
    assert np.array_equal(_pnp_any_focal(pts, uv - 50 + 49.5, None, 100, 100), np.eye(4))


def test_the_essential_matrix_pose_needs_five_correspondences_in_front_of_both_cameras():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    g = torch.Generator().manual_seed(2)
    X = torch.rand(12, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 3.0, 3.0]) + torch.tensor([-2.0, -1.5, 3.0])
    K1 = torch.tensor([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]], dtype=torch.float64)

    def pixels(X):  # the same pixels whether a point is in front of a camera or mirrored behind it
        X2 = transform_points(invert_rigid(gt), X)
        return ((X / X[:, 2:]) @ K1.T)[:, :2].numpy(), ((X2 / X2[:, 2:]) @ K1.T)[:, :2].numpy()

    k = K1.numpy()
    mostly_front = pm.pose_from_essential(*pixels(torch.cat([X[:8], -X[8:10]])), k, k)
    assert mostly_front is not None and max(pose_errors(torch.from_numpy(mostly_front), gt)) < 0.1
    assert pm.pose_from_essential(*pixels(torch.cat([X[:4], -X[4:8]])), k, k) is None  # 4 in front, 4 behind both
