"""COLMAP sparse model export (cameras, images, points3D; .bin, and .txt on request).

One PINHOLE camera per image at its ORIGINAL size (or one shared camera when every image has the same
intrinsics and size), image names as given (the input file names), world-to-camera poses as COLMAP
expects. COLMAP puts the centre of the top-left pixel at (0.5, 0.5) while pointmap puts it at (0, 0):
principal points and 2D observations are shifted by +0.5 on the way out.
Each exported 3D point is observed once, at the original-resolution pixel it was unprojected from.
``write_colmap_images`` puts the photographs beside the model (``images/``, the layout 3DGS trainers expect).
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np

from pointmap.io.atomic import atomic_open, atomic_path
from pointmap.io.points import PointSet

PINHOLE = 1


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> (w, x, y, z) unit quaternion with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    cands = [tr, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(cands))
    if k == 0:
        s = 2 * np.sqrt(max(1 + tr, 1e-300))
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2 * np.sqrt(max(1 + R[0, 0] - R[1, 1] - R[2, 2], 1e-300))
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2 * np.sqrt(max(1 + R[1, 1] - R[0, 0] - R[2, 2], 1e-300))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2 * np.sqrt(max(1 + R[2, 2] - R[0, 0] - R[1, 1], 1e-300))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _model(recon, points: PointSet, shared_camera: bool | None):
    n = len(recon)
    K = recon.K.double().numpy()
    sizes = [tuple(int(x) for x in s) for s in recon.original_sizes]
    cams = []  # (camera_id, width, height, fx, fy, cx, cy)
    same = all(np.allclose(K[k], K[0], rtol=1e-6, atol=1e-6) and sizes[k] == sizes[0] for k in range(n))
    share = same if shared_camera is None else shared_camera
    if share and not same:
        raise ValueError("shared_camera=True but the images have different intrinsics or sizes")
    cam_of = []
    for k in range(n):
        if share and cams:
            cam_of.append(1)
            continue
        cams.append((len(cams) + 1, sizes[k][0], sizes[k][1], K[k, 0, 0], K[k, 1, 1], K[k, 0, 2] + 0.5, K[k, 1, 2] + 0.5))
        cam_of.append(len(cams))
    # observations in original pixels (COLMAP convention)
    mfo = recon.map_from_original.double().numpy()[points.image]
    sx, sy, left, top = mfo.T
    u_orig = (points.uv_map[:, 0] + 0.5 + left) / sx - 0.5
    v_orig = (points.uv_map[:, 1] + 0.5 + top) / sy - 0.5
    xy = np.stack([u_orig + 0.5, v_orig + 0.5], -1)
    obs = [[] for _ in range(n)]  # per image: (x, y, point3D_id)
    tracks = []
    for pid in range(len(points.xyz)):
        k = int(points.image[pid])
        tracks.append((k + 1, len(obs[k])))
        obs[k].append((xy[pid, 0], xy[pid, 1], pid + 1))
    w2c = np.linalg.inv(recon.cam2world.double().numpy())
    images = [(k + 1, rotation_to_quaternion(w2c[k, :3, :3]), w2c[k, :3, 3], cam_of[k], recon.names[k], obs[k])
              for k in range(n)]
    return cams, images, tracks


def write_colmap(recon, out_dir, points: PointSet, *, text: bool = False, binary: bool = True,
                 shared_camera: bool | None = None) -> list[Path]:
    """Write ``cameras``, ``images``, ``points3D`` (.bin and/or .txt) under ``out_dir``."""
    out_dir = Path(out_dir)
    cams, images, tracks = _model(recon, points, shared_camera)
    written = []
    if binary:
        with atomic_open(out_dir / "cameras.bin") as f:
            f.write(struct.pack("<Q", len(cams)))
            for cid, w, h, fx, fy, cx, cy in cams:
                f.write(struct.pack("<iiQQ4d", cid, PINHOLE, w, h, fx, fy, cx, cy))
        with atomic_open(out_dir / "images.bin") as f:
            f.write(struct.pack("<Q", len(images)))
            for iid, q, t, cid, name, obs in images:
                f.write(struct.pack("<I7dI", iid, *q, *t, cid))
                f.write(name.encode("utf-8") + b"\x00")
                f.write(struct.pack("<Q", len(obs)))
                if obs:
                    arr = np.array(obs, dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
                    f.write(arr.tobytes())
        with atomic_open(out_dir / "points3D.bin") as f:
            f.write(struct.pack("<Q", len(points.xyz)))
            rec = np.empty(len(points.xyz), dtype=[("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3),
                                                   ("err", "<f8"), ("tlen", "<u8"), ("img", "<u4"), ("p2d", "<u4")])
            rec["id"] = np.arange(1, len(points.xyz) + 1)
            rec["xyz"], rec["rgb"], rec["err"], rec["tlen"] = points.xyz, points.rgb, 0.0, 1
            rec["img"] = [t[0] for t in tracks]
            rec["p2d"] = [t[1] for t in tracks]
            f.write(rec.tobytes())
        written += [out_dir / "cameras.bin", out_dir / "images.bin", out_dir / "points3D.bin"]
    if text:
        written += _write_text(out_dir, cams, images, tracks, points)
    return written


def _write_text(out_dir: Path, cams, images, tracks, points) -> list[Path]:
    with atomic_open(out_dir / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(cams)}\n")
        for cid, w, h, fx, fy, cx, cy in cams:
            f.write(f"{cid} PINHOLE {w} {h} " + " ".join(repr(float(v)) for v in (fx, fy, cx, cy)) + "\n")
    with atomic_open(out_dir / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(images)}\n")
        for iid, q, t, cid, name, obs in images:
            f.write(" ".join([str(iid)] + [repr(float(x)) for x in (*q, *t)] + [str(cid), name]) + "\n")
            # the second line is always written (possibly empty): loaders read two lines per image
            f.write(" ".join(f"{float(x)!r} {float(y)!r} {pid}" for x, y, pid in obs) + "\n")
    with atomic_open(out_dir / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {len(points.xyz)}\n")
        lines = [f"{pid + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0.0 {tracks[pid][0]} {tracks[pid][1]}\n"
                 for pid, ((x, y, z), (r, g, b)) in enumerate(zip(points.xyz.tolist(), points.rgb.tolist()))]
        f.writelines(lines)
    return [out_dir / "cameras.txt", out_dir / "images.txt", out_dir / "points3D.txt"]


def write_colmap_images(sources, names, out_dir) -> list[Path]:
    """Copy the photographs a COLMAP model refers to into ``out_dir`` (COLMAP's ``images/``) under the model's
    image ``names``: a file whose pixels need no EXIF rotation and whose suffix is the name's is copied byte for
    byte; any other (a rotated JPEG, a renamed duplicate with another suffix) is written as ``load_images`` reads
    it (EXIF orientation applied: the pixels the poses and intrinsics refer to), in the format of the name's
    suffix. ``sources``: file paths, or None for images given as arrays (skipped: they exist nowhere on disk);
    a source that no longer exists is skipped with a warning.
    Returns the paths written; every file is written atomically."""
    import shutil

    from PIL import Image, ImageOps

    if len(sources) != len(names):
        raise ValueError(f"write_colmap_images expected one source per name, got {len(sources)} and {len(names)}")
    out_dir = Path(out_dir)
    written = []
    for src, name in zip(sources, names):
        if src is None:
            continue
        src, dst = Path(src), out_dir / name
        if not src.is_file():  # e.g. a reconstruction.npz reloaded on another machine
            warnings.warn(f"write_colmap_images: {src} no longer exists; {dst} not written", stacklevel=2)
            continue
        with Image.open(src) as im:
            upright = im.getexif().get(0x0112, 1) in (None, 1)
            with atomic_path(dst) as tmp:
                if upright and src.suffix.lower() == dst.suffix.lower():
                    shutil.copyfile(src, tmp)
                else:
                    im = ImageOps.exif_transpose(im)
                    if dst.suffix.lower() in (".jpg", ".jpeg"):
                        im.convert("RGB").save(tmp, quality=95)
                    else:
                        im.save(tmp)
        written.append(dst)
    return written
