"""Loading images for the network: read, orient, convert to RGB, resize and crop to a patch multiple.

The transform from the original image to the network input is kept on each View, so intrinsics can be
reported in original pixels (docs/conventions.md).
"""

from __future__ import annotations

import contextlib
import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pointmap.errors import ImageError, is_int

PATCH = 16
# The network's cost grows with the fourth power of the input size (attention over (size / 16)^2 tokens): 2048 is
# already 256 times 512's, and a typo such as 5120 for 512 would run for hours or exhaust memory without a word.
MAX_INPUT_SIZE = 2048
MIN_INPUT_SIZE = 2 * PATCH  # a square photograph's 4:3 crop keeps one patch of height
INPUT_SIZE_RULE = f"224 or a multiple of {PATCH} from {MIN_INPUT_SIZE} to {MAX_INPUT_SIZE} (e.g. 512)"


@dataclass
class View:
    """One image prepared for the network.

    img: [3, h, w] float32 in [0, 1], h and w multiples of 16
    original_size: (width, height) of the image as given (after EXIF orientation)
    map_from_original: (sx, sy, left, top): u_map = (u_orig + 0.5) * sx - 0.5 - left (same for v)
    name: file name (or ``image_007.png`` for arrays)
    index: position in the input list
    """

    img: torch.Tensor
    original_size: tuple
    map_from_original: tuple
    name: str
    index: int

    @property
    def shape(self) -> tuple:
        """(h, w) of the network input."""
        return tuple(self.img.shape[-2:])


def is_input_size(size) -> bool:
    """Whether ``size`` is an input size ``load_images`` takes: 224 (the official 224 models' crop), or a multiple of
    the patch size (16) from two patches (``MIN_INPUT_SIZE``: at one, a 4:3 crop is less than a patch high) up to
    ``MAX_INPUT_SIZE``."""
    return is_int(size) and MIN_INPUT_SIZE <= size <= MAX_INPUT_SIZE and (size == 224 or size % PATCH == 0)


def _as_list(paths_or_arrays, caller: str):
    """One image (a path, an array or a PIL image) as a list of one; an iterable as it is; ImageError otherwise."""
    from PIL import Image

    if isinstance(paths_or_arrays, (str, os.PathLike, np.ndarray, Image.Image)):
        return [paths_or_arrays]
    if isinstance(paths_or_arrays, (bytes, bytearray)):  # iterated, it would be a list of ints
        raise ImageError(f"{caller} expected a list of image paths, arrays or PIL images, got bytes (a path as bytes: "
                         "pass os.fsdecode(path))")
    if not hasattr(paths_or_arrays, "__iter__"):
        raise ImageError(f"{caller} expected a list of image paths, arrays or PIL images, got "
                         f"{type(paths_or_arrays).__name__}")
    return paths_or_arrays


HEIF_SUFFIXES = (".heic", ".heif")  # an iPhone's photographs: read through the optional pillow-heif


def open_heif_ready(path) -> None:
    """Before PIL opens ``path``: for a HEIC / HEIF photograph, pillow-heif's opener registered with PIL (it applies
    the file's rotation and mirroring as it decodes); ImageError naming the optional dependency when it is not
    installed. Nothing for other files."""
    if Path(path).suffix.lower() not in HEIF_SUFFIXES:
        return
    try:
        import pillow_heif
    except ImportError:
        raise ImageError(f"{path} is a HEIC / HEIF photograph: reading it needs pillow-heif (pip install "
                         "'pointmap[heic]', or pillow-heif)") from None
    pillow_heif.register_heif_opener()


def _read(src, index: int):
    from PIL import Image, UnidentifiedImageError

    if isinstance(src, Image.Image):  # a PIL image: the file rule for its mode (16-bit grey, palette, alpha)
        try:
            src.load()  # decoded now: a truncated or closed file is said here, not deep in the resize
            return _to_rgb(upright(src)), f"image_{index:03d}.png"  # turned by its EXIF, as its file would be
        except (OSError, ValueError, SyntaxError) as e:
            raise ImageError(f"image {index}: the PIL image cannot be read ({e.__class__.__name__}: {e})") from None
    if isinstance(src, np.ndarray):
        arr = src
        name = f"image_{index:03d}.png"
        if arr.ndim == 2:
            arr = np.repeat(arr[..., None], 3, axis=-1)
        if arr.ndim != 3 or arr.shape[-1] not in (1, 3, 4) or arr.size == 0:
            raise ImageError(f"image {index}: expected an HxWx3 (or HxW, HxWx4) array with pixels, got shape "
                             f"{arr.shape}")
        if arr.shape[-1] == 1:
            arr = np.repeat(arr, 3, axis=-1)
        if arr.dtype.byteorder not in ("=", "|"):  # e.g. big-endian 16-bit, as some FITS / TIFF readers give
            arr = arr.astype(arr.dtype.newbyteorder("="))
        if arr.dtype == np.uint16:  # as a 16-bit file: 0-65535 onto 0-255
            arr = (arr / 257.0).round().astype(np.uint8)
        elif np.issubdtype(arr.dtype, np.floating):  # float16, float32, float64
            arr = arr.astype(np.float64)
            if not np.isfinite(arr).all() or arr.min() < 0 or arr.max() > 1:
                got = "non-finite values" if not np.isfinite(arr).all() else \
                    f"values in [{arr.min():.3g}, {arr.max():.3g}] (0-255 floats? divide by 255)"
                raise ImageError(f"image {index}: float arrays must be finite and in [0, 1], got {got}")
            arr = (arr * 255).round().astype(np.uint8)
        elif arr.dtype != np.uint8:
            raise ImageError(f"image {index}: expected dtype uint8, uint16 or float in [0, 1], got {arr.dtype}")
        return _to_rgb(Image.fromarray(np.ascontiguousarray(arr))), name
    if not isinstance(src, (str, os.PathLike)):
        raise ImageError(f"image {index}: expected a path, an HxWx3 numpy array or a PIL image, got "
                         f"{type(src).__name__}" + (" (a [3, H, W] tensor: pass img.permute(1, 2, 0).numpy())"
                                                    if isinstance(src, torch.Tensor) else ""))
    if os.fspath(src) in ("", b""):  # Path("") is the working directory
        raise ImageError(f"image {index}: expected a path, got an empty one")
    path = Path(src)
    if not path.exists():
        raise ImageError(f"image not found: {path}")
    if path.is_dir():
        raise ImageError(f"expected an image file, got a directory: {path}")
    open_heif_ready(path)
    try:
        with Image.open(path) as im:  # closed once turned: a multi-frame file (GIF, TIFF) keeps its file open
            im.load()
            im = upright(im)
    except Image.DecompressionBombError as e:
        raise ImageError(f"{path} is too large to read safely ({e}); downscale it first") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        from pointmap.video import is_video

        if is_video(path):  # e.g. `pointmap pair clip.mp4 a.jpg`: a video is frames, not one image
            raise ImageError(f"expected an image file, got a video: {path} (reconstruct and localize take videos and "
                             f"read their frames; pointmap.video.extract_frames writes them as images)") from None
        raise ImageError(f"not a readable image: {path} ({e.__class__.__name__})") from None
    try:
        return _to_rgb(im), path.name
    except ValueError as e:
        raise ImageError(f"{path}: {e}") from None


def upright(im):
    """``im`` turned by its EXIF orientation (``ImageOps.exif_transpose``), also when the rest of its EXIF is
    malformed: Pillow rewrites the block as it turns the image and can fail on a tag of the wrong type (a
    TypeError or struct.error), so the turn is then made from the orientation tag alone."""
    import struct

    from PIL import Image, ImageOps

    try:
        return ImageOps.exif_transpose(im)
    except (TypeError, struct.error, KeyError, IndexError):
        turn = {2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
                5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
                8: Image.Transpose.ROTATE_90}.get(im.getexif().get(0x0112))
        return im.transpose(turn) if turn is not None else im.copy()


def _to_rgb(im):
    """RGB of any PIL image, one rule for files and arrays: 16-bit (and 32-bit integer) grey maps 0-65535 onto
    0-255, as a 16-bit photograph's full scale (not stretched to each image's own maximum, which would give the
    views of one scene different exposures); 32-bit float grey (mode F) must be finite and in [0, 1], as float
    arrays (ValueError otherwise); transparency is composited on white."""
    from PIL import Image

    if im.mode == "F":
        a = np.asarray(im, dtype=np.float64)
        if not np.isfinite(a).all() or a.min() < 0 or a.max() > 1:
            raise ValueError(f"a 32-bit float image must be finite and in [0, 1], got values in "
                             f"[{np.nanmin(a):.4g}, {np.nanmax(a):.4g}]")
        return Image.fromarray((a * 255).round().astype(np.uint8)).convert("RGB")
    if im.mode in ("I;16", "I;16B", "I;16L", "I"):
        a = np.clip(np.asarray(im).astype(np.float64) / 257.0, 0, 255).round().astype(np.uint8)
        return Image.fromarray(a).convert("RGB")
    if im.mode in ("RGBA", "LA", "P", "PA") or (im.mode in ("L", "RGB") and "transparency" in im.info):
        im = im.convert("RGBA")
        bg = Image.new("RGBA", im.size, (255, 255, 255, 255))
        return Image.alpha_composite(bg, im).convert("RGB")
    return im if im.mode == "RGB" else im.convert("RGB")


def read_rgb(src) -> np.ndarray:
    """One image (a path or an array, as ``load_images`` takes) as the [H, W, 3] uint8 RGB array the loader
    starts from: EXIF orientation applied, 16-bit scaled, alpha composited on white. ImageError when unreadable."""
    return np.asarray(_read(src, 0)[0])


def image_sizes(paths_or_arrays) -> list[tuple[int, int]]:
    """(width, height) of each image as ``load_images`` reads it (EXIF orientation applied): the "original
    pixels" that known intrinsics refer to."""
    return [_read(src, i)[0].size for i, src in enumerate(_as_list(paths_or_arrays, "image_sizes"))]


# An EXIF 35 mm-equivalent focal length scales the 36x24 mm frame's diagonal onto the image's diagonal, as phone and
# compact-camera makers compute it (their crop factor is the sensor's diagonal against this one)
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD, ORIENTATION, MAKE, MODEL = 0x8769, 0x0112, 0x010F, 0x0110  # the Exif sub-IFD; tags of the first IFD
FOCAL_MM, DIGITAL_ZOOM, FOCAL_35MM, LENS_MODEL = 0x920A, 0xA404, 0xA405, 0xA434  # tags of the Exif sub-IFD
FOCAL_35MM_RANGE = (4, 5000)  # fisheye to the longest telephoto; 0 means unknown, and other values are junk


@dataclass(frozen=True)
class ExifCamera:
    """What a photograph's EXIF says of the camera that took it.

    size: (width, height) as the loader reads it (EXIF orientation applied)
    focal_35mm: FocalLengthIn35mmFilm in mm, None when absent, 0 (unknown) or out of ``FOCAL_35MM_RANGE``
    body: (make, model, lens model, focal length in mm, digital zoom), or None unless make, model and focal length
        are all there. Photographs of one ``body`` and one ``size`` were taken by one camera at one zoom: they share
        one focal length in pixels (the lens model tells a phone's cameras apart, the zoom its digital crops).
    """

    size: tuple[int, int]
    focal_35mm: float | None
    body: tuple | None

    @property
    def focal_px(self) -> float | None:
        """The focal length in the image's own pixels from ``focal_35mm`` (any orientation: the diagonal is the
        same): ``f35 * hypot(w, h) / 43.27``; None without one."""
        return None if self.focal_35mm is None else self.focal_35mm * math.hypot(*self.size) / FULL_FRAME_DIAGONAL_MM


def _exif_number(value) -> float | None:
    """An EXIF number (an integer or a rational) as a float; None when absent, not a number or not finite."""
    try:
        out = float(value) if isinstance(value, numbers.Real) else None
    except ZeroDivisionError:  # a rational 0/0
        return None
    return out if out is not None and math.isfinite(out) else None


def _exif_text(value) -> str | None:
    """An EXIF string without its padding (NULs, spaces); None when absent or empty."""
    out = value.strip(" \x00") if isinstance(value, str) else None
    return out or None


def exif_cameras(paths_or_arrays) -> list[ExifCamera | None]:
    """Each image's ``ExifCamera``, read from the file's header (not decoded); None for an array (it carries no EXIF).
    A file without EXIF, or whose EXIF block is broken, gives its size alone. ImageError for a file that is not an
    image; a file whose header reads but whose pixels are cut short (a truncated JPEG) still gives its camera here, and
    the loader refuses it when it decodes the pixels."""
    from PIL import Image

    out = []
    for i, src in enumerate(_as_list(paths_or_arrays, "exif_cameras")):
        if not isinstance(src, (str, os.PathLike, Image.Image)):
            _read(src, i)  # an array carries no EXIF; a bad one is refused as the loader refuses it
            out.append(None)
            continue
        if not isinstance(src, Image.Image):
            open_heif_ready(src)
        try:  # the caller's own PIL image is left open
            with contextlib.nullcontext(src) if isinstance(src, Image.Image) else Image.open(src) as im:
                (w, h), exif = im.size, im.getexif()
                sub = exif.get_ifd(EXIF_IFD)
        except (OSError, ValueError, SyntaxError, TypeError):  # unreadable: the loader's own message
            (w, h), exif, sub = _read(src, i)[0].size, {}, {}  # readable, its EXIF broken: the size as read
        f35 = _exif_number(sub.get(FOCAL_35MM))
        zoom = _exif_number(sub.get(DIGITAL_ZOOM))
        body = (_exif_text(exif.get(MAKE)), _exif_text(exif.get(MODEL)), _exif_text(sub.get(LENS_MODEL)),
                _exif_number(sub.get(FOCAL_MM)), 1.0 if not zoom else zoom)  # a zoom of 0: none used
        out.append(ExifCamera(size=(h, w) if exif.get(ORIENTATION) in (5, 6, 7, 8) else (w, h),
                              focal_35mm=f35 if f35 and FOCAL_35MM_RANGE[0] <= f35 <= FOCAL_35MM_RANGE[1] else None,
                              body=body if None not in (body[0], body[1]) and body[3] else None))
    return out


def exif_focals(paths_or_arrays) -> list[float | None]:
    """Each image's focal length in its own pixels from its EXIF 35 mm-equivalent focal length
    (``ExifCamera.focal_px``); None for an image without one (arrays, most PNGs, video frames, or a value of 0:
    unknown). Exact for a photograph of the sensor's own shape; an in-camera crop to another shape (16:9 from a 3:2
    sensor) keeps the sensor's f35, so the focal comes out a few percent short. FocalLength in millimetres is not
    used: it needs the sensor's size, and the FocalPlaneXResolution that would give it is left stale by editors that
    resize (docs/alignment.md). ImageError for an image the loader cannot read."""
    return [None if cam is None else cam.focal_px for cam in exif_cameras(paths_or_arrays)]


def exif_camera_labels(cameras: list[ExifCamera | None]) -> list[int]:
    """A camera label per photograph (0, 1, ... in order of first appearance): those of one ``body`` and one ``size``
    by their EXIF share one (one camera at one zoom: one focal in pixels); one without a body has its own."""
    first: dict = {}
    return [first.setdefault((c.body, c.size) if c is not None and c.body is not None else ("alone", k), len(first))
            for k, c in enumerate(cameras)]


def prepare(im, size: int, *, square_ok: bool = False, whole: bool = False):
    """Resize and centre-crop a PIL RGB image as the official ``load_images`` does.

    size 224: short side to 224, centre square crop. Other sizes: long side to ``size``, centre crop to
    multiples of 16 (a square image becomes 4:3 landscape unless ``square_ok``). ``whole``: at every size, the long
    side to ``size`` and each side cut to whole patches about the centre (a square stays square): the photograph's
    whole field of view at its own shape.
    Returns (PIL image, (sx, sy, left, top)).
    """
    from PIL import Image

    W, H = im.size
    square = size == 224 and not whole
    square_ok = square_ok or whole
    if square:
        S = min(W, H)
    else:
        S = max(W, H)
    new_w, new_h = round(W * size / S), round(H * size / S)
    if min(new_w, new_h) < PATCH:
        raise ImageError(f"{W}x{H} is too elongated: resized for size {size} it is {new_w}x{new_h}, smaller than "
                         "one patch")
    resample = Image.LANCZOS if S > size else Image.BICUBIC
    im = im.resize((new_w, new_h), resample)
    cx, cy = new_w // 2, new_h // 2
    if square:
        half = min(cx, cy)
        left, top, right, bottom = cx - half, cy - half, cx + half, cy + half
    else:
        halfw = ((2 * cx) // PATCH) * PATCH / 2
        halfh = ((2 * cy) // PATCH) * PATCH / 2
        if not square_ok and new_w == new_h:  # 4:3 landscape, its height a multiple of the patch too
            halfh = (3 * halfw / 4) // (PATCH / 2) * (PATCH / 2)
        left, top, right, bottom = cx - halfw, cy - halfh, cx + halfw, cy + halfh
    im = im.crop((int(left), int(top), int(right), int(bottom)))
    return im, (new_w / W, new_h / H, float(int(left)), float(int(top)))


def load_images(paths_or_arrays, size: int = 512, *, square_ok: bool = False, whole: bool = False) -> list[View]:
    """Read images (paths, HxWx3 uint8 arrays or PIL images) and prepare them for the network (``prepare``:
    224 crops each to a square, as the official code; ``whole=True`` keeps each photograph's field of view at its own
    shape at every size, e.g. 224 x 160 for a 4:3 landscape at 224).

    Example:
        >>> views = load_images([np.zeros((480, 640, 3), np.uint8)], size=512)
        >>> views[0].img.shape, views[0].original_size
        (torch.Size([3, 384, 512]), (640, 480))
    """
    paths_or_arrays = _as_list(paths_or_arrays, "load_images")
    if not is_input_size(size):
        raise ImageError(f"size expected {INPUT_SIZE_RULE}, got {size!r}")
    for name, flag in (("square_ok", square_ok), ("whole", whole)):
        if not isinstance(flag, bool):
            raise ImageError(f"{name} expected True or False, got {flag!r}")
    views = []
    for i, src in enumerate(paths_or_arrays):
        im, name = _read(src, i)
        W, H = im.size
        if min(W, H) < PATCH:
            raise ImageError(f"image {name} is {W}x{H}: smaller than one {PATCH}x{PATCH} patch")
        try:
            prepared, transform = prepare(im, size, square_ok=square_ok, whole=whole)
        except ImageError as e:
            raise ImageError(f"image {name}: {e}") from None
        if min(prepared.size) < PATCH:
            raise ImageError(f"image {name} ({W}x{H}) is too elongated: its crop at size {size} is "
                             f"{prepared.size[0]}x{prepared.size[1]}, smaller than one patch")
        img = torch.from_numpy(np.asarray(prepared, dtype=np.uint8).copy()).permute(2, 0, 1).float() / 255.0
        views.append(View(img=img, original_size=(W, H), map_from_original=transform, name=name, index=i))
    if not views:
        raise ImageError("load_images expected at least one image, got none")
    return views
