"""Procedural textures in numpy/OpenCV: every generator takes a ``np.random.Generator`` and returns
an ``[S, S, 3]`` uint8 RGB image. Most patterns tile seamlessly (spectral noise is periodic; stripes,
checkers and tiles use integer frequencies) because meshes sample them with repeat wrapping.

``random_texture(rng)`` draws one pattern from the whole family; ``TEXTURES`` names them all.
"""

from __future__ import annotations

import cv2
import numpy as np

from pointmap.errors import ShapeError

TEXTURE_SIZE = 256


def _check(rng, size):
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng expected a numpy.random.Generator, got {type(rng).__name__}")
    if not isinstance(size, (int, np.integer)) or size < 8 or size > 4096:
        raise ShapeError(f"texture size expected an int in [8, 4096], got {size!r}")


def random_color(rng: np.random.Generator, *, saturation=(0.1, 0.9), value=(0.2, 1.0)) -> np.ndarray:
    """A random RGB colour in [0, 1] drawn in HSV (hue uniform, given saturation/value ranges)."""
    h = rng.uniform(0, 360)  # float HSV in OpenCV: H in degrees, S and V in [0, 1]
    s = rng.uniform(*saturation)
    v = rng.uniform(*value)
    hsv = np.array([[[h, s, v]]], dtype=np.float32)
    return np.clip(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0], 0, 1).astype(np.float64)


def palette(rng: np.random.Generator, n: int = 3) -> np.ndarray:
    """``n`` colours [n, 3] in [0, 1], often harmonious (near hues), sometimes contrasting."""
    base = random_color(rng)
    cols = [base]
    for _ in range(n - 1):
        if rng.random() < 0.6:
            c = np.clip(base + rng.normal(0, 0.18, 3), 0, 1)
        else:
            c = random_color(rng)
        cols.append(c)
    return np.stack(cols).astype(np.float32)


def colorize(field: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Map a scalar field in [0, 1] through a piecewise-linear colour ramp -> uint8 RGB (via a
    1024-entry lookup table)."""
    cols = np.asarray(cols, np.float64)
    f = np.linspace(0, 1, 1024) * (len(cols) - 1)
    i = np.minimum(f.astype(np.int32), len(cols) - 2)
    t = (f - i)[:, None]
    lut = np.clip((cols[i] * (1 - t) + cols[i + 1] * t) * 255 + 0.5, 0, 255).astype(np.uint8)
    idx = (np.clip(field, 0, 1) * 1023 + 0.5).astype(np.intp)
    return lut[idx]


def _normalize(x: np.ndarray) -> np.ndarray:
    sample = np.sort(x[::7, ::5].ravel())  # robust range from a subsample (1st/99th percentile)
    lo, hi = sample[len(sample) // 100], sample[len(sample) * 99 // 100]
    return np.clip((x - lo) / max(hi - lo, 1e-8), 0, 1)


def fractal_field(rng: np.random.Generator, size: int = TEXTURE_SIZE, *, beta: float | None = None,
                  min_freq: float = 1.0) -> np.ndarray:
    """Periodic 1/f^beta noise in [0, 1] by spectral synthesis (seamless by construction)."""
    _check(rng, size)
    beta = rng.uniform(1.6, 3.2) if beta is None else beta
    fy = np.fft.fftfreq(size)[:, None] * size
    fx = np.fft.rfftfreq(size)[None, :] * size
    f = np.sqrt(fx * fx + fy * fy)
    amp = np.where(f < min_freq, 0.0, 1.0 / np.maximum(f, 1e-6) ** (beta / 2))
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    spec = amp * (np.cos(phase) + 1j * np.sin(phase))
    field = np.fft.irfft2(spec.astype(np.complex64), s=(size, size))
    return _normalize(field.astype(np.float32))


def fractal_noise(rng, size=TEXTURE_SIZE):
    return colorize(fractal_field(rng, size), palette(rng, int(rng.integers(2, 5))))


def _grid(size):
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    return x, y


def stripes(rng, size=TEXTURE_SIZE):
    _check(rng, size)
    x, y = _grid(size)
    a, b = int(rng.integers(0, 4)), int(rng.integers(1, 12))  # integer frequencies keep it periodic
    if rng.random() < 0.5:
        a, b = b, a
    phase = 2 * np.pi * (a * x + b * y)
    if rng.random() < 0.5:
        phase = phase + 0.8 * np.pi * (fractal_field(rng, size) - 0.5)
    wave = 0.5 + 0.5 * np.sin(phase)
    if rng.random() < 0.5:
        wave = (wave > rng.uniform(0.3, 0.7)).astype(np.float32)
    return colorize(wave, palette(rng, 2))


def checkers(rng, size=TEXTURE_SIZE):
    _check(rng, size)
    x, y = _grid(size)
    n = int(rng.choice([2, 4, 6, 8, 12, 16]))
    board = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float32)
    img = colorize(board, palette(rng, 2))
    if rng.random() < 0.4:  # dirt layer
        img = _blend_noise(rng, img, 0.25)
    return img


def tiles(rng, size=TEXTURE_SIZE):
    """Rectangular tiles or running-bond bricks with grout and per-tile colour variation."""
    _check(rng, size)
    nx = int(rng.choice([2, 4, 8]))
    ny = int(rng.choice([2, 4, 8, 16]))
    bricks = rng.random() < 0.5
    base = palette(rng, 2)
    img = np.empty((size, size, 3), np.float32)
    th, tw = size / ny, size / nx
    for r in range(ny):
        off = (tw / 2 if (bricks and r % 2) else 0.0)
        for c in range(-1, nx + 1):
            col = np.clip(base[0] * rng.uniform(0.75, 1.15) + rng.normal(0, 0.03, 3), 0, 1)
            x0, x1 = int(round(c * tw + off)), int(round((c + 1) * tw + off))
            y0, y1 = int(round(r * th)), int(round((r + 1) * th))
            img[y0:y1, max(x0, 0):max(min(x1, size), 0)] = col
            if x1 > size:  # wrap around to keep the texture periodic
                img[y0:y1, 0:x1 - size] = col
    grout = max(1, int(size * rng.uniform(0.006, 0.02)))
    for r in range(ny + 1):
        y = int(round(r * th)) % size
        img[max(y - grout, 0):y + grout] = base[1]
        off = 0
        if r < ny:
            off = (tw / 2 if (bricks and r % 2) else 0.0)
            for c in range(nx + 1):
                x = int(round(c * tw + off)) % size
                y0, y1 = int(round(r * th)), int(round((r + 1) * th))
                img[y0:y1, max(x - grout, 0):x + grout] = base[1]
    img = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    return _blend_noise(rng, img, rng.uniform(0.05, 0.25))


def wood(rng, size=TEXTURE_SIZE):
    _check(rng, size)
    x, y = _grid(size)
    turb = fractal_field(rng, size, beta=2.5)
    freq = int(rng.integers(4, 14))
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (freq * y + 1.5 * turb) + 6 * np.pi * x * 0)
    grain = fractal_field(rng, size, beta=1.2)
    field = 0.75 * rings ** rng.uniform(0.6, 2.0) + 0.25 * grain
    brown = np.array([rng.uniform(0.35, 0.7), rng.uniform(0.2, 0.45), rng.uniform(0.08, 0.25)], np.float32)
    cols = np.stack([brown * 0.55, brown, np.clip(brown * 1.35, 0, 1)])
    if rng.random() < 0.3:
        cols = palette(rng, 3)
    return colorize(field, cols)


def marble(rng, size=TEXTURE_SIZE):
    _check(rng, size)
    x, y = _grid(size)
    turb = fractal_field(rng, size, beta=2.2)
    a, b = int(rng.integers(1, 4)), int(rng.integers(0, 3))
    veins = np.abs(np.sin(2 * np.pi * (a * x + b * y) + rng.uniform(3, 9) * turb))
    field = 1 - veins ** rng.uniform(0.15, 0.5)
    light = np.clip(random_color(rng, saturation=(0.0, 0.15), value=(0.75, 1.0)), 0, 1)
    dark = np.clip(random_color(rng, saturation=(0.0, 0.5), value=(0.1, 0.5)), 0, 1)
    return colorize(field, np.stack([light, light * 0.9 + dark * 0.1, dark]).astype(np.float32))


_FONTS = [cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_DUPLEX,
          cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX]
_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789#&%@$+-=/"


def glyphs(rng, size=TEXTURE_SIZE):
    """Text-like rows of random glyphs (posters, signs, book spines) drawn with cv2.putText."""
    _check(rng, size)
    bg, fg = palette(rng, 2)
    if abs(float(bg.mean() - fg.mean())) < 0.25:
        fg = 1 - bg
    img = np.empty((size, size, 3), np.uint8)
    img[:] = (bg * 255).astype(np.uint8)
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    scale = rng.uniform(0.4, 1.6) * size / 256
    thick = int(rng.integers(1, 3))
    (_, th), _ = cv2.getTextSize("Ag", font, scale, thick)
    line = int(th * rng.uniform(1.6, 2.4)) + 1
    y = line
    while y < size + line:
        n = int(rng.integers(3, 30))
        text = "".join(rng.choice(list(_CHARS), n))
        if rng.random() < 0.5:
            text = " ".join(text[i:i + int(rng.integers(2, 7))] for i in range(0, n, 5))
        colour = tuple(int(c) for c in (np.clip(fg + rng.normal(0, 0.05, 3), 0, 1) * 255))
        cv2.putText(img, text, (int(rng.integers(-20, 10)), y), font, scale, colour, thick, cv2.LINE_AA)
        y += line
    return img


def gradient(rng, size=TEXTURE_SIZE):
    """Linear or radial colour gradients (smooth, low texture but not constant)."""
    _check(rng, size)
    x, y = _grid(size)
    if rng.random() < 0.5:
        ang = rng.uniform(0, 2 * np.pi)
        field = np.abs(np.sin(np.pi * (np.cos(ang) * x + np.sin(ang) * y)))  # periodic triangle-ish ramp
    else:
        cx, cy = rng.uniform(0.2, 0.8, 2)
        d = np.sqrt(np.minimum(np.abs(x - cx), 1 - np.abs(x - cx)) ** 2
                    + np.minimum(np.abs(y - cy), 1 - np.abs(y - cy)) ** 2)
        field = d / d.max()
    return colorize(field.astype(np.float32), palette(rng, int(rng.integers(2, 4))))


def dots(rng, size=TEXTURE_SIZE):
    _check(rng, size)
    bg, fg = palette(rng, 2)
    img = np.empty((size, size, 3), np.uint8)
    img[:] = (bg * 255).astype(np.uint8)
    n = int(rng.integers(10, 200))
    rmax = max(2, int(size * rng.uniform(0.01, 0.08)))
    for _ in range(n):
        c = tuple(int(v) for v in (np.clip(fg + rng.normal(0, 0.1, 3), 0, 1) * 255))
        cx, cy = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(1, rmax + 1))
        for ox in (-size, 0, size):  # draw wrapped copies: seamless tiling
            for oy in (-size, 0, size):
                cv2.circle(img, (cx + ox, cy + oy), r, c, -1, cv2.LINE_AA)
    return img


def _blend_noise(rng, img, amount):
    n = fractal_field(rng, img.shape[0])[..., None]
    out = img.astype(np.float32) * (1 - amount + 2 * amount * n)
    return np.clip(out, 0, 255).astype(np.uint8)


TEXTURES = {
    "noise": fractal_noise, "stripes": stripes, "checkers": checkers, "tiles": tiles, "wood": wood,
    "marble": marble, "glyphs": glyphs, "gradient": gradient, "dots": dots,
}
_WEIGHTS = np.array([3, 1.5, 1, 2, 2, 1.5, 1.5, 0.7, 1], np.float64)


def random_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE, *, kind: str | None = None) -> np.ndarray:
    """One procedural texture ``[size, size, 3]`` uint8; ``kind`` picks a family from ``TEXTURES``."""
    _check(rng, size)
    if kind is None:
        names = list(TEXTURES)
        kind = names[int(rng.choice(len(names), p=_WEIGHTS / _WEIGHTS.sum()))]
    elif kind not in TEXTURES:
        raise ValueError(f"texture kind expected one of {sorted(TEXTURES)}, got {kind!r}")
    img = TEXTURES[kind](rng, size)
    if img.shape != (size, size, 3) or img.dtype != np.uint8:  # pragma: no cover - internal invariant
        raise ShapeError(f"texture {kind} produced {img.shape} {img.dtype}")
    return img


# ---------------------------------------------------------------------------------------------------
# photographs

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp")
# Debian packages (apt-get install mate-backgrounds lomiri-wallpapers-16.04): 12 nature photographs from
# MATE and 15 Ubuntu community photographs ("NAME_by_AUTHOR.jpg", installed straight into backgrounds/).
DEFAULT_PHOTO_DIRS = ("/usr/share/backgrounds/mate/nature", "/usr/share/backgrounds/*_by_*.jpg")
PHOTO_PACKAGES = ("mate-backgrounds", "lomiri-wallpapers-16.04")
_PHOTO_MAX_SIDE = 1024


def _photo_files(source: str):
    """(root, files) of one source: a directory (searched recursively) or a glob pattern of files."""
    from pathlib import Path

    if any(c in source for c in "*?["):
        import glob

        root = Path(source).parent
        while any(c in str(root) for c in "*?["):
            root = root.parent
        files = [Path(p) for p in glob.glob(source, recursive=True)]
    else:
        root = Path(source)
        files = list(root.rglob("*")) if root.is_dir() else []
    files = [p for p in files if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file()]
    return root, sorted(files, key=lambda p: p.relative_to(root).as_posix())


class PhotoCollection:
    """Photographs from ``dirs`` (directories searched recursively for PHOTO_SUFFIXES, or glob patterns),
    in a fixed order, decoded lazily and kept at most 1024 px on their long side. ``fingerprint`` (sha256
    of each source's sorted relative names and byte sizes) identifies the collection, so data rendered
    from another collection is detectable."""

    def __init__(self, dirs) -> None:
        import hashlib

        self.dirs = tuple(str(d) for d in dirs)
        files = []
        h = hashlib.sha256()
        for k, d in enumerate(self.dirs):
            root, found = _photo_files(d)
            for p in found:
                h.update(f"{k}/{p.relative_to(root).as_posix()}:{p.stat().st_size}\n".encode())
            files += found
        if not files:
            raise FileNotFoundError(
                f"no photographs ({', '.join(PHOTO_SUFFIXES)}) found under {list(self.dirs)}; install the "
                f"default collection (`apt-get install {' '.join(PHOTO_PACKAGES)}`), or without root "
                "`apt-get download PKG && dpkg -x PKG_*.deb DIR` and pass --photo-dirs with the photos' "
                "directories, or pass --photo-dirs with any directory of photographs")
        self.files = files
        self.fingerprint = h.hexdigest()[:16]
        self._cache: dict = {}

    def __len__(self) -> int:
        return len(self.files)

    def image(self, k: int) -> np.ndarray:
        """Photograph ``k`` as RGB uint8, long side at most 1024 px."""
        if k not in self._cache:
            img = cv2.imread(str(self.files[k]), cv2.IMREAD_COLOR)
            if img is None:
                raise ValueError(f"cannot decode photograph {self.files[k]}")
            s = _PHOTO_MAX_SIDE / max(img.shape[:2])
            if s < 1:
                img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self._cache[k] = np.ascontiguousarray(img[..., ::-1])
        return self._cache[k]


_COLLECTIONS: dict = {}


def photo_collection(dirs) -> PhotoCollection:
    """The PhotoCollection of these sources, rescanned on every call (a few stats) but with the decoded
    images of this process reused while the fingerprint stays the same."""
    fresh = PhotoCollection(dirs)
    cached = _COLLECTIONS.get(fresh.dirs)
    if cached is not None and cached.fingerprint == fresh.fingerprint:
        return cached
    _COLLECTIONS[fresh.dirs] = fresh
    return fresh


def _wrap_blend(a: np.ndarray, n: int, axis: int) -> np.ndarray:
    """Length n + m -> n along ``axis``, periodic: the first m samples cross-fade into the m past the end."""
    a = np.moveaxis(a, axis, 0)
    m = a.shape[0] - n
    out = a[:n].copy()
    w = ((np.arange(m, dtype=np.float32) + 0.5) / m).reshape((m,) + (1,) * (a.ndim - 1))
    out[:m] = w * a[:m] + (1 - w) * a[n:n + m]
    return np.moveaxis(out, 0, axis)


def photo_texture(rng: np.random.Generator, photos: PhotoCollection, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A texture ``[size, size, 3]`` uint8 from a random photograph: a square crop (side 15-70 % of the
    photo's short side) at a random position and rotation (any angle half of the time, else a quarter
    turn; the rotated square stays inside the photo), maybe mirrored, with colour variation (saturation,
    per-channel gain, gamma). It tiles without seams under repeat wrapping: the crop reaches a quarter
    tile further, and that margin is cross-faded into the opposite edge."""
    _check(rng, size)
    img = photos.image(int(rng.integers(len(photos))))
    h, w = img.shape[:2]
    n = size + size // 4  # pixels warped per side: the tile plus the cross-fade margin
    theta = rng.uniform(0, 2 * np.pi) if rng.random() < 0.5 else int(rng.integers(4)) * np.pi / 2
    c, s = np.cos(theta), np.sin(theta)
    reach = abs(c) + abs(s)  # a rotated square of side L spans L * reach along x and y
    side = min(h, w) * rng.uniform(0.15, 0.7) * n / size
    side = max(8.0, min(side, (min(h, w) - 2) / reach))
    ext = side * reach / 2
    cx = rng.uniform(ext, max(w - ext, ext + 1e-6))
    cy = rng.uniform(ext, max(h - ext, ext + 1e-6))
    # box-filter the bounding region down to the output scale first (no aliasing), then rotate bilinearly
    x0, y0 = max(int(np.floor(cx - ext)) - 1, 0), max(int(np.floor(cy - ext)) - 1, 0)
    x1, y1 = min(int(np.ceil(cx + ext)) + 2, w), min(int(np.ceil(cy + ext)) + 2, h)
    region = img[y0:y1, x0:x1]
    if n < side:
        f = n / side
        region = cv2.resize(region, (max(1, round((x1 - x0) * f)), max(1, round((y1 - y0) * f))),
                            interpolation=cv2.INTER_AREA)
    fx, fy = region.shape[1] / (x1 - x0), region.shape[0] / (y1 - y0)
    # output pixel (u, v) -> region pixel: centre + R(theta) @ ((u + 0.5) * step - side / 2, ...) (inverse map)
    step = side / n
    a = np.array([[c * step * fx, -s * step * fx], [s * step * fy, c * step * fy]])
    t = np.array([(cx - x0) * fx, (cy - y0) * fy]) - 0.5 + a @ np.full(2, 0.5 - n / 2)
    crop = cv2.warpAffine(np.ascontiguousarray(region), np.concatenate([a, t[:, None]], 1), (n, n),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    tile = _wrap_blend(_wrap_blend(crop.astype(np.float32) / 255, size, 1), size, 0)
    grey = tile.mean(axis=2, keepdims=True)
    tile = grey + (tile - grey) * rng.uniform(0.6, 1.3)  # saturation
    tile = np.clip(tile * rng.uniform(0.8, 1.2, 3), 0, 1) ** rng.uniform(0.8, 1.25)  # channel gain, gamma
    return (tile * 255 + 0.5).astype(np.uint8)
