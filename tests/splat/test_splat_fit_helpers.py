"""Fit helpers on hand-made Gaussians (no rendered scene, so no pyrender): the loss, PSNR, working sizes, align_view,
rendering, densification."""

import dataclasses
import math

import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import Gaussians, SplatFit, auto_budget
from pointmap.splat.fit import _densify_prune, _level_size, _resize_image, photometric_loss, psnr
from tests.splat.test_splat_init import _plane_recon


def _strip_fit(width=64, height=10):
    g = Gaussians.from_points(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)) * 0.3
                              + torch.tensor([0, 0, 3.0]), torch.rand(200, 3, generator=torch.Generator()
                                                                       .manual_seed(1)), 0.05)
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
    # long along its own x (sigma 1), thin across; turned 45 degrees about z (a turn that is not its own inverse,
    # so its transpose would put the copies across): long along the world's (1, 1, 0)
    n = 2000
    q = torch.tensor([math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)]).repeat(n, 1)
    params = {"offset": torch.zeros(n, 3), "sh_dc": torch.zeros(n, 3), "opacity": torch.zeros(n),
              "scales": torch.log(torch.tensor([1.0, 1e-3, 1e-3])).repeat(n, 1), "quats": q}
    base, mult, out, _, _ = _densify_prune(torch.zeros(n, 3), torch.ones(n), params, torch.ones(n), torch.ones(n),
                                           0.5, 1.0, torch.Generator().manual_seed(0))
    assert len(base) == 2 * n and len(mult) == 2 * n and out["quats"].shape == (2 * n, 4)
    along, across = torch.tensor([1.0, 1.0, 0.0]) / math.sqrt(2), torch.tensor([1.0, -1.0, 0.0]) / math.sqrt(2)
    copies = base[n:]
    assert 0.9 < float((copies @ along).std()) < 1.1
    assert float((copies @ across).std()) < 0.01 and float(copies[:, 2].std()) < 0.01


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


def test_the_masked_loss_treats_the_filled_in_target_pixels_as_constants_in_its_gradient():
    import kornia

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(24, 32, 3, generator=g), torch.rand(24, 32, 3, generator=g)
    left = torch.zeros(24, 32, dtype=torch.bool)
    left[:, :16] = True
    r = a.clone().requires_grad_(True)
    photometric_loss(r, b, 0.2, left).backward()
    # by hand: the target outside the mask is a constant copy of the render
    r2 = a.clone().requires_grad_(True)
    b_kept = torch.where(left[..., None], b, a)
    ssim_map = kornia.metrics.ssim(r2.permute(2, 0, 1)[None], b_kept.permute(2, 0, 1)[None], 11)[0]
    (0.8 * (r2[:, :16] - b[:, :16]).abs().mean() + 0.2 * (1 - ssim_map[:, :, :16].mean())).backward()
    assert torch.allclose(r.grad, r2.grad, atol=1e-7)


def test_psnr_clamps_the_render_to_the_unit_range_and_is_infinite_for_a_perfect_match():
    ones = torch.ones(4, 5, 3)
    assert psnr(ones * 1.5, ones) == math.inf   # an over-bright render scores as white
    assert psnr(ones * 0.5, ones * 0.5) == math.inf
    assert psnr(ones * 0.5, ones) == pytest.approx(-10 * math.log10(0.25))


def test_a_quarter_size_working_image_averages_its_source_pixels_like_an_area_filter():
    noise = torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(0))
    small = _resize_image(noise, 16, 16)
    # a 4 x 4 box average of uniform noise has a standard deviation of sigma / 4; a 2-tap bilinear sample sigma / 2
    assert float(small.std()) < 0.3 * float(noise.std())
    assert abs(float(small.mean()) - float(noise.mean())) < 0.01


def test_a_working_image_is_resized_when_only_one_of_its_sides_changes():
    # 260 x 30 at a working size of 256: the height rounds back to 30 (30 x 256 / 260 = 29.5)
    img = torch.rand(30, 260, 3, generator=torch.Generator().manual_seed(0))
    assert tuple(_resize_image(img, 256, 30).shape) == (30, 256, 3)
    assert tuple(_resize_image(img[:, :30], 30, 29).shape) == (29, 30, 3)


def test_each_views_share_of_a_working_level_is_rounded_to_the_nearest_pixel():
    recon = dataclasses.replace(_plane_recon(n=2, W=96, H=72), map_sizes=[(96, 72), (67, 72)])
    assert _level_size(recon, 1, (40, 30)) == (28, 30)   # 67 x 40 / 96 = 27.9


def test_the_cpu_budget_caps_the_working_size_and_runs_mostly_at_half_resolution():
    b = auto_budget(3, (512, 384), "cpu")
    assert b["max_side"] == 256 and b["max_gaussians"] == 10_000 and 0 < b["coarse_frac"] < 1
    assert auto_budget(3, (200, 100), "cpu")["max_side"] == 200


def test_align_view_takes_a_uint8_photograph_as_its_value_over_255():
    res, K = _strip_fit(32, 32)
    img = (res.render(torch.eye(4), K, 32, 32) * 255).round().to(torch.uint8)
    off = torch.eye(4)
    off[:3, 3] = torch.tensor([0.03, -0.02, 0.0])
    assert torch.equal(res.align_view(img, off, K, steps=3), res.align_view(img.float() / 255, off, K, steps=3))


def test_align_view_refuses_nan_intrinsics():
    res, K = _strip_fit(32, 32)
    with pytest.raises(ShapeError, match=r"K expected finite \[3, 3\] intrinsics with positive focals"):
        res.align_view(torch.zeros(32, 32, 3), torch.eye(4), torch.full((3, 3), float("nan")), steps=1)


def test_align_view_keeps_its_last_pose_when_that_is_the_best():
    res, K = _strip_fit(32, 32)
    img = res.render(torch.eye(4), K, 32, 32)
    off = torch.eye(4)
    off[:3, 3] = torch.tensor([0.02, 0.0, 0.0])
    # one step, on the coarse level: the only pose it can return besides the start is the last one
    c2w = res.align_view(img, off, K, steps=1, lr_trans=0.01, lr_rot=0.0)
    assert not torch.equal(c2w, off) and abs(float(c2w[0, 3])) < 0.02


def test_align_view_with_a_rotation_rate_of_zero_moves_the_camera_without_turning_it():
    res, K = _strip_fit(32, 32)
    img = res.render(torch.eye(4), K, 32, 32)
    off = torch.eye(4)
    off[:3, 3] = torch.tensor([0.03, -0.02, 0.0])
    c2w = res.align_view(img, off, K, steps=6, lr_rot=0.0, lr_trans=0.01)
    assert torch.allclose(c2w[:3, :3], torch.eye(3), atol=1e-6) and not torch.allclose(c2w[:3, 3], off[:3, 3])


def test_align_view_runs_its_first_half_at_half_the_size_and_scores_poses_at_the_full_size(spy):
    res, K = _strip_fit(32, 32)
    img = res.render(torch.eye(4), K, 32, 32)
    renders = spy("rasterize")
    res.align_view(img, torch.eye(4), K, steps=4)
    assert [tuple(args[7:9]) for args, _, _ in renders] == [(32, 32), (16, 16), (16, 16), (32, 32), (32, 32), (32, 32)]  # start, 4 steps, last


def test_align_view_scales_the_intrinsics_of_each_level_by_its_own_width_and_height_factors(spy):
    res, _ = _strip_fit(32, 32)
    W, H = 45, 31   # the coarse level, 22 x 15, is 0.489 of the width and 0.484 of the height
    K = torch.tensor([[40.0, 0, (W - 1) / 2], [0, 50.0, (H - 1) / 2], [0, 0, 1]])
    renders = spy("rasterize")
    res.align_view(torch.full((H, W, 3), 0.5), torch.eye(4), K, steps=2, max_side=45)
    assert {tuple(args[7:9]) for args, _, _ in renders} == {(22, 15), (45, 31)}
    for args, _, _ in renders:
        Ks, w, h = args[6:9]
        assert Ks[0, 0] == pytest.approx(40.0 * w / W) and Ks[1, 1] == pytest.approx(50.0 * h / H)


def test_a_render_of_gaussians_brighter_than_white_is_clamped_to_the_unit_range():
    res, K = _strip_fit(32, 32)
    g = res.gaussians
    bright = dataclasses.replace(res, gaussians=dataclasses.replace(g, sh_dc=g.sh_dc + 5.0,
                                                                     opacity_logits=g.opacity_logits + 5.0))
    assert float(bright.render(torch.eye(4), K, 32, 32, return_all=True).image.max()) > 1   # what it clamps
    img = bright.render(torch.eye(4), K, 32, 32)
    assert float(img.max()) <= 1 and float(img.min()) >= 0


def test_to_reconstruction_refuses_a_reconstruction_of_another_view_count():
    res, _ = _strip_fit(32, 32)
    with pytest.raises(ShapeError, match="reconstruction has 2 views, the fit 1"):
        res.to_reconstruction(_plane_recon(n=2))


def test_densify_grows_by_the_mean_screen_gradient_over_the_steps_that_saw_each_gaussian():
    params = {"offset": torch.zeros(2, 3), "sh_dc": torch.arange(2.0)[:, None].repeat(1, 3), "opacity": torch.zeros(2),
              "scales": torch.log(torch.full((2, 3), 0.005)), "quats": torch.tensor([1.0, 0, 0, 0]).repeat(2, 1)}
    # 0: 0.8 over 2 steps (a mean of 0.4, below the threshold); 1: 0.8 over 1 step
    _, _, out, _, _ = _densify_prune(torch.zeros(2, 3), torch.ones(2), params, torch.tensor([0.8, 0.8]),
                                     torch.tensor([2.0, 1.0]), 0.5, 1.0, torch.Generator().manual_seed(0))
    assert out["sh_dc"][:, 0].tolist() == [0.0, 1.0, 1.0]   # only 1 is cloned
