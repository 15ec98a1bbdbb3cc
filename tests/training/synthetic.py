"""A tiny in-memory pair dataset in the layout of DESIGN.md section 4 (for loop tests without rendering)."""

import torch

from pointmap.geometry import depth_to_points_cam, invert_rigid, project, transform_points


class PlanePairs(torch.utils.data.Dataset):
    def __init__(self, n=16, H=32, W=32, seed=0):
        self.n, self.H, self.W, self.seed = n, H, W, seed

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        g = torch.Generator().manual_seed(self.seed * 10_000 + i)
        H, W = self.H, self.W
        K = torch.tensor([[30.0, 0, (W - 1) / 2], [0, 30.0, (H - 1) / 2], [0, 0, 1]])
        c2w1 = torch.eye(4)
        c2w2 = torch.eye(4)
        c2w2[0, 3] = 0.2 + 0.1 * float(torch.rand((), generator=g))
        d1 = 2 + 0.5 * torch.rand(H, W, generator=g)
        d2 = 2 + 0.5 * torch.rand(H, W, generator=g)
        pts = transform_points(invert_rigid(c2w2) @ c2w1, depth_to_points_cam(d1, K))
        uv, _ = project(pts, K)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
        corr = torch.where(inside[..., None], uv, torch.full_like(uv, float("nan")))
        view = lambda d, c2w: dict(img=torch.rand(3, H, W, generator=g), K=K, cam2world=c2w, depth_z=d,  # noqa: E731
                                   valid=torch.ones(H, W, dtype=torch.bool))
        v1, v2 = view(d1, c2w1), view(d2, c2w2)
        v1["corr"] = corr
        v2["corr"] = torch.full((H, W, 2), float("nan"))
        return v1, v2
