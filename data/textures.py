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
DEFAULT_PHOTO_DIRS = ("/usr/share/backgrounds/mate/nature",)  # Debian/Ubuntu package mate-backgrounds
_PHOTO_MAX_SIDE = 1024


class PhotoCollection:
    """Photographs under ``dirs`` (files with PHOTO_SUFFIXES, sorted by path), decoded lazily and kept at
    most 1024 px on their long side. ``fingerprint`` (sha256 of the sorted names and byte sizes) identifies
    the collection, so shards rendered from another collection are detectable."""

    def __init__(self, dirs) -> None:
        import hashlib
        from pathlib import Path

        self.dirs = tuple(str(d) for d in dirs)
        files = []
        for d in self.dirs:
            root = Path(d)
            if root.is_dir():
                files += sorted(p for p in root.rglob("*") if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
        if not files:
            raise FileNotFoundError(f"no photographs ({', '.join(PHOTO_SUFFIXES)}) found under {list(self.dirs)}; "
                                    "install one (e.g. `apt-get install mate-backgrounds`) or pass --photo-dirs")
        self.files = files
        h = hashlib.sha256()
        for p in files:
            h.update(f"{p.name}:{p.stat().st_size}\n".encode())
        self.fingerprint = h.hexdigest()[:16]
        self._cache: dict = {}

    def __len__(self) -> int:
        return len(self.files)

    def image(self, k: int) -> np.ndarray:
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
    """One PhotoCollection per set of directories and process (decoded images are reused)."""
    key = tuple(str(d) for d in dirs)
    if key not in _COLLECTIONS:
        _COLLECTIONS[key] = PhotoCollection(key)
    return _COLLECTIONS[key]


def photo_texture(rng: np.random.Generator, photos: PhotoCollection, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A texture from a random crop of a random photograph (scale 10-60 % of its short side, random quarter
    turn and flips, mild colour gain), mirrored 2x2 so that it tiles without seams under repeat wrapping."""
    _check(rng, size)
    img = photos.image(int(rng.integers(len(photos))))
    h, w = img.shape[:2]
    side = max(8, int(min(h, w) * rng.uniform(0.1, 0.6)))
    y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    crop = np.rot90(img[y0:y0 + side, x0:x0 + side], int(rng.integers(4)))
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    half = cv2.resize(np.ascontiguousarray(crop), (size // 2, size // 2), interpolation=cv2.INTER_AREA)
    tile = np.concatenate([np.concatenate([half, half[:, ::-1]], 1),
                           np.concatenate([half[::-1], half[::-1, ::-1]], 1)], 0)
    gain = rng.uniform(0.8, 1.2, 3)
    return np.clip(tile.astype(np.float32) * gain, 0, 255).astype(np.uint8)
