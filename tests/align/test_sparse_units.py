"""Fast unit tests of the sparse refinement's pieces: its configuration, how matches are read and filtered
(gather_matches), and small refinements of a tiny synthetic scene."""

import math

import numpy as np
import pytest
import torch

from pointmap.align.sparse import SparseConfig, gather_matches, refine_matches
from pointmap.errors import ShapeError
from pointmap.reconstruction import Reconstruction


def flat_recon(n=3, h=8, w=12, depth=2.0):
    """n views of an h x w map, identity poses, constant depth: enough for reading and filtering matches."""
    K = torch.tensor([[10.0, 0, (w - 1) / 2], [0, 10.0, (h - 1) / 2], [0, 0, 1]]).repeat(n, 1, 1)
    return Reconstruction(images=torch.zeros(n, h, w, 3), cam2world=torch.eye(4).repeat(n, 1, 1), K=K,
                          depth_z=torch.full((n, h, w), depth), conf=torch.ones(n, h, w))


def grid_matches(h=8, w=12, step=1):
    """Every pixel of an h x w grid (row-major), matched to itself, score 1."""
    v, u = np.mgrid[0:h:step, 0:w:step]
    xy = np.stack([u.ravel(), v.ravel()], -1).astype(float)
    return xy, xy.copy(), np.ones(len(xy))


# --- the configuration


def test_the_sparse_config_defaults_are_the_documented_ones():
    cfg = SparseConfig()
    assert (cfg.niter, cfg.robust_px, cfg.depth_prior, cfg.optimize_focal, cfg.optimize_pp, cfg.min_score,
            cfg.max_matches_per_pair, cfg.quiet) == (100, None, 0.01, True, False, 0.0, 4096, False)


@pytest.mark.parametrize("field, value, message", [
    ("niter", 0, "niter expected an int >= 1, got 0"),
    ("robust_px", math.inf, "robust_px expected pixels > 0 (None: automatic), got inf"),
    ("robust_px", -1.0, "robust_px expected pixels > 0"),
    ("depth_prior", -0.01, "depth_prior expected a weight >= 0, got -0.01"),
    ("depth_prior", math.inf, "depth_prior expected a weight >= 0, got inf"),
    ("max_matches_per_pair", 0, "max_matches_per_pair expected an int >= 1, got 0"),
    ("min_score", math.inf, "min_score expected a finite score, got inf"),
])
def test_a_config_at_the_edge_of_its_ranges_is_refused_naming_the_field_and_the_value(field, value, message):
    with pytest.raises(ShapeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        SparseConfig(**{field: value})


def test_a_config_just_inside_its_ranges_is_accepted():
    cfg = SparseConfig(niter=1, robust_px=1e-3, depth_prior=0.0, max_matches_per_pair=1, min_score=-5.0)
    assert cfg.niter == 1 and cfg.depth_prior == 0.0 and cfg.max_matches_per_pair == 1


# --- reading and filtering matches


def test_matches_given_as_two_arrays_are_all_kept_with_the_same_weight_as_a_score_of_one():
    recon = flat_recon()
    xy1, xy2, s = grid_matches()
    I, J, A, B, S = gather_matches(recon, {(0, 1): (xy1, xy2)}, SparseConfig())
    assert len(I) == len(xy1) and torch.equal(S, torch.ones(len(xy1), dtype=torch.float64))
    assert torch.equal(A, torch.as_tensor(xy1)) and torch.equal(B, torch.as_tensor(xy2))


def test_match_objects_are_read_as_xy1_in_the_first_image_and_xy2_in_the_second():
    class Matches:
        def __init__(self, xy1, xy2, score):
            self.xy1, self.xy2, self.score = xy1, xy2, score

    recon = flat_recon()
    xy1, _, s = grid_matches()
    xy2 = xy1[::-1].copy()  # a different pixel in image 1 for each match
    I, J, A, B, S = gather_matches(recon, {(0, 2): Matches(xy1, xy2, 0.5 * s)}, SparseConfig())
    assert torch.equal(A, torch.as_tensor(xy1)) and torch.equal(B, torch.as_tensor(xy2))
    assert set(I.tolist()) == {0} and set(J.tolist()) == {2} and torch.allclose(S, torch.full_like(S, 0.5))


def test_matches_whose_arrays_differ_in_length_are_refused_naming_each_shape():
    recon = flat_recon()
    xy1, xy2, s = grid_matches()
    for bad in [(xy1, xy2[:-1], s), (xy1, xy2, s[:-1])]:
        with pytest.raises(ShapeError, match=r"matches\[\(0, 1\)\] expected .* got xy1 \[96, 2\], xy2 \[9\d, 2\], "
                                             r"score \[9\d\]"):
            gather_matches(recon, {(0, 1): bad}, SparseConfig())


def test_a_pair_of_an_image_with_itself_is_ignored():
    recon = flat_recon()
    m = grid_matches()
    I, J, *_ = gather_matches(recon, {(0, 1): m, (2, 2): m}, SparseConfig())
    assert len(I) == len(m[0]) and not bool((I == J).any())
    with pytest.raises(ShapeError, match="no usable matches"):
        gather_matches(recon, {(1, 1): m}, SparseConfig())


def test_a_match_scored_exactly_min_score_is_dropped_and_one_just_above_is_kept():
    recon = flat_recon()
    xy1, xy2, _ = grid_matches()
    score = np.full(len(xy1), 0.3)
    score[:10] = 0.3 + 1e-9
    I, *_ , S = gather_matches(recon, {(0, 1): (xy1, xy2, score)}, SparseConfig(min_score=0.3))
    assert len(I) == 10
    I, *_ = gather_matches(recon, {(0, 1): (xy1, xy2, np.zeros(len(xy1)) + 0.2)}, SparseConfig())
    assert len(I) == len(xy1)  # the default keeps every positive score


def test_a_match_left_of_or_above_the_image_is_dropped_not_read_from_the_far_edge():
    recon = flat_recon()
    xy1, xy2, s = grid_matches()
    n = len(xy1)
    for bad in ([-3.0, 2.0], [2.0, -3.0], [-0.6, 2.0]):
        for first in (True, False):  # outside image i, or outside image j
            a = np.r_[xy1, [bad if first else [1.0, 1.0]]]
            b = np.r_[xy2, [[1.0, 1.0] if first else bad]]
            I, *_ = gather_matches(recon, {(0, 1): (a, b, np.r_[s, 1.0])}, SparseConfig())
            assert len(I) == n, (bad, first)


def test_a_match_on_the_first_column_and_row_is_kept():
    recon = flat_recon()
    xy = np.array([[0.0, 0.0], [0.0, 7.0], [11.0, 0.0], [11.0, 7.0]])
    I, *_ = gather_matches(recon, {(0, 1): (xy, xy, np.ones(4))}, SparseConfig())
    assert len(I) == 4


def test_the_depth_of_a_match_is_read_at_its_nearest_pixel_of_the_first_image():
    recon = flat_recon()
    depth = recon.depth_z.clone()
    depth[0, 2, 3] = 0  # image 0 has no depth at (u=3, v=2)
    depth[1] = 0  # image 1 has none at all: matches (0, 1) still have their depth in image 0
    recon = Reconstruction(images=recon.images, cam2world=recon.cam2world, K=recon.K, depth_z=depth, conf=recon.conf)
    xy1 = np.array([[2.6, 2.0], [3.0, 1.6], [3.4, 2.4], [2.4, 2.0], [3.0, 2.6], [5.0, 5.0]])
    xy2 = np.full((6, 2), 4.0)
    I, J, A, *_ = gather_matches(recon, {(0, 1): (xy1, xy2, np.ones(6))}, SparseConfig())
    # the first three round to (3, 2): dropped; (2.4, 2) -> (2, 2), (3, 2.6) -> (3, 3) and (5, 5) keep theirs
    assert A.tolist() == [[2.4, 2.0], [3.0, 2.6], [5.0, 5.0]]
    with pytest.raises(ShapeError, match="no usable matches"):
        gather_matches(recon, {(1, 0): (xy2, xy1, np.ones(6))}, SparseConfig())  # image 1 has no depth


def test_the_default_keeps_every_match_of_a_large_pair_and_a_cap_keeps_a_random_spread_subset():
    recon = flat_recon(h=24, w=32)
    xy1, xy2, s = grid_matches(24, 32)  # 768 matches, row by row
    I, *_ = gather_matches(recon, {(0, 1): (xy1, xy2, s)}, SparseConfig())
    assert len(I) == len(xy1)
    I, J, A, *_ = gather_matches(recon, {(0, 1): (xy1, xy2, s)}, SparseConfig(max_matches_per_pair=40))
    assert len(I) == 40 and len({tuple(a) for a in A.tolist()}) == 40
    # not the first 40 (the top rows): spread over the whole image
    assert float(A[:, 1].max()) > 12 and float(A[:, 1].min()) < 12
    again = gather_matches(recon, {(0, 1): (xy1, xy2, s)}, SparseConfig(max_matches_per_pair=40))[2]
    assert torch.equal(A, again)  # seeded: the same subset each time


# --- small refinements of a two-view scene whose geometry the test knows exactly

F, H, W = 10.0, 8, 12
BASELINE = 0.5


def two_view_recon(depth0=None, depth=2.0, pp_shift=(0.0, 0.0)):
    """Camera 0 at the origin, camera 1 BASELINE to its right (same orientation), focal F, both maps H x W; image
    0's depth ``depth0`` (default: ``depth`` everywhere). pp_shift moves image 1's principal point in K."""
    K = torch.tensor([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64).repeat(2, 1, 1)
    K[1, 0, 2] += pp_shift[0]
    K[1, 1, 2] += pp_shift[1]
    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[1, 0, 3] = BASELINE
    d = torch.full((2, H, W), depth, dtype=torch.float64)
    if depth0 is not None:
        d[0] = depth0
    return Reconstruction(images=torch.zeros(2, H, W, 3), cam2world=c2w.float(), K=K.float(), depth_z=d.float(),
                          conf=torch.ones(2, H, W))


def project_into_1(xy1, z):
    """Where image 0's pixels xy1 [M, 2] at depths z [M] land in image 1 (true geometry of two_view_recon)."""
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    p = (xy1 - c) / F * z[:, None]  # x, y in camera 0 (= world)
    p[:, 0] -= BASELINE  # in camera 1
    return p / z[:, None] * F + c


def test_the_initial_loss_is_the_cauchy_loss_of_the_reprojection_error_in_pixels():
    recon = two_view_recon()
    v, u = np.mgrid[1:7, 2:10]
    xy1 = np.stack([u.ravel(), v.ravel()], -1).astype(float)
    xy2 = project_into_1(xy1, np.full(len(xy1), 2.0)) + [3.0, 4.0]  # every match 5 px off
    keep = (xy2[:, 0] <= W - 1) & (xy2[:, 1] <= H - 1) & (xy2[:, 0] >= 0)
    m = {(0, 1): (xy1[keep], xy2[keep], np.full(int(keep.sum()), 0.7))}
    for robust_px in (10.0, None):
        rep = refine_matches(recon, m, config=SparseConfig(quiet=True, niter=5, robust_px=robust_px,
                                                           optimize_focal=False), fixed_poses=True).info["sparse"]
        s2 = (robust_px or min(2.0, max(H, W) / 100)) ** 2  # automatic: 0.12 px on a 12-pixel-wide map
        assert rep["init_loss"] == pytest.approx(s2 * math.log1p(25 / s2), rel=1e-9), (robust_px, rep)
        assert rep["median_reproj_px_before"] == pytest.approx(5.0, abs=1e-9)
        assert rep["median_reproj_px_after"] < rep["median_reproj_px_before"]


def test_each_matchs_depth_starts_from_the_pixel_nearest_to_it_in_the_first_image():
    u = np.arange(W)
    depth0 = torch.from_numpy(np.where(u % 2 == 0, 2.0, 4.0)).expand(H, W)  # 2 on even columns, 4 on odd ones
    recon = two_view_recon(depth0=depth0)
    v, u = np.mgrid[0:H, 1:W - 2:2]
    xy1 = np.stack([u.ravel() + 0.6, v.ravel()], -1)  # nearest pixel: an even column (2), truncated: odd (4)
    xy2 = project_into_1(xy1, np.full(len(xy1), 2.0))
    keep = xy2[:, 0] >= 0
    out = refine_matches(recon, {(0, 1): (xy1[keep], xy2[keep])}, config=SparseConfig(quiet=True, niter=30),
                         fixed_poses=True, fixed_intrinsics=True)
    rep = out.info["sparse"]
    # the matches agree with the depths at their nearest pixels: nothing to change
    assert rep["applied"] and rep["median_reproj_px_before"] < 1e-5, rep
    assert rep["depth_scale"][0] == pytest.approx(1.0, abs=1e-3), rep


def _two_view_matches(depth=2.0, score=1.0):
    v, u = np.mgrid[0:H, 0:W]
    xy1 = np.stack([u.ravel(), v.ravel()], -1).astype(float)
    xy2 = project_into_1(xy1, np.full(len(xy1), depth))
    keep = (xy2[:, 0] >= 0) & (xy2[:, 0] <= W - 1)
    return {(0, 1): (xy1[keep], xy2[keep], np.where(np.arange(int(keep.sum())) % 2 == 0, 1.0, 0.5) * score)}


def test_scaling_every_score_by_one_factor_changes_nothing():
    recon = two_view_recon(depth0=torch.full((H, W), 2.4))  # image 0's depth 20 % too deep
    cfg = SparseConfig(quiet=True, niter=50)
    out = [refine_matches(recon, _two_view_matches(score=s), config=cfg, fixed_poses=True,
                          fixed_intrinsics=True).info["sparse"] for s in (1.0, 1e-4)]
    assert out[0]["depth_scale"][0] == pytest.approx(1 / 1.2, abs=2e-3), out[0]
    assert out[1]["depth_scale"] == pytest.approx(out[0]["depth_scale"], rel=1e-5), out


def test_the_fit_shows_a_progress_bar_unless_quiet(capsys):
    recon = two_view_recon(depth0=torch.full((H, W), 2.4))
    for quiet in (False, True):
        refine_matches(recon, _two_view_matches(), config=SparseConfig(quiet=quiet, niter=5), fixed_poses=True)
        err = capsys.readouterr().err
        assert ("sparse refinement" in err) is not quiet, (quiet, err)


def test_a_held_principal_point_is_held_during_the_fit_not_only_in_the_result():
    recon = two_view_recon(pp_shift=(0.0, 1.5))  # image 1's principal point 1.5 px low: across the epipolar lines
    cfg = SparseConfig(quiet=True, niter=50, optimize_pp=True, optimize_focal=False)
    held = refine_matches(recon, _two_view_matches(), config=cfg, fixed_poses=True, fixed_intrinsics=[0, 1])
    free = refine_matches(recon, _two_view_matches(), config=cfg, fixed_poses=True, fixed_intrinsics=[0])
    assert torch.equal(held.K, recon.K) and torch.equal(free.K[0], recon.K[0])
    h, f = held.info["sparse"], free.info["sparse"]
    # poses held: only the principal point can bring the matches back onto their rows
    assert f["median_reproj_px_after"] < 0.05 and h["median_reproj_px_after"] > 1.0, (h, f)
    assert float(free.K[1, 1, 2]) == pytest.approx(float(recon.K[1, 1, 2]) - 1.5, abs=0.05)


def test_without_held_poses_the_image_with_the_most_matches_is_held_during_the_fit_and_the_report_says_so():
    recon = flat_recon(n=3)
    xy1, xy2, s = grid_matches()
    m = {(0, 1): (xy1[:5], xy2[:5], s[:5]), (1, 2): (xy1, xy2, s), (2, 0): (xy1, xy2, s)}
    rep = refine_matches(recon, m, config=SparseConfig(quiet=True, niter=2)).info["sparse"]
    assert rep["held_during_optimisation"] == [2] and rep["fixed_poses"] == [], rep
    rep = refine_matches(recon, m, config=SparseConfig(quiet=True, niter=2), fixed_poses=[1]).info["sparse"]
    assert rep["held_during_optimisation"] == [1] and rep["fixed_poses"] == [1], rep


def test_the_depth_prior_holds_a_views_whole_depth_change_not_only_each_matchs_own():
    recon = two_view_recon(depth0=torch.full((H, W), 2.4))  # image 0's depth 20 % too deep, poses and K held
    kw = dict(config=None, fixed_poses=True, fixed_intrinsics=True)
    free = refine_matches(recon, _two_view_matches(), **{**kw, "config": SparseConfig(
        quiet=True, niter=100, robust_px=100.0, depth_prior=0.0)}).info["sparse"]
    held = refine_matches(recon, _two_view_matches(), **{**kw, "config": SparseConfig(
        quiet=True, niter=100, robust_px=100.0, depth_prior=6.0)}).info["sparse"]
    assert free["depth_scale"][0] == pytest.approx(1 / 1.2, abs=2e-3), free
    # a prior about as strong as the reprojection error (2.5 px of disparity per unit log-depth) stops the
    # depth about half way (sqrt(1 / 1.2) = 0.913)
    assert 0.88 < held["depth_scale"][0] < 0.95, held


def _diverted_step(monkeypatch, change):
    """LBFGS.step replaced by ``change`` of its parameters [xi, dlf, dpp, log_scale, delta] (a fit gone wrong)."""
    def step(self, closure):
        with torch.no_grad():
            change(self.param_groups[0]["params"])

    monkeypatch.setattr(torch.optim.LBFGS, "step", step)


def test_a_fit_that_ends_worse_than_it_started_is_refused_and_the_input_kept(monkeypatch):
    recon = two_view_recon()
    _diverted_step(monkeypatch, lambda p: p[0].add_(0.05))  # every pose moved off: a higher loss
    out = refine_matches(recon, _two_view_matches(), config=SparseConfig(quiet=True), fixed_poses=[])
    rep = out.info["sparse"]
    assert rep["applied"] is False and rep["reason"] == "did not improve" and rep["final_loss"] > rep["init_loss"]
    assert torch.equal(out.cam2world, recon.cam2world) and torch.equal(out.depth_z, recon.depth_z)


def test_a_fit_that_shrinks_a_focal_below_a_quarter_is_refused_and_the_input_kept():
    from align_scene import gt_matches, make_scene

    sc = make_scene(3, 24, 32, seed=1)
    K = torch.from_numpy(sc["K"]).clone()
    K[:, :2, :2] *= 6.0  # every focal 6x too long: the fit must scale them by 1/6
    recon = Reconstruction(images=torch.from_numpy(sc["images"]).float(), cam2world=torch.from_numpy(
        sc["cam2world"]).float(), K=K.float(), depth_z=torch.from_numpy(sc["depth"]).float(),
        conf=torch.ones(3, 24, 32))
    m = {(i, j): gt_matches(sc, i, j, step=2) for i in range(3) for j in range(3) if i != j}
    out = refine_matches(recon, m, config=SparseConfig(quiet=True, niter=300), fixed_poses=True)
    rep = out.info["sparse"]
    assert rep["applied"] is False and "beyond 4x either way): degenerate" in rep["reason"], rep
    assert torch.equal(out.K, recon.K)


def test_matches_all_scored_at_or_below_min_score_are_refused_naming_the_score_filter_and_the_counts():
    recon = flat_recon()
    xy1, xy2, _ = grid_matches()
    with pytest.raises(ShapeError, match=r"no usable matches of 96 given: 96 scored at or below min_score=0\.0"):
        refine_matches(recon, {(0, 1): (xy1, xy2, np.zeros(len(xy1)))}, config=SparseConfig(quiet=True))


def test_matches_all_outside_the_images_are_refused_with_the_counts():
    recon = flat_recon()
    xy = np.array([[-5.0, -5.0], [20.0, 1.0]])
    with pytest.raises(ShapeError, match=r"no usable matches of 2 given: 0 scored at or below min_score=0\.0, "
                                         r"2 outside image i or j \(or not finite\), 0 without depth at xy1"):
        refine_matches(recon, {(0, 1): (xy, xy, np.ones(2))}, config=SparseConfig(quiet=True))
