"""Ground truth checked against the library's own (torch) camera functions, independently of data.geom."""

import numpy as np
import pytest
import torch

from data.cameras import CameraConfig, sample_views
from data.geom import (
    axis_angle,
    correspondences,
    decode_corr,
    encode_corr,
    intrinsics_from_fov,
    look_at,
    unproject,
)
from data.scene import make_scene
from pointmap.errors import ShapeError
from pointmap.geometry import (
    axis_angle_to_matrix,
    depth_to_points_cam,
    invert_rigid,
    project,
    transform_points,
)


def _reproject_checks(d1, K1, T1, d2, K2, T2, corr):
    """Fractions of co-visible pixels whose depth agrees within 0.5 % and whose pixel is within
    0.5 px of the stored correspondence, computed with pointmap.geometry."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    pts1 = depth_to_points_cam(t(d1), t(K1))
    pts2 = transform_points(invert_rigid(t(T2)) @ t(T1), pts1)
    uv, z = project(pts2, t(K2))
    covis = torch.from_numpy(np.isfinite(corr).all(-1))
    assert covis.sum() > 0
    uv_c, z_c = uv[covis], z[covis]
    # view 2's depth at the projected point: nearest pixel, or bilinear inverse depth (planes are exact there)
    h, w = d2.shape
    D2 = t(d2)
    ui = uv_c[:, 0].round().clamp(0, w - 1).long()
    vi = uv_c[:, 1].round().clamp(0, h - 1).long()
    near_ok = ((D2[vi, ui] - z_c).abs() <= 0.005 * z_c)
    u0 = uv_c[:, 0].floor().clamp(0, w - 2).long()
    v0 = uv_c[:, 1].floor().clamp(0, h - 2).long()
    a, b = uv_c[:, 0] - u0, uv_c[:, 1] - v0
    inv = lambda yy, xx: torch.where(D2[yy, xx] > 0, 1 / D2[yy, xx].clamp_min(1e-9), torch.nan)  # noqa: E731
    ib = (inv(v0, u0) * (1 - a) * (1 - b) + inv(v0, u0 + 1) * a * (1 - b) + inv(v0 + 1, u0) * (1 - a) * b
          + inv(v0 + 1, u0 + 1) * a * b)
    bil_ok = (ib * z_c - 1).abs() <= 0.005
    depth_ok = (near_ok | bil_ok).double().mean().item()
    px_ok = ((uv_c - t(corr)[covis]).norm(dim=-1) <= 0.5).double().mean().item()
    return depth_ok, px_ok, int(covis.sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reprojected_view1_depth_agrees_with_view2_and_stored_correspondences(renderer, seed):
    rng = np.random.default_rng(100 + seed)
    scene = make_scene(rng, kind=["room", "cluster", "courtyard"][seed])
    vs = sample_views(rng, scene, renderer, 2, 96, CameraConfig(overlap=(0.2, 0.95)))
    a, b = vs.views
    stored = decode_corr(encode_corr(vs.corr(0, 1)))  # what a shard holds
    depth_ok, px_ok, n = _reproject_checks(a.depth, a.K, a.cam2world, b.depth, b.K, b.cam2world, stored)
    assert n > 0.15 * (a.depth > 0).sum()
    assert depth_ok >= 0.98 and px_ok >= 0.98


def test_two_views_of_a_plane_are_co_visible_wherever_they_overlap(renderer):
    from data.scene import plane_scene
    scene = plane_scene(4.0)
    K = intrinsics_from_fov(64, 48, 60.0)
    T1 = np.eye(4)
    T2 = look_at([0.6, 0.1, 0.0], [0.2, 0.0, 4.0])
    _, d1 = renderer.render(scene, K, T1, 64, 48)
    _, d2 = renderer.render(scene, K, T2, 64, 48)
    corr, covis = correspondences(d1, K, T1, d2, K, T2)
    # analytic: every view-1 pixel whose plane point projects inside view 2 is co-visible
    pts = unproject(d1, K)
    p2 = pts @ np.linalg.inv(T2)[:3, :3].T + np.linalg.inv(T2)[:3, 3]
    u = K[0, 0] * p2[..., 0] / p2[..., 2] + K[0, 2]
    v = K[1, 1] * p2[..., 1] / p2[..., 2] + K[1, 2]
    inside = (u > -0.5) & (u < 63.5) & (v > -0.5) & (v < 47.5)
    # pixels within half a pixel of view 2's border may lack the four depth neighbours: allow those
    strict = (u > 0.5) & (u < 62.5) & (v > 0.5) & (v < 46.5)
    assert covis[strict].all() and not covis[~inside].any()
    assert np.allclose(corr[covis][:, 0], u[covis], atol=1e-3)


def test_numpy_unprojection_matches_the_library():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.5, 5, (12, 16)).astype(np.float32)
    K = intrinsics_from_fov(16, 12, 70, cx_offset=0.3)
    ours = unproject(d, K)
    lib = depth_to_points_cam(torch.from_numpy(d).double(), torch.from_numpy(K)).numpy()
    assert np.allclose(ours, lib, atol=1e-9)


def test_numpy_axis_angle_rotation_matches_the_library():
    rng = np.random.default_rng(1)
    for _ in range(5):
        axis, angle = rng.normal(size=3), rng.uniform(-np.pi, np.pi)
        lib = axis_angle_to_matrix(torch.from_numpy(axis / np.linalg.norm(axis) * angle)).numpy()
        assert np.allclose(axis_angle(axis, angle), lib, atol=1e-12)
    with pytest.raises(ShapeError, match="non-zero axis"):
        axis_angle([0.0, 0.0, 0.0], 1.0)


def test_look_at_builds_an_opencv_camera_facing_the_target():
    T = look_at([0, 0, 1], [5, 0, 1])
    assert np.allclose(T[:3, 2], [1, 0, 0])      # z forward
    assert np.allclose(T[:3, 1], [0, 0, -1])     # y down (world z is up)
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3)) and np.isclose(np.linalg.det(T[:3, :3]), 1)


def test_correspondence_encoding_round_trips_within_a_128th_of_a_pixel():
    rng = np.random.default_rng(0)
    c = rng.uniform(-0.5, 511.4, (8, 9, 2)).astype(np.float32)
    c[2, 3] = np.nan
    back = decode_corr(encode_corr(c))
    assert np.isnan(back[2, 3]).all()
    ok = np.isfinite(c).all(-1)
    assert np.abs(back[ok] - c[ok]).max() <= 1 / 128 + 1e-5


def test_geometry_helpers_reject_bad_shapes_dtypes_and_fields_of_view():
    with pytest.raises(ShapeError, match=r"corr expected \[H, W, 2\], got \[4, 4, 3\]"):
        encode_corr(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ShapeError, match=r"encoded corr expected uint16 \[H, W, 2\], got uint16 \[4, 4, 3\]"):
        decode_corr(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ShapeError, match=r"encoded corr expected uint16 \[H, W, 2\], got float32 \[4, 4, 2\]"):
        decode_corr(np.zeros((4, 4, 2), np.float32))
    with pytest.raises(ShapeError, match=r"unproject expected depth \[H, W\] and K \[3, 3\], got \(4, 4, 1\)"):
        unproject(np.zeros((4, 4, 1)), np.eye(3))
    with pytest.raises(ShapeError, match=r"fov_deg expected in \(0, 180\), got 190"):
        intrinsics_from_fov(10, 10, 190)
