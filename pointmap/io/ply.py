"""Coloured point cloud as binary little-endian PLY (x y z float, red green blue uchar, confidence float)."""

from __future__ import annotations

import numpy as np

from pointmap.errors import ShapeError
from pointmap.io.atomic import atomic_open


def _points(xyz, rgb, conf):
    """(xyz [M, 3] float32, rgb [M, 3] uint8, conf [M] float32 or None) checked; ShapeError for anything else."""
    xyz, rgb = np.asarray(xyz), np.asarray(rgb)
    if xyz.ndim < 1 or xyz.shape[-1] != 3 or not np.issubdtype(xyz.dtype, np.number):
        raise ShapeError(f"xyz expected [M, 3] (or [..., 3]) numbers, got {list(xyz.shape)} of {xyz.dtype}")
    if rgb.shape == xyz.shape:  # maps [..., 3] of points and colours: one row per point
        rgb = rgb.reshape(-1, 3)
    xyz = xyz.reshape(-1, 3)
    f32 = np.finfo(np.float32).max  # the file holds float32: a larger coordinate would be written as inf
    if not (np.isfinite(xyz).all() and np.abs(xyz).max(initial=0) <= f32):
        bad = int((~(np.isfinite(xyz) & (np.abs(xyz) <= f32)).all(1)).sum())
        raise ShapeError(f"xyz expected finite points within float32's range, got {bad} with NaN, inf or beyond")
    if rgb.shape != xyz.shape:
        raise ShapeError(f"rgb expected {list(xyz.shape)} (one colour per point), got {list(rgb.shape)}")
    if rgb.dtype == np.uint8:
        pass
    elif np.issubdtype(rgb.dtype, np.floating) and rgb.size and np.isfinite(rgb).all() and \
            rgb.min() >= 0 and rgb.max() <= 255:
        rgb = (rgb * (255 if rgb.max() <= 1 else 1)).round().astype(np.uint8)  # [0, 1] floats, or 0..255 ones
    elif np.issubdtype(rgb.dtype, np.integer) and (not rgb.size or (rgb.min() >= 0 and rgb.max() <= 255)):
        rgb = rgb.astype(np.uint8)
    elif rgb.size:
        raise ShapeError(f"rgb expected uint8 colours (or numbers in 0..255, or floats in [0, 1]), got {rgb.dtype} "
                         f"in [{rgb.min()}, {rgb.max()}]")
    else:
        rgb = rgb.astype(np.uint8)
    if conf is not None:
        try:
            conf = np.asarray(conf, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise ShapeError(f"conf expected numbers (one per point), got {type(conf).__name__}") from None
        if conf.shape != (len(xyz),):
            raise ShapeError(f"conf expected [{len(xyz)}] (one per point), got {list(conf.shape)}")
        if not np.isfinite(conf).all():
            raise ShapeError(f"conf expected finite values, got {int((~np.isfinite(conf)).sum())} NaN or inf")
    return xyz.astype(np.float32), rgb, conf


def write_ply(path, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray | None = None):
    """Points ``xyz`` [M, 3] or [..., 3] (finite), colours ``rgb`` of the same shape (uint8, numbers in 0..255, or
    floats all in [0, 1], which are scaled) and an optional ``conf`` (one per point) as a binary PLY, written
    atomically. ShapeError for anything else."""
    xyz, rgb, conf = _points(xyz, rgb, conf)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if conf is not None:
        fields.append(("confidence", "<f4"))
    data = np.empty(len(xyz), dtype=fields)
    data["x"], data["y"], data["z"] = xyz.T
    data["red"], data["green"], data["blue"] = rgb.T
    if conf is not None:
        data["confidence"] = conf
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by pointmap",
              f"element vertex {len(xyz)}"] + [f"property {types[t]} {name}" for name, t in fields] + ["end_header"]
    with atomic_open(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return path


_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
          "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2", "int16": "<i2",
          "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def read_ply(path) -> dict:
    """Read a binary little-endian PLY's vertex properties (what ``write_ply`` writes, and other programs' point
    clouds): {property name: [M] array}. ShapeError (one line, naming the file) for a file that is not such a PLY
    or is truncated."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise ShapeError(f"{path}: cannot read it ({e.strerror or e.__class__.__name__})") from None
    # header lines end in \n, or \r\n from some Windows writers (the data after the header is the same)
    newline = b"\r\n" if raw.startswith(b"ply\r\n") else b"\n"
    end = raw.find(b"end_header" + newline)
    if not raw.startswith(b"ply" + newline) or end < 0:
        raise ShapeError(f"{path}: not a PLY file (expected a 'ply' header ending in 'end_header')")
    end += len(b"end_header" + newline)
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = next((ln for ln in lines if ln.startswith("format")), "")
    if fmt.split()[:2] != ["format", "binary_little_endian"]:
        raise ShapeError(f"{path}: only binary little-endian PLY is supported, got {fmt!r}")
    count, fields, element = 0, [], None
    for ln in lines:
        parts = ln.split()
        if parts[:1] == ["element"]:
            element = parts[1] if len(parts) > 1 else None
            if element != "vertex" and not fields:
                raise ShapeError(f"{path}: expected the vertex element first, got {ln!r}")
            if element == "vertex":
                count = int(parts[2]) if len(parts) > 2 and parts[2].isdigit() else -1
                if count < 0:
                    raise ShapeError(f"{path}: bad vertex count in {ln!r}")
        elif parts[:1] == ["property"] and element == "vertex":
            if len(parts) != 3 or parts[1] not in _TYPES:
                raise ShapeError(f"{path}: unsupported vertex property {ln!r} (scalar types only: "
                                 f"{', '.join(sorted(_TYPES))})")
            if parts[2] in {name for name, _ in fields}:
                raise ShapeError(f"{path}: vertex property {parts[2]!r} is declared twice")
            fields.append((parts[2], _TYPES[parts[1]]))
    dtype = np.dtype(fields)
    if len(raw) - end < count * dtype.itemsize:
        raise ShapeError(f"{path}: truncated: {count} vertices of {dtype.itemsize} bytes need "
                         f"{count * dtype.itemsize} bytes, the file has {len(raw) - end} after its header")
    data = np.frombuffer(raw[end:], dtype=dtype, count=count)
    return {name: data[name] for name, _ in fields}
