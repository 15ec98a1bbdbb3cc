"""Fit helpers on hand-made Gaussians (no rendered scene, so no pyrender): the loss, align_view, densification."""

import math

import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import Gaussians, SplatFit
from pointmap.splat.fit import _densify_prune, photometric_loss


def _strip_fit(width=64, height=10):
    g = Gaussians.from_points(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)) * 0.3
                              + torch.tensor([0, 0, 3.0]), torch.full((200, 3), 0.5), 0.05)
    K = torch.tensor([[60.0, 0, (width - 1) / 2], [0, 60.0, (height - 1) / 2], [0, 0, 1]])
    return SplatFit(gaussians=g, cam2world=torch.eye(4)[None], cam2world_init=torch.eye(4)[None], K=K[None],
                    size=(width, height), config={"max_side": width}), K


@pytest.mark.parametrize("height", [1, 3, 5])
def test_the_loss_scores_images_thinner_than_the_ssim_window(height):
    a, b = torch.rand(height, 16, 3), torch.rand(height, 16, 3)
    loss = photometric_loss(a, b)  # kornia's 11-tap window needs a side > 5: a RuntimeError before
    assert math.isfinite(float(loss)) and float(photometric_loss(a, a)) < 1e-3


def test_align_view_aligns_a_strip_whose_coarse_level_is_thinner_than_the_ssim_window():
    res, K = _strip_fit()  # 64 x 10: the coarse level is 32 x 5
    img = res.render(torch.eye(4), K, 64, 10)
    c2w = res.align_view(img, torch.eye(4), K, steps=4)
    assert c2w.shape == (4, 4) and bool(torch.isfinite(c2w).all())


def test_a_photograph_with_no_pixel_is_refused_by_name():
    res, K = _strip_fit()
    for shape in ((0, 64, 3), (10, 0, 3)):  # min() of an empty tensor: a RuntimeError before
        with pytest.raises(ShapeError, match=r"image expected \[H, W, 3\] with H, W >= 1, got"):
            res.align_view(torch.zeros(shape), torch.eye(4), K, steps=1)


def test_densify_places_each_copy_by_a_sample_of_its_own_rotated_gaussian():
    n = 2000  # long along its own x (sigma 1), thin across; turned 90 degrees about z: long along the world's y
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]).repeat(n, 1)
    params = {"offset": torch.zeros(n, 3), "sh_dc": torch.zeros(n, 3), "opacity": torch.zeros(n),
              "scales": torch.log(torch.tensor([1.0, 1e-3, 1e-3])).repeat(n, 1), "quats": q}
    base, mult, out, _, _ = _densify_prune(torch.zeros(n, 3), torch.ones(n), params, torch.ones(n), torch.ones(n),
                                           0.5, 1.0, torch.Generator().manual_seed(0))
    assert len(base) == 2 * n and len(mult) == 2 * n and out["quats"].shape == (2 * n, 4)
    spread = base[n:].std(0)  # the copies lay along the world's x, off the Gaussian, before
    assert 0.9 < float(spread[1]) < 1.1 and float(spread[0]) < 0.01 and float(spread[2]) < 0.01
