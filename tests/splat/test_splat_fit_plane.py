"""``fit`` on a flat plane seen by two or three cameras (no rendered scene, so no pyrender): its working sizes and
coarse-to-fine schedule, option checks, masks, pose updates and rates, and densification inside the run, read
through spies on its internals (the ``spy`` fixture of tests/splat/conftest.py)."""

import dataclasses

import pytest
import torch

from pointmap.errors import ShapeError
from pointmap.splat import Gaussians, fit, init_from
from pointmap.splat.fit import photometric_loss
from tests.splat.test_splat_init import _plane_recon


def _plane(n=2, **kw):
    recon = _plane_recon(n=n, **kw)
    return recon, init_from(recon, max_gaussians=300)


def test_a_fit_never_works_above_the_maps_resolution():
    recon, g = _plane()
    res = fit(recon, g, steps=2, max_side=512, coarse_frac=0.0, progress=False)
    assert {h["size"] for h in res.history} == {(32, 24)} and res.config["levels"] == [(32, 24)]


def test_the_coarse_steps_are_the_first_coarse_frac_of_the_run_at_half_the_working_size():
    recon, g = _plane(W=64, H=48)
    res = fit(recon, g, steps=10, max_side=64, coarse_frac=0.3, progress=False)
    assert [h["size"] for h in res.history] == [(32, 24)] * 3 + [(64, 48)] * 7


@pytest.mark.parametrize("kw,message", [
    ({"max_side": 8}, "max_side expected an int >= 16"),
    ({"coarse_frac": 1.0}, r"coarse_frac expected a fraction in \[0, 1\)"),
    ({"lr": {"opacity": 0.0}}, r"lr\['opacity'\] expected a finite rate > 0, got 0.0"),
    ({"ssim_weight": 1.5}, r"ssim_weight expected a weight in \[0, 1\], got 1.5"),
    ({"ssim_weight": float("nan")}, r"ssim_weight expected a weight in \[0, 1\]"),
    ({"densify_grad": 0.0}, "densify_grad expected a finite threshold > 0, got 0.0"),
])
def test_fit_refuses_settings_at_the_edge_of_their_range(kw, message):
    recon, g = _plane()
    with pytest.raises(ShapeError, match=message):
        fit(recon, g, progress=False, **kw)


def test_a_fit_of_zero_steps_returns_the_gaussians_and_poses_as_given():
    recon, g = _plane()
    res = fit(recon, g, steps=0, progress=False)
    assert res.history == [] and torch.equal(res.gaussians.means, g.means)
    assert torch.allclose(res.cam2world, recon.cam2world, atol=1e-6)


def test_fit_refuses_no_gaussians_by_name():
    recon, g = _plane()
    empty = Gaussians(means=g.means[:0], quats=g.quats[:0], log_scales=g.log_scales[:0],
                      opacity_logits=g.opacity_logits[:0], sh_dc=g.sh_dc[:0])
    with pytest.raises(ShapeError, match="fit needs at least one Gaussian"):
        fit(recon, empty, steps=1, progress=False)


def test_a_fit_whose_masks_keep_every_pixel_is_the_unmasked_fit():
    recon, g = _plane()
    full = dataclasses.replace(recon, masks=torch.ones(2, 24, 32, dtype=torch.bool))
    res = fit(full, g, steps=3, coarse_frac=0.0, progress=False)
    plain = fit(recon, g, steps=3, coarse_frac=0.0, progress=False)
    assert res.config["masked"] is False and torch.equal(res.gaussians.sh_dc, plain.gaussians.sh_dc)


def test_a_view_whose_mask_keeps_pixels_only_at_the_working_size_is_still_fitted(fit_module):
    recon = _plane_recon(n=2, W=64, H=48)
    masks = torch.ones(2, 48, 64, dtype=torch.bool)
    masks[1] = False
    masks[1, 10:40, 30:32] = True   # a strip 2 pixels wide: none of it survives the half-size filter
    recon = dataclasses.replace(recon, masks=masks)
    g = init_from(recon, max_gaussians=300)
    assert not bool(fit_module._level_view(recon, recon.masks, 1, (32, 24), fit_module._resize_mask).any())
    res = fit(recon, g, steps=12, max_side=64, coarse_frac=0.5, progress=False)
    assert 1 in {h["view"] for h in res.history[6:]}


def test_a_fit_without_pose_optimisation_keeps_every_pose():
    recon, g = _plane(n=3)
    res = fit(recon, g, steps=6, optimize_poses=False, coarse_frac=0.0, progress=False)
    assert torch.allclose(res.cam2world, recon.cam2world, atol=1e-6)
    moved = fit(recon, g, steps=6, coarse_frac=0.0, progress=False, pose_lr=(1e-2, 1e-2))
    assert not torch.allclose(moved.cam2world[1:], recon.cam2world[1:], atol=1e-4)


def test_the_anchored_first_view_renders_from_its_given_pose_throughout_the_fit():
    # only view 0 is fitted: with its pose anchored, optimising the poses changes nothing
    recon = _plane_recon(n=2)
    masks = torch.ones(2, 24, 32, dtype=torch.bool)
    masks[1] = False
    recon = dataclasses.replace(recon, masks=masks)
    g = init_from(recon, max_gaussians=300)
    with pytest.warns(UserWarning, match="keep no pixel of 1 view"):
        a = fit(recon, g, steps=8, coarse_frac=0.0, progress=False, pose_lr=(1e-2, 1e-2))
    with pytest.warns(UserWarning, match="keep no pixel of 1 view"):
        b = fit(recon, g, steps=8, coarse_frac=0.0, progress=False, optimize_poses=False)
    assert torch.equal(a.gaussians.means, b.gaussians.means) and torch.equal(a.gaussians.sh_dc, b.gaussians.sh_dc)


def test_the_fit_renders_the_first_view_from_its_given_pose_and_turns_the_others_about_their_centres(spy):
    # a translation rate of 0: each pose update is a turn of the camera about its own centre
    recon = _plane_recon(n=3)
    g = init_from(recon, max_gaussians=300)
    renders = spy("rasterize")
    res = fit(recon, g, steps=12, coarse_frac=0.0, progress=False, pose_lr=(1e-2, 0.0))
    w2c_init = torch.linalg.inv(recon.cam2world.double())
    turned = 0
    for h, (args, _, _) in zip(res.history, renders, strict=True):
        w2c = args[5]
        i = h["view"]
        if i == 0:
            assert torch.allclose(w2c.double(), w2c_init[0], atol=1e-6)   # anchored
        centre = -w2c[:3, :3].double().T @ w2c[:3, 3].double()
        assert torch.allclose(centre, recon.cam2world[i, :3, 3].double(), atol=1e-5)
        turned += not torch.allclose(w2c.double(), w2c_init[i], atol=1e-6)
    assert turned > 0


def test_the_first_step_moves_each_point_by_the_position_rate_times_the_extent_and_its_confidence_multiplier():
    recon = _plane_recon(n=1)   # one camera: no spread, so the extent is 5 % of the depth scale
    g = init_from(recon, max_gaussians=300)
    conf = torch.linspace(-3, 3, len(g))
    g = dataclasses.replace(g, conf=conf)
    res = fit(recon, g, steps=1, coarse_frac=0.0, progress=False)
    extent = res.config["extent"]
    assert extent == pytest.approx(0.05 * res.config["depth_scale"]) and extent > 0
    step = (res.gaussians.means - g.means).abs().amax(dim=1)   # Adam's first step: the rate, on each coordinate
    mult = 1 + 99 * (1 - torch.sigmoid(conf))                   # less confident points move faster
    moved = step > 0
    assert int(moved.sum()) > len(g) // 2
    assert torch.allclose(step[moved], 1.6e-4 * extent * mult[moved], rtol=5e-3)


def _spy_pose_steps(monkeypatch):
    steps = []
    real = torch.optim.Adam

    class Spy(real):
        def step(self, *a, **k):
            if len(self.param_groups) == 2:   # the pose optimiser: [phi], [rho]
                steps.append(([grp["lr"] for grp in self.param_groups],
                              [None if grp["params"][0].grad is None else grp["params"][0].grad.clone()
                               for grp in self.param_groups]))
            return super().step(*a, **k)

    monkeypatch.setattr(torch.optim, "Adam", Spy)
    return steps


def test_the_pose_rates_decay_tenfold_over_the_run_and_each_step_moves_only_the_rendered_view(monkeypatch):
    recon = _plane_recon(n=3)
    g = init_from(recon, max_gaussians=300)
    pose_steps = _spy_pose_steps(monkeypatch)
    res = fit(recon, g, steps=10, coarse_frac=0.0, progress=False, pose_lr=(1e-3, 3e-4))
    assert len(pose_steps) == 10
    depth_scale = res.config["depth_scale"]
    for it, ((lr_rot, lr_trans), grads) in enumerate(pose_steps):
        assert lr_rot == pytest.approx(1e-3 * 0.1 ** (it / 10)) and lr_trans == pytest.approx(3e-4 * depth_scale
                                                                                             * 0.1 ** (it / 10))
        i = res.history[it]["view"]
        others = [j for j in range(3) if j != i]
        assert all(not bool(grad[others].any()) for grad in grads), it   # no gradient left from an earlier step


def test_a_loss_that_is_not_finite_stops_the_fit_naming_the_step(monkeypatch, fit_module):
    recon, g = _plane()
    calls = []

    def nan_at_the_second(render, *a, **k):
        calls.append(1)
        loss = photometric_loss(render, *a, **k)
        return loss * float("nan") if len(calls) == 2 else loss

    monkeypatch.setattr(fit_module, "photometric_loss", nan_at_the_second)
    with pytest.raises(ShapeError, match=r"fit: the loss is NaN or inf at step 1 \(view .*; the last finite loss"):
        fit(recon, g, steps=4, coarse_frac=0.0, progress=False)


def test_a_densifying_fit_grows_the_gaussians_and_keeps_optimising_the_new_set(spy):
    recon, g = _plane()
    seen = spy("_densify_prune", keep=lambda out: {key: v.detach().clone() for key, v in out[2].items()})
    res = fit(recon, g, steps=10, densify=True, densify_every=5, densify_grad=1e-12, coarse_frac=0.0,
              progress=False)
    assert len(seen) == 1 and len(res.gaussians) > len(g)  # at step 4 (inside 10 % - 80 % of the run) only
    grown = seen[0][2]
    assert len(res.gaussians) == len(grown["sh_dc"])
    assert not torch.equal(res.gaussians.sh_dc, grown["sh_dc"])  # the 5 steps after it moved the colours


def test_densify_averages_each_gaussians_screen_gradient_in_ndc_units_over_the_steps_that_saw_it(spy):
    recon = _plane_recon(n=2, W=32, H=24)   # non-square
    recon.cam2world[1, 2, 3] = 4.0          # camera 1 beyond the plane z = 3: view 0's points are behind it
    g = init_from(recon, max_gaussians=400)
    renders, densified = spy("rasterize"), spy("_densify_prune")
    fit(recon, g, steps=10, densify=True, densify_every=5, coarse_frac=0.0, progress=False)
    acc, cnt = torch.zeros(len(g)), torch.zeros(len(g))
    for _, _, out in renders[:5]:   # steps 0-4: the densification at step 4
        vis = out.radii > 0
        h, w = out.image.shape[:2]
        acc[vis] += (out.means2d.grad * torch.tensor([w / 2, h / 2])).norm(dim=-1)[vis]
        cnt[vis] += 1
    assert len(densified) == 1 and 0 < int((cnt < 5).sum()) < len(g)   # some Gaussians were out of some views
    grad_acc, grad_cnt = densified[0][0][3:5]
    assert torch.equal(grad_cnt, cnt) and torch.allclose(grad_acc, acc, rtol=1e-6, atol=1e-12)
