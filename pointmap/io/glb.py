"""GLB scene: the coloured point cloud plus one wireframe frustum per camera (trimesh).

glTF's axes, as every glTF viewer (Blender, three.js, model-viewer) assumes them: x right, y up, the view along -z.
The reconstruction's world (OpenCV axes: y down, z forward; image 0's camera unless poses were given) is turned
180 degrees about x, ``GLTF_FROM_WORLD``: a point (x, y, z) is stored as (x, -y, -z). Image 0's view then opens
upright, seen the way its camera saw it, instead of upside down and from behind. Other formats keep the world as is.
Colours are stored linear, as glTF's COLOR_0 is defined (``srgb_to_linear_u8``); the PLY keeps the photographs' sRGB.
"""

from __future__ import annotations

import numpy as np

from pointmap.io.atomic import write_bytes

GLTF_FROM_WORLD = np.diag([1.0, -1.0, -1.0])  # a rotation (det +1): OpenCV axes to glTF's


def srgb_to_linear_u8(rgb: np.ndarray) -> np.ndarray:
    """uint8 sRGB colours -> uint8 linear ones: glTF's vertex colours (COLOR_0) are linear, and viewers encode
    them to sRGB for display; the photographs' sRGB bytes stored as they are show brighter and paler."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return (lin * 255.0).round().astype(np.uint8)


def frustum_lines(cam2world: np.ndarray, K: np.ndarray, size: tuple, depth: float) -> np.ndarray:
    """[8, 2, 3] line segments: apex to the 4 image corners at ``depth`` and the rectangle between them."""
    w, h = size
    corners_px = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    rays = np.stack([(corners_px[:, 0] - K[0, 2]) / K[0, 0], (corners_px[:, 1] - K[1, 2]) / K[1, 1], np.ones(4)], -1)
    pts_cam = rays * depth
    pts = pts_cam @ cam2world[:3, :3].T + cam2world[:3, 3]
    apex = cam2world[:3, 3]
    segs = [(apex, pts[k]) for k in range(4)] + [(pts[k], pts[(k + 1) % 4]) for k in range(4)]
    return np.asarray(segs)


def write_glb(path, recon, points, frustum_scale: float = 0.05) -> None:
    import trimesh

    scene = trimesh.Scene()
    if len(points.xyz):
        rgba = np.concatenate([srgb_to_linear_u8(points.rgb), np.full((len(points.rgb), 1), 255, np.uint8)], 1)
        scene.add_geometry(trimesh.PointCloud(points.xyz @ GLTF_FROM_WORLD.T, colors=rgba), geom_name="points")
    c2w = recon.cam2world.double().numpy()
    K = recon.K.double().numpy()
    extent = points.xyz.max(0) - points.xyz.min(0) if len(points.xyz) > 1 else np.ones(3)
    depth = frustum_scale * float(np.linalg.norm(extent)) or 0.1
    for k in range(len(recon)):
        segs = frustum_lines(c2w[k], K[k], recon.original_sizes[k], depth) @ GLTF_FROM_WORLD.T
        path3d = trimesh.load_path(segs)
        path3d.colors = np.tile([[*srgb_to_linear_u8([255, 64, 0]), 255]], (len(path3d.entities), 1))
        scene.add_geometry(path3d, geom_name=f"camera_{k:03d}")
    write_bytes(path, scene.export(file_type="glb"))
