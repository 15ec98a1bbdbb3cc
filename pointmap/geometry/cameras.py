"""Pinhole cameras in the OpenCV convention (docs/conventions.md): batched, differentiable.

Pixel (u, v) = integer column/row index of a pixel centre. ``K`` is [..., 3, 3] in pixels.
"""

from __future__ import annotations

import torch

from pointmap.errors import ShapeError, check_shape


def pixel_grid(height: int, width: int, *, device=None, dtype=torch.float32) -> torch.Tensor:
    """[H, W, 2] pixel-centre coordinates (u, v) = (column, row)."""
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                          torch.arange(width, device=device, dtype=dtype), indexing="ij")
    return torch.stack([u, v], dim=-1)


def intrinsics(focal, cx, cy, *, fy=None, dtype=torch.float32) -> torch.Tensor:
    """A [3, 3] K from a focal (fx, optionally fy) and a principal point, all in pixels."""
    fy = focal if fy is None else fy
    return torch.tensor([[focal, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def depth_to_points_cam(depth_z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Unproject z-depth [..., H, W] with K [..., 3, 3] into camera-frame points [..., H, W, 3]."""
    if depth_z.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ShapeError(f"depth_z expected [..., H, W] and K [..., 3, 3], got {list(depth_z.shape)} "
                         f"and {list(K.shape)}")
    h, w = depth_z.shape[-2:]
    uv = pixel_grid(h, w, device=depth_z.device, dtype=depth_z.dtype)
    fx = K[..., 0, 0, None, None]
    fy = K[..., 1, 1, None, None]
    cx = K[..., 0, 2, None, None]
    cy = K[..., 1, 2, None, None]
    x = (uv[..., 0] - cx) / fx * depth_z
    y = (uv[..., 1] - cy) / fy * depth_z
    return torch.stack([x, y, depth_z], dim=-1)


def transform_points(T: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Apply a rigid/similarity transform T [..., 4, 4] to points [..., *, 3] (T batch broadcast
    over the point dims: T [B, 4, 4] with pts [B, H, W, 3] works)."""
    if T.shape[-2:] != (4, 4) or pts.shape[-1] != 3:
        raise ShapeError(f"T expected [..., 4, 4] and pts [..., 3], got {list(T.shape)} and {list(pts.shape)}")
    extra = pts.ndim - T.ndim + 1  # number of point dims to broadcast over
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    for _ in range(max(extra, 0)):
        R = R.unsqueeze(-3)
        t = t.unsqueeze(-2)
    return (R @ pts.unsqueeze(-1)).squeeze(-1) + t


def depth_to_points_world(depth_z: torch.Tensor, K: torch.Tensor, cam2world: torch.Tensor) -> torch.Tensor:
    """[..., H, W] depth -> [..., H, W, 3] world points."""
    return transform_points(cam2world, depth_to_points_cam(depth_z, K))


def project(pts_cam: torch.Tensor, K: torch.Tensor, eps: float = 1e-8):
    """Project camera-frame points [..., N, 3] (or [..., H, W, 3]) to pixels; returns (uv, z).

    K is broadcast over the point dims like ``transform_points``.
    """
    check_shape("pts_cam", pts_cam, (..., 3))
    check_shape("K", K, (..., 3, 3))
    z = pts_cam[..., 2]
    extra = pts_cam.ndim - K.ndim + 1
    Kb = K
    for _ in range(max(extra, 0)):
        Kb = Kb.unsqueeze(-3)
    fx, fy, cx, cy = Kb[..., 0, 0], Kb[..., 1, 1], Kb[..., 0, 2], Kb[..., 1, 2]
    zs = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
    u = fx * pts_cam[..., 0] / zs + cx
    v = fy * pts_cam[..., 1] / zs + cy
    return torch.stack([u, v], dim=-1), z


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4] (rotation + translation, no scale)."""
    check_shape("T", T, (..., 4, 4))
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    out = torch.zeros_like(T)
    Rt = R.transpose(-1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1
    return out


def head_translation(t_head: torch.Tensor, t_points: torch.Tensor) -> torch.Tensor:
    """Camera translations [..., 3] with the pose head's direction (``t_head`` [..., 3]) and the length of the
    pointmaps' own estimate (``t_points`` [..., 3], e.g. a Procrustes'): the rule of ``relative_pose`` and of
    the global alignment's start. The head's directions are the better ones, its baselines come out short (about
    0.6 of the truth, session 49, docs/training-log.md). Where the head gives no direction (zero or not finite),
    the pointmaps' translation as it is. ShapeError unless both are [..., 3] of one shape."""
    if t_head.shape != t_points.shape or t_head.shape[-1:] != (3,):
        raise ShapeError(f"head_translation expected two [..., 3] translations of one shape, got "
                         f"{list(t_head.shape)} and {list(t_points.shape)}")
    length = t_head.norm(dim=-1, keepdim=True)
    out = t_head / length.clamp_min(1e-12) * t_points.norm(dim=-1, keepdim=True)
    return torch.where(torch.isfinite(length) & (length > 0), out, t_points)


def is_rigid(T: torch.Tensor, atol: float = 1e-3) -> torch.Tensor:
    """[...] bool: whether each [..., 4, 4] ``T`` is a finite rigid transform [R t; 0 0 0 1]: R^T R within ``atol`` of
    the identity with det +1 (>= 0.99), the last row within 1e-6 of (0, 0, 0, 1), t finite."""
    check_shape("T", T, (..., 4, 4))
    Td = T.double()
    R = Td[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64, device=T.device)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device=T.device)
    return (((R.transpose(-1, -2) @ R - eye).abs().amax((-1, -2)) <= atol) & (torch.det(R) >= 0.99)
            & ((Td[..., 3, :] - bottom).abs().amax(-1) <= 1e-6) & torch.isfinite(Td).all(-1).all(-1))


K_LAYOUT = "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"  # pinhole intrinsics in pixels, as is_pinhole_K accepts them


def is_pinhole_K(K, atol: float = 1e-6) -> torch.Tensor:
    """[...] bool: whether each [..., 3, 3] ``K`` is finite pinhole intrinsics in pixels, [[fx, 0, cx], [0, fy, cy],
    [0, 0, 1]] with fx, fy > 0 (the zeros and the 1 within ``atol``). A transposed K (cx, cy in the bottom row) fails,
    and so does a skew (K[0, 1]): every unprojection, projection and export here is skew-free and would drop it.
    Accepts tensors and arrays."""
    K = torch.as_tensor(K).double()
    check_shape("K", K, (..., 3, 3))
    bottom = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=K.device)
    return (torch.isfinite(K).all(-1).all(-1) & (K[..., 0, 0] > 0) & (K[..., 1, 1] > 0)
            & (K[..., 1, 0].abs() <= atol) & (K[..., 0, 1].abs() <= atol)
            & ((K[..., 2, :] - bottom).abs().amax(-1) <= atol))


def similarity_on_cam2world(cam2world: torch.Tensor, scale: float, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Cameras [..., 4, 4] (cam2world) after the world moves by x -> scale * R x + t: orientations R @ R_c,
    centres scale * R c + t (the camera frames themselves are not scaled)."""
    check_shape("cam2world", cam2world, (..., 4, 4))
    check_shape("R", R, (3, 3))
    check_shape("t", t, (3,))
    out = cam2world.clone()
    out[..., :3, :3] = R @ cam2world[..., :3, :3]
    out[..., :3, 3] = scale * cam2world[..., :3, 3] @ R.T + t
    return out


def scale_intrinsics(K: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """K of an image resized by (sx, sy), pixel centres at integers (u' + 0.5 = sx (u + 0.5))."""
    check_shape("K", K, (..., 3, 3))
    K = K.clone()
    K[..., 0, 0] *= sx
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 1] *= sy
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def crop_intrinsics(K: torch.Tensor, left: float, top: float) -> torch.Tensor:
    """K after cropping ``left`` columns and ``top`` rows off the image."""
    check_shape("K", K, (..., 3, 3))
    K = K.clone()
    K[..., 0, 2] -= left
    K[..., 1, 2] -= top
    return K


# Camera axes of the conventions users meet, as (right, down, forward) signs of OpenCV's x, y, z:
# OpenCV / COLMAP / pointmap: x right, y down, z forward; OpenGL / nerfstudio / Blender / three.js: x right, y up,
# z backward; PyTorch3D: x left, y up, z forward.
CAMERA_AXES = {"opencv": (1.0, 1.0, 1.0), "opengl": (1.0, -1.0, -1.0), "pytorch3d": (-1.0, -1.0, 1.0)}


def convert_camera_axes(cam2world, src: str = "opencv", dst: str = "opengl"):
    """``cam2world`` [..., 4, 4] (torch or NumPy) with its camera axes in convention ``src`` -> the same cameras
    (same centres, same orientation in the world) with axes in ``dst`` (names in ``CAMERA_AXES``): a right
    multiplication by a diagonal sign matrix. For world-to-camera matrices, invert first (``invert_rigid``)."""
    for name, conv in (("src", src), ("dst", dst)):
        if conv not in CAMERA_AXES:
            raise ShapeError(f"{name} expected one of {sorted(CAMERA_AXES)}, got {conv!r}")
    if getattr(cam2world, "shape", ())[-2:] != (4, 4):
        raise ShapeError(f"cam2world expected [..., 4, 4], got {tuple(getattr(cam2world, 'shape', ()))}")
    signs = [a * b for a, b in zip(CAMERA_AXES[src], CAMERA_AXES[dst])] + [1.0]
    if isinstance(cam2world, torch.Tensor):
        return cam2world * torch.tensor(signs, dtype=cam2world.dtype, device=cam2world.device)
    import numpy as np

    return np.asarray(cam2world) * np.asarray(signs)
