"""nerfstudio / instant-ngp ``transforms.json`` export, and the reader of such files (``read_transforms``).

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

from pointmap.geometry.cameras import convert_camera_axes
from pointmap.io.atomic import atomic_open
from pointmap.io.ply import write_ply
from pointmap.io.points import PointSet


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
                       "transform_matrix": convert_camera_axes(c2w[k], "opencv", "opengl").tolist()})
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


_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def read_transforms(path) -> dict:
    """Cameras of a nerfstudio / instant-ngp ``transforms.json`` (ours, or an app's: Polycam, Record3D, ...):
    {file name: {"K": [3, 3] float64 in our pixel convention at the size (w, h) the file states (None when the
    file gives no focal), "cam2world": [4, 4] float64 OpenCV axes, "size": (w, h) or None, "camera_angle_x": the
    horizontal field of view in radians when that is all the file gives (NeRF-synthetic files state no size: the
    caller resolves it with the image's width), else None}}, keyed by the base name of each frame's ``file_path``
    (which NeRF-synthetic files give without a suffix). Intrinsics may be per frame or global (frame keys win);
    ``camera_angle_x`` stands for ``fl_x`` when ``w`` is known; a missing principal point is the image centre.
    "distortion": a ``pointmap.undistort.Distortion`` for frames whose lens distortion coefficients are not all
    zero (OPENCV: k1, k2, k3, p1, p2; OPENCV_FISHEYE: k1-k4), else None. PointmapError for a file that is not such
    a JSON, a frame without a pose or with a non-rigid one, or a camera model pointmap cannot undistort."""
    from pointmap.errors import PointmapError
    from pointmap.undistort import Distortion

    path = Path(path)
    try:
        meta = json.loads(path.read_text(encoding="utf-8-sig"))  # -sig: a byte-order mark is not JSON
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PointmapError(f"{path}: not a readable transforms.json ({e.__class__.__name__}: {e})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise PointmapError(f"{path}: expected a JSON object with a non-empty 'frames' list (nerfstudio format)")
    out = {}
    for i, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise PointmapError(f"{path}: frame {i} lacks 'file_path' or 'transform_matrix'")
        get = lambda key: frame.get(key, meta.get(key))  # noqa: E731
        model = str(get("camera_model") or "OPENCV").upper()
        if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE"):
            raise PointmapError(f"{path}: frame {i} ({frame['file_path']}) has a {model} camera: pointmap reads "
                                "pinhole cameras, with or without OPENCV / OPENCV_FISHEYE lens distortion")
        try:
            dist = Distortion.from_named("OPENCV_FISHEYE" if model == "OPENCV_FISHEYE" else "OPENCV",
                                         {k: float(get(k) or 0) for k in _DISTORTION})
        except (PointmapError, TypeError, ValueError) as e:
            raise PointmapError(f"{path}: frame {i} ({frame['file_path']}): {e}") from None
        try:
            T = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):  # "eye", ragged rows: said as the shape check below says it
            T = np.full(1, np.nan)
        if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]) \
                or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4) or np.linalg.det(T[:3, :3]) < 0:
            got = T.tolist() if T.size == 16 else repr(frame["transform_matrix"])[:80]
            raise PointmapError(f"{path}: frame {i} ({frame['file_path']}): transform_matrix must be a rigid "
                                f"[4, 4] camera-to-world matrix, got {got}")
        try:  # numbers that are not numbers ("w": "abc") are refused like the rest
            w, h = get("w"), get("h")
            size = (int(w), int(h)) if w is not None and h is not None else None
            fx, fy = get("fl_x"), get("fl_y")
            if get("camera_angle_x") is not None and not 0 < float(get("camera_angle_x")) < np.pi:
                raise PointmapError(f"{path}: frame {i} ({frame['file_path']}): camera_angle_x expected a field of "
                                    f"view in radians, in (0, pi), got {get('camera_angle_x')}")
            if fx is None and get("camera_angle_x") is not None and w is not None:
                fx = focal_from_angle(float(get("camera_angle_x")), float(w))
            K = None
            if fx is not None:
                fy = fx if fy is None else fy
                cx = get("cx") if get("cx") is not None else (float(w) / 2 if w is not None else None)
                cy = get("cy") if get("cy") is not None else (float(h) / 2 if h is not None else None)
                if cx is None or cy is None:
                    raise PointmapError(f"{path}: frame {i} ({frame['file_path']}) has a focal but neither a principal "
                                        "point (cx, cy) nor the image size (w, h)")
                K = np.array([[float(fx), 0.0, float(cx) - 0.5], [0.0, float(fy), float(cy) - 0.5], [0.0, 0.0, 1.0]])
                if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0):
                    raise PointmapError(f"{path}: frame {i} ({frame['file_path']}): focal lengths must be positive, "
                                        f"got {fx}, {fy}")
        except (TypeError, ValueError) as e:
            raise PointmapError(f"{path}: frame {i} ({frame['file_path']}): an intrinsics field (w, h, fl_x, fl_y, "
                                f"cx, cy, camera_angle_x) is not a number: {e}") from None
        angle = get("camera_angle_x") if K is None and get("camera_angle_x") is not None else None
        if not dist.is_identity and K is None:
            raise PointmapError(f"{path}: frame {i} ({frame['file_path']}) states lens distortion but no focal length "
                                "(fl_x) and image size (w, h): the distortion cannot be undone without them")
        name = Path(str(frame["file_path"])).name
        if name in out:  # frames are matched to images by base name: a second would silently replace the first
            raise PointmapError(f"{path}: two frames have the image name {name!r} (frame {i}: "
                                f"{frame['file_path']}); pointmap matches cameras to images by file name")
        out[name] = {"K": K, "cam2world": convert_camera_axes(T, "opengl", "opencv"), "size": size,
                     "camera_angle_x": None if angle is None else float(angle),
                     "distortion": None if dist.is_identity else dist}
    return out


def focal_from_angle(camera_angle_x: float, width: float) -> float:
    """Focal length in pixels of a pinhole camera ``width`` pixels wide with horizontal field of view
    ``camera_angle_x`` (radians)."""
    return 0.5 * width / float(np.tan(0.5 * camera_angle_x))


def intrinsics_from_angle(camera_angle_x: float, width: int, height: int) -> np.ndarray:
    """K [3, 3] (our pixel convention) of a pinhole camera with horizontal field of view ``camera_angle_x``
    (radians) and a centred principal point, for an image of ``width`` x ``height`` pixels."""
    f = focal_from_angle(camera_angle_x, width)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
