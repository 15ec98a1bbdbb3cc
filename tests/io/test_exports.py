"""Exports read back by independent readers (pycolmap, trimesh) and checked against their sources."""

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from recon_factory import make_recon  # noqa: E402

from pointmap.io import confidence_mask, load_npz, read_ply, save_reconstruction, select_points  # noqa: E402
from pointmap.io.atomic import atomic_open  # noqa: E402
from pointmap.io.colmap import rotation_to_quaternion  # noqa: E402
from pointmap.io.glb import frustum_lines  # noqa: E402

pycolmap = pytest.importorskip("pycolmap")


def _check_colmap(model_dir, recon):
    rec = pycolmap.Reconstruction(str(model_dir))
    assert rec.num_images() == len(recon) and rec.num_points3D() > 0
    names = sorted(im.name for im in rec.images.values())
    assert names == sorted(recon.names)
    worst = 0.0
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (100, 75)
        k = recon.names.index(im.name)
        # pose: COLMAP cam_from_world is the inverse of our cam2world
        M = np.asarray(im.cam_from_world().matrix())
        w2c = np.linalg.inv(recon.cam2world[k].double().numpy())
        assert np.allclose(M, w2c[:3], atol=1e-6)
        if len(im.points2D) == 0:
            continue
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in im.points2D])
        xy = np.array([p.xy for p in im.points2D])
        uv = cam.img_from_cam((xyz @ M[:, :3].T + M[:, 3]))
        worst = max(worst, float(np.abs(uv - xy).max()))
    assert worst < 1.0 and worst < 1e-3  # well inside the 1 px contract
    return rec


def test_colmap_binary_reprojects_at_original_resolution(tmp_path):
    recon = make_recon()
    written = save_reconstruction(recon, tmp_path, formats=("colmap",), colmap_max_points=None)
    assert {p.name for p in written["colmap"]} == {"cameras.bin", "images.bin", "points3D.bin"}
    rec = _check_colmap(tmp_path / "sparse" / "0", recon)
    assert rec.num_points3D() == int(recon.valid().sum())
    # an independent check of the pixel convention: the observation of the point from map pixel (u, v)
    # of image k is the ORIGINAL pixel (u + 0.5 + left) / sx - 0.5, plus COLMAP's 0.5 offset
    pts = select_points(recon)
    k, (u, v) = int(pts.image[100]), pts.uv_map[100]
    im = [im for im in rec.images.values() if im.name == recon.names[k]][0]
    obs = [p for p in im.points2D if np.allclose(rec.points3D[p.point3D_id].xyz, pts.xyz[100])][0]
    assert np.allclose(obs.xy, [(u + 0.5 + 2.0) / 0.36, (v + 0.5 + 1.0) / 0.36], atol=1e-9)
    # and with our own projection using K in original pixels
    w2c = np.linalg.inv(recon.cam2world[k].double().numpy())
    pc = w2c[:3, :3] @ pts.xyz[100] + w2c[:3, 3]
    K = recon.K[k].double().numpy()
    assert np.allclose(K[:2, :2] @ (pc[:2] / pc[2]) + K[:2, 2] + 0.5, obs.xy, atol=1e-4)


def test_colmap_text_only_is_readable_and_has_two_lines_per_image(tmp_path):
    recon = make_recon(n=4, seed=1)
    save_reconstruction(recon, tmp_path, formats=("colmap_txt",), colmap_max_points=500)
    model = tmp_path / "sparse" / "0"
    assert not (model / "images.bin").exists()
    lines = [ln for ln in (model / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 2 * 4
    rec = _check_colmap(model, recon)
    assert rec.num_points3D() == 500


def test_colmap_text_warns_of_image_names_with_spaces_which_colmaps_text_readers_cut(tmp_path):
    recon = make_recon(n=2, seed=1)
    recon.names = ["IMG 0001.jpg", "b.png"]
    with pytest.warns(RuntimeWarning, match=r"images.txt: 1 image name\(s\) contain whitespace \(e.g. 'IMG 0001.jpg'\)"
                                            r".* use the binary model"):
        save_reconstruction(recon, tmp_path, formats=("colmap_txt",), colmap_max_points=50)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save_reconstruction(recon, tmp_path / "bin", formats=("colmap",), colmap_max_points=50)  # binary: exact


def test_colmap_shared_camera_and_empty_observations(tmp_path):
    recon = make_recon(n=3)
    recon.K[:] = recon.K[0]
    recon.masks = torch.zeros_like(recon.conf, dtype=torch.bool)
    recon.masks[0, 5:10, 5:10] = True  # only image 0 has points
    save_reconstruction(recon, tmp_path, formats=("colmap", "colmap_txt"))
    rec = _check_colmap(tmp_path / "sparse" / "0", recon)
    assert len(rec.cameras) == 1 and rec.num_points3D() == 25
    lines = [ln for ln in (tmp_path / "sparse/0/images.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 6 and lines[3] == "" and lines[5] == ""


def test_colmap_writes_one_camera_per_distinct_intrinsics_and_size_unless_told_one_per_image(tmp_path):
    recon = make_recon(n=4)
    recon.K[2] = recon.K[0]  # images 0 and 2 of one camera, 1 and 3 of another
    recon.K[1, 0, 0] = recon.K[1, 1, 1] = recon.K[0, 0, 0] * 1.3
    recon.K[3] = recon.K[1]
    save_reconstruction(recon, tmp_path / "a", formats=("colmap",))
    rec = _check_colmap(tmp_path / "a" / "sparse" / "0", recon)
    assert len(rec.cameras) == 2 and [rec.images[k + 1].camera_id for k in range(4)] == [1, 2, 1, 2]
    assert rec.cameras[2].params[0] == pytest.approx(float(recon.K[1, 0, 0]), rel=1e-6)
    save_reconstruction(recon, tmp_path / "b", formats=("colmap",), shared_camera=False)
    assert len(_check_colmap(tmp_path / "b" / "sparse" / "0", recon).cameras) == 4


def test_ply_roundtrip_and_trimesh(tmp_path):
    import trimesh

    recon = make_recon()
    save_reconstruction(recon, tmp_path, formats=("ply",), min_conf=3.0)
    data = read_ply(tmp_path / "points.ply")
    keep = recon.valid() & (recon.conf > 3.0)
    assert len(data["x"]) == int(keep.sum()) and float(data["confidence"].min()) > 3.0
    pts = recon.pts_world[keep].numpy()
    assert np.allclose(np.stack([data["x"], data["y"], data["z"]], -1), pts, atol=1e-5)
    rgb = (recon.images[keep].numpy() * 255).round().astype(np.uint8)
    assert np.array_equal(np.stack([data["red"], data["green"], data["blue"]], -1), rgb)
    cloud = trimesh.load(tmp_path / "points.ply")
    assert len(cloud.vertices) == len(pts)
    header = (tmp_path / "points.ply").read_bytes()[:400]
    assert b"binary_little_endian" in header and b"property float confidence" in header


def test_glb_has_cloud_and_frustums(tmp_path):
    import trimesh

    recon = make_recon(n=3)
    save_reconstruction(recon, tmp_path, formats=("glb",), max_points=1000)
    scene = trimesh.load(tmp_path / "scene.glb")
    geoms = list(scene.geometry.values())
    clouds = [g for g in geoms if isinstance(g, trimesh.PointCloud)]
    paths = [g for g in geoms if isinstance(g, trimesh.path.Path3D)]
    assert len(clouds) == 1 and len(clouds[0].vertices) == 1000
    assert len(paths) == 3
    # glTF axes, (x, -y, -z) of the world: each frustum's apex is its camera centre so turned
    flip = np.array([1.0, -1.0, -1.0])
    centres = recon.cam2world[:, :3, 3].numpy() * flip
    for c in centres:
        assert min(np.linalg.norm(p.vertices - c, axis=1).min() for p in paths) < 1e-4
    pts = select_points(recon, max_points=1000)
    assert np.allclose(np.asarray(clouds[0].vertices), pts.xyz * flip, atol=1e-5)


def test_frustum_corners_are_the_image_corners_rays_through_k_inverse_moved_by_a_turned_camera():
    from pointmap.geometry import axis_angle_to_matrix

    c2w = np.eye(4)
    c2w[:3, :3] = axis_angle_to_matrix(torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)).numpy()
    c2w[:3, 3] = [1.0, -2.0, 0.5]
    K = np.array([[300.0, 0, 170.0], [0, 250.0, 110.0], [0, 0, 1]])  # fx != fy, principal point off centre
    segs = frustum_lines(c2w, K, (320, 240), 0.7)
    corners = [(-0.5, -0.5), (319.5, -0.5), (319.5, 239.5), (-0.5, 239.5)]
    for k, (u, v) in enumerate(corners):  # the slow reference: K^-1 [u, v, 1] at depth 0.7, into the world
        want = c2w[:3, :3] @ (np.linalg.inv(K) @ np.array([u, v, 1.0]) * 0.7) + c2w[:3, 3]
        assert np.allclose(segs[k], [c2w[:3, 3], want], atol=1e-12)  # apex to corner
        assert np.allclose(segs[4 + k], [want, segs[(k + 1) % 4][1]], atol=1e-12)  # the image's rectangle


def test_the_glbs_frustums_stand_a_twentieth_of_the_clouds_extent_in_front_of_each_camera(tmp_path):
    import trimesh

    recon = make_recon(n=3)
    save_reconstruction(recon, tmp_path, formats=("glb",), max_points=1000)
    geoms = list(trimesh.load(tmp_path / "scene.glb").geometry.values())
    cloud = [g for g in geoms if isinstance(g, trimesh.PointCloud)][0]
    depth = 0.05 * np.linalg.norm(np.ptp(np.asarray(cloud.vertices), axis=0))  # the default frustum_scale
    flip = np.array([1.0, -1.0, -1.0])
    for path in (g for g in geoms if isinstance(g, trimesh.path.Path3D)):
        world = np.asarray(path.vertices) * flip
        k = int(np.argmin([np.linalg.norm(world - c, axis=1).min() for c in recon.cam2world[:, :3, 3].numpy()]))
        w2c = np.linalg.inv(recon.cam2world[k].double().numpy())
        z = world @ w2c[:3, :3].T + w2c[:3, 3]
        corners = z[np.linalg.norm(z, axis=1) > 1e-6]
        assert len(corners) and np.allclose(corners[:, 2], depth, rtol=1e-4)


def test_in_the_glb_image_0s_camera_looks_along_minus_z_with_its_image_upright(tmp_path):
    import trimesh

    recon = make_recon(n=1)
    recon.cam2world = torch.eye(4)[None]  # the default world: image 0's camera (OpenCV: looks along +z, top at -y)
    save_reconstruction(recon, tmp_path, formats=("glb",))
    path = [g for g in trimesh.load(tmp_path / "scene.glb").geometry.values() if isinstance(g, trimesh.path.Path3D)][0]
    v = np.asarray(path.vertices)
    corners = np.unique(v[np.linalg.norm(v, axis=1) > 1e-6].round(9), axis=0)  # the apex is the origin
    assert len(corners) == 4  # the image's corners
    view = corners.mean(0) / np.linalg.norm(corners.mean(0))
    assert view[2] < -0.99  # seen along -z, glTF's forward
    by_height = corners[np.argsort(corners[:, 1])]
    assert (by_height[2:, 1] > 0).all() and (by_height[:2, 1] < 0).all()
    # the upper two are the image's top corners (pixel row -0.5: OpenCV y < 0 in the camera)
    top = frustum_lines(np.eye(4), recon.K[0].double().numpy(), recon.original_sizes[0], 1.0)[:2, 1]
    assert (top[:, 1] < 0).all()
    unit = lambda x: x / np.linalg.norm(x, axis=1, keepdims=True)  # noqa: E731
    upper = unit(by_height[2:])
    for corner in unit(top * np.array([1.0, -1.0, -1.0])):
        assert np.abs(upper - corner).sum(1).min() < 1e-6


def test_npz_roundtrip(tmp_path):
    recon = make_recon(with_mask=True)
    save_reconstruction(recon, tmp_path, formats=("npz",))
    back = load_npz(tmp_path / "reconstruction.npz")
    for name in ("images", "cam2world", "K", "depth_z", "conf", "map_from_original", "masks"):
        assert torch.equal(getattr(back, name), getattr(recon, name)), name
    assert back.names == recon.names and back.original_sizes == recon.original_sizes
    assert back.info["align"]["final_loss"] == 0.1


def test_recon_save_all_formats_and_no_temp_files(tmp_path):
    recon = make_recon()
    written = recon.save(tmp_path, formats=("ply", "glb", "colmap", "npz"))
    assert set(written) == {"ply", "glb", "colmap", "npz"}
    leftovers = [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert not leftovers
    with pytest.raises(ValueError, match="formats expected"):
        recon.save(tmp_path, formats=("obj",))


def test_saving_points_that_no_pixel_passes_warns_that_the_clouds_are_empty_and_the_npz_alone_does_not(tmp_path):
    import warnings

    recon = make_recon()
    top = float(recon.conf.max())
    with pytest.warns(UserWarning, match=rf"no point passes .*min_conf={top}.*: colmap, ply hold an empty point cloud"):
        written = recon.save(tmp_path / "a", formats=("ply", "colmap", "npz"), min_conf=top)
    assert set(written) == {"ply", "colmap", "npz"}  # written all the same: the cameras are there
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        recon.save(tmp_path / "b", formats=("npz",), min_conf=top)  # no points in it: nothing to warn about
        recon.save(tmp_path / "c", formats=("ply",))


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "x.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_open(target) as f:
            f.write(b"partial")
            raise RuntimeError("boom")
    assert target.read_bytes() == b"old" and len(list(tmp_path.iterdir())) == 1


def test_confidence_thresholds_keep_what_they_say_and_refuse_a_nan_threshold_that_would_keep_nothing():
    conf = torch.arange(1, 101, dtype=torch.float32).reshape(1, 10, 10)
    assert int(confidence_mask(conf, min_conf=50).sum()) == 50
    assert int(confidence_mask(conf, percentile=90).sum()) == 10  # >= the 90th percentile (90.1)
    assert int(confidence_mask(conf, min_conf=95, percentile=50).sum()) == 5
    with pytest.raises(ValueError, match=r"percentile expected a percentile in \[0, 100\), got 100"):
        confidence_mask(conf, percentile=100)
    assert int(confidence_mask(conf, min_conf=torch.tensor(50.0), percentile=np.float32(0)).sum()) == 50
    for bad in (float("nan"), True, "3", torch.tensor([3.0])):
        with pytest.raises(ValueError, match="min_conf expected a finite confidence"):
            confidence_mask(conf, min_conf=bad)
    with pytest.raises(ValueError, match="min_conf expected a finite confidence"):
        select_points(make_recon(n=2), min_conf=float("nan"))


def test_a_confidence_percentile_is_taken_over_the_pixels_a_mask_keeps_not_over_the_masked_ones():
    conf = torch.arange(1, 101, dtype=torch.float32).reshape(1, 10, 10)
    within = torch.zeros(1, 10, 10, dtype=torch.bool)
    within[..., 5:] = True  # 50 pixels
    conf[~within] = 0  # as the pipeline leaves masked pixels
    keep = confidence_mask(conf, percentile=50, within=within)
    assert int(keep.sum()) == 25 and not keep[~within].any()  # half of the 50, none outside
    assert int(confidence_mask(conf, percentile=50).sum()) == 50  # over all 100 pixels the zeros count
    with pytest.raises(ValueError, match=r"within expected a bool tensor of conf's shape \(1, 10, 10\)"):
        confidence_mask(conf, percentile=50, within=within[0])
    recon = make_recon(n=2, with_mask=True)  # the left half of every view masked, one pixel without depth
    eligible = int(recon.valid().sum())
    assert len(select_points(recon, conf_percentile=50).xyz) == eligible - eligible // 2


@pytest.mark.parametrize("cap", [-1, 0, 2.5, True, "5"])
def test_a_point_cap_that_is_not_a_positive_int_is_refused_before_anything_is_written(tmp_path, cap):
    recon = make_recon(n=2)
    for kw in ({"max_points": cap}, {"colmap_max_points": cap}):
        with pytest.raises(ValueError, match=f"{next(iter(kw))} expected None \\(all points\\) or an int >= 1"):
            save_reconstruction(recon, tmp_path / "out", formats=("ply", "colmap"), **kw)
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="max_points expected None"):
        select_points(recon, max_points=cap)
    assert len(select_points(recon, max_points=7).xyz) == 7


def test_quaternion_matches_rotation():
    from pointmap.geometry.rotations import random_rotation

    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        R = random_rotation(g).numpy()
        w, x, y, z = rotation_to_quaternion(R)
        Rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                       [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                       [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        assert np.allclose(Rq, R, atol=1e-12) and w >= 0


def test_a_path_writer_that_fails_leaves_neither_the_target_nor_a_temp_file(tmp_path):
    from pointmap.atomic import atomic_path

    target = tmp_path / "model.safetensors"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert tmp.suffix == ".safetensors" and tmp.parent == tmp_path
            tmp.write_bytes(b"half")
            raise RuntimeError("writer crashed")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole" and (target.stat().st_mode & 0o777) == 0o666 & ~_umask()


def _umask():
    import os

    m = os.umask(0)
    os.umask(m)
    return m


def test_io_tests_run_single_threaded():
    import torch

    assert torch.get_num_threads() == 1


def test_colmap_export_puts_the_photographs_beside_the_model_upright_and_under_the_models_names(tmp_path):
    from PIL import Image

    recon = make_recon(n=3)
    rng = np.random.default_rng(0)
    src = tmp_path / "src"
    src.mkdir()
    pixels = rng.integers(0, 255, (75, 100, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(src / "plain.JPG", quality=90)
    portrait = Image.fromarray(rng.integers(0, 255, (100, 75, 3), dtype=np.uint8))  # stored sideways + EXIF 6
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to view
    portrait.transpose(Image.Transpose.ROTATE_90).save(src / "rotated.jpg", exif=exif, quality=90)
    Image.fromarray(pixels).save(src / "dup.png")
    recon.names = ["plain.JPG", "rotated.jpg", "dup_1.png"]
    recon.info["sources"] = [str(src / "plain.JPG"), str(src / "rotated.jpg"), str(src / "dup.png")]
    written = save_reconstruction(recon, tmp_path / "out", formats=("colmap",))
    images = tmp_path / "out" / "images"
    assert sorted(p.name for p in written["colmap_images"]) == sorted(recon.names)
    assert (images / "plain.JPG").read_bytes() == (src / "plain.JPG").read_bytes()  # upright: copied as is
    assert (images / "dup_1.png").read_bytes() == (src / "dup.png").read_bytes()
    with Image.open(images / "rotated.jpg") as im:  # rotated: written upright, the pixels load_images saw
        assert im.size == (75, 100) and im.getexif().get(0x0112, 1) == 1
    assert not list(images.glob(".*"))  # no temporary files left
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert all((images / im.name).exists() for im in rec.images.values())


def test_images_given_as_arrays_are_not_written(tmp_path):
    recon = make_recon(n=2)
    recon.info["sources"] = [None, None]
    written = save_reconstruction(recon, tmp_path / "out", formats=("colmap",))
    assert "colmap_images" not in written and not (tmp_path / "out" / "images").exists()


def test_nerfstudio_transforms_reproject_every_point_onto_its_original_pixel_in_nerfstudios_convention(tmp_path):
    import json

    recon = make_recon(n=3)
    written = save_reconstruction(recon, tmp_path, formats=("nerfstudio",), colmap_max_points=500)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert written["nerfstudio"] == [tmp_path / "transforms.json", tmp_path / "sparse_pc.ply"]
    assert meta["ply_file_path"] == "sparse_pc.ply" and len(read_ply(tmp_path / "sparse_pc.ply")["x"]) == 500
    pts = select_points(recon)
    sx, sy, left, top = recon.map_from_original[0].double().numpy()  # the same transform for every image
    worst = 0.0
    for k, frame in enumerate(meta["frames"]):
        assert frame["file_path"] == f"images/{recon.names[k]}" and (frame["w"], frame["h"]) == (100, 75)
        # nerfstudio's camera: ray through pixel coordinate (i + 0.5, j + 0.5) has direction
        # ((u - cx) / fx, -(v - cy) / fy, -1) in OpenGL camera axes, rotated by transform_matrix
        T = np.asarray(frame["transform_matrix"])
        sel = pts.image == k
        cam = (pts.xyz[sel] - T[:3, 3]) @ T[:3, :3]  # world -> OpenGL camera
        u = frame["fl_x"] * cam[:, 0] / -cam[:, 2] + frame["cx"]
        v = -frame["fl_y"] * cam[:, 1] / -cam[:, 2] + frame["cy"]
        u_orig = (pts.uv_map[sel, 0] + 0.5 + left) / sx - 0.5  # our convention: pixel centres at integers
        v_orig = (pts.uv_map[sel, 1] + 0.5 + top) / sy - 0.5
        worst = max(worst, float(np.abs(u - (u_orig + 0.5)).max()), float(np.abs(v - (v_orig + 0.5)).max()))
    assert worst < 1e-3, worst


def test_read_transforms_inverts_the_export_and_reads_global_and_angle_intrinsics(tmp_path):
    import json

    from pointmap.io.nerfstudio import read_transforms

    recon = make_recon(n=3)
    save_reconstruction(recon, tmp_path, formats=("nerfstudio",))
    cams = read_transforms(tmp_path / "transforms.json")
    assert list(cams) == recon.names
    for k, name in enumerate(recon.names):
        assert np.allclose(cams[name]["K"], recon.K[k].double().numpy(), atol=1e-9)
        assert np.allclose(cams[name]["cam2world"], recon.cam2world[k].double().numpy(), atol=1e-6)
        assert cams[name]["size"] == (100, 75)
    # instant-ngp style: one global camera given by its horizontal field of view, centred principal point
    T = np.eye(4).tolist()
    meta = {"camera_angle_x": 2 * np.arctan(0.5), "w": 80, "h": 60, "frames": [{"file_path": "./a/b.png",
                                                                              "transform_matrix": T}]}
    (tmp_path / "ngp.json").write_text(json.dumps(meta))
    K = read_transforms(tmp_path / "ngp.json")["b.png"]["K"]
    assert np.allclose(K, [[80.0, 0, 39.5], [0, 80.0, 29.5], [0, 0, 1]])


def test_read_colmap_inverts_our_binary_and_text_export(tmp_path):
    from pointmap.io.colmap import read_colmap

    recon = make_recon(n=3)
    save_reconstruction(recon, tmp_path, formats=("colmap", "colmap_txt"))
    from_bin = read_colmap(tmp_path)  # the scene folder: its sparse/0 is found
    for f in ("cameras.bin", "images.bin"):
        (tmp_path / "sparse" / "0" / f).unlink()
    from_txt = read_colmap(tmp_path / "sparse" / "0" / "cameras.txt")
    for cams in (from_bin, from_txt):
        assert list(cams) == recon.names
        for k, name in enumerate(recon.names):
            assert np.allclose(cams[name]["K"], recon.K[k].double().numpy(), atol=1e-9)
            assert np.allclose(cams[name]["cam2world"], recon.cam2world[k].double().numpy(), atol=1e-6)
            assert cams[name]["size"] == (100, 75) and cams[name]["distortion"] is None


@pytest.mark.parametrize("model,params,lens", [
    ("OPENCV", [70, 71, 40, 30, -0.1, 0.02, 0.001, -0.002], ("OPENCV", (-0.1, 0.02, 0.001, -0.002))),
    ("SIMPLE_RADIAL", [70, 40, 30, -0.05], ("SIMPLE_RADIAL", (-0.05,))),
    ("FULL_OPENCV", [70, 71, 40, 30, -0.1, 0.02, 0.001, -0.002, 0.01, 0.1, 0, 0.02],
     ("FULL_OPENCV", (-0.1, 0.02, 0.001, -0.002, 0.01, 0.1, 0, 0.02))),
    ("OPENCV_FISHEYE", [70, 71, 40, 30, 0.03, -0.01, 0.002, 0.0], ("OPENCV_FISHEYE", (0.03, -0.01, 0.002, 0.0))),
    ("RADIAL_FISHEYE", [70, 40, 30, 0.03, -0.01], ("OPENCV_FISHEYE", (0.03, -0.01))),
    ("PINHOLE", [70, 71, 40, 30], None),
    ("RADIAL", [70, 40, 30, -0.05, 0.01], ("RADIAL", (-0.05, 0.01))),  # k1 before k2
    ("SIMPLE_PINHOLE", [70, 40, 30], None),
    ("SIMPLE_RADIAL_FISHEYE", [70, 40, 30, 0.03], ("OPENCV_FISHEYE", (0.03,))),
])
def test_read_colmap_reads_the_cameras_and_lenses_pycolmap_writes(tmp_path, model, params, lens):
    from pointmap.io.colmap import read_colmap
    from pointmap.undistort import Distortion

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=80, height=60, params=params, camera_id=1))
    q = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])  # x, y, z, w (Eigen's order)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(q), np.array([0.5, -0.2, 1.0]))
    rec.add_image_with_trivial_frame(pycolmap.Image(name="sub/a.png", camera_id=1, image_id=1), pose)
    w2c = np.vstack([rec.image(1).cam_from_world().matrix(), [0, 0, 0, 1]])
    f = params[0]
    fy, cx, cy = (params[1], params[2], params[3]) if model in ("OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE",
                                                                "PINHOLE") else (f, params[1], params[2])
    for kind in ("bin", "txt"):
        (tmp_path / kind).mkdir()
        getattr(rec, "write_binary" if kind == "bin" else "write_text")(str(tmp_path / kind))
        cam = read_colmap(tmp_path / kind)["a.png"]
        assert np.allclose(cam["K"], [[f, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])  # COLMAP: centres at +0.5
        assert np.allclose(cam["cam2world"], np.linalg.inv(w2c), atol=1e-9) and cam["size"] == (80, 60)
        assert cam["distortion"] == (None if lens is None else Distortion(*lens))


def test_read_colmap_text_parses_as_colmap_does_blank_lines_comments_and_names_with_spaces(tmp_path):
    from pointmap.io.colmap import read_colmap

    (tmp_path / "cameras.txt").write_text("  # indented comment\n\n1 SIMPLE_RADIAL_FISHEYE 80 60 70 40 30 0\n\n")
    (tmp_path / "images.txt").write_text(
        "# header\n\n1 1 0 0 0 0 0 0 1 my photo.png  \n10 20 -1\n  # between images\n"
        "2 1 0 0 0 1 2 3 1 sub/b.png\n\n\n\n")
    cams = read_colmap(tmp_path / "cameras.txt")
    assert sorted(cams) == ["b.png", "my photo.png"]
    assert np.allclose(cams["b.png"]["cam2world"][:3, 3], [-1, -2, -3])
    assert cams["b.png"]["distortion"] is not None  # a fisheye with k = 0 is still a fisheye


def test_read_colmap_reads_the_text_model_when_its_cameras_txt_is_named_beside_a_binary_one(tmp_path):
    from pointmap.io.colmap import read_colmap

    recon = make_recon(n=2)
    save_reconstruction(recon, tmp_path, formats=("colmap", "colmap_txt"))
    model = tmp_path / "sparse" / "0"
    text = (model / "cameras.txt").read_text().splitlines()
    (model / "cameras.txt").write_text("\n".join(
        " ".join(t.split()[:4] + ["123.0"] + t.split()[5:]) if t and not t.startswith("#") else t for t in text))
    assert read_colmap(model / "cameras.txt")[recon.names[0]]["K"][0, 0] == 123.0
    assert read_colmap(model)[recon.names[0]]["K"][0, 0] != 123.0  # the folder: the binary model


def test_read_colmap_refuses_what_it_cannot_use_and_says_why(tmp_path):
    from pointmap.errors import PointmapError
    from pointmap.io.colmap import read_colmap

    with pytest.raises(PointmapError, match="expected a COLMAP sparse model folder"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 FOV 80 60 70 70 40 30 0.5\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(PointmapError, match="COLMAP camera model FOV is not one pointmap can undistort"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 80 60 70 70 40\n")
    with pytest.raises(PointmapError, match=r"camera 1 \(PINHOLE\) has 3 parameters"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("2 PINHOLE 80 60 70 70 40 30\n")
    with pytest.raises(PointmapError, match="refers to camera 1, which cameras.txt lacks"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 80 60 70 70 40 30\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 x/a.png\n\n2 1 0 0 0 0 0 0 1 y/a.png\n\n")
    with pytest.raises(PointmapError, match="two images are named a.png"):
        read_colmap(tmp_path)
    (tmp_path / "images.txt").write_text("1 one 0 0 0\n")
    with pytest.raises(PointmapError, match="not a readable COLMAP model"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.bin").write_bytes(b"\x05")
    (tmp_path / "images.bin").write_bytes(b"")
    with pytest.raises(PointmapError, match="not a readable COLMAP model"):
        read_colmap(tmp_path)
    import struct

    (tmp_path / "cameras.bin").write_bytes(struct.pack("<QiiQQ", 1, 1, 42, 80, 60))
    with pytest.raises(PointmapError, match="COLMAP camera model id 42 is not one pointmap can undistort"):
        read_colmap(tmp_path)


def test_read_transforms_reads_opencv_and_fisheye_lens_distortion_per_frame_or_global(tmp_path):
    import json

    from pointmap.io.nerfstudio import read_transforms
    from pointmap.undistort import Distortion

    T = np.eye(4).tolist()
    cam = {"fl_x": 50.0, "fl_y": 50.0, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30}
    meta = {"camera_model": "OPENCV", "k1": -0.1, "p2": 0.002, **cam, "frames": [
        {"file_path": "a.png", "transform_matrix": T},
        {"file_path": "b.png", "transform_matrix": T, "camera_model": "OPENCV_FISHEYE", "k1": 0.03, "k4": 0.001,
         "p2": 0},
        {"file_path": "c.png", "transform_matrix": T, "k1": 0, "p2": 0},
        {"file_path": "d.png", "transform_matrix": T, "camera_model": "OPENCV_FISHEYE", "k1": 0, "p2": 0}]}
    (tmp_path / "t.json").write_text(json.dumps(meta))
    cams = read_transforms(tmp_path / "t.json")
    assert cams["a.png"]["distortion"] == Distortion("OPENCV", (-0.1, 0, 0, 0.002, 0))
    assert cams["b.png"]["distortion"] == Distortion("OPENCV_FISHEYE", (0.03, 0, 0, 0.001))
    assert cams["c.png"]["distortion"] is None  # all zero: a pinhole camera
    assert cams["d.png"]["distortion"] == Distortion("OPENCV_FISHEYE")  # all zero, yet a fisheye


@pytest.mark.parametrize("change,message", [
    ({"camera_model": "EQUIRECTANGULAR"}, "has a EQUIRECTANGULAR camera"),
    ({"k4": 0.1}, "OPENCV has no coefficient k4"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "OPENCV_FISHEYE has no coefficient p1"),
    ({"k1": 0.1, "fl_x": None, "fl_y": None}, "states lens distortion but no focal length"),
    ({"transform_matrix": (2 * np.eye(4)).tolist()}, "must be a rigid"),
    ({"transform_matrix": None}, "lacks 'file_path' or 'transform_matrix'"),
    ({"fl_x": -3.0}, "focal lengths must be positive"),
    ({"w": "abc"}, "an intrinsics field .* is not a number"),
    ({"transform_matrix": "eye"}, "must be a rigid \\[4, 4\\] camera-to-world matrix, got 'eye'"),
    ({"transform_matrix": [[1, 0, 0, 0], [0, 1, 0]]}, "must be a rigid"),
    ({"fl_x": None, "fl_y": None, "camera_angle_x": 0}, "camera_angle_x expected a field of view in radians"),
    ({"fl_x": None, "fl_y": None, "w": None, "camera_angle_x": 4.0}, "camera_angle_x expected a field of view"),
])
def test_read_transforms_refuses_what_pointmap_cannot_use_and_says_why(tmp_path, change, message):
    import json

    from pointmap.errors import PointmapError
    from pointmap.io.nerfstudio import read_transforms

    frame = {"file_path": "images/x.png", "transform_matrix": np.eye(4).tolist(), "fl_x": 50.0, "fl_y": 50.0,
             "cx": 20.0, "cy": 15.0, "w": 40, "h": 30, **change}
    frame = {k: v for k, v in frame.items() if v is not None}
    (tmp_path / "t.json").write_text(json.dumps({"frames": [frame]}))
    with pytest.raises(PointmapError, match=message):
        read_transforms(tmp_path / "t.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(PointmapError, match="not a readable transforms.json"):
        read_transforms(tmp_path / "bad.json")



def test_read_transforms_refuses_two_frames_of_one_image_name_as_read_colmap_does(tmp_path):
    import json

    from pointmap.errors import PointmapError
    from pointmap.io.nerfstudio import read_transforms

    frame = {"transform_matrix": np.eye(4).tolist(), "fl_x": 50.0, "w": 40, "h": 30}
    (tmp_path / "two.json").write_text(json.dumps({"frames": [dict(frame, file_path=p) for p in ("x/a.png", "y/a.png")]}))
    with pytest.raises(PointmapError, match="two frames have the image name 'a.png' \\(frame 1: y/a.png\\)"):
        read_transforms(tmp_path / "two.json")


def test_a_photograph_that_no_longer_exists_is_skipped_with_a_warning(tmp_path):
    from PIL import Image

    recon = make_recon(n=2)
    Image.fromarray(np.zeros((75, 100, 3), np.uint8)).save(tmp_path / "here.png")
    recon.names = ["here.png", "gone.png"]
    recon.info["sources"] = [str(tmp_path / "here.png"), str(tmp_path / "gone.png")]
    with pytest.warns(UserWarning, match="gone.png no longer exists"):
        written = save_reconstruction(recon, tmp_path / "out", formats=("colmap",))
    assert [p.name for p in written["colmap_images"]] == ["here.png"]
    assert (tmp_path / "out" / "sparse" / "0" / "images.bin").exists()
    (tmp_path / "gone.png").write_bytes(b"replaced by something that is no image")
    with pytest.warns(UserWarning, match="gone.png cannot be read .*gone.png not written"):
        written = save_reconstruction(recon, tmp_path / "out2", formats=("colmap",))
    assert [p.name for p in written["colmap_images"]] == ["here.png"]


def test_tum_trajectory_lines_give_back_each_camera_to_world_pose(tmp_path):
    from scipy.spatial.transform import Rotation  # an independent reader of (x, y, z, w) quaternions

    recon = make_recon(n=3)
    path = save_reconstruction(recon, tmp_path, formats=("tum",))["tum"]
    rows = [ln.split() for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 3
    for k, row in enumerate(rows):
        t, tx, ty, tz, qx, qy, qz, qw = map(float, row)
        R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        assert t == k
        assert np.allclose([tx, ty, tz], recon.cam2world[k, :3, 3].numpy(), atol=1e-6)
        assert np.allclose(R, recon.cam2world[k, :3, :3].double().numpy(), atol=1e-6)


def _fields(**change):
    recon = make_recon(n=2)
    kw = {k: getattr(recon, k) for k in ("images", "cam2world", "K", "depth_z", "conf", "map_from_original",
                                         "original_sizes", "names", "masks")}
    return {**kw, **change}


@pytest.mark.parametrize("change,message", [
    ({"names": ["a.png"]}, "names expected 2 non-empty strings"),
    ({"names": ["a.png", "a.png"]}, "names expected to be unique .*\\['a.png'\\]"),
    ({"masks": torch.ones(2, 24, 32)}, "masks expected dtype bool"),
    ({"K": torch.zeros(2, 3, 3)}, "K expected finite pinhole intrinsics .* with fx, fy > 0, got K\\[0\\]"),
    ({"K": torch.tensor([[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [15.5, 11.5, 1.0]]).expand(2, 3, 3)},
     "K expected finite pinhole intrinsics"),  # transposed
    ({"K": torch.tensor([[40.0, 8.0, 15.5], [0.0, 40.0, 11.5], [0.0, 0.0, 1.0]]).expand(2, 3, 3)},
     "K expected finite pinhole intrinsics \\[\\[fx, 0, cx\\]"),  # a skew: COLMAP's PINHOLE and the rest dropped it
    ({"cam2world": torch.zeros(2, 4, 4)}, "cam2world expected rigid"),
    ({"cam2world": 2 * torch.eye(4).repeat(2, 1, 1)}, "cam2world expected rigid"),
    ({"depth_z": -torch.ones(2, 24, 32)}, "depth_z expected values >= 0"),
    ({"map_from_original": torch.zeros(2, 4)}, "map_from_original expected finite rows .*sx, sy > 0"),
    ({"images": [[0.5]]}, "images expected a torch.Tensor \\(or numpy array\\), got list"),
])
def test_a_reconstruction_refuses_fields_its_exports_would_crash_on_or_write_wrong(change, message):
    from pointmap.errors import ShapeError
    from pointmap.reconstruction import Reconstruction

    with pytest.raises(ShapeError, match=message):
        Reconstruction(**_fields(**change))


def test_a_reconstruction_takes_numpy_arrays_as_the_tensors_they_hold():
    from pointmap.reconstruction import Reconstruction

    kw = _fields()
    back = Reconstruction(**{k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in kw.items()})
    assert all(torch.equal(getattr(back, k), kw[k]) for k in ("images", "cam2world", "K", "depth_z", "conf"))


def test_load_npz_names_the_file_when_it_is_missing_foreign_corrupt_or_truncated(tmp_path):
    from pointmap.errors import PointmapError

    with pytest.raises(PointmapError, match="nope.npz', which is not a file"):
        load_npz(tmp_path / "nope.npz")
    np.savez(tmp_path / "foreign.npz", x=np.zeros(3))
    with pytest.raises(PointmapError, match="foreign.npz is not a pointmap reconstruction.npz \\(missing images"):
        load_npz(tmp_path / "foreign.npz")
    (tmp_path / "garbage.npz").write_bytes(b"not an archive at all")
    with pytest.raises(PointmapError, match="garbage.npz is not a readable reconstruction.npz"):
        load_npz(tmp_path / "garbage.npz")
    save_reconstruction(make_recon(), tmp_path, formats=("npz",))
    raw = (tmp_path / "reconstruction.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(PointmapError, match="cut.npz is not a readable reconstruction.npz"):
        load_npz(tmp_path / "cut.npz")
    # damage inside a compressed member: zlib.error (or NotImplementedError) escaped at some offsets before
    hit = []
    for offset in range(200, len(raw) - 200, max(1, (len(raw) - 400) // 60)):
        bad = bytearray(raw)
        bad[offset:offset + 8] = b"\x00\xff" * 4
        (tmp_path / "bad.npz").write_bytes(bytes(bad))
        try:
            load_npz(tmp_path / "bad.npz")
        except PointmapError as e:
            assert "bad.npz" in str(e)
            hit.append(offset)
    assert hit  # (damage in a member the loader does not read, or in padding, still loads)
    assert len(load_npz(tmp_path / "reconstruction.npz")) == 3  # the whole file still reads


def test_write_ply_refuses_points_and_colours_it_would_write_wrong_and_scales_float_colours(tmp_path):
    from pointmap.errors import ShapeError
    from pointmap.io import write_ply

    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    write_ply(tmp_path / "f.ply", xyz, np.full((4, 3), 0.5))
    assert read_ply(tmp_path / "f.ply")["red"].tolist() == [128] * 4  # floats in [0, 1] scaled, not cast to 0
    write_ply(tmp_path / "g.ply", xyz.reshape(2, 2, 3), np.full((2, 2, 3), 200.0), np.ones((2, 2)))  # maps, 0..255
    g = read_ply(tmp_path / "g.ply")
    assert g["red"].tolist() == [200] * 4 and np.array_equal(np.stack([g["x"], g["y"], g["z"]], -1), xyz)
    for args, message in [((np.zeros((6, 2)), np.zeros((6, 3), np.uint8)), "xyz expected \\[M, 3\\]"),
                          ((xyz, np.zeros((3, 3), np.uint8)), "rgb expected \\[4, 3\\] \\(one colour per point\\)"),
                          ((xyz, np.full((4, 3), 300)), "rgb expected uint8 colours .*in \\[300, 300\\]"),
                          ((np.full((4, 3), np.nan), np.zeros((4, 3), np.uint8)), "xyz expected finite points"),
                          ((xyz.astype(np.float64) * 1e40, np.zeros((4, 3), np.uint8)), "within float32's range, got 4 with"),
                          ((xyz, np.zeros((4, 3), np.uint8), [1, 2, np.nan, 4]), "conf expected finite values, got 1"),
                          ((xyz, np.zeros((4, 3), np.uint8), ["a", "b", "c", "d"]), "conf expected numbers")]:
        with pytest.raises(ShapeError, match=message):
            write_ply(tmp_path / "bad.ply", *args)
    assert not (tmp_path / "bad.ply").exists()


def test_read_ply_reads_other_programs_scalar_properties_and_names_files_it_cannot_read(tmp_path):
    from pointmap.errors import ShapeError

    body = np.array([(1.0, 2.0, 3.0, 7)], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")]).tobytes()
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n" \
           "property float z\nproperty uint8 red\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    (tmp_path / "other.ply").write_bytes(head.encode() + body)
    got = read_ply(tmp_path / "other.ply")
    assert got["x"].tolist() == [1.0] and got["red"].tolist() == [7]
    (tmp_path / "crlf.ply").write_bytes(head.replace("\n", "\r\n").encode() + body)  # "not a PLY file" before
    assert {k: v.tolist() for k, v in read_ply(tmp_path / "crlf.ply").items()} == {k: v.tolist() for k, v in got.items()}
    (tmp_path / "cut.ply").write_bytes(head.encode() + body[:-3])
    with pytest.raises(ShapeError, match="cut.ply: truncated: 1 vertices of 13 bytes need 13 bytes, the file has 10"):
        read_ply(tmp_path / "cut.ply")
    (tmp_path / "garbage.ply").write_bytes(b"\x00\x01 nothing like a ply")
    with pytest.raises(ShapeError, match="garbage.ply: not a PLY file"):
        read_ply(tmp_path / "garbage.ply")
    (tmp_path / "ascii.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ShapeError, match="only binary little-endian PLY is supported, got 'format ascii 1.0'"):
        read_ply(tmp_path / "ascii.ply")
    with pytest.raises(ShapeError, match="missing.ply: cannot read it"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "twice.ply").write_bytes(head.replace("property float y", "property float x").encode() + body)
    with pytest.raises(ShapeError, match="twice.ply: vertex property 'x' is declared twice"):
        read_ply(tmp_path / "twice.ply")


def test_saving_into_a_path_that_is_a_file_is_refused_naming_it(tmp_path):
    from pointmap.errors import ShapeError

    (tmp_path / "taken").write_text("x")
    with pytest.raises(ShapeError, match="out_dir expected a folder to write into, got .*taken', which is a file"):
        save_reconstruction(make_recon(), tmp_path / "taken", formats=("npz",))


def test_tum_timestamps_come_from_the_argument_else_the_recorded_times_else_the_index_and_are_checked_first(
        tmp_path):
    from pointmap.io.tum import tum_timestamps, write_tum

    recon = make_recon(n=3)
    assert tum_timestamps(recon).tolist() == [0, 1, 2]
    recon.info["timestamps"] = [0.5, 1.0, 1.5]
    assert tum_timestamps(recon).tolist() == [0.5, 1.0, 1.5] and tum_timestamps(recon, [7, 8, 9]).tolist() == [7, 8, 9]
    recon.info = None  # a Reconstruction built by hand may carry no info
    assert write_tum(recon, tmp_path / "t.txt").exists()
    recon.info = {"timestamps": [0.5, 1.0]}  # one short: refused before any file is written
    with pytest.raises(ValueError, match="timestamps expected 3 finite numbers"):
        save_reconstruction(recon, tmp_path / "out", formats=("ply", "tum"))
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="one distinct time per image, got \\[1.0\\] more than once"):
        tum_timestamps(recon, [1.0, 1.0, 2.0])  # two poses at one time: trajectory tools cannot associate them
    recon.info = None
    lines = write_tum(recon, tmp_path / "back.txt", [5.0, 1.0, 3.0]).read_text().splitlines()[1:]
    assert [float(line.split()[0]) for line in lines] == [1.0, 3.0, 5.0]  # in time order
    assert lines[0].split()[1:4] == [f"{v:.9g}" for v in recon.cam2world[1, :3, 3].double().tolist()]  # image 1's
    frames = [1000.0 + k / 60 for k in range(3)]  # a 60 fps video's presentation times, long into it
    lines = write_tum(recon, tmp_path / "video.txt", frames).read_text().splitlines()[1:]
    assert [float(line.split()[0]) for line in lines] == pytest.approx(frames, abs=1e-6)  # microseconds kept


def test_colours_on_the_0_255_scale_are_refused_as_floats_and_taken_as_uint8_where_a_reconstruction_is_made():
    from dataclasses import replace

    recon = make_recon(n=2)
    with pytest.raises(ValueError, match=r"images: expected colours in \[0, 1\], got values from .* \(0-255 images: "
                                         r"divide by 255, or pass uint8\)"):
        replace(recon, images=recon.images * 255)
    as_uint8 = replace(recon, images=(recon.images * 255).round().to(torch.uint8))
    assert as_uint8.images.dtype == torch.float32 and torch.allclose(as_uint8.images, recon.images, atol=0.5 / 255)
    for bad in (["a", "b"], (64, 48)):
        with pytest.raises(ValueError, match=r"original_sizes expected 2 \(width, height\) pairs of positive ints"):
            replace(recon, original_sizes=bad)


@pytest.mark.parametrize("change,message", [
    (lambda r: {"info": [1, 2]}, "info expected a dict .*got list"),
    (lambda r: {"depth_z": r.depth_z.to(torch.complex64)}, "depth_z expected a floating-point tensor, got torch.complex64"),
    (lambda r: {"K": r.K.int()}, "K expected a floating-point tensor, got torch.int32"),
    (lambda r: {"depth_z": r.depth_z[:0], "conf": r.conf[:0], "images": r.images[:0], "cam2world": r.cam2world[:0],
                "K": r.K[:0], "map_from_original": None, "original_sizes": [], "names": []},
     "expected at least one view"),
])
def test_a_reconstruction_with_no_view_numbers_that_are_not_real_or_info_that_is_not_a_dict_is_refused(change, message):
    from dataclasses import replace

    recon = make_recon(n=2)
    with pytest.raises(ValueError, match=message):
        replace(recon, **change(recon))
    assert replace(recon, info=None).info == {}  # no info: an empty one


def test_global_align_refuses_float_colours_on_the_0_255_scale_and_reads_uint8_views():
    from pointmap.align.inputs import parse_views

    img = torch.rand(3, 8, 12)
    with pytest.raises(ValueError, match=r"view 1: expected colours in \[0, 1\]"):
        parse_views([img, img * 255])
    info = parse_views([(img * 255).round().to(torch.uint8).numpy()])
    assert torch.allclose(info.images[0], img.permute(1, 2, 0), atol=0.5 / 255)


def test_a_canvas_of_several_image_sizes_exports_only_each_views_own_pixels_and_round_trips(tmp_path):
    import dataclasses

    from pointmap.errors import ShapeError
    from pointmap.reconstruction import Reconstruction, to_canvas

    recon = make_recon(n=3, h=24, w=32)  # depth and confidence everywhere, padding included
    sizes = [(32, 24), (16, 24), (32, 8)]  # views 1 and 2 fill part of the 32x24 canvas
    padded = dataclasses.replace(recon, map_sizes=sizes)
    assert padded.padded and not recon.padded
    own = torch.zeros(3, 24, 32, dtype=torch.bool)
    own[0], own[1, :, :16], own[2, :8] = True, True, True
    assert torch.equal(padded.regions, own) and torch.equal(padded.valid(), recon.valid() & own)
    assert padded.crop(padded.depth_z, 1).shape == (24, 16) and padded.crop(padded.images, 2).shape == (8, 32, 3)
    pts = select_points(padded)
    assert len(pts.xyz) == int((recon.valid() & own).sum())
    for k, (w, h) in enumerate(sizes):  # every point from inside its view's own map
        uv = pts.uv_map[pts.image == k]
        assert (uv[:, 0] < w).all() and (uv[:, 1] < h).all()
    save_reconstruction(padded, tmp_path, formats=("npz", "ply"))
    back = load_npz(tmp_path / "reconstruction.npz")
    assert back.map_sizes == sizes and len(read_ply(tmp_path / "points.ply")["x"]) == len(pts.xyz)
    # the canvas: each map at its top-left, the rest filled
    canvas, got = to_canvas([torch.ones(2, 3), torch.ones(4, 1)], fill=0)
    assert got == [(3, 2), (1, 4)] and canvas.shape == (2, 4, 3) and int(canvas.sum()) == 10
    assert torch.equal(canvas[1, :, 0], torch.ones(4)) and canvas[1, 0, 1] == 0
    # built directly: each view's original size defaults to its own map's, as the COLMAP cameras say
    direct = Reconstruction(images=recon.images, cam2world=recon.cam2world, K=recon.K, depth_z=recon.depth_z,
                            conf=recon.conf, map_sizes=sizes)
    assert direct.original_sizes == sizes
    save_reconstruction(direct, tmp_path / "direct", formats=("colmap_txt",))
    cams = [ln.split() for ln in (tmp_path / "direct" / "sparse" / "0" / "cameras.txt").read_text().splitlines()
            if ln and not ln.startswith("#")]
    assert [(int(c[2]), int(c[3])) for c in cams] == sizes
    for bad in ([(33, 24)] * 3, [(32, 24)] * 2, [(0, 24)] * 3, [(32.0, 24)] * 3, "32x24"):
        with pytest.raises(ShapeError, match="map_sizes expected 3 .width, height. pairs of ints within the 32x24"):
            Reconstruction(images=recon.images, cam2world=recon.cam2world, K=recon.K, depth_z=recon.depth_z,
                           conf=recon.conf, map_sizes=bad)


def test_glb_vertex_colours_are_the_photographs_in_linear_light_as_gltf_defines_them(tmp_path):
    import trimesh

    from pointmap.io.glb import srgb_to_linear_u8

    recon = make_recon(n=2)
    save_reconstruction(recon, tmp_path, formats=("glb",), max_points=500)
    cloud = [g for g in trimesh.load(tmp_path / "scene.glb").geometry.values() if isinstance(g, trimesh.PointCloud)][0]
    rgb = select_points(recon, max_points=500).rgb
    assert np.array_equal(np.asarray(cloud.colors)[:, :3], srgb_to_linear_u8(rgb))
    assert srgb_to_linear_u8([0, 188, 255]).tolist() == [0, 128, 255]  # sRGB 188 is half the light


def test_a_hand_made_reconstruction_that_resizes_needs_its_original_sizes():
    from pointmap.reconstruction import Reconstruction

    r = make_recon(n=2)
    from pointmap.errors import ShapeError

    with pytest.raises(ShapeError, match="original_sizes expected with a map_from_original"):
        Reconstruction(images=r.images, cam2world=r.cam2world, K=r.K, depth_z=r.depth_z, conf=r.conf,
                       map_from_original=torch.tensor([[0.25, 0.25, 0.0, 0.0]] * 2))


def test_numpy_arrays_in_info_round_trip_through_the_npz_as_lists(tmp_path):
    recon = make_recon(n=2)
    recon.info["timestamps"] = np.array([0.0, 0.5])
    save_reconstruction(recon, tmp_path, formats=("npz", "tum"))
    assert load_npz(tmp_path / "reconstruction.npz").info["timestamps"] == [0.0, 0.5]


def test_a_reconstruction_holding_tensors_that_require_grad_exports(tmp_path):
    r = make_recon(n=2)
    from pointmap.reconstruction import Reconstruction

    grad = Reconstruction(images=r.images, cam2world=r.cam2world.clone().requires_grad_(), K=r.K,
                          depth_z=r.depth_z.clone().requires_grad_(), conf=r.conf, map_from_original=r.map_from_original,
                          original_sizes=r.original_sizes)
    assert not grad.cam2world.requires_grad and not grad.depth_z.requires_grad
    written = save_reconstruction(grad, tmp_path, formats=("ply", "glb", "colmap", "nerfstudio", "tum", "npz"))
    assert {"ply", "glb", "colmap", "nerfstudio", "tum", "npz"} <= set(written)


def test_shared_camera_with_different_intrinsics_is_refused_before_anything_is_written(tmp_path):
    recon = make_recon(n=2)
    recon.K[1, 0, 0] += 10
    with pytest.raises(ValueError, match="shared_camera=True"):
        save_reconstruction(recon, tmp_path / "out", formats=("ply", "glb", "colmap"), shared_camera=True)
    assert not (tmp_path / "out" / "points.ply").exists()


def test_text_files_are_written_as_utf8_whatever_the_locale(tmp_path):
    import os
    import subprocess

    code = ("import sys; from pointmap.io.atomic import atomic_open\n"
            "with atomic_open(sys.argv[1], 'w') as f: f.write('caf\\u00e9.jpg')")
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}
    subprocess.run([sys.executable, "-X", "utf8=0", "-c", code, str(tmp_path / "t.txt")], check=True, env=env)
    assert (tmp_path / "t.txt").read_bytes() == "café.jpg".encode("utf-8")


def test_photographs_that_need_re_encoding_are_written_as_the_loader_reads_them(tmp_path):
    from PIL import Image

    from pointmap.images import read_rgb
    from pointmap.io.colmap import write_colmap_images

    Image.fromarray(np.full((16, 24), 30000, np.uint16)).save(tmp_path / "grey16.png")  # 16-bit grey
    img = Image.fromarray(np.arange(16 * 24 * 3, dtype=np.uint8).reshape(16, 24, 3))
    exif = img.getexif()
    exif[0x0112] = 6  # rotated: needs re-encoding
    img.save(tmp_path / "turned.jpg", exif=exif)
    (tmp_path / "turned.jpg").rename(tmp_path / "turned")  # no extension
    out = write_colmap_images([tmp_path / "grey16.png", tmp_path / "turned"], ["grey16.jpg", "turned"], tmp_path / "i")
    grey = np.asarray(Image.open(out[0]).convert("RGB")).astype(int)
    assert abs(grey.mean() - read_rgb(tmp_path / "grey16.png").mean()) < 2 and grey.max() < 255  # not saturated
    assert np.array_equal(np.asarray(Image.open(out[1])), read_rgb(tmp_path / "turned"))  # PNG: exact, turned
    rgba = np.zeros((16, 24, 4), np.uint8)
    rgba[..., 0] = 200  # red, half of it transparent: the loader composites it on white
    rgba[:, :12, 3] = 255
    Image.fromarray(rgba).save(tmp_path / "cut.png")
    Image.fromarray(np.full((16, 24, 3), 90, np.uint8)).save(tmp_path / "plain.png")
    out = write_colmap_images([tmp_path / "cut.png", tmp_path / "plain.png"], ["cut.png", "plain.png"], tmp_path / "j")
    assert np.array_equal(np.asarray(Image.open(out[0])), read_rgb(tmp_path / "cut.png"))  # not the RGBA bytes
    assert out[1].read_bytes() == (tmp_path / "plain.png").read_bytes()  # an 8-bit RGB file: copied as it is


def test_a_16_bit_colour_png_is_re_encoded_at_8_bits_not_copied(tmp_path):
    import cv2
    from PIL import Image

    from pointmap.images import read_rgb
    from pointmap.io.colmap import write_colmap_images

    wide = np.random.default_rng(0).integers(0, 65535, (16, 24, 3)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "wide.png"), wide)  # 48-bit RGB: PIL reads it as 8-bit "RGB", as the model did
    out = write_colmap_images([tmp_path / "wide.png"], ["wide.png"], tmp_path / "i")
    kept = cv2.imread(str(out[0]), cv2.IMREAD_UNCHANGED)  # a loader that keeps the file's depth
    assert kept.dtype == np.uint8 and np.array_equal(np.asarray(Image.open(out[0])), read_rgb(tmp_path / "wide.png"))


def test_heic_photographs_are_exported_as_jpegs_named_so_in_the_model(tmp_path):
    pillow_heif = pytest.importorskip("pillow_heif")
    from dataclasses import replace

    from PIL import Image

    from pointmap.errors import ShapeError

    pillow_heif.register_heif_opener()
    recon = make_recon(n=2)
    sources = []
    for k, name in enumerate(("IMG_0001.HEIC", "b.jpg")):
        Image.fromarray(np.full((75, 100, 3), 60 + 80 * k, np.uint8)).save(tmp_path / name, quality=95)
        sources.append(str(tmp_path / name))
    recon = replace(recon, names=["IMG_0001.HEIC", "b.jpg"], info={**recon.info, "sources": sources})
    save_reconstruction(recon, tmp_path / "out", formats=("colmap", "nerfstudio", "npz"))
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == ["IMG_0001.jpg", "b.jpg"]
    with Image.open(tmp_path / "out" / "images" / "IMG_0001.jpg") as im:
        assert im.format == "JPEG" and im.size == (100, 75)  # what 3DGS trainers can read
    model = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    assert sorted(im.name for im in model.images.values()) == ["IMG_0001.jpg", "b.jpg"]
    import json

    frames = json.loads((tmp_path / "out" / "transforms.json").read_text())["frames"]
    assert sorted(f["file_path"] for f in frames) == ["images/IMG_0001.jpg", "images/b.jpg"]
    assert load_npz(tmp_path / "out" / "reconstruction.npz").names == ["IMG_0001.HEIC", "b.jpg"]  # the recon's own
    clash = replace(recon, names=["IMG_0001.HEIC", "img_0001.jpg"])
    with pytest.raises(ShapeError, match="IMG_0001.HEIC and img_0001.jpg would both be exported as img_0001.jpg"):
        save_reconstruction(clash, tmp_path / "clash", formats=("colmap",))
    assert not (tmp_path / "clash").exists()  # refused before anything was written


def test_a_points3d_ply_a_trainer_made_from_an_earlier_model_is_removed_with_a_warning(tmp_path):
    model = tmp_path / "sparse" / "0"
    save_reconstruction(make_recon(n=2), tmp_path, formats=("colmap",))
    (model / "points3D.ply").write_text("ply of the earlier model's points\n")  # what 3DGS writes on its first run
    with pytest.warns(UserWarning, match="removed points3D.ply, which a 3DGS trainer made from an earlier model"):
        save_reconstruction(make_recon(n=3), tmp_path, formats=("colmap",))
    assert not (model / "points3D.ply").exists()


def test_photographs_already_in_the_output_images_folder_are_never_overwritten(tmp_path):
    # `pointmap reconstruct scene/ -o scene/` on a COLMAP-layout scene: the sources are scene/images/* themselves
    from PIL import Image

    from pointmap.io.colmap import write_colmap_images

    images = tmp_path / "scene" / "images"
    images.mkdir(parents=True)
    rgba = np.zeros((16, 24, 4), np.uint8)
    rgba[..., 1], rgba[:, :12, 3] = 150, 255  # half transparent: the loader's copy would be flattened on white
    Image.fromarray(rgba).save(images / "cut.png")
    Image.fromarray(np.full((16, 24, 3), 90, np.uint8)).save(images / "plain.png")
    before = {p.name: p.read_bytes() for p in images.iterdir()}
    with pytest.warns(UserWarning, match="cut.png is the source photograph itself and is left as it is"):
        out = write_colmap_images([images / "cut.png", images / "plain.png"], ["cut.png", "plain.png"], images)
    assert out == [images / "cut.png", images / "plain.png"]
    assert {p.name: p.read_bytes() for p in images.iterdir()} == before  # the user's files, byte for byte


def test_a_colmap_model_written_over_another_formats_files_names_them_in_a_warning(tmp_path):
    recon = make_recon(n=2)
    save_reconstruction(recon, tmp_path, formats=("colmap",))
    with pytest.warns(UserWarning, match="still holds cameras.bin, images.bin, points3D.bin of an earlier run"):
        save_reconstruction(recon, tmp_path, formats=("colmap_txt",))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save_reconstruction(recon, tmp_path / "fresh", formats=("colmap_txt",))


def test_a_colmap_model_written_over_a_newer_colmaps_model_leaves_no_rigs_or_frames_that_break_readers(tmp_path):
    from dataclasses import replace

    model = tmp_path / "sparse" / "0"
    save_reconstruction(replace(make_recon(n=3), names=["x.jpg", "y.jpg", "z.jpg"]), tmp_path, formats=("colmap",))
    pycolmap.Reconstruction(str(model)).write(str(model))  # as COLMAP 3.12+ writes it: with rigs and frames
    (model / "rigs.txt").write_text("# rigs of a text model\n")
    (model / "frames.txt").write_text("# frames of a text model\n")
    with pytest.warns(UserWarning, match="removed rigs.bin, frames.bin, rigs.txt, frames.txt of an earlier COLMAP model"):
        save_reconstruction(make_recon(n=2), tmp_path, formats=("colmap", "colmap_txt"))
    assert not any((model / f"{n}{s}").exists() for n in ("rigs", "frames") for s in (".bin", ".txt"))
    assert sorted(i.name for i in pycolmap.Reconstruction(str(model)).images.values()) == ["IMG_0000.JPG",
                                                                                          "IMG_0001.JPG"]


def test_a_name_that_is_not_utf8_or_a_flag_that_is_not_a_bool_is_refused_before_any_file_is_written(tmp_path):
    from dataclasses import replace

    from pointmap.errors import ShapeError

    recon = make_recon()
    latin1 = replace(recon, names=["caf\udce9.png", *recon.names[1:]])  # how Python reads a Latin-1 file name
    with pytest.raises(ShapeError, match="not UTF-8 .*rename the file"):
        save_reconstruction(latin1, tmp_path / "a", formats=("ply", "colmap", "npz"))
    assert not (tmp_path / "a").exists() or not any((tmp_path / "a").rglob("*"))
    for kw, said in (({"colmap_text": "false"}, "colmap_text expected True or False"),
                     ({"shared_camera": "no"}, "shared_camera expected True or False \\(or None\\)")):
        with pytest.raises(ShapeError, match=said):
            save_reconstruction(recon, tmp_path / "b", formats=("colmap",), **kw)
    with pytest.raises(ShapeError, match="save_reconstruction expected a Reconstruction, got NoneType"):
        save_reconstruction(None, tmp_path / "c")


def test_an_export_into_a_folder_of_an_earlier_export_names_the_files_it_leaves_from_that_run(tmp_path):
    # before: `reconstruct -o out --export ply` over a folder of another scene's run left its reconstruction.npz,
    # which `pointmap splat out/` then read without a word
    import warnings

    from pointmap.io import FORMATS, OUTPUT_NAMES

    assert sorted(OUTPUT_NAMES) == sorted(FORMATS)
    recon = make_recon()
    save_reconstruction(recon, tmp_path, formats=("npz", "tum"))
    with pytest.warns(UserWarning, match="holds reconstruction.npz, trajectory.txt of an earlier export, which this "
                                         "one \\(ply\\) does not rewrite"):
        save_reconstruction(recon, tmp_path, formats=("ply",))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save_reconstruction(recon, tmp_path, formats=("ply", "npz", "tum"))  # everything there rewritten
