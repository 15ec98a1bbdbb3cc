"""Outputs of a splat fit: PNG renders of training and novel views, an orbit GIF/MP4, and ``run``, the
whole job (init + fit + files) in one call for the command line."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from pointmap.atomic import atomic_path, write_bytes
from pointmap.errors import ShapeError, check_seed, check_shape, is_int, is_number
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K, is_rigid
from pointmap.geometry.rotations import axis_angle_to_matrix
from pointmap.reconstruction import Reconstruction


def _to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def save_png(img: torch.Tensor, path) -> Path:
    from PIL import Image

    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(_to_uint8(img)).save(tmp, format="PNG")
    return path


def interpolate_pose(c2w_a: torch.Tensor, c2w_b: torch.Tensor, t: float) -> torch.Tensor:
    """Geodesic interpolation of two cam2world [4, 4] (rotation slerp, centre lerp). The relative rotation's
    axis-angle is scipy's, which holds at 180 degrees too (one of the two shortest arcs)."""
    from scipy.spatial.transform import Rotation

    check_shape("c2w_a", c2w_a, (4, 4))
    check_shape("c2w_b", c2w_b, (4, 4))
    if not (is_number(t) and math.isfinite(t)):
        raise ShapeError(f"interpolate_pose: t expected a finite number, got {t!r}")
    Ra, Rb = c2w_a[:3, :3].double(), c2w_b[:3, :3].double()
    aa = torch.from_numpy(Rotation.from_matrix((Ra.T @ Rb).cpu().numpy()).as_rotvec())
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = Ra @ axis_angle_to_matrix(aa * t)
    out[:3, 3] = (1 - t) * c2w_a[:3, 3].double() + t * c2w_b[:3, 3].double()
    return out.to(c2w_a.dtype)


def orbit_poses(cam2world: torch.Tensor, center: torch.Tensor, n_frames: int = 36,
                max_angle_deg: float = 15.0) -> torch.Tensor:
    """[n_frames, 4, 4]: ``cam2world`` swung left-right around ``center`` about the camera's up axis."""
    up = -cam2world[:3, 1].double()
    c2w = cam2world.double()
    out = []
    for k in range(n_frames):
        ang = math.radians(max_angle_deg) * math.sin(2 * math.pi * k / n_frames)
        R = axis_angle_to_matrix(up * ang)
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = R
        T[:3, 3] = center.double() - R @ center.double()
        out.append(T @ c2w)
    return torch.stack(out).to(cam2world.dtype)


def save_orbit(frames: list, path, fps: int = 12) -> Path:
    """Animated GIF (PIL) or MP4 (OpenCV) from [H, W, 3] frames, by the file extension."""
    path = Path(path)
    if path.suffix.lower() not in (".gif", ".mp4"):
        raise ShapeError(f"orbit path must end in .gif or .mp4, got {path.name}")
    if not frames:
        raise ShapeError("save_orbit expected at least one frame, got none")
    arrs = [_to_uint8(f) for f in frames]
    with atomic_path(path) as tmp:  # tmp keeps the suffix: both writers pick the format from it
        if path.suffix.lower() == ".gif":
            from PIL import Image

            ims = [Image.fromarray(a) for a in arrs]
            ims[0].save(tmp, save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)
        else:
            import cv2

            h, w = arrs[0].shape[:2]
            vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
            if not vw.isOpened():
                raise OSError(f"OpenCV could not open an mp4 writer for {path}")
            for a in arrs:
                vw.write(a[..., ::-1])
            vw.release()
    return path


def scene_center(fit_result, view: int = 0) -> torch.Tensor:
    """A look-at point: along view ``view``'s optical axis at the median depth of the Gaussians."""
    c2w = fit_result.cam2world[view]
    means = fit_result.gaussians.means
    z = (means - c2w[:3, 3]) @ c2w[:3, 2]
    d = float(z[z > 0].median()) if bool((z > 0).any()) else 1.0
    return c2w[:3, 3] + d * c2w[:3, 2]


def strict_json(obj) -> bytes:
    """``obj`` as strict JSON: NaN and infinite numbers (a view with no pixel to score, an exact render's PSNR)
    written as null, which every parser reads, not as the bare NaN / Infinity Python writes by default."""
    clean = json.loads(json.dumps(obj), parse_constant=lambda c: None)
    return json.dumps(clean, indent=1, allow_nan=False).encode()


def run(recon: Reconstruction, out_dir, *, max_gaussians: int | None = None, steps: int | None = None,
        optimize_poses: bool = True, time_budget: float | None = None, orbit: str = "orbit.gif",
        orbit_frames: int = 36, progress: bool = True, quiet: bool = False, seed: int = 0) -> dict:
    """Init + fit + outputs. Writes under ``out_dir``:

    - ``splat.ply``: fitted Gaussians (3DGS layout);
    - ``renders/train_XXX.png`` (render | photo) and ``renders/novel_XXX.png`` (between training views);
    - ``orbit.gif`` (or .mp4 by ``orbit``'s extension);
    - ``cameras_refined.json``: refined and initial cam2world per view, K;
    - ``splat_metrics.json``: per-view training PSNR, Gaussian count, timings;
    - ``refined/``: the reconstruction with the refined cameras (COLMAP + npz, via ``Reconstruction.save``).

    ``quiet`` silences the progress bar and the summary line.

    Returns a dict with the paths, the ``fit`` result and ``recon_refined`` (a Reconstruction with the
    refined cameras; save it with ``recon_refined.save(...)`` for a COLMAP export).
    """
    from pointmap.splat.fit import auto_budget, fit, psnr
    from pointmap.splat.init import check_has_points, init_from

    if not isinstance(recon, Reconstruction):
        raise ShapeError(f"run expects a pointmap Reconstruction, got {type(recon).__name__}")
    if time_budget is not None and not (is_number(time_budget) and 0 < time_budget < math.inf):
        raise ShapeError(f"time_budget expected seconds > 0 (None: no limit), got {time_budget!r}")
    if orbit and Path(orbit).suffix.lower() not in (".gif", ".mp4"):  # checked before minutes of fitting
        raise ShapeError(f"orbit expected a file name ending in .gif or .mp4 (or '' for none), got {orbit!r}")
    if not (is_int(orbit_frames) and orbit_frames >= 0):
        raise ShapeError(f"orbit_frames expected an int >= 0, got {orbit_frames!r}")
    if max_gaussians is not None and not (is_int(max_gaussians) and max_gaussians >= 1):
        raise ShapeError(f"max_gaussians expected an int >= 1 (None: the budget's), got {max_gaussians!r}")
    check_seed(seed)  # before the output folder is made
    check_has_points(recon)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    n, h, w = recon.depth_z.shape
    budget = auto_budget(n, (w, h))
    mg = budget["max_gaussians"] if max_gaussians is None else max_gaussians
    gaussians = init_from(recon, max_gaussians=mg, seed=seed)
    t_init = time.perf_counter() - t0
    remaining = None if time_budget is None else max(1.0, time_budget - t_init)
    progress = progress and not quiet
    res = fit(recon, gaussians, steps=steps, optimize_poses=optimize_poses, progress=progress,
              time_budget=remaining, seed=seed)
    paths = {"ply": res.gaussians.save_ply(out_dir / "splat.ply")}
    K = res.K
    train_psnr = []
    rdir = out_dir / "renders"
    for i in range(n):
        vw, vh = recon.map_sizes[i]  # each view at its own size (a canvas of several sizes pads the smaller)
        img = res.render(res.cam2world[i], K[i], vw, vh)
        photo = recon.crop(recon.images, i).float()
        # over the pixels the fit was fitted to (the masks', when the fit used them)
        train_psnr.append(psnr(img, photo, recon.crop(recon.masks, i) if res.config.get("masked") else None))
        save_png(torch.cat([img, photo], dim=1), rdir / f"train_{i:03d}.png")
    for i in range(n - 1):
        c2w = interpolate_pose(res.cam2world[i], res.cam2world[i + 1], 0.5)
        save_png(res.render(c2w, K[i], *recon.map_sizes[i]), rdir / f"novel_{i:03d}.png")
    paths["renders"] = rdir
    if orbit and orbit_frames > 0:
        center = scene_center(res)
        frames = [res.render(T, K[0], *recon.map_sizes[0]) for T in orbit_poses(res.cam2world[0], center, orbit_frames)]
        paths["orbit"] = save_orbit(frames, out_dir / orbit)
    cams = {"names": list(recon.names), "cam2world_refined": res.cam2world.tolist(),
            "cam2world_init": res.cam2world_init.tolist(), "K": recon.K.float().tolist(),
            "convention": "OpenCV cam2world; K in original image pixels"}
    paths["cameras"] = out_dir / "cameras_refined.json"
    write_bytes(paths["cameras"], json.dumps(cams, indent=1).encode())
    metrics = {"train_psnr": train_psnr, "n_gaussians": len(res.gaussians), "init_seconds": t_init,
               "fit_seconds": res.seconds, "total_seconds": time.perf_counter() - t0,
               "steps_run": res.config["steps_run"], "working_sizes": res.config["levels"]}
    paths["metrics"] = out_dir / "splat_metrics.json"
    write_bytes(paths["metrics"], strict_json(metrics))
    refined = res.to_reconstruction(recon)
    try:
        paths["refined"] = refined.save(out_dir / "refined", formats=("colmap", "npz"))
    except ImportError:   # pointmap.io not available: the cameras JSON above still has the poses
        paths["refined"] = None
    if not quiet:
        scored = [p for p in train_psnr if math.isfinite(p)]  # a view with no pixel fitted has none
        mean = f"{sum(scored) / len(scored):.2f} dB" if scored else "none"
        print(f"splat: {len(res.gaussians)} Gaussians, {res.config['steps_run']} steps, training PSNR "
              f"{mean}, {metrics['total_seconds']:.0f} s -> {paths['ply']}")
    return {"paths": paths, "fit": res, "recon_refined": refined, "metrics": metrics}


def evaluate_views(res, images, cam2world, K, out_dir=None, *, align_steps: int = 100, names=None,
                   quiet: bool = False) -> dict:
    """Novel-view evaluation of a fit (InstantSplat's protocol): each held-out ``images[k]`` ([H, W, 3] in
    [0, 1] or uint8, e.g. a View's image at the maps' resolution) is rendered from ``cam2world[k]`` (e.g. from
    ``pointmap.localization``) with ``K[k]`` (that image's pixels), its pose aligned photometrically with the
    Gaussians frozen (``SplatFit.align_view``, ``align_steps``; 0 keeps the given pose), and rendered again.
    Returns {"views": [{name, psnr_init, psnr, ssim, cam2world}], "psnr", "ssim"} (means after alignment);
    with ``out_dir``, writes ``test_XXX.png`` (render | photograph) and ``test_views.json`` there."""
    from pointmap.splat.fit import _check_image, _ssim, psnr

    cam2world = torch.as_tensor(cam2world, dtype=torch.float32)
    K = torch.as_tensor(K, dtype=torch.float32)
    m = len(images)
    if m == 0 or tuple(cam2world.shape) != (m, 4, 4) or tuple(K.shape) != (m, 3, 3):
        raise ShapeError(f"evaluate_views expected M >= 1 images with cam2world [M, 4, 4] and K [M, 3, 3], got "
                         f"{m} images, {list(cam2world.shape)} and {list(K.shape)}")
    if not (torch.isfinite(cam2world).all() and torch.isfinite(K).all()):
        raise ShapeError("evaluate_views: every test view needs a finite pose and K (drop the ones localize "
                         "could not pose)")
    for name, T, ok, what in (("cam2world", cam2world, is_rigid(cam2world), "rigid [R t; 0 0 0 1] (R a rotation)"),
                              ("K", K, is_pinhole_K(K), f"pinhole intrinsics {K_LAYOUT} with positive focals")):
        if not bool(ok.all()):
            k = int((~ok).nonzero()[0])
            raise ShapeError(f"evaluate_views: {name} expected {what}, got {name}[{k}] = {T[k].tolist()}")
    if not (is_int(align_steps) and align_steps >= 0):
        raise ShapeError(f"evaluate_views: align_steps expected an int >= 0 (0: score the given poses), got "
                         f"{align_steps!r}")
    names = names or [f"test_{k:03d}" for k in range(m)]
    if len(names) != m or not all(isinstance(nm, str) for nm in names):
        raise ShapeError(f"evaluate_views: names expected {m} strings (one per test image), got {names!r}")
    if not (callable(getattr(res, "render", None)) and callable(getattr(res, "align_view", None))):
        raise ShapeError(f"evaluate_views expected a fit (pointmap.splat.fit's SplatFit), got {type(res).__name__}")
    imgs = [_check_image(images[k], f"test image {k}") for k in range(m)]  # all of them before any is written
    rows = []
    for k in range(m):
        img = imgs[k]
        h, w = img.shape[:2]
        before = res.render(cam2world[k], K[k], w, h)
        if align_steps > 0:
            T = res.align_view(img, cam2world[k], K[k], steps=align_steps)
            after = res.render(T, K[k], w, h)
        else:  # the given pose is scored as it is: its render is the one above
            T, after = cam2world[k], before
        rows.append({"name": names[k], "psnr_init": psnr(before, img), "psnr": psnr(after, img),
                     "ssim": float(_ssim(after, img)), "cam2world": T.tolist()})
        if out_dir is not None:
            save_png(torch.cat([after, img], dim=1), Path(out_dir) / f"test_{k:03d}.png")
    result = {"views": rows, "psnr": sum(r["psnr"] for r in rows) / m, "ssim": sum(r["ssim"] for r in rows) / m,
              "align_steps": align_steps}
    if out_dir is not None:  # strict JSON: an exact render's infinite PSNR is written as null
        write_bytes(Path(out_dir) / "test_views.json", strict_json(result))
    if not quiet:
        print(f"splat: {m} test views, PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.3f} after "
              f"{align_steps} steps of pose alignment (before: "
              f"{sum(r['psnr_init'] for r in rows) / m:.2f} dB)")
    return result
