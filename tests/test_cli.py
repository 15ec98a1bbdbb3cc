"""The command line's argument handling: folders of images, the export list, flags after the command, and
refusals that come before any model runs."""

import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import pointmap as pm
from pointmap.cli import main


@pytest.fixture
def tiny(tmp_path):
    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for name in ("b.PNG", "a.jpg", "c.png"):
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    (folder / "notes.txt").write_text("not an image")
    return weights, folder


def _save_test_recon(folder):
    """recon_factory's small reconstruction, saved as an npz in ``folder`` (what splat and localize read)."""
    from pointmap.io import save_reconstruction

    sys.path.insert(0, str(Path(__file__).parent / "io"))
    from recon_factory import make_recon

    save_reconstruction(make_recon(), folder, formats=("npz",))


class _Reached(Exception):
    """A stand-in stops a command once it got where the test looks."""


def _stop(*args, **kwargs):
    """A stand-in (e.g. for load_model) that ends the command where the test has seen what it looks for."""
    raise _Reached


def test_a_folder_stands_for_its_images_sorted_by_name_and_flags_may_follow_the_command(tiny, tmp_path, capsys):
    from pointmap.io import load_npz

    weights, folder = tiny
    out = tmp_path / "out"
    assert main(["reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64",
                 "--export", "npz,colmap-txt", "--quiet"]) == 0
    recon = load_npz(out / "reconstruction.npz")
    assert list(recon.names) == ["a.jpg", "b.PNG", "c.png"]
    assert (out / "sparse/0/images.txt").exists() and not (out / "sparse/0/images.bin").exists()
    assert sorted(p.name for p in (out / "images").iterdir()) == ["a.jpg", "b.PNG", "c.png"]  # a scene folder
    with pytest.warns(UserWarning, match="holds reconstruction.npz of an earlier export, which this one"):
        assert main(["reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64", "--quiet",
                     "--export", "ply,colmap-txt", "--max-points", "50", "--colmap-points", "20"]) == 0
    from pointmap.io import read_ply

    assert len(read_ply(out / "points.ply")["x"]) == 50
    assert len([ln for ln in (out / "sparse/0/points3D.txt").read_text().splitlines() if not ln.startswith("#")]) == 20
    assert "inference" not in capsys.readouterr().err  # --quiet after the command silenced the progress bar



def test_a_folder_of_unpadded_frame_numbers_is_read_in_frame_order(tmp_path):
    # a plain string sort put frame_10 .. frame_19 between frame_1 and frame_2: the auto graph paired neighbours
    # in file order, so the wrong ones
    from pointmap.cli import expand_images, natural_key

    for k in (1, 2, 10, 11, 20, 3):
        (tmp_path / f"frame_{k}.png").write_bytes(b"")
    (tmp_path / "frame_2b.png").write_bytes(b"")
    got = [Path(p).name for p in expand_images([str(tmp_path)])]
    assert got == ["frame_1.png", "frame_2.png", "frame_2b.png", "frame_3.png", "frame_10.png", "frame_11.png",
                   "frame_20.png"]
    assert sorted(["b1", "a10", "a9", "a"], key=natural_key) == ["a", "a9", "a10", "b1"]


def test_hidden_files_in_a_folder_are_not_images_and_a_missing_path_is_named(tiny, tmp_path, capsys):
    import shutil

    from pointmap.cli import expand_images

    _, folder = tiny
    scene = tmp_path / "scene"
    shutil.copytree(folder, scene)
    (scene / "._a.jpg").write_bytes(b"\x00\x05\x16\x07 macOS resource fork")
    assert [Path(p).name for p in expand_images([str(scene)])] == ["a.jpg", "b.PNG", "c.png"]
    with pytest.raises(pm.PointmapError, match="no such file or folder: nodir$"):
        expand_images(["nodir"])
    with pytest.raises(pm.PointmapError, match=r"an unexpanded shell pattern\?"):
        expand_images([str(scene / "*.jpeg")])
    assert main(["reconstruct", "nodir", str(scene / "a.jpg"), "-o", str(tmp_path / "o")]) == 2
    assert "no such file or folder: nodir" in capsys.readouterr().err
    assert main(["reconstruct", str(scene), "-o", str(tmp_path / "o"), "--graph", "oneref-5", "--model",
                 "no_such_model"]) == 2  # said before the model loads
    assert "--graph oneref-5: oneref-5: reference index out of range for 3 images" in capsys.readouterr().err


@pytest.mark.parametrize("extra,message", [
    (["--export", "ply,obj"], "--export expected comma-separated formats from ply, glb, colmap, colmap_txt, nerfstudio, tum, npz, got 'ply,obj'"),
    (["--conf-percentile", "100"], "--conf-percentile expected a percentile in [0, 100), got 100.0"),
    (["--min-conf", "nan"], "--min-conf expected a finite confidence, got nan"),
    (["--colmap-points", "-5"], "--max-points and --colmap-points expected >= 0 (0: all), got 0 and -5"),
    (["--max-points", "-5"], "--max-points and --colmap-points expected >= 0 (0: all), got -5 and 100000"),
    (["--cameras", "sparse/0", "--focal", "70"], "--cameras and --focal both give intrinsics: use one"),
    (["--head-prior", "inf"], "--head-prior expected a finite weight >= 0 (0: off), got inf"),
    (["--shared-focal", "--focal", "70,71,72"], "--shared-focal says one camera, but --focal gives 3 different focals"),
])
def test_bad_options_are_refused_before_the_model_is_even_loaded(tiny, tmp_path, capsys, extra, message):
    _, folder = tiny
    # the model named does not exist: the option's own error shows it was checked first
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", "no_such_model", *extra]) == 2
    assert message in capsys.readouterr().err


def test_shared_focal_over_images_of_several_sizes_is_refused_by_flag_and_size_before_the_model_loads(
        tiny, tmp_path, capsys):
    _, folder = tiny
    cv2.imwrite(str(folder / "d.jpg"), np.zeros((80, 60, 3), np.uint8))  # a portrait among landscapes
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", "no_such_model",
                 "--shared-focal"]) == 2
    assert "--shared-focal expected the images of one camera, all of one size (EXIF orientation applied), got " \
           "80x60: a.jpg, b.PNG, c.png; 60x80: d.jpg" in capsys.readouterr().err


def test_heic_photographs_are_reconstructed_from_jpeg_copies_that_the_exports_hold(tiny, tmp_path, capsys):
    pillow_heif = pytest.importorskip("pillow_heif")
    from PIL import Image

    from pointmap.io import load_npz

    pillow_heif.register_heif_opener()
    weights, folder = tiny
    rng = np.random.default_rng(8)
    for name in ("IMG_0001.HEIC", "IMG_0002.heif"):
        Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(folder / name, quality=95)
    out = tmp_path / "out"
    assert main(["reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64",
                 "--export", "colmap,npz"]) == 0
    assert f"2 HEIC / HEIF photograph(s) converted to JPEG in {out / 'converted'}" in capsys.readouterr().err
    names = load_npz(out / "reconstruction.npz").names
    assert names == ["IMG_0001.jpg", "IMG_0002.jpg", "a.jpg", "b.PNG", "c.png"]
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(names)  # what 3DGS trainers read
    with Image.open(out / "images" / "IMG_0001.jpg") as im:
        assert im.format == "JPEG" and im.size == (80, 60)
    (folder / "IMG_0001.jpg").write_bytes((folder / "a.jpg").read_bytes())  # the converted name is taken
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "o2"), "--model", str(weights)]) == 2
    assert "IMG_0001.HEIC is converted to IMG_0001.jpg (3DGS trainers cannot read HEIC), the name of another " \
           "input" in capsys.readouterr().err


def test_cameras_and_pairs_files_may_name_heic_originals_that_were_converted_to_jpeg(tiny, tmp_path, monkeypatch):
    import json

    pillow_heif = pytest.importorskip("pillow_heif")
    from PIL import Image

    pillow_heif.register_heif_opener()
    folder = tiny[1]
    rng = np.random.default_rng(9)
    Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(folder / "IMG_0001.HEIC", quality=95)
    # a phone app's or a retrieval's files, written for the originals: sorted, the images are IMG_0001.jpg, a, b, c
    (tmp_path / "pairs.txt").write_text("IMG_0001.HEIC a.jpg\na.jpg b.PNG\nb.PNG c.png\n")
    frames = [{"file_path": "images/IMG_0001.HEIC", "fl_x": 70.0, "fl_y": 70.0, "cx": 40.0, "cy": 30.0,
               "w": 80, "h": 60, "transform_matrix": np.eye(4).tolist()}]
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    seen, _ = _reconstruct_recording(tiny, tmp_path, monkeypatch, lambda k: (k["graph"], k["K"]), ([],), "--pairs",
                                     str(tmp_path / "pairs.txt"), "--cameras", str(tmp_path / "transforms.json"))
    (graph, K), = seen
    assert sorted(graph) == [(0, 1), (1, 2), (2, 3)]
    # the file's principal point in nerfstudio's pixel corners, ours in pixel centres
    assert sorted(K) == [0] and np.allclose(K[0], [[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]])


def test_a_folder_without_images_is_refused_by_name(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    # the model named does not exist: the folder's own error shows the inputs were read before the model
    assert main(["reconstruct", str(tmp_path / "empty"), "-o", str(tmp_path / "o"), "--model", "no_such_model"]) == 2
    assert f"folder {tmp_path / 'empty'} holds no images" in capsys.readouterr().err


def test_splat_given_the_npz_file_writes_beside_it_and_says_where_even_when_quiet(tiny, tmp_path, monkeypatch,
                                                                                  capsys):
    import pointmap.splat

    weights, folder = tiny
    out = tmp_path / "out"
    assert main(["--quiet", "reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64",
                 "--export", "npz"]) == 0
    seen = {}

    def run(recon, out_dir, **kw):
        seen.update(out=out_dir, n=len(recon))
        return {"paths": {"ply": out_dir / "splat.ply"}}

    monkeypatch.setattr(pointmap.splat, "run", run)
    capsys.readouterr()
    assert main(["splat", str(out / "reconstruction.npz"), "--quiet"]) == 0
    assert seen == {"out": out / "splat", "n": 3}
    assert capsys.readouterr().out == f"splat: {out / 'splat' / 'splat.ply'}\n"  # quiet: no progress, still the path
    assert main(["--quiet", "reconstruct", str(folder), "-o", str(tmp_path / "again"), "--model", str(weights),
                 "--size", "64", "--export", "npz", "--splat"]) == 0
    assert capsys.readouterr().out.splitlines() == [f"npz: {tmp_path / 'again' / 'reconstruction.npz'}",
                                                    f"splat: {tmp_path / 'again' / 'splat' / 'splat.ply'}"]


def test_splat_test_views_are_localized_then_scored_and_unposed_ones_reported(tiny, tmp_path, monkeypatch, capsys):
    import pointmap.localization
    import pointmap.splat
    import pointmap.splat.outputs

    weights, folder = tiny
    out = tmp_path / "out"
    assert main(["--quiet", "reconstruct", str(folder / "a.jpg"), str(folder / "b.PNG"), "-o", str(out), "--model",
                 str(weights), "--size", "64", "--export", "npz"]) == 0
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: {"fit": "the fit"})
    K = torch.tensor([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]], dtype=torch.float64)
    monkeypatch.setattr(pointmap.localization, "localize", lambda model, recon, images, **kw: pointmap.localization.Localization(
        torch.eye(4, dtype=torch.float64).repeat(2, 1, 1), K.repeat(2, 1, 1), [1, -1], [2.0, float("nan")],
        [1.0, float("nan")], ["c.png", "a.jpg"]))
    seen = {}
    monkeypatch.setattr(pointmap.splat.outputs, "evaluate_views",
                        lambda res, images, c2w, K_map, out_dir, **kw: seen.update(res=res, n=len(images),
                                                                                   shape=images[0].shape, K=K_map, **kw))
    assert main(["splat", str(out), "--quiet", "--test", str(folder / "c.png"), str(folder / "a.jpg"), "--model",
                 str(weights), "--test-align-steps", "7"]) == 0
    assert seen["res"] == "the fit" and seen["n"] == 1 and seen["names"] == ["c.png"] and seen["align_steps"] == 7
    h, w = seen["shape"][:2]  # the test photograph at the maps' size, K mapped onto it
    assert (h, w) == (48, 64) and np.allclose(seen["K"][0, 0, 0].item(), 70 * 64 / 80)
    assert "1 test view(s) could not be localized and are left out: a.jpg" in capsys.readouterr().err
    assert main(["splat", str(out), "--test", str(folder / "c.png"), "--test-align-steps", "-1"]) == 2
    monkeypatch.setattr(pointmap.splat, "run", lambda *a, **k: pytest.fail("the fit ran before the inputs were read"))
    assert main(["splat", str(out), "--test", str(folder / "missing.png"), "--model", str(weights)]) == 2
    assert main(["splat", str(out), "--test", str(folder / "c.png"), "--model", "no_such_model"]) == 2
    import pointmap.checkpoint
    from pointmap.runtime.onnx import OnnxPointmapModel

    single = object.__new__(OnnxPointmapModel)  # a single-graph ONNX export: refused before the fit
    single.split = False
    with monkeypatch.context() as mp:
        mp.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: single)
        assert main(["splat", str(out), "--test", str(folder / "c.png"), "--model", "export/"]) == 2
    assert "single-graph ONNX export (export/) does not give" in capsys.readouterr().err
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: {"fit": "the fit"})

    def none_posed(*a, **k):
        raise pointmap.PointmapError("none of the 1 queries could be posed")

    monkeypatch.setattr(pointmap.localization, "localize", none_posed)
    assert main(["splat", str(out), "--test", str(folder / "c.png"), "--model", str(weights)]) == 2
    assert "could be posed" in (err := capsys.readouterr().err) and "without test scores" in err


def test_cameras_from_a_transforms_json_are_held_fixed_poses_too_with_known_poses(tiny, tmp_path, capsys):
    import json

    from pointmap.geometry.rotations import axis_angle_to_matrix
    from pointmap.io import load_npz

    weights, folder = tiny
    first = tmp_path / "first"
    base = ["--quiet", "reconstruct", str(folder), "--model", str(weights), "--size", "64"]
    assert main([*base, "-o", str(first), "--export", "nerfstudio"]) == 0
    meta = json.loads((first / "transforms.json").read_text())
    given = []
    for k, frame in enumerate(meta["frames"]):  # cameras of our choosing: a focal and a pose per image
        frame["fl_x"] = frame["fl_y"] = 60.0 + 10 * k
        T = np.eye(4)
        T[:3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.2 * k, 0.05 * k], dtype=torch.float64)).numpy()
        T[:3, 3] = [0.4 * k, 0.1 * k, 0.0]
        frame["transform_matrix"] = (T @ np.diag([1.0, -1, -1, 1])).tolist()  # stored in OpenGL axes
        given.append(T)
    cams = tmp_path / "cams.json"
    cams.write_text(json.dumps(meta))
    out = tmp_path / "out"
    assert main([*base, "-o", str(out), "--export", "npz", "--cameras", str(cams), "--known-poses"]) == 0
    recon = load_npz(out / "reconstruction.npz")
    assert np.allclose(recon.K[:, 0, 0].numpy(), [60.0, 70.0, 80.0], atol=1e-3)
    assert np.allclose(recon.cam2world.numpy(), np.stack(given), atol=1e-5)
    capsys.readouterr()
    assert main([*base, "-o", str(out), "--known-poses"]) == 2
    assert "--known-poses holds the poses of --cameras FILE fixed" in capsys.readouterr().err
    meta["frames"][0]["w"] = 81
    cams.write_text(json.dumps(meta))
    assert main([*base, "-o", str(out), "--cameras", str(cams)]) == 2
    assert "states 81x60 for a.jpg, but the image is 80x60" in capsys.readouterr().err
    for k, frame in enumerate(meta["frames"]):
        frame["file_path"] = f"images/other{k}.png"
    cams.write_text(json.dumps(meta))
    assert main([*base, "-o", str(out), "--cameras", str(cams)]) == 2
    assert "names none of the 3 images" in capsys.readouterr().err
    # poses alone, without --known-poses: the file changed nothing (and turned off the shared focal of a video)
    bare = json.loads((first / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y"):
        bare.pop(key, None)
        for frame in bare["frames"]:
            frame.pop(key, None)
    cams.write_text(json.dumps(bare))
    assert main([*base, "-o", str(out), "--cameras", str(cams)]) == 2
    assert "gives no intrinsics for the images it names, only poses: pass --known-poses" in capsys.readouterr().err
    assert main([*base, "-o", str(out), "--export", "npz", "--cameras", str(cams), "--known-poses"]) == 0


def test_masks_from_a_folder_are_matched_by_stem_and_refused_before_the_inference_when_wrong(tiny, tmp_path, capsys,
                                                                                            monkeypatch):
    from pointmap.io import load_npz

    weights, folder = tiny
    masks = tmp_path / "masks"
    masks.mkdir()
    m = np.full((60, 80), 255, np.uint8)
    m[:, :40] = 0  # the left half of a.jpg masked out
    cv2.imwrite(str(masks / "a.png"), m)
    out = tmp_path / "out"
    base = ["--quiet", "reconstruct", str(folder), "-o", str(out), "--size", "64", "--export", "npz"]
    assert main([*base, "--model", str(weights), "--masks", str(masks)]) == 0
    kept = load_npz(out / "reconstruction.npz").masks
    h, w = kept.shape[1:]
    assert not kept[0, :, : w // 2 - 1].any() and kept[0, :, w // 2 + 1:].any() and kept[1].any()
    cv2.imwrite(str(masks / "b.png"), np.zeros((5, 5), np.uint8))  # neither the original size nor the map's
    capsys.readouterr()
    import pointmap.inference

    def no_inference(*a, **k):
        raise AssertionError("a wrong mask must be refused before the inference")

    monkeypatch.setattr(pointmap.inference, "predict_pairs", no_inference)
    assert main([*base, "--model", str(weights), "--masks", str(masks)]) == 2
    assert "mask 1 (of image b.PNG) expected the image's original size 80x60 or the network's map size 64x48 " \
           "(width x height), got 5x5" in capsys.readouterr().err
    assert main([*base, "--model", "no_such_model", "--masks", str(tmp_path / "nowhere")]) == 2
    assert "--masks expected a folder of mask images" in capsys.readouterr().err


def test_a_cut_out_with_transparency_as_mask_keeps_its_visible_pixels_dark_ones_too(tmp_path):
    from PIL import Image

    from pointmap.cli import masks_from_folder

    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((6, 8, 3), np.uint8))
    (tmp_path / "m").mkdir()
    cut = np.zeros((6, 8, 4), np.uint8)  # a background remover's output: a dark object on a transparent ground
    cut[:, 4:, :3], cut[:, 4:, 3] = 10, 255
    cut[0, 5, :3] = 0  # a black pixel of the object: kept
    cut[2, 3, 3] = 128  # a half-transparent edge pixel (hair, a soft matte): kept
    Image.fromarray(cut).save(tmp_path / "m" / "a.png")
    keep = masks_from_folder(str(tmp_path / "m"), [str(tmp_path / "a.jpg")])[0]
    assert keep[:, 4:].all() and keep[2, 3] and keep[:, :4].sum() == 1
    cut[2, 3, 3] = 0
    Image.fromarray(np.dstack([cut[..., 0], np.full((6, 8), 255, np.uint8)]), "LA").save(tmp_path / "m" / "a.png")
    keep = masks_from_folder(str(tmp_path / "m"), [str(tmp_path / "a.jpg")])[0]  # opaque: the grey levels
    assert keep[:, 4:].sum() == 23 and not keep[:, :4].any()


def test_a_mask_with_a_malformed_exif_block_is_turned_by_its_orientation_as_the_photographs_are(tmp_path):
    from PIL import Image

    from pointmap.cli import masks_from_folder

    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((8, 6, 3), np.uint8))  # upright 6 x 8
    (tmp_path / "m").mkdir()
    stored = np.zeros((6, 8), np.uint8)
    stored[:, :4] = 255  # the left half as stored: the top half once turned (orientation 6: 90 degrees clockwise)
    im = Image.fromarray(stored)
    exif = im.getexif()
    exif[0x0112], exif[0x0110] = 6, "CAMERA"
    im.save(tmp_path / "m" / "a.jpg", exif=exif, quality=100)
    data = bytearray((tmp_path / "m" / "a.jpg").read_bytes())
    at = data.find(bytes([0x01, 0x10, 0x00, 0x02]))  # the model tag, ASCII: turned into XResolution, a rational
    data[at + 1] = 0x1A  # holding text, which Pillow's exif_transpose fails on
    (tmp_path / "m" / "a.jpg").write_bytes(bytes(data))
    keep = masks_from_folder(str(tmp_path / "m"), [str(tmp_path / "a.jpg")])[0]
    assert keep.shape == (8, 6) and keep[:3].all() and not keep[5:].any()


def test_nerf_synthetic_cameras_match_by_stem_and_take_the_focal_from_the_angle_and_the_images_width(tiny, tmp_path):
    import json

    from pointmap.cli import cameras_from_file

    _, folder = tiny
    images = [str(folder / n) for n in ("a.jpg", "b.PNG", "c.png")]
    frames = [{"file_path": f"./train/{stem}", "transform_matrix": np.eye(4).tolist()} for stem in ("a", "c")]
    (tmp_path / "t.json").write_text(json.dumps({"camera_angle_x": 2 * np.arctan(0.5), "frames": frames}))
    K, poses, distortions = cameras_from_file(str(tmp_path / "t.json"), images, poses=True)
    assert sorted(K) == [0, 2] and sorted(poses) == [0, 2] and distortions == {}
    assert np.allclose(K[0], [[80.0, 0, 39.5], [0, 80.0, 29.5], [0, 0, 1]])  # 80 px wide, a 53-degree field of view: f = 40 / tan(26.6 deg)
    # a file naming an image both in full and by its stem: the full name is that image's, the stem another's
    turned = np.eye(4)
    turned[0, 3] = 5.0
    frames = [{"file_path": "./train/a", "transform_matrix": np.eye(4).tolist()},
              {"file_path": "./train/a.jpg", "transform_matrix": turned.tolist()}]
    (tmp_path / "both.json").write_text(json.dumps({"camera_angle_x": 2 * np.arctan(0.5), "frames": frames}))
    _, poses, _ = cameras_from_file(str(tmp_path / "both.json"), images[:1], poses=True)
    assert poses[0][0, 3] == 5.0  # the OpenGL -> OpenCV axes change leaves the centre as it is


def test_a_transforms_json_lens_is_undone_before_the_model_and_the_exports_carry_the_undistorted_photographs(
        tiny, tmp_path):
    import json

    from pointmap.images import read_rgb
    from pointmap.io import load_npz
    from pointmap.undistort import Distortion, pinhole_for, undistort

    weights, folder = tiny
    frames = [{"file_path": f"images/{name}", "transform_matrix": np.eye(4).tolist(), "fl_x": 70.0, "fl_y": 70.0,
               "cx": 40.0, "cy": 30.0, "w": 80, "h": 60, **({"k1": -0.2, "k2": 0.05} if name != "a.jpg" else {})}
              for name in ("a.jpg", "b.PNG", "c.png")]  # a.jpg: a pinhole camera
    cams = tmp_path / "transforms.json"
    cams.write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    out = tmp_path / "out"
    assert main(["--quiet", "reconstruct", str(folder), "--model", str(weights), "--size", "64", "-o", str(out),
                 "--cameras", str(cams), "--export", "npz,colmap"]) == 0
    K_in = np.array([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]])
    lens = Distortion("OPENCV", (-0.2, 0.05))
    K_pin = pinhole_for(K_in, lens, (80, 60))
    recon = load_npz(out / "reconstruction.npz")
    assert recon.names == ["a.jpg", "b.PNG", "c.png"]
    assert np.allclose(recon.K[0].double().numpy(), K_in, atol=1e-4)  # the pinhole camera as given
    assert np.allclose(recon.K[1].double().numpy(), K_pin, atol=1e-4)  # the pinhole camera the photo was moved to
    undistorted = undistort(read_rgb(folder / "b.PNG"), K_in, lens, K_pin)
    assert np.array_equal(read_rgb(out / "undistorted" / "b.PNG"), undistorted)
    assert sorted(p.name for p in (out / "undistorted").iterdir()) == ["b.PNG", "c.png"]
    assert np.array_equal(read_rgb(out / "images" / "b.PNG"), undistorted)  # the COLMAP scene's photograph


def test_a_colmap_models_cameras_and_lens_serve_as_known_cameras_like_a_transforms_json(tiny, tmp_path):
    from pointmap.io import load_npz
    from pointmap.undistort import Distortion, pinhole_for

    weights, folder = tiny
    model = tmp_path / "scene" / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("# a COLMAP text model\n1 OPENCV 80 60 70 70 40 30 -0.2 0.05 0 0\n"
                                       "2 SIMPLE_PINHOLE 80 60 65 40 30\n")
    poses = "0.9238795 0 0.3826834 0 0.1 0 0"  # 45 degrees about y
    (model / "images.txt").write_text(f"1 {poses} 1 photos/b.PNG\n\n2 1 0 0 0 0 0 0 2 c.png\n\n")
    out = tmp_path / "out"
    assert main(["--quiet", "reconstruct", str(folder), "--model", str(weights), "--size", "64", "-o", str(out),
                 "--cameras", str(tmp_path / "scene"), "--export", "npz"]) == 0
    recon = load_npz(out / "reconstruction.npz")
    K_in = np.array([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]])
    assert np.allclose(recon.K[1].double().numpy(), pinhole_for(K_in, Distortion("OPENCV", (-0.2, 0.05)), (80, 60)),
                       atol=1e-4)
    assert np.allclose(recon.K[2].double().numpy(), [[65.0, 0, 39.5], [0, 65.0, 29.5], [0, 0, 1]], atol=1e-4)
    assert sorted(p.name for p in (out / "undistorted").iterdir()) == ["b.PNG"]


def test_cameras_naming_any_file_of_a_colmap_model_reads_the_model_not_a_transforms_json(tiny, tmp_path):
    from pointmap.cli import cameras_from_file

    _, folder = tiny
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 SIMPLE_PINHOLE 80 60 65 40 30\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.jpg\n\n")
    (model / "points3D.txt").write_text("# no points\n")
    images = [str(folder / "a.jpg"), str(folder / "b.PNG")]
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        K, _, _ = cameras_from_file(str(model / name), images, poses=False)
        assert np.allclose(K[0], [[65.0, 0, 39.5], [0, 65.0, 29.5], [0, 0, 1]]), name


def test_an_output_folder_that_would_overwrite_the_input_cameras_or_photographs_is_refused_before_the_model(
        tiny, tmp_path, capsys):
    import shutil

    _, folder = tiny
    scene = tmp_path / "scene"  # a COLMAP scene: images/ and sparse/0 with a distorting lens
    shutil.copytree(folder, scene / "images")
    model = scene / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 OPENCV 80 60 70 70 40 30 -0.2 0.05 0 0\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.jpg\n\n2 1 0 0 0 0.1 0 0 1 b.PNG\n\n")
    before = {p: p.read_bytes() for p in scene.rglob("*") if p.is_file()}
    for cameras in (model, scene, model / "cameras.txt"):  # the model "no_such_model": refused before it loads
        assert main(["--quiet", "reconstruct", str(scene), "-o", str(scene), "--cameras", str(cameras),
                     "--model", "no_such_model"]) == 2
        err = capsys.readouterr().err
        assert not (scene / "undistorted").exists()  # refused before the undistortion too
        assert f"-o {scene} would overwrite the inputs: the --cameras model {model}; the photograph(s) " \
               f"{scene / 'images' / 'a.jpg'}, {scene / 'images' / 'b.PNG'} (their undistorted copies" in err
    assert main(["--quiet", "reconstruct", str(scene), "-o", str(scene), "--cameras", str(model), "--model",
                 "no_such_model", "--export", "ply,npz"]) == 2  # nothing of the inputs exported: the model's error
    assert "no such file or shipped model" in capsys.readouterr().err
    transforms = scene / "transforms.json"  # a nerfstudio scene's cameras, and -o its folder
    transforms.write_text('{"frames": [{"file_path": "images/a.jpg", "fl_x": 70, "w": 80, "h": 60, '
                          '"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}')
    before[transforms] = transforms.read_bytes()
    assert main(["--quiet", "reconstruct", str(scene), "-o", str(scene), "--cameras", str(transforms),
                 "--model", "no_such_model", "--export", "nerfstudio"]) == 2
    assert f"the --cameras file {transforms}; give another output folder, or --export without nerfstudio" in \
        capsys.readouterr().err
    assert {p: p.read_bytes() for p in before} == before


@pytest.fixture
def tiny_recon(tiny, tmp_path):
    """The tiny model, its photographs, and a reconstruction (npz) of a.jpg and b.PNG to localize the others in."""
    weights, folder = tiny
    rec = tmp_path / "rec"
    assert main(["--quiet", "reconstruct", str(folder / "a.jpg"), str(folder / "b.PNG"), "--model", str(weights),
                 "--size", "64", "-o", str(rec), "--export", "npz"]) == 0
    return weights, folder, rec


def test_localize_writes_each_querys_pose_to_json_and_the_posed_ones_to_a_tum_trajectory(tiny_recon, tmp_path,
                                                                                          capsys, monkeypatch):
    import json

    import pointmap.localization

    weights, folder, rec = tiny_recon
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    calls = []

    def pose_against(recon, ref, pred, rev, K_map=None, patch=16):  # the geometry is tested in tests/align/test_localize.py
        calls.append(ref)
        pose = T if len(calls) == 1 else torch.full((4, 4), float("nan"), dtype=torch.float64)
        return pose, K_map, 2.0

    monkeypatch.setattr(pointmap.localization, "pose_against", pose_against)
    out = tmp_path / "loc"
    with pytest.warns(UserWarning, match="the reconstruction's focals were estimated"):  # pm.localize's, passed on
        assert main(["--quiet", "localize", str(rec), str(folder / "c.png"), str(folder / "a.jpg"), "--model",
                     str(weights), "-o", str(out), "--focal", "70", "--n-refs", "1"]) == 0

    def no_nan(c):
        raise AssertionError(f"{c} in localization.json: not strict JSON")

    rows = json.loads((out / "localization.json").read_text(), parse_constant=no_nan)["queries"]
    assert [r["name"] for r in rows] == ["c.png", "a.jpg"] and len(calls) == 2
    assert rows[0]["reference"] in ("a.jpg", "b.PNG") and np.allclose(rows[0]["cam2world"], T.numpy())
    assert np.allclose(rows[0]["K"], [[70, 0, 39.5], [0, 70, 29.5], [0, 0, 1]]) and rows[0]["scale"] == 2.0
    assert rows[1]["reference"] is None and rows[1]["cam2world"] is None  # not posed: reported, not in the TUM
    lines = [ln.split() for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 1 and np.allclose([float(x) for x in lines[0]], [0, 1, 2, 3, 0, 0, 0, 1])
    printed = capsys.readouterr().out
    assert "c.png: posed against" in printed and "a.jpg: not posed" in printed
    assert main(["localize", str(tmp_path / "nowhere"), str(folder / "c.png"), "-o", str(out)]) == 2
    assert "no reconstruction.npz in" in capsys.readouterr().err
    assert main(["localize", str(rec), str(folder / "c.png"), "-o", str(out), "--n-refs", "0"]) == 2
    assert "--n-refs expected >= 1" in capsys.readouterr().err
    assert main(["localize", str(rec), str(folder / "c.png"), "-o", str(rec)]) == 2  # would replace its files
    assert "the reconstruction's own folder" in capsys.readouterr().err


def test_localize_takes_the_queries_cameras_from_a_transforms_json_undoing_a_lens_first(tiny_recon, tmp_path,
                                                                                         capsys, monkeypatch):
    import json

    import pointmap.localization
    from pointmap.images import read_rgb
    from pointmap.undistort import Distortion, pinhole_for, undistort

    weights, folder, rec = tiny_recon
    frames = [{"file_path": f"images/{name}", "transform_matrix": np.eye(4).tolist(), "fl_x": 70.0, "fl_y": 72.0,
               "cx": 40.0, "cy": 30.0, "w": 80, "h": 60, **({"k1": -0.2, "k2": 0.05} if name == "c.png" else {})}
              for name in ("a.jpg", "c.png")]
    cams = tmp_path / "transforms.json"
    cams.write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    seen = {}

    def localize(model, recon, images, K=None, **kw):  # what the command hands the library
        seen.update(images=list(images), K=K)
        m = len(seen["images"])
        return pointmap.localization.Localization(torch.eye(4, dtype=torch.float64).repeat(m, 1, 1), K, [0] * m,
                                                  [1.0] * m, [1.0] * m, [Path(i).name for i in seen["images"]])

    monkeypatch.setattr(pointmap.localization, "localize", localize)
    out = tmp_path / "loc"
    assert main(["--quiet", "localize", str(rec), str(folder / "c.png"), str(folder / "a.jpg"), "--model",
                 str(weights), "-o", str(out), "--cameras", str(cams)]) == 0
    K_in = np.array([[70.0, 0, 39.5], [0, 72.0, 29.5], [0, 0, 1]])  # cx - 0.5: the file's pixel-corner convention
    lens = Distortion("OPENCV", (-0.2, 0.05))
    K_pin = pinhole_for(K_in, lens, (80, 60))
    assert np.allclose(seen["K"][0].numpy(), K_pin, atol=1e-4) and np.allclose(seen["K"][1].numpy(), K_in, atol=1e-4)
    assert seen["images"][0] == str(out / "undistorted" / "c.png") and seen["images"][1] == str(folder / "a.jpg")
    assert np.array_equal(read_rgb(out / "undistorted" / "c.png"), undistort(read_rgb(folder / "c.png"), K_in, lens,
                                                                             K_pin))
    rows = json.loads((out / "localization.json").read_text())["queries"]
    assert [r["name"] for r in rows] == ["c.png", "a.jpg"] and np.allclose(rows[1]["K"], K_in)
    # a query the file does not name, and two sources of the same intrinsics: refused before the model loads
    for extra, message in ((["--cameras", str(cams)], "gives no intrinsics for 1 of the 2 photographs (b.PNG)"),
                           (["--cameras", str(cams), "--focal", "70"], "--cameras and --focal both give"),
                           (["--cameras", str(tmp_path / "none.json")], "--cameras expected a transforms.json")):
        assert main(["localize", str(rec), str(folder / "c.png"), str(folder / "b.PNG"), "--model", "no_such_model",
                     "-o", str(out), *extra]) == 2
        assert message in capsys.readouterr().err


def test_each_folder_reconstructs_every_scene_with_one_model_and_skips_a_bad_one(tiny, tmp_path, capsys, monkeypatch):
    import shutil

    import pointmap.checkpoint

    weights, folder = tiny
    scenes = tmp_path / "scenes"
    shutil.copytree(folder, scenes / "one")
    shutil.copytree(folder, scenes / "two")
    (scenes / "empty").mkdir()  # no images: reported, skipped, the others still run
    loads = []
    real_load = pointmap.checkpoint.load_model
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: loads.append(a) or real_load(*a, **k))
    out = tmp_path / "out"
    code = main(["--quiet", "reconstruct", str(scenes), "--each-folder", "-o", str(out), "--model", str(weights),
                 "--size", "64", "--export", "npz"])
    err = capsys.readouterr().err
    assert code == 1 and len(loads) == 1
    assert (out / "one" / "reconstruction.npz").exists() and (out / "two" / "reconstruction.npz").exists()
    assert "scene empty skipped: PointmapError: folder" in err and "1 of 3 scenes failed: empty" in err
    assert main(["reconstruct", str(folder / "a.jpg"), "--each-folder", "-o", str(out)]) == 2
    assert "--each-folder expected one folder whose sub-folders are scenes" in capsys.readouterr().err
    assert main(["reconstruct", str(scenes), "--each-folder", "-o", str(out), "--masks", str(folder)]) == 2
    assert "takes --cameras, --masks, --pairs and --metric-depth relative to each scene folder" in capsys.readouterr().err


def test_each_folder_reads_every_scenes_own_cameras_and_masks_and_its_images_folder(tiny, tmp_path, capsys):
    import shutil

    from pointmap.io import load_npz

    weights, folder = tiny
    scenes = tmp_path / "scenes"
    for k, name in enumerate(("one", "two", "three")):  # COLMAP-style scenes: images/ and sparse/0
        shutil.copytree(folder, scenes / name / "images")
        model = scenes / name / "sparse" / "0"
        model.mkdir(parents=True)
        (model / "cameras.txt").write_text(f"1 SIMPLE_PINHOLE 80 60 {50 + 10 * k} 40 30\n")
        (model / "images.txt").write_text("".join(f"{i + 1} 1 0 0 0 0 0 0 1 {n}\n\n"
                                                  for i, n in enumerate(("a.jpg", "b.PNG", "c.png"))))
    shutil.rmtree(scenes / "three" / "sparse")  # no model: this scene fails, the others still run
    (scenes / "two" / "masks").mkdir()
    half = np.full((60, 80), 255, np.uint8)
    half[:, :40] = 0  # the left half of a.jpg masked out
    cv2.imwrite(str(scenes / "two" / "masks" / "a.png"), half)
    out = tmp_path / "out"
    code = main(["--quiet", "reconstruct", str(scenes), "--each-folder", "-o", str(out), "--model", str(weights),
                 "--size", "64", "--export", "npz", "--cameras", "sparse/0"])
    err = capsys.readouterr().err
    assert code == 1 and "scene three skipped: PointmapError: --cameras expected a transforms.json" in err
    for k, name in enumerate(("one", "two")):
        recon = load_npz(out / name / "reconstruction.npz")
        assert recon.names == ["a.jpg", "b.PNG", "c.png"]
        assert np.allclose(recon.K[:, 0, 0].numpy(), 50 + 10 * k)  # each scene's own focal
    shutil.rmtree(out)
    code = main(["--quiet", "reconstruct", str(scenes), "--each-folder", "-o", str(out), "--model", str(weights),
                 "--size", "64", "--export", "npz", "--masks", "masks"])
    err = capsys.readouterr().err
    assert code == 1 and "scene one skipped: PointmapError: --masks expected a folder" in err, err
    kept = load_npz(out / "two" / "reconstruction.npz").masks
    w = kept.shape[2]
    assert not kept[0, :, : w // 2 - 1].any() and kept[0, :, w // 2 + 1:].all() and kept[1].all()  # scene two's own


def test_each_folder_skips_hidden_folders_and_its_own_output_and_survives_any_scene_error(tiny, tmp_path, capsys):
    import shutil

    weights, folder = tiny
    scenes = tmp_path / "scenes"
    shutil.copytree(folder, scenes / "good")
    shutil.copytree(folder, scenes / ".ipynb_checkpoints")
    shutil.copytree(folder, scenes / "__MACOSX")
    (scenes / "broken").mkdir()
    for name in ("x.png", "y.png"):  # fails inside the scene (reading), not in the argument checks
        (scenes / "broken" / name).write_bytes(b"not a png")
    args = ["--quiet", "reconstruct", str(scenes), "--each-folder", "-o", str(scenes / "out"), "--model", str(weights),
            "--size", "64", "--export", "npz"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "1 of 2 scenes failed: broken" in err and "scene broken skipped: ImageError" in err
    assert main(args) == 1  # a re-run does not take its own output folder for a scene
    assert "1 of 2 scenes failed" in capsys.readouterr().err


def _reconstruct_recording(tiny, tmp_path, monkeypatch, read, variants, *common):
    """``pointmap reconstruct`` of the tiny folder once per list of extra arguments in ``variants`` (after
    ``common``), with ``pipeline.reconstruct`` wrapped to record ``read(its keyword arguments)``; each run must
    succeed and write its npz. Returns (the recorded values, the loaded npz files)."""
    import pointmap.pipeline

    weights, folder = tiny
    seen, saved = [], []
    real = pointmap.pipeline.reconstruct
    monkeypatch.setattr(pointmap.pipeline, "reconstruct", lambda *a, **k: seen.append(read(k)) or real(*a, **k))
    for n, extra in enumerate(variants):
        out = tmp_path / f"out{n}"
        assert main(["--quiet", "reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64",
                     "--export", "npz", *common, *extra]) == 0
        saved.append(np.load(out / "reconstruction.npz", allow_pickle=False))
    return seen, saved


def test_no_epipolar_turns_the_pose_refinement_on_matches_off(tiny, tmp_path, monkeypatch):
    seen, _ = _reconstruct_recording(tiny, tmp_path, monkeypatch, lambda k: k["epipolar"], ([], ["--no-epipolar"]))
    assert seen == [True, False]


def test_whole_reaches_reconstruct_and_is_recorded_for_localize(tiny, tmp_path, monkeypatch):
    import json

    seen, saved = _reconstruct_recording(tiny, tmp_path, monkeypatch, lambda k: k["whole"], ([], ["--whole"]),
                                         "--no-epipolar")
    assert seen == [False, True]
    assert [json.loads(str(f["info_json"]))["pipeline"]["whole"] for f in saved] == [False, True]


def test_align_init_chooses_the_alignments_start(tiny, tmp_path, monkeypatch, capsys):
    seen, saved = _reconstruct_recording(tiny, tmp_path, monkeypatch, lambda k: k["align"].init,
                                         ([], ["--align-init", "mst"]))
    assert seen == ["averaging", "mst"]
    assert all(f["cam2world"].shape[0] >= 2 for f in saved)
    folder = tiny[1]
    with pytest.raises(SystemExit):
        main(["reconstruct", str(folder), "-o", str(tmp_path / "x"), "--align-init", "tree"])
    assert "invalid choice: 'tree'" in capsys.readouterr().err


def test_head_prior_reaches_the_alignment_and_a_negative_weight_or_a_model_without_pose_head_is_refused(
        tiny, tmp_path, monkeypatch, capsys):
    from dataclasses import replace

    from pointmap.align import AlignConfig

    weights, folder = tiny
    torch.manual_seed(0)
    posed = pm.save_model(pm.PointmapNet(replace(pm.PRESETS["test"], pose_head=True)), tmp_path / "posed.safetensors")
    seen, _ = _reconstruct_recording((posed, folder), tmp_path, monkeypatch, lambda k: k["align"].head_prior,
                                     ([], ["--head-prior", "0.5"], ["--head-prior", "2"]), "--no-epipolar")
    assert seen == [AlignConfig().head_prior, 0.5, 2.0]
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "x"), "--model", str(posed), "--size", "64",
                 "--head-prior", "-1"]) != 0
    assert "--head-prior expected a finite weight >= 0 (0: off), got -1.0" in capsys.readouterr().err
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "y"), "--model", str(weights), "--size", "64",
                 "--head-prior", "0.5"]) == 2  # the tiny model has no pose head: the weight would do nothing
    assert "--head-prior applies only to a model with a pose head" in capsys.readouterr().err
    assert not (tmp_path / "y" / "reconstruction.npz").exists()


def test_align_init_offers_exactly_the_alignments_starts():
    from pointmap.align.optimize import INITS
    from pointmap.cli import build_parser

    sub = next(a for a in build_parser()._subparsers._group_actions[0].choices["reconstruct"]._actions
               if a.dest == "align_init")
    assert tuple(sub.choices) == INITS and sub.default == INITS[0]


@pytest.mark.parametrize("command", ["reconstruct", "pair", "localize", "demo"])
def test_an_output_path_that_is_a_file_is_refused_before_the_model_is_even_loaded(tiny, tmp_path, capsys, command):
    _, folder = tiny
    (tmp_path / "taken").write_text("x")
    images = [str(folder / "a.jpg"), str(folder / "c.png")]
    args = {"reconstruct": images, "pair": images, "localize": [str(tmp_path), *images], "demo": []}[command]
    if command == "localize":  # the reconstruction it reads must exist for -o to be the first error
        _save_test_recon(tmp_path)
    # the model named does not exist: the -o error shows the folder was checked first
    assert main([command, *args, "-o", str(tmp_path / "taken" / "sub"), "--model", "no_such_model"]) == 2
    assert "-o expected a folder to write into, got" in capsys.readouterr().err


@pytest.mark.parametrize("extra,message", [
    (["--size", "17"], "--size expected 224 or a multiple of 16"),
    (["--size", "5120"], "--size expected 224 or a multiple of 16 from 32 to 2048 (e.g. 512), got 5120"),
    (["--graph", "swin-0"], "--graph: swin-0: window must be >= 1"),
    (["--graph", "bogus"], "--graph: unknown graph 'bogus'; expected one of: auto, complete, swin-K"),
    (["--splat", "--splat-budget", "-5"], "--splat-budget expected seconds >= 0"),
])
def test_size_graph_and_splat_budget_are_refused_before_the_model_even_for_each_folder(tiny, tmp_path, capsys, extra,
                                                                                       message):
    _, folder = tiny
    for scene_flags in ([str(folder)], [str(tmp_path), "--each-folder"]):
        if "--each-folder" in scene_flags:
            (tmp_path / "scene").mkdir(exist_ok=True)
        assert main(["reconstruct", *scene_flags, "-o", str(tmp_path / "o"), "--model", "no_such_model", *extra]) == 2
        assert message in capsys.readouterr().err


def test_the_device_resolves_to_what_torch_can_use_and_a_missing_gpu_is_refused_with_the_way_out(monkeypatch):
    from pointmap.cli import resolve_device
    from pointmap.errors import PointmapError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device(" CPU ") == "cpu"
    for name, message in [("cuda", "torch sees 0 CUDA device(s) here (torch.cuda.is_available() is False); use "
                                   "cpu or auto"),
                          ("cuda:1", "torch sees 0 CUDA device(s)"), ("mps", "MPS backend is not available"),
                          ("tpu", "--device expected auto, cpu, cuda, cuda:N or mps, got 'tpu'"),
                          ("cuda:x", "got 'cuda:x'")]:
        with pytest.raises(PointmapError, match=message.replace("(", r"\(").replace(")", r"\)")):
            resolve_device(name)
    # a machine with one GPU: auto takes it, cuda:0 is it, cuda:1 does not exist
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == "cuda" and resolve_device("cuda:0") == "cuda:0"
    with pytest.raises(PointmapError, match="torch sees 1 CUDA device"):
        resolve_device("cuda:1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # no CUDA, but Apple's MPS
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert resolve_device("auto") == "mps"


@pytest.mark.parametrize("command", ["reconstruct", "pair", "localize", "splat", "demo"])
def test_a_device_torch_cannot_use_is_refused_in_one_line_before_the_model_loads(tiny, tmp_path, capsys, monkeypatch,
                                                                                command):
    import pointmap.checkpoint

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    weights, folder = tiny
    images = [str(folder / "a.jpg"), str(folder / "c.png")]
    args = {"reconstruct": images, "pair": images, "localize": [str(tmp_path), *images],
            "splat": [str(tmp_path), "--test", images[0]], "demo": []}[command]
    assert main([command, *args, "-o", str(tmp_path / "out"), "--model", str(weights), "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pointmap: error: --device cuda: torch sees 0 CUDA device(s)") and err.count("\n") == 1


@pytest.mark.parametrize("command", ["reconstruct", "pair", "localize", "splat", "demo"])
def test_the_device_reaches_the_model_and_the_stage_that_runs_it_on_every_command(tiny, tmp_path, monkeypatch,
                                                                                  command):
    import pointmap.checkpoint
    import pointmap.demo
    import pointmap.io_pair
    import pointmap.localization
    import pointmap.pipeline
    import pointmap.splat

    weights, folder = tiny
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a machine with one GPU: auto takes it
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    seen = {}

    def record(name):
        def stand_in(*a, **k):
            seen[name] = k.get("device")
            if name == "load":
                return pm.PointmapNet(pm.PRESETS["test"]).eval()  # on the CPU: nothing here runs on the GPU
            if name == "splat":
                return {"fit": None}
            raise _Reached(name)
        return stand_in

    monkeypatch.setattr(pointmap.checkpoint, "load_model", record("load"))
    for module, name in ((pointmap.pipeline, "reconstruct"), (pointmap.io_pair, "write_pair_outputs"),
                         (pointmap.localization, "localize"), (pointmap.demo, "run_demo"), (pointmap.splat, "run")):
        monkeypatch.setattr(module, name, record(name if name != "run" else "splat"))
    _save_test_recon(tmp_path / "rec")
    images = [str(folder / "a.jpg"), str(folder / "c.png")]
    args = {"reconstruct": images, "pair": images, "localize": [str(tmp_path / "rec"), *images],
            "splat": [str(tmp_path / "rec"), "--test", images[0]], "demo": []}[command]
    with pytest.raises(_Reached):
        main(["--quiet", command, *args, "-o", str(tmp_path / "out"), "--model", str(weights), "--size", "64"]
             if command in ("reconstruct", "pair") else
             ["--quiet", command, *args, "-o", str(tmp_path / "out"), "--model", str(weights)])
    stage = {"reconstruct": "reconstruct", "pair": "write_pair_outputs", "localize": "localize", "splat": "localize",
             "demo": "run_demo"}[command]
    assert seen[stage] == "cuda"
    if command != "demo":  # run_demo loads its own model, with the device it was given
        assert seen["load"] == "cuda"


def test_splat_without_test_views_never_asks_for_the_device(tiny, tmp_path, monkeypatch):
    import pointmap.splat

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: {"fit": None})
    _save_test_recon(tmp_path / "rec")
    assert main(["--quiet", "splat", str(tmp_path / "rec"), "--device", "cuda"]) == 0  # the fit runs on the CPU


def test_a_retrieval_graph_pairs_the_photographs_by_similarity_end_to_end(tiny, tmp_path, monkeypatch):
    import pointmap.inference
    import pointmap.pairs
    from pointmap.io import load_npz

    weights, folder = tiny
    seen = []
    real = pointmap.pairs.pairs_from_similarity
    monkeypatch.setattr(pointmap.pairs, "pairs_from_similarity", lambda sim, k: seen.append((sim, k)) or real(sim, k))
    out = tmp_path / "r"
    assert main(["--quiet", "reconstruct", str(folder), "-o", str(out), "--model", str(weights), "--size", "64",
                 "--export", "npz", "--graph", "retrieval-1"]) == 0
    (sim, k), = seen
    assert k == 1 and sim.shape == (3, 3)  # the three photographs' similarity, from the model itself
    expected = real(sim, 1)
    info = load_npz(out / "reconstruction.npz").info["pipeline"]
    assert info["graph"] == "retrieval-1" and info["pairs"] == len(expected) >= 2


def test_a_pairs_file_names_the_pairs_by_path_or_unique_file_name_and_reconstruct_runs_exactly_them(tiny, tmp_path,
                                                                                                   monkeypatch):
    import json

    folder = tiny[1]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"# from a retrieval\n\na.jpg b.PNG\n{folder / 'c.png'} photos/b.PNG\n  b.PNG a.jpg  \n")
    seen, saved = _reconstruct_recording(tiny, tmp_path, monkeypatch, lambda k: k["graph"], ([],), "--pairs",
                                         str(pairs))
    # the folder's images sorted by name: a.jpg, b.PNG, c.png; (b, a) is (a, b)
    assert seen == [[(0, 1), (1, 2)]]
    info = json.loads(str(saved[0]["info_json"]))["pipeline"]
    assert info["graph"] == "given" and info["pairs"] == 2


@pytest.mark.parametrize("text,extra,message", [
    ("a.jpg zzz.png\n", [], "line 1: 'zzz.png' is none of the 3 photographs"),
    ("a.jpg b.PNG c.png\n", [], "line 1: expected two image names, got 'a.jpg b.PNG c.png'"),
    ("# nothing\n", [], "no pairs in the file"),
    ("a.jpg b.PNG\n", [], "pairs.txt: the pair graph is disconnected: 2 components"),  # c.png in no pair
    ("a.jpg ./photos/a.jpg\n", [], "line 1: a photograph paired with itself"),
    ("a.jpg b.PNG\n", ["--graph", "complete"], "--pairs and --graph complete both choose the pairs"),
])
def test_a_pairs_file_that_cannot_be_used_is_refused_by_line_before_the_model_loads(tiny, tmp_path, capsys,
                                                                                    monkeypatch, text, extra, message):
    import pointmap.checkpoint

    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    weights, folder = tiny
    (tmp_path / "pairs.txt").write_text(text)
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "r"), "--model", str(weights),
                 "--pairs", str(tmp_path / "pairs.txt"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_a_file_name_two_photographs_share_is_refused_as_ambiguous(tmp_path):
    from pointmap.cli import pairs_from_file
    from pointmap.errors import PointmapError

    (tmp_path / "p.txt").write_text("x/a.jpg y/a.jpg\n")
    assert pairs_from_file(str(tmp_path / "p.txt"), ["s/x/a.jpg", "s/y/a.jpg"]) == [(0, 1)]
    (tmp_path / "p.txt").write_text("a.jpg y/a.jpg\n")
    with pytest.raises(PointmapError, match="'a.jpg' names several of the 2 photographs .* e.g. 'x/a.jpg'"):
        pairs_from_file(str(tmp_path / "p.txt"), ["s/x/a.jpg", "s/y/a.jpg"])
    # a photograph's own path names it even when it is also a tail of another's
    (tmp_path / "p.txt").write_text("a/b.jpg ./c/a/b.jpg\n")
    assert pairs_from_file(str(tmp_path / "p.txt"), ["a/b.jpg", "c/a/b.jpg"]) == [(0, 1)]
    with pytest.raises(PointmapError, match="--pairs expected a text file"):
        pairs_from_file(str(tmp_path / "missing.txt"), ["a.jpg"])


def test_a_pairs_file_saved_by_a_windows_editor_with_a_byte_order_mark_and_crlf_reads_as_any_other(tmp_path):
    from pointmap.cli import pairs_from_file

    (tmp_path / "p.txt").write_bytes("a.jpg b.jpg\r\nc.jpg a.jpg\r\n".encode("utf-8-sig"))
    assert pairs_from_file(str(tmp_path / "p.txt"), ["s/a.jpg", "s/b.jpg", "s/c.jpg"]) == [(0, 1), (2, 0)]


def test_cameras_files_saved_with_a_byte_order_mark_read_as_any_other(tmp_path):
    from pointmap.io.colmap import read_colmap
    from pointmap.io.nerfstudio import read_transforms

    (tmp_path / "cameras.txt").write_bytes("# cameras\r\n1 SIMPLE_PINHOLE 80 60 65 40 30\r\n".encode("utf-8-sig"))
    (tmp_path / "images.txt").write_bytes("1 1 0 0 0 0 0 0 1 a.jpg\r\n\r\n".encode("utf-8-sig"))
    assert np.allclose(read_colmap(tmp_path)["a.jpg"]["K"], [[65.0, 0, 39.5], [0, 65.0, 29.5], [0, 0, 1]])
    (tmp_path / "transforms.json").write_bytes(
        '{"fl_x": 65, "w": 80, "h": 60, "frames": [{"file_path": "images/a.jpg", "transform_matrix": '
        '[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}'.encode("utf-8-sig"))
    assert read_transforms(tmp_path / "transforms.json")["a.jpg"]["size"] == (80, 60)


def test_reconstruct_with_cache_reads_the_pairs_back_on_a_second_run(tiny, tmp_path, capsys):
    from pointmap.io import load_npz

    weights, folder = tiny
    args = ["reconstruct", str(folder), "--model", str(weights), "--size", "64", "--export", "npz", "--graph",
            "complete", "--no-epipolar", "--cache", str(tmp_path / "cache")]
    assert main([*args, "-o", str(tmp_path / "a")]) == 0
    assert "0 of 6 directed pairs read, 6 to predict" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert "6 of 6 directed pairs read, 0 to predict" in err and "~0.0 s (6 of 6 directed pairs in the cache)" in err
    info = load_npz(tmp_path / "b" / "reconstruction.npz").info["pipeline"]["cache"]
    assert info["hits"] == 6 and info["misses"] == 0 and info["dir"].startswith(str(tmp_path / "cache"))
    assert main([*args[:-1], str(tmp_path / "half"), "--cache-half", "-o", str(tmp_path / "c")]) == 0
    full = sum(p.stat().st_size for p in (tmp_path / "cache").rglob("*.safetensors"))
    half = sum(p.stat().st_size for p in (tmp_path / "half").rglob("*.safetensors"))
    assert half < 0.6 * full
    capsys.readouterr()


def test_cache_options_that_cannot_be_used_are_refused_before_the_model_loads(tiny, tmp_path, capsys, monkeypatch):
    import pointmap.checkpoint

    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    weights, folder = tiny
    (tmp_path / "file").write_text("x")
    for extra, message in [(["--cache", str(tmp_path / "file")], "--cache expected a folder to write into, got "
                                                                  ".*which is a file"),
                           (["--cache", str(tmp_path / "file" / "c")], "--cache expected a folder .*cannot be made"),
                           (["--cache-half"], "--cache-half sets how --cache DIR stores predictions: give --cache")]:
        assert main(["reconstruct", str(folder), "-o", str(tmp_path / "r"), "--model", str(weights), *extra]) == 2
        assert re.search(message, capsys.readouterr().err)


def test_metric_depth_scales_the_reconstruction_to_the_measured_maps(tiny, tmp_path, capsys):
    from pointmap.io import load_npz

    weights, folder = tiny
    (tmp_path / "depth").mkdir()
    np.save(tmp_path / "depth" / "a.npy", np.full((30, 40), 5.0, np.float32))  # a sensor at half resolution
    cv2.imwrite(str(tmp_path / "depth" / "b.png"), np.full((60, 80), 5000, np.uint16))  # millimetres
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "r"), "--model", str(weights), "--size", "64",
                 "--export", "npz", "--no-epipolar", "--metric-depth", str(tmp_path / "depth")]) == 0
    assert "to the measured depth of 2 image(s)" in capsys.readouterr().err
    recon = load_npz(tmp_path / "r" / "reconstruction.npz")
    report = recon.info["metric_depth"]
    assert report["images"] == 2 and report["per_image"][2] is None  # c.png has no map
    names = [Path(n).name for n in recon.names]
    d = torch.cat([recon.depth_z[names.index(n)].flatten() for n in ("a.jpg", "b.PNG")])
    assert float(d[d > 0].median()) == pytest.approx(5.0, rel=0.01)


@pytest.mark.parametrize("extra,message", [
    (["--metric-depth", "nowhere"], "--metric-depth expected a folder of depth maps"),
    (["--metric-depth", "EMPTY"], "holds no depth map named like the images"),
    (["--metric-depth", "EMPTY", "--cameras", "X", "--known-poses"], "--known-poses already fixes its scale"),
])
def test_metric_depth_that_cannot_be_used_is_refused_before_the_model_loads(tiny, tmp_path, capsys, monkeypatch,
                                                                           extra, message):
    import pointmap.checkpoint

    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    weights, folder = tiny
    (tmp_path / "EMPTY").mkdir()
    extra = [str(tmp_path / e) if e in ("nowhere", "EMPTY") else e for e in extra]
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "r"), "--model", str(weights), *extra]) == 2
    assert message in capsys.readouterr().err


def test_metric_depth_of_another_shape_is_refused_before_the_model_and_too_few_pixels_save_unscaled(tiny, tmp_path,
                                                                                                  capsys, monkeypatch):
    import pointmap.checkpoint

    weights, folder = tiny
    (tmp_path / "depth").mkdir()
    np.save(tmp_path / "depth" / "a.npy", np.ones((80, 60), np.float32))  # portrait map for a landscape photo
    real = pointmap.checkpoint.load_model
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    args = ["reconstruct", str(folder), "--model", str(weights), "--size", "64", "--export", "npz",
            "--no-epipolar", "--metric-depth", str(tmp_path / "depth")]
    assert main([*args, "-o", str(tmp_path / "r")]) == 2
    assert "is 60x80, not the aspect ratio of its photograph (80x60" in capsys.readouterr().err
    monkeypatch.setattr(pointmap.checkpoint, "load_model", real)
    np.save(tmp_path / "depth" / "a.npy", np.zeros((60, 80), np.float32))  # no usable pixel
    assert main([*args, "-o", str(tmp_path / "r")]) == 0
    assert "--metric-depth not applied, the reconstruction keeps its own scale" in capsys.readouterr().err
    assert (tmp_path / "r" / "reconstruction.npz").exists()


def test_info_tells_what_a_model_is_its_licence_and_training_and_refuses_a_missing_one(tmp_path, capsys):
    import json

    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"])
    path = pm.save_model(model, tmp_path / "m.safetensors", provenance={
        "steps": 12, "batch_size": 8, "data": "train_a", "eval_data": "eval_b", "licence": "Apache-2.0",
        "heldout_metrics": {"step": 12, "RRA15": 61.25, "AbsRel": 0.3}, "note": "a test"})
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    cfg = pm.PRESETS["test"]
    assert f"encoder {cfg.enc_depth} x {cfg.enc_dim}" in out and "licence: Apache-2.0" in out
    assert "trained: 12 steps, batch 8, data train_a" in out and "held-out (eval_b, the run at step 12): RRA15 61.2" in out
    assert f"{sum(p.numel() for p in model.parameters()) / 1e6:.1f} M parameters" in out
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["licence"] == "Apache-2.0" and info["config"]["enc_dim"] == cfg.enc_dim
    assert info["provenance"]["note"] == "a test" and info["megabytes"] > 0
    bare = pm.save_model(model, tmp_path / "bare.safetensors", provenance={})
    assert main(["info", str(bare)]) == 0 and "licence: not recorded in the file" in capsys.readouterr().out
    assert main(["info", str(tmp_path / "none.safetensors")]) == 2
    assert "checkpoint not found" in capsys.readouterr().err


def test_info_describes_the_file_load_model_reads_when_a_local_file_has_a_shipped_models_name(tmp_path, monkeypatch):
    from pointmap.checkpoint import WEIGHTS_DIR, shipped_path
    from pointmap.cli import model_summary

    model = pm.PointmapNet(pm.PRESETS["test"])
    (tmp_path / "here").mkdir()
    (tmp_path / "here" / "small").write_bytes(b"a checkpoint named like the shipped model")
    monkeypatch.chdir(tmp_path / "here")  # ./small exists: load_model reads it, not the shipped small
    assert shipped_path("small") is None
    assert model_summary(model, "small")["path"] == str((tmp_path / "here" / "small").resolve())
    monkeypatch.chdir(tmp_path)
    assert shipped_path("small") == WEIGHTS_DIR / "small.safetensors"  # the package ships it
    assert model_summary(model, "small")["path"] == str((WEIGHTS_DIR / "small.safetensors").resolve())


def test_a_file_system_refusal_during_a_command_is_one_line_and_exit_2_with_the_trace_under_verbose(tiny, tmp_path,
                                                                                                 monkeypatch, capsys):
    import pointmap.io_pair

    weights, folder = tiny

    def refuse(*args, **kw):
        raise FileNotFoundError(2, "No such file or directory", str(tmp_path / "gone" / "pair.npz"))

    monkeypatch.setattr(pointmap.io_pair, "write_pair_outputs", refuse)
    argv = ["pair", str(folder / "a.jpg"), str(folder / "b.PNG"), "-o", str(tmp_path / "out"), "--model", str(weights),
            "--size", "64"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "pointmap: error: [Errno 2] No such file or directory" in err and "gone/pair.npz" in err
    assert "Traceback" not in err and "run with -v" in err
    with pytest.raises(FileNotFoundError):
        main(["-v", *argv])


def test_output_piped_into_a_reader_that_closes_early_ends_quietly_not_as_an_error(monkeypatch, capsys):
    import pointmap.cli

    def closed_pipe(args):  # what printing into `| head -1` raises once head has exited
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(pointmap.cli, "cmd_info", closed_pipe)
    assert main(["info", "--json"]) == 141
    assert capsys.readouterr().err == ""


def test_a_warning_during_a_command_is_one_line_and_the_library_formatting_is_restored_after(monkeypatch):
    import warnings

    import pointmap.cli

    before = warnings.formatwarning
    seen = []
    monkeypatch.setattr(pointmap.cli, "cmd_info", lambda args: seen.append(
        warnings.formatwarning("duplicates add no parallax", UserWarning, "pointmap/align/inputs.py", 80)) or 0)
    assert main(["info"]) == 0
    assert seen == ["pointmap: warning: duplicates add no parallax\n"] and warnings.formatwarning is before
    assert main(["-v", "info"]) == 0  # verbose: the source line stays
    assert "pointmap/align/inputs.py:80" in seen[1]


def test_flags_that_would_be_ignored_are_refused_before_the_model_loads(tiny, tmp_path, capsys, monkeypatch):
    import pointmap.checkpoint

    weights, folder = tiny
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pytest.fail("the model loaded"))
    base = ["reconstruct", str(folder), "-o", str(tmp_path / "out"), "--model", str(weights)]
    cases = [(["--stride", "5"], "--stride applies only to a video among IMG"),
             (["--max-frames", "5"], "--max-frames applies only to a video among IMG, without --stride"),
             (["--depth-png-scale", "0.01"], "--depth-png-scale applies only with --metric-depth"),
             (["--splat-budget", "10"], "--splat-budget applies only with --splat"),
             (["--colmap-points", "10", "--export", "npz,ply"], "--colmap-points applies only to the colmap"),
             (["--max-points", "10", "--export", "npz,colmap"], "--max-points applies only to the ply and glb")]
    for extra, said in cases:
        assert main(base + extra) == 2, extra
        assert said in capsys.readouterr().err
    assert main(["splat", str(tmp_path / "rec"), "--test-align-steps", "7"]) == 2  # no reconstruction needed first
    assert "no reconstruction.npz" in capsys.readouterr().err
    _save_test_recon(tmp_path / "rec")
    for extra in (["--test-align-steps", "7"], ["--model", "nonexistent_model"]):
        assert main(["splat", str(tmp_path / "rec"), *extra]) == 2
        assert f"{extra[0]} applies only with --test" in capsys.readouterr().err
    assert main(["localize", str(tmp_path / "rec"), str(folder), "-o", str(tmp_path / "loc"), "--stride", "2"]) == 2
    assert "--stride applies only to a video among IMG" in capsys.readouterr().err


def test_a_video_with_both_stride_and_max_frames_is_refused_and_one_frame_is_said_in_its_terms(tmp_path, capsys):
    from tests.test_video import _video

    video = _video(tmp_path / "clip.avi", n=1)
    out = ["-o", str(tmp_path / "out"), "--model", "no_such_model"]
    assert main(["reconstruct", str(video), *out, "--stride", "2", "--max-frames", "5"]) == 2
    assert "--max-frames applies only to a video among IMG, without --stride" in capsys.readouterr().err
    assert main(["reconstruct", str(video), *out]) == 2
    err = capsys.readouterr().err
    assert "needs at least 2 images, got 1" in err and "the video holds 1 frame(s)" in err and "None" not in err


def test_two_images_of_one_file_name_are_refused_when_cameras_or_masks_match_by_it(tmp_path):
    import json

    from pointmap.cli import cameras_from_file, masks_from_folder
    from pointmap.errors import PointmapError

    rng = np.random.default_rng(0)
    for d in ("x", "y", "masks"):
        (tmp_path / d).mkdir()
    for d in ("x", "y"):
        cv2.imwrite(str(tmp_path / d / "a.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    cv2.imwrite(str(tmp_path / "x" / "b.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    frame = {"file_path": "images/a.png", "w": 80, "h": 60, "fl_x": 70.0, "fl_y": 70.0, "cx": 40.0, "cy": 30.0,
             "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [frame]}))
    images = [str(tmp_path / "x" / "a.png"), str(tmp_path / "y" / "a.png"), str(tmp_path / "x" / "b.png")]
    with pytest.raises(PointmapError, match="--cameras matches images by file name, and .*x/a.png and .*y/a.png are "
                                            "both 'a.png'"):
        cameras_from_file(str(tmp_path / "transforms.json"), images, poses=True)
    K, poses, _ = cameras_from_file(str(tmp_path / "transforms.json"), images[1:], poses=True)  # one a.png: fine
    assert sorted(K) == [0] and sorted(poses) == [0]
    cv2.imwrite(str(tmp_path / "masks" / "a.png"), np.full((60, 80), 255, np.uint8))
    with pytest.raises(PointmapError, match="--masks matches images by file name without suffix"):
        masks_from_folder(str(tmp_path / "masks"), images)
    assert len(masks_from_folder(str(tmp_path / "masks"), images[1:])) == 2


# what reaches the pipeline, the fit and the exports: defaults and forwarded values (a mutation review of the
# subcommands found these untested)
class _SavedRecon:
    """What pipeline.reconstruct returns in these tests: save() records its keyword arguments."""

    def __init__(self, seen):
        self.info, self.seen = {}, seen

    def save(self, out, **kw):
        self.seen["save"] = kw
        return {}


def _record_pipeline(monkeypatch, seen):
    import pointmap.pipeline

    monkeypatch.setattr(pointmap.pipeline, "reconstruct",
                        lambda model, images, **kw: seen.update(reconstruct=kw) or _SavedRecon(seen))


def test_the_point_caps_default_to_all_of_the_cloud_and_100000_colmap_points_and_apply_to_every_export_they_name(
        tiny, tmp_path, monkeypatch):
    weights, folder = tiny
    seen = {}
    _record_pipeline(monkeypatch, seen)
    base = ["--quiet", "reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", str(weights), "--size", "64"]
    assert main(base) == 0
    assert seen["save"]["max_points"] is None and seen["save"]["colmap_max_points"] == 100_000
    for extra, key, value in ((["--export", "nerfstudio", "--colmap-points", "7"], "colmap_max_points", 7),
                              (["--export", "glb", "--max-points", "9"], "max_points", 9),
                              (["--export", "colmap", "--colmap-points", "0"], "colmap_max_points", None)):
        assert main([*base, *extra]) == 0, extra
        assert seen["save"][key] == value, extra


def test_head_prior_0_is_off_for_any_model_even_one_without_a_pose_head(tiny, tmp_path, monkeypatch):
    weights, folder = tiny
    seen = {}
    _record_pipeline(monkeypatch, seen)
    assert main(["--quiet", "reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", str(weights), "--size",
                 "64", "--head-prior", "0"]) == 0
    assert seen["reconstruct"]["align"].head_prior == 0.0


def test_the_splat_fit_takes_120_seconds_by_default_the_given_budget_or_no_limit_for_0(tiny, tmp_path, monkeypatch):
    import pointmap.splat

    weights, folder = tiny
    budgets = []
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: budgets.append(kw["time_budget"]) or {})
    _save_test_recon(tmp_path / "rec")
    for extra in ([], ["--splat-budget", "5"], ["--splat-budget", "0"]):
        assert main(["--quiet", "splat", str(tmp_path / "rec"), *extra]) == 0
    seen = {}
    _record_pipeline(monkeypatch, seen)
    for extra in ([], ["--splat-budget", "5"], ["--splat-budget", "0"]):
        assert main(["--quiet", "reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", str(weights),
                     "--size", "64", "--splat", *extra]) == 0
    assert budgets == [120.0, 5.0, None] * 2


def test_a_video_without_stride_gives_at_most_30_frames_or_max_frames(tmp_path, monkeypatch):
    import pointmap.checkpoint
    from tests.test_video import _video

    monkeypatch.setattr(pointmap.checkpoint, "load_model", _stop)  # the frames are read before the model loads
    video = _video(tmp_path / "clip.avi", n=30)
    for extra, n in (([], 30), (["--max-frames", "5"], 5)):
        out = tmp_path / f"out{n}"
        with pytest.raises(_Reached):
            main(["--quiet", "reconstruct", str(video), "-o", str(out), *extra])
        assert len(list((out / "frames").glob("clip_*.png"))) == n


def test_each_folder_refuses_two_folders_an_absolute_cameras_path_per_image_focals_and_an_unusable_head_prior(
        tiny, tmp_path, capsys):
    import shutil

    weights, folder = tiny
    scenes = tmp_path / "scenes"
    shutil.copytree(folder, scenes / "one")
    base = ["reconstruct", str(scenes), "--each-folder", "-o", str(tmp_path / "out"), "--model", str(weights),
            "--size", "64"]
    for argv, message in (
            ([*base[:2], str(folder), *base[2:]], "--each-folder expected one folder whose sub-folders are scenes"),
            ([*base, "--cameras", str(tmp_path / "sparse")], "relative to each scene folder"),
            ([*base, "--focal", "70,71,72"], "relative to each scene folder"),
            ([*base, "--head-prior", "0.5"], "--head-prior applies only to a model with a pose head")):
        assert main(argv) == 2, argv
        assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "one").exists()


def test_each_folder_reads_every_scenes_own_depth_maps_and_keeps_their_predictions_in_the_cache(tiny, tmp_path,
                                                                                                capsys):
    import shutil

    from pointmap.io import load_npz

    weights, folder = tiny
    scenes = tmp_path / "scenes"
    for k, name in enumerate(("one", "two")):
        shutil.copytree(folder, scenes / name)
        (scenes / name / "depth").mkdir()
        np.save(scenes / name / "depth" / "a.npy", np.full((60, 80), 2.0 + 3 * k, np.float32))
    out, cache = tmp_path / "out", tmp_path / "cache"
    assert main(["--quiet", "reconstruct", str(scenes), "--each-folder", "-o", str(out), "--model", str(weights),
                 "--size", "64", "--export", "npz", "--no-epipolar", "--metric-depth", "depth", "--cache",
                 str(cache)]) == 0, capsys.readouterr().err
    for k, name in enumerate(("one", "two")):
        recon = load_npz(out / name / "reconstruction.npz")
        assert recon.info["metric_depth"]["images"] == 1  # a.jpg's map, from the scene's own depth/
        cached = recon.info["pipeline"]["cache"]  # scene two holds scene one's photographs: read back
        assert (cached["misses"] > 0) if name == "one" else (cached["hits"] > 0 and cached["misses"] == 0)
        d = recon.depth_z[[Path(n).name for n in recon.names].index("a.jpg")].flatten()
        assert float(d[d > 0].median()) == pytest.approx(2.0 + 3 * k, rel=0.01)
    assert any(cache.rglob("*.safetensors"))


def test_confidence_filters_and_refine_reach_the_pipeline(tiny, tmp_path, monkeypatch):
    weights, folder = tiny
    seen = {}
    _record_pipeline(monkeypatch, seen)
    base = ["--quiet", "reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", str(weights), "--size", "64"]
    assert main(base) == 0
    assert (seen["reconstruct"]["min_conf"], seen["reconstruct"]["conf_percentile"], seen["reconstruct"]["refine"]) \
        == (None, None, False)
    assert main([*base, "--min-conf", "3", "--conf-percentile", "40", "--refine"]) == 0
    assert (seen["reconstruct"]["min_conf"], seen["reconstruct"]["conf_percentile"], seen["reconstruct"]["refine"]) \
        == (3.0, 40.0, True)


def test_metric_depth_for_photographs_with_lens_distortion_is_refused_before_the_model_loads(tiny, tmp_path, capsys):
    import json

    _, folder = tiny
    frames = [{"file_path": f"images/{n}", "transform_matrix": np.eye(4).tolist(), "fl_x": 70.0, "fl_y": 70.0,
               "cx": 40.0, "cy": 30.0, "w": 80, "h": 60, **({"k1": -0.2} if n == "a.jpg" else {})}
              for n in ("a.jpg", "b.PNG", "c.png")]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    (tmp_path / "depth").mkdir()
    np.save(tmp_path / "depth" / "a.npy", np.full((60, 80), 5.0, np.float32))
    assert main(["reconstruct", str(folder), "-o", str(tmp_path / "o"), "--model", "no_such_model", "--cameras",
                 str(tmp_path / "transforms.json"), "--metric-depth", str(tmp_path / "depth")]) == 2
    assert "--metric-depth: the photographs have lens distortion" in capsys.readouterr().err


def test_more_than_12_photographs_keep_the_wrap_around_pairs_that_only_a_videos_frames_drop(tmp_path, monkeypatch):
    import pointmap.checkpoint

    rng = np.random.default_rng(0)
    for k in range(13):
        cv2.imwrite(str(tmp_path / f"p{k:02d}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    monkeypatch.setattr(pointmap.checkpoint, "load_model", lambda *a, **k: pm.PointmapNet(pm.PRESETS["test"]).eval())
    seen = {}
    _record_pipeline(monkeypatch, seen)
    assert main(["--quiet", "reconstruct", str(tmp_path), "-o", str(tmp_path / "o"), "--size", "64"]) == 0
    assert seen["reconstruct"]["graph"] == "auto"  # photographs: the pipeline's own choice, not a video's -noncyclic


def _splat_test_setup(tiny, tmp_path, monkeypatch):
    """A reconstruction of a.jpg, b.PNG; splat.run returns a refined reconstruction; localize and evaluate_views
    record what they were given; the one test view is posed against reconstruction view 0."""
    import pointmap.localization
    import pointmap.splat
    import pointmap.splat.outputs

    weights, folder = tiny
    out = tmp_path / "out"
    assert main(["--quiet", "reconstruct", str(folder / "a.jpg"), str(folder / "b.PNG"), "-o", str(out), "--model",
                 str(weights), "--size", "64", "--export", "npz"]) == 0
    seen = {}
    refined = object()
    monkeypatch.setattr(pointmap.splat, "run", lambda recon, out_dir, **kw: seen.update(budget=kw["time_budget"]) or
                        {"fit": "the fit", "recon_refined": refined})
    K = torch.tensor([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]], dtype=torch.float64)

    def localize(model, recon, images, **kw):
        seen["localized_in"] = recon
        return pointmap.localization.Localization(torch.eye(4, dtype=torch.float64)[None], K[None], [0], [2.0],
                                                  [1.0], ["c.png"])

    monkeypatch.setattr(pointmap.localization, "localize", localize)
    monkeypatch.setattr(pointmap.splat.outputs, "evaluate_views",
                        lambda res, images, c2w, K_map, out_dir, **kw: seen.update(n=len(images), **kw))
    return weights, folder, out, seen, refined


def test_splat_test_views_are_posed_in_the_refined_cameras_and_one_posed_against_view_0_is_scored(
        tiny, tmp_path, monkeypatch):
    weights, folder, out, seen, refined = _splat_test_setup(tiny, tmp_path, monkeypatch)
    assert main(["--quiet", "splat", str(out), "--test", str(folder / "c.png"), "--model", str(weights)]) == 0
    assert seen["localized_in"] is refined and seen["n"] == 1
    assert seen["align_steps"] == 100 and seen["budget"] == 120.0  # the defaults
    assert main(["--quiet", "splat", str(out), "--test", str(folder / "c.png"), "--model", str(weights),
                 "--test-align-steps", "0"]) == 0  # 0: the localized pose
    assert seen["align_steps"] == 0


def test_splat_refuses_a_negative_budget_before_the_fit(tiny, tmp_path, monkeypatch, capsys):
    import pointmap.splat

    monkeypatch.setattr(pointmap.splat, "run", lambda *a, **k: pytest.fail("the fit ran"))
    _save_test_recon(tmp_path / "rec")
    assert main(["splat", str(tmp_path / "rec"), "--splat-budget", "-5"]) == 2
    assert "--splat-budget expected seconds >= 0" in capsys.readouterr().err


def test_localize_names_the_reference_view_it_posed_against_and_pairs_with_2_references_by_default(
        tiny, tmp_path, monkeypatch):
    import json

    import pointmap.localization

    weights, folder = tiny
    rec = tmp_path / "rec"
    assert main(["--quiet", "reconstruct", str(folder / "a.jpg"), str(folder / "b.PNG"), "--model", str(weights),
                 "--size", "64", "-o", str(rec), "--export", "npz"]) == 0
    seen = {}

    def localize(model, recon, images, **kw):
        seen.update(kw)
        return pointmap.localization.Localization(torch.eye(4, dtype=torch.float64).repeat(2, 1, 1),
                                                  torch.eye(3, dtype=torch.float64).repeat(2, 1, 1), [0, 1],
                                                  [1.0, 1.0], [1.0, 1.0], ["c.png", "a.jpg"])

    monkeypatch.setattr(pointmap.localization, "localize", localize)
    out = tmp_path / "loc"
    assert main(["--quiet", "localize", str(rec), str(folder / "c.png"), str(folder / "a.jpg"), "--model",
                 str(weights), "-o", str(out)]) == 0
    rows = json.loads((out / "localization.json").read_text())["queries"]
    assert [r["reference"] for r in rows] == ["a.jpg", "b.PNG"] and seen["n_refs"] == 2


def test_localize_takes_max_frames_of_a_video_and_one_frame_is_enough(tmp_path, monkeypatch):
    import pointmap.checkpoint
    from tests.test_video import _video

    monkeypatch.setattr(pointmap.checkpoint, "load_model", _stop)  # the frames are read before the model loads
    _save_test_recon(tmp_path / "rec")
    video = _video(tmp_path / "walk.avi", n=12)
    for n in (3, 1):
        out = tmp_path / f"loc{n}"
        with pytest.raises(_Reached):
            main(["--quiet", "localize", str(tmp_path / "rec"), str(video), "-o", str(out), "--max-frames", str(n)])
        assert len(list((out / "frames").glob("walk_*.png"))) == n


def test_info_says_whether_the_model_has_a_pose_head_and_where_an_official_checkpoint_came_from(tmp_path, capsys):
    from dataclasses import replace

    plain = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "plain.safetensors",
                          provenance={"note": "a test"})
    posed = pm.save_model(pm.PointmapNet(replace(pm.PRESETS["test"], pose_head=True)), tmp_path / "posed.safetensors",
                          provenance={"source": "official", "ctor": "AsymmetricCroCo3DStereo(...)"})
    assert main(["info", str(plain)]) == 0
    out = capsys.readouterr().out
    assert "pose head no" in out and "source: official" not in out and "note: a test" in out
    assert main(["info", str(posed)]) == 0
    out = capsys.readouterr().out
    assert "pose head yes" in out and "source: official checkpoint, AsymmetricCroCo3DStereo(...)" in out


def test_demo_runs_the_model_it_is_given(tmp_path, monkeypatch):
    import pointmap.demo

    seen = {}
    monkeypatch.setattr(pointmap.demo, "run_demo", lambda out, **kw: seen.update(kw) or 0)
    assert main(["--quiet", "demo", "-o", str(tmp_path / "d"), "--model", "base", "--device", "cpu"]) == 0
    assert seen["model_name"] == "base" and seen["quiet"] is True


def test_info_counts_an_onnx_graphs_external_data_beside_it_in_its_size(tmp_path):
    from pointmap.cli import model_summary

    (tmp_path / "m.onnx").write_bytes(b"g" * 100_000)
    (tmp_path / "m.onnx.data").write_bytes(b"w" * 2_000_000)  # the weights, saved as external data
    assert model_summary(pm.PointmapNet(pm.PRESETS["test"]), str(tmp_path / "m.onnx"))["megabytes"] == 2.1
