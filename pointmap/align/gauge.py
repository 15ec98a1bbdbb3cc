"""The gauge of alignment (world frame and scale): fitting the initialisation to known poses, or putting the
world at the first camera."""

from __future__ import annotations

import torch

from pointmap.align.inputs import as_mask
from pointmap.geometry.cameras import invert_rigid, is_rigid, similarity_on_cam2world
from pointmap.geometry.rotations import project_to_rotation


def similarity_to_known(cam2world: torch.Tensor, known: dict, min_spread: float = 1e-6):
    """(a, Ra, ta, scale_fixed) taking the initial world onto the known poses' world.

    Rotation: chordal mean of R_known R_init^T. Scale: least squares on camera centres when >= 2 known
    centres are spread out (then the scale is fixed by the user's poses), else 1 (scale stays free).
    """
    idx = sorted(known)
    Rk = torch.stack([known[i][:3, :3].double() for i in idx])
    ck = torch.stack([known[i][:3, 3].double() for i in idx])
    Ri = cam2world[idx, :3, :3].double()
    ci = cam2world[idx, :3, 3].double()
    Ra = project_to_rotation((Rk @ Ri.transpose(-1, -2)).sum(0))
    mk, mi = ck.mean(0), ci.mean(0)
    spread_k = (ck - mk).norm(dim=-1).max() if len(idx) > 1 else torch.tensor(0.0, dtype=torch.float64)
    spread_i = (ci - mi).norm(dim=-1).max() if len(idx) > 1 else torch.tensor(0.0, dtype=torch.float64)
    scale_fixed = bool(len(idx) > 1 and spread_k > min_spread * max(1.0, float(ck.norm(dim=-1).max()))
                       and spread_i > 0)
    if scale_fixed:
        xi = (ci - mi) @ Ra.T
        a = float(((ck - mk) * xi).sum() / (xi * xi).sum().clamp_min(1e-300))
        if a <= 0:
            a = float(spread_k / spread_i)
    else:
        a = 1.0
    ta = mk - a * (Ra @ mi)
    return a, Ra, ta, scale_fixed


def apply_similarity(a: float, Ra, ta, cam2world, depth, pw_s, pw_R, pw_t):
    """Move an initialisation by x -> a Ra x + ta (depths and edge scales scale by a)."""
    return similarity_on_cam2world(cam2world, a, Ra, ta), depth * a, pw_s * a, Ra @ pw_R, a * pw_t @ Ra.T + ta


def anchor_to_first(cam2world: torch.Tensor, first: torch.Tensor | None = None) -> torch.Tensor:
    """The same cameras [N, 4, 4] (float64) in the world where camera 0's cam2world is ``first`` (default: the
    identity, i.e. seen from camera 0's frame): a rigid change of world frame that leaves relative poses,
    depths and scale untouched. Without known poses a Reconstruction's world is camera 0's frame
    (docs/conventions.md)."""
    move = invert_rigid(cam2world[0].double())
    if first is not None:
        move = first.double() @ move
    return move[None] @ cam2world.double()


def align_to_cameras(recon, cam2world, mask=None, *, with_scale: bool = True):
    """Move ``recon`` into the world of reference cameras (e.g. ground truth, a phone's metric poses) by the
    similarity ``similarity_to_known`` fits: rotation from the chordal mean of the per-camera rotation offsets,
    scale (when ``with_scale`` and two or more reference centres are spread out) and translation by least squares
    on the camera centres. ``cam2world``: [N, 4, 4] reference poses (OpenCV axes), all used unless ``mask`` [N]
    bool picks some. Returns (the moved Reconstruction, report): ``scale``, ``R``, ``t`` of the similarity,
    ``scale_fixed`` (False: the scale was left as it was, because ``with_scale`` is False or the reference has one
    camera or coincident centres), and the
    residual after the move over the reference cameras: ``ate_rmse`` (camera centres, the reference's units),
    ``rot_err_deg_median`` / ``_max``."""
    from pointmap.errors import ShapeError
    from pointmap.geometry.rotations import rotation_angle
    from pointmap.reconstruction import Reconstruction

    if not isinstance(recon, Reconstruction) or not isinstance(with_scale, bool):
        raise ShapeError(f"align_to_cameras expected a Reconstruction and with_scale True or False, got "
                         f"{type(recon).__name__} and {with_scale!r}")
    n = len(recon)
    try:
        ref = torch.as_tensor(cam2world, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ShapeError(f"cam2world expected [{n}, 4, 4] reference poses, got {type(cam2world).__name__}") from None
    keep = torch.ones(n, dtype=torch.bool) if mask is None else as_mask(mask, "mask")
    if tuple(keep.shape) != (n,) or not bool(keep.any()):
        raise ShapeError(f"mask expected [{n}] bool with at least one True, got {list(keep.shape)}")
    if tuple(ref.shape) != (n, 4, 4) or not bool(torch.isfinite(ref[keep]).all()):  # rows left out may be NaN
        raise ShapeError(f"cam2world expected [{n}, 4, 4] reference poses, finite where used, got {list(ref.shape)}")
    rigid = is_rigid(ref[keep])
    if not bool(rigid.all()):
        bad = [i for i, ok in zip(keep.nonzero()[:, 0].tolist(), rigid.tolist()) if not ok]
        raise ShapeError(f"cam2world expected rigid reference poses (a rotation and a translation, last row 0 0 0 1), "
                         f"got others at {bad[:8]}")
    known = {i: ref[i] for i in range(n) if keep[i]}
    a, Ra, ta, scale_fixed = similarity_to_known(recon.cam2world.double(), known)
    if not with_scale and scale_fixed:  # rotation as fitted; translation by the centres at scale 1
        idx = sorted(known)
        a, scale_fixed = 1.0, False
        ta = ref[idx, :3, 3].mean(0) - recon.cam2world.double()[idx, :3, 3].mean(0) @ Ra.T
    moved = recon.transformed(a, Ra, ta)
    est = moved.cam2world.double()[keep]
    centre_err = (est[:, :3, 3] - ref[keep, :3, 3]).norm(dim=-1)
    rot_err = torch.rad2deg(rotation_angle(est[:, :3, :3].transpose(-1, -2) @ ref[keep, :3, :3]))
    report = {"scale": float(a), "R": Ra.tolist(), "t": ta.tolist(), "scale_fixed": bool(scale_fixed),
              "cameras": int(keep.sum()), "ate_rmse": float(centre_err.pow(2).mean().sqrt()),
              "rot_err_deg_median": float(torch.quantile(rot_err, 0.5)), "rot_err_deg_max": float(rot_err.max())}
    return moved, report


def scale_to_depth(recon, depth, *, min_pixels: int = 50):
    """Put ``recon`` in the units of measured depth (a phone's LiDAR or ToF map, an RGB-D camera's, sparse depth
    from a survey): the scale is the median over every usable pixel of measured / reconstructed z-depth, applied
    about the world origin (``Reconstruction.transformed``: camera centres and depths scale, rotations stay).
    ``depth``: one entry per image, a [H, W] z-depth map (numpy or torch) in the wanted units at the ORIGINAL
    image's size or any size of its aspect ratio (a depth sensor's lower resolution), 0 / NaN / inf = none; None
    for images without one. Each reconstruction pixel reads the measured depth at the same original-image point
    (``map_from_original``; nearest). Pixels count where both depths exist and the reconstruction keeps the pixel
    (``recon.masks``). Returns (the scaled Reconstruction, report): ``scale``, ``pixels`` and ``images`` used,
    ``per_image`` (each image's own median ratio, None without depth), ``spread`` (1.4826 x the median absolute
    deviation of the log ratios: the relative scatter of the per-pixel scale, e.g. 0.05 = 5%). PointmapError with
    fewer than ``min_pixels`` usable pixels; ShapeError for a map of the wrong count or aspect ratio."""
    import numpy as np

    from pointmap.errors import PointmapError, ShapeError, is_int
    from pointmap.io.depth import same_aspect
    from pointmap.reconstruction import Reconstruction

    if not isinstance(recon, Reconstruction) or not (is_int(min_pixels) and min_pixels >= 1):
        raise ShapeError(f"scale_to_depth expected a Reconstruction and min_pixels an int >= 1, got "
                         f"{type(recon).__name__} and {min_pixels!r}")
    n = len(recon)
    if not isinstance(depth, (list, tuple)) or len(depth) != n:
        got = f"{len(depth)} entries" if isinstance(depth, (list, tuple)) else type(depth).__name__
        raise ShapeError(f"depth expected a list of {n} maps (None for an image without one), got {got}")
    h, w = recon.depth_z.shape[1:]
    ratios, per_image = [], []
    for i, d in enumerate(depth):
        if d is None:
            per_image.append(None)
            continue
        d = d.detach().cpu().numpy() if isinstance(d, torch.Tensor) else np.asarray(d)
        if d.ndim != 2 or not np.issubdtype(d.dtype, np.number) or min(d.shape) < 1:
            raise ShapeError(f"depth[{i}] expected a [H, W] map of numbers, got {d.dtype} {list(d.shape)}")
        ow, oh = recon.original_sizes[i]
        dh, dw = d.shape
        if not same_aspect((dw, dh), (ow, oh)):
            raise ShapeError(f"depth[{i}] is {dw}x{dh}, not the aspect ratio of image {i} ({ow}x{oh} original)")
        sx, sy, left, top = (float(x) for x in recon.map_from_original[i])
        u = (np.arange(w) + 0.5 + left) / sx  # map pixel centres in original edge coordinates
        v = (np.arange(h) + 0.5 + top) / sy
        cu = np.floor(u * dw / ow).astype(np.int64)  # the depth pixel holding that point
        cv = np.floor(v * dh / oh).astype(np.int64)
        inside = (cv[:, None] >= 0) & (cv[:, None] < dh) & (cu[None] >= 0) & (cu[None] < dw)
        measured = np.where(inside, d.astype(np.float64)[np.clip(cv, 0, dh - 1)][:, np.clip(cu, 0, dw - 1)], 0.0)
        ours = recon.depth_z[i].double().numpy()
        # ours: depth present, inside the user's masks and the view's own pixels (not a canvas's padding)
        keep = inside & np.isfinite(measured) & (measured > 0) & (ours > 0) & recon.valid()[i].numpy()
        r = np.log(measured[keep] / ours[keep])
        per_image.append(float(np.exp(np.median(r))) if r.size else None)
        ratios.append(r)
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if r.size < min_pixels:
        raise PointmapError(f"scale_to_depth needs at least {min_pixels} pixels where both the measured and the "
                            f"reconstructed depth exist, got {r.size}")
    log_scale = float(np.median(r))
    moved = recon.transformed(float(np.exp(log_scale)), torch.eye(3, dtype=torch.float64),
                              torch.zeros(3, dtype=torch.float64))
    report = {"scale": float(np.exp(log_scale)), "pixels": int(r.size),
              "images": sum(p is not None for p in per_image), "per_image": per_image,
              "spread": float(1.4826 * np.median(np.abs(r - log_scale)))}
    return moved, report
