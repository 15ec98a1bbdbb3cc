"""Pose refinement on matches (pointmap.align.epipolar): the vectorised residuals against the two-view reference,
the fit on exact and outlier-laden matches of the analytic scene, the gauge, the stage end to end on predictions
with descriptors, and what it refuses or skips."""

import dataclasses

import numpy as np
import pytest
import torch
from align_scene import (
    complete_pairs,
    gt_matches,
    gt_preds,
    make_scene,
    pose_errors,
    ring_matches,
    views_of,
    with_descriptors,
)

import pointmap.align.epipolar as epi
from pointmap.align import AlignConfig, EpipolarConfig, global_align, refine_epipolar
from pointmap.align.epipolar import (
    _cheirality_jacobian,
    _left_jacobian,
    _residual_jacobian,
    _residuals_by_pair,
    _rotvec_to_matrix,
    _skew,
    cheirality_margins,
    epipolar_residuals,
    in_front_share,
    mirrored_pairs,
    pinned_cameras,
    solve_poses,
)
from pointmap.errors import ShapeError
from pointmap.geometry.rotations import axis_angle_to_matrix
from pointmap.pose import _bearings, _epipolar_residuals


@pytest.fixture(scope="module")
def scene():
    return make_scene(5, 32, 48, seed=61)


def exact_rays(sc, i, j, step=3, outliers=0.0, seed=0):
    """Rays (camera frames) of grid pixels of image i and of where their true points land in image j (``gt_matches``,
    hidden points included)."""
    xy1, xy2, _ = gt_matches(sc, i, j, step=step, outliers=outliers, seed=seed, occluded=True)
    return _bearings(xy1, sc["K"][i]), _bearings(xy2, sc["K"][j])


def stacked(sc, outliers=0.0, step=3):
    n = len(sc["cam2world"])
    I, J, r1, r2 = [], [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            a, b = exact_rays(sc, i, j, step=step, outliers=outliers, seed=10 * i + j)
            I.append(np.full(len(a), i))
            J.append(np.full(len(a), j))
            r1.append(a)
            r2.append(b)
    return np.concatenate(I), np.concatenate(J), np.concatenate(r1), np.concatenate(r2)


def perturbed(c2w, rot_deg=3.0, centre=0.3, seed=0, held=(0,)):
    rng = np.random.default_rng(seed)
    out = c2w.copy()
    for k in range(len(c2w)):
        if k in held:
            continue
        axis = rng.normal(size=3)
        axis *= np.radians(rot_deg) / np.linalg.norm(axis)
        out[k, :3, :3] = axis_angle_to_matrix(torch.from_numpy(axis)).numpy() @ out[k, :3, :3]
        out[k, :3, 3] += rng.normal(scale=centre, size=3)
    return out


def direction_errors(c2w, gt):
    """Max rotation and direction errors (degrees) of every camera pair's relative pose."""
    rot, dirs = [], []
    for i in range(len(gt)):
        for j in range(i + 1, len(gt)):
            e, g = np.linalg.inv(c2w[i]) @ c2w[j], np.linalg.inv(gt[i]) @ gt[j]
            rot.append(np.degrees(np.arccos(np.clip((np.trace(e[:3, :3].T @ g[:3, :3]) - 1) / 2, -1, 1))))
            a, b = e[:3, 3] / np.linalg.norm(e[:3, 3]), g[:3, 3] / np.linalg.norm(g[:3, 3])
            dirs.append(np.degrees(np.arccos(np.clip(a @ b, -1, 1))))
    return max(rot), max(dirs)


def test_vectorised_residuals_agree_with_the_two_view_reference(scene):
    I, J, r1, r2 = stacked(scene)
    c2w = perturbed(scene["cam2world"], seed=3)
    R, C = c2w[:, :3, :3], c2w[:, :3, 3]
    fast = epipolar_residuals(R, C, I, J, r1, r2)
    ref = np.empty_like(fast)
    for m in range(len(I)):  # one match at a time through the two-view function pair_pose refines with
        rel = np.linalg.inv(c2w[I[m]]) @ c2w[J[m]]
        t = rel[:3, 3] / np.linalg.norm(rel[:3, 3])
        ref[m] = _epipolar_residuals(rel[:3, :3], t, r1[m:m + 1], r2[m:m + 1])[0]
    assert np.abs(fast).max() > 1e-3  # the perturbed poses do not fit: the comparison is not of zeros
    np.testing.assert_allclose(fast, ref, atol=1e-12)
    exact = epipolar_residuals(scene["cam2world"][:, :3, :3], scene["cam2world"][:, :3, 3], I, J, r1, r2)
    assert np.abs(exact).max() < 1e-9


@pytest.fixture(scope="module")
def wide_scene():
    """The analytic scene at 144 x 96 px: random outliers then fall far from most epipolar lines, as in photographs."""
    return make_scene(5, 96, 144, seed=61, focal_range=(114.0, 156.0))


@pytest.mark.parametrize("outliers, rot_deg, px, bound", [(0.0, 3.0, 1.0, 0.01), (0.3, 3.0, 2.0, 0.3)])
def test_the_fit_recovers_rotations_and_directions_from_perturbed_poses(wide_scene, outliers, rot_deg, px, bound):
    """From a start degrees off, on exact matches and on matches of which 30% are random (those that fall inside
    the gate by chance bias the Cauchy fit a little: the bound is a tenth of a degree or so there)."""
    gt = wide_scene["cam2world"]
    I, J, r1, r2 = stacked(wide_scene, outliers)
    start = perturbed(gt, rot_deg=rot_deg, centre=0.1 * rot_deg, seed=5)
    rot0, dir0 = direction_errors(start, gt)
    scale = np.full(len(I), px / 135.0)  # px pixels at the scene's ~135 px focal
    R, C, rep = solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[0], keep_scale=True,
                            prior_deg=30.0)
    out = start.copy()
    out[:, :3, :3], out[:, :3, 3] = R, C
    rot, dirs = direction_errors(out, gt)
    assert rot0 > rot_deg and dir0 > 2 * rot_deg  # the start is well off
    assert rot < bound and dirs < bound, (rot, dirs, rot0, dir0)
    assert rep["median_residual_after"] < rep["median_residual_before"]
    rot_s, centre_s, _ = pose_errors(out, gt)  # the whole rig up to a similarity
    assert rot_s < bound and centre_s < bound / 50


def test_the_fit_does_not_depend_on_where_the_world_origin_is():
    """The fit's parameters are the free cameras' moves from the start, so the world's origin (a gauge) does not reach
    the solver. With the centres themselves as parameters, scipy's first trust region was their norm: this start,
    20 degrees off with 30% random matches, ended up to 1 unit apart in centre (and 2.5 degrees in rotation) once the
    world was shifted by 50 units (docs/alignment.md)."""
    sc = make_scene(8, 96, 144, seed=3, focal_range=(114.0, 156.0))
    I, J, r1, r2 = stacked(sc, 0.3)
    start = perturbed(sc["cam2world"], rot_deg=20.0, centre=2.0, seed=3)
    scale = np.full(len(I), 2.0 / 135.0)
    shift = np.array([40.0, -25.0, 15.0])  # the same rig, the world's origin elsewhere
    R, C, _ = solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[0], keep_scale=True)
    R2, C2, _ = solve_poses(start[:, :3, :3], start[:, :3, 3] + shift, I, J, r1, r2, scale, held=[0],
                            keep_scale=True)
    np.testing.assert_allclose(R2, R, atol=1e-5)
    np.testing.assert_allclose(C2 - shift, C, atol=1e-4)
    assert np.abs(C - start[:, :3, 3]).max() > 0.1  # the fit moved the cameras


def test_held_cameras_stay_and_the_scale_is_kept(scene):
    gt = scene["cam2world"]
    I, J, r1, r2 = stacked(scene)
    start = perturbed(gt, seed=7, held=(0, 2))
    scale = np.full(len(I), 0.5 / 45.0)
    R, C, _ = solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[0, 2], keep_scale=False)
    assert np.array_equal(R[[0, 2]], start[[0, 2], :3, :3]) and np.array_equal(C[[0, 2]], start[[0, 2], :3, 3])
    d0 = np.linalg.norm(start[[1, 3, 4], :3, 3] - start[0, :3, 3], axis=1).mean()
    R, C, _ = solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[0], keep_scale=True)
    assert np.array_equal(C[0], start[0, :3, 3])
    assert np.linalg.norm(C[1:] - C[0], axis=1).mean() == pytest.approx(
        np.linalg.norm(start[1:, :3, 3] - start[0, :3, 3], axis=1).mean(), rel=1e-3)
    assert d0 > 0
    with pytest.raises(ShapeError, match="at least one held camera"):
        solve_poses(start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale, held=[], keep_scale=True)


@pytest.fixture(scope="module")
def mid_scene():
    """The analytic scene at 96 x 64 px, its views, predictions with descriptors (8-degree pose noise per pass,
    2% depth noise) over the complete graph, and their dense alignment."""
    sc = make_scene(5, 64, 96, seed=61, focal_range=(76.0, 104.0))
    n = len(sc["cam2world"])
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    views = views_of(sc)
    preds = with_descriptors(gt_preds(sc, pairs, seed=2, pair_rot_deg=8.0, noise=0.02), sc)
    return sc, views, preds, global_align(views, preds, config=AlignConfig(quiet=True))


def test_the_stage_fits_the_matches_better_and_refits_the_depths_to_its_poses(mid_scene):
    """The stage end to end on predictions with descriptors: coarse matches of every pair (some wrong where the views
    do not overlap), focals from the own-frame pointmaps, the fit, the depths re-fitted with its poses held. How much
    the poses improve on a trained model's predictions is measured by benchmarks/bench_ga.py ('+E'); on these
    near-exact pointmaps dense alignment is already within a few degrees, close to what 8-px cells can tell."""
    sc, views, preds, recon = mid_scene
    n = len(sc["cam2world"])
    cfg = EpipolarConfig(patch=8)
    out = refine_epipolar(views, preds, recon, config=cfg)
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["matches"] > 150 and rep["inliers_after"] > rep["inliers_before"]
    assert rep["median_residual_after"] < 0.5 * rep["median_residual_before"]
    rot, dirs = direction_errors(out.cam2world.double().numpy(), sc["cam2world"])
    assert rot < 15 and dirs < 15  # stays near the truth
    # the depths were re-fitted with the refined poses held: they come back as given, with the focals used
    assert out.info["align_refit"]["known_pose_indices"] == list(range(n))
    assert np.median(np.abs(out.K[:, 0, 0].numpy() / sc["K"][:, 0, 0] - 1)) < 0.02  # the own-frame maps' focals
    assert torch.equal(out.cam2world[0], recon.cam2world[0])  # the world stays camera 0's frame
    assert 0 < rep["fit_seconds"] < rep["seconds"]  # the matching and fit timed apart from the depth re-fit
    kept = refine_epipolar(views, preds, recon, config=dataclasses.replace(cfg, refit_depth=False))
    assert torch.equal(kept.depth_z, recon.depth_z) and torch.allclose(kept.cam2world, out.cam2world, atol=1e-5)
    pts_refit = out.pts_world[out.depth_z > 0]
    assert torch.isfinite(pts_refit).all()


def test_the_stage_gives_each_camera_of_a_labelled_alignment_one_focal_and_refits_with_them():
    sc = make_scene(5, 64, 96, seed=61, focals=[80.0, 100.0, 80.0, 100.0, 80.0])
    pairs = [(i, j) for i in range(5) for j in range(i + 1, 5)]
    views = views_of(sc)
    preds = with_descriptors(gt_preds(sc, pairs, seed=2, pair_rot_deg=8.0, noise=0.02), sc)
    recon = global_align(views, preds, config=AlignConfig(quiet=True, shared_focal=(0, 1, 0, 1, 0)))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    assert out.info["epipolar"]["applied"]
    f = out.K[:, 0, 0].double()
    assert float(f[[0, 2, 4]].max() - f[[0, 2, 4]].min()) == 0 and float(f[1] - f[3]) == 0
    assert abs(float(f[0]) / 80 - 1) < 0.03 and abs(float(f[1]) / 100 - 1) < 0.03, f
    assert out.info["align_refit"]["config"]["shared_focal"] == (0, 1, 0, 1, 0)


def test_the_stage_skips_models_without_descriptors_and_scenes_with_every_pose_known(scene):
    n = len(scene["cam2world"])
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    views = views_of(scene)
    preds = gt_preds(scene, pairs, seed=2)
    recon = global_align(views, preds, config=AlignConfig(quiet=True))
    out = refine_epipolar(views, preds, recon)
    assert not out.info["epipolar"]["applied"] and "descriptor" in out.info["epipolar"]["reason"]
    assert torch.equal(out.cam2world, recon.cam2world)
    preds = with_descriptors(preds, scene)
    known = global_align(views, preds, cam2world=torch.from_numpy(scene["cam2world"]).float(),
                         config=AlignConfig(quiet=True))
    out = refine_epipolar(views, preds, known, config=EpipolarConfig(patch=4))
    assert not out.info["epipolar"]["applied"] and "every pose is known" in out.info["epipolar"]["reason"]
    with pytest.raises(ShapeError, match="indices below 5"):
        refine_epipolar(views, {(0, 7): preds[(0, 1)]}, recon)


def test_a_reversed_direction_puts_the_matched_points_behind_the_cameras_and_is_flagged(wide_scene):
    gt = wide_scene["cam2world"]
    I, J, r1, r2 = stacked(wide_scene, 0.1)
    R, C = gt[:, :3, :3], gt[:, :3, 3]
    pairs, pid = np.unique(np.stack([I, J], 1), axis=0, return_inverse=True)
    share, counted = in_front_share(R, C, I, J, r1, r2, len(pairs), pid.reshape(-1))
    assert counted.min() > 50 and share.min() > 0.85  # true poses: the outliers aside, every point is in front
    # camera 3 mirrored through camera 1: pair (1, 3)'s direction reversed, the epipolar residuals of it unchanged
    C_m = C.copy()
    C_m[3] = 2 * C[1] - C[3]
    sel = (I == 1) & (J == 3)
    np.testing.assert_allclose(np.abs(epipolar_residuals(R, C_m, I[sel], J[sel], r1[sel], r2[sel])),
                               np.abs(epipolar_residuals(R, C, I[sel], J[sel], r1[sel], r2[sel])), atol=1e-12)
    share_m, _ = in_front_share(R, C_m, I, J, r1, r2, len(pairs), pid.reshape(-1))
    assert share_m[(pairs == [1, 3]).all(1)][0] < 0.15
    assert [1, 3] in mirrored_pairs(R, C, R, C_m, I, J, r1, r2)
    assert mirrored_pairs(R, C, R, C, I, J, r1, r2) == []
    assert mirrored_pairs(R, C_m, R, C, I, J, r1, r2) == []  # un-mirroring a pair is not flagged


def test_cameras_touching_every_reversed_pair_are_few():
    assert pinned_cameras([[4, 6], [5, 6], [6, 8]]) == [6]
    assert pinned_cameras([[0, 1], [2, 3]]) == [0, 2]
    assert pinned_cameras([]) == []
    assert pinned_cameras([[0, 3]], held=[0]) == [3] and pinned_cameras([[0, 3]], held=[0, 3]) == []


def test_a_fit_that_reverses_a_direction_is_refitted_with_that_camera_held_then_rejected(mid_scene, monkeypatch):
    _, views, preds, recon = mid_scene
    real = epi.solve_poses
    calls = []

    def mirroring(R0, C0, *args, times=2, pairs=([0, 2], [1, 2], [2, 4]), **kwargs):
        R, C, rep = real(R0, C0, *args, **kwargs)
        calls.append((list(kwargs["held"]), kwargs["keep_scale"], kwargs["anchor"]))
        if len(calls) <= times:
            C[2] = 2 * C[0] - C[2]  # what the scale-free variant did to the demo room
            rep = {**rep, "mirrored_pairs": [list(p) for p in pairs]}
        return R, C, rep

    monkeypatch.setattr(epi, "solve_poses", mirroring)
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    # the second fit holds camera 2, the one in every reversed pair, with the first fit's gauge
    assert calls == [([0], True, 0), ([0, 2], True, 0)]
    assert not rep["applied"] and "reversed the direction of camera pair(s) [[0, 2], [1, 2], [2, 4]]" in rep["reason"]
    assert "the re-fit with cameras [2] held reversed" in rep["reason"] and rep["matches"] > 150
    assert torch.equal(out.cam2world, recon.cam2world)
    calls.clear()
    monkeypatch.setattr(epi, "solve_poses", lambda *a, **k: mirroring(*a, times=1, **k))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["pinned"] == [2] and rep["held"] == [0, 2]
    assert rep["first_fit"]["mirrored_pairs"] == [[0, 2], [1, 2], [2, 4]]
    assert rep["evaluations"] > rep["first_fit"]["evaluations"] > 0  # both fits counted
    assert torch.allclose(out.cam2world[2], recon.cam2world[2], atol=1e-5)  # held where it was aligned
    calls.clear()  # reversed pairs touching every free camera: holding them all would leave nothing to fit
    monkeypatch.setattr(epi, "solve_poses",
                        lambda *a, **k: mirroring(*a, pairs=([0, 1], [0, 2], [0, 3], [0, 4]), **k))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    assert len(calls) == 1 and not rep["applied"] and "would hold every camera" in rep["reason"]
    assert torch.equal(out.cam2world, recon.cam2world)
    monkeypatch.setattr(epi, "solve_poses", real)
    fit = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8)).info["epipolar"]
    assert fit["applied"] and fit["mirrored_pairs"] == [] and "pinned" not in fit


def test_the_mirror_check_refuses_bad_settings_and_counts_only_rays_with_parallax(wide_scene):
    gt = wide_scene["cam2world"]
    I, J, r1, r2 = stacked(wide_scene)
    R, C = gt[:, :3, :3], gt[:, :3, 3]
    with pytest.raises(ValueError, match="mirrored_pairs expected"):
        mirrored_pairs(R, C, R, C, I, J, r1, r2, was=0.3, now=0.7)
    with pytest.raises(ShapeError, match="one pair index"):
        in_front_share(R, C, I, J, r1, r2, 1, np.full(len(I), 3))
    assert mirrored_pairs(R, C, R, C, I[:0], J[:0], r1[:0], r2[:0]) == []
    # a camera on top of another (no baseline): its rays meet nowhere in particular, and none of them counts
    C_same = C.copy()
    C_same[1] = C[0]
    R_same = R.copy()
    R_same[1] = R[0]
    sel = (I == 0) & (J == 1)
    _, counted = in_front_share(R_same, C_same, I[sel], J[sel], r1[sel], r1[sel], 1, np.zeros(int(sel.sum()), int))
    assert counted[0] == 0


@pytest.mark.parametrize("kwargs", [dict(rotation_prior_deg=0.0), dict(threshold_px=-1.0), dict(rounds=0),
                                    dict(patch=0), dict(rotation_prior_deg=float("nan")), dict(max_evals=2.5),
                                    dict(rounds=2.5), dict(patch=8.0), dict(patch=True)])
def test_bad_settings_are_refused_when_the_config_is_made(kwargs):
    with pytest.raises(ValueError, match="EpipolarConfig expected"):
        EpipolarConfig(**kwargs)


@pytest.mark.parametrize("kwargs, message", [
    (dict(refit_depth="no"), "refit_depth expected True or False, got 'no'"),  # truthy: the refit ran
    (dict(cheirality=0), "cheirality expected True or False, got 0"),
    (dict(second_descent="False"), "second_descent expected True or False"),
    (dict(rotation_prior_deg="3"), "EpipolarConfig expected rotation_prior_deg > 0"),  # a raw TypeError before
    (dict(threshold_px="4"), "EpipolarConfig expected"),
    (dict(threshold_px=float("inf")), "EpipolarConfig expected"),  # every residual 0: the fit moved nothing
    (dict(rotation_prior_deg=True), "EpipolarConfig expected")])
def test_switches_given_as_strings_and_numbers_given_as_strings_or_bools_are_refused(kwargs, message):
    with pytest.raises(ShapeError, match=message):
        EpipolarConfig(**kwargs)
    assert EpipolarConfig(refit_depth=False, rotation_prior_deg=2, threshold_px=3).rotation_prior_deg == 2


def test_the_analytic_residual_jacobian_agrees_with_central_differences(scene):
    """``_residual_jacobian`` and ``_left_jacobian`` against central differences of the residuals through the fit's
    own parameterisation R_k = exp(w_k) R_k0 (w well away from 0, where the left Jacobian matters)."""
    I, J, r1, r2 = stacked(scene, 0.2)
    c2w = perturbed(scene["cam2world"], seed=4)
    R0, C0 = c2w[:, :3, :3], c2w[:, :3, 3]
    rng = np.random.default_rng(0)
    w = rng.normal(scale=0.4, size=(len(R0), 3))
    pairs, pid = np.unique(np.stack([I, J], 1), axis=0, return_inverse=True)

    def residuals(w_, C_):
        return _residuals_by_pair(_rotvec_to_matrix(w_) @ R0, C_, pairs[:, 0], pairs[:, 1], pid.reshape(-1), r1, r2)

    d_phi_i, d_phi_j, d_C_i, d_C_j = _residual_jacobian(_rotvec_to_matrix(w) @ R0, C0, I, J, r1, r2)
    Jl = _left_jacobian(w)
    h = 1e-6
    for cam in (1, 3):
        for c in range(3):
            dw, dc = np.zeros_like(w), np.zeros_like(C0)
            dw[cam, c] = dc[cam, c] = h
            num_w = (residuals(w + dw, C0) - residuals(w - dw, C0)) / (2 * h)
            num_c = (residuals(w, C0 + dc) - residuals(w, C0 - dc)) / (2 * h)
            ana_w = np.where(I == cam, (d_phi_i @ Jl[cam])[:, c], 0) + np.where(J == cam, (d_phi_j @ Jl[cam])[:, c], 0)
            ana_c = np.where(I == cam, d_C_i[:, c], 0) + np.where(J == cam, d_C_j[:, c], 0)
            assert np.abs(num_w).max() > 1e-2 and np.abs(num_c).max() > 1e-2  # not a comparison of zeros
            np.testing.assert_allclose(ana_w, num_w, atol=1e-6)
            np.testing.assert_allclose(ana_c, num_c, atol=1e-6)
    # the series branch near 0 against its own truncation I + W / 2 + W^2 / 6, and both branches meeting at 1e-4
    axis = np.array([0.6, -0.64, 0.48])
    for th in (0.0, 3e-5, 0.99e-4):
        W = _skew(th * axis)
        np.testing.assert_allclose(_left_jacobian((th * axis)[None])[0], np.eye(3) + W / 2 + W @ W / 6,
                                   rtol=0, atol=1e-13)  # the series' next terms are ~th^3 / 24
    below, above = _left_jacobian(np.stack([0.999999e-4 * axis, 1.000001e-4 * axis]))
    np.testing.assert_allclose(below, above, rtol=0, atol=1e-9)


def test_the_cheirality_margins_have_the_signs_of_the_rays_meeting_depths_and_at_most_their_sine(wide_scene):
    """Against the closest points of each pair of rays, solved one match at a time (lstsq of C_i + l a = C_j + m b),
    at the true poses and with camera 3 mirrored through camera 1 (its pairs' points then behind)."""
    gt = wide_scene["cam2world"]
    I, J, r1, r2 = stacked(wide_scene, 0.1, step=6)
    R, C = gt[:, :3, :3], gt[:, :3, 3].copy()
    C_m = C.copy()
    C_m[3] = 2 * C[1] - C[3]
    for C_ in (C, C_m):
        got = cheirality_margins(R, C_, I, J, r1, r2)
        a, b = (R[I] @ r1[..., None])[..., 0], (R[J] @ r2[..., None])[..., 0]
        depths = np.array([np.linalg.lstsq(np.stack([a[k], -b[k]], 1), C_[J[k]] - C_[I[k]], rcond=None)[0]
                           for k in range(len(I))])
        sine = np.linalg.norm(np.cross(a, b), axis=1)
        parallax = sine > 0.02  # near-parallel rays: the depths' sign is noise in lstsq
        assert parallax.mean() > 0.8
        np.testing.assert_array_equal(np.sign(got[parallax]), np.sign(depths[parallax]))
        assert (np.abs(got) <= sine[:, None] + 1e-12).all()
    assert (cheirality_margins(R, C, I, J, r1, r2) > 0).all(1).mean() > 0.95  # true poses: the outliers aside
    behind = cheirality_margins(R, C_m, I, J, r1, r2)[((I == 1) & (J == 3))]
    assert (behind < 0).all(1).mean() > 0.8  # mirrored: the pair's points behind both cameras


def test_the_cheirality_jacobian_agrees_with_central_differences(wide_scene):
    I, J, r1, r2 = stacked(wide_scene, 0.2, step=6)
    c2w = perturbed(wide_scene["cam2world"], rot_deg=20.0, centre=0.5, seed=3)
    c2w[3, :3, 3] = 2 * c2w[1, :3, 3] - c2w[3, :3, 3]  # some margins negative, some positive
    R, C = c2w[:, :3, :3], c2w[:, :3, 3]
    d_phi_i, d_phi_j, d_C_i, d_C_j = _cheirality_jacobian(R, C, I, J, r1, r2)
    h = 1e-6
    for cam in (1, 3):
        for c in range(3):
            w = np.zeros((len(R), 3))
            w[cam, c] = h
            dc = np.zeros_like(C)
            dc[cam, c] = h
            num_w = (cheirality_margins(_rotvec_to_matrix(w) @ R, C, I, J, r1, r2)
                     - cheirality_margins(_rotvec_to_matrix(-w) @ R, C, I, J, r1, r2)) / (2 * h)
            num_c = (cheirality_margins(R, C + dc, I, J, r1, r2) - cheirality_margins(R, C - dc, I, J, r1, r2)) / (2 * h)
            ana_w = np.where((I == cam)[:, None], d_phi_i[..., c], 0) + np.where((J == cam)[:, None], d_phi_j[..., c], 0)
            ana_c = np.where((I == cam)[:, None], d_C_i[..., c], 0) + np.where((J == cam)[:, None], d_C_j[..., c], 0)
            assert np.abs(num_w).max() > 1e-2 and np.abs(num_c).max() > 1e-2  # not a comparison of zeros
            np.testing.assert_allclose(ana_w, num_w, atol=1e-6)
            np.testing.assert_allclose(ana_c, num_c, atol=1e-6)


def _camera_2_beside_camera_1():
    """Four cameras looking down +z; 0, 1 and 3 at their places, camera 2 seen by pair (1, 2) at x = 1.05 (just past
    camera 1 on the x axis) and by pairs (0, 2) and (2, 3) at x = 0.95 (just short of it): the exact rays of 300
    points for each of six pairs, and the centres."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2, 3, 300), rng.uniform(-1.5, 2.5, 300), rng.uniform(3, 6, 300)]
    centres = {0: [0.0, 0, 0], 1: [1.0, 0, 0], 3: [1.0, 1, 0]}
    here, there = [1.05, 0, 0], [0.95, 0, 0]

    def rays(c):
        v = X - np.asarray(c)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    I, J, r1, r2 = [], [], [], []
    for i, j, c2 in ((0, 1, None), (0, 3, None), (1, 3, None), (1, 2, here), (0, 2, there), (2, 3, there)):
        I.append(np.full(len(X), i))
        J.append(np.full(len(X), j))
        r1.append(rays(centres.get(i, c2)))
        r2.append(rays(centres.get(j, c2)))
    I, J, r1, r2 = (np.concatenate(x) for x in (I, J, r1, r2))
    return I, J, r1, r2, centres, here, there


def test_a_camera_pulled_through_its_neighbour_by_other_pairs_passes_without_the_cheirality_residuals_only():
    """Cameras 0, 1, 3 held; camera 2 seen by pair (1, 2) at x = 1.05, just past camera 1 along the x axis, and by
    pairs (0, 2) and (2, 3) at x = 0.95, just short of it. x = 0.95 fits every match exactly, with pair (1, 2)'s
    direction reversed (the epipolar residuals cannot tell): the ring's failure in small. With the cheirality
    residuals the fit stops at camera 1 instead, its pair's points still in front."""
    I, J, r1, r2, centres, here, there = _camera_2_beside_camera_1()
    R0, C0 = np.tile(np.eye(3), (4, 1, 1)), np.array([centres[0], centres[1], here, centres[3]])
    args = (R0, C0, I, J, r1, r2, np.full(len(I), 1 / 200))
    _, C, rep = solve_poses(*args, held=[0, 1, 3], keep_scale=False, cheirality=False)
    np.testing.assert_allclose(C[2], there, atol=1e-6)
    assert rep["mirrored_pairs"] == [[1, 2]]
    R, C, rep = solve_poses(*args, held=[0, 1, 3], keep_scale=False)
    assert C[2, 0] > 1 - 1e-3 and np.abs(C[2, 1:]).max() < 1e-2 and rep["mirrored_pairs"] == []
    np.testing.assert_allclose(R[2], np.eye(3), atol=1e-2)
    # the second descent (uncharged, then charged) passes through camera 1, then turns camera 2 until pair (1, 2)'s
    # rays are parallel, which the charge cannot see: it costs less, but reverses the pair, so it is refused
    assert rep["descent"] == "aligned"


def test_a_camera_the_charge_stops_at_a_wall_is_freed_by_the_descent_that_crosses_it_uncharged():
    """An 8-view ring started 15 degrees and 0.3 units off, 10% outliers: the charged descent from the start stops
    with a camera 14 degrees off; the uncharged descent, then the charged one from where it ended, costs less,
    reverses no pair and lands within half a degree."""
    gt, start, (I, J, r1, r2, scale), _ = ring_matches(8, 48, 64, 2, 0.1, 15.0, 0.3, seed=7)
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale)
    errors = {}
    for second in (False, True):
        R, C, rep = solve_poses(*args, held=[0], keep_scale=True, second_descent=second)
        c2w = np.tile(np.eye(4), (8, 1, 1))
        c2w[:, :3, :3], c2w[:, :3, 3] = R, C
        errors[second] = direction_errors(c2w, gt)[0]
        assert rep["descent"] == ("uncharged first" if second else "aligned") and rep["mirrored_pairs"] == []
    assert errors[False] > 10 and errors[True] < 0.5, errors


def test_random_matches_that_meet_behind_a_camera_do_not_pull_the_charged_fit():
    """An 8-view ring started 15 degrees and 0.3 units off, 10% random matches, which fail nothing: the charged fit
    lands where the uncharged one does (each match charged for its own margin, session 33's form, ended 1.6 degrees
    off against 0.24)."""
    gt, start, (I, J, r1, r2, scale), _ = ring_matches(8, 48, 64, 2, 0.1, 15.0, 0.3, seed=0)
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale)
    errors = []
    for ch in (False, True):
        R, C, rep = solve_poses(*args, held=[0], keep_scale=True, cheirality=ch)
        c2w = np.tile(np.eye(4), (8, 1, 1))
        c2w[:, :3, :3], c2w[:, :3, 3] = R, C
        errors.append(direction_errors(c2w, gt)[0])
    assert errors[0] < 0.5 and abs(errors[1] - errors[0]) < 0.1, errors


def test_rays_turned_parallel_count_as_behind_only_when_asked():
    """Matches with the same ray in both cameras (r2 = r1) meet in front of two cameras converging by 4 degrees, 0.2
    apart; turned parallel (camera 1 with camera 0's rotation) nothing is counted after, so the pair is not flagged
    by default; with ``parallel_is_behind`` the matches counted before count as behind."""
    rng = np.random.default_rng(3)
    r = np.c_[rng.uniform(-0.4, 0.4, (200, 2)), np.ones(200)]
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    I, J = np.zeros(200, int), np.ones(200, int)
    C0 = np.array([[0.0, 0, 0], [0.2, 0, 0]])
    R0 = np.stack([np.eye(3), _rotvec_to_matrix(np.array([0.0, -np.radians(4), 0]))])
    assert in_front_share(R0, C0, I, J, r, r, 1, np.zeros(200, int))[0][0] > 0.9
    R = np.stack([np.eye(3), np.eye(3)])
    assert in_front_share(R, C0, I, J, r, r, 1, np.zeros(200, int))[1][0] == 0  # nothing counted after
    assert mirrored_pairs(R0, C0, R, C0, I, J, r, r) == []
    assert mirrored_pairs(R0, C0, R, C0, I, J, r, r, parallel_is_behind=True) == [[0, 1]]


@pytest.mark.parametrize("jac", ["analytic", "2-point"])
def test_the_sparse_jacobian_path_agrees_with_the_dense_one(jac):
    sc = make_scene(10, 64, 96, seed=62, focal_range=(76.0, 104.0))
    gt = sc["cam2world"]
    I, J, r1, r2 = stacked(sc, 0.1, step=6)
    start = perturbed(gt, rot_deg=1.0, centre=0.1, seed=9)
    scale = np.full(len(I), 1.0 / 90.0)
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, scale)
    Rd, Cd, rep_d = solve_poses(*args, held=[0], keep_scale=True, sparse=False, jac=jac)
    Rs, Cs, rep_s = solve_poses(*args, held=[0], keep_scale=True, sparse=True, jac=jac)
    assert rep_d["median_residual_after"] < 0.1 * rep_d["median_residual_before"]
    assert rep_s["evaluations"] < 100  # lsmr at its default tolerances crawled (hundreds, 1 degree off)
    # two solvers stopping at ftol 1e-6: the same poses to a few hundredths of a degree and 1% in the centres
    # (the baselines' lengths are the weakly held part: matches fix directions only), both near the truth
    np.testing.assert_allclose(Rs, Rd, atol=1e-3)
    np.testing.assert_allclose(Cs, Cd, atol=1e-2 * np.abs(Cd).max())
    for R, C in ((Rd, Cd), (Rs, Cs)):
        c2w = np.tile(np.eye(4), (len(R), 1, 1))
        c2w[:, :3, :3], c2w[:, :3, 3] = R, C
        assert max(direction_errors(c2w, gt)) < 0.5


def test_the_analytic_jacobian_fit_agrees_with_the_finite_difference_one_on_outlier_laden_matches(wide_scene):
    gt = wide_scene["cam2world"]
    I, J, r1, r2 = stacked(wide_scene, 0.3)
    start = perturbed(gt, rot_deg=3.0, centre=0.3, seed=5)
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, np.full(len(I), 2.0 / 135.0))
    Ra, Ca, rep_a = solve_poses(*args, held=[0], keep_scale=True, jac="analytic")
    Rn, Cn, rep_n = solve_poses(*args, held=[0], keep_scale=True, jac="2-point")
    np.testing.assert_allclose(Ra, Rn, atol=2e-4)
    np.testing.assert_allclose(Ca, Cn, atol=2e-3 * np.abs(Cn).max())
    assert rep_a["inliers_after"] == pytest.approx(rep_n["inliers_after"], abs=3)
    with pytest.raises(ValueError, match="jac expected"):
        solve_poses(*args, held=[0], keep_scale=True, jac="3-point")


def test_known_poses_and_intrinsics_come_back_as_given(mid_scene):
    sc, views, preds, _ = mid_scene
    known_c2w = {1: torch.from_numpy(sc["cam2world"][1]).float(), 3: torch.from_numpy(sc["cam2world"][3]).float()}
    known_K = {0: torch.from_numpy(sc["K"][0]).float() * torch.tensor([[1.1, 1, 1], [1, 1.1, 1], [1, 1, 1]])}
    recon = global_align(views, preds, K=known_K, cam2world=known_c2w, config=AlignConfig(quiet=True))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["held"] == [1, 3]
    for k, T in known_c2w.items():
        assert torch.equal(out.cam2world[k], T)
    assert torch.equal(out.K[0], known_K[0])  # a known (here deliberately 10% off) focal is not replaced
    assert not torch.equal(out.cam2world[2], recon.cam2world[2])  # the free cameras moved
    # two known centres fix the scale: the free cameras stay at the scene's size
    assert np.linalg.norm(out.cam2world[2, :3, 3].numpy() - sc["cam2world"][2, :3, 3]) < 0.5


def test_masked_pixels_give_no_matches(mid_scene):
    """Pixels masked out (descriptor confidence 0, as ``reconstruct``'s masks leave them) are left out of the fit."""
    _, views, preds, recon = mid_scene
    cfg = EpipolarConfig(patch=8, refit_depth=False)
    full = refine_epipolar(views, preds, recon, config=cfg).info["epipolar"]["matches"]
    masked = {}
    for key, p in preds.items():
        c1, c2 = p.desc_conf1.clone(), p.desc_conf2.clone()
        c1[..., :48] = 0  # the left half of view 1 of every pass
        masked[key] = dataclasses.replace(p, desc_conf1=c1, desc_conf2=c2)
    half = refine_epipolar(views, masked, recon, config=cfg).info["epipolar"]["matches"]
    assert 0 < half < 0.7 * full


def test_the_stage_refines_views_of_several_sizes_and_keeps_their_canvas():
    shapes = [(64, 96), (96, 64), (64, 96), (96, 64), (64, 96)]  # (h, w): portrait among landscape
    sc = make_scene(5, shapes=shapes, seed=61, focal_range=(76.0, 104.0))
    views = views_of(sc)
    preds = with_descriptors(gt_preds(sc, [(i, j) for i in range(5) for j in range(i + 1, 5)], seed=2, pair_rot_deg=8.0, noise=0.02), sc)
    recon = global_align(views, preds, config=AlignConfig(quiet=True))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["median_residual_after"] < 0.5 * rep["median_residual_before"]
    rot, dirs = direction_errors(out.cam2world.double().numpy(), sc["cam2world"])
    assert rot < 15 and dirs < 15
    assert out.map_sizes == recon.map_sizes == [(w, h) for h, w in shapes]
    assert not (out.depth_z > 0)[~out.regions].any()


def test_two_centres_the_fit_brings_together_count_as_a_reversed_pair_and_are_refitted_held():
    from pointmap.align.epipolar import collapsed_pairs

    C0 = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    C = np.array([[0.0, 0, 0], [1.5, 0, 0], [1.55, 0, 0]])  # cameras 1 and 2 met: 0.05 of their aligned 1.0
    I, J = np.array([0, 0, 1, 1]), np.array([1, 2, 2, 2])
    assert collapsed_pairs(C0, C, I, J) == [[1, 2]]
    C[2] = np.nan
    assert collapsed_pairs(C0, C, I, J) == [[0, 2], [1, 2]]  # no finite centre: nothing to keep


def test_a_fit_that_collapses_two_centres_is_refitted_with_one_of_them_held(mid_scene, monkeypatch):
    _, views, preds, recon = mid_scene
    real = epi.solve_poses
    calls = []

    def collapsing(R0, C0, *args, **kwargs):
        R, C, rep = real(R0, C0, *args, **kwargs)
        calls.append(list(kwargs["held"]))
        if len(calls) == 1:
            C[3] = C[2] + 1e-6  # camera 3 settles onto camera 2: that pair's residuals vanish
        return R, C, rep

    monkeypatch.setattr(epi, "solve_poses", collapsing)
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["first_fit"]["mirrored_pairs"] == [[2, 3]] and rep["collapsed_pairs"] == []
    assert rep["first_fit"]["collapsed_pairs"] == [[2, 3]]
    assert calls[1] == [0] + rep["pinned"] and rep["pinned"] in ([2], [3])
    gap = (out.cam2world[2, :3, 3] - out.cam2world[3, :3, 3]).norm()
    assert float(gap) > 0.2 * float((recon.cam2world[2, :3, 3] - recon.cam2world[3, :3, 3]).norm())


def test_the_stages_own_focals_leave_out_masked_pixels_as_the_alignment_does():
    sc = make_scene(4, 64, 96, seed=61, focal_range=(76.0, 104.0))
    preds = {}
    for k, p in with_descriptors(gt_preds(sc, complete_pairs(4)), sc).items():
        m = torch.ones(64, 96)
        m[:, :40] = 0  # the user's mask; the model's points there are wrong (a moving object, a reflection)
        p1, p2 = p.pts1_cam1.clone(), p.pts2_cam1.clone()
        p1[0, :, :40, :2] *= 1.6
        p2[0, :, :40, :2] *= 1.6
        preds[k] = dataclasses.replace(p, pts1_cam1=p1, pts2_cam1=p2, conf1=p.conf1 * m, conf2=p.conf2 * m,
                                       desc_conf1=p.desc_conf1 * m, desc_conf2=p.desc_conf2 * m)
    views = views_of(sc)
    aligned = global_align(views, preds, config=AlignConfig(quiet=True, niter=40))
    refined = refine_epipolar(views, preds, aligned, config=EpipolarConfig(patch=8))
    assert refined.info["epipolar"]["applied"]
    err = (refined.K[:, 0, 0].numpy() / sc["K"][:, 0, 0] - 1)
    assert np.abs(err).max() < 1e-3, err  # was -36.6% with the masked pixels in the Weiszfeld focal


def test_the_depth_refit_does_not_repeat_the_warnings_about_the_views_the_alignment_gave():
    """pm.reconstruct aligns, then the epipolar stage re-fits the depths with global_align over the same views: the
    views' own warnings (identical images, repeated names) were given once by the first alignment, not again."""
    import warnings

    sc = make_scene(4, 64, 96, seed=61, focal_range=(76.0, 104.0))
    for key in ("cam2world", "K", "depth", "pts_world", "images"):
        sc[key][3] = sc[key][0]
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    views = views_of(sc)
    views[1].name = views[2].name = "a.png"
    preds = with_descriptors(gt_preds(sc, pairs, seed=2, pair_rot_deg=8.0, noise=0.02), sc)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        recon = global_align(views, preds, config=AlignConfig(quiet=True))
        first = [str(w.message)[:20] for w in caught]
        out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8))
    again = [str(w.message)[:20] for w in caught[len(first):]]
    assert "identical images [(0" in first and "duplicate image name" in first
    assert "align_refit" in out.info and not [m for m in again if m.startswith(("identical", "duplicate"))], again


# gaps a mutation review of epipolar.py found (23 of 52 mutants survived; 14 of them mattered)
def two_cameras(points, c_j=(1.0, 0.0, 0.0)):
    """Two cameras with the world's rotation, at the origin and at c_j, and each one's unit ray to every point."""
    C = np.array([[0.0, 0, 0], list(c_j)])
    a = points - C[0]
    b = points - C[1]
    return np.tile(np.eye(3), (2, 1, 1)), C, a / np.linalg.norm(a, axis=1, keepdims=True), \
        b / np.linalg.norm(b, axis=1, keepdims=True)


def test_a_pair_index_equal_to_the_number_of_pairs_is_refused():
    R, C, r1, r2 = two_cameras(np.array([[0.0, 0, 5], [1.0, 1, 5], [-1.0, 0, 4]]))
    I, J = np.zeros(3, int), np.ones(3, int)
    with pytest.raises(ShapeError, match="one pair index"):
        in_front_share(R, C, I, J, r1, r2, 1, np.array([0, 0, 1]))  # pair 1 of 1


def test_points_met_behind_one_of_the_two_cameras_are_not_in_front():
    """Rays that meet at points in front of camera 0 and behind camera 1 (camera 1's ray points away from them)."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1, 2, 40), rng.uniform(-1, 1, 40), rng.uniform(3, 6, 40)]
    R, C, r1, r2 = two_cameras(X)
    I, J, pid = np.zeros(40, int), np.ones(40, int), np.zeros(40, int)
    share, counted = in_front_share(R, C, I, J, r1, r2, 1, pid)
    assert counted[0] == 40 and share[0] == 1.0
    share, counted = in_front_share(R, C, I, J, r1, -r2, 1, pid)  # camera 1's rays reversed: behind it only
    assert counted[0] == 40 and share[0] == 0.0


def test_the_anchor_defaults_to_the_first_held_camera_and_must_be_held(scene):
    """With two held cameras and keep_scale, the distance kept is the free cameras' mean distance from the first
    held one (camera 0 here, whatever order held is given in)."""
    I, J, r1, r2 = stacked(scene)
    start = perturbed(scene["cam2world"], seed=7, held=(0, 2))
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, np.full(len(I), 0.5 / 45.0))
    R, C, _ = solve_poses(*args, held=[2, 0], keep_scale=True)
    R0, C0, _ = solve_poses(*args, held=[2, 0], keep_scale=True, anchor=0)
    _, C2, _ = solve_poses(*args, held=[2, 0], keep_scale=True, anchor=2)
    assert np.abs(C0 - C2).max() > 1e-4  # the anchor matters here (the two held centres mostly fix the scale)
    np.testing.assert_array_equal(C, C0)
    np.testing.assert_array_equal(R, R0)
    with pytest.raises(ShapeError, match="anchor"):
        solve_poses(*args, held=[0, 2], keep_scale=True, anchor=1)


def test_a_narrow_rotation_prior_holds_weakly_constrained_rotations_near_the_aligned_ones():
    """Exact matches of four views, the start 4 degrees off, a wide Cauchy scale (the matches pull weakly): with a
    0.5-degree prior each rotation stays within about that of where it started; with no prior to speak of the fit
    takes the whole 4 degrees. (prior_deg is in degrees: left in radians, 0.5 is a 29-degree prior.)"""
    sc = make_scene(4, 32, 48, seed=61)
    I, J, r1, r2 = stacked(sc, step=6)
    start = perturbed(sc["cam2world"], rot_deg=4.0, centre=0.0, seed=1)
    args = (start[:, :3, :3], start[:, :3, 3], I, J, r1, r2, np.full(len(I), 0.2))

    def moved(R):
        return max(np.degrees(np.arccos(np.clip((np.trace(R[k].T @ start[k, :3, :3]) - 1) / 2, -1, 1)))
                   for k in range(1, 4))

    tight, _, _ = solve_poses(*args, held=[0], keep_scale=True, prior_deg=0.5, cheirality=False)
    loose, _, _ = solve_poses(*args, held=[0], keep_scale=True, prior_deg=1e4, cheirality=False)
    assert moved(tight) < 1.0 and moved(loose) > 3.5, (moved(tight), moved(loose))


def test_a_pair_already_reversed_at_the_start_is_not_charged():
    """Cameras 0, 1, 3 held; camera 2 starts at x = 0.95, where every match fits exactly, but pair (1, 2)'s matches
    were made at x = 1.05, so that pair's points meet behind its cameras from the start. Only pairs whose points met
    mostly in front at the start are charged: the fit has nothing to do and camera 2 stays where it is (charging
    that pair pushed it through camera 1, against every other pair)."""
    I, J, r1, r2, centres, here, there = _camera_2_beside_camera_1()
    R0, C0 = np.tile(np.eye(3), (4, 1, 1)), np.array([centres[0], centres[1], there, centres[3]])
    R, C, _ = solve_poses(R0, C0, I, J, r1, r2, np.full(len(I), 1 / 200), held=[0, 1, 3], keep_scale=False)
    np.testing.assert_allclose(C[2], there, atol=1e-6)
    np.testing.assert_allclose(R[2], np.eye(3), atol=1e-6)


def test_pairs_predicted_only_in_the_reverse_order_are_matched_once():
    p = object()
    assert epi._pair_list({(1, 0): p, (2, 0): p, (0, 2): p, (3, 3): p}) == [(0, 2), (1, 0)]


def test_the_mirror_check_flags_a_share_under_three_tenths_and_wants_ten_counted_matches():
    """Pair (0, 1): 80 matches meet in front of both cameras, 20 (both rays turned around) behind both. Camera 1
    mirrored through camera 0 flips every meeting side: 0.8 in front before, 0.2 after, a reversal (share < 0.3);
    with only 9 of the matches there are too few to tell."""
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-1, 2, 100), rng.uniform(-1, 1, 100), rng.uniform(3, 6, 100)]
    R, C, r1, r2 = two_cameras(X)
    r1[80:], r2[80:] = -r1[80:], -r2[80:]
    I, J = np.zeros(100, int), np.ones(100, int)
    C_m = C.copy()
    C_m[1] = -C[1]
    pid = np.zeros(100, int)
    assert in_front_share(R, C, I, J, r1, r2, 1, pid)[0][0] == 0.8
    assert in_front_share(R, C_m, I, J, r1, r2, 1, pid)[0][0] == pytest.approx(0.2)
    assert mirrored_pairs(R, C, R, C_m, I, J, r1, r2) == [[0, 1]]
    assert mirrored_pairs(R, C, R, C_m, I[:9], J[:9], r1[:9], r2[:9]) == []  # 9 counted matches: too few
    assert mirrored_pairs(R, C, R, C_m, I[:10], J[:10], r1[:10], r2[:10]) == [[0, 1]]


def test_the_default_threshold_is_the_maps_longer_side_over_56(mid_scene):  # noqa: F811
    _, views, preds, recon = mid_scene
    rep = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8, refit_depth=False)).info["epipolar"]
    h, w = recon.depth_z.shape[1:]
    assert (h, w) == (64, 96) and rep["threshold_px"] == 96 / 56


def test_a_known_focal_is_the_one_the_fit_uses_whatever_the_pointmaps_say(mid_scene, monkeypatch):  # noqa: F811
    sc, views, preds, _ = mid_scene
    known = {0: torch.from_numpy(sc["K"][0]).float()}
    recon = global_align(views, preds, K=known, config=AlignConfig(quiet=True))
    real = epi.own_focals
    outs = []
    for f0 in (1.0, 3.0):  # image 0's own-frame focal as the maps give it, then three times that
        def own(preds_, n, f0=f0):
            f = real(preds_, n)
            f[0] *= f0
            return f
        monkeypatch.setattr(epi, "own_focals", own)
        outs.append(refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8, refit_depth=False)))
    assert outs[0].info["epipolar"]["applied"]
    assert outs[0].info["epipolar"]["median_residual_before"] == outs[1].info["epipolar"]["median_residual_before"]
    assert torch.equal(outs[0].cam2world, outs[1].cam2world) and torch.equal(outs[1].K[0], known[0])


def test_one_known_pose_holds_the_gauge_and_the_free_cameras_keep_their_mean_distance_from_it(mid_scene):  # noqa: F811
    sc, views, preds, _ = mid_scene
    recon = global_align(views, preds, cam2world={1: torch.from_numpy(sc["cam2world"][1]).float()},
                         config=AlignConfig(quiet=True))
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8, refit_depth=False))
    rep = out.info["epipolar"]
    assert rep["applied"] and rep["held"] == [1]
    free = [0, 2, 3, 4]

    def mean_dist(c2w):
        return float((c2w[free, :3, 3].double() - c2w[1, :3, 3].double()).norm(dim=1).mean())

    assert not torch.allclose(out.cam2world[free], recon.cam2world[free], atol=1e-4)  # the free cameras moved
    assert mean_dist(out.cam2world) == pytest.approx(mean_dist(recon.cam2world), rel=1e-3)


def test_with_parallel_is_behind_matches_parallel_at_the_start_cannot_vouch_for_a_pair_after():
    """Pair (0, 1): 60 matches of points in front, 40 of parallel rays (not counted at the start). Camera 1 mirrored
    through camera 0 and turned 6 degrees: the 60 meet behind, the 40 now converge in front. Over the matches counted
    at the start none is in front: reversed; counting the 40 (0.4 in front) hides it."""
    rng = np.random.default_rng(2)
    X = np.c_[rng.uniform(-1, 2, 60), rng.uniform(-1, 1, 60), rng.uniform(3, 6, 60)]
    R0, C0, a, b = two_cameras(X)
    u = np.c_[rng.uniform(-0.2, 0.2, (40, 2)), np.ones(40)]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r1, r2 = np.r_[a, u], np.r_[b, u]
    I, J = np.zeros(100, int), np.ones(100, int)
    R = R0.copy()
    R[1] = _rotvec_to_matrix(np.array([0, np.radians(6), 0]))
    C = C0.copy()
    C[1] = -C0[1]
    share, counted = in_front_share(R, C, I, J, r1, r2, 1, np.zeros(100, int))
    assert counted[0] == 100 and share[0] == pytest.approx(0.4)
    assert mirrored_pairs(R0, C0, R, C, I, J, r1, r2) == []  # by default over the matches counted after: 0.4
    assert mirrored_pairs(R0, C0, R, C, I, J, r1, r2, parallel_is_behind=True) == [[0, 1]]


def test_each_matchs_cauchy_scale_is_the_threshold_over_the_focal_of_its_first_camera(mid_scene, monkeypatch):  # noqa: F811
    """The residual is an angle in camera I's frame, so its scale is threshold_px over camera I's focal (the
    scene's focals differ by up to a third)."""
    _, views, preds, recon = mid_scene
    real, seen = epi.solve_poses, []

    def spy(R0, C0, I, J, r1, r2, scale, **kwargs):
        seen.append((I, J, scale))
        return real(R0, C0, I, J, r1, r2, scale, **kwargs)

    monkeypatch.setattr(epi, "solve_poses", spy)
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8, refit_depth=False))
    I, J, scale = seen[0]
    f = out.K[:, 0, 0].double().numpy()  # map pixels: these views are their maps (map_from_original the identity)
    assert np.ptp(f[I]) > 10 and (f[I] != f[J]).any()
    np.testing.assert_allclose(scale, out.info["epipolar"]["threshold_px"] / f[I], rtol=1e-5)


def test_a_known_intrinsic_comes_back_bit_for_bit_from_maps_smaller_than_the_originals(mid_scene):  # noqa: F811
    """The same alignment seen as of photographs 1080/224 times the maps' size: a known K in original pixels goes to
    the map's pixels and back in floating point (one in ten float32 values does not survive the round trip), so
    the stage hands the given one back, not the round trip's."""
    from pointmap.reconstruction import K_to_map, K_to_original

    sc, views, preds, _ = mid_scene
    mfo = torch.tensor([[224 / 1080, 224 / 1080, 0.0, 0.0]]).repeat(5, 1)
    K0 = K_to_original(torch.from_numpy(sc["K"][0]).float(), mfo[0])
    # a known K whose map round trip (float32 map, float64 back, float32) changes it
    for step in range(200):
        K0[0, 0] = K0[1, 1] = float(K0[0, 0]) + 0.37
        back = K_to_original(K_to_map(K0, mfo[0]).double(), mfo[0].double()).float()
        if not torch.equal(back, K0):
            break
    assert not torch.equal(back, K0)
    aligned = global_align(views, preds, K={0: K_to_map(K0, mfo[0])}, config=AlignConfig(quiet=True))
    recon = dataclasses.replace(aligned, map_from_original=mfo, K=K_to_original(aligned.K, mfo))
    recon.K[0] = K0
    assert recon.info["align"]["known_K_indices"] == [0]
    out = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=8, refit_depth=False))
    assert out.info["epipolar"]["applied"] and torch.equal(out.K[0], K0)
