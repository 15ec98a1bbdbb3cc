"""Exports of a Reconstruction: PLY, GLB, COLMAP (bin/txt), npz. All files are written atomically."""

from __future__ import annotations

from pathlib import Path

from pointmap.errors import ShapeError, check_seed
from pointmap.io.colmap import check_shared_camera, exported_names, write_colmap, write_colmap_images
from pointmap.io.glb import write_glb
from pointmap.io.nerfstudio import write_transforms
from pointmap.io.npz import load_npz, write_npz
from pointmap.io.ply import read_ply, write_ply
from pointmap.io.points import check_conf_filter, check_point_cap, confidence_mask, select_points
from pointmap.io.tum import tum_timestamps, write_tum

FORMATS = ("ply", "glb", "colmap", "colmap_txt", "nerfstudio", "tum", "npz")


# what each format writes under out_dir (the COLMAP model's folder for both of its kinds)
OUTPUT_NAMES = {"ply": "points.ply", "glb": "scene.glb", "colmap": "sparse/0", "colmap_txt": "sparse/0",
                "nerfstudio": "transforms.json", "tum": "trajectory.txt", "npz": "reconstruction.npz"}


def save_reconstruction(recon, out_dir, formats=("ply", "glb", "colmap", "npz"), *, min_conf: float | None = None,
                        conf_percentile: float | None = None, max_points: int | None = None,
                        colmap_max_points: int | None = 100_000, colmap_text: bool = False,
                        shared_camera: bool | None = None, seed: int = 0) -> dict:
    """Write ``recon`` under ``out_dir``; returns {format: path or [paths]}.

    formats: any of "ply" (points.ply), "glb" (scene.glb), "colmap" (sparse/0/*.bin),
        "colmap_txt" (sparse/0/*.txt), "nerfstudio" (transforms.json + sparse_pc.ply), "tum"
        (trajectory.txt: one pose per image, for trajectory tools), "npz" (reconstruction.npz). With a COLMAP
        or the nerfstudio format, the photographs named in ``recon.info["sources"]`` (file paths, as
        ``pm.reconstruct`` records them) are copied to ``images/`` (``write_colmap_images``): ``out_dir`` then has
        the scene layout 3DGS trainers expect.
    Points are the pixels with depth inside ``recon.masks`` that pass ``min_conf`` (absolute) and
    ``conf_percentile`` (relative; see ``confidence_mask``); ``max_points`` caps the PLY/GLB cloud and
    ``colmap_max_points`` the COLMAP points3D and nerfstudio's sparse_pc.ply (dense clouds slow 3DGS trainers
    down; None = all). ``shared_camera``: the COLMAP model's cameras, None (default) one per distinct intrinsics and
    size (a shared focal's images share one), True one for all (refused when they differ), False one per image.
    """
    from pointmap.reconstruction import Reconstruction

    if not isinstance(recon, Reconstruction):
        raise ShapeError(f"save_reconstruction expected a Reconstruction, got {type(recon).__name__}")
    if isinstance(formats, str):
        formats = tuple(f.strip() for f in formats.split(",") if f.strip())
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise ValueError(f"formats expected a subset of {FORMATS}, got {bad}")
    for name, flag in (("colmap_text", colmap_text), ("shared_camera", shared_camera)):
        if not (isinstance(flag, bool) or (name == "shared_camera" and flag is None)):
            raise ShapeError(f"{name} expected True or False{' (or None)' if name == 'shared_camera' else ''}, got "
                             f"{flag!r}")
    undecodable = [n for n in recon.names if not _utf8(n)]
    if undecodable:  # every format stores names as UTF-8 text: refused before a file is written, not half-way
        raise ShapeError(f"image name(s) {[n.encode('utf-8', 'surrogateescape') for n in undecodable][:3]} are not "
                         "UTF-8 (a file name in another encoding): rename the file(s) to export")
    check_conf_filter(min_conf, conf_percentile)  # every argument before anything is written
    check_point_cap(max_points, "max_points")
    check_point_cap(colmap_max_points, "colmap_max_points")
    check_seed(seed)
    if "tum" in formats:
        tum_timestamps(recon)
    if "colmap" in formats or "colmap_txt" in formats:
        check_shared_camera(recon, shared_camera)
    sources = recon.info.get("sources")
    scene = recon  # what the COLMAP and nerfstudio exports name: HEIC photographs as the JPEGs copied beside them
    if {"colmap", "colmap_txt", "nerfstudio"} & set(formats) and sources:
        from dataclasses import replace

        scene = replace(recon, names=exported_names(recon.names, sources))
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ShapeError(f"out_dir expected a folder to write into, got {str(out)!r}, which is a file")
    out.mkdir(parents=True, exist_ok=True)
    stale = sorted({name for name in OUTPUT_NAMES.values() if (out / name).exists()} - {OUTPUT_NAMES[f] for f in formats})
    if stale:  # e.g. a reconstruction.npz of another scene, which `pointmap splat` / `localize` would then read
        import warnings

        warnings.warn(f"save_reconstruction: {out} holds {', '.join(stale)} of an earlier export, which this one "
                      f"({', '.join(formats)}) does not rewrite: they describe that run's scene; remove them or "
                      "write to another folder", stacklevel=2)
    written: dict = {}
    point_formats = sorted({"ply", "glb", "colmap", "colmap_txt", "nerfstudio"} & set(formats))
    if point_formats and not confidence_mask(recon.conf, min_conf, conf_percentile, within=recon.valid()).any():
        import warnings

        warnings.warn(f"save_reconstruction: no point passes the masks and the confidence filter (min_conf={min_conf}, "
                      f"conf_percentile={conf_percentile}): {', '.join(point_formats)} hold an empty point cloud (an "
                      "empty COLMAP points3D stops 3DGS trainers); lower the filter", stacklevel=2)
    if "ply" in formats or "glb" in formats:
        pts = select_points(recon, min_conf, conf_percentile, max_points, seed)
        if "ply" in formats:
            write_ply(out / "points.ply", pts.xyz, pts.rgb, pts.conf)
            written["ply"] = out / "points.ply"
        if "glb" in formats:
            write_glb(out / "scene.glb", recon, pts)
            written["glb"] = out / "scene.glb"
    if {"colmap", "colmap_txt", "nerfstudio"} & set(formats):
        pts = select_points(recon, min_conf, conf_percentile, colmap_max_points, seed)
        if "colmap" in formats or "colmap_txt" in formats:
            written["colmap"] = write_colmap(scene, out / "sparse" / "0", pts, binary="colmap" in formats,
                                             text=colmap_text or "colmap_txt" in formats,
                                             shared_camera=shared_camera)
        if "nerfstudio" in formats:
            written["nerfstudio"] = write_transforms(scene, out, pts)
        if sources and any(s is not None for s in sources):
            written["colmap_images"] = write_colmap_images(sources, scene.names, out / "images")
    if "tum" in formats:
        written["tum"] = write_tum(recon, out / "trajectory.txt")
    if "npz" in formats:
        write_npz(out / "reconstruction.npz", recon)
        written["npz"] = out / "reconstruction.npz"
    return written


__all__ = ["confidence_mask", "load_npz", "read_ply", "save_reconstruction", "select_points", "write_colmap",
           "write_colmap_images", "write_glb", "write_npz", "write_ply", "write_transforms", "write_tum"]


def _utf8(name: str) -> bool:
    """Whether ``name`` encodes as UTF-8 (a file name read in another encoding holds surrogate escapes)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True
