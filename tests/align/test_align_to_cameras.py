"""align_to_cameras / Reconstruction.transformed: moving a reconstruction into reference cameras' world."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "io"))
from recon_factory import make_recon  # noqa: E402

import pointmap as pm  # noqa: E402
from pointmap.geometry.rotations import axis_angle_to_matrix  # noqa: E402

S, R, T = 2.5, axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)), torch.tensor([1.0, -2, 0.5])


def _reference(recon):
    """The recon's cameras moved by a known similarity: what a metric ground truth would be."""
    ref = recon.cam2world.double().clone()
    ref[:, :3, :3] = R @ ref[:, :3, :3]
    ref[:, :3, 3] = S * ref[:, :3, 3] @ R.T + T.double()
    return ref


def test_the_similarity_to_reference_cameras_is_recovered_and_moves_points_and_depths_with_it():
    recon = make_recon(n=4)
    moved, rep = pm.align_to_cameras(recon, _reference(recon))
    assert rep["scale"] == pytest.approx(S, rel=1e-6) and rep["scale_fixed"] and rep["cameras"] == 4
    assert rep["ate_rmse"] < 1e-5 and rep["rot_err_deg_max"] < 1e-3
    assert torch.allclose(moved.depth_z, recon.depth_z * S, rtol=1e-5)
    valid = recon.depth_z > 0
    expected = S * recon.pts_world.double() @ R.T + T.double()  # every world point moved by the similarity
    assert torch.allclose(moved.pts_world.double()[valid], expected[valid], atol=1e-4)
    assert torch.equal(moved.K, recon.K) and moved.info["transformed"]["scale"] == pytest.approx(S, rel=1e-6)


def test_one_reference_camera_fixes_the_frame_but_not_the_scale_and_with_scale_false_keeps_it():
    recon = make_recon(n=3)
    ref = _reference(recon)
    moved, rep = pm.align_to_cameras(recon, ref, mask=[False, True, False])
    assert not rep["scale_fixed"] and rep["scale"] == 1.0
    assert torch.allclose(moved.cam2world[1].double(), ref[1], atol=1e-5)  # that camera lands exactly
    moved, rep = pm.align_to_cameras(recon, ref, with_scale=False)
    assert rep["scale"] == 1.0 and rep["rot_err_deg_max"] < 1e-3 and rep["ate_rmse"] > 0.1  # the scale is off by 2.5


def test_bad_references_and_similarities_are_refused():
    recon = make_recon(n=3)
    with pytest.raises(pm.ShapeError, match=r"cam2world expected \[3, 4, 4\]"):
        pm.align_to_cameras(recon, torch.eye(4).repeat(2, 1, 1))
    with pytest.raises(pm.ShapeError, match="at least one True"):
        pm.align_to_cameras(recon, _reference(recon), mask=np.zeros(3, bool))
    with pytest.raises(pm.ShapeError, match="mask expected bools"):  # 0.5 was cast to True
        pm.align_to_cameras(recon, _reference(recon), mask=np.full(3, 0.5))
    scaled = _reference(recon).clone()
    scaled[1, :3, :3] *= 2  # not a rotation: the similarity fitted to it would be meaningless
    with pytest.raises(pm.ShapeError, match=r"cam2world expected rigid reference poses .* got others at \[1\]"):
        pm.align_to_cameras(recon, scaled)
    with pytest.raises(pm.ShapeError, match="R to be a rotation"):
        recon.transformed(1.0, 2 * torch.eye(3), torch.zeros(3))
    with pytest.raises(pm.ShapeError, match="scale > 0"):
        recon.transformed(-1.0, torch.eye(3), torch.zeros(3))


def test_two_moves_are_recorded_as_one_similarity_from_the_original_world():
    recon = make_recon(n=3)
    R2 = axis_angle_to_matrix(torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64))
    twice = recon.transformed(S, R, T).transformed(0.5, R2, torch.tensor([0.0, 1.0, 0.0]))
    rec = twice.info["transformed"]
    once = recon.transformed(rec["scale"], torch.tensor(rec["R"]), torch.tensor(rec["t"]))
    assert torch.allclose(once.cam2world, twice.cam2world, atol=1e-5) and rec["scale"] == pytest.approx(1.25)


def test_reference_rows_the_mask_leaves_out_may_be_nan_placeholders():
    recon = make_recon(n=4)
    ref = _reference(recon)
    ref[3] = float("nan")  # a camera the reference does not have
    moved, rep = pm.align_to_cameras(recon, ref, mask=[True, True, True, False])
    assert rep["scale"] == pytest.approx(S, rel=1e-6) and rep["cameras"] == 3
    with pytest.raises(pm.ShapeError, match="finite where used"):
        pm.align_to_cameras(recon, ref)
