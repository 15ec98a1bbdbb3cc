"""Bugs found by the mutation review of the splatting rasterizer (session 93): inputs ``rasterize`` took without a word
and then drew wrong (opacities above 1 lost the rim of their footprint to tile culling; a NaN near plane or low-pass
drew nothing) or crashed on deep inside (a float tile or chunk)."""

import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import rasterize
from tests.splat.reference import reference_render

F64 = torch.float64


def _one(opacity=0.9, scale=0.2, W=96, H=96):
    K = torch.tensor([[0.94 * W, 0, (W - 1) / 2], [0, 0.94 * H, (H - 1) / 2], [0, 0, 1]], dtype=F64)
    return [torch.tensor([[0.0, 0.0, 2.0]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
            torch.full((1, 3), scale, dtype=F64), torch.tensor([opacity], dtype=F64), torch.ones(1, 3, dtype=F64),
            torch.eye(4, dtype=F64), K, W, H]


def test_an_opacity_above_one_is_drawn_as_the_reference_draws_it_or_refused():
    """The radius took min(opacity, 1) while the alpha takes the opacity itself: at opacity 20 the tiles beyond
    sqrt(2 ln 255 lambda) were culled though alpha there is above 1/255 (up to 0.05 of the image lost)."""
    args = _one(opacity=20.0)
    try:
        out = rasterize(*args)
    except ShapeError as e:
        assert "opacities expected values in [0, 1]" in str(e)
        return
    ref, _, _ = reference_render(*args)
    assert (out.image - ref).abs().max() < 1e-12


@pytest.mark.parametrize("opacity", [1.5, -0.5])
def test_opacities_outside_0_1_are_refused_naming_them(opacity):
    with pytest.raises(ShapeError, match=rf"opacities expected values in \[0, 1\], got 1 outside \(first {opacity}\)"):
        rasterize(*_one(opacity=opacity))


@pytest.mark.parametrize("opacity", [0.0, 1.0])
def test_opacities_of_exactly_0_and_1_are_taken(opacity):
    out = rasterize(*_one(opacity=opacity, W=12, H=10))
    assert bool(torch.isfinite(out.image).all())


@pytest.mark.parametrize("tile,chunk", [(4.0, 32), (2.5, 32), (4, 32.0), (True, 32), (4, True)])
def test_a_tile_or_chunk_that_is_not_an_int_is_refused(tile, chunk):
    with pytest.raises(ShapeError, match=rf"tile and chunk expected ints >= 1, got {tile!r}, {chunk!r}"):
        rasterize(*_one(W=12, H=10), tile=tile, chunk=chunk)


@pytest.mark.parametrize("near,eps2d", [(float("nan"), 0.3), (-1.0, 0.3), (0.01, float("nan")), (0.01, -1.0),
                                        (0.01, True), (float("inf"), 0.3)])
def test_a_near_plane_or_low_pass_that_is_not_a_finite_number_at_least_zero_is_refused(near, eps2d):
    """A NaN near plane or eps2d drew an empty image without a word; a negative near plane drew Gaussians behind the
    camera, mirrored."""
    with pytest.raises(ShapeError, match=rf"near and eps2d expected finite numbers >= 0, got {near!r}, {eps2d!r}"):
        rasterize(*_one(W=12, H=10), near=near, eps2d=eps2d)


def test_a_numpy_tile_chunk_near_and_eps2d_are_taken():
    np = pytest.importorskip("numpy")
    a = rasterize(*_one(W=12, H=10))
    b = rasterize(*_one(W=12, H=10), tile=np.int64(4), chunk=np.int32(32), near=np.float64(0.01), eps2d=np.float32(0.3))
    assert torch.allclose(a.image, b.image, atol=1e-7)
