"""Relocalisation (pointmap.localization): new views of the analytic scene posed in a reconstruction built from its
other views, with a stand-in network that returns ground-truth pointmaps at an unknown per-pair scale."""

import sys
import types

import numpy as np
import pytest
import torch
from align_scene import STAND_IN, gt_preds, make_scene, recon_of

from pointmap.errors import GraphError, PointmapError, ShapeError
from pointmap.localization import localize
from pointmap.reconstruction import Reconstruction

N_REC = 4  # views 0..3 make the reconstruction, 4 and 5 are the queries


def rotation_error_deg(A, B):
    R = A[:3, :3].T @ B[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def assert_at_true_pose(cam2world, sc, view, world_scale):
    """``cam2world`` [4, 4] is scene view ``view``'s true pose in the reconstruction's units (the scene is ~8 units
    across): rotation within 0.5 degrees, centre within 2% of the scale."""
    truth = sc["cam2world"][view].copy()
    truth[:3, 3] *= world_scale
    est = np.asarray(cam2world)
    assert rotation_error_deg(est, truth) < 0.5
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 0.02 * world_scale


@pytest.fixture
def scene(monkeypatch):
    sc = make_scene(6, 32, 48, seed=7)
    world_scale = 2.5  # the reconstruction's units are not the scene's: the queries must land in the former
    recon = recon_of(sc, N_REC, world_scale)
    calls = {}

    def predict_pairs(model, views, pairs, batch_size=8, **kw):  # indices are the scene's (queries follow)
        calls["pairs"] = list(pairs)
        preds = gt_preds(sc, pairs, seed=3)
        for e in calls.get("broken", ()):  # a pair whose view-1 depth is all behind the camera: no scale
            preds[e].pts1_cam1[..., 2] *= -1
        for (i, j), p in preds.items():  # view 2's confidence tells the pair apart from view 1's: 10 + j
            p.conf2[:] = 10.0 + j
        return preds

    monkeypatch.setitem(sys.modules, "pointmap.inference",
                        types.SimpleNamespace(predict_pairs=predict_pairs, encode_views=None))
    queries = [(sc["images"][k] * 255).round().astype(np.uint8) for k in (4, 5)]
    return sc, recon, queries, world_scale, calls


def test_queries_land_on_their_true_poses_in_the_reconstructions_world_and_units(scene):
    sc, recon, queries, world_scale, calls = scene
    loc = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert sorted(calls["pairs"]) == [(0, 5), (2, 4), (3, 4)]
    for k, q in enumerate((4, 5)):
        assert_at_true_pose(loc.cam2world[k], sc, q, world_scale)
        assert abs(loc.K[k, 0, 0].item() - sc["K"][q, 0, 0]) / sc["K"][q, 0, 0] < 0.03  # focal estimated
    assert loc.ref == [3, 0] and loc.names == ["image_000.png", "image_001.png"]  # the first reference given
    assert loc.conf == [14.0, 15.0]  # the median confidence of each query's own map (view 2 of its pair)


def test_queries_predicted_a_chunk_at_a_time_get_the_poses_they_get_together(scene, monkeypatch):
    import pointmap.localization

    sc, recon, queries, world_scale, calls = scene
    together = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    monkeypatch.setattr(pointmap.localization, "QUERY_CHUNK", 1)
    apart = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert calls["pairs"] == [(0, 5)]  # the last chunk: the second query's pairs alone
    # the stand-in draws each call's pair scales afresh: the scales differ, the poses in the world do not
    assert torch.allclose(apart.cam2world, together.cam2world, atol=1e-5) and torch.allclose(apart.K, together.K)
    assert apart.ref == together.ref


def test_a_reference_whose_pair_gives_no_pose_falls_back_to_the_next(scene):
    sc, recon, queries, world_scale, calls = scene
    calls["broken"] = [(3, 4)]
    loc = localize(STAND_IN, recon, queries, refs=[[3, 2], [0]], quiet=True)
    assert loc.ref == [2, 0]
    assert_at_true_pose(loc.cam2world[0], sc, 4, world_scale)
    loc = localize(STAND_IN, recon, queries, refs=[[3], [0]], quiet=True)  # no fallback: that query is not posed
    assert loc.ref == [-1, 0] and torch.isnan(loc.cam2world[0]).all() and torch.isfinite(loc.cam2world[1]).all()
    K = sc["K"][4].copy()
    loc = localize(STAND_IN, recon, queries, refs=[[3], [0]], K=K, quiet=True)  # a given K: NaN where not posed
    assert torch.isnan(loc.K[0]).all() and torch.allclose(loc.K[1], torch.from_numpy(K))
    calls["broken"] = [(3, 4), (0, 5)]
    with pytest.raises(PointmapError, match="none of the 2 queries could be posed"):
        localize(STAND_IN, recon, queries, refs=[[3], [0]], quiet=True)


def test_a_known_focal_is_used_as_given_and_reported_with_the_true_pose(scene):
    sc, recon, queries, world_scale, _ = scene
    K = torch.from_numpy(sc["K"][4:6])
    loc = localize(STAND_IN, recon, queries, refs=[[3], [0]], K=K, quiet=True)
    assert torch.equal(loc.K, K.double())
    for k, q in enumerate((4, 5)):
        assert_at_true_pose(loc.cam2world[k], sc, q, world_scale)


def test_intrinsics_of_another_kind_than_the_reconstructions_are_warned_about(scene):
    import dataclasses
    import warnings

    sc, recon, queries, world_scale, _ = scene
    K = torch.from_numpy(sc["K"][4:6])
    estimated = dataclasses.replace(recon, info={"align": {"known_K_indices": []}})
    known = dataclasses.replace(recon, info={"align": {"known_K_indices": list(range(N_REC))}})
    with pytest.warns(UserWarning, match="the queries' intrinsics are given but the reconstruction's focals were "
                                         "estimated"):
        localize(STAND_IN, estimated, queries, refs=[[3], [0]], K=K, quiet=True)
    with pytest.warns(UserWarning, match="the reconstruction was given its intrinsics but the queries' are estimated"):
        localize(STAND_IN, known, queries, refs=[[3], [0]], quiet=True)
    with warnings.catch_warnings():  # of one kind, or nothing recorded (a hand-made reconstruction): no warning
        warnings.simplefilter("error")
        localize(STAND_IN, known, queries, refs=[[3], [0]], K=K, quiet=True)
        localize(STAND_IN, estimated, queries, refs=[[3], [0]], quiet=True)
        localize(STAND_IN, recon, queries, refs=[[3], [0]], K=K, quiet=True)


def doubled(K: torch.Tensor) -> torch.Tensor:
    """K of the images resized to twice their size, written out by hand (pixel centres at integers:
    u_big = (u + 0.5) * 2 - 0.5)."""
    K = K.clone()
    K[:, :2, :2] *= 2
    K[:, :2, 2] = (K[:, :2, 2] + 0.5) * 2 - 0.5
    return K


def test_a_known_K_reaches_the_pair_pose_beside_the_references_own(scene, monkeypatch):
    import pointmap.pose

    sc, recon, queries, _, _ = scene
    seen, pair_pose = [], pointmap.pose.pair_pose

    def spy(pred, rev, K1=None, K2=None, **kw):
        seen.append((K1, K2))
        return pair_pose(pred, rev, K1, K2, **kw)

    monkeypatch.setattr(pointmap.pose, "pair_pose", spy)
    K = torch.from_numpy(sc["K"][4:6])
    localize(STAND_IN, recon, queries, refs=[[3], [0]], K=K, quiet=True)  # queries at the maps' size: K as given
    assert [(torch.equal(K1, recon.K_map[r].double()), torch.allclose(K2, K[k].double()))
            for k, (r, (K1, K2)) in enumerate(zip((3, 0), seen))] == [(True, True)] * 2
    seen.clear()
    import cv2

    big = [cv2.resize(q, (96, 64), interpolation=cv2.INTER_NEAREST) for q in queries]  # twice the maps' size
    K_big = doubled(K)
    localize(STAND_IN, recon, big, refs=[[3], [0]], K=K_big, quiet=True)  # K of the photographs: mapped to the maps'
    assert all(torch.allclose(K2, K[k].double(), atol=1e-9) for k, (_, K2) in enumerate(seen))
    seen.clear()
    localize(STAND_IN, recon, queries, refs=[[3], [0]], quiet=True)
    assert [K2 for _, K2 in seen] == [None, None]  # unknown: pair_pose takes the focal from the query's pointmap


def test_photographs_larger_than_the_maps_get_their_K_in_their_own_pixels(scene):
    import cv2

    sc, recon, queries, world_scale, _ = scene
    big = [cv2.resize(q, (96, 64), interpolation=cv2.INTER_NEAREST) for q in queries]  # twice the maps' size
    K_big = doubled(torch.from_numpy(sc["K"][4:6]))
    loc = localize(STAND_IN, recon, big, refs=[[3], [0]], quiet=True)
    assert torch.allclose(loc.K[:, 0, 0], K_big[:, 0, 0], rtol=0.03)  # estimated on the maps, reported here
    assert torch.allclose(loc.K[:, :2, 2], K_big[:, :2, 2], atol=1e-6)
    known = localize(STAND_IN, recon, big, refs=[[3], [0]], K=K_big, quiet=True)  # mapped onto the maps for pair_pose
    for k, q in enumerate((4, 5)):
        assert_at_true_pose(known.cam2world[k], sc, q, world_scale)


def test_bad_references_and_inputs_are_refused_with_what_was_expected(scene):
    _, recon, queries, _, _ = scene
    with pytest.raises(GraphError, match=r"view indices in 0..3"):
        localize(STAND_IN, recon, queries, refs=[[4], [0]], quiet=True)
    with pytest.raises(GraphError, match="for each of the 2 queries"):
        localize(STAND_IN, recon, queries, refs=[[1]], quiet=True)
    with pytest.raises(ShapeError, match=r"K expected \[3, 3\] or \[2, 3, 3\]"):
        localize(STAND_IN, recon, queries, refs=[[1], [2]], K=torch.eye(4), quiet=True)
    with pytest.raises(PointmapError, match="non-empty list of images"):
        localize(STAND_IN, recon, [], quiet=True)
    # one image, not in a list, is one query (its rows were taken for images)
    one = localize(STAND_IN, recon, queries[0], refs=[[3]], quiet=True)
    assert len(one.names) == 1
    assert torch.equal(one.cam2world, localize(STAND_IN, recon, [queries[0]], refs=[[3]], quiet=True).cam2world)
    # and one reference index for it is its list of one
    assert torch.equal(one.cam2world, localize(STAND_IN, recon, queries[0], refs=3, quiet=True).cam2world)
    with pytest.raises(GraphError, match="a list of view indices, got 'near'"):
        localize(STAND_IN, recon, queries, refs="near", quiet=True)
    with pytest.raises(ShapeError, match=r"K expected \[3, 3\] or \[2, 3, 3\] .* got \[\[1, 2, 3\], \[4, 5\]"):
        localize(STAND_IN, recon, queries, refs=[[1], [2]], K=[[1, 2, 3], [4, 5]], quiet=True)
    # maps the network cannot take (not multiples of the patch size), e.g. a hand-made reconstruction's
    odd = Reconstruction(images=recon.images[:, :30, :45], cam2world=recon.cam2world, K=recon.K,
                         depth_z=recon.depth_z[:, :30, :45], conf=recon.conf[:, :30, :45])
    with pytest.raises(ShapeError, match="multiple of the model's patch size 16; got view 0: 45x30"):
        localize(STAND_IN, odd, queries, refs=[[1], [2]], quiet=True)
    for bad in (0, True):  # (a bool is not a count)
        with pytest.raises(PointmapError, match="n_refs expected an int >= 1"):
            localize(STAND_IN, recon, queries, n_refs=bad, quiet=True)


def test_references_are_ranked_by_encoder_similarity_so_a_copy_of_a_view_finds_that_view():
    import pointmap as pm
    from pointmap.images import View
    from pointmap.localization import rank_references

    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"]).eval()
    rng = np.random.default_rng(0)
    imgs = [torch.from_numpy(rng.random((3, 32, 48))).float() for _ in range(4)]
    views = [View(im, (48, 32), (1.0, 1.0, 0.0, 0.0), f"v{k}", k) for k, im in enumerate(imgs)]
    ranked = rank_references(model, views, [views[2], views[0]], n_refs=2)
    assert [r[0] for r in ranked] == [2, 0] and all(len(r) == 2 for r in ranked)


def test_intrinsics_with_a_negative_fy_or_a_transposed_layout_are_refused_and_numpy_reference_indices_taken(scene):
    _, recon, queries, _, _ = scene
    K = np.array([[20.0, 0, 23.5], [0, 20.0, 15.5], [0, 0, 1]])
    for bad in (np.diag([20.0, -20.0, 1.0]), K.T):
        with pytest.raises(ShapeError, match=r"K expected .*\[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"):
            localize(STAND_IN, recon, queries, refs=[[1], [2]], K=bad, quiet=True)
    loc = localize(STAND_IN, recon, queries, refs=[np.int64(3), [np.int64(0)]], quiet=True)
    assert loc.ref == [3, 0]
    # an argmax's output: 0-d tensors or arrays, a [M, k] tensor, a row of references per query
    for refs in (list(torch.tensor([3, 0])), list(np.array([3, 0])), torch.tensor([[3], [0]]), [torch.tensor([3, 2]),
                                                                                                 np.array([0])]):
        assert localize(STAND_IN, recon, queries, refs=refs, quiet=True).ref == [3, 0]


def test_a_reconstruction_of_several_image_sizes_pairs_each_reference_at_its_own_size(monkeypatch):
    from pointmap.localization import reference_views
    from pointmap.reconstruction import to_canvas

    shapes = [(32, 48), (48, 32), (32, 48), (48, 32), (32, 48)]  # views 0..3 reconstructed, 4 the query
    sc = make_scene(5, shapes=shapes, seed=7)
    as_t = [torch.from_numpy(x).float() for x in sc["depth"][:4]]
    depth, sizes = to_canvas(as_t)
    recon = Reconstruction(images=to_canvas([torch.from_numpy(x).float() for x in sc["images"][:4]])[0],
                           cam2world=torch.from_numpy(sc["cam2world"][:4]), K=torch.from_numpy(sc["K"][:4]),
                           depth_z=depth, conf=to_canvas([torch.full_like(d, 3.0) for d in as_t])[0], map_sizes=sizes)
    refs = reference_views(recon)
    assert [v.shape for v in refs] == shapes[:4] and torch.equal(refs[1].img.permute(1, 2, 0),
                                                                 torch.from_numpy(sc["images"][1]).float())
    monkeypatch.setitem(sys.modules, "pointmap.inference", types.SimpleNamespace(
        predict_pairs=lambda model, views, pairs, batch_size=8, **kw: gt_preds(sc, pairs, seed=3), encode_views=None))
    query = (sc["images"][4] * 255).round().astype(np.uint8)
    loc = localize(STAND_IN, recon, [query], refs=[[1]], quiet=True)  # paired with the portrait reference
    assert_at_true_pose(loc.cam2world[0], sc, 4, 1.0)


def test_queries_are_prepared_whole_when_the_reconstruction_was(scene):
    from pointmap.localization import query_views

    _, recon, _, _, _ = scene
    wide = np.zeros((48, 96, 3), np.uint8)
    recon.info["pipeline"] = {"size": 224, "whole": True}
    assert query_views(recon, [wide])[0].shape == (112, 224)
    recon.info["pipeline"] = {"size": 224}  # an earlier file, or reconstruct's default: the square crop
    assert query_views(recon, [wide])[0].shape == (224, 224)


def test_pm_localize_stays_the_function_after_its_module_is_imported_and_on_every_access():
    """The module is pointmap.localization, not pointmap.localize: importing a submodule binds it on the package, and
    a submodule named like the function it exports would replace ``pm.localize`` after first use."""
    import pointmap as pm
    import pointmap.localization

    for _ in range(3):
        assert pm.localize is pointmap.localization.localize and callable(pm.localize)
    assert pm.Localization is pointmap.localization.Localization


def test_the_query_scale_is_the_median_depth_ratio_over_the_references_valid_confident_pixels_only():
    import pointmap as pm
    from pointmap.localization import depth_scale

    g = torch.Generator().manual_seed(2)
    h, w = 12, 16
    z = 1 + torch.rand(1, h, w, generator=g)
    conf = torch.full((1, h, w), 5.0)
    z_pred = z / 2.0  # the reconstruction's units are twice the pair's
    z_pred[0, 0, :5] *= 40  # a few outliers among the valid pixels: a mean would move, the median does not
    z_rec = z.clone()
    z_rec[0, 1:4] = 0.0  # no depth there (a quarter of the pixels): the pair's values at them are wild
    z_pred[0, 1:4] = 1e3
    conf[0, 4:10] = 1.5  # unconfident pixels, most of the rest and wrong: out below min_conf 2
    z_pred[0, 4:10] = 1e-3
    recon = Reconstruction(images=torch.rand(1, h, w, 3, generator=g), cam2world=torch.eye(4)[None],
                           K=torch.tensor([[[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]]), depth_z=z_rec, conf=conf)
    pts = torch.zeros(1, h, w, 3)
    pts[..., 2] = z_pred
    pred = pm.PairPrediction(pts, pts.clone(), torch.ones(1, h, w), torch.ones(1, h, w))
    assert depth_scale(recon, 0, pred, min_conf=2.0) == pytest.approx(2.0, rel=1e-9)
    assert depth_scale(recon, 0, pred, min_conf=0.0) > 100  # the unconfident pixels count without the threshold
    few = torch.ones(1, h, w)
    few[0, 10, :15] = 5.0  # only 15 valid, confident pixels
    sparse = Reconstruction(images=recon.images, cam2world=recon.cam2world, K=recon.K, depth_z=z_rec, conf=few)
    assert np.isnan(depth_scale(sparse, 0, pred, min_conf=2.0))
    few[0, 10, 15] = 5.0
    assert depth_scale(sparse, 0, pred, min_conf=2.0) == pytest.approx(2.0, rel=1e-9)
