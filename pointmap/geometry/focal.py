"""Focal length of a pinhole camera from its own camera-frame pointmap (as DUSt3R/MASt3R do)."""

from __future__ import annotations

import torch

from pointmap.errors import ShapeError
from pointmap.geometry.cameras import pixel_grid


def focal_from_pointmap(pts_cam: torch.Tensor, valid: torch.Tensor | None = None, *, pp=None,
                        iters: int = 10, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Estimate one focal per image (fx = fy) from camera-frame points [B, H, W, 3].

    The principal point defaults to the image centre ((W-1)/2, (H-1)/2 in our integer-centre pixel
    convention; the official code uses (W/2, H/2) with half-integer centres: the same point). Starts
    from the least-squares focal and refines the L1 (Weiszfeld) estimate, so outlier pixels do
    not pull it. Returns [B] focals in pixels of this pointmap's resolution; NaN for an image without a single
    usable pixel (finite, in front of the camera, inside ``valid``).
    """
    if not isinstance(pts_cam, torch.Tensor) or pts_cam.ndim != 4 or pts_cam.shape[-1] != 3:
        raise ShapeError(f"pts_cam expected a [B, H, W, 3] tensor, got "
                         f"{list(pts_cam.shape) if isinstance(pts_cam, torch.Tensor) else type(pts_cam).__name__}")
    B, H, W, _ = pts_cam.shape
    dtype = pts_cam.dtype
    if valid is not None and (not isinstance(valid, torch.Tensor) or valid.dtype != torch.bool
                              or tuple(valid.shape) != (B, H, W)):
        raise ShapeError(f"valid expected a bool [{B}, {H}, {W}] tensor, got "
                         f"{(valid.dtype, list(valid.shape)) if isinstance(valid, torch.Tensor) else type(valid).__name__}")
    if weights is not None and tuple(getattr(weights, "shape", ())) != (B, H, W):
        raise ShapeError(f"weights expected [{B}, {H}, {W}], got {list(getattr(weights, 'shape', ()))}")
    if pp is None:
        pp = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=dtype, device=pts_cam.device).expand(B, 2)
    else:
        pp = torch.as_tensor(pp, dtype=dtype, device=pts_cam.device)
        pp = pp.expand(B, 2) if tuple(pp.shape) == (2,) else pp
        if tuple(pp.shape) != (B, 2):
            raise ShapeError(f"pp expected (cx, cy) or [{B}, 2], got {list(pp.shape)}")
    p, r, ok = focal_rays(pts_cam, valid, pp)
    w0 = ok.to(dtype) if weights is None else ok.to(dtype) * weights.reshape(B, -1)
    return solve_focal(p, r, w0, iters)


def focal_rays(pts_cam: torch.Tensor, valid: torch.Tensor | None, pp: torch.Tensor):
    """What the focal is solved from, for camera-frame points [B, H, W, 3] and principal points ``pp`` [B, 2]
    (pixels): each pixel's offset from the principal point p [B, H*W, 2], its point's x / z and y / z r
    [B, H*W, 2] (0 where unusable), and ``ok`` [B, H*W], the usable pixels (finite, in front of the camera, inside
    ``valid`` [B, H, W] when given). Differentiable in the points (no division by z <= 0). No input checks: the
    callers' (``focal_from_pointmap``; ``training.losses.focal_loss``)."""
    B, H, W, _ = pts_cam.shape
    p = pixel_grid(H, W, device=pts_cam.device, dtype=pts_cam.dtype)[None] - pp[:, None, None, :]  # [B, H, W, 2]
    z = pts_cam[..., 2:3]
    r = pts_cam[..., :2] / torch.where(z > 0, z, torch.ones_like(z))
    ok = torch.isfinite(r).all(-1) & (z[..., 0] > 0)
    if valid is not None:
        ok = ok & valid
    r = torch.where(ok[..., None], r, torch.zeros_like(r))
    return p.expand_as(r).reshape(B, -1, 2), r.reshape(B, -1, 2), ok.reshape(B, -1)


def solve_focal(p: torch.Tensor, r: torch.Tensor, w0: torch.Tensor, iters: int) -> torch.Tensor:
    """[B] focal minimising the w0-weighted sum of |p - f r| (``focal_rays``' p, r [B, N, 2], weights w0 [B, N]):
    the weighted least-squares focal, then ``iters`` Weiszfeld steps toward the L1 one (0: least squares alone,
    differentiable in p, r and w0). NaN for an image whose weights are all 0."""
    f = (w0[..., None] * r * p).sum((1, 2)) / (w0[..., None] * r * r).sum((1, 2)).clamp_min(1e-12)
    for _ in range(iters):
        resid = (p - f[:, None, None] * r).norm(dim=-1)
        w = w0 / resid.clamp_min(1e-8)
        f = (w[..., None] * r * p).sum((1, 2)) / (w[..., None] * r * r).sum((1, 2)).clamp_min(1e-12)
    return torch.where(w0.sum(-1) > 0, f, torch.full_like(f, float("nan")))
