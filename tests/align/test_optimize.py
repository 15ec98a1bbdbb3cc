"""global_align's own steps (pointmap/align/optimize.py): its start focals, known and shared cameras, gauge,
depth fusion and refusals, on ground-truth pointmaps of an analytic scene (tests/align/align_scene.py). Written
from a mutation review (session 86): each test fails on a change of optimize.py the other tests let through."""

import dataclasses
import warnings

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, pose_errors, views_of

from pointmap.align import AlignConfig, global_align

START = AlignConfig(quiet=True, niter=0)  # the start, unoptimised: what the initialisation chose


@pytest.fixture(scope="module")
def scene():
    return make_scene(4, 32, 48, seed=3)


def _with_focal_heads(preds, focals):
    """Every prediction given a focal head that reads ``focals[i]`` for view i (and focals[j] for view 2)."""
    return {(i, j): dataclasses.replace(p, focal1=torch.tensor([float(focals[i])]),
                                        focal2=torch.tensor([float(focals[j])])) for (i, j), p in preds.items()}


def test_a_focal_heads_focal_is_the_start_focal_of_its_image_not_the_pointmaps(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    heads = scene["K"][:, 0, 0] * np.array([1.2, 0.9, 1.1, 0.8])  # each off the pointmaps' own (true) focal
    recon = global_align(views_of(scene), _with_focal_heads(preds, heads), config=START)
    assert np.allclose(recon.K[:, 0, 0].double().numpy(), heads, rtol=1e-5), (recon.K[:, 0, 0], heads)


def test_a_known_K_is_the_focal_the_alignment_uses_whatever_the_focal_heads_say(scene):
    """Known K for all images, focal heads 40% short: the poses must come from the given focal (exact here), not
    from the heads' (the output K is the given one either way, so look at the geometry)."""
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    wrong = _with_focal_heads(preds, scene["K"][:, 0, 0] * 0.6)
    K = torch.from_numpy(scene["K"]).float()
    recon = global_align(views_of(scene), wrong, K=K, config=AlignConfig(quiet=True, niter=30))
    assert torch.equal(recon.K, K)
    rot, centre, a = pose_errors(recon.cam2world.numpy(), scene["cam2world"])
    depth = float(np.median(np.abs(recon.depth_z.numpy() * a / scene["depth"] - 1)))
    assert rot < 0.1 and centre < 0.005 and depth < 1e-3, (rot, centre, depth)


def test_an_image_whose_pointmap_gives_no_focal_starts_from_its_longer_side(scene, monkeypatch):
    import pointmap.align.optimize as optimize

    monkeypatch.setattr(optimize, "focal_from_pointmap",
                        lambda pts, **kw: torch.full((pts.shape[0],), float("nan"), dtype=pts.dtype))
    recon = global_align(views_of(scene), gt_preds(scene, complete_pairs(4), seed=4), config=START)
    assert recon.K[:, 0, 0].tolist() == [48.0] * 4 and recon.K[:, 1, 1].tolist() == [48.0] * 4


def test_quiet_false_overrides_a_quiet_config(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    recon = global_align(views_of(scene), preds, config=START, quiet=False)
    assert recon.info["align"]["config"]["quiet"] is False
    recon = global_align(views_of(scene), preds, config=AlignConfig(niter=0), quiet=True)
    assert recon.info["align"]["config"]["quiet"] is True


def test_each_shared_camera_starts_from_the_median_of_its_images_focal_estimates():
    """Camera 0 has two images (median = their mean), camera 1 three (median = the middle one), with focals far
    enough apart that the mean, the geometric mean and the largest all differ from the median."""
    focals = [40.0, 60.0, 40.0, 50.0, 70.0]
    sc = make_scene(5, 32, 48, seed=11, focals=focals)
    preds = gt_preds(sc, complete_pairs(5), seed=12)
    own = global_align(views_of(sc), preds, config=START).K[:, 0, 0].double()  # each image's own estimate
    assert np.allclose(own.numpy(), focals, rtol=1e-3)
    shared = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, niter=0, shared_focal=(0, 0, 1, 1, 1)))
    f = shared.K[:, 0, 0].double()
    want0 = float(own[:2].mean())
    want1 = float(own[2:].median())
    assert torch.allclose(f, torch.tensor([want0] * 2 + [want1] * 3, dtype=torch.float64), rtol=1e-5), (f, want0, want1)


def test_a_known_K_comes_back_bit_for_bit_from_maps_smaller_than_the_originals(scene):
    """Maps 224/1080 of the originals: a K in original pixels does not survive the float round trip to map pixels
    and back, so the alignment must hand back the given one (as it does for known poses)."""
    from pointmap.reconstruction import K_to_map, K_to_original

    mfo = torch.tensor([224 / 1080, 224 / 1080, 0.0, 0.0])
    K0 = K_to_original(torch.from_numpy(scene["K"][0]).float(), mfo)
    def round_trip(K):
        return K_to_original(K_to_map(K, mfo).double(), mfo.double()).float()

    for _ in range(200):  # a focal whose round trip (float32 map, float64 back, float32) changes it
        K0[0, 0] = K0[1, 1] = float(K0[0, 0]) + 0.37
        if not torch.equal(round_trip(K0), K0):
            break
    assert not torch.equal(round_trip(K0), K0)
    views = views_of(scene)
    for v in views:
        v.original_size = (round(48 * 1080 / 224), round(32 * 1080 / 224))
        v.map_from_original = tuple(mfo.tolist())
    recon = global_align(views, gt_preds(scene, complete_pairs(4), seed=4), K={0: K0}, config=START)
    assert torch.equal(recon.K[0], K0) and recon.info["align"]["known_K_indices"] == [0]


def test_a_shared_focal_is_refused_for_known_focals_a_few_percent_apart(scene):
    from pointmap.errors import PointmapError

    K = torch.from_numpy(scene["K"][:1]).repeat(4, 1, 1).float()
    K[1, 0, 0] = K[1, 1, 1] = K[0, 0, 0] * 1.03  # two phones of nearly one focal are still two cameras
    with pytest.raises(PointmapError, match="known focals that differ"):
        global_align(views_of(scene), gt_preds(scene, complete_pairs(4), seed=4), K=K,
                     config=AlignConfig(quiet=True, niter=0, shared_focal=True))


def test_without_known_poses_image_0_is_the_world_frame_even_when_the_start_is_rooted_elsewhere(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    for (i, j), p in preds.items():  # image 0's pairs the least confident: the start's root is another image
        if 0 in (i, j):
            preds[(i, j)] = dataclasses.replace(p, conf1=p.conf1 * 0 + 1.5, conf2=p.conf2 * 0 + 1.5)
    for init in ("averaging", "mst"):
        recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=0, init=init))
        assert recon.info["align"]["root"] != 0, init
        assert torch.allclose(recon.cam2world[0], torch.eye(4), atol=1e-5), (init, recon.cam2world[0])


def test_without_known_poses_the_scene_comes_out_in_the_pairs_mean_scale(scene):
    """The free gauge: the geometric mean of the edges' scales is 1, so the reconstruction is in the units of the
    predictions (ground truth times the geometric mean of gt_preds' random per-pair scales)."""
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    c2w, pw = scene["cam2world"], scene["pts_world"]
    log_s = []
    for (i, _), p in preds.items():
        w2c = np.linalg.inv(c2w[i])
        own = pw[i] @ w2c[:3, :3].T + w2c[:3, 3]
        log_s.append(np.log(float(p.pts1_cam1.double().norm()) / np.linalg.norm(own)))
    recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=30))
    _, _, a = pose_errors(recon.cam2world.numpy(), c2w)  # truth ~ a * estimate
    assert abs(1 / a / np.exp(np.mean(log_s)) - 1) < 1e-3, (1 / a, np.exp(np.mean(log_s)))


def test_a_known_focal_is_held_during_the_optimisation_not_only_in_the_result(scene):
    """Known K 30% off the pointmaps' focal: the output K is the given one either way, but a held focal cannot fit
    the maps, so the loss stays far above that of a free focal (which fits them exactly)."""
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    cfg = AlignConfig(quiet=True, niter=30)
    free = global_align(views_of(scene), preds, config=cfg).info["align"]
    K = torch.from_numpy(scene["K"]).float()
    K[:, :2, :2] *= 1.3
    held = global_align(views_of(scene), preds, K=K, config=cfg)
    assert torch.equal(held.K, K)
    rep = held.info["align"]
    assert rep["final_loss"] > 0.3 * rep["init_loss"] and rep["final_loss"] > 1e4 * free["final_loss"], (rep, free)


def test_more_depth_fusion_passes_downweight_outliers_in_the_full_resolution_depth(scene):
    preds = gt_preds(scene, complete_pairs(4), seed=5, noise=0.02, outliers=0.1)
    err = {}
    for passes in (0, 3):
        recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=30, fuse_iters=passes))
        _, _, a = pose_errors(recon.cam2world.numpy(), scene["cam2world"])
        err[passes] = float(np.abs(recon.depth_z.numpy() * a / scene["depth"] - 1).mean())
    assert err[3] < 0.85 * err[0], err


def test_an_alignment_that_ends_in_non_finite_depth_is_refused_with_a_clear_message(scene, monkeypatch):
    import pointmap.align.optimize as optimize
    from pointmap.errors import PointmapError

    real = optimize.fuse_depth

    def nan_in_image_1(*args, **kw):  # as degenerate predictions would leave it
        depths, confs = real(*args, **kw)
        depths[1] = depths[1].clone()
        depths[1][3, 4] = float("nan")
        return depths, confs

    monkeypatch.setattr(optimize, "fuse_depth", nan_in_image_1)
    with pytest.raises(PointmapError, match="non-finite depth_z"):
        global_align(views_of(scene), gt_preds(scene, complete_pairs(4), seed=4), config=START)


def test_a_negative_confidence_block_weighs_nothing_in_the_start_focal(scene):
    """As NaN and inf confidences (and as the edge weights treat them): a negative confidence is no weight, so
    wrong points under it do not move the Weiszfeld focal."""
    preds = gt_preds(scene, complete_pairs(4), seed=4)
    for p in preds.values():
        p.pts1_cam1[0, :6, :8, :2] *= 1.5  # wrong points...
        p.conf1[0, :6, :8] = -20.0  # ...that the confidence disowns (the maps' mean confidence stays positive)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the start is the usual one: no fallback, nothing to warn about
        recon = global_align(views_of(scene), preds, config=START)
    assert np.abs(recon.K[:, 0, 0].double().numpy() / scene["K"][:, 0, 0] - 1).max() < 1e-4, recon.K[:, 0, 0]


@pytest.mark.parametrize("optimizer, blames_lr", [("adam", True), ("lbfgs", False)])
def test_a_non_finite_loss_warning_suggests_the_learning_rate_only_for_adam(scene, monkeypatch, optimizer, blames_lr):
    from pointmap.align import loop

    monkeypatch.setattr(loop, "loss_and_grad", lambda *a, **k: float("nan"))
    with pytest.warns(RuntimeWarning, match="loss became non-finite") as said:
        global_align(views_of(scene), gt_preds(scene, complete_pairs(4), seed=4),
                     config=AlignConfig(quiet=True, niter=5, optimizer=optimizer))
    text = " ".join(str(w.message) for w in said if "non-finite" in str(w.message))
    assert ("too high a learning rate" in text) == blames_lr, text
