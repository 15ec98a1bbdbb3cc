"""Unit tests for pointmap/images.py written from a mutation review: each closes a gap the existing tests left open.

Self-contained: every image is made here with numpy / PIL under tmp_path. The last four tests are of bugs the review
found (session 90): a grey or RGB PNG's transparency key, a multi-frame file left open, a path given as bytes.
"""

import gc
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

import pointmap as pm
from pointmap.images import exif_cameras, image_sizes, read_rgb


def rgb_noise(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


# --- the size rule -----------------------------------------------------------------------------------------------

def test_a_size_that_is_a_multiple_of_8_but_not_of_16_is_refused():
    with pytest.raises(pm.ImageError, match="size expected 224 or a multiple of 16"):
        pm.load_images([rgb_noise(64, 64)], size=520)


def test_a_numpy_integer_size_is_taken_as_the_int_it_is():
    assert pm.load_images([rgb_noise(48, 64)], size=np.int64(64))[0].shape == (48, 64)


# --- arrays ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(32, 32, 2), (2, 32, 32, 3)])
def test_an_array_of_two_channels_or_of_four_dimensions_is_refused_naming_its_shape(shape):
    with pytest.raises(pm.ImageError, match=r"expected an HxWx3 \(or HxW, HxWx4\) array with pixels, got shape"):
        pm.load_images([np.zeros(shape, np.uint8)], size=32)


def test_an_hxwx1_array_loads_as_its_grey_hxw_twin():
    grey = rgb_noise(32, 48)[..., 0]
    assert np.array_equal(read_rgb(grey[..., None]), read_rgb(grey))
    assert np.array_equal(read_rgb(grey), np.repeat(grey[..., None], 3, axis=-1))


@pytest.mark.parametrize("bad,got", [(np.nan, "non-finite values"), (-0.25, r"values in \[-0.25, 0.5\]")])
def test_a_float_array_with_nan_or_negative_values_is_refused(bad, got):
    arr = np.full((32, 32, 3), 0.5, np.float32)
    arr[0, 0, 0] = bad
    with pytest.raises(pm.ImageError, match=f"float arrays must be finite and in \\[0, 1\\], got {got}"):
        pm.load_images([arr], size=32)


def test_a_float_array_loads_as_its_values_times_255_rounded_to_the_nearest():
    x = np.random.default_rng(1).random((32, 48, 3)).astype(np.float32)
    assert np.array_equal(read_rgb(x), np.round(x.astype(np.float64) * 255).astype(np.uint8))


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.int8, bool])
def test_an_array_of_any_other_dtype_than_uint8_uint16_or_float_is_refused_naming_it(dtype):
    with pytest.raises(pm.ImageError, match="expected dtype uint8, uint16 or float in \\[0, 1\\], got"):
        pm.load_images([np.zeros((32, 32, 3), dtype)], size=32)


# --- files -------------------------------------------------------------------------------------------------------

def test_a_directory_is_refused_as_a_directory_not_as_an_unreadable_image(tmp_path):
    with pytest.raises(pm.ImageError, match="expected an image file, got a directory"):
        pm.load_images([tmp_path], size=32)


def test_a_truncated_jpeg_file_is_an_image_error_naming_the_file(tmp_path):
    Image.fromarray(rgb_noise(128, 128)).save(tmp_path / "full.jpg", quality=95)
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[:len(data) // 2])
    with pytest.raises(pm.ImageError, match=r"not a readable image: .*cut.jpg \(OSError\)"):
        pm.load_images([tmp_path / "cut.jpg"], size=32)


def test_loading_or_reading_the_exif_of_a_heic_photograph_registers_pillow_heifs_opener_first(tmp_path, monkeypatch):
    pillow_heif = pytest.importorskip("pillow_heif")
    pillow_heif.register_heif_opener()
    Image.fromarray(rgb_noise(48, 64)).save(tmp_path / "IMG.heic")
    calls = []
    register = pillow_heif.register_heif_opener

    def spy(*args, **kwargs):
        calls.append("called")
        return register(*args, **kwargs)

    monkeypatch.setattr(pillow_heif, "register_heif_opener", spy)
    pm.load_images([tmp_path / "IMG.heic"], size=32)
    assert len(calls) == 1
    exif_cameras(tmp_path / "IMG.heic")
    assert len(calls) == 2


# --- colour conversion -------------------------------------------------------------------------------------------

def test_a_pil_float_image_holding_nan_is_refused():
    grey = np.full((32, 32), 0.5, np.float32)
    grey[3, 3] = np.nan
    with pytest.raises(pm.ImageError, match=r"a 32-bit float image must be finite and in \[0, 1\]"):
        pm.load_images(Image.fromarray(grey, mode="F"), size=32)


def test_a_32_bit_integer_grey_image_maps_0_65535_onto_0_255_clipped_at_both_ends():
    values = np.array([[-5, 0, 32896, 65535, 100000]], np.int32).repeat(4, axis=0)
    im = Image.fromarray(values)
    assert im.mode == "I"
    assert read_rgb(im)[0, :, 0].tolist() == [0, 0, 128, 255, 255]


def test_the_transparent_pixels_of_a_grey_png_with_alpha_load_white(tmp_path):
    la = np.zeros((32, 32, 2), np.uint8)
    la[:, 16:] = (60, 255)  # the right half opaque grey 60, the left half transparent black
    Image.fromarray(la, mode="LA").save(tmp_path / "la.png")
    rgb = read_rgb(tmp_path / "la.png")
    assert (rgb[:, :16] == 255).all() and (rgb[:, 16:] == 60).all()


def test_a_half_transparent_black_pixel_is_composited_to_mid_grey_on_white():
    rgba = np.zeros((32, 32, 4), np.uint8)
    rgba[..., 3] = 128
    assert abs(int(read_rgb(rgba)[0, 0, 0]) - 127) <= 1  # 255 * (1 - 128 / 255)


def test_a_red_image_is_red_in_read_rgb_and_in_channel_0_of_the_network_input():
    red = np.zeros((32, 32, 3), np.uint8)
    red[..., 0] = 255
    assert read_rgb(red)[0, 0].tolist() == [255, 0, 0]
    img = pm.load_images([red], size=32)[0].img
    assert torch.equal(img[0], torch.ones(16, 32)) and float(img[1:].abs().max()) == 0


# --- sizes and EXIF --------------------------------------------------------------------------------------------

def test_image_sizes_are_width_by_height_after_exif_orientation(tmp_path):
    im = Image.fromarray(rgb_noise(30, 40))
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(tmp_path / "turned.jpg", exif=exif)
    assert image_sizes([rgb_noise(30, 40), tmp_path / "turned.jpg"]) == [(40, 30), (30, 40)]


def save_jpeg_with_exif(path, wh=(40, 30), orientation=1, f35=None, make="Apple", model="iPhone 13", focal_mm=None):
    im = Image.fromarray(rgb_noise(wh[1], wh[0]))
    exif = im.getexif()
    exif[0x0112] = orientation
    for tag, value in ((0x010F, make), (0x0110, model)):
        if value is not None:
            exif[tag] = value
    sub = exif.get_ifd(0x8769)
    if f35 is not None:
        sub[0xA405] = f35
    if focal_mm is not None:
        sub[0x920A] = focal_mm
    im.save(path, exif=exif)
    return path


@pytest.mark.parametrize("f35", [2, 10000])
def test_a_35mm_equivalent_focal_outside_4_to_5000_mm_is_taken_as_junk(tmp_path, f35):
    cam = exif_cameras(save_jpeg_with_exif(tmp_path / "a.jpg", f35=f35))[0]
    assert cam.focal_35mm is None and cam.focal_px is None


def test_a_non_finite_exif_focal_length_gives_no_camera_body(tmp_path):
    from PIL.TiffImagePlugin import IFDRational

    cam = exif_cameras(save_jpeg_with_exif(tmp_path / "a.jpg", focal_mm=IFDRational(1, 0)))[0]  # 1/0: no number
    assert cam.body is None


def test_a_make_of_padding_only_or_no_model_gives_no_camera_body(tmp_path):
    assert exif_cameras(save_jpeg_with_exif(tmp_path / "a.jpg", make="  \x00", focal_mm=5.1))[0].body is None
    assert exif_cameras(save_jpeg_with_exif(tmp_path / "b.jpg", model=None, focal_mm=5.1))[0].body is None
    assert exif_cameras(save_jpeg_with_exif(tmp_path / "c.jpg", focal_mm=5.1))[0].body is not None  # the control


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_cameras_give_the_size_the_loader_reads_for_every_orientation(tmp_path, orientation):
    path = save_jpeg_with_exif(tmp_path / "a.jpg", wh=(40, 30), orientation=orientation)
    assert exif_cameras(path)[0].size == image_sizes(path)[0] == ((30, 40) if orientation >= 5 else (40, 30))


def test_exif_cameras_refuse_a_bad_array_as_the_loader_does():
    with pytest.raises(pm.ImageError, match="got shape"):
        exif_cameras([np.zeros((8, 8, 3, 2), np.uint8)])


# --- resize and crop ---------------------------------------------------------------------------------------------

def test_an_image_resized_to_under_a_patch_is_refused_naming_its_resized_size():
    with pytest.raises(pm.ImageError, match="40x4000 is too elongated: resized for size 512 it is 5x512"):
        pm.load_images([np.zeros((4000, 40, 3), np.uint8)], size=512)


@pytest.mark.parametrize("wh,size,resized,resample", [((300, 200), 256, (256, 171), Image.LANCZOS),
                                                      ((100, 75), 256, (256, 192), Image.BICUBIC)])
def test_the_network_input_is_a_lanczos_downscale_or_a_bicubic_upscale_then_a_centred_crop(wh, size, resized,
                                                                                          resample):
    arr = rgb_noise(wh[1], wh[0])
    v = pm.load_images([arr], size=size)[0]
    sx, sy, left, top = v.map_from_original
    h, w = v.shape
    want = np.asarray(Image.fromarray(arr).resize(resized, resample))[int(top):int(top) + h, int(left):int(left) + w]
    assert np.array_equal((v.img * 255).round().byte().permute(1, 2, 0).numpy(), want)


def test_a_nearly_square_photograph_that_resizes_to_a_square_is_cut_to_4_3():
    assert pm.load_images([np.zeros((2000, 2001, 3), np.uint8)], size=512)[0].shape == (384, 512)


@pytest.mark.parametrize("wh,expected", [((400, 600), (341 / 400, 512 / 600, 2.0, 0.0)),
                                         ((600, 400), (512 / 600, 341 / 400, 0.0, 2.0))])
def test_the_crop_is_centred_and_map_from_original_holds_each_axis_own_scale_exactly(wh, expected):
    v = pm.load_images([np.zeros((wh[1], wh[0], 3), np.uint8)], size=512)[0]
    assert v.map_from_original == expected  # the resized 341 px side cut to 336 about its centre: 2 px off each end


def test_an_image_under_a_patch_on_its_short_side_only_is_refused():
    with pytest.raises(pm.ImageError, match="is 100x8: smaller than one 16x16 patch"):
        pm.load_images([np.zeros((8, 100, 3), np.uint8)], size=512)


def test_views_are_indexed_by_their_position_in_the_input_list():
    views = pm.load_images([rgb_noise(32, 32, s) for s in range(3)], size=32)
    assert [v.index for v in views] == [0, 1, 2] and [v.name for v in views] == [
        "image_000.png", "image_001.png", "image_002.png"]


def test_an_empty_list_is_refused():
    with pytest.raises(pm.ImageError, match="load_images expected at least one image, got none"):
        pm.load_images([], size=32)


def test_square_ok_keeps_a_square_image_square():
    assert pm.load_images([np.zeros((100, 100, 3), np.uint8)], size=64, square_ok=True)[0].shape == (64, 64)
    assert pm.load_images([np.zeros((100, 100, 3), np.uint8)], size=64)[0].shape == (48, 64)


def test_photographs_without_a_camera_body_each_get_a_camera_label_of_their_own(tmp_path):
    from pointmap.images import exif_camera_labels

    bare = exif_cameras([save_jpeg_with_exif(tmp_path / f"{n}.jpg", make=None) for n in "ab"])
    assert [c.body for c in bare] == [None, None]
    assert exif_camera_labels(bare + [None, None]) == [0, 1, 2, 3]


# --- bugs the review found ---------------------------------------------------------------------------------------

def test_the_transparent_pixels_of_a_grey_png_with_a_transparency_key_load_white_as_a_palette_pngs_do(tmp_path):
    grey = np.full((32, 32), 100, np.uint8)
    grey[:, :16] = 0  # the transparent key: the left half
    Image.fromarray(grey).save(tmp_path / "g.png", transparency=0)
    with Image.open(tmp_path / "g.png") as im:
        assert im.mode == "L" and im.info["transparency"] == 0  # a tRNS chunk, not an alpha channel
    rgb = read_rgb(tmp_path / "g.png")
    assert (rgb[:, :16] == 255).all() and (rgb[:, 16:] == 100).all()


def test_the_transparent_pixels_of_an_rgb_png_with_a_transparency_key_load_white(tmp_path):
    rgb = np.full((32, 32, 3), (10, 200, 30), np.uint8)
    rgb[:, :16] = 0
    Image.fromarray(rgb).save(tmp_path / "c.png", transparency=(0, 0, 0))
    out = read_rgb(tmp_path / "c.png")
    assert (out[:, :16] == 255).all() and (out[:, 16:] == (10, 200, 30)).all()


@pytest.mark.parametrize("name", ["a.gif", "pages.tif"])
def test_reading_a_multi_frame_file_leaves_no_file_open(tmp_path, name):
    frames = [Image.fromarray(np.full((32, 32, 3), v, np.uint8)) for v in (10, 200)]
    frames[0].save(tmp_path / name, save_all=True, append_images=frames[1:])  # an animated GIF, a 2-page TIFF
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResourceWarning)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            pm.load_images([tmp_path / name], size=32)
            gc.collect()
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)]


def test_a_bytes_path_given_alone_is_named_as_a_path_not_as_its_first_byte(tmp_path):
    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(tmp_path / "a.png")
    path = str(tmp_path / "a.png").encode()
    with pytest.raises(pm.ImageError, match="got bytes .*os.fsdecode"):  # not "image 0: ... got int"
        pm.load_images(path, size=32)


def test_an_empty_path_is_refused_as_empty_not_as_the_working_directory():
    with pytest.raises(pm.ImageError, match="image 1: expected a path, got an empty one"):
        pm.load_images([np.zeros((32, 32, 3), np.uint8), ""], size=32)
