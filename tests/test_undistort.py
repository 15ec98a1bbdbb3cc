"""Lens distortion undone onto pinhole cameras (pointmap.undistort), checked against a pattern drawn straight
into the pinhole view (the slow reference: every pixel's ray inverted one by one with OpenCV's iterative
undistortPoints); the CLI's --cameras is tested in tests/test_cli.py."""


import cv2
import numpy as np
import pytest

from pointmap.errors import PointmapError
from pointmap.undistort import Distortion, distort, pinhole_for, undistort, undistort_photos

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
W, H = 320, 240
LENSES = [
    Distortion("OPENCV", (-0.25, 0.08, 0.001, -0.0005)),  # barrel, with a little tangential distortion
    Distortion("OPENCV", (0.2,)),                          # pincushion
    Distortion("SIMPLE_RADIAL", (-0.1,)),
    Distortion("RADIAL", (-0.1, 0.02)),
    Distortion("OPENCV_FISHEYE", (0.05, -0.02, 0.01, 0.0)),
    Distortion("OPENCV_FISHEYE"),  # zero coefficients: still the equidistant projection, not a pinhole
]


def pattern(x, y):
    """A smooth grey pattern over normalised pinhole coordinates."""
    return 127.5 + 127.5 * np.sin(7 * x) * np.cos(5 * y)


def photograph(dist: Distortion) -> np.ndarray:
    """The pattern as the distorting lens photographs it: each pixel's ray found by inverting the lens model."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if dist.fisheye:
        n = cv2.fisheye.undistortPoints(pix, K, dist.opencv(), criteria=crit)[:, 0]
    else:
        n = cv2.undistortPoints(pix, K, dist.opencv(), criteria=crit)[:, 0]
    assert np.abs(distort(n, K, dist) - pix[:, 0]).max() < 1e-6  # the inversion is exact
    return pattern(n[:, 0], n[:, 1]).reshape(H, W).astype(np.float32)


@pytest.mark.parametrize("dist", LENSES, ids=lambda d: f"{d.model}{d.coeffs[0]:+}".replace("+0.0", "-zero"))
def test_an_undistorted_photograph_is_the_pinhole_view_of_the_same_scene(dist):
    K_new = pinhole_for(K, dist, (W, H))
    out = undistort(photograph(dist), K, dist, K_new)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    truth = pattern((u - K_new[0, 2]) / K_new[0, 0], (v - K_new[1, 2]) / K_new[1, 1])
    err = np.abs(out - truth)
    assert err[4:-4, 4:-4].max() < 0.1, err[4:-4, 4:-4].max()  # bilinear resampling of a smooth pattern
    assert err.max() < 1.0  # the outermost pixels come from within half a pixel of the photograph's edge
    assert np.allclose(K_new[:2, 2], K[:2, 2]) and np.isclose(K_new[0, 0] / K_new[1, 1], 1.0)


@pytest.mark.parametrize("dist", LENSES, ids=lambda d: f"{d.model}{d.coeffs[0]:+}".replace("+0.0", "-zero"))
def test_the_pinhole_view_is_the_widest_whose_every_pixel_comes_from_the_photograph(dist):
    K_new = pinhole_for(K, dist, (W, H))
    u, v = np.meshgrid(np.arange(W), np.arange(H))

    def sources(Kp):
        xy = np.stack([(u.ravel() - Kp[0, 2]) / Kp[0, 0], (v.ravel() - Kp[1, 2]) / Kp[1, 1]], 1)
        return distort(xy, K, dist)

    src = sources(K_new)  # every pixel, not only the border the search looks at
    assert src[:, 0].min() >= -0.5 and src[:, 0].max() <= W - 0.5
    assert src[:, 1].min() >= -0.5 and src[:, 1].max() <= H - 0.5
    wider = K_new.copy()
    wider[0, 0] *= 0.99
    wider[1, 1] *= 0.99
    src = sources(wider)
    assert (src[:, 0].min() < -0.5 or src[:, 0].max() > W - 0.5 or src[:, 1].min() < -0.5
            or src[:, 1].max() > H - 0.5)


def test_a_strong_barrel_lens_is_cut_before_its_model_folds_back_instead_of_mirroring_the_image():
    dist = Distortion("OPENCV", (-1.5,))  # r (1 - 1.5 r^2) turns back at r = 0.47
    K_new = pinhole_for(K, dist, (W, H))

    def diagonal_radius(Kp):
        corner = (np.array([W - 1.0, H - 1.0]) - Kp[:2, 2]) / np.diag(Kp)[:2]
        rays = distort(np.linspace(0, 1, 200)[:, None] * corner, K, dist)
        return np.linalg.norm(rays - K[:2, 2], axis=1)

    assert (np.diff(diagonal_radius(K_new)) > 0).all()
    wider = K_new.copy()
    wider[0, 0] *= 0.95
    wider[1, 1] *= 0.95
    assert not (np.diff(diagonal_radius(wider)) > 0).all()


def test_a_fisheye_with_zero_coefficients_is_not_taken_for_a_pinhole():
    lens = Distortion("OPENCV_FISHEYE")
    assert not lens.is_identity
    assert pinhole_for(K, lens, (W, H))[0, 0] < 0.97 * K[0, 0]  # the equidistant image is wider than a pinhole's


def test_a_circular_fisheye_seeing_180_degrees_in_the_frame_is_refused_instead_of_squeezed_to_a_dot():
    wide = np.array([[30.0, 0, 63.5], [0, 30.0, 47.5], [0, 0, 1]])  # 30 px per radian: 90 degrees at 47 px
    with pytest.raises(PointmapError, match="180 degrees or more"):
        pinhole_for(wide, Distortion("OPENCV_FISHEYE"), (128, 96))
    narrower = np.array([[60.0, 0, 63.5], [0, 60.0, 47.5], [0, 0, 1]])  # 90 degrees at 94 px: outside the frame
    assert pinhole_for(narrower, Distortion("OPENCV_FISHEYE"), (128, 96))[0, 0] > 30


def test_a_one_channel_image_keeps_its_channel_axis():
    img = np.random.default_rng(0).integers(0, 255, (H, W, 1), dtype=np.uint8)
    assert undistort(img, K, LENSES[0]).shape == (H, W, 1)
    assert undistort(img[..., 0], K, LENSES[0]).shape == (H, W)


def test_no_distortion_leaves_the_image_and_intrinsics_as_they_are():
    img = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)
    none = Distortion("OPENCV")
    assert none.is_identity and np.array_equal(pinhole_for(K, none, (W, H)), K)
    assert np.array_equal(undistort(img, K, none), img)


def test_masks_are_resampled_by_nearest_and_stay_boolean():
    mask = np.zeros((H, W), bool)
    mask[:, W // 2:] = True
    out = undistort(mask, K, LENSES[0], nearest=True)
    assert out.dtype == bool and set(np.unique(out)) == {False, True}
    assert out[:, :W // 2 - 8].sum() == 0 and out[:, W // 2 + 8:].all()  # the centre column barely moves


@pytest.mark.parametrize("make,message", [
    (lambda: Distortion("KANNALA"), "expected one of"),
    (lambda: Distortion("SIMPLE_RADIAL", (0.1, 0.2)), "up to 1 finite"),
    (lambda: Distortion("OPENCV", (float("nan"),)), "finite coefficients"),
    (lambda: Distortion.from_named("opencv_fisheye", {"k1": 0.1, "p2": 0.3}), "has no coefficient p2"),
    (lambda: pinhole_for(np.eye(2), LENSES[0], (W, H)), r"K expected a finite \[3, 3\]"),
    (lambda: pinhole_for(K, LENSES[0], (W, 0)), "size expected"),
    (lambda: undistort(np.zeros((H, W, 3, 2)), K, LENSES[0]), "expected an"),
    (lambda: pinhole_for(K.T, LENSES[0], (W, H)), r"\[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
    (lambda: undistort(np.zeros((H, W, 3), np.int64), K, LENSES[0]), "dtype uint8, uint16, float32, float64 or bool"),
    (lambda: undistort(np.zeros((H, W, 0), np.uint8), K, LENSES[0]), r"\(C 1..4\)"),
    (lambda: Distortion("OPENCV", 0.1), "expected a sequence of up to 5 numbers"),
    (lambda: undistort_photos(["a.jpg"], {0: K}, {3: LENSES[0]}, "."), r"photograph indices in 0..0, got \[3\]"),
    (lambda: undistort(np.zeros((H, W, 3), np.uint8), K, None), "expected a Distortion .*got NoneType"),
])
def test_bad_lenses_and_inputs_are_refused_with_what_was_expected(make, message):
    with pytest.raises(PointmapError, match=message):
        make()


def test_named_coefficients_map_to_opencvs_order():
    d = Distortion.from_named("OPENCV", {"k1": 0.1, "k2": 0.2, "p1": 0.3, "p2": 0.4, "k3": 0.5, "k4": 0})
    assert np.array_equal(d.opencv(), [0.1, 0.2, 0.3, 0.4, 0.5])
    assert np.array_equal(Distortion("RADIAL", (0.1, 0.2)).opencv(), [0.1, 0.2, 0, 0, 0])
    assert np.array_equal(Distortion("OPENCV_FISHEYE", (1, 2, 3, 4)).opencv(), [1, 2, 3, 4])


def test_undistort_photos_writes_the_distorted_ones_with_their_masks_and_leaves_the_others(tmp_path):
    from pointmap.images import read_rgb

    rng = np.random.default_rng(1)
    paths = []
    for name in ("a.png", "b.jpg"):
        cv2.imwrite(str(tmp_path / name), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        paths.append(str(tmp_path / name))
    masks = [np.zeros((H, W), bool), None]
    masks[0][20:90, 30:140] = True  # off-centre: the lens moves its edges
    new_paths, new_K, new_masks = undistort_photos(paths, {0: K, 1: K}, {0: LENSES[0]}, tmp_path / "out",
                                                   [m if m is None else m.copy() for m in masks])
    assert new_paths == [str(tmp_path / "out" / "a.png"), paths[1]]
    assert np.allclose(new_K[0], pinhole_for(K, LENSES[0], (W, H))) and np.array_equal(new_K[1], K)
    expected = undistort(read_rgb(paths[0]), K, LENSES[0])
    assert np.array_equal(read_rgb(new_paths[0]), expected)  # PNG: lossless
    assert np.array_equal(new_masks[0], undistort(masks[0], K, LENSES[0], nearest=True)) and new_masks[1] is None
    assert new_masks[0].dtype == bool and not np.array_equal(new_masks[0], masks[0])  # resampled with the photograph
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.png"]  # no temporary left behind
    with pytest.raises(PointmapError, match=r"needs its mask at its own size \[240, 320\]"):
        undistort_photos(paths, {0: K}, {0: LENSES[0]}, tmp_path / "out", [np.ones((10, 10), bool), None])
    with pytest.raises(PointmapError, match="no intrinsics"):
        undistort_photos(paths, {}, {0: LENSES[0]}, tmp_path / "out")
    rotated = K.copy()
    rotated[0, 2], rotated[1, 2] = 119.5, 300.0  # a portrait camera's K for this landscape photograph
    with pytest.raises(PointmapError, match=r"principal point at \(119.5, 300.0\), outside it"):
        undistort_photos(paths, {0: rotated}, {0: LENSES[0]}, tmp_path / "out")
    with pytest.raises(PointmapError, match="masks expected one entry .* per photograph, 2, got 1"):
        undistort_photos(paths, {0: K}, {0: LENSES[0]}, tmp_path / "out", [None])
    with pytest.raises(PointmapError, match="K and distortions expected dicts .* got NoneType and dict"):
        undistort_photos(paths, None, {0: LENSES[0]}, tmp_path / "out")
    # a re-run on the undistorted folder itself, written to the same folder: refused, the photograph kept
    before = (tmp_path / "out" / "a.png").read_bytes()
    with pytest.raises(PointmapError, match="would be overwritten by its own undistorted copy"):
        undistort_photos(new_paths, {0: K, 1: K}, {0: LENSES[0]}, tmp_path / "out")
    assert (tmp_path / "out" / "a.png").read_bytes() == before


def test_a_heic_photograph_is_undistorted_into_a_jpeg_of_its_stem(tmp_path):
    # OpenCV has no HEIC writer: imwrite raised a raw cv2.error (localize --cameras reached it)
    pillow_heif = pytest.importorskip("pillow_heif")
    from PIL import Image

    from pointmap.images import read_rgb

    pillow_heif.register_heif_opener()
    rng = np.random.default_rng(2)
    Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(tmp_path / "IMG_1.HEIC", quality=95)
    paths, _, _ = undistort_photos([str(tmp_path / "IMG_1.HEIC")], {0: K}, {0: LENSES[0]}, tmp_path / "out")
    assert paths == [str(tmp_path / "out" / "IMG_1.jpg")] and read_rgb(paths[0]).shape == (H, W, 3)
    Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(tmp_path / "IMG_1.jpg")
    with pytest.raises(PointmapError, match="would share a file name"):  # IMG_1.HEIC and IMG_1.jpg: one name
        undistort_photos([str(tmp_path / "IMG_1.HEIC"), str(tmp_path / "IMG_1.jpg")], {0: K, 1: K},
                         {0: LENSES[0], 1: LENSES[0]}, tmp_path / "out2")
