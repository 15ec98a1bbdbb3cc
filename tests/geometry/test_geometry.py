import math

import kornia
import pytest
import torch

from pointmap.geometry import (
    axis_angle_to_matrix,
    depth_to_points_cam,
    focal_from_pointmap,
    invert_rigid,
    project,
    random_rotation,
    rotation_angle,
    se3_exp,
    to_matrix,
    transform_points,
    weighted_procrustes,
)


def test_axis_angle_agrees_with_kornia_and_is_smooth_at_zero():
    torch.manual_seed(0)
    aa = torch.randn(50, 3, dtype=torch.float64)
    assert torch.allclose(axis_angle_to_matrix(aa), kornia.geometry.conversions.axis_angle_to_rotation_matrix(aa),
                          atol=1e-10)
    small = torch.tensor([[1e-9, 0, 0]], dtype=torch.float64, requires_grad=True)
    R = axis_angle_to_matrix(small)
    R.sum().backward()
    assert torch.isfinite(small.grad).all()


def test_se3_exp_agrees_with_kornia():
    torch.manual_seed(1)
    xi = torch.randn(20, 6, dtype=torch.float64)
    ref = kornia.geometry.liegroup.Se3.exp(torch.cat([xi[:, :3], xi[:, 3:]], -1)).matrix()
    assert torch.allclose(se3_exp(xi), ref, atol=1e-9)


def test_se3_exp_in_float32_gives_float64s_translation_and_gradients_at_small_angles():
    # (1 - cos t) / t^2 cancelled in float32 from t ~ 1e-4: at 1.5e-4 rad the translation's gradient came out 30x too
    # small and of the wrong sign, which dense alignment and the splat fit's pose refinement run into near a solution
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=torch.float64)
    rho = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    for angle in (0.0, 3e-6, 5e-5, 1.5e-4, 3e-4, 1e-3, 1e-2, 0.049, 0.051, 0.3, 2.0):
        grads, ts = [], []
        for dtype in (torch.float64, torch.float32):
            xi = torch.cat([rho, axis * angle]).to(dtype).requires_grad_()
            T = se3_exp(xi)
            T[:3, 3].sum().backward()
            ts.append(T[:3, 3].detach().double())
            grads.append(xi.grad.double())
        assert torch.allclose(ts[1], ts[0], atol=1e-6), angle
        assert torch.allclose(grads[1], grads[0], atol=1e-5), (angle, grads)


def test_rotation_angle_is_accurate_for_tiny_and_large_angles():
    for ang in (1e-6, 0.3, 3.1):
        R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, ang], dtype=torch.float64))
        assert abs(float(rotation_angle(R)) - ang) < 1e-9


def test_weighted_procrustes_recovers_a_similarity_and_ignores_zero_weight_outliers():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(200, 3, generator=g, dtype=torch.float64)
    R = random_rotation(g)
    dst = 2.5 * src @ R.T + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    w = torch.ones(200, dtype=torch.float64)
    dst[:20] += 10
    w[:20] = 0
    s, R_est, t = weighted_procrustes(src, dst, w)
    assert abs(float(s) - 2.5) < 1e-9 and torch.allclose(R_est, R, atol=1e-9)
    T = to_matrix(s, R_est, t)
    assert torch.allclose(transform_points(T, src[20:]), dst[20:], atol=1e-9)


@pytest.mark.parametrize("with_scale", [True, False])
def test_an_integer_weight_counts_as_that_many_copies_of_the_point_on_noisy_data(with_scale):
    g = torch.Generator().manual_seed(4)
    src = torch.randn(40, 3, generator=g, dtype=torch.float64)
    dst = 1.8 * src @ random_rotation(g).T + torch.randn(3, generator=g, dtype=torch.float64)
    dst += 0.3 * torch.randn(40, 3, generator=g, dtype=torch.float64)  # no exact answer: the weights decide
    k = torch.randint(0, 5, (40,), generator=g)
    weighted = weighted_procrustes(src, dst, k.double(), with_scale=with_scale)
    copies = weighted_procrustes(src.repeat_interleave(k, 0), dst.repeat_interleave(k, 0), with_scale=with_scale)
    unweighted = weighted_procrustes(src, dst, with_scale=with_scale)
    for a, b in zip(weighted, copies):
        assert torch.allclose(a, b, atol=1e-10)
    assert not torch.allclose(weighted[1], unweighted[1], atol=1e-3)  # the weights changed the answer


def test_procrustes_never_returns_a_reflection():
    src = torch.randn(30, 3, dtype=torch.float64)
    dst = src * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # a mirror image
    _, R, _ = weighted_procrustes(src, dst)
    assert abs(float(torch.det(R)) - 1) < 1e-9


def test_unproject_then_project_returns_the_pixel_grid():
    K = torch.tensor([[80.0, 0, 31.5], [0, 90.0, 23.5], [0, 0, 1]])
    depth = 1 + torch.rand(48, 64)
    uv, z = project(depth_to_points_cam(depth, K), K)
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    assert torch.allclose(uv, torch.stack([u, v], -1), atol=1e-3) and torch.allclose(z, depth)


def test_invert_rigid_is_the_matrix_inverse():
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = random_rotation(torch.Generator().manual_seed(3))
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    assert torch.allclose(invert_rigid(T), torch.linalg.inv(T), atol=1e-12)


@pytest.mark.parametrize("f", [50.0, 120.0, 400.0])
def test_weiszfeld_focal_recovers_the_focal_of_an_exact_pointmap_even_with_outliers(f):
    K = torch.tensor([[f, 0, 31.5], [0, f, 23.5], [0, 0, 1]])
    pts = depth_to_points_cam(2 + torch.rand(48, 64), K)[None]
    pts[0, :5, :5] *= torch.tensor([3.0, 0.2, 1.0])  # corrupt 25 pixels
    est = focal_from_pointmap(pts)
    assert math.isclose(float(est), f, rel_tol=1e-3)


def test_rotation_projection_of_a_batch_equals_one_matrix_at_a_time():
    from pointmap.geometry.rotations import project_to_rotation

    g = torch.Generator().manual_seed(0)
    M = torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    M[2] = -M[2] @ M[2].T  # a symmetric negative-definite one: det(U Vh) = -1, the reflection branch
    batched = project_to_rotation(M)
    single = torch.stack([project_to_rotation(m) for m in M])
    assert batched.shape == (5, 3, 3) and torch.allclose(batched, single, atol=1e-12)
    assert torch.allclose(batched @ batched.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-12)
    assert torch.allclose(torch.det(batched), torch.ones(5, dtype=torch.float64), atol=1e-12)


def test_the_focal_of_an_image_without_a_usable_pixel_is_nan_and_bad_arguments_are_refused():
    from pointmap.errors import ShapeError
    from pointmap.geometry import focal_from_pointmap

    pts = torch.rand(2, 8, 8, 3) + 0.5
    pts[1, ..., 2] = -1.0  # every point of image 1 behind its camera
    f = focal_from_pointmap(pts)
    assert math.isfinite(float(f[0])) and math.isnan(float(f[1]))
    with pytest.raises(ShapeError, match="valid expected a bool \\[2, 8, 8\\] tensor"):
        focal_from_pointmap(pts, torch.ones(2, 8, 8))
    with pytest.raises(ShapeError, match="pp expected \\(cx, cy\\) or \\[2, 2\\]"):
        focal_from_pointmap(pts, pp=torch.zeros(3))
    assert torch.allclose(focal_from_pointmap(pts[:1], pp=(3.5, 3.5)), f[:1])  # the centre, given as a tuple


def test_procrustes_refuses_nan_points_and_weights_of_another_shape():
    from pointmap.errors import ShapeError
    from pointmap.geometry.procrustes import weighted_procrustes

    src = torch.rand(10, 3)
    with pytest.raises(ShapeError, match="finite src, dst and weights"):
        weighted_procrustes(src, torch.full((10, 3), float("nan")))
    with pytest.raises(ShapeError, match="weights expected \\[10\\], got \\[9\\]"):
        weighted_procrustes(src, src, torch.ones(9))


def test_the_rotation_and_camera_helpers_refuse_tensors_of_the_wrong_trailing_shape():
    from pointmap.errors import ShapeError
    from pointmap.geometry import (
        axis_angle_to_matrix,
        crop_intrinsics,
        invert_rigid,
        project,
        rotation_angle,
        scale_intrinsics,
        se3_exp,
        to_matrix,
        translation_angle_deg,
    )
    from pointmap.geometry.cameras import is_rigid, similarity_on_cam2world
    from pointmap.geometry.rotations import project_to_rotation

    cases = [(lambda: rotation_angle(torch.eye(4)), r"R expected \[\.\.\., 3, 3\], got \[4, 4\]"),
             (lambda: project_to_rotation(torch.ones(3)), r"M expected \[\.\.\., 3, 3\], got \[3\]"),
             (lambda: translation_angle_deg(torch.ones(2, 4), torch.ones(2, 3)), r"t_pred expected \[\.\.\., 3\]"),
             (lambda: axis_angle_to_matrix(torch.ones(4)), r"axis_angle expected \[\.\.\., 3\], got \[4\]"),
             (lambda: se3_exp(torch.zeros(2, 3)), r"xi expected \[\.\.\., 6\], got \[2, 3\]"),
             (lambda: invert_rigid(torch.eye(3)), r"T expected \[\.\.\., 4, 4\]"),
             (lambda: is_rigid(torch.eye(3)), r"T expected \[\.\.\., 4, 4\]"),
             (lambda: project(torch.ones(5, 2), torch.eye(3)), r"pts_cam expected \[\.\.\., 3\]"),
             (lambda: scale_intrinsics(torch.eye(4), 2.0, 2.0), r"K expected \[\.\.\., 3, 3\]"),
             (lambda: crop_intrinsics([[1.0]], 1, 1), r"K expected an array or tensor"),
             (lambda: similarity_on_cam2world(torch.eye(4), 1.0, torch.eye(4), torch.zeros(3)),
              r"R expected \[3, 3\]"),
             (lambda: to_matrix(torch.ones(()), torch.eye(3), torch.zeros(4)), r"t expected \[\.\.\., 3\]")]
    for call, message in cases:
        with pytest.raises(ShapeError, match=message):
            call()
    with pytest.raises(ValueError, match=r"max_angle expected radians in \[0, pi\]"):
        random_rotation(max_angle=-0.1)
    # the right shapes, batched, still pass
    assert rotation_angle(torch.eye(3).expand(2, 5, 3, 3)).shape == (2, 5)
    assert se3_exp(torch.zeros(7, 6)).shape == (7, 4, 4)


def test_procrustes_without_any_weight_answers_nan_for_that_problem_only():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(3, 20, 3, generator=g, dtype=torch.float64)
    R = random_rotation(g)
    dst = 2.0 * src @ R.T + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    w = torch.ones(3, 20, dtype=torch.float64)
    w[1] = 0.0
    s, R_est, t = weighted_procrustes(src, dst, w)
    assert torch.isnan(s[1]) and torch.isnan(R_est[1]).all() and torch.isnan(t[1]).all()
    for b in (0, 2):
        assert torch.allclose(s[b], torch.tensor(2.0, dtype=torch.float64)) and torch.allclose(R_est[b], R)
    s0, R0, t0 = weighted_procrustes(src[0, :0], dst[0, :0])  # no point at all
    assert torch.isnan(s0) and torch.isnan(R0).all() and torch.isnan(t0).all()
    from pointmap.errors import ShapeError

    with pytest.raises(ShapeError, match=r"src and dst expected \[\.\.\., N, 3\] tensors, got \[3\]"):
        weighted_procrustes(torch.ones(3), torch.ones(3))
    s2, R2, t2 = weighted_procrustes(src.reshape(1, 3, 20, 3), dst.reshape(1, 3, 20, 3), w.reshape(1, 3, 20))
    assert s2.shape == (1, 3) and R2.shape == (1, 3, 3, 3) and torch.isnan(s2[0, 1]) and torch.allclose(s2[0, 0], s[0])


def test_pinhole_intrinsics_are_finite_with_positive_focals_a_0_0_1_bottom_row_and_no_skew_and_a_transposed_K_is_not():
    from pointmap.geometry import is_pinhole_K

    K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    bad = [K.T, K * torch.tensor([[-1.0], [1.0], [1.0]]), K.clone().fill_(float("nan")),
           torch.tensor([[500.0, 0.0, 320.0], [0.1, 480.0, 240.0], [0.0, 0.0, 1.0]]),
           torch.tensor([[500.0, 0.5, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]]),  # a skew every export dropped
           torch.tensor([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 2.0]])]
    got = is_pinhole_K(torch.stack([K, *bad]))
    assert got.tolist() == [True] + [False] * len(bad)
    assert bool(is_pinhole_K(K.double().numpy()))  # arrays too


def test_camera_axes_convert_between_opencv_opengl_and_pytorch3d_keeping_the_camera_where_it_looks():
    import numpy as np

    from pointmap.errors import ShapeError
    from pointmap.geometry.cameras import convert_camera_axes
    from pointmap.geometry.rotations import axis_angle_to_matrix

    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[1, :3, :3] = axis_angle_to_matrix(torch.tensor([0.3, -0.5, 0.2], dtype=torch.float64))
    c2w[1, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    gl = convert_camera_axes(c2w, "opencv", "opengl")
    p3 = convert_camera_axes(c2w, "opencv", "pytorch3d")
    for k in range(2):
        forward, down, right = c2w[k, :3, 2], c2w[k, :3, 1], c2w[k, :3, 0]  # OpenCV: x right, y down, z forward
        assert torch.allclose(gl[k, :3, 2], -forward) and torch.allclose(gl[k, :3, 1], -down)  # GL looks along -z
        assert torch.allclose(gl[k, :3, 0], right) and torch.allclose(gl[k, :3, 3], c2w[k, :3, 3])
        assert torch.allclose(p3[k, :3, 0], -right) and torch.allclose(p3[k, :3, 1], -down)
        assert torch.allclose(p3[k, :3, 2], forward)
        assert torch.linalg.det(gl[k, :3, :3]) > 0 and torch.linalg.det(p3[k, :3, :3]) > 0  # still rotations
    for a in ("opencv", "opengl", "pytorch3d"):
        for b in ("opencv", "opengl", "pytorch3d"):
            back = convert_camera_axes(convert_camera_axes(c2w, "opencv", a), a, b)
            assert torch.allclose(convert_camera_axes(back, b, "opencv"), c2w)
    assert np.allclose(convert_camera_axes(c2w.numpy(), "opencv", "opengl"), gl.numpy())  # NumPy alike
    with pytest.raises(ShapeError, match=r"dst expected one of \['opencv', 'opengl', 'pytorch3d'\], got 'blender'"):
        convert_camera_axes(c2w, "opencv", "blender")
    with pytest.raises(ShapeError, match=r"cam2world expected \[..., 4, 4\], got \(3, 3\)"):
        convert_camera_axes(torch.eye(3))


def test_head_translation_takes_the_head_direction_and_the_points_length():
    from pointmap.errors import ShapeError
    from pointmap.geometry.cameras import head_translation

    t_head = torch.tensor([[0.0, 0.0, 0.3], [0.6, 0.8, 0.0]], dtype=torch.float64)
    t_points = torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, -5.0]], dtype=torch.float64)
    out = head_translation(t_head, t_points)
    assert torch.allclose(out, torch.tensor([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]], dtype=torch.float64))
    assert torch.allclose(head_translation(t_head[0], t_points[0]), out[0])  # unbatched [3]
    # no direction from the head (zero, NaN): the pointmaps' translation, not a zero that puts two centres together
    for none in (torch.zeros(3), torch.full((3,), float("nan"))):
        assert torch.equal(head_translation(none, torch.ones(3)), torch.ones(3))
    with pytest.raises(ShapeError, match=r"\[2, 3\] and \[3\]"):  # one length for every edge: refused
        head_translation(t_head, t_points[0])


@pytest.mark.parametrize("unit", [1e-5, 1e-7])
def test_procrustes_recovers_the_scale_and_translation_whatever_the_units_of_points_and_weights(unit):
    g = torch.Generator().manual_seed(3)
    src = (torch.randn(100, 3, generator=g) + 5) * unit  # float32, tiny scene: variance far below 1e-9
    R = random_rotation(g).float()
    dst = 2.57 * src @ R.T + unit
    s, R_est, t = weighted_procrustes(src, dst)
    assert abs(float(s) - 2.57) < 1e-3 and torch.allclose(R_est, R, atol=1e-3)
    assert torch.allclose(t, torch.full((3,), unit), atol=1e-3 * unit)
    s, _, t = weighted_procrustes(src / unit, dst / unit, torch.full((100,), 1e-13))  # tiny weights
    assert abs(float(s) - 2.57) < 1e-3 and torch.allclose(t, torch.ones(3), atol=1e-3)
    s, _, _ = weighted_procrustes(torch.zeros(10, 3), torch.randn(10, 3, generator=g))  # no spread: s = 0
    assert float(s) == 0.0


def test_procrustes_in_float32_keeps_the_scale_of_a_cloud_far_from_the_origin_and_zero_for_one_place():
    # a cloud 1 across at 1e5 from the origin got s = 0: the "no spread" threshold was 10^4 times the rounding
    g = torch.Generator().manual_seed(4)
    R = random_rotation(g)
    for offset in (1e4, 1e5, 1e6):
        src = torch.randn(500, 3, generator=g, dtype=torch.float64) + offset
        s, R_est, _ = weighted_procrustes(src.float(), (2 * src @ R.T).float())
        assert abs(float(s) - 2) < 2e-2 and torch.allclose(R_est.double(), R, atol=1e-2)
        eps = torch.finfo(torch.float32).eps
        one = (offset * (1 + eps * torch.randn(500, 3, generator=g, dtype=torch.float64))).float()  # rounding only
        assert float(weighted_procrustes(one, torch.randn(500, 3, generator=g))[0]) == 0.0


def test_is_rigid_is_false_for_a_transform_with_a_nan_or_infinite_translation():
    from pointmap.geometry.cameras import is_rigid

    T = torch.eye(4).repeat(3, 1, 1)
    T[1, 0, 3], T[2, 2, 3] = float("nan"), float("inf")
    assert is_rigid(T).tolist() == [True, False, False]
