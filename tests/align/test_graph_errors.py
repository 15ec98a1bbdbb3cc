"""Unusable inputs: clear errors or warnings, never NaNs."""

import warnings

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, views_of

from pointmap.align import AlignConfig, global_align
from pointmap.errors import GraphError, ShapeError
from pointmap.prediction import PairPrediction

QUIET = AlignConfig(quiet=True, niter=30)


@pytest.fixture(scope="module")
def scene():
    return make_scene(4, 32, 48, seed=21)


def test_a_disconnected_graph_is_refused_naming_its_components(scene):
    preds = gt_preds(scene, [(0, 1), (2, 3)], seed=1)
    with pytest.raises(GraphError, match=r"disconnected.*\[0, 1\]; \[2, 3\]"):
        global_align(views_of(scene), preds, config=QUIET)


def test_a_single_image_is_refused(scene):
    preds = gt_preds(scene, [(0, 1)], seed=1)
    with pytest.raises(GraphError, match="at least 2 images"):
        global_align(views_of(scene)[:1], preds, config=QUIET)


def test_an_empty_prediction_dict_is_refused(scene):
    with pytest.raises(GraphError, match="non-empty dict"):
        global_align(views_of(scene), {}, config=QUIET)


def test_pair_index_out_of_range(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    with pytest.raises(GraphError, match="outside 0..2"):
        global_align(views_of(scene)[:3], preds, config=QUIET)


def test_one_direction_only_or_first_view_maps_without_a_usable_point_are_explained(scene):
    preds = {k: v for k, v in gt_preds(scene, complete_pairs(4), seed=1).items() if k[0] < k[1]}
    with pytest.raises(GraphError, match="have no pair left in which they come first"):
        global_align(views_of(scene), preds, config=QUIET)
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    for j in (0, 1, 3):  # image 2's own maps all NaN: both orders given, still no own frame
        preds[(2, j)].pts1_cam1[0] = float("nan")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        with pytest.raises(GraphError, match="their first-view maps held no usable point"):
            global_align(views_of(scene), preds, config=QUIET)
    assert any("no finite points" in str(w.message) for w in said)


def test_a_map_of_the_wrong_size_is_refused_naming_its_pair(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    p = preds[(0, 1)]
    preds[(0, 1)] = PairPrediction(p.pts1_cam1[:, :16], p.pts2_cam1, p.conf1[:, :16], p.conf2)
    with pytest.raises(ShapeError, match=r"pair \(0, 1\)"):
        global_align(views_of(scene), preds, config=QUIET)


def test_all_low_confidence_pairs(scene):
    """Every confidence at 1: log weighting leaves nothing to align (a clear error); the default ('auto')
    weighs the pixels by conf itself instead and aligns."""
    preds = gt_preds(scene, complete_pairs(4), seed=1, conf=1.0)
    with pytest.raises(GraphError, match="every pair has zero weight"):
        global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=30, conf_transform="log"))
    recon = global_align(views_of(scene), preds, config=QUIET)
    assert recon.info["align"]["conf_transform"] == "id" and torch.isfinite(recon.cam2world).all()


def test_some_low_confidence_pairs_warn_and_still_align(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    low = gt_preds(scene, [(0, 1)], seed=1, conf=1.0)
    preds.update(low)
    with pytest.warns(UserWarning, match="zero weight in a view"):
        recon = global_align(views_of(scene), preds, config=QUIET)
    assert recon.info["align"]["num_edges"] == 10
    assert torch.isfinite(recon.cam2world).all() and torch.isfinite(recon.depth_z).all()


def test_low_confidence_disconnecting_the_graph(scene):
    preds = gt_preds(scene, [(0, 1), (1, 2), (2, 3)], seed=1)
    preds.update(gt_preds(scene, [(1, 2)], seed=1, conf=1.0))
    with pytest.warns(UserWarning), pytest.raises(GraphError, match="after dropping zero-confidence"):
        global_align(views_of(scene), preds, config=QUIET)


def test_duplicate_images_warn_without_nans(scene):
    """Image 3 is an exact copy of image 0 (same pixels, same camera)."""
    sc = {k: v.copy() for k, v in scene.items()}
    for key in ("cam2world", "K", "depth", "pts_world", "images"):
        sc[key][3] = sc[key][0]
    preds = gt_preds(sc, complete_pairs(4), seed=2)
    with pytest.warns(UserWarning, match=r"identical images \[\(0, 3\)\]"):
        recon = global_align(views_of(sc), preds, config=QUIET)
    assert torch.isfinite(recon.cam2world).all() and torch.isfinite(recon.depth_z).all()
    assert float((recon.cam2world[0, :3, 3] - recon.cam2world[3, :3, 3]).norm()) < 1e-3


def test_nan_pixels_are_ignored(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=3)
    for p in preds.values():
        p.pts2_cam1[0, :4, :4] = float("nan")
        p.conf1[0, -3:, -3:] = float("inf")
    recon = global_align(views_of(scene), preds, config=QUIET)
    assert torch.isfinite(recon.depth_z).all() and torch.isfinite(recon.cam2world).all()


def test_a_nan_or_inf_confidence_pixel_leaves_the_start_focal_and_the_result_exact(scene):
    from align_scene import pose_errors

    preds = gt_preds(scene, complete_pairs(4), seed=0)
    for bad in (float("nan"), float("inf")):
        for p in preds.values():
            p.conf1[0, 5, 5] = bad
        recon = global_align(views_of(scene), preds, config=QUIET)
        focal_err = np.abs(recon.K[:, 0, 0].double().numpy() / scene["K"][:, 0, 0] - 1).max()
        assert focal_err < 1e-4 and pose_errors(recon.cam2world.numpy(), scene["cam2world"])[0] < 0.05


def test_a_hole_in_an_images_own_map_starts_from_the_other_pairs_maps_and_aligns_exactly(scene):
    from align_scene import pose_errors

    preds = gt_preds(scene, complete_pairs(4), seed=0)
    for (i, _), p in preds.items():
        if i == 0:  # image 0's own-frame passes lose a block; the passes where it is view 2 still see it
            p.pts1_cam1[0, :16, :24] = float("nan")
    for opt in ("none", "adam"):
        recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, optimizer=opt))
        rot, centre, a = pose_errors(recon.cam2world.numpy(), scene["cam2world"])
        focal_err = np.abs(recon.K[:, 0, 0].double().numpy() / scene["K"][:, 0, 0] - 1).max()
        depth_err = np.median(np.abs(recon.depth_z[0, :16, :24].double().numpy() * a / scene["depth"][0][:16, :24] - 1))
        assert rot < 0.05 and centre < 1e-4 and focal_err < 1e-4 and depth_err < 1e-4, (opt, rot, centre, focal_err,
                                                                                         depth_err)


def test_self_pairs_are_ignored_with_a_warning(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    preds[(1, 1)] = preds[(1, 2)]
    with pytest.warns(UserWarning, match="with itself"):
        recon = global_align(views_of(scene), preds, config=QUIET)
    assert recon.info["align"]["num_edges"] == 12
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isfinite(recon.K.numpy()).all()


def test_plain_tensor_views_get_default_names_and_a_nan_image_is_refused(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    tensors = [v.img for v in views_of(scene)]
    recon = global_align(tensors, preds, config=QUIET)
    assert recon.names == [f"view_{k:03d}.png" for k in range(4)]
    tensors[2] = tensors[2].clone()
    tensors[2][0, 0, 0] = float("nan")
    with pytest.raises(ShapeError, match="view 2: expected a finite image"):
        global_align(tensors, preds, config=QUIET)


def test_repeated_names_get_suffixes_no_other_image_has(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    views = views_of(scene)
    for v, name in zip(views, ["x/a.png", "y/a.png", "a_1.png", "b.png"]):
        v.name = name.split("/")[-1]
    with pytest.warns(UserWarning, match="duplicate image names"):
        recon = global_align(views, preds, config=QUIET)
    assert recon.names == ["a.png", "a_2.png", "a_1.png", "b.png"]


def test_a_prediction_entry_that_is_not_a_prediction_is_refused_naming_its_pair(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=1)
    preds[(1, 2)] = preds[(1, 2)].as_dict()
    with pytest.raises(ShapeError, match="preds\\[\\(1, 2\\)\\] expected a PairPrediction"):
        global_align(views_of(scene), preds, config=QUIET)


def test_an_image_whose_weighted_pixels_never_overlap_its_placing_pair_is_refused_by_the_mst_init(scene):
    """Each view is confident only on its top half in its own pair and only on its bottom half in the other: the
    spanning-tree init has no pixel to place the second image by, and says so instead of placing it at scale 0."""
    preds = gt_preds(scene, [(0, 1), (1, 0)], seed=1)
    h = preds[(0, 1)].conf1.shape[1]
    for p in preds.values():
        p.conf1[:, h // 2:] = 1.0  # weight 0 under log
        p.conf2[:, :h // 2] = 1.0
    views = views_of(scene)[:2]
    with pytest.raises(GraphError, match="no pixel with a positive confidence weight"):
        global_align(views, preds, config=AlignConfig(quiet=True, niter=5, conf_transform="log", init="mst"))


def test_entry_points_refuse_keys_configs_and_switches_of_the_wrong_type_naming_them():
    import pointmap as pm
    from pointmap.align import align_to_cameras, refine_epipolar, scale_to_depth

    sc = make_scene(3, 24, 32, seed=1)
    views, preds = views_of(sc), gt_preds(sc, complete_pairs(3))
    for key in ((0.0, 1.5), ("1", 2), (2, 0.5)):  # truncated to another pair's key, or a raw KeyError before
        with pytest.raises(GraphError, match="tuples of image indices \\(integers\\)"):
            global_align(views, {**preds, key: preds[(0, 1)]}, config=AlignConfig(quiet=True, niter=2))
    with pytest.raises(ShapeError, match="config expected an AlignConfig, got dict"):
        global_align(views, preds, config={"niter": 5})
    recon = global_align(views, preds, config=AlignConfig(quiet=True, niter=2))
    with pytest.raises(ShapeError, match="refine_epipolar expected a Reconstruction"):
        refine_epipolar(views, [1, 2], recon)
    with pytest.raises(ShapeError, match="with_scale True or False, got Reconstruction and 'no'"):
        align_to_cameras(recon, torch.tensor(sc["cam2world"]), with_scale="no")
    with pytest.raises(ShapeError, match="cam2world expected \\[3, 4, 4\\] reference poses, got str"):
        align_to_cameras(recon, "abc")
    with pytest.raises(ShapeError, match="min_pixels an int >= 1, got Reconstruction and -1"):
        scale_to_depth(recon, [None] * 3, min_pixels=-1)
    assert isinstance(recon, pm.Reconstruction)
