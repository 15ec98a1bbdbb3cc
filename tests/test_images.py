"""load_images: orientation, colour conversion, the official resize/crop, the kept transform, bad input."""

import numpy as np
import pytest
import torch
from PIL import Image

import pointmap as pm
from pointmap.errors import ImageError
from pointmap.reconstruction import K_to_map, K_to_original


@pytest.mark.parametrize("wh,expected", [((640, 480), (512, 384)), ((600, 400), (512, 336)),
                                         ((1920, 1080), (512, 288)), ((800, 800), (512, 384)),
                                         ((480, 640), (384, 512))])
def test_size_512_matches_the_official_crops(wh, expected):
    v = pm.load_images([np.zeros((wh[1], wh[0], 3), np.uint8)], size=512)[0]
    assert (v.img.shape[2], v.img.shape[1]) == expected
    assert v.original_size == wh


@pytest.mark.parametrize("size", [256, 336, 352, 384, 448, 512, 640])
def test_a_square_image_becomes_a_4_3_landscape_of_whole_patches_at_every_size(size):
    v = pm.load_images([np.zeros((700, 700, 3), np.uint8)], size=size)[0]
    h, w = v.img.shape[1:]
    assert w == size and h % 16 == 0 and w % 16 == 0
    assert abs(h / w - 0.75) < 16 / w  # the nearest 4:3 crop in whole patches, never taller


def test_size_224_resizes_the_short_side_and_crops_a_centred_square():
    v = pm.load_images([np.zeros((480, 640, 3), np.uint8)], size=224)[0]
    assert v.img.shape == (3, 224, 224)
    sx, sy, left, top = v.map_from_original
    assert round(640 * sx) == 299 and top == 0 and left == (299 // 2 - 112)


def test_the_kept_transform_maps_original_pixels_onto_network_pixels():
    # a bright dot at a known original pixel must land where the transform says
    img = np.zeros((480, 640, 3), np.uint8)
    img[300:304, 400:404] = 255
    v = pm.load_images([img], size=512)[0]
    sx, sy, left, top = v.map_from_original
    u = (401.5 + 0.5) * sx - 0.5 - left
    w = (301.5 + 0.5) * sy - 0.5 - top
    ys, xs = np.nonzero(v.img[0].numpy() > 0.5)
    assert abs(xs.mean() - u) < 0.5 and abs(ys.mean() - w) < 0.5


def test_intrinsics_round_trip_between_original_and_map_pixels():
    K = torch.tensor([[[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]])
    t = torch.tensor([[0.8, 0.8, 0.0, 64.0]])
    assert torch.allclose(K_to_original(K_to_map(K, t), t), K)
    assert torch.allclose(K_to_map(K, t)[0, 1, 2], torch.tensor((239.5 + 0.5) * 0.8 - 0.5 - 64))


def test_exif_orientation_is_applied(tmp_path):
    im = Image.fromarray(np.zeros((100, 200, 3), np.uint8))
    exif = im.getexif()
    exif[0x0112] = 6  # rotate 90 degrees
    im.save(tmp_path / "r.jpg", exif=exif)
    assert pm.load_images([tmp_path / "r.jpg"], size=512)[0].original_size == (100, 200)


def test_a_photograph_with_a_malformed_exif_block_still_loads_turned_by_its_orientation(tmp_path):
    from PIL import ImageOps

    im = Image.fromarray(np.arange(20 * 30 * 3, dtype=np.uint8).reshape(20, 30, 3))
    exif = im.getexif()
    exif[0x0112] = 6  # stored 30 x 20, upright 20 x 30
    exif[0x0110] = "CAMERA"  # the model tag, ASCII text
    im.save(tmp_path / "r.jpg", exif=exif)
    data = bytearray((tmp_path / "r.jpg").read_bytes())
    at = data.find(bytes([0x01, 0x10, 0x00, 0x02]))  # its entry: tag 0x0110, type ASCII (Pillow writes big endian)
    assert at > 0
    data[at + 1] = 0x1A  # now XResolution, a rational tag holding text: Pillow's rewrite fails on it
    (tmp_path / "bad.jpg").write_bytes(bytes(data))
    with Image.open(tmp_path / "bad.jpg") as probe:
        with pytest.raises(TypeError):
            ImageOps.exif_transpose(probe)
    assert pm.load_images([tmp_path / "bad.jpg"], size=64)[0].original_size == (20, 30)
    assert np.array_equal(pm.load_images([tmp_path / "bad.jpg"], size=64)[0].img,
                          pm.load_images([tmp_path / "r.jpg"], size=64)[0].img)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_the_fallback_for_a_malformed_exif_turns_every_orientation_as_pillow_does(orientation, monkeypatch):
    from PIL import ImageOps

    from pointmap.images import upright

    im = Image.fromarray(np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3))  # no symmetry
    im.getexif()[0x0112] = orientation
    want = np.asarray(ImageOps.exif_transpose(im))  # a turned copy (im.copy() would lose the tag)
    assert im.getexif().get(0x0112) == orientation and (want.shape[0] == 6) == (orientation >= 5)

    def malformed(_):
        raise TypeError("a rational tag holding text")

    monkeypatch.setattr(ImageOps, "exif_transpose", malformed)
    assert np.array_equal(np.asarray(upright(im)), want)


def test_a_pil_image_is_turned_by_its_exif_as_its_file_and_a_truncated_or_closed_one_is_refused(tmp_path):
    im = Image.fromarray(np.random.default_rng(0).integers(0, 255, (60, 100, 3), dtype=np.uint8))
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(tmp_path / "r.jpg", exif=exif)
    from_file = pm.load_images([tmp_path / "r.jpg"], size=64)[0]
    with Image.open(tmp_path / "r.jpg") as opened:
        from_pil = pm.load_images([opened], size=64)[0]
    assert from_pil.original_size == from_file.original_size == (60, 100)
    data = (tmp_path / "r.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[:len(data) // 2])
    with Image.open(tmp_path / "cut.jpg") as cut:
        with pytest.raises(pm.ImageError, match="image 0: the PIL image cannot be read"):
            pm.load_images([cut], size=64)
    closed = Image.open(tmp_path / "r.jpg")
    closed.close()
    with pytest.raises(pm.ImageError, match="image 0: the PIL image cannot be read"):
        pm.load_images([closed], size=64)


def test_a_big_endian_16_bit_array_loads_as_its_native_twin_and_0_255_floats_are_named(tmp_path):
    native = np.random.default_rng(0).integers(0, 65535, (32, 48, 3)).astype(np.uint16)
    a = pm.load_images([native], size=32)[0].img
    b = pm.load_images([native.astype(">u2")], size=32)[0].img
    assert torch.equal(a, b)
    with pytest.raises(pm.ImageError, match=r"got values in \[0, 255\] \(0-255 floats\? divide by 255\)"):
        pm.load_images([np.linspace(0, 255, 32 * 48 * 3).reshape(32, 48, 3)], size=32)


def save_with_focal_35mm(path, wh, f35, orientation=1):
    """A JPEG of size wh whose EXIF says f35 (FocalLengthIn35mmFilm, in the Exif sub-IFD) and orientation."""
    im = Image.fromarray(np.full((wh[1], wh[0], 3), 128, np.uint8))
    exif = im.getexif()
    exif[0x0112] = orientation
    exif.get_ifd(0x8769)[0xA405] = f35
    im.save(path, exif=exif)
    return path


def test_exif_focals_put_the_35mm_equivalent_focal_on_each_photographs_diagonal(tmp_path):
    from pointmap.images import exif_focals

    # a 3:2 photograph taken at 36 mm equivalent sees exactly what 36 mm of film width sees: f = its width in pixels
    wide = save_with_focal_35mm(tmp_path / "wide.jpg", (300, 200), 36)
    turned = save_with_focal_35mm(tmp_path / "turned.jpg", (300, 200), 36, orientation=6)  # read as 200x300
    phone = save_with_focal_35mm(tmp_path / "phone.jpg", (400, 300), 26)  # 4:3, the diagonal's 500 px at 26 mm
    unknown = save_with_focal_35mm(tmp_path / "unknown.jpg", (300, 200), 0)  # 0: the camera did not know
    Image.fromarray(np.zeros((20, 30, 3), np.uint8)).save(tmp_path / "plain.png")
    f = exif_focals([wide, turned, phone, unknown, tmp_path / "plain.png", np.zeros((20, 30, 3), np.uint8),
                     Image.open(wide)])
    assert f[0] == pytest.approx(300, rel=1e-3) and f[1] == pytest.approx(300, rel=1e-3)
    assert f[2] == pytest.approx(26 * 500 / np.hypot(36, 24), rel=1e-9)
    assert f[3:6] == [None, None, None] and f[6] == pytest.approx(300, rel=1e-3)
    (tmp_path / "bad.jpg").write_bytes(b"not an image")
    with pytest.raises(ImageError, match="not a readable image"):
        exif_focals([wide, tmp_path / "bad.jpg"])
    with pytest.raises(ImageError, match="image not found"):
        exif_focals(tmp_path / "missing.jpg")


def save_with_camera(path, wh, make="Apple", model="iPhone 13", lens="iPhone 13 back camera 5.1mm f/1.6",
                     focal_mm=5.1, zoom=None, orientation=1):
    """A JPEG of size wh whose EXIF names its camera: make and model (NUL-padded, as cameras write them), lens model,
    focal length in mm and digital zoom (each left out when None)."""
    from PIL.TiffImagePlugin import IFDRational

    im = Image.fromarray(np.full((wh[1], wh[0], 3), 128, np.uint8))
    exif = im.getexif()
    exif[0x0112] = orientation
    for tag, value in ((0x010F, make and make + "\x00"), (0x0110, model)):
        if value is not None:
            exif[tag] = value
    sub = exif.get_ifd(0x8769)
    for tag, value in ((0xA434, lens), (0x920A, focal_mm), (0xA404, zoom)):
        if value is not None:
            sub[tag] = value if isinstance(value, str) else IFDRational(round(value * 100), 100)
    im.save(path, exif=exif)
    return path


def test_exif_cameras_name_each_photographs_camera_and_one_camera_needs_one_body_and_one_size(tmp_path):
    from pointmap.images import exif_camera_labels, exif_cameras

    a, b = (save_with_camera(tmp_path / f"{n}.jpg", (40, 30)) for n in "ab")
    cams = exif_cameras([a, b, np.zeros((30, 40, 3), np.uint8)])
    assert cams[0].body == ("Apple", "iPhone 13", "iPhone 13 back camera 5.1mm f/1.6", 5.1, 1.0)  # NUL stripped
    assert cams[0].size == (40, 30) and cams[0].focal_35mm is None and cams[0].focal_px is None and cams[2] is None
    assert exif_camera_labels(cams) == [0, 0, 1]  # an array carries no EXIF: a camera of its own
    others = {  # each differs from a in one thing that changes the focal in pixels, or says nothing of it
        "ultrawide": dict(lens="iPhone 13 back camera 1.54mm f/2.4", focal_mm=1.54),
        "zoomed": dict(zoom=2.0),
        "tele": dict(lens=None, focal_mm=7.0),
        "turned": dict(orientation=6),  # read as 30x40
        "no_focal": dict(focal_mm=None),
        "no_make": dict(make=None),
    }
    for name, kw in others.items():
        cam = exif_cameras(save_with_camera(tmp_path / f"{name}.jpg", (40, 30), **kw))[0]
        assert exif_camera_labels([cams[0], cam, cams[1]]) == [0, 1, 0], name
    assert exif_cameras(tmp_path / "turned.jpg")[0].size == (30, 40)
    assert exif_cameras(tmp_path / "no_focal.jpg")[0].body is None
    unzoomed = exif_cameras(save_with_camera(tmp_path / "z0.jpg", (40, 30), zoom=0.0))[0]  # 0: no digital zoom
    assert exif_camera_labels([cams[0], unzoomed]) == [0, 0]


def test_a_photograph_whose_exif_block_cannot_be_parsed_gives_its_size_as_read_and_no_camera(tmp_path, monkeypatch):
    import sys

    from pointmap.images import exif_cameras

    path = save_with_camera(tmp_path / "t.jpg", (40, 30), orientation=6)
    getexif = Image.Image.getexif

    def broken_in_the_header_read(self):  # fails as on a mangled EXIF block; the loader's own read succeeds
        if sys._getframe(1).f_code.co_name == "exif_cameras":
            raise SyntaxError("not a TIFF file")
        return getexif(self)

    monkeypatch.setattr(Image.Image, "getexif", broken_in_the_header_read)
    cam = exif_cameras(path)[0]
    assert cam.size == (30, 40) and cam.body is None and cam.focal_35mm is None  # as the loader reads it: turned


def test_heic_photographs_are_read_through_pillow_heif_and_refused_by_name_without_it(tmp_path, monkeypatch):
    import sys

    pillow_heif = pytest.importorskip("pillow_heif")
    from pointmap.images import exif_cameras

    pillow_heif.register_heif_opener()
    im = Image.fromarray(np.zeros((48, 64, 3), np.uint8))
    im.paste((255, 255, 255), (0, 0, 16, 16))  # a white corner: top left as read
    exif = im.getexif()
    exif[0x010F], exif[0x0110] = "Apple", "iPhone 13"
    exif.get_ifd(0x8769)[0x920A] = 5.1
    im.save(tmp_path / "IMG_0001.HEIC", quality=95, exif=exif)
    view = pm.load_images([tmp_path / "IMG_0001.HEIC"], size=64, whole=True)[0]
    assert view.original_size == (64, 48) and view.name == "IMG_0001.HEIC"
    assert float(view.img[:, :8, :8].mean()) > 0.9 and float(view.img[:, -8:, -8:].mean()) < 0.1
    assert exif_cameras(tmp_path / "IMG_0001.HEIC")[0].body[:2] == ("Apple", "iPhone 13")
    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # not installed: the import fails
    with pytest.raises(ImageError, match=r"IMG_0001.HEIC is a HEIC / HEIF photograph: reading it needs pillow-heif "
                                         r"\(pip install 'pointmap\[heic\]', or pillow-heif\)"):
        pm.load_images([tmp_path / "IMG_0001.HEIC"], size=64)


def test_gray_rgba_and_16_bit_images_become_rgb(tmp_path):
    Image.fromarray(np.full((64, 64), 128, np.uint8)).save(tmp_path / "g.png")
    Image.fromarray(np.zeros((64, 64, 4), np.uint8)).save(tmp_path / "a.png")  # transparent -> white
    Image.fromarray(np.full((64, 64), 65535, np.uint16)).save(tmp_path / "d.png")
    g, a, d = pm.load_images([tmp_path / "g.png", tmp_path / "a.png", tmp_path / "d.png"], size=224)
    assert g.img.shape[0] == 3 and abs(float(g.img.mean()) - 128 / 255) < 1e-3
    assert float(a.img.min()) > 0.99
    assert float(d.img.min()) > 0.99


def test_an_rgba_or_16_bit_picture_loads_the_same_from_its_file_and_from_its_array(tmp_path):
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (64, 64, 4), dtype=np.uint8)  # partly transparent: composited on white
    dim16 = rng.integers(0, 4096, (64, 64), dtype=np.uint16)  # a dim 16-bit picture: not stretched to its maximum
    Image.fromarray(rgba).save(tmp_path / "a.png")
    Image.fromarray(dim16).save(tmp_path / "d.png")
    for name, arr in (("a.png", rgba), ("d.png", dim16)):
        from_file, from_array = pm.load_images([tmp_path / name, arr], size=64)
        assert torch.equal(from_file.img, from_array.img), name
    assert float(pm.load_images([dim16], size=64)[0].img.mean()) < 0.05  # 2,048 of 65,535 on average


def test_bad_images_raise_image_errors_naming_the_file(tmp_path):
    (tmp_path / "x.jpg").write_text("not an image")
    with pytest.raises(pm.ImageError, match="x.jpg"):
        pm.load_images([tmp_path / "x.jpg"])
    with pytest.raises(pm.ImageError, match="not found"):
        pm.load_images([tmp_path / "missing.png"])
    (tmp_path / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")  # a video where an image was expected
    with pytest.raises(pm.ImageError, match="expected an image file, got a video: .*clip.mp4 \\(reconstruct and "
                                            "localize take videos"):
        pm.load_images([tmp_path / "clip.mp4"])
    with pytest.raises(pm.ImageError, match="smaller than one"):
        pm.load_images([np.zeros((8, 8, 3), np.uint8)])
    with pytest.raises(pm.ImageError, match=r"image image_000.png: 2000x16 is too elongated: resized for size 32 it "
                                            r"is 32x0"):  # PIL's own error before
        pm.load_images([np.zeros((16, 2000, 3), np.uint8)], size=32)
    with pytest.raises(pm.ImageError, match="shape"):
        pm.load_images([np.zeros((8, 8, 3, 2), np.uint8)])
    with pytest.raises(pm.ImageError, match="size"):
        pm.load_images([np.zeros((64, 64, 3), np.uint8)], size=500)
    for too_big in (2064, 5120, 10**6):  # refused before any resize: a typo for 512 would exhaust memory
        with pytest.raises(pm.ImageError, match=f"from 32 to 2048 \\(e.g. 512\\), got {too_big}"):
            pm.load_images([np.zeros((64, 64, 3), np.uint8)], size=too_big)
    assert pm.load_images([np.zeros((16, 16, 3), np.uint8)], size=2048)[0].img.shape == (3, 1536, 2048)  # a square at 4:3, as at 512
    with pytest.raises(pm.ImageError, match="from 32 to 2048 \\(e.g. 512\\), got 16"):  # a 4:3 crop 16 x 0
        pm.load_images([np.zeros((100, 100, 3), np.uint8)], size=16)
    assert pm.load_images([np.zeros((100, 100, 3), np.uint8)], size=32)[0].img.shape == (3, 16, 32)
    with pytest.raises(pm.ImageError, match="with pixels, got shape \\(0, 0, 3\\)"):
        pm.load_images([np.zeros((0, 0, 3), np.float32)])
    half = np.random.default_rng(0).random((32, 32, 3)).astype(np.float16)  # float16 is a float in [0, 1] too
    assert torch.equal(pm.load_images([half], size=32)[0].img, pm.load_images([half.astype(np.float32)], size=32)[0].img)


def test_a_pil_image_loads_exactly_as_its_array_and_a_tensor_is_refused_with_the_conversion_to_use():
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    from_pil = pm.load_images(Image.fromarray(arr), size=32)[0]
    from_arr = pm.load_images([arr], size=32)[0]
    assert torch.equal(from_pil.img, from_arr.img) and from_pil.original_size == (80, 60)
    with pytest.raises(pm.ImageError, match="got Tensor \\(a \\[3, H, W\\] tensor: pass img.permute"):
        pm.load_images([torch.zeros(3, 64, 64)])
    with pytest.raises(pm.ImageError, match="expected a list of image paths, arrays or PIL images, got int"):
        pm.load_images(123)


def test_a_pil_image_of_any_mode_loads_as_its_file_does_16_bit_palette_alpha_and_float(tmp_path):
    dim16 = np.full((32, 32), 32896, np.uint16)  # half scale: 128
    pal = Image.new("P", (32, 32), 0)
    pal.putpalette([0, 0, 0] * 256)
    pal.info["transparency"] = 0  # every pixel transparent: white
    grey = Image.fromarray(np.full((32, 32), 0.5, np.float32), mode="F")
    grey.save(tmp_path / "f.tif")
    for im, want in ((Image.fromarray(dim16), 128), (pal, 255), (grey, 128)):
        pil = pm.load_images(im, size=32)[0].img
        assert abs(float(pil.mean()) * 255 - want) < 1, im.mode
    assert abs(float(pm.load_images([tmp_path / "f.tif"], size=32)[0].img.mean()) * 255 - 128) < 1  # not black
    Image.fromarray(np.full((32, 32), 7.0, np.float32), mode="F").save(tmp_path / "hot.tif")
    with pytest.raises(pm.ImageError, match=r"hot.tif: a 32-bit float image must be finite and in \[0, 1\]"):
        pm.load_images([tmp_path / "hot.tif"], size=32)


def test_an_image_too_large_to_decode_safely_is_an_image_error(tmp_path, monkeypatch):
    Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(tmp_path / "big.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 4,096 pixels: over twice the limit, Pillow's bomb error
    with pytest.raises(pm.ImageError, match="too large to read safely"):
        pm.load_images([tmp_path / "big.png"], size=32)


def test_whole_keeps_each_photographs_field_of_view_at_its_own_shape_even_at_224_with_the_transform_exact():
    land, port, square = np.zeros((480, 640, 3), np.uint8), np.zeros((640, 480, 3), np.uint8), np.zeros((300, 300, 3), np.uint8)
    land[300:304, 400:404] = 255
    port[200:204, 100:104] = 255
    views = pm.load_images([land, port, square], size=224, whole=True)
    assert [v.shape for v in views] == [(160, 224), (224, 160), (224, 224)]  # 224 x 168 cut to whole patches
    for v, (x, y) in zip(views, [(401.5, 301.5), (101.5, 201.5)]):  # each dot lands where the transform says
        sx, sy, left, top = v.map_from_original
        ys, xs = np.nonzero(v.img[0].numpy() > 0.5)
        assert abs(xs.mean() - ((x + 0.5) * sx - 0.5 - left)) < 0.5
        assert abs(ys.mean() - ((y + 0.5) * sy - 0.5 - top)) < 0.5
    assert [v.shape for v in pm.load_images([land, square], size=224)] == [(224, 224)] * 2  # the default: squares
    assert pm.load_images([square], size=512, whole=True)[0].shape == (512, 512)  # not cut to 4:3
    with pytest.raises(pm.ImageError, match="whole expected True or False, got 'yes'"):
        pm.load_images([land], size=224, whole="yes")
