"""Unit tests of pointmap.localization from a mutation review: the pieces localize is made of (subset, the reference
and query views, the depth scale, pose_against) and what localize hands on and reports, on the analytic scene of
align_scene.py with a stand-in network (no model is run; no downloads)."""

import sys
import types
import warnings

import numpy as np
import pytest
import torch
from align_scene import STAND_IN, gt_preds, make_scene, recon_of

from pointmap.errors import GraphError, PointmapError, ShapeError
from pointmap.localization import (
    Localization,
    depth_scale,
    localize,
    pose_against,
    query_views,
    reference_views,
)
from pointmap.prediction import PairPrediction
from pointmap.reconstruction import Reconstruction

N_REC = 4  # views 0..3 make the reconstruction, 4 and 5 are the queries
FOCALS = [40.0, 44.0, 48.0, 52.0, 30.0, 60.0]  # the queries' focals far from the references': a mix-up shows


def rotation_error_deg(A, B):
    R = np.asarray(A)[:3, :3].T @ np.asarray(B)[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def at_true_pose(cam2world, sc, view, world_scale) -> bool:
    truth = sc["cam2world"][view].copy()
    truth[:3, 3] *= world_scale
    est = np.asarray(cam2world)
    return rotation_error_deg(est, truth) < 0.5 and np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 0.02 * world_scale


@pytest.fixture
def scene(monkeypatch):
    """Six views of the analytic scene (focals FOCALS); 0..3 reconstructed in units 2.5 times the scene's; a stand-in
    ``predict_pairs`` that returns ground-truth pointmaps at a random per-pair scale and records what it was given
    (``calls``: its arguments; ``calls["preds"]``: what it returned)."""
    sc = make_scene(6, 32, 48, seed=7, focals=FOCALS)
    world_scale = 2.5
    recon = recon_of(sc, N_REC, world_scale)
    calls = {}

    def predict_pairs(model, views, pairs, batch_size=8, **kw):
        calls.update(views=list(views), pairs=list(pairs), batch_size=batch_size, kw=kw)
        preds = gt_preds(sc, pairs, seed=3)
        for (i, j), p in preds.items():
            p.conf2[:] = 10.0 + j
            p.conf2[0, :4] = 1000.0  # a few very confident pixels: they move a mean, not the median
        calls["preds"] = preds
        return preds

    monkeypatch.setitem(sys.modules, "pointmap.inference",
                        types.SimpleNamespace(predict_pairs=predict_pairs, encode_views=None))
    queries = [(sc["images"][k] * 255).round().astype(np.uint8) for k in (4, 5)]
    return sc, recon, queries, world_scale, calls


def test_subset_takes_every_field_of_the_chosen_queries_in_the_order_asked():
    m = 3
    loc = Localization(torch.arange(m * 16, dtype=torch.float64).reshape(m, 4, 4),
                       torch.arange(m * 9, dtype=torch.float64).reshape(m, 3, 3), [5, -1, 7], [0.1, 0.2, 0.3],
                       [1.5, 2.5, 3.5], ["a", "b", "c"])
    sub = loc.subset([2, 0])
    assert torch.equal(sub.cam2world, loc.cam2world[[2, 0]]) and torch.equal(sub.K, loc.K[[2, 0]])
    assert sub.ref == [7, 5] and sub.conf == [0.3, 0.1] and sub.scale == [3.5, 1.5] and sub.names == ["c", "a"]
    assert len(sub) == 2


def test_reference_views_carry_each_views_cropped_pixels_original_size_resize_name_and_position():
    """A reconstruction of photographs at twice the maps' size, of two map sizes on one canvas."""
    from pointmap.reconstruction import to_canvas

    g = torch.Generator().manual_seed(0)
    imgs = [torch.rand(32, 48, 3, generator=g), torch.rand(48, 32, 3, generator=g)]
    images, sizes = to_canvas(imgs)
    depth = to_canvas([torch.ones(32, 48), torch.ones(48, 32)])[0]
    K = torch.tensor([[[80.0, 0, 47.5], [0, 80.0, 31.5], [0, 0, 1]], [[70.0, 0, 31.5], [0, 70.0, 47.5], [0, 0, 1]]])
    mfo = torch.tensor([[0.5, 0.5, 0.0, 0.0], [0.25, 0.25, 1.0, 2.0]])
    recon = Reconstruction(images=images, cam2world=torch.eye(4).repeat(2, 1, 1), K=K, depth_z=depth,
                           conf=torch.ones_like(depth), map_from_original=mfo, original_sizes=[(96, 64), (130, 200)],
                           names=["first.jpg", "second.jpg"], map_sizes=sizes)
    views = reference_views(recon)
    for k, v in enumerate(views):
        assert torch.equal(v.img, imgs[k].permute(2, 0, 1)) and v.img.is_contiguous()
        assert v.original_size == recon.original_sizes[k] and v.map_from_original == tuple(mfo[k].tolist())
        assert v.name == recon.names[k] and v.index == k


def test_queries_are_prepared_at_the_longest_map_side_and_kept_square_when_a_reconstruction_map_is_square():
    """A hand-made reconstruction (no pipeline recorded) of a landscape and a square map."""
    recon = types.SimpleNamespace(info={}, map_sizes=[(48, 32), (32, 32)])
    square, wide = np.zeros((64, 64, 3), np.uint8), np.zeros((64, 96, 3), np.uint8)
    assert [v.shape for v in query_views(recon, [square, wide])] == [(48, 48), (32, 48)]
    recon.map_sizes = [(48, 32), (64, 48)]  # the longest side of any map
    assert query_views(recon, [wide])[0].shape == (32, 64)


def test_a_query_list_mixing_views_and_photographs_is_not_passed_on_as_it_is():
    """Only a list of Views alone is taken as already prepared."""
    from pointmap.errors import ImageError

    recon = types.SimpleNamespace(info={}, map_sizes=[(48, 32)])
    view = query_views(recon, [np.zeros((64, 96, 3), np.uint8)])[0]
    assert query_views(recon, [view]) == [view]
    with pytest.raises((ImageError, PointmapError)):
        query_views(recon, [view, np.zeros((64, 96, 3), np.uint8)])


def _recon_for_scale(conf0: float, conf1: float, h=12, w=16):
    g = torch.Generator().manual_seed(1)
    z = 1 + torch.rand(2, h, w, generator=g)
    recon = Reconstruction(images=torch.rand(2, h, w, 3, generator=g), cam2world=torch.eye(4).repeat(2, 1, 1),
                           K=torch.tensor([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]).repeat(2, 1, 1), depth_z=z,
                           conf=torch.stack([torch.full((h, w), conf0), torch.full((h, w), conf1)]))
    return recon, z


def _pred_with_depth(z_pred):
    pts = torch.zeros(1, *z_pred.shape, 3)
    pts[..., 2] = z_pred
    return PairPrediction(pts, pts.clone(), torch.ones(1, *z_pred.shape), torch.ones(1, *z_pred.shape))


def test_the_query_scale_leaves_out_pair_depths_that_are_zero_or_infinite_even_when_they_are_most_pixels():
    """A pair whose view-1 map is mostly empty (0) or blown up (inf) still gives the scale of the rest."""
    recon, z = _recon_for_scale(3.0, 3.0)
    for bad in (0.0, float("inf")):
        z_pred = z[1] / 2.0
        z_pred[:8] = bad  # two thirds of the pixels
        assert depth_scale(recon, 1, _pred_with_depth(z_pred)) == pytest.approx(2.0, rel=1e-9)


def test_the_query_scale_by_default_counts_every_reference_pixel_of_positive_confidence_of_that_reference():
    """A hand-made reconstruction's confidences may be below 1; view 0's are all 0 (no valid pixel)."""
    recon, z = _recon_for_scale(0.0, 0.5)
    assert depth_scale(recon, 1, _pred_with_depth(z[1] / 4.0)) == pytest.approx(4.0, rel=1e-9)
    assert np.isnan(depth_scale(recon, 0, _pred_with_depth(z[0] / 4.0)))


def _pair(sc, ref, query, seed=3):
    preds = gt_preds(sc, [(ref, query)], seed=seed)
    return preds[(ref, query)], preds[(query, ref)]


def test_pose_against_reports_a_given_query_K_as_given_and_the_scale_it_applied(scene):
    """The pose at the truth, K untouched, the scale the depth ratio."""
    sc, recon, _, world_scale, _ = scene
    pred, rev = _pair(sc, 2, 4)
    K_map = torch.from_numpy(sc["K"][4]).double()
    T, Km, s = pose_against(recon, 2, pred, rev, K_map)
    assert at_true_pose(T, sc, 4, world_scale) and torch.equal(Km, K_map)
    pair_scale = float((pred.pts1_cam1[0, ..., 2].double() / torch.from_numpy(sc["depth"][2])).median())
    assert s == pytest.approx(world_scale / pair_scale, rel=1e-5)


def test_pose_against_estimates_the_querys_focal_from_the_querys_own_pass_with_the_centre_at_the_middle(scene):
    """The query (30 px) and the reference (48 px) have different focals; a 32x48 map."""
    sc, recon, _, world_scale, _ = scene
    pred, rev = _pair(sc, 2, 4)
    T, Km, _ = pose_against(recon, 2, pred, rev)
    assert at_true_pose(T, sc, 4, world_scale)
    assert Km[0, 0].item() == pytest.approx(FOCALS[4], rel=0.03) and Km[1, 1] == Km[0, 0]
    assert Km[0, 2].item() == 23.5 and Km[1, 2].item() == 15.5


def test_pose_against_hands_pair_pose_the_references_K_at_the_maps_resolution_and_the_models_patch(scene, monkeypatch):
    """A reconstruction of photographs twice the maps' size (its K in their pixels)."""
    import dataclasses

    import pointmap.pose

    sc, recon, _, _, _ = scene
    K_big = recon.K.clone().double()
    K_big[:, :2, :2] *= 2
    K_big[:, :2, 2] = (K_big[:, :2, 2] + 0.5) * 2 - 0.5
    big = dataclasses.replace(recon, K=K_big, map_from_original=torch.tensor([[0.5, 0.5, 0.0, 0.0]]).repeat(N_REC, 1),
                              original_sizes=[(96, 64)] * N_REC)
    seen, pair_pose = [], pointmap.pose.pair_pose

    def spy(pred, rev, K1=None, K2=None, **kw):
        seen.append((K1, kw.get("patch")))
        return pair_pose(pred, rev, K1, K2, **kw)

    monkeypatch.setattr(pointmap.pose, "pair_pose", spy)
    pred, rev = _pair(sc, 2, 4)
    pose_against(big, 2, pred, rev, patch=8)
    assert torch.allclose(seen[0][0], torch.from_numpy(sc["K"][2]), atol=1e-9) and seen[0][1] == 8


def test_a_pair_that_gives_a_pose_but_no_focal_or_a_partly_nan_pose_falls_back_to_the_next_reference(scene, monkeypatch):
    import pointmap.localization

    sc, recon, queries, world_scale, _ = scene
    real = pointmap.localization.pose_against

    def no_focal_from_3(recon, ref, pred, rev, K_map=None, patch=16):
        T, Km, s = real(recon, ref, pred, rev, K_map, patch=patch)
        if ref == 3:
            Km = torch.full_like(Km, float("nan"))
        return T, Km, s

    monkeypatch.setattr(pointmap.localization, "pose_against", no_focal_from_3)
    loc = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert loc.ref == [2, 0] and at_true_pose(loc.cam2world[0], sc, 4, world_scale)
    assert torch.isfinite(loc.K).all()

    def nan_translation_from_3(recon, ref, pred, rev, K_map=None, patch=16):
        T, Km, s = real(recon, ref, pred, rev, K_map, patch=patch)
        if ref == 3:
            T = T.clone()
            T[0, 3] = float("nan")
        return T, Km, s

    monkeypatch.setattr(pointmap.localization, "pose_against", nan_translation_from_3)
    loc = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert loc.ref == [2, 0] and torch.isfinite(loc.cam2world).all()


def test_each_query_reports_the_median_confidence_and_the_depth_scale_of_the_pair_it_was_posed_with(scene):
    sc, recon, queries, world_scale, calls = scene
    loc = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert loc.conf == [14.0, 15.0]  # 1000 at four pixels of each: the mean would be above 50
    for k, (r, q) in enumerate(((3, 4), (0, 5))):
        pred = calls["preds"][(r, q)]
        expected = float((recon.depth_z[r].double() / pred.pts1_cam1[0, ..., 2].double()).median())
        assert loc.scale[k] == pytest.approx(expected, rel=1e-6) and loc.scale[k] != pytest.approx(1.0, abs=0.05)


def test_localize_hands_predict_pairs_its_batch_size_and_keeps_descriptors_with_each_view_indexed_by_its_position(
        scene):
    """Every View's index is its position in the list the pairs index."""
    _, recon, queries, _, calls = scene
    localize(STAND_IN, recon, queries, refs=[[3], [0]], batch_size=3, quiet=True)
    assert calls["batch_size"] == 3 and calls["kw"].get("keep_desc") is True
    assert [v.index for v in calls["views"]] == list(range(N_REC + 2))


def test_queries_of_different_sizes_get_each_their_own_estimated_K_in_their_own_pixels(scene):
    """The first query at the maps' size, the second twice it."""
    import cv2

    sc, recon, queries, world_scale, _ = scene
    mixed = [queries[0], cv2.resize(queries[1], (96, 64), interpolation=cv2.INTER_NEAREST)]
    loc = localize(STAND_IN, recon, mixed, refs=[[3], [0]], quiet=True)
    assert loc.K[0, 0, 2].item() == pytest.approx(23.5) and loc.K[0, 1, 2].item() == pytest.approx(15.5)
    assert loc.K[1, 0, 2].item() == pytest.approx(47.5) and loc.K[1, 1, 2].item() == pytest.approx(31.5)
    assert loc.K[0, 0, 0].item() == pytest.approx(FOCALS[4], rel=0.03)
    assert loc.K[1, 0, 0].item() == pytest.approx(2 * FOCALS[5], rel=0.03)


def test_a_given_K_is_reported_exactly_as_given_for_photographs_the_maps_shrink_by_two_thirds(scene):
    """The K the user gave comes back bit for bit, not through a round trip to the maps' pixels."""
    import cv2

    sc, recon, queries, world_scale, _ = scene
    big = [cv2.resize(q, (72, 48), interpolation=cv2.INTER_LINEAR) for q in queries]
    # values whose trip to the maps' pixels (x 2/3) and back changes their last bits
    K = torch.tensor([[50.611319773115156, 0.0, 12.83220645627843], [0.0, 34.446844310369016, 23.671924378590163],
                      [0.0, 0.0, 1.0]], dtype=torch.float64)
    loc = localize(STAND_IN, recon, big, refs=[[3], [0]], K=K, quiet=True)
    assert torch.equal(loc.K, K.expand(2, 3, 3))


def test_by_default_each_query_is_paired_with_its_two_most_similar_reconstruction_views(scene, monkeypatch):
    """`rank_references` gets the reconstruction's views as references, the queries as queries, and 2."""
    import pointmap.localization

    _, recon, queries, _, calls = scene
    seen = {}

    def rank(model, refs, qs, n_refs, *, device="cpu"):
        seen.update(refs=[v.name for v in refs], queries=len(qs), n_refs=n_refs)
        return [[3, 2], [0, 1]][:len(qs)]

    monkeypatch.setattr(pointmap.localization, "rank_references", rank)
    loc = localize(STAND_IN, recon, queries, quiet=True)
    assert seen == {"refs": recon.names, "queries": 2, "n_refs": 2} and loc.ref == [3, 0]


def test_a_query_given_an_empty_list_of_references_is_refused(scene):
    _, recon, queries, _, _ = scene
    with pytest.raises(GraphError, match="a non-empty list of view indices in 0..3"):
        localize(STAND_IN, recon, queries, refs=[[], [0]], quiet=True)


def test_maps_the_network_cannot_take_are_named_for_up_to_three_views(scene):
    _, recon, queries, _, _ = scene
    odd = Reconstruction(images=recon.images[:, :30, :45], cam2world=recon.cam2world, K=recon.K,
                         depth_z=recon.depth_z[:, :30, :45], conf=recon.conf[:, :30, :45])
    with pytest.raises(ShapeError, match="got view 0: 45x30, view 1: 45x30, view 2: 45x30$"):
        localize(STAND_IN, odd, queries, refs=[[1], [2]], quiet=True)


def test_a_wrong_K_for_a_single_query_is_shown_with_its_values(scene):
    _, recon, queries, _, _ = scene
    with pytest.raises(ShapeError, match=r"K expected .*got .*\[0\.0, -20\.0, 0\.0\]"):
        localize(STAND_IN, recon, queries[:1], refs=[[1]], K=np.diag([20.0, -20.0, 1.0]), quiet=True)


def test_the_warning_about_mixed_intrinsics_points_at_the_line_that_called_localize(scene):
    import dataclasses

    sc, recon, queries, _, _ = scene
    known = dataclasses.replace(recon, info={"align": {"known_K_indices": list(range(N_REC))}})
    estimated = dataclasses.replace(recon, info={"align": {"known_K_indices": []}})
    for r, K in ((known, None), (estimated, torch.from_numpy(sc["K"][4]))):
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            localize(STAND_IN, r, queries, refs=[[3], [0]], K=K, quiet=True)
        mine = [w for w in rec if "localize:" in str(w.message)]
        assert len(mine) == 1 and mine[0].filename == __file__


def test_more_references_asked_for_than_the_reconstruction_has_gives_every_view_once():
    """`n_refs` above the number of views is clipped, not an error."""
    import pointmap as pm
    from pointmap.images import View
    from pointmap.localization import rank_references

    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"]).eval()
    rng = np.random.default_rng(0)
    views = [View(torch.from_numpy(rng.random((3, 32, 48))).float(), (48, 32), (1.0, 1.0, 0.0, 0.0), f"v{k}", k)
             for k in range(3)]
    ranked = rank_references(model, views, [views[1]], n_refs=5)
    assert len(ranked) == 1 and sorted(ranked[0]) == [0, 1, 2] and ranked[0][0] == 1


def test_the_query_scale_refuses_a_pair_predicted_at_another_size_than_the_references_map():
    recon, z = _recon_for_scale(3.0, 3.0)
    with pytest.raises(ShapeError, match=r"the pair's view-1 map is \[8, 16\] but reference 1's depth is \[12, 16\]"):
        depth_scale(recon, 1, _pred_with_depth(z[1, :8]))


def test_queries_without_K_in_a_reconstruction_given_only_some_of_its_intrinsics_are_not_warned_about(scene):
    """The warning is for a reconstruction whose every focal was given."""
    import dataclasses

    _, recon, queries, _, _ = scene
    some = dataclasses.replace(recon, info={"align": {"known_K_indices": [0, 1]}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        localize(STAND_IN, some, queries, refs=[[3], [0]], quiet=True)


def test_something_other_than_a_reconstruction_is_refused_by_name(scene):
    _, _, queries, _, _ = scene
    for bad in ("scene.npz", [1, 2]):
        with pytest.raises(PointmapError, match=f"expected a Reconstruction with at least one view, got "
                                                f"{type(bad).__name__}"):
            localize(STAND_IN, bad, queries, refs=[[0], [0]], quiet=True)


def test_maps_with_only_their_height_off_the_patch_grid_are_refused_too(scene):
    """48x30, the width a multiple of 16, the height not."""
    _, recon, queries, _, _ = scene
    odd = Reconstruction(images=recon.images[:, :30], cam2world=recon.cam2world, K=recon.K,
                         depth_z=recon.depth_z[:, :30], conf=recon.conf[:, :30])
    with pytest.raises(ShapeError, match="got view 0: 48x30"):
        localize(STAND_IN, odd, queries, refs=[[1], [2]], quiet=True)


def test_intrinsics_refused_for_one_query_of_several_refuse_the_call(scene):
    """Query 0's K is fine, query 1's has a negative fy."""
    sc, recon, queries, _, _ = scene
    K = torch.from_numpy(sc["K"][4:6]).clone()
    K[1, 1, 1] *= -1
    with pytest.raises(ShapeError, match=r"K expected \[3, 3\] or \[2, 3, 3\] intrinsics .*got K\[1\] = \[\[") as err:
        localize(STAND_IN, recon, queries, refs=[[3], [0]], K=K, quiet=True)
    assert repr(float(K[1, 1, 1])) in str(err.value) and "K[0]" not in str(err.value)  # which one, with its values


def test_a_bool_is_not_taken_for_a_reference_index(scene):
    """[[True], [0]] was posed against view 1 (True == 1), where n_refs=True is refused ("a bool is not a count")."""
    _, recon, queries, _, _ = scene
    for refs in ([[True], [0]], torch.tensor([[True], [False]])):
        with pytest.raises(GraphError, match=r"a non-empty list of view indices in 0..3, got \[\[True\]"):
            localize(STAND_IN, recon, queries, refs=refs, quiet=True)


def test_subset_with_a_boolean_mask_keeps_the_same_queries_in_every_field():
    """loc.subset([r >= 0 for r in loc.ref]): torch took the list as a mask (the posed rows) while the lists took
    the bools as indices 1 and 0 (other queries' names, references, scales)."""
    loc = Localization(torch.arange(32, dtype=torch.float64).reshape(2, 4, 4),
                       torch.arange(18, dtype=torch.float64).reshape(2, 3, 3), [-1, 2], [float("nan"), 0.5],
                       [float("nan"), 1.5], ["unposed.jpg", "posed.jpg"])
    for mask in ([r >= 0 for r in loc.ref], torch.tensor([False, True]), np.array([False, True])):
        sub = loc.subset(mask)
        assert sub.names == ["posed.jpg"] and sub.ref == [2] and sub.scale == [1.5]
        assert torch.equal(sub.cam2world, loc.cam2world[1:]) and torch.equal(sub.K, loc.K[1:])
    with pytest.raises(ShapeError, match="a mask of 2 bools, got 3 bools"):
        loc.subset([True, False, True])
