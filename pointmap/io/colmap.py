"""COLMAP sparse model export (cameras, images, points3D; .bin, and .txt on request), and the reader of a
model's cameras (``read_colmap``, for known cameras and lens distortion).

One PINHOLE camera per distinct intrinsics and size, at the ORIGINAL size (images aligned with one focal per
camera, ``AlignConfig.shared_focal``, share one; ``shared_camera`` True / False: one for all / one per image),
image names as given (the input file names), world-to-camera poses as COLMAP
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

from pointmap.errors import ConventionError, PointmapError
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K, is_rigid
from pointmap.io.atomic import atomic_open, atomic_path
from pointmap.io.points import PointSet

PINHOLE = 1
RIG_FILES = ("rigs", "frames")  # the model files COLMAP 3.12+ writes beside cameras, images and points3D
MODEL_FILES = ("cameras", "images", "points3D", *RIG_FILES)  # a sparse model's files, each .bin or .txt


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


def check_shared_camera(recon, shared_camera: bool | None) -> bool:
    """Whether the COLMAP model writes one camera for all images: ``shared_camera``, or (None) whether every image
    has the same intrinsics and size. ValueError for True when they differ."""
    K = recon.K.double().numpy()
    sizes = [tuple(int(x) for x in s) for s in recon.original_sizes]
    same = all(np.allclose(K[k], K[0], rtol=1e-6, atol=1e-6) and sizes[k] == sizes[0] for k in range(len(recon)))
    if shared_camera and not same:
        raise ValueError("shared_camera=True but the images have different intrinsics or sizes")
    return same if shared_camera is None else bool(shared_camera)


def _model(recon, points: PointSet, shared_camera: bool | None):
    n = len(recon)
    K = recon.K.double().numpy()
    sizes = [tuple(int(x) for x in s) for s in recon.original_sizes]
    share = check_shared_camera(recon, shared_camera)
    # checked before any file is written: a Reconstruction's tensors can be changed after it was built, and a NaN
    # or mirrored pose would be written as a line COLMAP (and read_colmap) refuses, or as some other rotation
    for k in range(n):
        if not bool(is_rigid(recon.cam2world[k])):
            raise ConventionError(f"COLMAP export: cam2world[{k}] ({recon.names[k]}) is not a finite rigid transform "
                                  "(orthonormal rotation with det +1, last row 0 0 0 1)")
        if not bool(is_pinhole_K(recon.K[k])):
            raise ConventionError(f"COLMAP export: K[{k}] ({recon.names[k]}) expected finite pinhole intrinsics "
                                  f"{K_LAYOUT} with fx, fy > 0, got {recon.K[k].tolist()}")
    for name in recon.names:  # UnicodeEncodeError here, not after cameras.* was replaced (a mixed model)
        name.encode("utf-8")
    firsts, cam_of = [], []  # the first image of each camera; each image's camera_id
    for k in range(n):  # an image takes the first camera of its size and intrinsics (any one, when all share it)
        c = next((c for c, r in enumerate(firsts) if share or (shared_camera is None and sizes[r] == sizes[k] and
                                                               np.allclose(K[r], K[k], rtol=1e-6, atol=1e-6))), None)
        if c is None:
            firsts.append(k)
            c = len(firsts) - 1
        cam_of.append(c + 1)
    cams = [(c + 1, sizes[r][0], sizes[r][1], K[r, 0, 0], K[r, 1, 1], K[r, 0, 2] + 0.5, K[r, 1, 2] + 0.5)
            for c, r in enumerate(firsts)]  # (camera_id, width, height, fx, fy, cx, cy)
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
    """Write ``cameras``, ``images``, ``points3D`` (.bin and/or .txt) under ``out_dir``. Files of the format not
    written that an earlier run left there are named in a warning (COLMAP and 3DGS loaders read .bin first)."""
    out_dir = Path(out_dir)
    cams, images, tracks = _model(recon, points, shared_camera)
    other = [s for s, w in ((".bin", binary), (".txt", text)) if not w]
    stale = [out_dir / f"{n}{s}" for s in other for n in MODEL_FILES
             if (out_dir / f"{n}{s}").exists()]
    if stale:
        warnings.warn(f"{out_dir} still holds {', '.join(p.name for p in stale)} of an earlier run, which readers may take "
                      f"for this model (COLMAP reads .bin first): remove them, or write into an empty folder",
                      stacklevel=3)
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
    # 3DGS trainers convert points3D to points3D.ply beside it on their first run, and read that file from then on:
    # an earlier model's would start them from its cloud, not this one's
    cache = out_dir / "points3D.ply"
    if cache.exists():
        cache.unlink()
        warnings.warn(f"{out_dir}: removed points3D.ply, which a 3DGS trainer made from an earlier model's points "
                      "(it reads that file instead of points3D once it exists)", stacklevel=3)
    # COLMAP 3.12+ models also hold rigs and frames, which refer to their own images: left beside this model, a
    # reader (COLMAP, pycolmap) would join them to it and fail, or mismatch the cameras. This model has none.
    rigs = [out_dir / f"{n}{s}" for s, w in ((".bin", binary), (".txt", text)) if w for n in RIG_FILES
            if (out_dir / f"{n}{s}").exists()]
    for path in rigs:
        path.unlink()
    if rigs:
        warnings.warn(f"{out_dir}: removed {', '.join(p.name for p in rigs)} of an earlier COLMAP model, which "
                      f"described its images, not these (readers would join them to this model)", stacklevel=3)
    return written


def _write_text(out_dir: Path, cams, images, tracks, points) -> list[Path]:
    spaced = [name for _, _, _, _, name, _ in images if any(c.isspace() for c in name)]
    if spaced:  # COLMAP's own reader and read_write_model.py (3DGS, nerfstudio) take the name up to a space
        warnings.warn(f"images.txt: {len(spaced)} image name(s) contain whitespace (e.g. {spaced[0]!r}), which COLMAP's "
                      "text readers cut at the first space: use the binary model, or rename the images",
                      RuntimeWarning, stacklevel=3)
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


def _byte_copyable(src: Path) -> bool:
    """Whether the file's own bytes hold the pixels the model read (``read_rgb``), in a format trainers read: an
    upright 8-bit RGB or grey file. Not a HEIC / HEIF photograph (3DGS trainers cannot read it), a rotated one, nor a
    16-bit one: PIL reads a 48-bit PNG or TIFF as 8-bit RGB, as the model did, where a loader that keeps the depth
    (OpenCV's IMREAD_UNCHANGED) would not."""
    from PIL import Image

    from pointmap.images import HEIF_SUFFIXES

    if src.suffix.lower() in HEIF_SUFFIXES:
        return False
    with Image.open(src) as im:
        wide = any(";16" in str(t[3]) for t in im.tile)  # e.g. rawmode "RGB;16B"
        return im.getexif().get(0x0112, 1) in (None, 1) and im.mode in ("RGB", "L") and not wide


def exported_names(names: list, sources) -> list:
    """The image names a COLMAP or nerfstudio export writes for ``names``: a HEIC / HEIF photograph's (``sources``,
    file paths or None) as a JPEG beside the model (``write_colmap_images`` re-encodes it: 3DGS trainers cannot read
    HEIC), the others as they are. ShapeError when a JPEG name would be another image's."""
    from pointmap.errors import ShapeError
    from pointmap.images import HEIF_SUFFIXES

    out = [str(Path(n).with_suffix(".jpg")) if src is not None and Path(src).suffix.lower() in HEIF_SUFFIXES
           and Path(n).suffix.lower() in HEIF_SUFFIXES else n for n, src in zip(names, sources or [None] * len(names))]
    seen: dict = {}
    for n, new in zip(names, out):
        other = seen.setdefault(new.lower(), n)
        if other != n:
            raise ShapeError(f"{other} and {n} would both be exported as {new} (a HEIC photograph is exported as a "
                             "JPEG: 3DGS trainers cannot read HEIC; names match whatever their case): rename one of them")
    return out


def write_colmap_images(sources, names, out_dir) -> list[Path]:
    """Copy the photographs a COLMAP model refers to into ``out_dir`` (COLMAP's ``images/``) under the model's
    image ``names``: an upright 8-bit RGB or grey file whose suffix is the name's is copied byte for byte; any
    other (a rotated JPEG, a 16-bit, transparent or palette PNG, a HEIC photograph, a renamed duplicate with another
    suffix) is written as ``load_images`` reads
    it (``read_rgb``: EXIF orientation applied, 16-bit scaled, alpha composited on white: the pixels the poses and
    intrinsics refer to), in the format of the name's suffix (PNG when the suffix names none). ``sources``: file
    paths, or None for images given as arrays (skipped: they exist nowhere on disk); a source that no longer exists,
    or can no longer be read, is skipped with a warning.
    Returns the paths written; every file is written atomically."""
    import shutil

    from PIL import Image

    from pointmap.images import read_rgb

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
        try:
            as_read = _byte_copyable(src)
        except (OSError, SyntaxError, ValueError) as e:  # replaced since the run by something unreadable
            warnings.warn(f"write_colmap_images: {src} cannot be read ({e.__class__.__name__}); {dst} not written",
                          stacklevel=2)
            continue
        if dst.exists() and dst.resolve() == src.resolve():  # the output is the scene folder the photographs
            if not as_read:  # came from (its images/): the user's own file is never replaced by a re-encoded copy
                warnings.warn(f"write_colmap_images: {dst} is the source photograph itself and is left as it is "
                              "(not replaced by the upright 8-bit RGB copy the model read: its orientation, bit "
                              "depth or transparency may decode differently in a trainer)", stacklevel=2)
            written.append(dst)
            continue
        with atomic_path(dst) as tmp:  # (16-bit, alpha or palette files decode otherwise in a trainer's loader)
            if as_read and src.suffix.lower() == dst.suffix.lower():
                shutil.copyfile(src, tmp)
            else:  # re-encoded from the very pixels the poses refer to (EXIF turned, 16-bit scaled, alpha on white)
                fmt = Image.registered_extensions().get(dst.suffix.lower(), "PNG")
                Image.fromarray(read_rgb(src)).save(tmp, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
        written.append(dst)
    return written


# COLMAP's camera models: id -> (name, number of parameters)
CAMERA_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
                 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
# name -> (focal params, lens model of pointmap.undistort, its coefficients' positions in the parameters)
_LENSES = {"SIMPLE_PINHOLE": (1, None, ()), "PINHOLE": (2, None, ()), "SIMPLE_RADIAL": (1, "SIMPLE_RADIAL", (3,)),
           "RADIAL": (1, "RADIAL", (3, 4)), "OPENCV": (2, "OPENCV", (4, 5, 6, 7)),
           "OPENCV_FISHEYE": (2, "OPENCV_FISHEYE", (4, 5, 6, 7)),
           "FULL_OPENCV": (2, "FULL_OPENCV", tuple(range(4, 12))),
           "SIMPLE_RADIAL_FISHEYE": (1, "OPENCV_FISHEYE", (3,)), "RADIAL_FISHEYE": (1, "OPENCV_FISHEYE", (3, 4))}


def quaternion_to_rotation(q) -> np.ndarray:
    """(w, x, y, z) quaternion (normalised here) -> [3, 3] rotation."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _camera(model: str, params, where: str):
    """K [3, 3] (pointmap's pixel convention) and a ``pointmap.undistort.Distortion`` (None when all zero)."""
    from pointmap.undistort import Distortion

    if model not in _LENSES:
        raise PointmapError(f"{where}: COLMAP camera model {model} is not one pointmap can undistort (it reads "
                            f"{', '.join(_LENSES)})")
    p = [float(v) for v in params]
    n_focal, lens, at = _LENSES[model]
    fx, fy = (p[0], p[0]) if n_focal == 1 else (p[0], p[1])
    cx, cy = p[n_focal], p[n_focal + 1]
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])  # COLMAP: pixel centres at +0.5
    if not (np.isfinite(K).all() and fx > 0 and fy > 0):
        raise PointmapError(f"{where}: focal lengths must be positive and finite, got {fx}, {fy}")
    dist = None if lens is None else Distortion(lens, tuple(p[i] for i in at))
    return K, (None if dist is None or dist.is_identity else dist)


def _read_binary(folder: Path):
    cams, images = {}, []
    with open(folder / "cameras.bin", "rb") as f:
        for _ in range(struct.unpack("<Q", f.read(8))[0]):
            cid, mid, w, h = struct.unpack("<iiQQ", f.read(24))
            if mid not in CAMERA_MODELS:
                raise PointmapError(f"{folder}: COLMAP camera model id {mid} is not one pointmap can undistort (it "
                                    f"reads {', '.join(_LENSES)})")
            name, n = CAMERA_MODELS[mid]
            if cid in cams:  # the reader's ValueError: "not a readable COLMAP model"
                raise ValueError(f"camera id {cid} appears twice")
            cams[cid] = (name, int(w), int(h), struct.unpack(f"<{n}d", f.read(8 * n)))
    with open(folder / "images.bin", "rb") as f:
        for _ in range(struct.unpack("<Q", f.read(8))[0]):
            _, *qt, cid = struct.unpack("<I7dI", f.read(64))
            name = b""
            while (c := f.read(1)) != b"\x00":
                if not c:
                    raise ValueError("truncated image name")
                name += c
            n_obs = struct.unpack("<Q", f.read(8))[0]
            f.seek(24 * n_obs, 1)
            images.append((name.decode("utf-8"), qt[:4], qt[4:], cid))
    return cams, images


def _read_text(folder: Path):
    cams, images = {}, []
    for line in (folder / "cameras.txt").read_text(encoding="utf-8-sig").splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            tok = line.split()
            if int(tok[0]) in cams:
                raise ValueError(f"camera id {int(tok[0])} appears twice")
            cams[int(tok[0])] = (tok[1], int(tok[2]), int(tok[3]), tuple(float(v) for v in tok[4:]))
    lines = (folder / "images.txt").read_text(encoding="utf-8-sig").splitlines()
    i = 0
    while i < len(lines):  # as COLMAP reads it: an image line, then always its 2D points' line (possibly empty)
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        tok = line.split(maxsplit=9)
        images.append((tok[9].strip(), [float(v) for v in tok[1:5]], [float(v) for v in tok[5:8]], int(tok[8])))
        i += 1
    return cams, images


def colmap_model_folder(path) -> Path | None:
    """The folder of the COLMAP sparse model ``read_colmap`` reads at ``path`` (the model folder, a scene folder
    holding ``sparse/0`` or ``0``, or one of the model's files), or None when there is none."""
    path = Path(path)
    folder = path.parent if path.is_file() else path
    for candidate in (folder, folder / "sparse" / "0", folder / "0"):
        if all((candidate / f"{n}.bin").is_file() for n in ("cameras", "images")) or \
                all((candidate / f"{n}.txt").is_file() for n in ("cameras", "images")):
            return candidate
    return None


def read_colmap(path) -> dict:
    """Cameras of a COLMAP sparse model (``cameras`` + ``images``, .bin or .txt; ``path`` is the model folder,
    e.g. ``sparse/0``, a scene folder holding ``sparse/0``, or its cameras file), in ``read_transforms``'s
    form: {image base name: {"K": [3, 3] in pointmap's pixel convention at the camera's size, "cam2world":
    [4, 4] OpenCV axes, "size": (w, h), "camera_angle_x": None, "distortion": a ``pointmap.undistort.Distortion``
    or None}}. Every camera model with a radial / tangential or fisheye lens OpenCV models is read (SIMPLE_RADIAL,
    RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE); others are refused, as are
    files that are not such a model and two images with one base name."""
    path = Path(path)
    folder = colmap_model_folder(path)
    if folder is None:
        raise PointmapError(f"{path}: expected a COLMAP sparse model folder with cameras.bin and images.bin (or "
                            "cameras.txt and images.txt)")
    binary = (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file() and \
        not (path.is_file() and path.suffix == ".txt")  # a cameras.txt named: the text model
    try:
        cams, images = _read_binary(folder) if binary else _read_text(folder)
    except (OSError, ValueError, IndexError, struct.error, UnicodeDecodeError) as e:
        raise PointmapError(f"{folder}: not a readable COLMAP model ({e.__class__.__name__}: {e})") from None
    out = {}
    for name, q, t, cid in images:
        where = f"{folder}: image {name}"
        if cid not in cams:
            raise PointmapError(f"{where} refers to camera {cid}, which cameras.{'bin' if binary else 'txt'} lacks")
        model, w, h, params = cams[cid]
        if not (w > 0 and h > 0):
            raise PointmapError(f"{where}: camera {cid} has a size of {w} x {h} pixels")
        if len(params) != dict(CAMERA_MODELS.values()).get(model, len(params)):
            raise PointmapError(f"{where}: camera {cid} ({model}) has {len(params)} parameters")
        K, dist = _camera(model, params, where)
        if not (np.isfinite(q).all() and np.isfinite(t).all() and np.linalg.norm(q) > 0):
            raise PointmapError(f"{where}: its pose is not finite")
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = quaternion_to_rotation(q), t
        key = Path(name).name
        if key in out:
            raise PointmapError(f"{folder}: two images are named {key} (in different folders): the photographs "
                                "could not be told apart by file name")
        out[key] = {"K": K, "cam2world": np.linalg.inv(w2c), "size": (w, h), "camera_angle_x": None,
                    "distortion": dist}
    if not out:
        raise PointmapError(f"{folder}: the COLMAP model has no images")
    return out
