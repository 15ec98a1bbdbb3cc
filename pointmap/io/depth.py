"""Depth maps from files: ``.npy`` (float z-depth, its own units) or 16-bit ``.png`` (times a scale, millimetres
by default), as depth sensors, scanner apps and MVS tools write them. 0, NaN, inf or negative = no depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pointmap.errors import PointmapError

DEPTH_SUFFIXES = (".npy", ".png")


def read_depth(path, png_scale: float = 1e-3) -> np.ndarray:
    """A depth map as float32 [H, W], 0 where there is none. ``png_scale``: units per step of a 16-bit PNG.
    PointmapError for a file that is not a 2-D float .npy or a 16-bit single-channel .png."""
    import cv2

    path = Path(path)
    if path.suffix.lower() == ".npy":
        with open(path, "rb") as fh:
            magic = fh.read(6)
        if magic != b"\x93NUMPY":  # numpy would call any other file "pickled data" and offer allow_pickle
            raise PointmapError(f"{path}: not a .npy file (NumPy's files begin with \\x93NUMPY, this one with "
                                f"{magic!r}); a depth map expected a 2-D float array saved by numpy.save")
        try:
            d = np.load(path, allow_pickle=False)
        except ValueError as e:  # an array of Python objects: numpy refuses it without allow_pickle
            if "allow_pickle" not in str(e):
                raise PointmapError(f"{path}: not a readable .npy depth map ({e})") from None
            raise PointmapError(f"{path}: holds Python objects, not numbers; a depth map expected a 2-D float "
                                f"array (never unpickled: a pickle can run code)") from None
        except OSError as e:
            raise PointmapError(f"{path}: not a readable .npy depth map ({e})") from None
        if d.ndim == 3 and d.shape[-1] == 1:
            d = d[..., 0]
        if d.ndim != 2 or not np.issubdtype(d.dtype, np.floating):
            raise PointmapError(f"{path}: a depth map expected a 2-D float array, got {d.dtype} {list(d.shape)}")
    elif path.suffix.lower() == ".png":
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if d is None or d.ndim != 2 or d.dtype != np.uint16:
            got = "unreadable" if d is None else f"{d.dtype} {list(d.shape)}"
            raise PointmapError(f"{path}: a .png depth map expected a 16-bit single-channel image, got {got}")
        d = d.astype(np.float64) * png_scale
    else:
        raise PointmapError(f"{path}: a depth map expected a {' or '.join(DEPTH_SUFFIXES)} file")
    d = np.asarray(d, np.float32)
    if min(d.shape) < 1:
        raise PointmapError(f"{path}: an empty depth map ({d.shape[1]}x{d.shape[0]})")
    return np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)


def same_aspect(size, other, tol: float = 0.01) -> bool:
    """Whether two (width, height) sizes have one aspect ratio within ``tol`` (relative): a depth map at a sensor's
    resolution belongs to its photograph only then."""
    return abs(size[0] / size[1] - other[0] / other[1]) <= tol * other[0] / other[1]


def depth_file(folders, stem: str) -> Path | None:
    """The first ``<stem>.npy`` or ``<stem>.png`` in ``folders`` (a folder or a list of them), else None."""
    for folder in [folders] if isinstance(folders, (str, Path)) else folders:
        for ext in DEPTH_SUFFIXES:
            if (Path(folder) / f"{stem}{ext}").is_file():
                return Path(folder) / f"{stem}{ext}"
    return None
