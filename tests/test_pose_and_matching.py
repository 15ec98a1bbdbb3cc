"""Relative pose and matching on exact pointmaps of an analytic scene (a textured slanted plane)."""

import math
import re

import numpy as np
import pytest
import torch

import pointmap as pm
from pointmap.geometry import axis_angle_to_matrix, depth_to_points_cam, invert_rigid, transform_points
from pointmap.geometry.rotations import relative_rotation_error_deg, translation_angle_deg
from pointmap.matching import reciprocal_nn_bruteforce, reciprocal_nn_fast

H, W = 48, 64
K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)


def plane_depth(cam2world, n=(0.5, -0.3, 1.0), d=4.0):
    """z-depth of the plane n.X = d seen from a camera (world = camera 1)."""
    n = torch.tensor(n, dtype=torch.float64)
    n = n / n.norm()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    dirs = rays @ cam2world[:3, :3].T
    c = cam2world[:3, 3]
    return (d - n @ c) / (dirs @ n)


def two_views(angle_deg=12.0, t=(0.6, 0.1, 0.05)):
    c2w2 = torch.eye(4, dtype=torch.float64)
    c2w2[:3, :3] = axis_angle_to_matrix(torch.tensor([0.1, 1.0, 0.05], dtype=torch.float64) / math.sqrt(1.0125)
                                        * math.radians(angle_deg))
    c2w2[:3, 3] = torch.tensor(t, dtype=torch.float64)
    d1, d2 = plane_depth(torch.eye(4, dtype=torch.float64)), plane_depth(c2w2)
    p1 = depth_to_points_cam(d1, K)
    p2 = transform_points(c2w2, depth_to_points_cam(d2, K))
    return p1, p2, d1, d2, c2w2


def as_pred(p1, p2):
    return pm.PairPrediction(p1[None].float(), p2[None].float(), torch.ones(1, H, W) * 2, torch.ones(1, H, W) * 2)


def reverse_pass(p1, d2, gt, scale=0.5):
    """The exact reverse prediction (view 2, view 1) at another scale: view 2 in its own frame, view 1 in it."""
    return as_pred(depth_to_points_cam(d2, K) * scale, transform_points(invert_rigid(gt), p1) * scale)


def pose_errors(pred_c2w, gt_c2w):
    r = relative_rotation_error_deg(pred_c2w[:3, :3].double(), gt_c2w[:3, :3])
    t = translation_angle_deg(pred_c2w[:3, 3].double(), gt_c2w[:3, 3])
    return float(r), float(t)


def test_pnp_with_known_focal_recovers_the_relative_pose():
    p1, p2, _, _, gt = two_views()
    est = pm.relative_pose(as_pred(p1, p2), K2=K)[0]
    r, t = pose_errors(est, gt)
    assert r < 0.05 and t < 0.2
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)  # exact scale: points are metric here


@pytest.mark.parametrize("unit", [1e-6, 1e6])
def test_pnp_finds_the_same_pose_whatever_the_units_of_the_pointmap(unit):
    p1, p2, _, _, gt = two_views()
    est = pm.relative_pose(as_pred(p1 * unit, p2 * unit), K2=K)[0]
    r, t = pose_errors(est, gt)
    assert r < 0.05 and t < 0.2
    assert torch.allclose(est[:3, 3].double() / unit, gt[:3, 3], atol=1e-3)


def test_a_pairs_pnp_pose_is_the_same_alone_and_in_a_batch():
    # one generator for the whole batch drew each pair's 4,000-pixel subsample after the pairs before it: the second
    # pair's pose moved by degrees between the batch and alone
    g = torch.Generator().manual_seed(0)
    preds = []
    for angle in (8.0, 15.0):
        p1, p2, *_ = two_views(angle)
        # twice the size (points and K scaled together), so that more than 4,000 pixels are left to subsample
        big = [torch.nn.functional.interpolate(p.permute(2, 0, 1)[None], scale_factor=2, mode="bilinear")[0]
               .permute(1, 2, 0) for p in (p1, p2)]
        preds.append([p + 0.01 * torch.randn(p.shape, generator=g, dtype=p.dtype) for p in big])
    batch = pm.PairPrediction(torch.stack([a for a, _ in preds]).float(), torch.stack([b for _, b in preds]).float(),
                              torch.ones(2, 2 * H, 2 * W) * 2, torch.ones(2, 2 * H, 2 * W) * 2)
    K_big = torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=K.dtype)) @ K
    for K2 in (None, K_big[None].expand(2, 3, 3)):
        together = pm.relative_pose(batch, K2=K2)
        for b in range(2):
            alone = pm.relative_pose(batch[b], K2=None if K2 is None else K2[b:b + 1])[0]
            assert torch.equal(together[b], alone)


def test_pnp_with_unknown_focal_sweeps_focals_and_stays_close():
    p1, p2, _, _, gt = two_views()
    r, t = pose_errors(pm.relative_pose(as_pred(p1, p2))[0], gt)
    assert r < 3 and t < 10


def test_procrustes_on_the_reverse_prediction_recovers_the_pose_without_intrinsics():
    p1, p2, _, d2, gt = two_views()
    rev = reverse_pass(p1, d2, gt)  # at another scale on purpose
    est = pm.relative_pose(as_pred(p1, p2), pred_reverse=rev)[0]
    r, t = pose_errors(est, gt)
    assert r < 1e-3 and t < 1e-2
    assert torch.allclose(est[:3, 3].double(), gt[:3, 3], atol=1e-3)  # in the forward pass's (here metric) units


def test_the_two_pass_pose_averages_both_directions_and_its_rotation_inverts_the_swapped_calls():
    p1, p2, _, d2, gt = two_views()
    own2 = depth_to_points_cam(d2, K)
    err = torch.eye(4, dtype=torch.float64)  # the reverse pass sees view 1 turned 10 degrees too far
    err[:3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(10)], dtype=torch.float64))
    rev = as_pred(own2 * 0.5, transform_points(err @ invert_rigid(gt), p1) * 0.5)
    fwd = as_pred(p1, p2)
    est = pm.relative_pose(fwd, pred_reverse=rev)[0]
    assert abs(pose_errors(est, gt)[0] - 5.0) < 0.05  # exact one way, 10 degrees off the other: the mean is 5 off
    swapped = pm.relative_pose(rev, pred_reverse=fwd)[0].double()
    back = invert_rigid(swapped)
    assert relative_rotation_error_deg(back[:3, :3], est[:3, :3].double()) < 1e-3
    # translations: the same two centre estimates, averaged in camera 1's or camera 2's frame
    assert translation_angle_deg(back[:3, 3], est[:3, 3].double()) < 0.5
    # one way unusable (no finite own-frame points): the other alone, exact here
    blind = as_pred(p1 * float("nan"), p2)
    one = pm.relative_pose(blind, pred_reverse=reverse_pass(p1, d2, gt))[0]
    r, t = pose_errors(one, gt)
    assert r < 1e-3 and t < 1e-2


def _with_head(pred, T):
    from dataclasses import replace

    return replace(pred, cam2_to_cam1=T[None].float())


def test_a_pose_heads_transforms_of_both_passes_are_the_pose_and_not_the_procrustes_of_their_points():
    p1, p2, _, d2, gt = two_views()
    own2 = depth_to_points_cam(d2, K)
    # the reverse pass's own-frame view 2 is 8% deeper at the top than the forward pass's: a disagreement that
    # turns the Procrustes of the points, while both passes' pose heads have the true transform
    warp = 1 + 0.08 * torch.linspace(1, 0, H, dtype=torch.float64)[:, None, None]
    fwd = _with_head(as_pred(p1, p2), gt)
    rev_T = invert_rigid(gt).clone()
    rev_T[:3, 3] *= 0.5  # the reverse pass's units: half the forward's
    rev = _with_head(as_pred(own2 * warp * 0.5, transform_points(invert_rigid(gt), p1) * 0.5), rev_T)
    est = pm.relative_pose(fwd, pred_reverse=rev)[0].double()
    assert max(pose_errors(est, gt)) < 1e-3
    plain = pm.relative_pose(as_pred(p1, p2), pred_reverse=as_pred(rev.pts1_cam1[0], rev.pts2_cam1[0]))[0]
    assert pose_errors(plain, gt)[1] > 1  # the same points without the transforms: the Procrustes is off
    # ... but its baseline length is what the translation keeps (the head's own comes out short on real data)
    assert abs(float(est[:3, 3].norm()) - float(plain[:3, 3].double().norm())) < 1e-5
    short_fwd, short_rev = gt.clone(), rev_T.clone()
    short_fwd[:3, 3] *= 0.3
    short_rev[:3, 3] *= 0.3
    short = pm.relative_pose(_with_head(fwd, short_fwd), pred_reverse=_with_head(rev, short_rev))[0]
    assert torch.allclose(short, est.float(), atol=1e-6)  # heads with 0.3 of the baseline: the same pose
    # one transform off by 10 degrees: the mean is 5 off, and the swapped call's rotation is its inverse
    err = torch.eye(4, dtype=torch.float64)
    err[:3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(10)], dtype=torch.float64))
    rev10 = _with_head(rev, err @ rev_T)
    est10 = pm.relative_pose(fwd, pred_reverse=rev10)[0].double()
    assert abs(pose_errors(est10, gt)[0] - 5.0) < 0.05
    back = invert_rigid(pm.relative_pose(rev10, pred_reverse=fwd)[0].double())
    assert relative_rotation_error_deg(back[:3, :3], est10[:3, :3]) < 1e-3
    # a transform that is not finite: the other alone
    nan_fwd = _with_head(fwd, gt * float("nan"))
    one = pm.relative_pose(nan_fwd, pred_reverse=rev)[0].double()
    assert max(pose_errors(one, gt)) < 1e-3
    # only one pass with a transform (predictions of different models): the Procrustes of the points
    mixed = pm.relative_pose(fwd, pred_reverse=as_pred(rev.pts1_cam1[0], rev.pts2_cam1[0]))[0]
    assert torch.allclose(mixed, plain)


def test_degenerate_predictions_give_nan_poses_not_exceptions():
    zeros = torch.zeros(H, W, 3, dtype=torch.float64)
    est = pm.relative_pose(as_pred(zeros, zeros), K2=K)
    assert torch.isnan(est).all()


def test_bad_intrinsics_shapes_are_refused():
    p1, p2, *_ = two_views()
    with pytest.raises(pm.ShapeError, match="K2"):
        pm.relative_pose(as_pred(p1, p2), K2=torch.eye(4))


def test_fast_reciprocal_matches_are_a_subset_of_all_mutual_neighbours_and_equal_them_when_every_pixel_seeds():
    torch.manual_seed(0)
    f1 = torch.nn.functional.normalize(torch.randn(300, 8), dim=-1)
    f2 = torch.nn.functional.normalize(torch.randn(280, 8), dim=-1)
    ref = set(zip(*[t.tolist() for t in reciprocal_nn_bruteforce(f1, f2)]))
    sub = set(zip(*[t.tolist() for t in reciprocal_nn_fast(f1, f2, torch.arange(0, 300, 7))]))
    full = set(zip(*[t.tolist() for t in reciprocal_nn_fast(f1, f2, torch.arange(300))]))
    assert sub <= ref and full == ref and len(ref) > 20


def test_similarity_blocks_stay_within_their_budget_and_any_block_size_finds_the_same_neighbours(monkeypatch):
    import pointmap.matching as m

    # a fixed 4,096 query rows against a whole 512 x 384 view took 3.2 GB (12.9 GB at size 1024)
    assert m.block_rows(512 * 384) * 512 * 384 <= m.BLOCK_ENTRIES and m.block_rows(10 ** 9) == 1
    assert m.block_rows(512 * 384, chunk=7) == 7
    g = torch.Generator().manual_seed(3)
    f1, f2 = torch.randn(300, 8, generator=g), torch.randn(280, 8, generator=g)
    want = [m.nearest(f1, f2, metric) for metric in ("dot", "l2")], reciprocal_nn_bruteforce(f1, f2, "l2")
    monkeypatch.setattr(m, "BLOCK_ENTRIES", 280 * 3 + 5)  # 3 rows per block
    got = [m.nearest(f1, f2, metric) for metric in ("dot", "l2")], reciprocal_nn_bruteforce(f1, f2, "l2")
    assert all(torch.equal(a, b) for a, b in zip(want[0], got[0]))
    assert all(torch.equal(a, b) for a, b in zip(want[1], got[1]))


def test_pointmap_matching_finds_the_true_correspondences_of_exact_pointmaps():
    p1, p2, *_ = two_views(angle_deg=3.0, t=(0.2, 0.0, 0.0))
    m = pm.match(as_pred(p1, p2), subsample=4, use="pts")
    assert len(m) > 50
    # reproject: the 3D point of view-1 pixel xy1 seen in view 2 lands at xy2 (within a pixel)
    _, _, _, _, c2w2 = two_views(angle_deg=3.0, t=(0.2, 0.0, 0.0))
    X = p1[m.xy1[:, 1].long(), m.xy1[:, 0].long()]
    Xc2 = transform_points(invert_rigid(c2w2), X)
    uv = (Xc2[:, :2] / Xc2[:, 2:]) * K[0, 0] + K[:2, 2]
    assert ((uv - m.xy2.double()).norm(dim=-1) < 1.0).float().mean() > 0.95


def test_border_drops_exactly_the_matches_near_either_edge_and_the_score_is_the_root_of_the_confidences():
    p1, p2, *_ = two_views(angle_deg=3.0, t=(0.2, 0.0, 0.0))
    g = torch.Generator().manual_seed(5)
    c1, c2 = 1 + 4 * torch.rand(1, H, W, generator=g), 1 + 4 * torch.rand(1, H, W, generator=g)
    pred = pm.PairPrediction(p1[None].float(), p2[None].float(), c1, c2)
    every = pm.match(pred, subsample=2, use="pts")
    x1, y1, x2, y2 = every.xy1[:, 0].long(), every.xy1[:, 1].long(), every.xy2[:, 0].long(), every.xy2[:, 1].long()
    assert torch.allclose(every.score, (c1[0, y1, x1] * c2[0, y2, x2]).sqrt())
    for b in (1, 6):
        inside = [k for k in range(len(every)) if min(x1[k], y1[k], x2[k], y2[k]) >= b
                  and x1[k] < W - b and x2[k] < W - b and y1[k] < H - b and y2[k] < H - b]
        kept = pm.match(pred, subsample=2, use="pts", border=b)
        assert 0 < len(kept) < len(every)
        assert torch.equal(kept.xy1, every.xy1[inside]) and torch.equal(kept.xy2, every.xy2[inside])
        assert torch.equal(kept.score, every.score[inside])


def test_pointmap_matching_far_from_the_origin_finds_what_the_float64_reference_finds():
    torch.manual_seed(1)
    p1 = torch.rand(H, W, 3) + torch.tensor([100.0, -80.0, 300.0])  # a cloud far from its frame's origin
    p2 = p1 + 0.01 * torch.randn_like(p1)
    pred = as_pred(p1, p2)
    fast = set(map(tuple, pm.match(pred, subsample=1, use="pts").xy1.tolist()))
    ref = set(map(tuple, pm.match(pred, use="pts", bruteforce=True).xy1.tolist()))
    assert len(ref) > 300 and len(fast ^ ref) <= 0.01 * len(ref)


def test_matching_refuses_batches_and_missing_descriptors():
    p1, p2, *_ = two_views()
    pred = as_pred(p1, p2)
    with pytest.raises(pm.ShapeError, match="descriptor"):
        pm.match(pred, use="desc")
    with pytest.raises(pm.ShapeError, match="batch size 1"):
        pm.match(pm.PairPrediction.cat([pred, pred]))
    for kw, named in (({"subsample": 0}, "subsample expected an int >= 1, got 0"),
                      ({"subsample": True}, "subsample expected an int >= 1, got True"),
                      ({"max_iter": 0}, "max_iter expected an int >= 1"), ({"border": -1}, "border expected an int >= 0"),
                      ({"min_conf": float("nan")}, "min_conf expected a finite number or None, got nan")):
        with pytest.raises(pm.ShapeError, match=named):
            pm.match(pred, **kw)


def true_matches(p1, c2w2, step=4, outliers=0.0, seed=0):
    """View-1 pixels on a grid and where their 3D points land in view 2 (a share replaced by random pixels)."""
    v, u = torch.meshgrid(torch.arange(0, H, step), torch.arange(0, W, step), indexing="ij")
    xy1 = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    Xc2 = transform_points(invert_rigid(c2w2), p1[xy1[:, 1], xy1[:, 0]])
    xy2 = (Xc2[:, :2] / Xc2[:, 2:]) * K[0, 0] + K[:2, 2]
    g = torch.Generator().manual_seed(seed)
    bad = torch.rand(len(xy1), generator=g) < outliers
    xy2[bad] = torch.rand(int(bad.sum()), 2, generator=g, dtype=torch.float64) * torch.tensor([W, H])
    return pm.Matches(xy1.float(), xy2.float(), torch.ones(len(xy1)))


def test_pnp_on_matches_uses_view_ones_own_pointmap_and_survives_outliers():
    p1, _, _, _, gt = two_views(angle_deg=20.0)
    pred = as_pred(p1, torch.zeros_like(p1))  # a useless cross-view pointmap: the matches path must not need it
    m = true_matches(p1, gt, outliers=0.3)
    r, t = pose_errors(pm.relative_pose(pred, K2=K, matches=[m])[0], gt)
    assert r < 0.5 and t < 2
    r, t = pose_errors(pm.relative_pose(pred, matches=[m])[0], gt)  # focal unknown: swept
    assert r < 3 and t < 10
    assert torch.isnan(pm.relative_pose(pred, K2=K)[0]).all() or pose_errors(pm.relative_pose(pred, K2=K)[0], gt)[0] > 5


def test_pose_from_matches_checks_one_matches_per_pair():
    p1, p2, _, _, gt = two_views()
    with pytest.raises(pm.ShapeError, match="list of 1 Matches"):
        pm.relative_pose(as_pred(p1, p2), K2=K, matches=[true_matches(p1, gt)] * 2)


def test_coarse_matching_pairs_the_cells_whose_pooled_descriptors_agree():
    from pointmap.matching import match_coarse

    torch.manual_seed(0)
    p, h, w, D = 8, H // 8, W // 8, 16
    codes1 = torch.nn.functional.normalize(torch.randn(h, w, D), dim=-1)
    codes2 = torch.nn.functional.normalize(torch.randn(h, w, D), dim=-1)
    codes2[:, 1:] = codes1[:, :-1]  # view-1 cell (r, c) is view-2 cell (r, c + 1)

    def pix(codes):
        x = codes.repeat_interleave(p, 0).repeat_interleave(p, 1)
        return torch.nn.functional.normalize(x + 0.5 * torch.randn_like(x), dim=-1)[None]

    p1, p2, *_ = two_views()
    pred = pm.PairPrediction(p1[None].float(), p2[None].float(), torch.ones(1, H, W), torch.ones(1, H, W),
                             desc1=pix(codes1), desc2=pix(codes2), desc_conf1=torch.ones(1, H, W),
                             desc_conf2=torch.ones(1, H, W))
    m = match_coarse(pred, patch=p, refine=False)  # xy1, xy2: the centre pixels of the matched cells
    assert len(m) >= h * (w - 1)
    shifted = (m.xy2 - m.xy1 == torch.tensor([float(p), 0.0])).all(-1)  # no half-pixel between the two views
    assert shifted.float().mean() > 0.9 and float(m.xy1[0, 0]) % p == p // 2
    with pytest.raises(pm.ShapeError, match="multiples of patch"):
        match_coarse(pred, patch=7)


def test_coarse_matches_refined_inside_the_matched_cell_land_on_the_exact_pixel():
    from pointmap.matching import match_coarse

    torch.manual_seed(3)
    p, D, dx, dy = 8, 64, 5, 3  # view 2 is view 1 moved by (5, 3) pixels: most cell matches straddle cells
    big = torch.nn.functional.normalize(torch.randn(H + dy, W + dx, D), dim=-1)
    d1, d2 = big[dy:, dx:], big[:H, :W]  # pixel (u, v) of view 1 is pixel (u + 5, v + 3) of view 2
    p1, p2, *_ = two_views()
    ones = torch.ones(1, H, W)
    pred = pm.PairPrediction(p1[None].float(), p2[None].float(), ones, ones, desc1=d1[None], desc2=d2[None],
                             desc_conf1=ones, desc_conf2=ones)
    m = match_coarse(pred, patch=p)
    inside = (m.xy1[:, 0] + dx < W) & (m.xy1[:, 1] + dy < H)
    exact = (m.xy2 - m.xy1 == torch.tensor([float(dx), float(dy)])).all(-1)
    coarse = match_coarse(pred, patch=p, refine=False)
    near = ((coarse.xy2 - m.xy1 - torch.tensor([float(dx), float(dy)])).abs() <= p).all(-1)  # coarse cell right or adjacent
    assert int(inside.sum()) >= 20 and bool(exact[inside & near].all()) and float(exact[inside].float().mean()) > 0.9
    assert not bool(((coarse.xy2 - coarse.xy1) == torch.tensor([float(dx), float(dy)])).all(-1).any())


def test_the_essential_matrix_pose_needs_only_pixels_and_intrinsics_and_survives_outliers():
    g = torch.Generator().manual_seed(3)
    _, _, _, _, gt = two_views(angle_deg=15.0)
    X = torch.rand(300, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 3.0, 3.0]) \
        + torch.tensor([-2.0, -1.5, 3.0])  # a volume in front of both cameras (not a plane)
    K1 = torch.tensor([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]], dtype=torch.float64)  # 640 x 480
    K2 = torch.tensor([[800.0, 0, 300.0], [0, 780.0, 250.0], [0, 0, 1]], dtype=torch.float64)  # another camera
    uv1 = ((X / X[:, 2:]) @ K1.T)[:, :2]
    X2 = transform_points(invert_rigid(gt), X)
    uv2 = ((X2 / X2[:, 2:]) @ K2.T)[:, :2]
    bad = torch.rand(300, generator=g) < 0.3
    uv2[bad] = torch.rand(int(bad.sum()), 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    k1, k2 = K1.numpy(), K2.numpy()
    est = pm.pose_from_essential(uv1.numpy(), uv2.numpy(), k1, k2)
    r, t = pose_errors(torch.from_numpy(est), gt)
    assert r < 0.5 and t < 1.0
    assert abs(float(torch.from_numpy(est)[:3, 3].norm()) - 1.0) < 1e-9  # the direction only: unit length
    swapped = pm.pose_from_essential(uv1.numpy(), uv2.numpy(), k2, k1)  # each view needs its own intrinsics
    assert swapped is None or max(pose_errors(torch.from_numpy(swapped), gt)) > 2
    nan_rows = uv1.clone()  # rows with NaN are dropped, the rest still give the pose
    nan_rows[:40] = float("nan")
    r, t = pose_errors(torch.from_numpy(pm.pose_from_essential(nan_rows.numpy(), uv2.numpy(), k1, k2)), gt)
    assert r < 0.5 and t < 1.0


def test_the_essential_matrix_pose_gives_none_without_a_solution_and_refuses_bad_inputs():
    g = torch.Generator().manual_seed(4)
    uv = torch.rand(100, 2, generator=g, dtype=torch.float64) * 400
    k = K.numpy()
    assert pm.pose_from_essential(uv[:4].numpy(), uv[:4].numpy() + 3, k, k) is None  # fewer than 5
    assert pm.pose_from_essential(uv.numpy(), uv.numpy(), k, k) is None  # no motion: nothing in front of both
    with pytest.raises(pm.ShapeError, match=r"\[M, 2\]"):
        pm.pose_from_essential(uv[:, :1].numpy(), uv.numpy(), k, k)
    with pytest.raises(pm.ShapeError, match="K1 expected"):
        pm.pose_from_essential(uv.numpy(), uv.numpy(), k[:2], k)
    bad_k = k.copy()
    bad_k[0, 0] = 0.0
    with pytest.raises(pm.ShapeError, match="K2 expected"):
        pm.pose_from_essential(uv.numpy(), uv.numpy(), k, bad_k)
    with pytest.raises(pm.ShapeError, match="threshold_px"):
        pm.pose_from_essential(uv.numpy(), uv.numpy(), k, k, threshold_px=0.0)
    with pytest.raises(pm.ShapeError, match="prob"):
        pm.pose_from_essential(uv.numpy(), uv.numpy(), k, k, prob=1.5)


def test_the_correspondence_solvers_refuse_a_transposed_intrinsics_matrix():
    from pointmap.matching import Matches

    g = torch.Generator().manual_seed(4)
    uv = torch.rand(50, 2, generator=g, dtype=torch.float64).numpy() * 60
    kt = K.numpy().T  # cx, cy in the bottom row: finite, positive focals, and wrong
    with pytest.raises(pm.ShapeError, match="K1 expected.*pinhole"):
        pm.pose_from_essential(uv, uv + 1, kt, K.numpy())
    with pytest.raises(pm.ShapeError, match="K2 expected.*pinhole"):
        pm.translation_from_matches(np.eye(3), uv, uv + 1, K.numpy(), kt)
    m = Matches(torch.from_numpy(uv).float(), torch.from_numpy(uv + 1).float(), torch.ones(50))
    with pytest.raises(pm.ShapeError, match="pinhole"):
        pm.refine_pose_with_matches(torch.eye(4, dtype=torch.float64), m, kt, K.numpy())


def test_the_essential_matrix_pose_from_exactly_five_correspondences_is_exact_or_none_when_ambiguous():
    found = 0
    _, _, _, _, gt = two_views(angle_deg=15.0)
    for seed in range(10):
        uv1, uv2, K1, K2, _ = _scene_pixels(gt, n=5, seed=seed)
        est = pm.pose_from_essential(uv1.numpy(), uv2.numpy(), K1.numpy(), K2.numpy())
        if est is not None:  # OpenCV stacks the five-point solutions: each is tried, a tie is refused
            assert max(pose_errors(torch.from_numpy(est), gt)) < 1e-3
            found += 1
    assert found >= 3  # none was found before


def test_the_two_pass_pose_leaves_out_a_direction_whose_own_pointmap_collapsed_to_one_point():
    p1, p2, _, d2, gt = two_views()
    own2 = depth_to_points_cam(d2, K)
    rev = as_pred(own2 * 0.5, transform_points(invert_rigid(gt), p1) * 0.5)
    collapsed = as_pred(torch.ones_like(p1), p2)  # view 1's own pointmap at one place: no scale to invert
    est = pm.relative_pose(collapsed, pred_reverse=rev)[0]
    assert bool(torch.isfinite(est).all())
    r, t = pose_errors(est, gt)
    assert r < 1e-3 and t < 1e-2


def test_relative_pose_checks_K1_and_refuses_it_for_a_view_2_of_another_size():
    p1, p2, *_ = two_views()
    with pytest.raises(pm.ShapeError, match="K1 expected"):
        pm.relative_pose(as_pred(p1, p2), K1=K.T)
    with pytest.raises(pm.ShapeError, match="K1 expected"):
        pm.relative_pose(as_pred(p1, p2), K1=torch.zeros(2, 2))
    small = pm.PairPrediction(p1[None].float(), p2[None, :, :32].float(), torch.ones(1, H, W), torch.ones(1, H, 32))
    with pytest.raises(pm.ShapeError, match="give K2"):
        pm.relative_pose(small, K1=K)
    rev = pm.PairPrediction(p2[None, :, :32].float(), p1[None].float(), torch.ones(1, H, 32), torch.ones(1, H, W))
    assert pm.relative_pose(small, K1=K, pred_reverse=rev).shape == (1, 4, 4)  # the two-pass path reads no K
    same = pm.relative_pose(as_pred(p1, p2), K1=K)[0]  # a shared camera: K1 stands for view 2's
    assert torch.allclose(same, pm.relative_pose(as_pred(p1, p2), K2=K)[0])


def _scene_pixels(gt, n=300, seed=5):
    """Pixels of a random 3D volume in front of camera 1 (640 x 480, K1) and camera 2 (``gt``, K2)."""
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 3.0, 3.0]) + torch.tensor([-2.0, -1.5, 3.0])
    K1 = torch.tensor([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]], dtype=torch.float64)
    K2 = torch.tensor([[700.0, 0, 300.0], [0, 690.0, 250.0], [0, 0, 1]], dtype=torch.float64)
    X2 = transform_points(invert_rigid(gt), X)
    return ((X / X[:, 2:]) @ K1.T)[:, :2], ((X2 / X2[:, 2:]) @ K2.T)[:, :2], K1, K2, g


def _direction_by_sphere_search(R, xy1, xy2, K1, K2, n=200_000, seed=0):
    """Slow reference: the unit t among ``n`` random directions with the smallest summed squared epipolar
    residual (all correspondences inliers)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(n, 3, generator=g, dtype=torch.float64)
    t = t / t.norm(dim=1, keepdim=True)

    def rays(xy, K):
        r = torch.cat([xy, torch.ones(len(xy), 1, dtype=torch.float64)], 1) @ torch.linalg.inv(K).T
        return r / r.norm(dim=1, keepdim=True)

    A = torch.cross(rays(xy2, K2) @ R.T, rays(xy1, K1), dim=1)
    cost = ((t @ A.T) ** 2).sum(1)
    return t[cost.argmin()]


def test_the_translation_direction_from_matches_given_the_rotation_survives_outliers_and_finds_the_sign():
    for direction in ((0.6, 0.1, 0.05), (-0.3, 0.05, -0.8)):  # sideways, and backwards (the sign matters)
        _, _, _, _, gt = two_views(angle_deg=15.0, t=direction)
        uv1, uv2, K1, K2, g = _scene_pixels(gt)
        clean = pm.translation_from_matches(gt[:3, :3].numpy(), uv1.numpy(), uv2.numpy(), K1.numpy(), K2.numpy())
        assert float(translation_angle_deg(torch.from_numpy(clean), gt[:3, 3])) < 0.01
        assert abs(float(torch.from_numpy(clean).norm()) - 1.0) < 1e-9
        noisy = uv2 + torch.randn(uv2.shape, generator=g, dtype=torch.float64) * 0.5
        bad = torch.rand(len(uv2), generator=g) < 0.6  # 60% outliers: a 2-point sample still finds the inliers
        noisy[bad] = torch.rand(int(bad.sum()), 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
        est = pm.translation_from_matches(gt[:3, :3].numpy(), uv1.numpy(), noisy.numpy(), K1.numpy(), K2.numpy())
        assert float(translation_angle_deg(torch.from_numpy(est), gt[:3, 3])) < 1.0
        # a rotation 3 degrees off moves the direction, but not away
        off = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(3.0)], dtype=torch.float64)) @ gt[:3, :3]
        est_off = pm.translation_from_matches(off.numpy(), uv1.numpy(), noisy.numpy(), K1.numpy(), K2.numpy(),
                                              threshold_px=8.0)
        assert float(translation_angle_deg(torch.from_numpy(est_off), gt[:3, 3])) < 15.0


def test_the_ransac_direction_agrees_with_an_exhaustive_search_over_directions():
    _, _, _, _, gt = two_views(angle_deg=10.0, t=(0.2, -0.4, 0.5))
    uv1, uv2, K1, K2, g = _scene_pixels(gt, n=120, seed=7)
    uv2 = uv2 + torch.randn(uv2.shape, generator=g, dtype=torch.float64) * 0.3
    R = gt[:3, :3]
    est = torch.from_numpy(pm.translation_from_matches(R.numpy(), uv1.numpy(), uv2.numpy(), K1.numpy(), K2.numpy(),
                                                       threshold_px=5.0))
    ref = _direction_by_sphere_search(R, uv1, uv2, K1, K2)
    # the search is sign-free (t and -t score the same): compare the lines, and the sign against the truth
    assert float(translation_angle_deg(est, ref)) < 1.0 or float(translation_angle_deg(est, -ref)) < 1.0
    assert float(translation_angle_deg(est, gt[:3, 3])) < 1.0


def test_the_translation_direction_drops_nan_rows_gives_none_without_inliers_and_refuses_bad_inputs():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, g = _scene_pixels(gt)
    R, k1, k2 = gt[:3, :3].numpy(), K1.numpy(), K2.numpy()
    nan_rows = uv1.clone()
    nan_rows[:50] = float("nan")
    est = pm.translation_from_matches(R, nan_rows.numpy(), uv2.numpy(), k1, k2)
    assert float(translation_angle_deg(torch.from_numpy(est), gt[:3, 3])) < 0.01
    assert pm.translation_from_matches(R, uv1[:4].numpy(), uv2[:4].numpy(), k1, k2) is None  # fewer than 5
    noise = torch.rand(300, 2, generator=g, dtype=torch.float64) * 600  # unrelated pixels: < 5 on any plane
    assert pm.translation_from_matches(R, noise[:6].numpy(), noise[6:12].numpy(), k1, k2, threshold_px=0.01) is None
    with pytest.raises(pm.ShapeError, match="rotation"):
        pm.translation_from_matches(R * 2, uv1.numpy(), uv2.numpy(), k1, k2)
    with pytest.raises(pm.ShapeError, match="rotation"):
        pm.translation_from_matches(-R, uv1.numpy(), uv2.numpy(), k1, k2)  # a reflection
    with pytest.raises(pm.ShapeError, match=r"\[M, 2\]"):
        pm.translation_from_matches(R, uv1.numpy(), uv2[:10].numpy(), k1, k2)
    with pytest.raises(pm.ShapeError, match="K2 expected"):
        pm.translation_from_matches(R, uv1.numpy(), uv2.numpy(), k1, k2[:2])
    with pytest.raises(pm.ShapeError, match="threshold_px"):
        pm.translation_from_matches(R, uv1.numpy(), uv2.numpy(), k1, k2, threshold_px=-1.0)
    with pytest.raises(pm.ShapeError, match="max_iters"):
        pm.translation_from_matches(R, uv1.numpy(), uv2.numpy(), k1, k2, max_iters=0)


def test_a_pose_refined_without_rotation_freedom_keeps_its_rotation_and_baseline_length():
    _, _, _, _, gt = two_views(angle_deg=15.0)
    uv1, uv2, K1, K2, _ = _scene_pixels(gt)
    m = pm.Matches(uv1.float(), uv2.float(), torch.ones(len(uv1)))
    wrong = gt.clone().float()
    wrong[:3, 3] = torch.tensor([0.0, 0.0, 2.5])  # right rotation, wrong direction, baseline 2.5
    fixed = pm.refine_pose_with_matches(wrong, m, K1.numpy(), K2.numpy(), rotation_prior_deg=0)
    assert float(translation_angle_deg(fixed[:3, 3].double(), gt[:3, 3])) < 0.1
    assert abs(float(fixed[:3, 3].norm()) - 2.5) < 1e-5 and torch.equal(fixed[:3, :3], wrong[:3, :3])
    assert torch.equal(wrong[:3, 3], torch.tensor([0.0, 0.0, 2.5]))  # the input is not modified
    few = pm.Matches(uv1[:3].float(), uv2[:3].float(), torch.ones(3))
    assert torch.equal(pm.refine_pose_with_matches(wrong, few, K1.numpy(), K2.numpy()), wrong)  # no direction
    lost = torch.full((4, 4), float("nan"))
    assert torch.isnan(pm.refine_pose_with_matches(lost, m, K1.numpy(), K2.numpy())).all()
    with pytest.raises(pm.ShapeError, match=r"\[4, 4\]"):
        pm.refine_pose_with_matches(wrong[:3], m, K1.numpy(), K2.numpy())
    for bad in (-1.0, float("nan")):
        with pytest.raises(pm.ShapeError, match="rotation_prior_deg"):
            pm.refine_pose_with_matches(wrong, m, K1.numpy(), K2.numpy(), rotation_prior_deg=bad)
    for bad in (2.5, 0, True):  # 2.5 ran without end inside scipy
        with pytest.raises(pm.ShapeError, match=f"max_evals an int >= 1, got 10.0 and {bad}"):
            pm.refine_pose_with_matches(wrong, m, K1.numpy(), K2.numpy(), max_evals=bad)


def _perturbed_start(gt, deg=6.0):
    """gt with its rotation turned by ``deg`` about a fixed oblique axis and a wrong translation direction."""
    axis = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    turn = axis_angle_to_matrix(axis / axis.norm() * math.radians(deg))
    start = gt.clone()
    start[:3, :3] = turn @ gt[:3, :3]
    start[:3, 3] = torch.tensor([0.1, 0.3, 1.0], dtype=torch.float64)
    return start


def test_refining_a_pose_on_matches_recovers_rotation_and_direction_through_outliers():
    _, _, _, _, gt = two_views(angle_deg=15.0, t=(0.6, 0.1, 0.05))
    uv1, uv2, K1, K2, g = _scene_pixels(gt)
    noisy = uv2 + torch.randn(uv2.shape, generator=g, dtype=torch.float64) * 0.5
    bad = torch.rand(len(uv2), generator=g) < 0.4
    noisy[bad] = torch.rand(int(bad.sum()), 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    m = pm.Matches(uv1, noisy, torch.ones(len(uv1)))
    start = _perturbed_start(gt)
    assert float(relative_rotation_error_deg(start[:3, :3], gt[:3, :3])) > 5.9
    k1, k2 = K1.numpy(), K2.numpy()  # 0.5 px noise at 640 x 480: a 2 px threshold
    free = pm.refine_pose_with_matches(start, m, k1, k2, threshold_px=2.0, rotation_prior_deg=math.inf)
    assert float(relative_rotation_error_deg(free[:3, :3], gt[:3, :3])) < 0.3
    assert float(translation_angle_deg(free[:3, 3], gt[:3, 3])) < 1.5
    assert abs(float(free[:3, 3].norm()) - float(start[:3, 3].norm())) < 1e-9
    prior = pm.refine_pose_with_matches(start, m, k1, k2, threshold_px=2.0)  # prior 10 degrees: the matches win
    assert float(relative_rotation_error_deg(prior[:3, :3], gt[:3, :3])) < 1.0
    stiff = pm.refine_pose_with_matches(start, m, k1, k2, threshold_px=2.0, rotation_prior_deg=0.01)
    assert float(relative_rotation_error_deg(stiff[:3, :3], start[:3, :3])) < 0.1  # a stiff prior holds it


def test_the_refined_pose_is_a_minimum_of_the_robust_objective_it_states():
    """Slow reference: the stated objective (Cauchy on the angular epipolar residuals + Cauchy rotation prior)
    evaluated directly is not lower at any of 300 random nearby poses than at the refined one."""
    from scipy.spatial.transform import Rotation

    _, _, _, _, gt = two_views(angle_deg=20.0, t=(-0.3, 0.05, -0.8))
    uv1, uv2, K1, K2, g = _scene_pixels(gt, n=150, seed=3)
    uv2 = uv2 + torch.randn(uv2.shape, generator=g, dtype=torch.float64) * 1.0
    m = pm.Matches(uv1, uv2, torch.ones(len(uv1)))
    start = _perturbed_start(gt, deg=4.0)
    thr, prior_deg = 4.0, 10.0
    got = pm.refine_pose_with_matches(start, m, K1.numpy(), K2.numpy(), threshold_px=thr, rotation_prior_deg=prior_deg)
    s, prior = thr / float(K1[0, 0]), math.radians(prior_deg)

    def rays(xy, K):
        r = np.c_[xy, np.ones(len(xy))] @ np.linalg.inv(K).T
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    r1, r2 = rays(uv1.numpy(), K1.numpy()), rays(uv2.numpy(), K2.numpy())
    R0 = start[:3, :3].numpy()

    def residuals(R, t):
        t = t / np.linalg.norm(t)
        n = np.cross(t[None], r2 @ R.T)
        return (n * r1).sum(1) / np.linalg.norm(n, axis=1)

    R, t = got[:3, :3].numpy(), got[:3, 3].numpy()
    gate = np.abs(residuals(R, t)) < 3 * s  # the matches the refinement settled on
    assert gate.mean() > 0.9

    def cost(R, t):
        w = Rotation.from_matrix(R @ R0.T).as_rotvec()
        return np.log1p((residuals(R, t)[gate] / s) ** 2).sum() + np.log1p((w / prior) ** 2).sum()

    best = cost(R, t)
    rng = np.random.default_rng(0)
    for _ in range(300):
        dR = Rotation.from_rotvec(rng.normal(0, math.radians(0.3), 3)).as_matrix()
        dt = t / np.linalg.norm(t) + rng.normal(0, 0.005, 3)
        assert cost(dR @ R, dt) >= best - 1e-9


def _described(p1_own, p2_in1, p2_own, p1_in2, gt, seed=0):
    """Forward and reverse PairPredictions of the plane scene whose descriptors encode the world point (random
    Fourier features of its position in camera 1's frame), so descriptor matching finds the true pixels."""
    g = torch.Generator().manual_seed(seed)
    B = torch.randn(3, 24, generator=g, dtype=torch.float64) * 4.0

    def desc(X):  # [H, W, 3] in camera 1's frame
        f = X @ B
        return torch.nn.functional.normalize(torch.cat([f.sin(), f.cos()], -1), dim=-1)[None].float()

    world1, world2 = p1_own, transform_points(gt, p2_own)  # camera 1's frame: the world
    ones = torch.ones(1, H, W)
    fwd = pm.PairPrediction(p1_own[None].float(), p2_in1[None].float(), ones * 2, ones * 2, desc1=desc(world1),
                            desc2=desc(world2), desc_conf1=ones, desc_conf2=ones)
    rev = pm.PairPrediction(p2_own[None].float(), p1_in2[None].float(), ones * 2, ones * 2, desc1=desc(world2),
                            desc2=desc(world1), desc_conf1=ones, desc_conf2=ones)
    return fwd, rev


def test_the_pair_pose_takes_the_direction_from_the_matches_and_the_rotation_from_the_pointmaps():
    p1, p2, d1, d2, gt = two_views(angle_deg=10.0, t=(0.6, 0.1, 0.05))
    p2_own = depth_to_points_cam(d2, K)
    p1_in2 = transform_points(invert_rigid(gt), p1)
    shift = torch.tensor([0.0, 0.25, 0.4], dtype=torch.float64)  # the cross-view pointmaps misplaced: a wrong
    fwd, rev = _described(p1, p2 + shift, p2_own, p1_in2 - shift, gt)  # baseline, the rotation untouched
    plain = pm.relative_pose(fwd, pred_reverse=rev)[0]
    r0, t0 = pose_errors(plain, gt)
    assert r0 < 0.5 and t0 > 20  # what the pointmaps alone give
    est = pm.pair_pose(fwd, rev, patch=8)[0]  # focals from the (exact) own-frame pointmaps: 60 px
    r, t = pose_errors(est, gt)
    # the matches are whole pixels (+-0.5 px, +-0.5 degree of ray at 60 px) over ~9 degrees of parallax, and a
    # plane lets a little rotation trade for direction: a few degrees is what 32 matches can tell
    assert r < 0.5 and t < 3.0
    held = pm.pair_pose(fwd, rev, patch=8, rotation_prior_deg=0)[0]  # the pointmaps' (exact) rotation kept
    assert torch.equal(held[:3, :3], plain[:3, :3]) and pose_errors(held, gt)[1] < 1.0
    assert abs(float(est[:3, 3].norm()) - float(plain[:3, 3].norm())) < 1e-4  # the pointmaps' baseline length kept
    from pointmap.matching import match_coarse

    reused = pm.pair_pose(fwd, rev, patch=8, pose=plain[None], matches=[match_coarse(fwd[0], 8)])[0]
    assert torch.equal(reused, est) and torch.equal(plain, pm.relative_pose(fwd, pred_reverse=rev)[0])  # not modified
    known = pm.pair_pose(fwd, rev, K, K, patch=8, rotation_prior_deg=3.0)[0]  # exact pointmaps: the same focals
    assert torch.allclose(known, est, atol=1e-3)
    known = pm.pair_pose(fwd, rev, K, K, patch=8)[0]  # both K known: a 1-degree prior (3 with a focal estimated)
    assert torch.allclose(known, pm.pair_pose(fwd, rev, K, K, patch=8, rotation_prior_deg=1.0)[0])
    assert max(pose_errors(known, gt)) < 3.0
    # pointmaps that put camera 2 on the wrong side: the matches give the line, the pointmaps its sign
    back = gt[:3, 3] * 2
    fwd_b, rev_b = _described(p1, p2 - back, p2_own, p1_in2 + gt[:3, :3].T @ back, gt)
    flipped = pm.pair_pose(fwd_b, rev_b, patch=8)[0]
    assert float(flipped[:3, 3] @ pm.relative_pose(fwd_b, pred_reverse=rev_b)[0, :3, 3]) > 0
    assert pose_errors(flipped, gt)[1] > 177
    bare = [pm.PairPrediction(p.pts1_cam1, p.pts2_cam1, p.conf1, p.conf2) for p in (fwd, rev)]
    assert torch.equal(pm.pair_pose(*bare)[0], pm.relative_pose(bare[0], pred_reverse=bare[1])[0])  # no descriptors
    one = pm.pair_pose(fwd, rev, K, patch=8)[0]  # view 1 known, view 2's focal estimated (the same here)
    assert torch.allclose(one, est, atol=1e-3)
    with pytest.raises(pm.ShapeError, match="pred_reverse"):
        pm.pair_pose(fwd, None)
    with pytest.raises(pm.ShapeError, match=r"pose expected relative_pose's \[1, 4, 4\]"):
        pm.pair_pose(fwd, rev, pose=plain)
    with pytest.raises(pm.ShapeError, match="matches expected a list of 1 Matches"):
        pm.pair_pose(fwd, rev, matches=[])
    with pytest.raises(pm.ShapeError, match=r"K2 expected \[3, 3\] or \[1, 3, 3\]"):
        pm.pair_pose(fwd, rev, K, K[:2])
    assert torch.equal(pm.pair_pose(fwd, rev, patch=8, pose=plain[None].numpy()), est[None])  # an array is taken
    # settings checked also where no pair is refined (a model without descriptors): they passed silently before
    for kw, message in ((dict(patch=0), "patch expected an int >= 1, got 0"),
                        (dict(threshold_px=float("nan")), "threshold_px expected a finite number > 0, got nan"),
                        (dict(rotation_prior_deg=-1), "rotation_prior_deg expected None or a number >= 0")):
        with pytest.raises(pm.ShapeError, match=re.escape(message)):
            pm.pair_pose(*bare, **kw)


def test_a_prediction_refuses_descriptors_that_do_not_come_in_fours_fit_the_grid_or_agree_in_length():
    p1, p2, *_ = two_views()
    pts = (p1[None].float(), p2[None].float(), torch.ones(1, H, W), torch.ones(1, H, W))
    d, dc = torch.ones(1, H, W, 8), torch.ones(1, H, W)
    with pytest.raises(pm.ShapeError, match="all four or none, got only \\['desc1', 'desc2'\\]"):
        pm.PairPrediction(*pts, desc1=d, desc2=d)
    with pytest.raises(pm.ShapeError, match="desc1 expected .*pts1_cam1's grid"):
        pm.PairPrediction(*pts, desc1=torch.ones(1, 5, 5, 8), desc2=d, desc_conf1=dc, desc_conf2=dc)
    with pytest.raises(pm.ShapeError, match="desc_conf2 expected"):
        pm.PairPrediction(*pts, desc1=d, desc2=d, desc_conf1=dc, desc_conf2=torch.ones(1, 5, 5))
    with pytest.raises(pm.ShapeError, match="same descriptor length D, got \\[4, 8\\]"):
        pm.PairPrediction(*pts, desc1=d, desc2=d[..., :4], desc_conf1=dc, desc_conf2=dc)
    with pytest.raises(pm.ShapeError, match="pts1_cam1 expected a torch.Tensor, got ndarray"):
        pm.PairPrediction(pts[0].numpy(), *pts[1:])
    assert pm.PairPrediction(*pts, desc1=d, desc2=d, desc_conf1=dc, desc_conf2=dc).has_desc


def test_a_predictions_pose_head_transform_is_one_4x4_per_pair_and_follows_slices_and_concatenation():
    p1, p2, *_ = two_views()
    pts = (p1[None].float().expand(3, -1, -1, -1), p2[None].float().expand(3, -1, -1, -1), torch.ones(3, H, W),
           torch.ones(3, H, W))
    T = torch.eye(4).expand(3, 4, 4).clone()
    T[:, 0, 3] = torch.arange(3.0)
    with pytest.raises(pm.ShapeError, match=r"cam2_to_cam1 expected \[3, 4, 4\] \(one transform per pair\), "
                                            r"got \[4, 4\]"):
        pm.PairPrediction(*pts, cam2_to_cam1=T[0])
    with pytest.raises(pm.ShapeError, match="cam2_to_cam1 expected a torch.Tensor, got ndarray"):
        pm.PairPrediction(*pts, cam2_to_cam1=T.numpy())
    pred = pm.PairPrediction(*pts, cam2_to_cam1=T)
    assert torch.equal(pred[2].cam2_to_cam1, T[2:]) and "cam2_to_cam1" in pred.as_dict()
    assert torch.equal(pm.PairPrediction.cat([pred[0], pred[2]]).cam2_to_cam1, T[[0, 2]])
    assert pm.PairPrediction(*pts).cam2_to_cam1 is None


def test_intrinsics_with_a_zero_or_nan_focal_are_refused_not_turned_into_a_nan_pose():
    p1, p2, *_ = two_views()
    pred = as_pred(p1, p2)
    for bad in (torch.zeros(3, 3), torch.full((3, 3), float("nan"))):
        with pytest.raises(pm.ShapeError, match="K2 expected finite intrinsics with positive focals"):
            pm.relative_pose(pred, K2=bad)
        with pytest.raises(pm.ShapeError, match="K1 expected finite intrinsics with positive focals"):
            pm.pair_pose(pred, as_pred(p2, p1), bad, K)
    assert torch.isfinite(pm.relative_pose(pred, K2=K)).all()


def test_matching_and_pose_refuse_what_is_not_a_prediction():
    p1, p2, *_ = two_views()
    with pytest.raises(pm.ShapeError, match="pred expected a PairPrediction .*got dict"):
        pm.match(as_pred(p1, p2).as_dict())
    with pytest.raises(pm.ShapeError, match="pred expected a PairPrediction .*got dict"):
        pm.match_coarse(as_pred(p1, p2).as_dict())
    with pytest.raises(pm.ShapeError, match="pred_reverse expected a PairPrediction .*got tuple"):
        pm.relative_pose(as_pred(p1, p2), pred_reverse=(p2, p1))


def test_pnp_on_a_degenerate_sample_returns_no_pose_rather_than_an_opencv_assertion():
    from pointmap.pose import _pnp

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    pts = np.random.default_rng(0).uniform(-1, 1, (20, 3)) + [0, 0, 4]
    assert _pnp(pts, np.full((20, 2), 30.0), K, 100, 2.0) == (None, 0)  # every pixel the same (SQPnP asserts)
    uv = pts[:, :2] / pts[:, 2:] * 100 + 50  # a camera at the origin sees them: found, every point an inlier
    c2w, n = _pnp(pts, uv, K, 100, 2.0)
    assert n == 20 and np.allclose(c2w, np.eye(4), atol=1e-6)


def test_a_focal_heads_focals_are_one_per_pair_and_the_focal_the_pipeline_reads():
    from pointmap.geometry.focal import focal_from_pointmap
    from pointmap.pose import focal_from_prediction

    p1, p2, *_ = two_views()
    pts = (p1[None].float().expand(2, -1, -1, -1), p2[None].float().expand(2, -1, -1, -1), torch.ones(2, H, W),
           torch.ones(2, H, W))
    with pytest.raises(pm.ShapeError, match=r"focal1 expected \[2\] \(one focal per pair\), got \[2, 1\]"):
        pm.PairPrediction(*pts, focal1=torch.ones(2, 1), focal2=torch.ones(2))
    plain = pm.PairPrediction(*pts)
    assert torch.equal(focal_from_prediction(plain), focal_from_pointmap(pts[0]))  # no head: the pointmap's
    with pytest.raises(pm.ShapeError, match="run the reverse pair for view 2"):
        focal_from_prediction(plain, view=2)
    pred = pm.PairPrediction(*pts, focal1=torch.tensor([100.0, 110.0]), focal2=torch.tensor([120.0, 130.0]))
    assert focal_from_prediction(pred).tolist() == [100.0, 110.0]
    assert focal_from_prediction(pred, view=2).tolist() == [120.0, 130.0]
    assert torch.equal(pred[1].focal2, torch.tensor([130.0])) and "focal1" in pred.as_dict()
    assert torch.equal(pm.PairPrediction.cat([pred[1], pred[0]]).focal1, torch.tensor([110.0, 100.0]))
