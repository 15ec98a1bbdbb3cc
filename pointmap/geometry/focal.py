"""Focal length of a pinhole camera from its own camera-frame pointmap (as DUSt3R/MASt3R do)."""

from __future__ import annotations

import torch

from pointmap.errors import ShapeError


def focal_from_pointmap(pts_cam: torch.Tensor, valid: torch.Tensor | None = None, *, pp=None,
                        iters: int = 10, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Estimate one focal per image (fx = fy) from camera-frame points [B, H, W, 3].

    The principal point defaults to the image centre ((W-1)/2, (H-1)/2 in our integer-centre pixel
    convention; the official code uses (W/2, H/2) with half-integer centres: the same point). Starts
    from the least-squares focal and refines the L1 (Weiszfeld) estimate, so outlier pixels do
    not pull it. Returns [B] focals in pixels of this pointmap's resolution.
    """
    if pts_cam.ndim != 4 or pts_cam.shape[-1] != 3:
        raise ShapeError(f"pts_cam expected [B, H, W, 3], got {list(pts_cam.shape)}")
    B, H, W, _ = pts_cam.shape
    dtype = pts_cam.dtype
    if pp is None:
        pp = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=dtype, device=pts_cam.device).expand(B, 2)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype, device=pts_cam.device),
                          torch.arange(W, dtype=dtype, device=pts_cam.device), indexing="ij")
    p = torch.stack([u, v], -1)[None] - pp[:, None, None, :]  # [B, H, W, 2]
    z = pts_cam[..., 2:3]
    r = pts_cam[..., :2] / z
    ok = torch.isfinite(r).all(-1) & (z[..., 0] > 0)
    if valid is not None:
        ok = ok & valid
    w0 = ok.to(dtype) if weights is None else ok.to(dtype) * weights
    r = torch.where(ok[..., None], r, torch.zeros_like(r))
    p = p.expand_as(r).reshape(B, -1, 2)
    r = r.reshape(B, -1, 2)
    w0 = w0.reshape(B, -1)
    f = (w0[..., None] * r * p).sum((1, 2)) / (w0[..., None] * r * r).sum((1, 2)).clamp_min(1e-12)
    for _ in range(iters):
        resid = (p - f[:, None, None] * r).norm(dim=-1)
        w = w0 / resid.clamp_min(1e-8)
        f = (w[..., None] * r * p).sum((1, 2)) / (w[..., None] * r * r).sum((1, 2)).clamp_min(1e-12)
    return f
