import cv2
import numpy as np
import pytest
import torch

from benchmarks.bench_real import MOTO_B, MOTO_DOFFS, MOTO_F, median_abs_rel, motorcycle
from training.evaluate import abs_rel


def _write_pair(folder, disp, shape=(20, 30)):
    rng = np.random.default_rng(0)
    for name in ("motorcycle_left.png", "motorcycle_right.png"):
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (*shape, 3), dtype=np.uint8))
    np.savez(folder / "motorcycle_disp.npz", disp)


def test_the_motorcycle_depth_comes_from_disparity_through_the_calibration_and_unknown_pixels_stay_unknown(tmp_path):
    disp = np.full((20, 30), 10.0, np.float32)
    disp[0, 0] = np.inf  # scikit-image marks pixels without ground truth this way
    _write_pair(tmp_path, disp)
    left, right, depth, K1, K2, gt = motorcycle(tmp_path)
    assert left.shape == right.shape == (20, 30, 3)
    assert np.isnan(depth[0, 0]) and np.isfinite(depth).sum() == 20 * 30 - 1
    assert depth[5, 5] == pytest.approx(MOTO_F * MOTO_B / (10.0 + MOTO_DOFFS))
    assert K2[0, 2] - K1[0, 2] == pytest.approx(MOTO_DOFFS) and K1[0, 0] == K2[1, 1] == MOTO_F
    assert np.allclose(gt[:3, :3], np.eye(3)) and gt[0, 3] == MOTO_B and gt[1, 3] == gt[2, 3] == 0


def test_a_motorcycle_folder_with_missing_or_mismatched_files_is_refused_with_what_is_wrong(tmp_path):
    with pytest.raises(SystemExit, match="lacks motorcycle_left.png, motorcycle_right.png, motorcycle_disp.npz"):
        motorcycle(tmp_path)
    _write_pair(tmp_path, np.ones((10, 10), np.float32))
    with pytest.raises(SystemExit, match="do not agree"):
        motorcycle(tmp_path)


def test_median_abs_rel_forgives_the_scale_but_not_the_shape():
    true_z = np.linspace(1.0, 4.0, 100)
    valid = np.ones(100, bool)
    err, r = median_abs_rel(3.0 * true_z, true_z, valid)  # right up to scale
    assert err == pytest.approx(0.0, abs=1e-12) and r == pytest.approx(1.0)
    err_c, r_c = median_abs_rel(np.ones(100), true_z, valid)  # a constant: one depth everywhere
    assert err_c > 0.2 and r_c == 0.0


def test_median_abs_rel_is_the_held_out_sets_abs_rel():
    rng = np.random.default_rng(0)
    true_z = rng.uniform(1.0, 5.0, (12, 16))
    pred_z = true_z * rng.uniform(0.5, 1.5, true_z.shape)
    pred_z[0, :3] = -1.0  # behind the camera: full relative error, left out of the scale
    valid = rng.random(true_z.shape) > 0.2
    expected = abs_rel(torch.from_numpy(pred_z), torch.from_numpy(true_z), torch.from_numpy(valid))
    assert median_abs_rel(pred_z, true_z, valid)[0] == pytest.approx(expected, rel=1e-12)
    # abs_rel against its slow reference: tests/training/test_evaluate.py
