"""Units of the Gaussian initialisation on hand-made reconstructions and point sets: co-visibility pruning, the voxel
downsampling, the kNN scale and init_from's options."""

import numpy as np
import pytest
import torch

from pointmap import Reconstruction
from pointmap.errors import ShapeError
from pointmap.splat import init_from
from pointmap.splat.init import _voxel_downsample, covisibility_keep, knn_scale


def _recon(depths, shifts=None, fx=30.0, fy=30.0, W=32, H=24, conf=None, images=None):
    """Views of fronto-parallel planes at ``depths`` (one per view) from cameras translated by ``shifts`` [N, 3]."""
    n = len(depths)
    K = torch.tensor([[fx, 0, (W - 1) / 2], [0, fy, (H - 1) / 2], [0, 0, 1]])
    c2w = torch.eye(4).repeat(n, 1, 1)
    if shifts is not None:
        c2w[:, :3, 3] = torch.as_tensor(shifts, dtype=torch.float32)
    depth = torch.tensor(depths, dtype=torch.float32)[:, None, None].expand(n, H, W).clone()
    img = torch.rand(n, H, W, 3, generator=torch.Generator().manual_seed(0)) if images is None else images
    conf = torch.ones(n, H, W) * 2 if conf is None else conf
    return Reconstruction(images=img, cam2world=c2w, K=K.expand(n, 3, 3).clone(), depth_z=depth, conf=conf)


def _keep(recon, covis_tol=0.01, **kw):
    return covisibility_keep(recon, recon.valid(), list(range(len(recon))), covis_tol, **kw)


def test_a_camera_shifted_by_a_fraction_of_a_pixel_keeps_only_the_columns_it_newly_sees():
    # 0.14 units at depth 3 with fx = 30 is 1.4 pixels: view 0's column u lands on round(u - 1.4) = u - 1 of view 1
    # (fy differs from fx, so the columns depend on using fx)
    recon = _recon([3.0, 3.0], shifts=[[0, 0, 0], [0.14, 0, 0]], fx=30.0, fy=20.0)
    keep = _keep(recon)
    assert bool(keep[0].all())
    expected = torch.zeros(24, 32, dtype=torch.bool)
    expected[:, 31] = True                      # columns 0..30 are covered, the first one included
    assert torch.equal(keep[1], expected)
    back = _keep(_recon([3.0, 3.0], shifts=[[0, 0, 0], [-0.14, 0, 0]], fx=30.0, fy=20.0))
    expected = torch.zeros(24, 32, dtype=torch.bool)
    expected[:, 0] = True                       # a camera moved the other way sees its new column on the left
    assert torch.equal(back[1], expected)


def test_a_pixel_is_explained_only_when_the_depths_differ_by_strictly_less_than_covis_tol_of_its_depth():
    recon = _recon([2.5, 2.0])                  # |2.5 - 2.0| = 0.5, exactly 0.25 of the later view's depth 2
    assert bool(_keep(recon, covis_tol=0.25)[1].all())
    assert not bool(_keep(recon, covis_tol=0.26)[1].any())
    # an earlier surface well in front of the later one explains nothing
    front = _recon([2.0, 3.0])
    assert bool(_keep(front, covis_tol=0.1)[1].all())
    assert not bool(_keep(front, covis_tol=0.34)[1].any())


def test_a_later_view_is_pruned_by_every_valid_point_of_the_earlier_views_even_those_pruned_themselves():
    # view 1 (3.01) is explained by view 0 (3.0); view 2 (3.035) is within 1% of view 1 but not of view 0
    keep = _keep(_recon([3.0, 3.01, 3.035]))
    assert bool(keep[0].all()) and not bool(keep[1].any())
    assert not bool(keep[2].any())


def test_more_source_points_than_max_src_points_are_subsampled_to_exactly_that_many():
    recon = _recon([3.0, 3.0])                  # identical views: each source point explains one pixel
    assert int((~_keep(recon, max_src_points=100)[1]).sum()) == 100
    assert not bool(_keep(recon, max_src_points=24 * 32)[1].any())


def test_the_voxel_grid_keeps_the_most_confident_point_of_each_voxel_and_fills_the_budget():
    pts = np.array([[0, 0, 0], [0.01, 0, 0], [10, 0, 0]], dtype=np.float32)
    assert _voxel_downsample(pts, np.array([1.0, 5.0, 2.0]), 2).tolist() == [1, 2]
    assert _voxel_downsample(pts, np.array([5.0, 1.0, 2.0]), 2).tolist() == [0, 2]


def test_the_voxel_grid_keeps_every_point_of_a_grid_whose_size_is_the_budget_and_returns_sorted_indices():
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    pts = g[::-1].astype(np.float32)            # index order opposite to the voxels' order
    score = np.random.default_rng(0).random(len(pts))
    assert _voxel_downsample(pts, score, 64).tolist() == list(range(64))
    idx = _voxel_downsample(pts, score, 20)
    assert 1 <= len(idx) <= 20 and bool((np.diff(idx) > 0).all())


@pytest.mark.parametrize("budget", [500, 900])
def test_the_voxel_size_bisection_uses_nearly_all_of_the_budget(budget):
    pts = np.zeros((1000, 3), dtype=np.float32)
    pts[:, 0] = np.arange(1000)                 # a line of evenly spaced points: the count falls smoothly with size
    idx = _voxel_downsample(pts, np.ones(1000), budget)
    assert 0.9 * budget <= len(idx) <= budget


def test_the_knn_scale_is_the_root_mean_square_distance_to_the_three_nearest_neighbours():
    pts = np.random.default_rng(0).random((30, 3)).astype(np.float32)
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    d2 = np.sort(d2, 1)[:, 1:4]                 # without the point itself
    np.testing.assert_allclose(knn_scale(pts), np.sqrt(d2.mean(1)), rtol=1e-5)
    assert knn_scale(pts).dtype == np.float32


def test_coincident_points_get_five_percent_of_the_median_scale_and_a_lone_point_a_small_default():
    rng = np.random.default_rng(1)
    pts = np.concatenate([np.zeros((4, 3)), rng.random((40, 3)) + 2]).astype(np.float32)
    s = knn_scale(pts)
    np.testing.assert_allclose(s[:4], 0.05 * np.median(s), rtol=1e-5)
    assert bool((s[4:] > 0.05 * np.median(s)).all())
    assert knn_scale(np.zeros((1, 3), dtype=np.float32)).tolist() == [pytest.approx(0.01)]


def test_init_refuses_an_opacity_of_zero_and_an_infinite_covis_tol():
    recon = _recon([3.0])
    with pytest.raises(ShapeError, match=r"opacity must be a number in \(0, 1\), got 0.0"):
        init_from(recon, opacity=0.0)
    with pytest.raises(ShapeError, match="covis_tol expected a finite relative depth tolerance > 0, got inf"):
        init_from(recon, covis_tol=float("inf"))


def test_the_gaussians_start_only_from_pixels_inside_the_masks():
    recon = _recon([3.0])
    recon.masks = torch.zeros(1, 24, 32, dtype=torch.bool)
    recon.masks[0, :, :10] = True
    g = init_from(recon, max_gaussians=None)
    assert len(g) == 24 * 10 and g.info["points_valid"] == 24 * 10
    assert float(g.means[:, 0].max()) < (10 - 15.5) * 3 / 30 + 1e-4     # x of column 9


def test_views_are_ranked_by_the_mean_confidence_of_their_valid_pixels_and_a_view_with_none_goes_last():
    conf = torch.ones(3, 24, 32) * 2
    conf[0] = 0.5                               # nothing above min_conf = 1
    conf[1, :, :4] = 9.0                        # a few very confident pixels among many below the threshold
    conf[1, :, 4:] = 0.5
    g = init_from(_recon([3.0, 3.0, 3.0], conf=conf), max_gaussians=None, min_conf=1.0)
    assert g.info["view_order"] == [1, 2, 0]
    equal = init_from(_recon([3.0, 3.0, 3.0]), max_gaussians=None)
    assert equal.info["view_order"] == [0, 1, 2]


def test_init_passes_covis_tol_on_to_the_pruning():
    recon = _recon([2.5, 2.0])                  # the second view's depth is 25% off the first's
    g = init_from(recon, max_gaussians=None)
    assert len(g) == 2 * 24 * 32 and g.info["points_after_covisibility"] == 2 * 24 * 32
    g = init_from(recon, max_gaussians=None, covis_tol=0.26)
    assert len(g) == 24 * 32 and g.info["points_after_covisibility"] == 24 * 32
    assert g.info["points_valid"] == 2 * 24 * 32


def test_colours_a_hair_outside_zero_to_one_are_clamped():
    img = torch.rand(1, 24, 32, 3, generator=torch.Generator().manual_seed(2))
    img[0, 0, 0] = torch.tensor([1.005, -0.005, 0.5])   # the Reconstruction tolerates 0.01 of rounding
    g = init_from(_recon([3.0], images=img), max_gaussians=None)
    assert float(g.colors.min()) >= 0.0 and float(g.colors.max()) <= 1.0
    assert torch.allclose(g.colors, img[0].reshape(-1, 3).clamp(0, 1), atol=1e-5)


@pytest.mark.parametrize("downsample", ["voxel", "conf"])
def test_a_budget_one_below_the_point_count_is_kept(downsample):
    g = init_from(_recon([3.0]), max_gaussians=24 * 32 - 1, downsample=downsample)
    assert len(g) <= 24 * 32 - 1
    if downsample == "conf":
        assert len(g) == 24 * 32 - 1


def test_the_voxel_downsampling_keeps_the_more_confident_points():
    conf = 1 + torch.rand(1, 24, 32, generator=torch.Generator().manual_seed(3))
    g = init_from(_recon([3.0], conf=conf), max_gaussians=100)
    assert float(g.conf.mean()) > float(conf.mean()) + 0.2


def test_with_equal_confidences_the_seed_decides_which_point_of_a_voxel_is_kept():
    recon = _recon([3.0])
    a, b = (init_from(recon, max_gaussians=100, seed=s) for s in (3, 4))
    assert len(a) == len(b) and not torch.equal(a.means, b.means)


def test_the_confidence_weighted_draw_favours_confident_points_without_repeats_and_in_pixel_order():
    conf = torch.ones(1, 24, 32)
    conf[0, :, 16:] = 100.0
    g = init_from(_recon([3.0], conf=conf), max_gaussians=300, downsample="conf")
    assert len(g) == 300 and len(torch.unique(g.means, dim=0)) == 300
    assert int((g.conf == 100.0).sum()) >= 280
    u = torch.round(g.means[:, 0] * 30 / 3 + 15.5)
    v = torch.round(g.means[:, 1] * 30 / 3 + 11.5)
    assert bool((torch.diff(v * 32 + u) > 0).all())


def test_the_opacity_option_sets_every_gaussians_opacity():
    g = init_from(_recon([3.0]), max_gaussians=50, opacity=0.3)
    assert torch.allclose(g.opacities, torch.full((len(g),), 0.3))


# Bugs found by the mutation review


@pytest.mark.parametrize("name", ["covisibility", "rank_by_conf"])
@pytest.mark.parametrize("flag", ["no", 0, None])
def test_init_refuses_a_switch_that_is_not_true_or_false(name, flag):
    # "no" is truthy: it would silently prune (or rank) what the caller meant to leave alone
    with pytest.raises(ShapeError, match=f"{name} expected True or False, got {flag!r}"):
        init_from(_recon([3.0, 3.0]), max_gaussians=None, **{name: flag})
