"""A hand-made Reconstruction whose maps are a resized + cropped version of larger originals."""


import torch

from pointmap.geometry.rotations import axis_angle_to_matrix
from pointmap.reconstruction import Reconstruction


def make_recon(n=3, h=24, w=32, seed=0, with_mask=False):
    g = torch.Generator().manual_seed(seed)
    c2w = torch.eye(4).repeat(n, 1, 1)
    for k in range(n):
        c2w[k, :3, :3] = axis_angle_to_matrix(torch.tensor([0.1 * k, 0.4 * k - 0.3, 0.05]))
        c2w[k, :3, 3] = torch.tensor([0.5 * k, -0.2, 0.3 * k])
    # originals: 100x75 resized by 0.36 -> 36x27, cropped 2 px left, 1 px top -> 32x24 maps (as load_images)
    sx = sy = 0.36
    mfo = torch.tensor([[sx, sy, 2.0, 1.0]]).repeat(n, 1)
    K = torch.tensor([[80.0 + 5 * k, 0, 49.5 + k, 0, 79.0 + 5 * k, 37.0, 0, 0, 1] for k in range(n)]).reshape(n, 3, 3)
    depth = 2 + torch.rand(n, h, w, generator=g)
    depth[:, 0, 0] = 0  # a pixel without depth
    conf = 1 + 5 * torch.rand(n, h, w, generator=g)
    images = torch.rand(n, h, w, 3, generator=g)
    masks = None
    if with_mask:
        masks = torch.ones(n, h, w, dtype=torch.bool)
        masks[:, :, : w // 2] = False
    return Reconstruction(images=images, cam2world=c2w, K=K, depth_z=depth, conf=conf, map_from_original=mfo,
                          original_sizes=[(100, 75)] * n, names=[f"IMG_{k:04d}.JPG" for k in range(n)], masks=masks,
                          info={"align": {"final_loss": 0.1, "tree": [(0, 1, 2)]}})
