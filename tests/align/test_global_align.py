"""global_align on ground-truth pointmaps of an analytic scene (tests/align/align_scene.py)."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from align_scene import SCENE_SIZE, chain_pairs, complete_pairs, gt_preds, make_scene, pose_errors, views_of

from pointmap.align import AlignConfig, global_align

QUIET = AlignConfig(quiet=True)


@pytest.fixture(scope="module")
def scene():
    return make_scene(6, 32, 48, seed=1)


def _errors(recon, sc):
    rot, centre, a = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    focal = float(np.abs(recon.K[:, 0, 0].numpy() / sc["K"][:, 0, 0] - 1).max())
    depth = float(np.median(np.abs(recon.depth_z.numpy() * a / sc["depth"] - 1)))
    return rot, centre, focal, depth


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_noise_free_recovers_everything(scene, optimizer):
    preds = gt_preds(scene, complete_pairs(6), seed=2)
    recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, optimizer=optimizer, niter=60))
    rot, centre, focal, depth = _errors(recon, scene)
    assert rot < 0.1 and centre < 0.005 and focal < 0.005 and depth < 1e-3, (rot, centre, focal, depth)
    assert torch.isfinite(recon.pts_world).all()
    rep = recon.info["align"]
    assert rep["num_edges"] == 30 and rep["iterations"] >= 1 and rep["final_loss"] <= rep["init_loss"]


def test_without_known_poses_the_world_is_the_first_cameras_frame(scene):
    preds = gt_preds(scene, chain_pairs(6, 2), seed=3)
    recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=30))
    assert torch.allclose(recon.cam2world[0], torch.eye(4), atol=1e-5)
    # the relative poses are the truth's: camera 0 is not the truth's world, so compare in its frame
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), np.linalg.inv(scene["cam2world"][0]) @ scene["cam2world"])
    assert rot < 0.5 and centre < 0.02, (rot, centre)


def test_a_loss_that_turns_non_finite_mid_run_is_reported_and_the_best_iterate_is_kept(scene, monkeypatch):
    from pointmap.align import loop

    real, calls = loop.loss_and_grad, {"n": 0}

    def blows_up_at_the_sixth(*args, **kw):  # as a NaN in a prediction or a diverging step would
        calls["n"] += 1
        return float("nan") if calls["n"] == 6 else real(*args, **kw)

    monkeypatch.setattr(loop, "loss_and_grad", blows_up_at_the_sixth)
    preds = gt_preds(scene, complete_pairs(6), seed=2)
    with pytest.warns(RuntimeWarning, match=r"loss became non-finite after 5 of 60 iterations.*best iterate"):
        recon = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=60))
    rep = recon.info["align"]
    assert rep["stop_reason"] == "non-finite loss" and not rep["converged"] and rep["iterations"] == 5
    assert torch.isfinite(recon.cam2world).all() and rep["final_loss"] <= rep["init_loss"]
    calls["n"] = -100  # non-finite from the first iteration: nothing to keep but the start
    monkeypatch.setattr(loop, "loss_and_grad", lambda *a, **k: float("nan"))
    with pytest.warns(RuntimeWarning, match=r"after 0 of 60 iterations.*the initial state is returned, unoptimised"):
        global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=60))


def test_sparse_graph_and_original_pixels(scene):
    """Chain graph (each image paired with its next two) and maps that are a 2x downscale + crop of the
    original: K comes back in ORIGINAL pixels."""
    preds = gt_preds(scene, chain_pairs(6, 2), seed=3)
    views = views_of(scene)
    for v in views:  # pretend the originals were 2x larger with 3 px cut off the left of the resized map
        v.original_size = (2 * 48 + 6, 64)
        v.map_from_original = (0.5, 0.5, 1.5, 0.0)
    recon = global_align(views, preds, config=QUIET)
    rot, centre, _, _ = _errors(recon, scene)
    assert rot < 0.1 and centre < 0.005
    f_orig = scene["K"][:, 0, 0] * 2
    cx_orig = ((scene["K"][:, 0, 2] + 0.5 + 1.5) / 0.5) - 0.5
    assert np.allclose(recon.K[:, 0, 0].numpy(), f_orig, rtol=5e-3)
    assert np.allclose(recon.K[:, 0, 2].numpy(), cx_orig, atol=1e-3)
    assert np.allclose(recon.K_map[:, 0, 0].numpy(), scene["K"][:, 0, 0], rtol=5e-3)


def test_noise_and_outliers_degrade_gracefully(scene):
    preds = gt_preds(scene, complete_pairs(6), seed=4, noise=0.01, outliers=0.03, pair_rot_deg=0.5)
    init = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, optimizer="none"))
    recon = global_align(views_of(scene), preds, config=QUIET)
    rot0, centre0, _, _ = _errors(init, scene)
    rot, centre, focal, depth = _errors(recon, scene)
    assert rot < 0.5 and centre < 0.01 and focal < 0.02 and depth < 0.02, (rot, centre, focal, depth)
    assert rot <= rot0 + 1e-3  # optimisation improves on (or keeps) its start
    assert recon.info["align"]["final_loss"] < recon.info["align"]["init_loss"]


def test_downsampled_optimisation_matches_full_resolution(scene):
    preds = gt_preds(scene, complete_pairs(6), seed=5, noise=0.005)
    full = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, stride=1, niter=100))
    sub = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, stride=3, niter=100))
    assert sub.info["align"]["opt_pixels_per_image"] < full.info["align"]["opt_pixels_per_image"] / 8
    rot_f, c_f, _, _ = _errors(full, scene)
    rot_s, c_s, _, _ = _errors(sub, scene)
    assert rot_s < 0.3 and rot_f < 0.3 and c_s < 0.01
    assert sub.depth_z.shape == full.depth_z.shape == (6, 32, 48)  # depth is always full resolution


def test_a_stride_beyond_the_maps_keeps_their_middle_pixel_instead_of_failing():
    from pointmap.align.edges import sample_index

    rows, cols = sample_index(16, 24, 40)  # was arange(20, 16, 40): "upper bound and lower bound inconsistent"
    assert rows.tolist() == [7] and cols.tolist() == [20]  # the cell centre where the side reaches it
    assert [len(x) for x in sample_index(16, 24, 32)] == [1, 1]  # was no row at all
    assert [x.tolist() for x in sample_index(32, 48, 16)] == [[8, 24], [8, 24, 40]]  # within the map: as before
    sc = make_scene(3, 16, 24, seed=4)
    preds = gt_preds(sc, complete_pairs(3), seed=4)
    for stride in (32, 40):  # was a GraphError (every pair "zero weight"), then a raw RuntimeError
        with pytest.warns(UserWarning):  # one pixel per image places nothing well
            recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, stride=stride, niter=2))
        assert recon.info["align"]["opt_pixels_per_image"] == 1 and torch.isfinite(recon.cam2world).all()


def test_the_automatic_stride_keeps_at_most_max_opt_pixels_per_image():
    from pointmap.align.edges import choose_stride, sample_index

    # the square root alone rounds rows and columns up past the cap: 176 x 960 kept 1036 of 1000, 8 x 11 kept 12 of 10
    for (h, w), cap in (((176, 960), 1000), ((8, 11), 10), ((20, 8), 1), ((384, 512), 96 * 64)):
        stride = choose_stride([(h, w)], cap, None)
        rows, cols = sample_index(h, w, stride)
        assert 1 <= len(rows) * len(cols) <= cap, (h, w, cap, stride, len(rows) * len(cols))
    assert choose_stride([(384, 512)], 96 * 64, None) == 6  # where the root already fits, it is kept


def test_chunk_size_does_not_change_the_result(scene):
    preds = gt_preds(scene, complete_pairs(6), seed=6, noise=0.01)
    a = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=20, max_chunk_pixels=10**9))
    b = global_align(views_of(scene), preds, config=AlignConfig(quiet=True, niter=20, max_chunk_pixels=2000))
    assert b.info["align"]["chunk_edges"] == 1 and a.info["align"]["chunk_edges"] == 30
    assert torch.allclose(a.cam2world, b.cam2world, atol=1e-4)
    assert abs(a.info["align"]["final_loss"] - b.info["align"]["final_loss"]) < 1e-5


def test_scene_scale_is_consistent(scene):
    """All cameras share one scale: the ratio of estimated to true camera distances is constant."""
    preds = gt_preds(scene, complete_pairs(6), seed=7)
    recon = global_align(views_of(scene), preds, config=QUIET)
    c_est = recon.cam2world[:, :3, 3].double().numpy()
    c_gt = scene["cam2world"][:, :3, 3]
    d_est = np.linalg.norm(c_est[:, None] - c_est[None], axis=-1)[np.triu_indices(6, 1)]
    d_gt = np.linalg.norm(c_gt[:, None] - c_gt[None], axis=-1)[np.triu_indices(6, 1)]
    ratio = d_est / d_gt
    assert ratio.std() / ratio.mean() < 1e-3
    assert SCENE_SIZE > 0


def test_auto_weighting_reads_log_of_spread_confidences_and_conf_itself_at_their_floor(scene):
    """Confidences spread over 1..4 are weighted by log (DUSt3R); the same maps with every confidence squashed
    to within 1e-5 of 1 (a model whose confidence sits at its floor) by conf itself, and still align."""
    preds = gt_preds(scene, complete_pairs(6), seed=8, noise=0.01, outliers=0.03, pair_rot_deg=0.5)
    spread = global_align(views_of(scene), preds, config=QUIET)
    assert spread.info["align"]["conf_transform"] == "log"
    floor = {k: replace(p, conf1=1 + (p.conf1 - 1) * 1e-5, conf2=1 + (p.conf2 - 1) * 1e-5) for k, p in preds.items()}
    auto = global_align(views_of(scene), floor, config=QUIET)
    assert auto.info["align"]["conf_transform"] == "id"
    rot, centre, focal, _ = _errors(auto, scene)
    assert rot < 0.5 and centre < 0.01 and focal < 0.02, (rot, centre, focal)
    explicit = global_align(views_of(scene), floor, config=AlignConfig(quiet=True, conf_transform="id"))
    assert torch.equal(explicit.cam2world, auto.cam2world) and torch.equal(explicit.depth_z, auto.depth_z)


@pytest.mark.parametrize("field, value", [("niter", -5), ("niter", 2.5), ("lr", -1.0), ("lr", float("nan")),
                                          ("lr_focal", 0.0), ("early_stop_window", -1), ("max_opt_pixels", -10),
                                          ("stride", 0), ("fuse_iters", 2.5), ("max_chunk_pixels", True),
                                          ("early_stop_tol", float("inf")), ("quiet", "yes")])
def test_a_config_with_an_impossible_number_is_refused_when_it_is_made_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"AlignConfig.{field} expected .*, got {value!r}"):
        AlignConfig(**{field: value})


def test_a_config_of_zero_iterations_is_allowed_and_returns_the_start():
    assert AlignConfig(niter=0).niter == 0 and AlignConfig(max_opt_pixels=None, lr_focal=None).stride is None


@pytest.mark.parametrize("field, value", [("conf_transform", "rank"), ("optimizer", "sgd"), ("schedule", "step")])
def test_a_config_with_an_unknown_name_is_refused_when_it_is_made(field, value):
    with pytest.raises(ValueError, match=f"AlignConfig.{field} expected one of"):
        AlignConfig(**{field: value})


def test_a_shared_focal_is_one_value_for_all_images_and_recovers_one_camera():
    sc = make_scene(5, 32, 48, seed=11, focal_range=(44.0, 44.0))
    preds = gt_preds(sc, complete_pairs(5), seed=12, noise=0.01, outliers=0.03, pair_rot_deg=0.5)
    free = global_align(views_of(sc), preds, config=QUIET)
    shared = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, shared_focal=True))
    f_free, f_shared = free.K[:, 0, 0].double(), shared.K[:, 0, 0].double()
    assert float(f_shared.max() - f_shared.min()) == 0.0 and float(f_free.max() - f_free.min()) > 0.0
    assert abs(float(f_shared[0]) / 44.0 - 1) < 0.02, f_shared
    rot, centre, _, _ = _errors(shared, sc)
    assert rot < 0.5 and centre < 0.01, (rot, centre)


def test_camera_labels_share_one_focal_within_each_camera_and_recover_two_cameras():
    labels = (7, 3, 7, 3, 7)  # two phones: any ints, numbered in order of first appearance
    sc = make_scene(5, 32, 48, seed=11, focals=[44.0, 58.0, 44.0, 58.0, 44.0])
    preds = gt_preds(sc, complete_pairs(5), seed=12, noise=0.01, outliers=0.03, pair_rot_deg=0.5)
    recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, shared_focal=list(labels)))
    f = recon.K[:, 0, 0].double()
    assert float(f[[0, 2, 4]].max() - f[[0, 2, 4]].min()) == 0.0 and float(f[1] - f[3]) == 0.0
    assert abs(float(f[0]) / 44.0 - 1) < 0.02 and abs(float(f[1]) / 58.0 - 1) < 0.02, f
    assert recon.info["align"]["config"]["shared_focal"] == labels  # kept as a tuple, hashable
    rot, centre, _, _ = _errors(recon, sc)
    assert rot < 0.5 and centre < 0.01, (rot, centre)
    # the epipolar stage and the sparse refinement keep one focal per camera
    from pointmap.align.sparse import refine_matches

    matches = {k: (torch.rand(20, 2) * 40, torch.rand(20, 2) * 40, torch.ones(20)) for k in preds}
    refined = refine_matches(recon, matches)
    assert torch.equal(refined.K[:, 0, 0], recon.K[:, 0, 0])


def test_camera_labels_of_another_length_or_not_ints_are_refused_and_a_camera_of_two_sizes_is_named():
    from pointmap.errors import ShapeError

    sc = make_scene(4, 32, 48, seed=3)
    preds = gt_preds(sc, complete_pairs(4), seed=4)
    with pytest.raises(ShapeError, match=r"expected True, False or a camera label per image \(4\), got 3 labels"):
        global_align(views_of(sc), preds, config=AlignConfig(quiet=True, shared_focal=(0, 0, 1)))
    for bad in ("0011", (0, 0.5, 1, 1), 3):
        with pytest.raises(ShapeError, match="AlignConfig.shared_focal expected True, False or a camera label"):
            AlignConfig(shared_focal=bad)
    assert AlignConfig(shared_focal=(c for c in (0, 0, 1, 1))).shared_focal == (0, 0, 1, 1)  # a generator, read once
    with pytest.raises(ShapeError, match=r"AlignConfig.lr_min expected <= lr \(0.01\), got 0.5"):
        AlignConfig(lr=0.01, lr_min=0.5)  # the schedule would raise the rate, and the report say converged
    views = views_of(sc)
    views[3].original_size = (96, 64)
    views[3].map_from_original = (0.5, 0.5, 0.0, 0.0)
    global_align(views, preds, config=AlignConfig(quiet=True, shared_focal=(0, 0, 1, 2), niter=0))  # 3 alone: fine
    with pytest.raises(ShapeError, match=r"camera 1 \(images \[2, 3\]\): shared_focal expects images of one camera, "
                                         "all of one size"):
        global_align(views, preds, config=AlignConfig(quiet=True, shared_focal=(0, 0, 1, 1)))


def test_a_shared_focal_is_refused_for_images_of_two_sizes_or_for_k_known_for_some_images_only(scene):
    from pointmap.errors import PointmapError, ShapeError

    preds = gt_preds(scene, complete_pairs(6), seed=13)
    views = views_of(scene)
    views[2].original_size = (96, 64)
    views[2].map_from_original = (0.5, 0.5, 0.0, 0.0)
    with pytest.raises(ShapeError, match="shared_focal expects images of one camera, all of one size"):
        global_align(views, preds, config=AlignConfig(quiet=True, shared_focal=True))
    views = views_of(scene)  # one size, but one image cropped differently
    views[2].map_from_original = (1.0, 1.0, 2.0, 0.0)
    with pytest.raises(ShapeError, match="resized and cropped alike"):
        global_align(views, preds, config=AlignConfig(quiet=True, shared_focal=True))
    K0 = torch.from_numpy(scene["K"][0])
    with pytest.raises(PointmapError, match="give K for all images"):
        global_align(views_of(scene), preds, K={0: K0}, config=AlignConfig(quiet=True, shared_focal=True))
    with pytest.raises(PointmapError, match="known focals that differ"):
        global_align(views_of(scene), preds, K=torch.from_numpy(scene["K"]),
                     config=AlignConfig(quiet=True, shared_focal=True))


def test_a_shared_focal_is_one_parameter_that_the_loss_moves():
    from pointmap.align.params import AlignParams

    n, E, P = 3, 2, 5
    f = torch.tensor([40.0, 44.0, 48.0], dtype=torch.float64)
    params = AlignParams(torch.eye(4, dtype=torch.float64).repeat(n, 1, 1), torch.ones(n, dtype=torch.bool),
                         torch.ones(n, P, dtype=torch.float64), f, f, f * 0, f * 0, torch.ones(n, dtype=torch.bool),
                         torch.ones(E, dtype=torch.float64), torch.eye(3, dtype=torch.float64).repeat(E, 1, 1),
                         torch.zeros(E, 3, dtype=torch.float64), scale_free=True, camera=torch.zeros(n, dtype=torch.long))
    assert params.log_f.shape == (1,)
    fx, fy, _, _ = params.intrinsics()
    assert torch.allclose(fx.double(), torch.full((3,), float(f.log().mean().exp()), dtype=torch.float64))
    two = AlignParams(torch.eye(4, dtype=torch.float64).repeat(n, 1, 1), torch.ones(n, dtype=torch.bool),
                      torch.ones(n, P, dtype=torch.float64), f, f, f * 0, f * 0, torch.ones(n, dtype=torch.bool),
                      torch.ones(E, dtype=torch.float64), torch.eye(3, dtype=torch.float64).repeat(E, 1, 1),
                      torch.zeros(E, 3, dtype=torch.float64), scale_free=True, camera=torch.tensor([0, 1, 0]))
    fx2 = two.intrinsics()[0].double()
    assert two.log_f.shape == (2,) and torch.allclose(fx2, torch.tensor([(40.0 * 48.0) ** 0.5, 44.0, (40.0 * 48.0) ** 0.5], dtype=torch.float64))
    uv = torch.rand(n, P, 2) * 10
    params.world_points(uv)[..., 0].sum().backward()
    assert params.log_f.grad is not None and float(params.log_f.grad.abs()) > 0


def test_portrait_and_landscape_views_are_aligned_whole_and_held_on_one_canvas():
    shapes = [(32, 48), (48, 32), (32, 48), (48, 32), (32, 32)]  # (h, w): landscape, portrait, square
    sc = make_scene(5, shapes=shapes, seed=4)
    recon = global_align(views_of(sc), gt_preds(sc, complete_pairs(5), seed=5), config=QUIET)
    assert tuple(recon.depth_z.shape) == (5, 48, 48) and recon.map_sizes == [(w, h) for h, w in shapes]
    rot, centre, a = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1 and centre < 0.005, (rot, centre)
    assert np.abs(recon.K[:, 0, 0].numpy() / sc["K"][:, 0, 0] - 1).max() < 0.005
    assert np.allclose(recon.K[:, :2, 2].numpy(), sc["K"][:, :2, 2])  # each principal point at its own centre
    for k, (h, w) in enumerate(shapes):
        own = recon.crop(recon.depth_z, k).numpy()
        assert own.shape == (h, w) and np.median(np.abs(own * a / sc["depth"][k] - 1)) < 1e-3
        pad = ~recon.regions[k]
        assert (recon.depth_z[k][pad] == 0).all() and (recon.conf[k][pad] == 0).all() and not recon.valid()[k][pad].any()


@pytest.mark.parametrize("init", ["mst", "averaging"])
def test_a_pair_with_a_few_usable_points_does_not_lead_the_start_on_its_confidences_alone(init):
    sc = make_scene(4, 24, 32, seed=1)
    preds = gt_preds(sc, complete_pairs(4))
    for k in [(0, 1), (1, 0)]:  # view 2's map NaN but for 2 pixels, its confidences still full
        gone = torch.ones(24 * 32, dtype=torch.bool)
        gone[torch.randperm(24 * 32, generator=torch.Generator().manual_seed(0))[:2]] = False
        preds[k].pts2_cam1[0].view(-1, 3)[gone] = float("nan")
    recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, niter=30, init=init))
    rot, _, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1  # the spanning tree took that pair first: 71 degrees off


@pytest.mark.parametrize("bad", [float("nan"), 0.0, -40.0])
def test_a_focal_head_that_gives_no_focal_starts_the_image_from_its_pointmaps_focal_not_the_image_size(bad):
    import dataclasses

    sc = make_scene(4, 32, 48, seed=3)
    preds = gt_preds(sc, complete_pairs(4), seed=4)
    cfg = AlignConfig(quiet=True, niter=0)
    plain = global_align(views_of(sc), preds, config=cfg)  # no focal head: each image's Weiszfeld focal
    headless = {k: dataclasses.replace(p, focal1=torch.tensor([bad]), focal2=torch.tensor([bad]))
                for k, p in preds.items()}
    out = global_align(views_of(sc), headless, config=cfg)
    assert torch.allclose(out.K, plain.K) and np.abs(plain.K[:, 0, 0].numpy() / sc["K"][:, 0, 0] - 1).max() < 0.01
