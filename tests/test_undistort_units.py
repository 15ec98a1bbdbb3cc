"""Unit tests of pointmap/undistort.py from a mutation review (session 90): each closes a gap tests/test_undistort.py
leaves open (the mutants each kills are named in its comment); last, tests of the bug it found."""

import cv2
import numpy as np
import pytest

from pointmap.errors import PointmapError
from pointmap.undistort import Distortion, distort, pinhole_for, undistort, undistort_photos

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
W, H = 320, 240
BARREL = Distortion("OPENCV", (-0.25, 0.08, 0.001, -0.0005))


def sources(Kp, Ks, dist, w=W, h=H):
    """Where every pixel of the pinhole view Kp comes from in the photograph (Ks, dist)."""
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    xy = np.stack([(u.ravel() - Kp[0, 2]) / Kp[0, 0], (v.ravel() - Kp[1, 2]) / Kp[1, 1]], 1)
    return distort(xy, Ks, dist)


def test_positional_coefficients_are_in_colmaps_order_for_every_model():
    # m01 (OPENCV names reordered), m02 (FULL_OPENCV names reordered), m04 (fisheye names), m08 (FULL_OPENCV cut to 5)
    assert np.array_equal(Distortion("OPENCV", (1, 2, 3, 4, 5)).opencv(), [1, 2, 3, 4, 5])
    assert np.array_equal(Distortion("FULL_OPENCV", range(1, 9)).opencv(), [1, 2, 3, 4, 5, 6, 7, 8])
    full = Distortion.from_named("FULL_OPENCV", {"k1": 1, "k2": 2, "k3": 5, "k4": 6, "k5": 7, "k6": 8, "p1": 3, "p2": 4})
    assert np.array_equal(full.opencv(), [1, 2, 3, 4, 5, 6, 7, 8])
    fish = Distortion.from_named("OPENCV_FISHEYE", {"k4": 4, "k3": 3, "k2": 2, "k1": 1})
    assert np.array_equal(fish.opencv(), [1, 2, 3, 4])


def test_a_rational_full_opencv_lens_is_undistorted_with_all_eight_coefficients():
    # m08: k4..k6 (the rational denominator) silently dropped
    dist = Distortion("FULL_OPENCV", (-0.2, 0.05, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0))
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    n = cv2.undistortPoints(pix, K, dist.opencv(), criteria=crit)[:, 0]
    photo = (127.5 + 127.5 * np.sin(7 * n[:, 0]) * np.cos(5 * n[:, 1])).reshape(H, W).astype(np.float32)
    K_new = pinhole_for(K, dist, (W, H))
    out = undistort(photo, K, dist, K_new)
    truth = 127.5 + 127.5 * np.sin(7 * (u - K_new[0, 2]) / K_new[0, 0]) * np.cos(5 * (v - K_new[1, 2]) / K_new[1, 1])
    assert np.abs(out - truth)[4:-4, 4:-4].max() < 0.1


@pytest.mark.parametrize("size", [(1, H), (W, 1), (320.0, 240.0)])
def test_a_size_that_is_not_two_or_more_whole_pixels_a_side_is_refused(size):
    # m22 (w > 1 loosened to w > 0), m23 (the integer check dropped)
    with pytest.raises(PointmapError, match="size expected"):
        pinhole_for(K, BARREL, size)


@pytest.mark.parametrize("Ks", [[[300.0, 0, 100.0], [0, 340.0, 150.0], [0, 0, 1]],   # right and top far
                                [[330.0, 0, 159.5], [0, 300.0, 170.0], [0, 0, 1]]],  # top far, y binding
                         ids=["right", "top"])
@pytest.mark.parametrize("dist", [BARREL, Distortion("OPENCV", (0.2,)), Distortion("OPENCV_FISHEYE", (0.05, -0.02))],
                         ids=["barrel", "pincushion", "fisheye"])
def test_an_off_centre_anisotropic_camera_gets_the_view_that_just_touches_the_photographs_edge(dist, Ks):
    # m30 (limits at 0..w-1, half a pixel inside), m33 (right edge unchecked), m34 (top edge unchecked),
    # m42 (border sampled half a pixel off), m43 (fx and fy swapped in the border rays)
    Ks = np.array(Ks)
    K_new = pinhole_for(Ks, dist, (W, H))
    assert np.allclose(K_new[:2, 2], Ks[:2, 2]) and np.isclose(K_new[0, 0] / K_new[1, 1], Ks[0, 0] / Ks[1, 1])
    src = sources(K_new, Ks, dist)
    margins = np.array([src[:, 0].min() + 0.5, W - 0.5 - src[:, 0].max(), src[:, 1].min() + 0.5,
                        H - 0.5 - src[:, 1].max()])
    assert margins.min() >= -1e-6, margins  # every pixel from inside the photograph
    assert margins.min() < 0.01, margins    # and no narrower than it needs to be


def test_a_strong_barrel_lens_is_unfolded_a_little_beyond_the_corners_of_the_view():
    # m38 (the 2 % sampling margin past the corners dropped): the fold must not sit right at a corner
    dist = Distortion("OPENCV", (-1.5,))
    K_new = pinhole_for(K, dist, (W, H))
    corner = (np.array([W - 1.0, H - 1.0]) - K_new[:2, 2]) / np.diag(K_new)[:2]
    rays = distort(np.linspace(0, 1.01, 2000)[:, None] * corner, K, dist)
    assert (np.diff(np.linalg.norm(rays - K[:2, 2], axis=1)) > 0).all()


def test_an_off_centre_strong_barrel_lens_is_cut_before_its_farthest_corner_folds():
    # m44 (the bottom-right corner's diagonal not checked for folding)
    dist = Distortion("OPENCV", (-1.5,))
    Ks = np.array([[300.0, 0, 60.0], [0, 300.0, 50.0], [0, 0, 1]])  # (W-1, H-1) is the farthest corner
    K_new = pinhole_for(Ks, dist, (W, H))
    corner = (np.array([W - 1.0, H - 1.0]) - K_new[:2, 2]) / np.diag(K_new)[:2]
    rays = distort(np.linspace(0, 1, 500)[:, None] * corner, Ks, dist)
    assert (np.diff(np.linalg.norm(rays - Ks[:2, 2], axis=1)) > 0).all()


def test_a_very_wide_fisheye_that_still_fits_a_pinhole_view_is_undistorted_not_refused_as_circular():
    # m49 (the too-wide start of the bisection at 0.3 instead of 0.05: such lenses refused as 180 degrees)
    Kf = np.array([[45.0, 0, 63.5], [0, 45.0, 63.5], [0, 0, 1]])  # 81 degrees to the edge midpoints
    K_new = pinhole_for(Kf, Distortion("OPENCV_FISHEYE"), (128, 128))
    assert 0.1 < K_new[0, 0] / 45.0 < 0.3


def test_an_explicit_pinhole_camera_is_the_one_resampled_onto():
    # m59 (K_new ignored for pinhole_for's), m60 (no distortion: returned as is whatever K_new says)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    pattern = lambda x, y: 127.5 + 127.5 * np.sin(7 * x) * np.cos(5 * y)  # noqa: E731
    photo = pattern((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]).astype(np.float32)  # a pinhole photograph
    zoomed = K.copy()
    zoomed[0, 0] = zoomed[1, 1] = 450.0
    truth = pattern((u - K[0, 2]) / 450.0, (v - K[1, 2]) / 450.0)
    assert np.abs(undistort(photo, K, Distortion("OPENCV"), zoomed) - truth)[2:-2, 2:-2].max() < 0.1
    n = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64), K, BARREL.opencv(),
                            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0]
    barrel_photo = pattern(n[:, 0], n[:, 1]).reshape(H, W).astype(np.float32)
    assert not np.allclose(zoomed, pinhole_for(K, BARREL, (W, H)))
    assert np.abs(undistort(barrel_photo, K, BARREL, zoomed) - truth)[4:-4, 4:-4].max() < 0.1


def label_mask():
    m = np.zeros((H, W), np.uint8)
    m[20:120, 30:170] = 100
    m[100:200, 150:300] = 200
    return m


def test_label_masks_are_resampled_by_nearest_and_keep_only_their_labels():
    # m64 (undistort's nearest ignored: bilinear invents labels between neighbours)
    out = undistort(label_mask(), K, BARREL, nearest=True)
    assert set(np.unique(out)) == {0, 100, 200}


def test_undistort_photos_resamples_label_masks_by_nearest_and_leaves_the_callers_list_as_given(tmp_path):
    # m71 (the photographs' masks resampled bilinearly), m82 (the caller's masks list overwritten)
    cv2.imwrite(str(tmp_path / "a.png"), np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8))
    mask = label_mask()
    masks = [mask]
    _, _, new_masks = undistort_photos([str(tmp_path / "a.png")], {0: K}, {0: BARREL}, tmp_path / "out", masks)
    assert set(np.unique(new_masks[0])) == {0, 100, 200}
    assert masks[0] is mask and new_masks is not masks


def test_output_names_that_differ_only_in_case_are_refused_as_one_name(tmp_path):
    # m74 (names compared case-sensitively: A.png and a.png overwrite each other on macOS and Windows)
    with pytest.raises(PointmapError, match="would share a file name"):
        undistort_photos([str(tmp_path / "x" / "A.png"), str(tmp_path / "y" / "a.png")], {0: K, 1: K},
                         {0: BARREL, 1: BARREL}, tmp_path / "out")


def test_a_distortion_for_the_index_one_past_the_last_photograph_is_refused():
    # m80 (0 <= k <= len(paths): the index len(paths) let through, an IndexError later)
    with pytest.raises(PointmapError, match=r"photograph indices in 0..0, got \[1\]"):
        undistort_photos(["a.jpg"], {0: K}, {1: BARREL}, ".")


def test_an_undistorted_photograph_opencv_could_not_write_is_reported(tmp_path, monkeypatch):
    # m83 (imwrite's False ignored: the photograph silently missing)
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((H, W, 3), np.uint8))
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: False)
    with pytest.raises(PointmapError, match="could not write the undistorted photograph"):
        undistort_photos([str(tmp_path / "a.png")], {0: K}, {0: BARREL}, tmp_path / "out")


# --- the bug the review found -----------------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["abc", [0.1, 0.2], {"x": 1}])
def test_named_coefficients_that_are_not_numbers_are_refused_with_what_was_expected(value):
    # today: a raw ValueError / TypeError from float() (the nerfstudio reader catches those, any other caller
    # of this public constructor gets no PointmapError)
    with pytest.raises(PointmapError, match=r"OPENCV expected numbers for k1, k2, p1, p2, k3"):
        Distortion.from_named("OPENCV", {"k1": value})


def test_a_named_coefficient_given_as_an_array_for_a_model_without_it_is_refused_with_what_was_expected():
    # today: "The truth value of an array ... is ambiguous" from `v not in (None, 0, 0.0)`
    with pytest.raises(PointmapError, match=r"OPENCV_FISHEYE has no coefficient p1|expected numbers"):
        Distortion.from_named("OPENCV_FISHEYE", {"k1": 0.1, "p1": np.array([0.1, 0.2])})
