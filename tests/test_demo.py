"""``pointmap demo`` on a shipped scene with the tiny test model (errors are meaningless, previews are not)."""

import numpy as np
import pytest

import pointmap.io_pair
from pointmap.demo import demo_scenes, evaluate_scene


def test_every_depth_preview_of_a_scene_is_drawn_over_one_colour_range(tmp_path, test_model, monkeypatch):
    scenes = demo_scenes()
    if not scenes:
        pytest.skip("no demo scenes shipped")
    ranges = []
    colorize = pointmap.io_pair.colorize

    def recording_colorize(x, valid=None, value_range=None):
        ranges.append(value_range)
        return colorize(x, valid, value_range)

    monkeypatch.setattr(pointmap.io_pair, "colorize", recording_colorize)
    res = evaluate_scene(test_model, scenes[0], tmp_path, size=64, quiet=True)
    n_pairs = len(res["rows"])
    assert n_pairs >= 2 and len(ranges) == 2 * n_pairs  # prediction and ground truth per pair
    assert all(r == res["depth_range"] for r in ranges)
    lo, hi = res["depth_range"]
    depth = res["gt"]["depth_z"].astype(np.float32)
    assert depth[depth > 0].min() <= lo < hi <= depth.max()
    assert len(list(tmp_path.glob("pair*_depth.png"))) == n_pairs
