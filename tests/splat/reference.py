"""Float64 sequential reference rasterizer: one Gaussian at a time, the exact 3DGS recurrence.

Written independently of pointmap.splat.rasterize (no shared code) so the fast path is checked
against a second implementation. Slow: use tiny images and a few hundred Gaussians at most.
"""

from __future__ import annotations

import torch


def _rotmat(q):
    q = q / q.norm()
    w, x, y, z = q
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ])


def reference_render(means, quats, scales, opacities, colors, world2cam, K, width, height, background=None,
                     near=0.01, eps2d=0.3):
    """Returns (image [H, W, D], alpha [H, W], accumulated depth [H, W])."""
    dt = torch.float64
    means, quats, scales, opacities, colors, world2cam, K = (
        t.to(dt) for t in (means, quats, scales, opacities, colors, world2cam, K))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    vv, uu = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
    Rw, tw = world2cam[:3, :3], world2cam[:3, 3]
    z_all = (means @ Rw.T + tw)[:, 2]
    order = torch.argsort(z_all.detach(), stable=True)
    T = torch.ones(height, width, dtype=dt)
    done = torch.zeros(height, width, dtype=torch.bool)
    img = torch.zeros(height, width, colors.shape[1], dtype=dt)
    dep = torch.zeros(height, width, dtype=dt)
    for i in order.tolist():
        p = Rw @ means[i] + tw
        x, y, z = p[0], p[1], p[2]
        if float(z.detach()) <= near:
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        # Jacobian at the point clamped to 1.3x the frustum, whose edges are the outer pixel edges -0.5, W - 0.5
        xz = torch.clamp(x / z, -1.3 * (cx + 0.5) / fx, 1.3 * (width - 0.5 - cx) / fx)
        yz = torch.clamp(y / z, -1.3 * (cy + 0.5) / fy, 1.3 * (height - 0.5 - cy) / fy)
        J = torch.stack([torch.stack([fx / z, torch.zeros((), dtype=dt), -fx * xz / z]),
                         torch.stack([torch.zeros((), dtype=dt), fy / z, -fy * yz / z])])
        S = torch.diag(scales[i] ** 2)
        Rg = _rotmat(quats[i])
        cov3 = Rg @ S @ Rg.T
        cov2 = J @ Rw @ cov3 @ Rw.T @ J.T + eps2d * torch.eye(2, dtype=dt)
        det = cov2[0, 0] * cov2[1, 1] - cov2[0, 1] ** 2
        if float(det.detach()) <= 0:
            continue
        inv = torch.linalg.inv(cov2)
        dx = uu - u
        dy = vv - v
        q = inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
        a = torch.clamp(opacities[i] * torch.exp(-0.5 * q), max=0.999)
        use = (~done) & (a >= 1.0 / 255.0)
        test_T = T * (1 - a)
        stop = use & (test_T < 1e-4)
        done = done | stop
        use = use & ~stop
        w = torch.where(use, a * T, torch.zeros_like(a))
        img = img + w[..., None] * colors[i]
        dep = dep + w * z
        T = torch.where(use, test_T, T)
    if background is not None:
        img = img + T[..., None] * background.to(dt)
    return img, 1 - T, dep
