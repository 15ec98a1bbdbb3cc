"""Rotation helpers: angles between rotations, SO(3)/se(3) exponentials (via kornia), random draws."""

from __future__ import annotations

import math

import torch

from pointmap.errors import check_shape


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Angle in radians of rotations [..., 3, 3], numerically safe near 0 and pi."""
    check_shape("R", R, (..., 3, 3))
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((trace - 1) / 2).clamp(-1.0, 1.0)
    # atan2 form is accurate for small angles, where acos loses precision.
    skew = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = skew.norm(dim=-1) / 2
    return torch.atan2(sin, cos)


def project_to_rotation(M: torch.Tensor) -> torch.Tensor:
    """The rotation nearest to a [..., 3, 3] matrix in Frobenius norm (SVD, det fixed to +1), batched over the
    leading dimensions. Applied to a sum of rotations it is their chordal mean."""
    check_shape("M", M, (..., 3, 3))
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.det(U @ Vh))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return U @ D @ Vh


def relative_rotation_error_deg(R_pred: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """Geodesic distance in degrees between rotations [..., 3, 3]."""
    check_shape("R_pred", R_pred, (..., 3, 3))
    check_shape("R_gt", R_gt, (..., 3, 3))
    return torch.rad2deg(rotation_angle(R_pred.transpose(-1, -2) @ R_gt))


def translation_angle_deg(t_pred: torch.Tensor, t_gt: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Angle in degrees between translation directions [..., 3] (scale-free, as RTA uses). A zero vector has no
    direction: its angle to anything is 90 (a miss at any threshold below 90), not NaN."""
    check_shape("t_pred", t_pred, (..., 3))
    check_shape("t_gt", t_gt, (..., 3))
    a = t_pred / t_pred.norm(dim=-1, keepdim=True).clamp_min(eps)
    b = t_gt / t_gt.norm(dim=-1, keepdim=True).clamp_min(eps)
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1.0, 1.0)))


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: [..., 3] -> [..., 3, 3]; smooth at zero (differentiable)."""
    check_shape("axis_angle", axis_angle, (..., 3))
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2.clamp_min(1e-24))
    small = theta2 < 1e-8
    # sin(t)/t and (1-cos t)/t^2 with Taylor expansions near zero
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*axis_angle.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(Kx)
    return eye + a[..., None] * Kx + b[..., None] * (Kx @ Kx)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential of se(3) twists [..., 6] = (rho, phi) -> [..., 4, 4] rigid transforms."""
    check_shape("xi", xi, (..., 6))
    rho, phi = xi[..., :3], xi[..., 3:]
    R = axis_angle_to_matrix(phi)
    theta2 = (phi * phi).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(1e-24))
    # b = (1 - cos t) / t^2 multiplies a first-order term of the translation: written as 2 sin^2(t/2) / t^2 it
    # keeps every digit (1 - cos t lost all of float32's from t ~ 1e-4 on: gradients 30x off and of the wrong sign);
    # c = (t - sin t) / t^3 by its series up to t ~ 0.05, whose next term is below float64's rounding there
    half = theta / 2
    b = 0.5 * (torch.sin(half) / half) ** 2
    c = torch.where(theta2 < 2.5e-3, 1.0 / 6 - theta2 / 120 + theta2 * theta2 / 5040,
                    (theta - torch.sin(theta)) / (theta2 * theta).clamp_min(1e-24))
    x, y, z = phi.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*phi.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(Kx)
    V = eye + b * Kx + c * (Kx @ Kx)
    T = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = (V @ rho.unsqueeze(-1)).squeeze(-1)
    T[..., 3, 3] = 1
    return T


def random_rotation(generator: torch.Generator | None = None, max_angle: float = math.pi,
                    dtype=torch.float64) -> torch.Tensor:
    """A random rotation [3, 3] with angle uniform in [0, max_angle] about a uniform axis."""
    if not 0 <= max_angle <= math.pi:
        raise ValueError(f"max_angle expected radians in [0, pi], got {max_angle!r}")
    axis = torch.randn(3, generator=generator, dtype=dtype)
    axis = axis / axis.norm()
    angle = torch.rand((), generator=generator, dtype=dtype) * max_angle
    return axis_angle_to_matrix(axis * angle)
