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


def test_align_view_never_returns_a_pose_that_matches_the_photograph_worse_than_its_start():
    res, K = _strip_fit(width=32, height=32)
    img = res.render(torch.eye(4), K, 32, 32)

    def loss(c2w):
        return float(photometric_loss(res.render(c2w, K, 32, 32), img))

    # from the true pose, with rates that throw it far off: the start is the best pose it ever visits
    c2w = res.align_view(img, torch.eye(4), K, steps=6, lr_rot=0.5, lr_trans=0.5)
    assert torch.allclose(c2w, torch.eye(4), atol=1e-5)
    off = torch.eye(4)
    off[:3, 3] = torch.tensor([0.05, -0.03, 0.0])
    c2w = res.align_view(img, off, K, steps=6, lr_rot=0.5, lr_trans=0.5)
    assert loss(c2w) <= loss(off) + 1e-6


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


def test_densify_clones_small_gaussians_and_splits_large_ones_into_two_at_scales_over_one_point_six():
    # four Gaussians, extent 1: 0 small and steep, 1 large and steep, 2 large and flat, 3 steep but transparent
    scales = torch.log(torch.tensor([[0.005] * 3, [0.5, 0.02, 0.02], [0.5] * 3, [0.005] * 3]))
    params = {"offset": torch.zeros(4, 3), "sh_dc": torch.arange(4.0)[:, None].repeat(1, 3),
              "opacity": torch.tensor([0.0, 0.0, 0.0, -9.0]), "scales": scales,
              "quats": torch.tensor([1.0, 0, 0, 0]).repeat(4, 1)}
    grads = torch.tensor([1.0, 1.0, 0.0, 1.0])
    base, mult, out, acc, cnt = _densify_prune(torch.arange(12.0).view(4, 3), torch.ones(4), params, grads,
                                               torch.ones(4), 0.5, 1.0, torch.Generator().manual_seed(0))
    ids = out["sh_dc"][:, 0].tolist()  # which parent each Gaussian comes from
    assert ids == [0, 2, 0, 1, 1]  # kept (0, 2; 1 replaced, 3 pruned), then 0's clone, then 1's two halves
    assert torch.equal(out["scales"][:3], scales[[0, 2, 0]])  # a clone keeps its parent's size
    assert torch.allclose(out["scales"][3:], scales[[1, 1]] - math.log(1.6))
    assert torch.equal(base[:2], torch.arange(12.0).view(4, 3)[[0, 2]])  # the kept ones stay where they were
    halves = base[3:] - torch.tensor([3.0, 4.0, 5.0])  # a sample of the parent: along its long axis, x
    assert bool((halves[:, 1:].abs() < 0.1).all()) and bool((halves[:, 0].abs() > 1e-4).all())
    assert len(mult) == len(acc) == len(cnt) == 5 and all(v.requires_grad for v in out.values())
    assert not bool(out["offset"].any())
