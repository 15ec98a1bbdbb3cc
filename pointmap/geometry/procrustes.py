"""Weighted rigid / similarity alignment of point sets (Umeyama), batched."""

from __future__ import annotations

import torch

from pointmap.errors import ShapeError, check_shape


def weighted_procrustes(src: torch.Tensor, dst: torch.Tensor, weights: torch.Tensor | None = None,
                        *, with_scale: bool = True, eps: float = 0.0):
    """Find (s, R, t) minimising sum_i w_i ||s R src_i + t - dst_i||^2.

    src, dst: [..., N, 3] (any leading batch dims, or none); weights: [..., N], non-negative (negative ones count
    as 0). Returns s [...], R [..., 3, 3], t [..., 3].
    The result is a proper rotation (det = +1), with the reflection fix of Umeyama (1991).
    A problem with no weight (no point, or every weight 0) has no answer: its s, R and t are NaN.
    The answer does not depend on the units of the points or of the weights (no absolute threshold): a
    problem whose src has no spread (its weighted points at one place, up to rounding) gets s = 0. ``eps``: an
    absolute source variance at or below which s is 0 too (default 0: none).
    """
    if not (isinstance(src, torch.Tensor) and isinstance(dst, torch.Tensor)) or src.ndim < 2:
        raise ShapeError(f"src and dst expected [..., N, 3] tensors, got "
                         f"{list(src.shape) if hasattr(src, 'shape') else type(src).__name__}")
    if src.shape != dst.shape or src.shape[-1] != 3:
        raise ShapeError(f"src and dst expected the same [..., N, 3] shape, got {list(src.shape)} and {list(dst.shape)}")
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device)
    if tuple(weights.shape) != tuple(src.shape[:-1]):
        raise ShapeError(f"weights expected {list(src.shape[:-1])}, got {list(weights.shape)}")
    if not (bool(torch.isfinite(src).all()) and bool(torch.isfinite(dst).all()) and bool(torch.isfinite(weights).all())):
        raise ShapeError("weighted_procrustes expected finite src, dst and weights, got NaN or inf (mask such points "
                         "out with a zero weight instead)")
    w = weights.clamp_min(0)
    wsum = w.sum(-1, keepdim=True)
    wsum = torch.where(wsum > 0, wsum, torch.ones_like(wsum))  # no weight: NaN answer below
    wn = (w / wsum).unsqueeze(-1)  # [..., N, 1]
    mu_s = (wn * src).sum(-2)
    mu_d = (wn * dst).sum(-2)
    xs = src - mu_s.unsqueeze(-2)
    xd = dst - mu_d.unsqueeze(-2)
    cov = (wn * xd).transpose(-1, -2) @ xs  # [..., 3, 3] = sum w d s^T
    U, S, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = U @ D @ Vh
    if with_scale:
        var_s = (wn * xs * xs).sum((-1, -2))
        num = (S * torch.diagonal(D, dim1=-2, dim2=-1)).sum(-1)
        # no spread, relative to the points' own magnitude (the rounding of src - mu), not to an absolute 1e-9: a
        # variance of 1e-10 is a real spread for points 1e-5 across
        noise = (4 * torch.finfo(src.dtype).eps) ** 2 * (wn * src * src).sum((-1, -2))  # (100 eps: s = 0 for a
        # float32 cloud 1 across at 1e5 from the origin)
        flat = var_s <= noise.clamp_min(eps)
        s = torch.where(flat, torch.zeros_like(num), num / torch.where(flat, torch.ones_like(var_s), var_s))
    else:
        s = torch.ones(src.shape[:-2], dtype=src.dtype, device=src.device)
    t = mu_d - s.unsqueeze(-1) * (R @ mu_s.unsqueeze(-1)).squeeze(-1)
    empty = w.sum(-1) <= 0
    if bool(empty.any()):
        nan = torch.tensor(float("nan"), dtype=s.dtype, device=s.device)
        s = torch.where(empty, nan, s)
        R = torch.where(empty[..., None, None], nan, R)
        t = torch.where(empty[..., None], nan, t)
    return s, R, t


def to_matrix(s: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Build [..., 4, 4] similarity matrices from scale [...], rotation [..., 3, 3], translation [..., 3]."""
    check_shape("R", R, (..., 3, 3))
    check_shape("t", t, (..., 3))
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T
