"""Unit tests of pointmap.io.colmap that pin down COLMAP's format facts the export tests leave open (tracks,
colours, per-image resize/crop, half-turn rotations, UTF-8 names, the camera model table, the reader's refusals,
the writer's refusals before any file is written). Found by a mutation review (session 90)."""

import struct
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from recon_factory import make_recon  # noqa: E402

from pointmap.errors import ConventionError, PointmapError  # noqa: E402
from pointmap.io import select_points  # noqa: E402
from pointmap.io.colmap import (  # noqa: E402
    CAMERA_MODELS,
    quaternion_to_rotation,
    read_colmap,
    rotation_to_quaternion,
    write_colmap,
)
from pointmap.io.points import PointSet  # noqa: E402

pycolmap = pytest.importorskip("pycolmap")


def _points(image, uv, seed=0):
    rng = np.random.default_rng(seed)
    m = len(image)
    return PointSet(xyz=rng.normal(size=(m, 3)), rgb=rng.integers(0, 256, (m, 3)).astype(np.uint8),
                    conf=np.ones(m, np.float32), image=np.asarray(image), uv_map=np.asarray(uv, np.float64))


def _both(recon, pts, tmp_path):
    """The model written as .bin in one folder and .txt in another, each read by pycolmap."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_colmap(recon, tmp_path / "bin", pts)
        write_colmap(recon, tmp_path / "txt", pts, text=True, binary=False)
    return pycolmap.Reconstruction(str(tmp_path / "bin")), pycolmap.Reconstruction(str(tmp_path / "txt"))


def _half_turns():
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, -1), (1, 1, 1), (-1, 2, 0.5)]
    for a in axes:
        a = np.asarray(a, float) / np.linalg.norm(a)
        for angle in (np.pi, np.pi - 1e-9, np.pi - 1e-4):
            K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            yield np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_rotations_near_a_half_turn_give_unit_quaternions_that_rebuild_them():
    for R in _half_turns():
        q = rotation_to_quaternion(R)
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12) and q[0] >= 0
        assert np.allclose(quaternion_to_rotation(q), R, atol=1e-9)


def test_read_colmap_normalises_a_quaternion_that_is_not_of_unit_length(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 80 60 70 70 40 30\n")
    (tmp_path / "images.txt").write_text("1 2 0 0 2 1 2 3 1 a.png\n\n")  # 2 * sqrt(2) * (cos 45deg, 0, 0, sin 45deg)
    c2w = read_colmap(tmp_path)["a.png"]["cam2world"]
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # a quarter turn about z
    assert np.allclose(c2w[:3, :3], R.T, atol=1e-12) and np.allclose(c2w[:3, 3], -R.T @ [1, 2, 3], atol=1e-12)


def test_each_points_track_names_the_image_and_index_of_its_one_observation(tmp_path):
    recon = make_recon(n=3)
    pts = select_points(recon, max_points=120)
    for rec in _both(recon, pts, tmp_path):
        assert rec.num_points3D() == 120
        for pid in range(1, 121):
            p = rec.points3D[pid]
            (el,) = p.track.elements
            assert rec.images[el.image_id].name == recon.names[int(pts.image[pid - 1])]
            assert rec.images[el.image_id].points2D[el.point2D_idx].point3D_id == pid
            assert np.array_equal(p.xyz, pts.xyz[pid - 1]) and np.array_equal(p.color, pts.rgb[pid - 1])


def test_binary_and_text_models_hold_the_same_cameras_poses_and_observations_to_the_last_bit(tmp_path):
    recon = make_recon(n=3)
    b, t = _both(recon, select_points(recon, max_points=60), tmp_path)
    assert sorted(b.cameras) == sorted(t.cameras) and sorted(b.images) == sorted(t.images)
    for cid in b.cameras:
        assert list(b.cameras[cid].params) == list(t.cameras[cid].params)
    for iid, im in b.images.items():
        other = t.images[iid]
        assert (im.name, im.camera_id) == (other.name, other.camera_id)
        assert np.array_equal(im.cam_from_world().matrix(), other.cam_from_world().matrix())
        assert [(tuple(p.xy), p.point3D_id) for p in im.points2D] == [(tuple(p.xy), p.point3D_id)
                                                                      for p in other.points2D]


def test_observations_follow_each_images_own_resize_and_crop_in_x_and_y(tmp_path):
    recon = make_recon(n=2)
    recon.map_from_original[0] = recon.map_from_original.new_tensor([0.5, 0.25, 3.0, 1.0])
    recon.map_from_original[1] = recon.map_from_original.new_tensor([0.2, 0.4, 0.0, 5.0])
    uv = [[4.0, 7.0], [10.0, 2.0], [4.0, 7.0], [0.0, 0.0]]
    pts = _points([0, 0, 1, 1], uv)
    for rec in _both(recon, pts, tmp_path):
        for pid, (k, (u, v)) in enumerate(zip([0, 0, 1, 1], uv), 1):
            sx, sy, left, top = recon.map_from_original[k].double().numpy()
            im = rec.images[k + 1]
            (xy,) = [p.xy for p in im.points2D if p.point3D_id == pid]
            assert np.allclose(xy, [(u + 0.5 + left) / sx, (v + 0.5 + top) / sy], atol=1e-12)


def test_an_image_with_a_single_observation_keeps_it(tmp_path):
    recon = make_recon(n=2)
    for rec in _both(recon, _points([1], [[3.0, 4.0]]), tmp_path):
        assert len(rec.images[1].points2D) == 0 and [p.point3D_id for p in rec.images[2].points2D] == [1]


def test_image_names_beyond_ascii_are_written_and_read_back_as_utf8(tmp_path):
    recon = make_recon(n=2)
    recon.names = ["café.jpg", "sub/日本.png"]
    for rec in _both(recon, _points([0, 1], [[1.0, 1.0], [2.0, 2.0]]), tmp_path):
        assert sorted(im.name for im in rec.images.values()) == sorted(recon.names)
    assert sorted(read_colmap(tmp_path / "bin")) == sorted(read_colmap(tmp_path / "txt")) == ["café.jpg", "日本.png"]


@pytest.mark.parametrize("binary", [True, False])
def test_a_name_that_cannot_be_encoded_leaves_no_half_written_images_file(tmp_path, binary):
    recon = make_recon(n=2)
    recon.names = ["a.png", "caf\udce9.png"]  # how Python reads a Latin-1 file name
    with pytest.raises(UnicodeEncodeError):
        write_colmap(recon, tmp_path, _points([0, 1], [[1.0, 1.0], [2.0, 2.0]]), binary=binary, text=not binary)
    assert not list(tmp_path.glob("images.*")) and not list(tmp_path.glob(".*"))


def test_the_camera_model_table_has_colmaps_ids_names_and_parameter_counts():
    for mid, (name, n) in CAMERA_MODELS.items():
        cam = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(mid), 100.0, 10, 10)
        assert (cam.model_name, len(cam.params)) == (name, n)


def test_a_binary_models_unused_camera_of_another_model_does_not_shift_the_cameras_after_it(tmp_path):
    fov = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(7), 100.0, 80, 60)
    cams = struct.pack("<QiiQQ", 2, 1, 7, 80, 60) + struct.pack("<5d", *fov.params)
    cams += struct.pack("<iiQQ4d", 2, 1, 80, 60, 70.0, 71.0, 40.0, 30.0)
    (tmp_path / "cameras.bin").write_bytes(cams)
    (tmp_path / "images.bin").write_bytes(struct.pack("<QI7dI", 1, 1, 1, 0, 0, 0, 0, 0, 0, 2) + b"a.png\x00"
                                          + struct.pack("<Q", 0))
    cam = read_colmap(tmp_path)["a.png"]
    assert np.allclose(cam["K"], [[70, 0, 39.5], [0, 71, 29.5], [0, 0, 1]]) and cam["size"] == (80, 60)


def test_read_colmap_finds_the_model_in_a_scene_folders_0_subfolder(tmp_path):
    recon = make_recon(n=2)
    write_colmap(recon, tmp_path / "0", _points([0], [[1.0, 1.0]]))
    assert sorted(read_colmap(tmp_path)) == sorted(recon.names)


@pytest.mark.parametrize("camera,image,said", [
    ("1 PINHOLE 80 60 70 -70 40 30", "1 1 0 0 0 0 0 0 1 a.png", "focal lengths must be positive and finite"),
    ("1 PINHOLE 80 60 70 70 nan 30", "1 1 0 0 0 0 0 0 1 a.png", "focal lengths must be positive and finite"),
    ("1 PINHOLE 80 60 70 70 40 30", "1 nan 0 0 0 0 0 0 1 a.png", "its pose is not finite"),
    ("1 PINHOLE 80 60 70 70 40 30", "1 1 0 0 0 0 inf 0 1 a.png", "its pose is not finite"),
    ("1 PINHOLE 80 60 70 70 40 30", "1 1 0 0 0 0 0 0 1", "not a readable COLMAP model \\(IndexError"),
    ("1 PINHOLE 80 60 70 70 40 30", "# no images", "the COLMAP model has no images"),
])
def test_read_colmap_refuses_a_text_model_it_cannot_use_and_says_why(tmp_path, camera, image, said):
    (tmp_path / "cameras.txt").write_text(camera + "\n")
    (tmp_path / "images.txt").write_text(image + "\n\n")
    with pytest.raises(PointmapError, match=said):
        read_colmap(tmp_path)


@pytest.mark.parametrize("name,said", [(b"a.png", "ValueError: truncated image name"),  # the file ends in the name
                                       (b"caf\xe9.png\x00" + struct.pack("<Q", 0), "UnicodeDecodeError")])
def test_read_colmap_refuses_a_binary_image_name_that_is_cut_short_or_not_utf8(tmp_path, name, said):
    (tmp_path / "cameras.bin").write_bytes(struct.pack("<QiiQQ4d", 1, 1, 1, 80, 60, 70.0, 70.0, 40.0, 30.0))
    (tmp_path / "images.bin").write_bytes(struct.pack("<QI7dI", 1, 1, 1, 0, 0, 0, 0, 0, 0, 1) + name)
    with pytest.raises(PointmapError, match=f"not a readable COLMAP model \\({said}"):
        read_colmap(tmp_path)


def _cameras(recon, tmp_path, shared_camera):
    write_colmap(recon, tmp_path, _points([0], [[1.0, 1.0]]), shared_camera=shared_camera)
    rec = pycolmap.Reconstruction(str(tmp_path))
    return [rec.images[k + 1].camera_id for k in range(len(recon))], rec.cameras


def test_images_of_one_intrinsics_but_another_size_get_their_own_camera_and_cannot_share_one(tmp_path):
    recon = make_recon(n=3)
    recon.K[:] = recon.K[0]
    recon.original_sizes = [(100, 75), (120, 90), (100, 75)]
    ids, cams = _cameras(recon, tmp_path / "a", None)
    assert ids == [1, 2, 1] and (cams[2].width, cams[2].height) == (120, 90)
    with pytest.raises(ValueError, match="shared_camera=True but the images have different intrinsics or sizes"):
        write_colmap(recon, tmp_path / "b", _points([0], [[1.0, 1.0]]), shared_camera=True)


def test_images_of_one_camera_get_one_camera_each_when_told_not_to_share(tmp_path):
    recon = make_recon(n=3)
    recon.K[:] = recon.K[0]
    assert _cameras(recon, tmp_path / "a", False)[0] == [1, 2, 3]
    assert _cameras(recon, tmp_path / "b", None)[0] == [1, 1, 1]


def test_focal_lengths_one_percent_apart_are_two_cameras(tmp_path):
    recon = make_recon(n=2)
    recon.K[1] = recon.K[0]
    recon.K[1, 0, 0] *= 1.01
    ids, cams = _cameras(recon, tmp_path, None)
    assert ids == [1, 2] and cams[2].params[0] == pytest.approx(float(recon.K[1, 0, 0]), rel=1e-7)


def test_the_paths_written_are_every_model_file_of_each_format_asked_for(tmp_path):
    written = write_colmap(make_recon(n=2), tmp_path, _points([0], [[1.0, 1.0]]), text=True)
    assert sorted(p.name for p in written) == sorted(f"{n}.{s}" for n in ("cameras", "images", "points3D")
                                                     for s in ("bin", "txt"))
    assert all(p.is_file() for p in written)


def test_text_image_names_with_a_tab_are_warned_about_like_spaces(tmp_path):
    recon = make_recon(n=2)
    recon.names = ["a\tb.png", "c.png"]
    with pytest.warns(RuntimeWarning, match="contain whitespace"):
        write_colmap(recon, tmp_path, _points([0], [[1.0, 1.0]]), text=True, binary=False)


def test_a_radial_camera_whose_coefficients_are_all_zero_reads_as_a_pinhole_camera(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 80 60 70 40 30 0\n2 OPENCV 80 60 70 70 40 30 0 0 0 0\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 2 b.png\n\n")
    cams = read_colmap(tmp_path)
    assert cams["a.png"]["distortion"] is None and cams["b.png"]["distortion"] is None


@pytest.mark.parametrize("spoil", ["nan translation", "mirrored rotation", "nan focal", "negative focal"])
def test_a_pose_or_intrinsics_changed_into_nonsense_after_the_reconstruction_was_built_is_refused_before_writing(
        spoil, tmp_path):
    recon = make_recon(n=2)
    pts = select_points(recon, max_points=20)
    if spoil == "nan translation":
        recon.cam2world[1, 0, 3] = float("nan")
    elif spoil == "mirrored rotation":
        recon.cam2world[1, :3, 0] *= -1
    elif spoil == "nan focal":
        recon.K[1, 0, 0] = float("nan")
    else:
        recon.K[1, 1, 1] = -recon.K[1, 1, 1]
    with pytest.raises(ConventionError, match=r"\[1\]"):
        write_colmap(recon, tmp_path, pts, text=True)
    assert list(tmp_path.iterdir()) == []


def test_a_name_that_cannot_be_encoded_leaves_an_earlier_model_whole(tmp_path):
    recon = make_recon(n=2)
    pts = select_points(recon, max_points=20)
    write_colmap(recon, tmp_path, pts)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    recon.names = ["x.png", "caf\udce9.png"]
    recon.K[:, 0, 0] = 500.0
    with pytest.raises(UnicodeEncodeError):
        write_colmap(recon, tmp_path, pts)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


@pytest.mark.parametrize("size", ["0 40", "60 -5"])
def test_read_colmap_refuses_a_camera_without_a_positive_size(size, tmp_path):
    (tmp_path / "cameras.txt").write_text(f"1 PINHOLE {size} 70 70 30 20\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(PointmapError, match="size"):
        read_colmap(tmp_path)


def test_read_colmap_refuses_a_camera_id_given_twice(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 60 40 70 70 30 20\n1 PINHOLE 60 40 90 90 30 20\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(PointmapError, match="camera id 1 appears twice"):
        read_colmap(tmp_path)


def test_write_colmap_images_refuses_a_source_list_of_another_length_than_the_names(tmp_path):
    from pointmap.io.colmap import write_colmap_images

    with pytest.raises(ValueError, match="one source per name, got 1 and 2"):
        write_colmap_images([None], ["a.png", "b.png"], tmp_path)
