"""nerfstudio / instant-ngp ``transforms.json`` export.

One frame per image: ``file_path`` ``images/<name>`` (the photographs ``write_colmap_images`` puts there), the
image's own intrinsics at its ORIGINAL size (``fl_x, fl_y, cx, cy, w, h``, camera model OPENCV with zero
distortion) and ``transform_matrix``, the camera-to-world pose in nerfstudio's OpenGL camera axes (x right,
y up, z backward): our OpenCV ``cam2world`` times diag(1, -1, -1, 1). nerfstudio casts rays through pixel
coordinates ``i + 0.5`` (the top-left pixel's centre at (0.5, 0.5), as COLMAP), so principal points are shifted by
+0.5 as in the COLMAP export. ``ply_file_path`` names the initial cloud (``sparse_pc.ply``, the one
``ns-process-data`` writes and splatfacto starts from).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pointmap.io.atomic import atomic_open
from pointmap.io.ply import write_ply
from pointmap.io.points import PointSet

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def write_transforms(recon, out_dir, points: PointSet | None = None) -> list[Path]:
    """Write ``out_dir/transforms.json`` (and ``out_dir/sparse_pc.ply`` from ``points`` when given); returns
    the paths written."""
    out_dir = Path(out_dir)
    K = recon.K.double().numpy()
    c2w = recon.cam2world.double().numpy()
    frames = []
    for k in range(len(recon)):
        w, h = (int(x) for x in recon.original_sizes[k])
        frames.append({"file_path": f"images/{recon.names[k]}", "fl_x": float(K[k, 0, 0]),
                       "fl_y": float(K[k, 1, 1]), "cx": float(K[k, 0, 2] + 0.5), "cy": float(K[k, 1, 2] + 0.5),
                       "w": w, "h": h, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                       "transform_matrix": (c2w[k] @ OPENCV_TO_OPENGL).tolist()})
    meta = {"camera_model": "OPENCV", "frames": frames}
    written = []
    if points is not None:
        write_ply(out_dir / "sparse_pc.ply", points.xyz, points.rgb, points.conf)
        meta["ply_file_path"] = "sparse_pc.ply"
        written.append(out_dir / "sparse_pc.ply")
    with atomic_open(out_dir / "transforms.json", "w") as f:
        json.dump(meta, f, indent=2)
    written.insert(0, out_dir / "transforms.json")
    return written
