"""Focals from matches (pointmap.align.selfcal): the essential-matrix cost against a per-focal reference, the focals
recovered from exact and outlier-laden matches of the analytic scene (per image and per camera), what the prior, known
and untouched cameras keep, and the epipolar stage starting from them."""

import dataclasses

import numpy as np
import pytest
import torch
from align_scene import gt_matches, gt_preds, make_scene, views_of, with_descriptors

import pointmap.align.epipolar as epipolar
from pointmap.align import AlignConfig, EpipolarConfig, global_align, refine_epipolar
from pointmap.align.selfcal import calibrate_focals, essential_cost, fundamental_matrices
from pointmap.errors import ShapeError

FOCALS = [70.0, 95.0, 80.0, 110.0, 90.0]


@pytest.fixture(scope="module")
def scene():
    return make_scene(5, 64, 96, seed=7, focals=FOCALS)


def true_F(sc, i, j):
    """x_j^T F x_i = 0 for the scene's cameras i and j (pixels)."""
    rel = np.linalg.inv(sc["cam2world"][j]) @ sc["cam2world"][i]  # camera i's points in camera j's frame
    R, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(sc["K"][j]).T @ tx @ R @ np.linalg.inv(sc["K"][i])


def all_matches(sc, outliers=0.0):
    n = len(sc["cam2world"])
    return {(i, j): gt_matches(sc, i, j, step=4, outliers=outliers, seed=3 * i + j, occluded=True)[:2]
            for i in range(n) for j in range(i + 1, n)}


def test_the_essential_cost_is_zero_at_the_true_focals_and_agrees_with_a_per_focal_reference(scene):
    F = true_F(scene, 0, 1)
    ci, cj = scene["K"][0, :2, 2], scene["K"][1, :2, 2]
    fi, fj = np.array([50.0, 70.0, 91.0]), np.array([95.0, 60.0, 130.0, 80.0])
    cost = essential_cost(F, fi, fj, ci, cj)
    for a, f1 in enumerate(fi):  # the slow reference: one SVD per focal pair
        for b, f2 in enumerate(fj):
            Ki = np.array([[f1, 0, ci[0]], [0, f1, ci[1]], [0, 0, 1]])
            Kj = np.array([[f2, 0, cj[0]], [0, f2, cj[1]], [0, 0, 1]])
            s = np.linalg.svd(Kj.T @ F @ Ki, compute_uv=False)
            assert cost[a, b] == pytest.approx((s[0] - s[1]) / (s[0] + s[1]), abs=1e-12)
    assert cost[1, 0] < 1e-9 and (np.delete(cost.ravel(), 0 * 4 + 0 + 4) > 1e-3).all()


@pytest.mark.parametrize("outliers", [0.0, 0.2])
def test_the_matches_give_every_image_its_focal_from_a_start_far_off(scene, outliers):
    Fs = fundamental_matrices(all_matches(scene, outliers), threshold_px=0.5)
    assert len(Fs) == 10
    start = np.array(FOCALS) * [1.4, 0.7, 1.3, 0.75, 1.2]
    f = calibrate_focals(Fs, start, scene["K"][:, :2, 2], prior=0.0)
    # exact: the grid (steps of 1.2%) then the joint polish, which follows the valley along which all four focals
    # shrink together (the ring's optical axes nearly meet) where one camera at a time stops 2-3% short
    assert np.abs(f / FOCALS - 1).max() < 0.005, f
    # the prior holds the focals near the start, and is what a pair's flat cost falls back to
    held = calibrate_focals(Fs, start, scene["K"][:, :2, 2], prior=1e3)
    assert np.allclose(held, start, rtol=1e-3)


def test_one_camera_of_several_images_gets_one_focal_and_a_known_camera_keeps_its_own():
    sc = make_scene(5, 64, 96, seed=7, focals=[80.0, 110.0, 80.0, 110.0, 80.0])
    Fs = fundamental_matrices(all_matches(sc), threshold_px=0.5)
    camera = np.array([0, 1, 0, 1, 0])
    start = np.array([100.0, 90.0, 100.0, 90.0, 100.0])
    f = calibrate_focals(Fs, start, sc["K"][:, :2, 2], camera, prior=0.0)
    assert np.ptp(f[[0, 2, 4]]) == 0 and f[1] == f[3]
    assert abs(f[0] / 80 - 1) < 0.005 and abs(f[1] / 110 - 1) < 0.005, f
    start[[1, 3]] = 110.0  # camera 1 known (image 3's K given): it stays, and camera 0 is fitted to it
    known = calibrate_focals(Fs, start, sc["K"][:, :2, 2], camera, fixed=[3], prior=0.0)
    assert known[1] == known[3] == 110.0 and abs(known[0] / 80 - 1) < 0.005, known
    alone = calibrate_focals({k: F for k, F in Fs.items() if 4 not in k}, start, sc["K"][:, :2, 2], prior=0.0)
    assert alone[4] == 100.0  # no pair touches it: its start


def test_pairs_with_too_few_matches_give_no_fundamental_matrix(scene):
    m = all_matches(scene)
    m[(0, 1)] = (m[(0, 1)][0][:10], m[(0, 1)][1][:10])
    assert sorted(fundamental_matrices(m, threshold_px=0.5)) == sorted(set(m) - {(0, 1)})


@pytest.mark.parametrize("kwargs,message", [
    ({"f_start": [80.0, -1.0, 90.0]}, "positive"),
    ({"f_start": [80.0, np.nan, 90.0]}, "positive"),
    ({"centres": np.zeros((2, 2))}, "centres"),
    ({"camera": [0, 0, 1], "f_start": [80.0, 81.0, 90.0]}, "one start focal per camera"),
    ({"span": 1.0}, "span > 1"),
    ({"prior": -0.1}, "prior >= 0"),
])
def test_bad_calibration_inputs_are_refused_by_what_was_expected(kwargs, message):
    args = {"Fs": {}, "f_start": [80.0, 85.0, 90.0], "centres": np.zeros((3, 2)), **kwargs}
    with pytest.raises(ShapeError, match=message):
        calibrate_focals(**args)


def test_the_stage_starts_from_the_matches_focals_when_the_networks_are_off(monkeypatch):
    scene = make_scene(5, 96, 144, seed=7, focals=[1.5 * f for f in FOCALS])  # 216 cells of 8 px per view
    pairs = [(i, j) for i in range(5) for j in range(i + 1, 5)]
    views = views_of(scene)
    preds = with_descriptors(gt_preds(scene, pairs, seed=2, pair_rot_deg=4.0, noise=0.01), scene)
    recon = global_align(views, preds, config=AlignConfig(quiet=True))
    wrong = 1.5 * np.array(FOCALS) * 1.3  # a network whose focals are all 30% long
    monkeypatch.setattr(epipolar, "own_focals", lambda preds, n: wrong.copy())
    cfg = EpipolarConfig(patch=8)
    plain = refine_epipolar(views, preds, recon, config=cfg)
    assert np.allclose(plain.K[:, 0, 0].numpy(), wrong) and plain.info["epipolar"]["self_calibration"] is None
    out = refine_epipolar(views, preds, recon, config=dataclasses.replace(cfg, self_calibrate=True))
    rep = out.info["epipolar"]["self_calibration"]
    assert rep["pairs"] >= 5 and np.allclose(rep["focals_own"], wrong)
    err = np.abs(out.K[:, 0, 0].double().numpy() / (1.5 * np.array(FOCALS)) - 1)
    assert np.median(err) < 0.1, err  # coarse 8-px cells: far nearer than the network's 30%
    assert torch.allclose(out.K[:, 0, 0].double(), torch.tensor(rep["focals"], dtype=torch.float64), rtol=1e-6)


def test_self_calibrate_must_be_a_switch():
    with pytest.raises(ShapeError, match="self_calibrate expected True or False"):
        EpipolarConfig(self_calibrate="yes")
