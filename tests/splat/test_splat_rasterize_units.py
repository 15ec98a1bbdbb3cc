"""Unit tests from a mutation review of the splatting rasterizer (session 93), of the contracts the image and gradient
comparisons in test_splat_rasterize.py do not reach: the near plane and the frustum clamp with fx != fy, radii,
images not a multiple of the tile, equal depths, more tiles than int16 ids hold, alphas at the 0.999 clamp (image
and gradients), termination, normalised depth and means2d, the gsplat dispatch and the input checks. Everything is
checked against the float64 reference in tests/splat/reference.py where an image or a gradient is compared. Last,
tests of the bugs it found: inputs ``rasterize`` took without a word and then drew wrong (opacities above 1 lost the
rim of their footprint to tile culling; a NaN near plane or low-pass drew nothing) or crashed on deep inside (a
float tile or chunk)."""

import importlib
import math
import warnings

import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import rasterize
from pointmap.splat.rasterize import project_gaussians, quat_to_rotmat
from tests.splat.reference import reference_render

rz = importlib.import_module("pointmap.splat.rasterize")
F64 = torch.float64


def _camera(W, H, f=None, fy=None, dtype=F64):
    f = 0.9 * W if f is None else f
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f if fy is None else fy, (H - 1) / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def _gaussians(n, seed=0, z=4.0, dtype=F64, op=(0.3, 0.9), scale=(0.05, 0.2)):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.8, 0.6, 0.3], dtype=dtype)
    means[:, 2] += z
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    opac = torch.rand(n, generator=g, dtype=dtype) * (op[1] - op[0]) + op[0]
    cols = torch.rand(n, 3, generator=g, dtype=dtype)
    return [means, quats, scales, opac, cols]


def _one(z=2.0, scale=0.1, opacity=0.9, dtype=F64):
    """One round Gaussian on the optical axis."""
    return [torch.tensor([[0.0, 0.0, z]], dtype=dtype), torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
            torch.full((1, 3), scale, dtype=dtype), torch.tensor([opacity], dtype=dtype),
            torch.tensor([[0.2, 0.5, 0.9]], dtype=dtype)]


def _grads(render, inputs, seed=7):
    """Gradients of a fixed random linear loss of (image, alpha, accumulated depth) for every input."""
    ins = [t.clone().requires_grad_(True) for t in inputs]
    img, alpha, dep = render(ins)
    g = torch.Generator().manual_seed(seed)
    loss = ((img * torch.randn(img.shape, generator=g, dtype=img.dtype)).sum()
            + (alpha * torch.randn(alpha.shape, generator=g, dtype=alpha.dtype)).sum()
            + 0.1 * (dep * torch.randn(dep.shape, generator=g, dtype=dep.dtype)).sum())
    loss.backward()
    return [t.grad for t in ins]


def _fast(W, H, **kw):
    def render(ins):
        out = rasterize(*ins, W, H, **kw)
        return out.image, out.alpha, out.depth_acc
    return render


def _assert_matches_reference_gradients(inputs, W, H, tol=1e-9, **kw):
    got = _grads(_fast(W, H, **kw), inputs)
    want = _grads(lambda ins: reference_render(*ins, W, H), inputs)
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors", "world2cam", "K"], got, want):
        assert bool(torch.isfinite(a).all()), name
        assert float((a - b).norm()) <= tol * float(b.norm()) + 1e-15, name


# -- projection -------------------------------------------------------------------------------------------------
def test_a_zero_quaternion_is_the_identity_rotation_and_the_norm_of_a_quaternion_does_not_matter():
    q = torch.tensor([[0.0, 0, 0, 0], [0.3, -0.2, 0.5, 0.1]], dtype=F64)
    R = quat_to_rotmat(q)
    assert torch.equal(R[0], torch.eye(3, dtype=F64))
    assert torch.allclose(quat_to_rotmat(q[1:] * 7.5), R[1:], atol=1e-15)
    W, H = 12, 10
    means, _, scales, opac, cols = _one()
    img = rasterize(means, q[:1], scales, opac, cols, *_camera(W, H), W, H).image
    assert bool(torch.isfinite(img).all()) and float(img.max()) > 0.1


def test_a_gaussian_on_the_near_plane_is_not_drawn_and_one_just_behind_it_is():
    W, H = 12, 10
    args = _one(z=0.5, scale=0.01)
    cam = _camera(W, H, f=4.0)
    assert float(rasterize(*args, *cam, W, H, near=0.5).alpha.max()) == 0.0   # z == near: culled, as the reference
    _, ref_alpha, _ = reference_render(*args, *cam, W, H, near=0.5)
    assert float(ref_alpha.max()) == 0.0
    drawn = rasterize(*args, *cam, W, H, near=0.4)
    assert float(drawn.alpha.max()) > 0.1 and int(drawn.radii[0]) > 0


def test_gradients_are_finite_and_zero_for_gaussians_behind_the_camera():
    W, H = 16, 12
    inputs = _gaussians(6, seed=1) + list(_camera(W, H))
    inputs[0][:2, 2] = -3.0   # two Gaussians behind the camera
    grads = _grads(_fast(W, H), inputs)
    for g in grads:
        assert bool(torch.isfinite(g).all())
    assert float(grads[0][:2].abs().max()) == 0.0 and float(grads[4][:2].abs().max()) == 0.0
    _assert_matches_reference_gradients(inputs, W, H)


def test_the_vertical_jacobian_clamp_uses_fy_when_fx_and_fy_differ():
    W, H, fx, fy, z = 32, 24, 30.0, 45.0, 2.0
    K = torch.tensor([[fx, 0, 10.0], [0, fy, 14.0], [0, 0, 1]], dtype=F64)
    means = torch.tensor([[0.0, 3.0, z], [0.0, -3.0, z]], dtype=F64)   # |y/z| 1.5, beyond both limits
    q = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64)
    s = torch.tensor([[0.1, 0.1, 1.0]] * 2, dtype=F64)
    _, _, _, ok, (_, _, c, _) = project_gaussians(means, q, s, torch.eye(4, dtype=F64), K, W, H)
    lim = torch.tensor([1.3 * (H - 0.5 - 14.0) / fy, -1.3 * (14.0 + 0.5) / fy], dtype=F64)
    assert bool(ok.all())
    assert torch.allclose(c - 0.3, (fy / z * 0.1) ** 2 + (fy * lim / z) ** 2, rtol=1e-12)


def test_a_gaussian_of_zero_size_without_the_low_pass_is_dropped_rather_than_painting_nan():
    W, H = 12, 10
    means, quats, _, opac, cols = _one()
    out = rasterize(means, quats, torch.zeros(1, 3, dtype=F64), opac, cols, *_camera(W, H), W, H, eps2d=0.0)
    assert int(out.radii[0]) == 0 and bool(torch.isfinite(out.image).all()) and float(out.alpha.max()) == 0.0


def test_eps2d_is_the_low_pass_the_reference_adds():
    W, H = 16, 12
    args = _gaussians(8, seed=2) + list(_camera(W, H))
    ref, ref_alpha, _ = reference_render(*args, W, H, eps2d=2.0)
    out = rasterize(*args, W, H, eps2d=2.0)
    assert (out.image - ref).abs().max() < 1e-12 and (out.alpha - ref_alpha).abs().max() < 1e-12


# -- radii and binning ------------------------------------------------------------------------------------------
def test_radii_are_int32_and_follow_the_bound_with_a_floor_of_0_1_on_the_discriminant():
    """lambda_max = (a + c) / 2 + sqrt(max(0.1, ((a + c) / 2)^2 - det)); r = ceil(sqrt(2 ln(255 o) lambda_max))."""
    W, H = 40, 30
    for scale, opacity in [(0.1, 0.5), (0.25, 0.9), (0.02, 0.05)]:   # the first two lose 1 px without the floor
        args = _one(scale=scale, opacity=opacity)
        out = rasterize(*args, *_camera(W, H), W, H)
        _, _, _, _, (a, b, c, det) = project_gaussians(*args[:3], *_camera(W, H), W, H)
        mid = (a + c) / 2
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        want = math.ceil(math.sqrt(2 * math.log(255 * opacity) * float(lam)))
        assert out.radii.dtype == torch.int32 and int(out.radii[0]) == want, (scale, opacity)


def test_an_image_whose_size_is_not_a_multiple_of_the_tile_matches_the_reference_up_to_its_last_row_and_column():
    W, H = 19, 13
    args = _gaussians(30, seed=3, z=3.0) + list(_camera(W, H))
    args[0][:4, :2] = torch.tensor([[0.6, 0.45], [-0.6, -0.45], [0.6, -0.45], [-0.6, 0.45]], dtype=F64) * 3.0
    ref, ref_alpha, _ = reference_render(*args, W, H)
    for tile in (4, 8):
        out = rasterize(*args, W, H, tile=tile)
        assert out.image.shape == (H, W, 3) and out.alpha.shape == (H, W)
        assert (out.image - ref).abs().max() < 1e-12 and (out.alpha - ref_alpha).abs().max() < 1e-12
        assert float(ref_alpha[-1].max()) > 0 and float(ref_alpha[:, -1].max()) > 0


def test_gaussians_at_the_same_depth_composite_in_index_order():
    W, H = 12, 10
    means, quats, scales, opac, cols = _gaussians(200, seed=4, scale=(0.2, 0.4))
    means[:, 2] = 4.0
    means[:, :2] *= 0.2
    args = [means, quats, scales, opac, cols, *_camera(W, H)]
    ref, _, _ = reference_render(*args, W, H)
    assert (rasterize(*args, W, H).image - ref).abs().max() < 1e-12


def test_more_tiles_than_int16_ids_hold_render_as_the_reference():
    W, H = 184, 182   # 33,488 tiles of 1 pixel
    args = _gaussians(5, seed=5, scale=(0.1, 0.3)) + list(_camera(W, H))
    args[0][:, 2] = 4.0
    args[0][:, :2] = torch.tensor([[-1.9, -1.9], [1.9, 1.9], [1.9, -1.9], [-1.9, 1.9], [0.0, 0.0]], dtype=F64)
    ref, _, _ = reference_render(*args, W, H)
    out = rasterize(*args, W, H, tile=1)
    assert (out.image - ref).abs().max() < 1e-12
    assert float(ref[-20:, -20:].max()) > 0.05   # the last tiles (ids >= 2**15) are drawn


# -- compositing ------------------------------------------------------------------------------------------------
def test_alpha_is_clamped_at_0_999_and_clamped_alphas_pass_no_gradient():
    W, H = 9, 7
    args = _one(scale=0.2, opacity=1.0) + list(_camera(W, H, f=8.0))
    out = rasterize(*args, W, H)
    assert float(out.alpha[3, 4]) == pytest.approx(0.999, abs=1e-12)   # the centre pixel, exp(0) = 1
    ref, ref_alpha, _ = reference_render(*args, W, H)
    assert (out.image - ref).abs().max() < 1e-12 and (out.alpha - ref_alpha).abs().max() < 1e-12
    _assert_matches_reference_gradients(args, W, H)
    op = torch.tensor([0.995, 0.9], dtype=F64)   # two overlapping: alpha 0.995 is kept as it is (not clamped)
    two = [torch.tensor([[0.0, 0, 2.0], [0.02, 0, 2.5]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64),
           torch.full((2, 3), 0.2, dtype=F64), op, torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=F64)]
    ref, ref_alpha, _ = reference_render(*two, *_camera(W, H, f=8.0), W, H)
    assert (rasterize(*two, *_camera(W, H, f=8.0), W, H).alpha - ref_alpha).abs().max() < 1e-12
    _assert_matches_reference_gradients(two + list(_camera(W, H, f=8.0)), W, H)


def test_after_a_pixel_terminates_nothing_more_is_drawn_and_the_gradients_match_the_reference():
    """Six opaque layers: the fourth takes T below 1e-4 at the centre, so it and those behind are not composited."""
    W, H = 9, 7
    n = 6
    means = torch.tensor([[0.01 * k, -0.01 * k, 2.0 + 0.3 * k] for k in range(n)], dtype=F64)
    args = [means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=F64), torch.full((n, 3), 0.25, dtype=F64),
            torch.full((n,), 0.95, dtype=F64), torch.rand(n, 3, generator=torch.Generator().manual_seed(0),
                                                           dtype=F64), *_camera(W, H, f=8.0)]
    ref, ref_alpha, ref_dep = reference_render(*args, W, H)
    out = rasterize(*args, W, H)
    assert float(out.alpha[3, 4]) == float(ref_alpha[3, 4]) and float(1 - ref_alpha[3, 4]) > 1e-4
    assert (out.image - ref).abs().max() < 1e-12 and (out.depth_acc - ref_dep).abs().max() < 1e-12
    _assert_matches_reference_gradients(args, W, H)
    for chunk in (1, 2, 4):   # termination across the chunks of a tile
        small = rasterize(*args, W, H, chunk=chunk)
        assert (small.image - ref).abs().max() < 1e-12, chunk
        _assert_matches_reference_gradients(args, W, H, chunk=chunk)


def test_gradients_match_the_reference_when_a_tiles_list_spans_several_chunks():
    W, H = 12, 10
    args = _gaussians(40, seed=6, scale=(0.1, 0.3)) + list(_camera(W, H))
    args[0][:, :2] *= 0.3
    for chunk in (3, 7):
        _assert_matches_reference_gradients(args, W, H, chunk=chunk)


def test_an_opacity_of_zero_gets_a_zero_gradient_not_nan():
    W, H = 12, 10
    args = _gaussians(4, seed=7) + list(_camera(W, H))
    args[3][1] = 0.0
    grads = _grads(_fast(W, H), args)
    assert all(bool(torch.isfinite(g).all()) for g in grads) and float(grads[3][1]) == 0.0


# -- outputs ----------------------------------------------------------------------------------------------------
def test_depth_is_the_accumulated_depth_over_alpha_and_zero_where_nothing_is_drawn():
    W, H = 16, 12
    out = rasterize(*_one(z=2.5, scale=0.1, opacity=0.8), *_camera(W, H), W, H)
    drawn = out.alpha > 0
    assert bool(drawn.any()) and not bool(drawn.all())
    assert torch.allclose(out.depth[drawn], torch.full_like(out.depth[drawn], 2.5), rtol=1e-12)
    assert float(out.depth[~drawn].abs().max()) == 0.0
    assert torch.allclose(out.depth_acc, out.depth * out.alpha, atol=1e-12)


def test_means2d_are_the_projected_centres_and_receive_gradients():
    W, H = 16, 12
    args = [t.requires_grad_(True) for t in _gaussians(5, seed=8)]
    w2c, K = _camera(W, H)
    out = rasterize(*args, w2c, K, W, H)
    m = args[0].detach()
    want = torch.stack([K[0, 0] * m[:, 0] / m[:, 2] + K[0, 2], K[1, 1] * m[:, 1] / m[:, 2] + K[1, 2]], -1)
    assert torch.allclose(out.means2d, want, atol=1e-12)
    assert out.means2d.requires_grad
    out.means2d.retain_grad()
    out.image.sum().backward()
    assert out.means2d.grad is not None and float(out.means2d.grad.abs().max()) > 0


# -- gsplat dispatch --------------------------------------------------------------------------------------------
def test_gsplat_counts_as_available_only_for_tensors_on_cuda(monkeypatch):
    monkeypatch.setattr(rz, "_GSPLAT_STATE", {"ok": True})
    assert not rz._gsplat_available("cpu") and not rz._gsplat_available(torch.device("cpu"))
    assert rz._gsplat_available("cuda")


def test_auto_renders_with_gsplat_when_it_is_available_and_torch_never_does(monkeypatch):
    W, H = 12, 10
    args = _one(dtype=torch.float32) + list(_camera(W, H, dtype=torch.float32))
    calls = []
    monkeypatch.setattr(rz, "_gsplat_available", lambda device: True)
    monkeypatch.setattr(rz, "_rasterize_gsplat", lambda *a: calls.append(a) or "gsplat")
    assert rasterize(*args, W, H, backend="auto") == "gsplat" and len(calls) == 1
    assert rasterize(*args, W, H, backend="gsplat") == "gsplat" and len(calls) == 2
    assert isinstance(rasterize(*args, W, H), rz.RenderOutput) and len(calls) == 2


def test_the_fallback_warns_once_for_an_explicit_gsplat_request_and_never_for_auto(monkeypatch):
    W, H = 12, 10
    args = _one(dtype=torch.float32) + list(_camera(W, H, dtype=torch.float32))
    monkeypatch.setattr(rz, "_GSPLAT_STATE", {"ok": False, "err": "CUDA is not available"})
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        rasterize(*args, W, H, backend="auto")
        assert not rec
        for _ in range(3):
            rasterize(*args, W, H, backend="gsplat")
    assert len(rec) == 1 and "gsplat backend unavailable (CUDA is not available)" in str(rec[0].message)


# -- input checks -----------------------------------------------------------------------------------------------
def _valid(n=3, dtype=torch.float32):
    return _gaussians(n, dtype=dtype) + list(_camera(12, 10, dtype=dtype))


@pytest.mark.parametrize("width,height", [(12, 0), (12, -3), (12, 10.0), (12, True)])
def test_a_height_that_is_not_a_positive_int_is_refused(width, height):
    with pytest.raises(ShapeError, match=f"width and height expected positive ints, got 12 x {height!r}"):
        rasterize(*_valid(), width, height)


@pytest.mark.parametrize("k,bad,message", [
    (1, torch.ones(3, 3), r"quats expected \[3, 4\], got \[3, 3\]"),
    (2, torch.ones(3, 2), r"scales expected \[3, 3\], got \[3, 2\]"),
    (2, torch.ones(3, 1), r"scales expected \[3, 3\], got \[3, 1\]"),
    (4, torch.ones(4, 3), r"colors expected \[N, D\] with N = 3, got \[4, 3\]"),
    (4, torch.ones(3), r"colors expected \[N, D\] with N = 3, got \[3\]"),
    (6, torch.eye(3).expand(2, 3, 3), r"K expected \[3, 3\], got \[2, 3, 3\]"),
])
def test_gaussians_and_intrinsics_of_the_wrong_shape_are_refused_naming_them(k, bad, message):
    args = _valid()
    args[k] = bad
    with pytest.raises(ShapeError, match=message):
        rasterize(*args, 12, 10)


@pytest.mark.parametrize("background", [torch.ones(1), torch.ones(2), torch.ones(1, 3)])
def test_a_background_that_is_not_one_value_per_channel_is_refused(background):
    with pytest.raises(ShapeError, match=r"background expected \[3\], got"):
        rasterize(*_valid(), 12, 10, background)


@pytest.mark.parametrize("tile,chunk", [(0, 32), (4, 0), (-1, 32)])
def test_a_tile_or_chunk_below_one_is_refused(tile, chunk):
    with pytest.raises(ShapeError, match="tile and chunk"):
        rasterize(*_valid(), 12, 10, tile=tile, chunk=chunk)


def test_a_float64_camera_renders_float32_means_in_float32_like_a_float32_camera():
    args = _valid()
    want = rasterize(*args, 12, 10).image
    for k in (5, 6):
        mixed = list(args)
        mixed[k] = mixed[k].double()
        got = rasterize(*mixed, 12, 10).image
        assert got.dtype == torch.float32 and (got - want).abs().max() < 1e-6


def test_integer_means_from_a_list_render_in_the_default_float_dtype():
    args = _valid(1)
    args[0] = torch.tensor([[0.0, 0.0, 4.0]])
    want = rasterize(*args, 12, 10)
    got = rasterize([[0, 0, 4]], *args[1:], 12, 10)
    assert got.image.dtype == torch.get_default_dtype() and torch.equal(got.image, want.image)


def test_a_ragged_list_is_refused_naming_the_argument():
    args = _valid(2)
    with pytest.raises(ShapeError, match="scales expected a tensor or an array of numbers, got list"):
        rasterize(args[0], args[1], [[0.1, 0.1, 0.1], [0.1, 0.1]], *args[3:], 12, 10)


# -- the bugs the review found ------------------------------------------------------------------------------------
def _one_view(opacity=0.9, W=12, H=10):
    """One round Gaussian on the optical axis and the camera looking at it: rasterize's positional arguments."""
    return [*_one(scale=0.2, opacity=opacity), *_camera(W, H), W, H]


@pytest.mark.parametrize("opacity", [20.0, 1.5, -0.5])
def test_opacities_outside_0_1_are_refused_naming_them(opacity):
    """The radius took min(opacity, 1) while the alpha takes the opacity itself: at opacity 20 the tiles beyond
    sqrt(2 ln 255 lambda) were culled though alpha there is above 1/255 (up to 0.05 of the image lost)."""
    with pytest.raises(ShapeError, match=rf"opacities expected values in \[0, 1\], got 1 outside \(first {opacity}\)"):
        rasterize(*_one_view(opacity=opacity))


@pytest.mark.parametrize("opacity", [0.0, 1.0])
def test_opacities_of_exactly_0_and_1_are_taken(opacity):
    out = rasterize(*_one_view(opacity=opacity))
    assert bool(torch.isfinite(out.image).all())


@pytest.mark.parametrize("tile,chunk", [(4.0, 32), (2.5, 32), (4, 32.0), (True, 32), (4, True)])
def test_a_tile_or_chunk_that_is_not_an_int_is_refused(tile, chunk):
    with pytest.raises(ShapeError, match=rf"tile and chunk expected ints >= 1, got {tile!r}, {chunk!r}"):
        rasterize(*_one_view(), tile=tile, chunk=chunk)


@pytest.mark.parametrize("near,eps2d", [(float("nan"), 0.3), (-1.0, 0.3), (0.01, float("nan")), (0.01, -1.0),
                                        (0.01, True), (float("inf"), 0.3)])
def test_a_near_plane_or_low_pass_that_is_not_a_finite_number_at_least_zero_is_refused(near, eps2d):
    """A NaN near plane or eps2d drew an empty image without a word; a negative near plane drew Gaussians behind the
    camera, mirrored."""
    with pytest.raises(ShapeError, match=rf"near and eps2d expected finite numbers >= 0, got {near!r}, {eps2d!r}"):
        rasterize(*_one_view(), near=near, eps2d=eps2d)


def test_a_numpy_tile_chunk_near_and_eps2d_are_taken():
    np = pytest.importorskip("numpy")
    a = rasterize(*_one_view())
    b = rasterize(*_one_view(), tile=np.int64(4), chunk=np.int32(32), near=np.float64(0.01), eps2d=np.float32(0.3))
    assert torch.allclose(a.image, b.image, atol=1e-7)
