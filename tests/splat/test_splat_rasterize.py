import math
import warnings

import pytest
import torch

from pointmap.errors import ConventionError, ShapeError
from pointmap.splat import rasterize
from tests.splat.reference import reference_render


def _scene(n, W, H, seed=0, dtype=torch.float64, op_lo=0.05, op_hi=0.95, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 0.8, 0.6], dtype=dtype) * spread
             + torch.tensor([0.0, 0.0, 4.0], dtype=dtype))
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.02
    opac = torch.rand(n, generator=g, dtype=dtype) * (op_hi - op_lo) + op_lo
    cols = torch.rand(n, 3, generator=g, dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = torch.tensor([[0.995, -0.0998, 0.0], [0.0998, 0.995, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    w2c[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=dtype)
    f = 0.9 * W
    K = torch.tensor([[f, 0, W / 2 - 0.3], [0, f * 1.05, H / 2 - 0.6], [0, 0, 1]], dtype=dtype)
    return [means, quats, scales, opac, cols, w2c, K]


def test_image_matches_float64_reference():
    W, H = 48, 36
    args = _scene(400, W, H)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    ref_img, ref_alpha, ref_dep = reference_render(*args, W, H, bg)
    out = rasterize(*[a.float() for a in args], W, H, bg.float())
    assert out.image.shape == (H, W, 3) and out.alpha.shape == (H, W) and out.depth.shape == (H, W)
    assert (out.image.double() - ref_img).abs().max() < 1e-5
    assert (out.alpha.double() - ref_alpha).abs().max() < 1e-5
    # accumulated depth is ~alpha * 4: compare relative to depth
    assert (out.depth_acc.double() - ref_dep).abs().max() < 1e-5 * 5
    # the scene is dense enough that some pixels terminate (T < 1e-4) and some are empty
    assert float(ref_alpha.max()) > 0.999 and float(ref_alpha.min()) < 0.5
    assert out.radii.shape == (400,) and int((out.radii > 0).sum()) > 100


def test_a_tiny_gaussian_far_off_screen_at_index_0_does_not_paint_the_padding_slots():
    W, H = 32, 24  # the tile lists are padded with Gaussian 0's parameters, blanked whatever they are
    means, quats, scales, opac, cols, w2c, K = _scene(40, W, H)
    means[0] = torch.tensor([150.0, 110.0, 4.0], dtype=means.dtype)  # projects ~1000 px off the image
    scales[0] = 0.001
    ref_img, ref_alpha, _ = reference_render(means, quats, scales, opac, cols, w2c, K, W, H)
    out = rasterize(*[a.float() for a in (means, quats, scales, opac, cols, w2c, K)], W, H)
    assert (out.image.double() - ref_img).abs().max() < 1e-5
    assert (out.alpha.double() - ref_alpha).abs().max() < 1e-5


def test_float64_fast_path_is_exact():
    W, H = 32, 24
    args = _scene(120, W, H, seed=3)
    ref_img, ref_alpha, _ = reference_render(*args, W, H)
    out = rasterize(*args, W, H)
    assert (out.image - ref_img).abs().max() < 1e-12
    assert (out.alpha - ref_alpha).abs().max() < 1e-12


def _grads(fn, base, cast):
    ins = [t.clone().to(cast).requires_grad_(True) for t in base]
    img, alpha, dep = fn(ins)
    g = torch.Generator().manual_seed(7)
    H, W = img.shape[:2]
    wi = torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    wa = torch.randn(H, W, generator=g, dtype=torch.float64)
    wd = torch.randn(H, W, generator=g, dtype=torch.float64) * 0.1
    loss = (img.double() * wi).sum() + (alpha.double() * wa).sum() + (dep.double() * wd).sum()
    loss.backward()
    return [t.grad.double() for t in ins]


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-4), (torch.float64, 1e-10)])
def test_gradients_match_float64_reference(dtype, tol):
    W, H = 36, 24
    base = _scene(150, W, H, seed=1)
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)

    def fast(ins):
        o = rasterize(*ins, W, H, bg.to(dtype))
        return o.image, o.alpha, o.depth_acc

    gf = _grads(fast, base, dtype)
    gr = _grads(lambda ins: reference_render(*ins, W, H, bg), base, torch.float64)
    names = ["means", "quats", "scales", "opacities", "colors", "world2cam", "K"]
    for name, a, b in zip(names, gf, gr):
        assert b.norm() > 0, name
        rel = float((a - b).norm() / b.norm())
        assert rel < tol, f"{name}: relative gradient error {rel:.2e}"


def test_gradcheck_float64_few_gaussians():
    W, H = 16, 12
    means, quats, scales, opac, cols, w2c, K = _scene(4, W, H, seed=5, op_lo=0.3, op_hi=0.8, spread=0.3)
    scales = scales + 0.1

    proj = torch.randn(H * W * 4, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(m, q, s, o, c, T):
        out = rasterize(m, q, s, o, c, T, K, W, H, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
        full = torch.cat([out.image, out.alpha[..., None]], -1).reshape(-1)
        return full @ proj   # a few random projections keep the analytic Jacobian cheap

    ins = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols, w2c)]
    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_every_tile_and_chunk_size_renders_the_same_image():
    W, H = 50, 37   # not a multiple of any tile size
    args = [a.float() for a in _scene(300, W, H, seed=2)]
    ref = rasterize(*args, W, H, tile=4, chunk=32).image
    for tile, chunk in [(8, 32), (4, 5), (16, 7)]:
        img = rasterize(*args, W, H, tile=tile, chunk=chunk).image
        assert (img - ref).abs().max() < 1e-5   # float32; differences come from tile-local coordinates


def test_gaussians_behind_the_camera_leave_the_background_and_no_alpha():
    W, H = 20, 16
    means, quats, scales, opac, cols, w2c, K = [a.float() for a in _scene(10, W, H)]
    means = means.clone()
    means[:, 2] = -4.0   # all behind the camera
    bg = torch.tensor([0.5, 0.25, 1.0])
    out = rasterize(means, quats, scales, opac, cols, torch.eye(4), K, W, H, bg)
    assert torch.allclose(out.image, bg.expand(H, W, 3))
    assert float(out.alpha.abs().max()) == 0.0 and int(out.radii.abs().max()) == 0


def test_inputs_of_the_wrong_shape_are_refused_naming_the_argument():
    W, H = 20, 16
    a = [t.float() for t in _scene(5, W, H)]
    with pytest.raises(ShapeError, match="means"):
        rasterize(a[0][:, :2], *a[1:], W, H)
    with pytest.raises(ShapeError, match="opacities"):
        rasterize(a[0], a[1], a[2], a[3][:3], *a[4:], W, H)
    with pytest.raises(ShapeError, match="world2cam"):
        rasterize(*a[:5], a[5][:3], a[6], W, H)
    with pytest.raises(ShapeError, match="width"):
        rasterize(*a, 0, H)
    for w in (True, 16.7):  # a bool and a fraction were taken (16.7 as 16)
        with pytest.raises(ShapeError, match=f"width and height expected positive ints, got {w!r}"):
            rasterize(*a, w, H)
    for k in (5, 6):  # a NaN camera rendered a blank image without a word
        bad = [t.clone() for t in a]
        bad[k][0, 0] = float("nan")
        with pytest.raises(ShapeError, match=f"{['world2cam', 'K'][k - 5]} expected finite values, got 1 NaN or inf"):
            rasterize(*bad, W, H)
    K = a[6].clone()
    K[0, 1] = 0.5
    with pytest.raises(ConventionError, match="skew"):
        rasterize(*a[:6], K, W, H)
    with pytest.raises(ShapeError, match="backend"):
        rasterize(*a, W, H, backend="vulkan")


def test_gsplat_backend_falls_back_on_cpu():
    W, H = 20, 16
    a = [t.float() for t in _scene(30, W, H)]
    ref = rasterize(*a, W, H).image
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        import sys

        sys.modules["pointmap.splat.rasterize"]._GSPLAT_STATE.pop("warned", None)
        img = rasterize(*a, W, H, backend="gsplat").image
    assert torch.equal(img, ref)
    assert any("gsplat backend unavailable" in str(w.message) for w in rec)
    assert math.isfinite(float(img.sum()))


def test_the_gsplat_glue_gives_the_torch_backends_image_depth_and_alpha_under_gsplats_contract(monkeypatch):
    """No GPU here: a stand-in for ``gsplat.rasterization`` keeps gsplat's contract (pixel centres at i + 0.5;
    "RGB+ED" appends the expected depth to the colours' channels itself) and renders with the torch backend, so
    the glue's conversions are what is tested. The glue once added a channel of its own: four colour channels."""
    import sys
    import types

    rz = sys.modules["pointmap.splat.rasterize"]

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, eps2d,
                      packed, render_mode, backgrounds):
        assert render_mode == "RGB+ED" and backgrounds is None and not packed
        K = Ks[0].clone()
        K[:2, 2] -= 0.5
        out = rasterize(means, quats, scales, opacities, colors, viewmats[0], K, width, height, near=near_plane,
                        eps2d=eps2d)
        img = torch.cat([out.image, out.depth[..., None]], -1)[None]
        return img, out.alpha[None, ..., None], {"radii": out.radii[None], "means2d": out.means2d[None]}

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=rasterization))
    W, H = 20, 16
    a = [t.float() for t in _scene(30, W, H)]
    bg = torch.tensor([0.2, 0.4, 0.6])
    ref = rasterize(*a, W, H, background=bg)
    got = rz._rasterize_gsplat(*a, W, H, bg, 0.01, 0.3)
    assert got.image.shape == (H, W, 3)
    assert torch.allclose(got.image, ref.image, atol=1e-6)
    assert torch.allclose(got.alpha, ref.alpha) and torch.equal(got.radii, ref.radii)


def test_a_transposed_K_and_non_finite_gaussians_or_background_are_refused_naming_the_input():
    W, H = 20, 16
    a = [t.float() for t in _scene(5, W, H)]
    with pytest.raises(ConventionError, match=r"K expected pinhole intrinsics .* transposed K puts cx, cy in the "
                                              r"bottom row\), got \[\[18\.0, 0\.0, 0\.0\], .*\[9\.69\d*, 7\.4\d*, 1\.0\]\]"):
        rasterize(*a[:6], a[6].T.contiguous(), W, H)  # cx, cy in the bottom row: drew a fifth of the coverage
    for k, name in enumerate(["means", "quats", "scales", "opacities", "colors"]):
        bad = [t.clone() for t in a]
        bad[k].view(-1)[1] = float("nan") if k != 2 else float("inf")
        with pytest.raises(ShapeError, match=f"{name} expected finite values, got 1 NaN or inf"):
            rasterize(*bad, W, H)  # a NaN colour painted NaN pixels; a NaN mean was dropped without a word
    with pytest.raises(ShapeError, match="background expected finite values, got 1 NaN or inf"):
        rasterize(*a, W, H, torch.tensor([0.0, float("nan"), 0.0]))
    assert bool(torch.isfinite(rasterize(*a, W, H, torch.tensor([0.0, 0.5, 0.0])).image).all())


def test_the_jacobian_is_clamped_at_1_3_times_the_frustum_through_the_outer_pixel_edges():
    """docs/conventions.md: pixel centres at integers, the image spans [-0.5, W - 0.5]. Beyond 1.3x that frustum
    the EWA Jacobian is taken at the clamped point: x/z in [-1.3 (cx + 0.5) / fx, 1.3 (W - 0.5 - cx) / fx]."""
    from pointmap.splat.rasterize import project_gaussians

    W, H, f = 32, 24, 30.0
    K = torch.tensor([[f, 0, 10.0], [0, f, 14.0], [0, 0, 1]], dtype=torch.float64)  # off-centre principal point
    q = torch.tensor([[1.0, 0, 0, 0]] * 4, dtype=torch.float64)
    s = torch.tensor([[0.1, 0.1, 1.0]] * 4, dtype=torch.float64)
    z = 2.0
    means = torch.tensor([[3.0, 0, z], [-3.0, 0, z], [0, 3.0, z], [0, -3.0, z]], dtype=torch.float64)  # |x/z| 1.5
    _, _, _, ok, (a, b, c, _) = project_gaussians(means, q, s, torch.eye(4, dtype=torch.float64), K, W, H)
    assert bool(ok.all())
    lim = {"x+": 1.3 * (W - 0.5 - 10.0) / f, "x-": -1.3 * (10.0 + 0.5) / f,
           "y+": 1.3 * (H - 0.5 - 14.0) / f, "y-": -1.3 * (14.0 + 0.5) / f}
    # J = [[f/z, 0, -f t/z], [0, f/z, -f t'/z]] at t = the clamped x/z (y/z), Sigma = diag(s^2): by hand
    expect_a = [(f / z * 0.1) ** 2 + (f * lim["x+"] / z * 1.0) ** 2, (f / z * 0.1) ** 2 + (f * lim["x-"] / z) ** 2,
                (f / z * 0.1) ** 2, (f / z * 0.1) ** 2]
    expect_c = [(f / z * 0.1) ** 2, (f / z * 0.1) ** 2, (f / z * 0.1) ** 2 + (f * lim["y+"] / z) ** 2,
                (f / z * 0.1) ** 2 + (f * lim["y-"] / z) ** 2]
    assert torch.allclose(a - 0.3, torch.tensor(expect_a, dtype=torch.float64), rtol=1e-12)
    assert torch.allclose(c - 0.3, torch.tensor(expect_c, dtype=torch.float64), rtol=1e-12)
    assert float(a[0] - 0.3) == pytest.approx(197.55, abs=0.01)  # 1.3 (W - cx) / fx gave 206.74
    # the reference applies the same clamp: a wide Gaussian beyond it renders the same
    big = torch.tensor([[0.1, 0.1, 3.0]] * 4, dtype=torch.float64)
    op, cols = torch.full((4,), 0.9, dtype=torch.float64), torch.eye(4, 3, dtype=torch.float64) + 0.1
    ref, _, _ = reference_render(means, q, big, op, cols, torch.eye(4, dtype=torch.float64), K, W, H)
    out = rasterize(means, q, big, op, cols, torch.eye(4, dtype=torch.float64), K, W, H)
    assert float(ref.max()) > 0.1 and (out.image - ref).abs().max() < 1e-12


def test_gaussians_of_mixed_float_dtypes_render_in_the_means_dtype_with_gradients_for_every_input():
    W, H = 20, 16
    a = [t.float() for t in _scene(30, W, H)]
    ref = rasterize(*a, W, H, torch.tensor([0.1, 0.2, 0.3]))
    for k in range(1, 5):  # float64 quats, scales, opacities or colours with float32 means: a RuntimeError deep inside
        mixed = [t.clone() for t in a]
        mixed[k] = mixed[k].double().requires_grad_(True)
        out = rasterize(*mixed, W, H, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
        assert out.image.dtype == torch.float32 and (out.image - ref.image).abs().max() < 1e-6
        out.image.sum().backward()
        assert mixed[k].grad is not None and mixed[k].grad.dtype == torch.float64
    with pytest.raises(ShapeError, match=r"means expected floating-point \[N, 3\], got \[30, 3\] torch.int64"):
        rasterize(a[0].long(), *a[1:], W, H)


def test_numpy_arrays_and_lists_render_as_the_same_tensors_would():
    # a list background or numpy means raised an AttributeError (.shape / .ndim of a list, .is_floating_point of numpy)
    W, H = 20, 16
    a = _scene(6, W, H)
    want = rasterize(*a, W, H, background=torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64))
    got = rasterize(*[t.numpy() for t in a], W, H, background=[0.2, 0.3, 0.4])
    assert got.image.dtype == torch.float64
    assert torch.equal(got.image, want.image) and torch.equal(got.depth, want.depth)
    with pytest.raises(ShapeError, match="colors expected a tensor or an array of numbers, got list"):
        rasterize(*a[:4], [["red"]] * 6, *a[5:], W, H)
