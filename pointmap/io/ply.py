"""Coloured point cloud as binary little-endian PLY (x y z float, red green blue uchar, confidence float)."""

from __future__ import annotations

import numpy as np

from pointmap.io.atomic import atomic_open


def write_ply(path, xyz: np.ndarray, rgb: np.ndarray, conf: np.ndarray | None = None):
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if conf is not None:
        fields.append(("confidence", "<f4"))
    data = np.empty(len(xyz), dtype=fields)
    data["x"], data["y"], data["z"] = xyz.T
    data["red"], data["green"], data["blue"] = rgb.T
    if conf is not None:
        data["confidence"] = np.asarray(conf, dtype=np.float32).reshape(-1)
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by pointmap",
              f"element vertex {len(xyz)}"] + [f"property {types[t]} {name}" for name, t in fields] + ["end_header"]
    with atomic_open(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return path


def read_ply(path) -> dict:
    """Read back what ``write_ply`` writes (binary little-endian, vertex properties only)."""
    with open(path, "rb") as f:
        raw = f.read()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    if lines[1] != "format binary_little_endian 1.0":
        raise ValueError(f"{path}: only binary little-endian PLY is supported, got {lines[1]!r}")
    count = 0
    fields = []
    for ln in lines:
        parts = ln.split()
        if parts[:2] == ["element", "vertex"]:
            count = int(parts[2])
        elif parts[0] == "property":
            fields.append((parts[2], {"float": "<f4", "uchar": "u1", "double": "<f8", "int": "<i4"}[parts[1]]))
    data = np.frombuffer(raw[end:], dtype=fields, count=count)
    return {name: data[name] for name, _ in fields}
