"""Full-resolution depth maps from the aligned pair predictions.

With poses, intrinsics and edge similarities fixed, the depth d of a pixel with ray r (z = 1) that
minimises sum_e w_e ||d r - Y_e|| (Y_e = the edge's prediction of that pixel moved into the camera frame)
is found by iteratively reweighted least squares: d = sum w' (r . Y) / sum w' |r|^2 with
w' = w / max(||d r - Y||, eps). Pass 0 is the weighted least-squares (L2) solution. This runs one edge
at a time, so memory is O(image) no matter how many pairs there are.
"""

from __future__ import annotations

import torch

from pointmap.align.edges import conf_to_weight
from pointmap.geometry.cameras import pixel_grid


def _edge_points_cam(pred, side: int, s, R, t, world2cam):
    pts = (pred.pts1_cam1 if side == 0 else pred.pts2_cam1)[0].detach().to(torch.float32)
    conf = (pred.conf1 if side == 0 else pred.conf2)[0].detach().to(torch.float32)
    ok = torch.isfinite(pts).all(-1) & torch.isfinite(conf)
    pts = torch.where(ok[..., None], pts, torch.zeros_like(pts))
    A = (world2cam[:3, :3] @ (s * R)).float()
    b = (world2cam[:3, :3] @ t + world2cam[:3, 3]).float()
    return torch.addmm(b, pts.reshape(-1, 3), A.T).reshape(pts.shape), ok, conf


def fuse_depth(preds: dict, keys: list, shapes: list, cam2world: torch.Tensor, fx, fy, cx, cy,
               pw_s, pw_R, pw_t, conf_transform: str = "log", iters: int = 2):
    """Returns (depth_z list of [h, w] float64 (0 = no value), conf list of [h, w] = max conf over edges).

    cam2world [N, 4, 4], intrinsics [N] in map pixels, pw_* per directed edge in ``keys`` order; all in
    the same (internal) world units.
    """
    n = len(shapes)
    c2w = cam2world.to(torch.float64)
    world2cam = torch.linalg.inv(c2w)
    ray = []
    for k, (h, w) in enumerate(shapes):
        uv = pixel_grid(h, w, dtype=torch.float64)
        ray.append(torch.stack([(uv[..., 0] - cx[k]) / fx[k], (uv[..., 1] - cy[k]) / fy[k],
                                torch.ones(h, w, dtype=torch.float64)], -1).float())
    by_image: dict[int, list] = {k: [] for k in range(n)}
    for e, (i, j) in enumerate(keys):
        by_image[i].append((e, 0))
        by_image[j].append((e, 1))
    depths, confs = [], []
    for k in range(n):
        h, w = shapes[k]
        r = ray[k]
        rr = (r * r).sum(-1)
        conf_max = torch.zeros(h, w)
        depth = torch.zeros(h, w)
        for it in range(iters + 1):  # accumulate in float64, per-edge work in float32
            num = torch.zeros(h, w, dtype=torch.float64)
            den = torch.zeros(h, w, dtype=torch.float64)
            for e, side in by_image[k]:
                i, j = keys[e]
                Y, ok, conf = _edge_points_cam(preds[(i, j)], side, pw_s[e].double(), pw_R[e].double(),
                                               pw_t[e].double(), world2cam[k])
                wgt = torch.where(ok, conf_to_weight(conf, conf_transform), torch.zeros_like(conf))
                if it == 0:
                    conf_max = torch.maximum(conf_max, torch.where(ok, conf, torch.zeros_like(conf)))
                else:
                    res = (depth[..., None] * r - Y).norm(dim=-1)
                    scale = depth.clamp_min(1e-12) * 1e-6
                    wgt = wgt / torch.maximum(res, scale)
                num += wgt * (r * Y).sum(-1)
                den += wgt * rr
            depth = torch.where(den > 0, num / den.clamp_min(1e-300), torch.zeros_like(num))
            depth = torch.where(depth > 0, depth, torch.zeros_like(depth)).float()
        depths.append(depth.double())
        confs.append(conf_max)
    return depths, confs
