"""Known intrinsics and known poses (all or a subset)."""

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, pose_errors, views_of

from pointmap.align import AlignConfig, global_align
from pointmap.errors import ConventionError, ShapeError

QUIET = AlignConfig(quiet=True)


@pytest.fixture(scope="module")
def scene():
    return make_scene(5, 32, 48, seed=11)


def test_known_poses_all_bit_identical_and_metric(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=1, noise=0.01)
    c2w = torch.from_numpy(scene["cam2world"]).float()
    recon = global_align(views_of(scene), preds, cam2world=c2w, config=QUIET)
    assert torch.equal(recon.cam2world, c2w)
    assert recon.info["align"]["scale_fixed_by_known_poses"]
    # the scale follows the given poses: depth in the scene's units
    rel = np.median(np.abs(recon.depth_z.numpy() / scene["depth"] - 1))
    assert rel < 0.02


def test_known_pose_subset_dict(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=2)
    known = {0: torch.from_numpy(scene["cam2world"][0]).float(), 3: torch.from_numpy(scene["cam2world"][3]).float()}
    recon = global_align(views_of(scene), preds, cam2world=known, config=QUIET)
    for i, T in known.items():
        assert torch.equal(recon.cam2world[i], T)
    # the free cameras land where they belong, in the given poses' frame and scale (no Sim(3) needed)
    err = (recon.cam2world[:, :3, 3].double() - torch.from_numpy(scene["cam2world"][:, :3, 3])).norm(dim=-1)
    assert float(err.max()) < 0.01 * 8.0
    rot, _, _ = pose_errors(recon.cam2world.numpy(), scene["cam2world"])
    assert rot < 0.1


def test_one_known_pose_with_mask_fixes_frame(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=3)
    c2w = torch.from_numpy(scene["cam2world"]).float()
    mask = torch.tensor([False, True, False, False, False])
    recon = global_align(views_of(scene), preds, cam2world=c2w, pose_mask=mask, config=QUIET)
    assert torch.equal(recon.cam2world[1], c2w[1])
    assert not recon.info["align"]["scale_fixed_by_known_poses"]
    # rotations are in the given frame even though the scale is free
    R_err = recon.cam2world[:, :3, :3].double().transpose(-1, -2) @ torch.from_numpy(scene["cam2world"][:, :3, :3])
    ang = torch.rad2deg(torch.acos(((R_err.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert float(ang.max()) < 0.1


def test_known_intrinsics_in_original_pixels_are_honoured(scene):
    """Maps are a 0.5x resize of the originals; K given at original resolution comes back unchanged."""
    preds = gt_preds(scene, complete_pairs(5), seed=4, noise=0.01)
    views = views_of(scene)
    for v in views:
        v.original_size = (96, 64)
        v.map_from_original = (0.5, 0.5, 0.0, 0.0)
    K_orig = torch.from_numpy(scene["K"]).clone()
    K_orig[:, :2, :2] *= 2
    K_orig[:, :2, 2] = (K_orig[:, :2, 2] + 0.5) * 2 - 0.5
    recon = global_align(views, preds, K=K_orig.float(), config=QUIET)
    assert torch.equal(recon.K, K_orig.float())
    assert torch.allclose(recon.K_map.double(), torch.from_numpy(scene["K"]), atol=1e-4)
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), scene["cam2world"])
    assert rot < 0.5 and centre < 0.01


def test_shared_K_and_known_K_beats_wrong_init():
    sc = make_scene(5, 32, 48, seed=12, focal_range=(44.0, 44.0))
    preds = gt_preds(sc, complete_pairs(5), seed=5)
    K = torch.from_numpy(sc["K"][0]).float()
    recon = global_align(views_of(sc), preds, K=K, config=QUIET)
    assert torch.equal(recon.K, K.expand(5, 3, 3))
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.1 and centre < 0.005


def test_bad_known_inputs_give_clear_errors(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=6)
    views = views_of(scene)
    with pytest.raises(ShapeError, match=r"K expected \[3, 3\]"):
        global_align(views, preds, K=torch.eye(4), config=QUIET)
    bad = torch.eye(4).repeat(5, 1, 1)
    bad[2, :3, :3] *= 2
    with pytest.raises(ConventionError, match="not a rigid transform"):
        global_align(views, preds, cam2world=bad, config=QUIET)
    with pytest.raises(ShapeError, match="cam2world expected"):
        global_align(views, preds, cam2world=torch.eye(4).repeat(3, 1, 1), config=QUIET)
    # what is not numbers, or not a mask, is named (it failed deep inside torch.as_tensor)
    for kw, named in (({"K": "K"}, "K expected numbers"), ({"cam2world": "x"}, "cam2world expected numbers"),
                      ({"K": {0: None}}, r"K\[0\] expected numbers"),
                      ({"cam2world": torch.eye(4).repeat(5, 1, 1), "pose_mask": "abc"}, "pose_mask expected bools"),
                      ({"cam2world": torch.eye(4).repeat(5, 1, 1), "pose_mask": [0.5] * 5}, "pose_mask expected bools")):
        with pytest.raises(ShapeError, match=named):
            global_align(views, preds, config=QUIET, **kw)


def test_a_transposed_K_fractional_image_keys_and_a_pose_mask_beside_a_dict_are_refused(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=1)
    K = torch.from_numpy(scene["K"][0]).double()
    with pytest.raises(ConventionError, match="a transposed K puts cx, cy in the bottom row"):
        global_align(views_of(scene), preds, K=K.T, config=QUIET)
    with pytest.raises(ShapeError, match="K: keys expected integer image indices, got float 0.7"):
        global_align(views_of(scene), preds, K={0.7: K}, config=QUIET)
    c2w = torch.from_numpy(scene["cam2world"]).float()
    with pytest.raises(ShapeError, match="cam2world: keys expected integer image indices, got float 1.9"):
        global_align(views_of(scene), preds, cam2world={1.9: c2w[1]}, config=QUIET)
    with pytest.raises(ShapeError, match="pose_mask expected only with a \\[N, 4, 4\\] cam2world"):
        global_align(views_of(scene), preds, cam2world={1: c2w[1]}, pose_mask=[True] * 5, config=QUIET)


def test_known_poses_too_far_from_the_origin_for_float32_are_refused_with_the_offset_to_subtract(scene):
    """Georeferenced poses (UTM: millions of metres) came back with depths 31% wrong and free cameras metres off,
    without a word; within float32's reach the free cameras land where they belong."""
    preds = gt_preds(scene, complete_pairs(5), seed=2)
    c2w = torch.from_numpy(scene["cam2world"]).double()
    for shift, ok in ((6e4, True), (4e6, False)):
        moved = c2w.clone()
        moved[:, :3, 3] += torch.tensor([1.0, 0.07, 1.2], dtype=torch.float64) * shift
        known = {0: moved[0], 3: moved[3]}
        if not ok:
            with pytest.raises(ConventionError, match=r"known poses lie up to 4\.8e\+06 units from the origin against "
                                                      r"a spread of .*subtract an offset .*\(e\.g\. their mean centre"):
                global_align(views_of(scene), preds, cam2world=known, config=QUIET)
            continue
        recon = global_align(views_of(scene), preds, cam2world=known, config=QUIET)
        err = (recon.cam2world[:, :3, 3].double() - moved[:, :3, 3]).norm(dim=-1)
        assert float(err.max()) < 0.01
    with pytest.raises(ConventionError, match="spread of 1"):  # one known camera fixes no scale: one unit across
        global_align(views_of(scene), preds, cam2world={0: moved[0]}, config=QUIET)


def test_known_poses_sharing_one_centre_a_tripod_are_accepted_and_nan_rows_left_out_by_the_mask_are_ignored(scene):
    preds = gt_preds(scene, complete_pairs(5), seed=2)
    c2w = torch.from_numpy(scene["cam2world"]).float()
    tripod = c2w.clone()
    tripod[:, :3, 3] = torch.tensor([2.0, 0.3, 1.0])  # rotations known, one centre: no scale, no float32 issue
    recon = global_align(views_of(scene), preds, cam2world=tripod, pose_mask=[True, True, False, False, False],
                         config=QUIET)
    assert torch.equal(recon.cam2world[:2], tripod[:2])
    placeholders = c2w.clone()
    placeholders[2:] = float("nan")  # unknown rows as NaN placeholders
    recon = global_align(views_of(scene), preds, cam2world=placeholders, pose_mask=[True, True, False, False, False],
                         config=QUIET)
    assert torch.equal(recon.cam2world[:2], c2w[:2]) and torch.isfinite(recon.cam2world).all()
    with pytest.raises(ShapeError, match=r"cam2world\[2\] contains NaN"):
        global_align(views_of(scene), preds, cam2world=placeholders, pose_mask=[True, True, True, False, False],
                     config=QUIET)
