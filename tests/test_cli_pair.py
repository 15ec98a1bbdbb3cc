"""`pointmap pair` end to end on two images, with a tiny model saved to disk."""

import numpy as np
import pytest
import torch

import pointmap as pm
from pointmap.cli import main
from pointmap.io_pair import write_pair_outputs


def test_the_pair_command_writes_pointmaps_matches_and_previews_for_two_images(tmp_path, capsys):
    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    import cv2

    rng = np.random.default_rng(0)
    for k in range(2):
        cv2.imwrite(str(tmp_path / f"im{k}.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    out = tmp_path / "out"
    assert main(["pair", str(tmp_path / "im0.png"), str(tmp_path / "im1.png"), "-o", str(out),
                 "--model", str(weights), "--size", "64"]) == 0
    assert "view 2 relative to view 1: rotation" in capsys.readouterr().out
    names = sorted(p.name for p in out.iterdir())
    assert names == ["conf1.png", "conf2.png", "depth1.png", "depth2.png", "matches.png", "pair.npz", "pair.ply"]
    from pointmap.io_pair import PAIR_OUTPUTS

    assert sorted(PAIR_OUTPUTS) == names  # the names the input check below guards
    # -o the folder of an input named as an output: refused before the model loads, the photograph untouched
    (out / "depth1.png").write_bytes((tmp_path / "im0.png").read_bytes())
    before = (out / "depth1.png").read_bytes()
    assert main(["pair", str(out / "depth1.png"), str(tmp_path / "im1.png"), "-o", str(out),
                 "--model", "no_such_model"]) == 2
    assert "would overwrite the input(s)" in capsys.readouterr().err and (out / "depth1.png").read_bytes() == before
    z = np.load(out / "pair.npz")
    assert z["pts1_cam1"].shape[-1] == 3 and z["pts1_cam1"].shape[:2] == z["conf1"].shape
    assert np.isfinite(z["pts1_cam1"]).all() and z["cam2world_2_in_1"].shape == (4, 4)


def test_the_pair_command_given_one_image_twice_warns_that_the_pose_has_no_baseline(tmp_path, capsys):
    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    import cv2

    cv2.imwrite(str(tmp_path / "im0.png"), np.random.default_rng(0).integers(0, 255, (60, 80, 3), dtype=np.uint8))
    with pytest.warns(UserWarning, match="im0.png and im0.png are the same image: no baseline"):
        assert main(["--quiet", "pair", str(tmp_path / "im0.png"), str(tmp_path / "im0.png"), "-o",
                     str(tmp_path / "out"), "--model", str(weights), "--size", "64"]) == 0
    printed = capsys.readouterr().out
    assert "towards" not in printed and "no translation direction (the same image twice: no baseline" in printed


def test_the_pair_command_refuses_a_missing_image_with_exit_code_2(tmp_path, capsys):
    assert main(["pair", str(tmp_path / "nope.png"), str(tmp_path / "nope2.png"), "-o", str(tmp_path / "o"),
                 "--model", "small"]) == 2
    assert "image not found" in capsys.readouterr().err


def test_the_pair_command_stores_given_focals_and_refuses_malformed_ones(tmp_path, capsys):
    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    import cv2

    rng = np.random.default_rng(1)
    for k in range(2):
        cv2.imwrite(str(tmp_path / f"im{k}.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    ims = [str(tmp_path / "im0.png"), str(tmp_path / "im1.png")]
    out = tmp_path / "out"
    assert main(["pair", *ims, "-o", str(out), "--model", str(weights), "--size", "64", "--focal", "70,90"]) == 0
    assert "focal 70 / 90 px (original pixels, given)" in capsys.readouterr().out
    z = np.load(out / "pair.npz")
    # stored in the original images' pixels, as given (the maps' are those times map_from_original)
    assert bool(z["focal_given"]) and str(z["focal_units"]) == "original"
    assert abs(float(z["focal1"]) - 70) < 1e-3 and abs(float(z["focal2"]) - 90) < 1e-3
    # a file written before the focals were stored in original pixels (the maps' pixels, no focal_units) reads alike
    from pointmap.cli import pair_summary

    old = {k: z[k] for k in z.files if k != "focal_units"}
    old["focal1"], old["focal2"] = z["focal1"] * z["map_from_original1"][0], z["focal2"] * z["map_from_original2"][0]
    np.savez(tmp_path / "old.npz", **old)
    assert "focal 70 / 90 px (original pixels, given)" in pair_summary(tmp_path / "old.npz")
    # called directly, malformed focals and output folders are refused before the model runs
    from pointmap.errors import ShapeError
    from pointmap.io_pair import write_pair_outputs

    for bad_focal, bad_out, message in ((500.0, out, "two positive focal lengths in pixels .* got 500.0"),
                                        (None, 3, "out expected a folder path, got int")):
        with pytest.raises(ShapeError, match=message):
            write_pair_outputs(pm.load_model(weights), *ims, bad_out, focal=bad_focal)
    assert np.isfinite(z["cam2world_2_in_1"]).all() or np.isnan(z["cam2world_2_in_1"]).all()
    for bad in ("abc", "-5", "1,2,3", "nan"):
        assert main(["pair", *ims, "-o", str(out), "--model", str(weights), "--size", "64", "--focal", bad]) == 2
        err = capsys.readouterr().err
        assert "focal" in err and bad in err


def test_the_reconstruct_command_holds_given_focals_fixed_with_the_principal_point_at_each_image_centre(tmp_path,
                                                                                                       capsys):
    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    import cv2

    rng = np.random.default_rng(2)
    ims = []
    for k in range(3):
        ims.append(str(tmp_path / f"im{k}.png"))
        cv2.imwrite(ims[-1], rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    out = tmp_path / "out"
    args = ["--quiet", "reconstruct", *ims, "-o", str(out), "--model", str(weights), "--size", "64", "--export", "npz"]
    assert main([*args, "--focal", "70,75,80"]) == 0
    K = load_npz(out / "reconstruction.npz").K.double()
    assert torch.allclose(K[:, 0, 0], torch.tensor([70.0, 75.0, 80.0], dtype=torch.float64), atol=1e-3)
    assert torch.allclose(K[:, 1, 1], K[:, 0, 0])
    assert torch.allclose(K[:, 0, 2], torch.full((3,), 39.5, dtype=torch.float64), atol=1e-3)
    assert torch.allclose(K[:, 1, 2], torch.full((3,), 29.5, dtype=torch.float64), atol=1e-3)
    for extra in ([], ["--refine"]):  # one focal estimated for the three images, kept by the sparse refinement
        assert main([*args, "--shared-focal", *extra]) == 0
        f = load_npz(out / "reconstruction.npz").K[:, 0, 0].double()
        assert float(f.max() - f.min()) == 0.0, (extra, f)
    capsys.readouterr()
    assert main([*args, "--shared-focal", "--focal", "70,75,80"]) == 2
    assert "--shared-focal says one camera, but --focal gives 3 different focals" in capsys.readouterr().err
    cv2.imwrite(ims[2], rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))  # same aspect, another size
    assert main([*args, "--shared-focal"]) == 2
    assert "all of one size" in capsys.readouterr().err
    for bad in ("70,75", "0", "inf"):
        assert main([*args, "--focal", bad]) == 2
        err = capsys.readouterr().err
        assert "--focal expected F, 3 comma-separated values" in err and bad in err


def test_focal_exif_holds_each_photographs_EXIF_35mm_equivalent_focal_and_names_those_without_one(tmp_path, capsys):
    from PIL import Image

    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    rng = np.random.default_rng(3)
    ims = []
    for k, f35 in enumerate((24, 36, 50)):  # 3:2 photographs: f = f35 / 36 x the width of 90 px
        im = Image.fromarray(rng.integers(0, 255, (60, 90, 3), dtype=np.uint8))
        exif = im.getexif()
        exif.get_ifd(0x8769)[0xA405] = f35
        ims.append(str(tmp_path / f"im{k}.jpg"))
        im.save(ims[-1], exif=exif)
    out = tmp_path / "out"
    args = ["--quiet", "reconstruct", *ims, "-o", str(out), "--model", str(weights), "--size", "64", "--export", "npz"]
    assert main([*args, "--focal", "exif"]) == 0
    K = load_npz(out / "reconstruction.npz").K.double()
    capsys.readouterr()
    assert main(args[1:]) == 0  # without --quiet and without the flag: a note names it
    assert "the photographs carry EXIF focal lengths; --focal exif would" in capsys.readouterr().err
    assert torch.allclose(K[:, 0, 0], torch.tensor([60.0, 90.0, 125.0], dtype=torch.float64), rtol=1e-3)
    assert main(["pair", *ims[:2], "-o", str(tmp_path / "pair"), "--model", str(weights), "--size", "64",
                 "--focal", "EXIF"]) == 0
    assert "focal 60 / 90 px (original pixels, given)" in capsys.readouterr().out
    Image.fromarray(rng.integers(0, 255, (60, 90, 3), dtype=np.uint8)).save(tmp_path / "plain.jpg")
    assert main(["--quiet", "reconstruct", *ims, str(tmp_path / "plain.jpg"), *args[len(ims) + 2:],
                 "--focal", "exif"]) == 2
    err = capsys.readouterr().err
    assert "--focal exif expected every image to carry an EXIF 35 mm-equivalent focal" in err
    assert "1 of 4 have none: plain.jpg" in err
    assert main(["reconstruct", *ims, str(tmp_path / "plain.jpg"), *args[len(ims) + 2:]]) == 0
    assert "EXIF focal" not in capsys.readouterr().err  # not every photograph carries one: no note


def test_photographs_of_one_camera_by_their_EXIF_share_one_estimated_focal_unless_told_otherwise(tmp_path, capsys):
    from PIL import Image

    from pointmap.io import load_npz

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    rng = np.random.default_rng(4)

    def photo(name, model, focal_mm):
        im = Image.fromarray(rng.integers(0, 255, (60, 90, 3), dtype=np.uint8))
        exif = im.getexif()
        if model is not None:
            exif[0x010F], exif[0x0110] = model.split()[0], model
            exif.get_ifd(0x8769)[0x920A] = focal_mm
        im.save(tmp_path / name, exif=exif)
        return str(tmp_path / name)

    ims = [photo(f"im{k}.jpg", "Canon EOS 80D", 35) for k in range(3)]
    out = tmp_path / "out"
    args = ["-o", str(out), "--model", str(weights), "--size", "64", "--export", "npz"]

    def focals():
        return load_npz(out / "reconstruction.npz").K[:, 0, 0].tolist()

    assert main(["reconstruct", *ims, *args]) == 0
    assert "one estimated focal per camera: 3 photographs of one camera by their EXIF (Canon EOS 80D, 35 mm, 90x60) " \
           "(--no-shared-focal: one per image)" in capsys.readouterr().err
    assert len(set(focals())) == 1
    assert main(["reconstruct", *ims, *args, "--no-shared-focal"]) == 0
    assert "one estimated focal per camera" not in capsys.readouterr().err
    assert len(set(focals())) == 3  # one per photograph, as asked
    # two cameras (the zoom lens turned to 50 mm for two of them) and a photograph without EXIF: three focals
    mixed = [ims[0], photo("z0.jpg", "Canon EOS 80D", 50), ims[1], photo("plain.jpg", None, None),
             photo("z1.jpg", "Canon EOS 80D", 50)]
    assert main(["reconstruct", *mixed, *args]) == 0
    assert "one estimated focal per camera: 2 photographs of one camera by their EXIF (Canon EOS 80D, 35 mm, 90x60); " \
           "2 photographs of one camera by their EXIF (Canon EOS 80D, 50 mm, 90x60); the other 1 image(s) each its " \
           "own" in capsys.readouterr().err
    f = focals()
    assert f[0] == f[2] and f[1] == f[4] and len(set(f)) == 3
    assert main(["--quiet", "reconstruct", *ims[:2], photo("z2.jpg", "Canon EOS 80D", 50), *args]) == 0
    assert len(set(focals())) == 2  # two of one camera, one of another: 2 focals


def test_the_pair_command_gives_two_photographs_of_one_camera_one_focal_by_their_EXIF_or_when_told(tmp_path, capsys,
                                                                                                    monkeypatch):
    from PIL import Image

    import pointmap.pose

    own = iter([])  # each pass's own focal (map pixels): 50 for the forward pass, 72 for the reverse one

    def focal_from_prediction(pred):  # the random test model's pointmaps give none
        return torch.tensor([next(own)])

    monkeypatch.setattr(pointmap.pose, "focal_from_prediction", focal_from_prediction)
    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    rng = np.random.default_rng(5)

    def photo(name, shape=(60, 90), camera=True):
        im = Image.fromarray(rng.integers(0, 255, (*shape, 3), dtype=np.uint8))
        exif = im.getexif()
        if camera:
            exif[0x010F], exif[0x0110] = "Apple", "iPhone 13"
            exif.get_ifd(0x8769)[0x920A] = 5
        im.save(tmp_path / name, exif=exif)
        return str(tmp_path / name)

    a, b = photo("a.jpg"), photo("b.jpg")
    out = tmp_path / "out"
    own = iter([50.0, 72.0] * 20)
    assert main(["pair", a, b, "-o", str(out), "--model", str(weights), "--size", "64"]) == 0
    captured = capsys.readouterr()
    assert "one estimated focal per camera: 2 photographs of one camera by their EXIF (Apple iPhone 13, 5 mm, " \
           "90x60)" in captured.err
    assert "(original pixels, one shared)" in captured.out
    z = np.load(out / "pair.npz")
    assert float(z["focal1"]) == float(z["focal2"]) and bool(z["focal_shared"])
    sx = pm.load_images([a], size=64)[0].map_from_original[0]  # the geometric mean 60, in original pixels
    assert float(z["focal1"]) == pytest.approx(60.0 / sx, rel=1e-6)
    model = pm.load_model(weights)
    assert main(["pair", a, b, "-o", str(out), "--model", str(weights), "--size", "64", "--no-shared-focal"]) == 0
    assert "one shared" not in capsys.readouterr().out and not bool(np.load(out / "pair.npz")["focal_shared"])
    c = photo("c.jpg", camera=False)  # no EXIF camera: one focal each unless told
    assert main(["pair", a, c, "-o", str(out), "--model", str(weights), "--size", "64"]) == 0
    assert "one shared" not in capsys.readouterr().out
    assert main(["pair", a, c, "-o", str(out), "--model", str(weights), "--size", "64", "--shared-focal"]) == 0
    assert "(original pixels, one shared)" in capsys.readouterr().out
    assert main(["pair", a, b, "-o", str(out), "--model", str(weights), "--focal", "70", "--shared-focal"]) == 2
    assert "--shared-focal applies only without --focal" in capsys.readouterr().err
    # --no-shared-focal with --focal: what --focal means anyway, as reconstruct takes it (refused before)
    assert main(["pair", a, b, "-o", str(out), "--model", str(weights), "--size", "64", "--focal", "70",
                 "--no-shared-focal"]) == 0
    capsys.readouterr()
    tall = photo("tall.jpg", shape=(90, 60))
    assert main(["pair", a, tall, "-o", str(out), "--model", "no/such/model.safetensors", "--size", "64",
                 "--shared-focal"]) == 2  # said before the model loads (a model that does not exist is not read)
    assert "--shared-focal says the two photographs are of one camera, of one size; they are 90x60 and 60x90" in \
        capsys.readouterr().err
    with pytest.raises(pm.PointmapError, match="shared_focal expected True or False, and False with a focal given"):
        write_pair_outputs(model, a, b, tmp_path / "lib", size=64, focal=(70, 70), shared_focal=True)


def test_the_pair_command_takes_a_portrait_and_a_landscape_photograph_each_at_its_own_shape(tmp_path, capsys):
    import cv2

    torch.manual_seed(0)
    weights = pm.save_model(pm.PointmapNet(pm.PRESETS["test"]), tmp_path / "tiny.safetensors")
    rng = np.random.default_rng(2)
    for name, shape in (("wide.png", (60, 80, 3)), ("tall.png", (80, 60, 3))):
        cv2.imwrite(str(tmp_path / name), rng.integers(0, 255, shape, dtype=np.uint8))
    out = tmp_path / "out"
    assert main(["pair", str(tmp_path / "wide.png"), str(tmp_path / "tall.png"), "-o", str(out), "--model",
                 str(weights), "--size", "64"]) == 0
    z = np.load(out / "pair.npz")
    assert z["pts1_cam1"].shape == (48, 64, 3) and z["pts2_cam1"].shape == (64, 48, 3)
    assert z["img1"].shape == (48, 64, 3) and z["img2"].shape == (64, 48, 3)
    assert "focal" in capsys.readouterr().out


def test_a_pair_whose_pose_is_not_found_is_not_recorded_as_refined_on_matches(tmp_path, monkeypatch):
    import cv2

    import pointmap.pose

    monkeypatch.setattr(pointmap.pose, "relative_pose", lambda *a, **k: torch.full((1, 4, 4), float("nan")))
    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"])
    rng = np.random.default_rng(1)
    for k in range(2):
        cv2.imwrite(str(tmp_path / f"im{k}.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    write_pair_outputs(model, tmp_path / "im0.png", tmp_path / "im1.png", tmp_path / "out", size=64, quiet=True)
    z = np.load(tmp_path / "out" / "pair.npz")
    assert not np.isfinite(z["cam2world_2_in_1"]).any() and not bool(z["refined_on_matches"])
