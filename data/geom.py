"""Numpy geometry for data generation (OpenCV camera convention, docs/conventions.md).

The library's batched torch versions live in ``pointmap.geometry``; these numpy twins exist because
generation runs per image on CPU workers where numpy is faster and torch is not needed. The tests
check both agree.
"""

from __future__ import annotations

import numpy as np

from pointmap.errors import ShapeError

CORR_SCALE = 64.0        # correspondences are stored as uint16 fixed point, 1/64 px
CORR_NONE = 65535        # stored value meaning "not co-visible"
CORR_MAX = (CORR_NONE - 1) / CORR_SCALE
MAX_SIDE = 8192  # the largest image side the renderer's framebuffer takes (data.render)


def intrinsics_from_fov(width: int, height: int, fov_deg: float, *, cx_offset: float = 0.0,
                        cy_offset: float = 0.0) -> np.ndarray:
    """K [3, 3] float64 with square pixels; ``fov_deg`` spans the longer image side. The principal
    point is the image centre ((W - 1) / 2, (H - 1) / 2) plus offsets in pixels."""
    if not (0 < fov_deg < 180):
        raise ShapeError(f"fov_deg expected in (0, 180), got {fov_deg}")
    if width < 1 or height < 1:
        raise ShapeError(f"image size expected positive, got {width}x{height}")
    f = 0.5 * max(width, height) / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2 + cx_offset], [0, f, (height - 1) / 2 + cy_offset], [0, 0, 1]])


def look_at(eye, target, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """OpenCV cam2world [4, 4] (x right, y down, z forward) at ``eye`` looking at ``target``; ``roll``
    (radians) turns the camera about its viewing axis."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-9:
        raise ShapeError("look_at: eye and target coincide")
    z = z / n
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking straight along up: any perpendicular will do
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def axis_angle(axis, angle: float) -> np.ndarray:
    """[3, 3] rotation of ``angle`` radians about ``axis`` (any length > 0; Rodrigues)."""
    k = np.asarray(axis, np.float64)
    n = np.linalg.norm(k)
    if k.shape != (3,) or n < 1e-12:
        raise ShapeError(f"axis_angle expected a non-zero axis of shape (3,), got {k!r}")
    k = k / n
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def invert_rigid(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def unproject(depth_z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[H, W] z-depth -> camera-frame points [H, W, 3] (pixel centres at integer coordinates)."""
    if depth_z.ndim != 2 or K.shape != (3, 3):
        raise ShapeError(f"unproject expected depth [H, W] and K [3, 3], got {depth_z.shape} and {K.shape}")
    h, w = depth_z.shape
    u = (np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    v = (np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    d = depth_z.astype(np.float64)
    return np.stack([u[None, :] * d, v[:, None] * d, d], -1)


def transform(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


def correspondences(depth1, K1, cam2world1, depth2, K2, cam2world2, *, rel_tol: float = 0.005, stride: int = 1):
    """Pixel of each view-1 pixel in view 2 where co-visible, by a depth test.

    Returns (corr [H1, W1, 2] float32 with NaN where not co-visible, covis [H1, W1] bool). A view-1
    pixel with depth is co-visible when its 3D point lands inside view 2 in front of the camera and
    view 2's depth there agrees within ``rel_tol`` (relative): either the bilinearly interpolated
    inverse depth (exact on planes, where 1/z is affine in the image; used only when all four
    neighbours have depth) or the nearest pixel's depth. ``stride`` > 1 tests only every stride-th
    row and column of view 1 (fast overlap estimates); the other pixels are left not co-visible.
    """
    import cv2

    for name, d in (("depth1", depth1), ("depth2", depth2)):
        if d.ndim != 2:
            raise ShapeError(f"{name} expected [H, W], got {list(d.shape)}")
    h1, w1 = depth1.shape
    h2, w2 = depth2.shape
    d1 = np.asarray(depth1, np.float32)[::stride, ::stride]
    u1 = np.arange(0, w1, stride, dtype=np.float64)
    v1 = np.arange(0, h1, stride, dtype=np.float64)
    T = invert_rigid(np.asarray(cam2world2, np.float64)) @ np.asarray(cam2world1, np.float64)
    # rays of view 1 in view 2's frame: p2 = R (ray * d) + t with ray = ((u - cx) / fx, (v - cy) / fy, 1)
    K1 = np.asarray(K1, np.float64)
    rx = ((u1 - K1[0, 2]) / K1[0, 0]).astype(np.float32)[None, :]
    ry = ((v1 - K1[1, 2]) / K1[1, 1]).astype(np.float32)[:, None]
    R = T[:3, :3].astype(np.float32)
    t = T[:3, 3].astype(np.float32)
    X = (R[0, 0] * rx + R[0, 1] * ry + R[0, 2]) * d1 + t[0]
    Y = (R[1, 0] * rx + R[1, 1] * ry + R[1, 2]) * d1 + t[1]
    Z = (R[2, 0] * rx + R[2, 1] * ry + R[2, 2]) * d1 + t[2]
    front = (d1 > 0) & (Z > 1e-6)
    Zs = np.where(front, Z, np.float32(1.0))
    K2 = np.asarray(K2, np.float64)
    u = (np.float32(K2[0, 0]) * X / Zs + np.float32(K2[0, 2])).astype(np.float32)
    v = (np.float32(K2[1, 1]) * Y / Zs + np.float32(K2[1, 2])).astype(np.float32)
    inside = front & (u > -0.5) & (u < w2 - 0.5) & (v > -0.5) & (v < h2 - 0.5)
    dep2 = np.asarray(depth2, np.float32)
    has2 = dep2 > 0
    inv2 = np.where(has2, 1.0 / np.where(has2, dep2, 1.0), 0.0).astype(np.float32)
    um = np.where(inside, u, np.float32(-10))
    vm = np.where(inside, v, np.float32(-10))
    dn = cv2.remap(dep2, um, vm, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inv_b = cv2.remap(inv2, um, vm, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    all4 = cv2.remap(has2.astype(np.float32), um, vm, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0) > 0.9999
    ok_nearest = (dn > 0) & (np.abs(dn - Z) <= rel_tol * Z)
    ok_bilinear = all4 & (np.abs(inv_b * Z - 1.0) <= rel_tol)
    ok = inside & (ok_nearest | ok_bilinear)
    corr = np.full((h1, w1, 2), np.nan, np.float32)
    covis = np.zeros((h1, w1), bool)
    sub = corr[::stride, ::stride]
    sub[..., 0] = np.where(ok, u, np.nan)
    sub[..., 1] = np.where(ok, v, np.nan)
    covis[::stride, ::stride] = ok
    return corr, covis


def overlap(depth1, K1, cam2world1, depth2, K2, cam2world2, *, stride: int = 1, **kw) -> float:
    """Fraction of view-1 pixels with depth that are co-visible in view 2 (estimated on every
    ``stride``-th row and column)."""
    n = int((depth1[::stride, ::stride] > 0).sum())
    if n == 0:
        return 0.0
    _, covis = correspondences(depth1, K1, cam2world1, depth2, K2, cam2world2, stride=stride, **kw)
    return float(covis.sum() / n)


def encode_corr(corr: np.ndarray) -> np.ndarray:
    """[H, W, 2] float (NaN = none) -> uint16 fixed point (1/64 px; 65535 = none). Lossless to 1/128 px."""
    if corr.ndim != 3 or corr.shape[-1] != 2:
        raise ShapeError(f"corr expected [H, W, 2], got {list(corr.shape)}")
    none = ~np.isfinite(corr).all(-1)
    c = np.where(none[..., None], 0.0, corr)
    if np.any((c < -0.5) | (c + 0.5 > CORR_MAX)):  # what is stored is c + 0.5 (65535 means none)
        raise ShapeError(f"corr values expected in [-0.5, {CORR_MAX - 0.5:.2f}] to fit the stored fixed point")
    q = np.rint(np.clip(c + 0.5, 0, None) * CORR_SCALE).astype(np.uint16)  # +0.5: pixel -0.5 is the image edge
    q[none] = CORR_NONE
    return q


def decode_corr(q: np.ndarray) -> np.ndarray:
    """Inverse of ``encode_corr``: uint16 [H, W, 2] -> float32 [H, W, 2] with NaN where not co-visible."""
    if q.dtype != np.uint16 or q.ndim != 3 or q.shape[-1] != 2:
        raise ShapeError(f"encoded corr expected uint16 [H, W, 2], got {q.dtype} {list(q.shape)}")
    out = q.astype(np.float32) / CORR_SCALE - 0.5
    out[(q == CORR_NONE).any(-1)] = np.nan
    return out
