"""Previews and atomic files of ``pointmap.io_pair`` (used by ``pointmap pair`` and ``pointmap demo``)."""

import os

import cv2
import numpy as np

from pointmap.io_pair import color_range, colorize, write_png


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m


def test_maps_drawn_over_one_color_range_give_equal_depths_equal_colours():
    near = np.linspace(1.0, 2.0, 64, dtype=np.float32).reshape(8, 8)
    far = near + 3.0
    shared = color_range((near, None), (far, None))
    a, b = colorize(near, value_range=shared), colorize(far, value_range=shared)
    assert shared[0] < 1.1 and shared[1] > 4.9
    assert np.array_equal(a[-1, -1], colorize(np.full((1, 1), 2.0, np.float32), value_range=shared)[0, 0])
    assert not np.array_equal(a[0, 0], b[0, 0])  # 1 m and 4 m differ once the range is shared
    assert np.array_equal(colorize(near)[0, 0], colorize(far)[0, 0])  # each on its own range they would not


def test_color_range_ignores_masked_out_and_non_finite_values():
    x = np.array([[1.0, 2.0, np.inf, 100.0]], np.float32)
    valid = np.array([[True, True, True, False]])
    lo, hi = color_range((x, valid))
    assert 1.0 <= lo < hi <= 2.0
    assert color_range((x, valid), (np.zeros_like(x), np.zeros_like(valid))) == (lo, hi)  # an all-invalid map adds nothing
    assert color_range((x, np.zeros_like(valid))) == (0.0, 1.0)


def test_write_png_leaves_an_ordinary_file_and_no_temporary_file(tmp_path):
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0] = 255
    path = write_png(tmp_path / "preview", rgb)
    assert path == tmp_path / "preview.png" and [p.name for p in tmp_path.iterdir()] == ["preview.png"]
    assert (path.stat().st_mode & 0o777) == 0o666 & ~_umask()
    assert np.array_equal(cv2.imread(str(path))[..., ::-1], rgb)
