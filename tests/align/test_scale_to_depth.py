"""scale_to_depth: a reconstruction put in the units of measured depth (a LiDAR / RGB-D map, sparse depth)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[1] / "io"))
from recon_factory import make_recon  # noqa: E402

import pointmap as pm  # noqa: E402

S = 3.7  # metres per reconstruction unit


def field(u_map, v_map):
    """The reconstruction's depth as a function of map coordinates: steep, so a misplaced lookup shows."""
    return 2 + 0.05 * u_map + 0.03 * v_map


def recon_with_field(n=3):
    recon = make_recon(n=n)  # 100x75 originals -> 32x24 maps: scale 0.36, cropped 2 px left, 1 px top
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    recon.depth_z = field(u, v)[None].repeat(n, 1, 1).float()
    return recon


def measured(width, height, scale=S):
    """The metric depth a sensor of width x height over the 100x75 original would read: the field at each sensor
    pixel's centre, mapped into the maps' coordinates (u_map = (u_orig + 0.5) 0.36 - 0.5 - 2)."""
    ud, vd = np.meshgrid(np.arange(width), np.arange(height))
    uo, vo = (ud + 0.5) * 100 / width, (vd + 0.5) * 75 / height  # edge coordinates of the original
    return scale * field(uo * 0.36 - 0.5 - 2.0, vo * 0.36 - 0.5 - 1.0)


@pytest.mark.parametrize("size", [(100, 75), (40, 30)])
def test_the_scale_of_measured_depth_is_recovered_within_a_percent_at_full_or_sensor_resolution(size):
    recon = recon_with_field()
    moved, rep = pm.scale_to_depth(recon, [measured(*size)] * 3)
    assert rep["scale"] == pytest.approx(S, rel=0.01) and rep["images"] == 3 and rep["spread"] < 0.02
    assert torch.allclose(moved.depth_z, recon.depth_z * rep["scale"], rtol=1e-5)
    centres = recon.cam2world[:, :3, 3].double() * rep["scale"]
    assert torch.allclose(moved.cam2world[:, :3, 3].double(), centres, atol=1e-5)


def test_a_lookup_that_ignored_the_crop_would_be_off_by_more_than_the_tolerance():
    recon = recon_with_field()
    shifted = np.roll(measured(100, 75), 6, axis=1)  # 6 original pixels: about the 2-map-pixel crop
    rep = pm.scale_to_depth(recon, [shifted] * 3)[1]
    assert abs(rep["scale"] / S - 1) > 0.02


def test_outliers_holes_masks_and_images_without_depth_leave_the_median_in_place():
    recon = recon_with_field()
    rng = np.random.default_rng(0)
    d = measured(100, 75)
    bad = rng.random(d.shape) < 0.2
    d[bad] = rng.uniform(0.1, 100, bad.sum())  # a fifth of the readings are garbage
    d[rng.random(d.shape) < 0.2] = np.nan
    d[:10] = 0
    recon.masks = torch.ones(3, 24, 32, dtype=torch.bool)
    recon.masks[:, :, :8] = False
    moved, rep = pm.scale_to_depth(recon, [d, None, torch.from_numpy(measured(40, 30))])
    assert rep["scale"] == pytest.approx(S, rel=0.01) and rep["images"] == 2 and rep["per_image"][1] is None
    assert rep["pixels"] < 2 * 24 * 24


def test_maps_that_cannot_be_used_are_refused_in_one_line():
    recon = recon_with_field()
    with pytest.raises(pm.ShapeError, match="depth expected a list of 3 maps .*got 2 entries"):
        pm.scale_to_depth(recon, [measured(100, 75)] * 2)
    with pytest.raises(pm.ShapeError, match=r"depth\[1\] is 50x50, not the aspect ratio of image 1 \(100x75"):
        pm.scale_to_depth(recon, [measured(100, 75), np.ones((50, 50)), None])
    with pytest.raises(pm.ShapeError, match=r"depth\[0\] expected a \[H, W\] map of numbers"):
        pm.scale_to_depth(recon, [np.ones((75, 100, 3)), None, None])
    with pytest.raises(pm.PointmapError, match="at least 50 pixels .*got 0"):
        pm.scale_to_depth(recon, [np.zeros((75, 100)), None, None])


def test_a_canvas_padding_is_not_read_even_where_it_holds_depth():
    import dataclasses

    recon = recon_with_field()
    recon.depth_z[1, :, 16:] *= 10  # view 1 fills the left half of the canvas; its padding holds a wrong depth
    padded = dataclasses.replace(recon, map_sizes=[(32, 24), (16, 24), (32, 24)])
    _, rep = pm.scale_to_depth(padded, [measured(100, 75)] * 3)
    assert rep["per_image"][1] == pytest.approx(S, rel=0.01) and rep["spread"] < 0.02
