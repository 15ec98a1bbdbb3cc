import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("pyrender")

from pointmap.errors import ShapeError  # noqa: E402
from pointmap.geometry import relative_rotation_error_deg  # noqa: E402
from pointmap.splat import Gaussians, fit, init_from, run  # noqa: E402
from pointmap.splat.fit import psnr  # noqa: E402
from tests.splat.scene import make_benchmark_scene  # noqa: E402


def _pose_err(c2w, gt):
    rot = relative_rotation_error_deg(c2w[:, :3, :3], gt[:, :3, :3])
    trans = (c2w[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1)
    return rot, trans


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    d = make_benchmark_scene(width=96, height=72, n_train=3, n_test=1, seed=1)
    g = init_from(d["recon"], max_gaussians=2500)
    res = fit(d["recon"], g, steps=80, max_side=96, coarse_frac=0.0, progress=False)
    return d, g, res


def test_tiny_fit_reduces_loss_and_pose_error(tiny):
    d, g, res = tiny
    losses = [h["loss"] for h in res.history]
    assert len(losses) == 80
    assert np.mean(losses[-10:]) < 0.8 * np.mean(losses[:10])
    rot0, tr0 = _pose_err(d["recon"].cam2world, d["train_c2w_gt"])
    rot1, tr1 = _pose_err(res.cam2world, d["train_c2w_gt"])
    assert float(rot0[0]) == 0.0 and float(rot1[0]) < 1e-4          # view 0 is anchored
    assert float(rot1[1:].mean()) < 0.7 * float(rot0[1:].mean())
    assert torch.equal(res.cam2world[0], d["recon"].cam2world[0])
    assert isinstance(res.gaussians, Gaussians) and len(res.gaussians) == len(g)
    # render contract
    img = res.render(res.cam2world[1], d["K"], 96, 72)
    assert img.shape == (72, 96, 3) and float(img.min()) >= 0 and float(img.max()) <= 1
    assert psnr(img, d["recon"].images[1]) > 25


def test_align_view_improves_held_out_pose(tiny):
    d, _, res = tiny
    img, init, gt, K = d["test_images"][0], d["test_c2w_init"][0], d["test_c2w_gt"][0], d["K"]
    before = psnr(res.render(init, K, 96, 72), img)
    c2w = res.align_view(img, init, K, steps=40)
    assert c2w.shape == (4, 4)
    after = psnr(res.render(c2w, K, 96, 72), img)
    assert after > before + 2
    rot_b, _ = _pose_err(init[None], gt[None])
    rot_a, _ = _pose_err(c2w[None], gt[None])
    assert float(rot_a) < float(rot_b)
    with pytest.raises(ShapeError, match="image"):
        res.align_view(img[..., :2], init, K)


def test_evaluate_views_scores_held_out_views_after_aligning_their_poses_and_writes_renders(tiny, tmp_path):
    from pointmap.splat import evaluate_views

    d, _, res = tiny
    img, init, K = d["test_images"][0], d["test_c2w_init"][0], d["K"]
    out = evaluate_views(res, [img, img], torch.stack([init, d["test_c2w_gt"][0]]), torch.stack([K, K]), tmp_path,
                         align_steps=40, names=["perturbed", "true"], quiet=True)
    perturbed, true = out["views"]
    assert perturbed["psnr"] > perturbed["psnr_init"] + 2 and 0 < perturbed["ssim"] <= 1
    assert abs(out["psnr"] - (perturbed["psnr"] + true["psnr"]) / 2) < 1e-9
    assert true["psnr_init"] > perturbed["psnr_init"]  # the true pose renders the photograph better
    assert json.loads((tmp_path / "test_views.json").read_text())["views"][0]["name"] == "perturbed"
    assert (tmp_path / "test_000.png").exists() and (tmp_path / "test_001.png").exists()
    kept = evaluate_views(res, [img], init[None], K[None], align_steps=0, quiet=True)["views"][0]
    assert kept["psnr"] == kept["psnr_init"] and np.allclose(kept["cam2world"], init.numpy())
    with pytest.raises(ShapeError, match="finite pose"):
        evaluate_views(res, [img], torch.full((1, 4, 4), float("nan")), K[None], quiet=True)
    with pytest.raises(ShapeError, match=r"cam2world \[M, 4, 4\]"):
        evaluate_views(res, [img, img], init[None], K[None], quiet=True)


def test_refined_reconstruction(tiny):
    d, _, res = tiny
    r2 = res.to_reconstruction(d["recon"])
    assert r2 is not d["recon"] and torch.equal(r2.cam2world, res.cam2world)
    assert torch.equal(r2.depth_z, d["recon"].depth_z) and r2.info.get("splat_refined_poses")
    assert not torch.equal(d["recon"].cam2world, res.cam2world)


def test_fit_validation(tiny):
    d, g, _ = tiny
    with pytest.raises(ShapeError, match="Reconstruction"):
        fit(None, g)
    with pytest.raises(ShapeError, match="Gaussians"):
        fit(d["recon"], "g")
    with pytest.raises(ShapeError, match="steps"):
        fit(d["recon"], g, steps=-1)


def test_run_writes_outputs(tmp_path, tiny):
    d, _, _ = tiny
    out = run(d["recon"], tmp_path, max_gaussians=1500, steps=15, orbit_frames=4, quiet=True)
    p = out["paths"]
    g = Gaussians.load_ply(p["ply"])
    assert len(g) == out["metrics"]["n_gaussians"]
    from PIL import Image

    im = Image.open(tmp_path / "renders" / "train_000.png")
    assert im.size == (2 * 96, 72)
    assert (tmp_path / "renders" / "novel_001.png").exists()
    gif = Image.open(p["orbit"])
    assert gif.n_frames == 4
    cams = json.loads(p["cameras"].read_text())
    assert np.array(cams["cam2world_refined"]).shape == (3, 4, 4)
    assert len(out["metrics"]["train_psnr"]) == 3
    assert out["recon_refined"].cam2world.shape == (3, 4, 4)
    if p["refined"] is not None:
        from pointmap.io import load_npz

        back = load_npz(tmp_path / "refined" / "reconstruction.npz")
        assert torch.allclose(back.cam2world, out["recon_refined"].cam2world)


@pytest.mark.parametrize("kw,message", [
    ({"lr": {"means": -1.0}}, "lr\\['means'\\] expected a finite rate > 0, got -1.0"),
    ({"lr": {"sh_dc": float("nan")}}, "lr\\['sh_dc'\\] expected a finite rate > 0"),
    ({"lr": {"mean": 1.0}}, "lr expected keys among .*unknown \\['mean'\\]"),
    ({"densify": True, "densify_every": 0}, "densify_every expected an int >= 1, got 0"),
    ({"max_side": 0}, "max_side expected an int >= 16"),
    ({"pose_lr": (1e-3,)}, "pose_lr expected \\(rotation, translation\\) rates >= 0"),
    ({"steps": "3"}, "steps expected an int >= 0, got '3'"),
    ({"time_budget": -1}, "time_budget expected seconds > 0"),
    ({"seed": 1.5}, "seed expected an int in \\[0, 2\\*\\*64\\), got 1.5"),
    ({"seed": -1}, "seed expected an int in .*got -1"),
])
def test_fit_refuses_settings_out_of_their_range_before_any_work(tiny, kw, message):
    d, g, _ = tiny
    with pytest.raises(ShapeError, match=message):
        fit(d["recon"], g, progress=False, **kw)


def test_a_fit_refuses_to_render_from_a_nan_pose_or_nan_intrinsics(tiny):
    d, _, res = tiny
    K = res.K[0]
    with pytest.raises(ShapeError, match="expected a finite \\[4, 4\\] cam2world"):
        res.render(torch.full((4, 4), float("nan")), K, 16, 16)
    with pytest.raises(ShapeError, match="K expected finite \\[3, 3\\] intrinsics with positive focals"):
        res.render(res.cam2world[0], torch.full((3, 3), float("nan")), 16, 16)


def test_run_refuses_an_orbit_it_cannot_write_before_it_fits_or_writes_anything(tmp_path, tiny):
    d, _, _ = tiny
    with pytest.raises(ShapeError, match="orbit expected a file name ending in .gif or .mp4"):
        run(d["recon"], tmp_path / "out", steps=2, orbit="orbit.png", quiet=True)
    with pytest.raises(ShapeError, match="orbit_frames expected an int >= 0"):
        run(d["recon"], tmp_path / "out", steps=2, orbit_frames=-1, quiet=True)
    with pytest.raises(ShapeError, match="seed expected an int"):
        run(d["recon"], tmp_path / "out", steps=2, seed="0", quiet=True)
    assert not (tmp_path / "out").exists()


def test_the_masked_photometric_loss_is_the_plain_one_over_the_kept_pixels():
    from pointmap.splat.fit import _ssim, photometric_loss

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(24, 32, 3, generator=g), torch.rand(24, 32, 3, generator=g)
    everything = torch.ones(24, 32, dtype=torch.bool)
    assert torch.allclose(photometric_loss(a, b, 0.2, everything), photometric_loss(a, b, 0.2))
    assert psnr(a, b, everything) == pytest.approx(psnr(a, b))
    left = torch.zeros(24, 32, dtype=torch.bool)
    left[:, :16] = True
    # by hand: the L1 of the kept pixels, and the mean over them of the SSIM map against a target whose other
    # pixels are the render's (so no window sees them)
    import kornia

    b_kept = b.clone()
    b_kept[:, 16:] = a[:, 16:]
    ssim_map = kornia.metrics.ssim(a.permute(2, 0, 1)[None], b_kept.permute(2, 0, 1)[None], 11)[0]
    expected = 0.8 * (a[:, :16] - b[:, :16]).abs().mean() + 0.2 * (1 - ssim_map[:, :, :16].mean())
    assert torch.allclose(photometric_loss(a, b, 0.2, left), expected, atol=1e-6)
    assert torch.allclose(_ssim(a, b_kept, left), ssim_map[:, :, :16].mean())
    painted = b.clone()
    painted[:, 16:] = 0.0  # what the photograph shows outside the mask does not count
    assert torch.equal(photometric_loss(a, painted, 0.2, left), photometric_loss(a, b, 0.2, left))
    mse = float(((a[:, :16] - b[:, :16]) ** 2).mean())
    assert psnr(a, b, left) == pytest.approx(-10 * np.log10(mse))
    # nothing kept: a zero loss that still back-propagates (a view masked out entirely), and no PSNR
    r = a.clone().requires_grad_(True)
    loss = photometric_loss(r, b, 0.2, torch.zeros(24, 32, dtype=torch.bool))
    loss.backward()
    assert float(loss.detach()) == 0.0 and r.grad is not None and np.isnan(psnr(a, b, left & ~left))


def test_a_masked_fit_ignores_what_the_photographs_show_outside_the_masks(tiny):
    import dataclasses

    d, _, _ = tiny
    recon = d["recon"]
    masks = torch.ones(recon.images.shape[:3], dtype=torch.bool)
    masks[1, 20:50, 30:70] = False  # a passer-by in view 1, masked out by the user
    painted = recon.images.clone()
    painted[1, 20:50, 30:70] = torch.tensor([1.0, 0.0, 0.0], dtype=painted.dtype)
    clean = dataclasses.replace(recon, masks=masks)
    walked = dataclasses.replace(recon, masks=masks, images=painted)
    g = init_from(clean, max_gaussians=800)

    def run_fit(r, max_side=96, coarse_frac=0.0, **kw):
        torch.manual_seed(0)
        return fit(r, g, steps=12, max_side=max_side, coarse_frac=coarse_frac, progress=False, **kw)

    # at the maps' resolution, and below it (40 x 30, then 20 x 15: the resized images mix the painted pixels into
    # their neighbours, which the level masks must leave out; nearest-neighbour masks kept some of them)
    for levels in ({}, {"max_side": 40, "coarse_frac": 0.5}):
        a, b = run_fit(clean, **levels), run_fit(walked, **levels)
        assert a.config["masked"] and torch.equal(a.gaussians.sh_dc, b.gaussians.sh_dc)
        assert torch.equal(a.gaussians.means, b.gaussians.means) and torch.equal(a.cam2world, b.cam2world)
    # masked=False fits the painted pixels too: the colours move
    c, e = run_fit(clean, masked=False), run_fit(walked, masked=False)
    assert not c.config["masked"] and not torch.equal(c.gaussians.sh_dc, e.gaussians.sh_dc)
    with pytest.raises(ShapeError, match="masked expected True or False, got 'yes'"):
        fit(recon, g, steps=1, progress=False, masked="yes")


def test_a_view_whose_masks_keep_nothing_is_left_out_of_the_fit_and_scored_null_and_all_masked_is_refused_first(
        tiny, tmp_path):
    import dataclasses

    d, _, _ = tiny
    masks = torch.ones(d["recon"].images.shape[:3], dtype=torch.bool)
    masks[1] = False
    recon = dataclasses.replace(d["recon"], masks=masks)
    with pytest.warns(UserWarning, match=r"keep no pixel of 1 view\(s\), which are left out of the fit"):
        out = run(recon, tmp_path / "one", max_gaussians=600, steps=6, orbit_frames=0, quiet=True)
    assert {h["view"] for h in out["fit"].history} == {0, 2}  # every step on a view with pixels
    assert torch.allclose(out["fit"].cam2world[1], recon.cam2world[1].float(), atol=1e-5)  # its pose as given
    text = (tmp_path / "one" / "splat_metrics.json").read_text()
    psnrs = json.loads(text)["train_psnr"]  # strict JSON: no bare NaN
    assert "NaN" not in text and psnrs[1] is None and all(math.isfinite(p) for p in (psnrs[0], psnrs[2]))
    with pytest.raises(ShapeError, match=r"masks \(recon.masks\) keep none of its pixels"):
        run(dataclasses.replace(recon, masks=torch.zeros_like(masks)), tmp_path / "none", quiet=True)
    assert not (tmp_path / "none").exists()  # refused before the output folder is made


def test_the_canvas_padding_of_views_of_several_sizes_is_neither_a_gaussian_nor_fitted(tiny):
    import dataclasses

    d, _, _ = tiny
    recon = d["recon"]  # 96 x 72 maps; views 1 and 2 made smaller, as a portrait and a wide photograph would be
    sizes = [(96, 72), (60, 72), (96, 40)]
    pad = ~dataclasses.replace(recon, map_sizes=sizes).regions

    def padded_with(colour, depth, conf):
        images, depth_z, c = recon.images.clone(), recon.depth_z.clone(), recon.conf.clone()
        images[pad] = torch.tensor(colour, dtype=images.dtype)
        depth_z[pad], c[pad] = depth, conf
        return dataclasses.replace(recon, images=images, depth_z=depth_z, conf=c, map_sizes=sizes)

    red, green = padded_with([1.0, 0.0, 0.0], 5.0, 9.0), padded_with([0.0, 1.0, 0.0], 0.0, 0.0)
    g_red, g_green = init_from(red, max_gaussians=800), init_from(green, max_gaussians=800)
    assert torch.equal(g_red.means, g_green.means) and torch.equal(g_red.sh_dc, g_green.sh_dc)

    def run_fit(r, **kw):
        torch.manual_seed(0)
        return fit(r, g_green, steps=12, progress=False, **{"max_side": 96, "coarse_frac": 0.0, **kw})

    # the padding is out of the loss whether or not the user's masks are used, and at working sizes below the
    # maps' (48: each view's own pixels are resized on their own, so no filter blends the padding into its edge)
    for kw in ({"masked": True}, {"masked": False}, {"max_side": 48, "coarse_frac": 0.5}):
        a, b = run_fit(red, **kw), run_fit(green, **kw)
        assert torch.equal(a.gaussians.sh_dc, b.gaussians.sh_dc) and torch.equal(a.gaussians.means, b.gaussians.means)
        assert torch.equal(a.cam2world, b.cam2world)
    # each view is rendered at its own share of the working size (its top-left), never at the canvas's
    a = run_fit(green, max_side=48, coarse_frac=0.0)
    assert {v: {h["size"] for h in a.history if h["view"] == v} for v in range(3)} == \
        {0: {(48, 36)}, 1: {(30, 36)}, 2: {(48, 20)}}
    # the same views filling the canvas: the painted pixels are fitted, and the colours move
    c = run_fit(dataclasses.replace(red, map_sizes=None))
    assert {h["size"] for h in c.history} == {(96, 72)}
    assert not torch.equal(c.gaussians.sh_dc, run_fit(dataclasses.replace(green, map_sizes=None)).gaussians.sh_dc)


def test_each_views_intrinsics_at_a_working_level_are_scaled_as_its_own_image_was(tiny, fit_module):
    """A view narrower than the canvas is resized to its rounded share of the level: 61 px at 40/96 becomes 25 px
    (x 0.410), not x 0.417 (the canvas's factor, which its intrinsics were scaled by: half a level pixel off at the
    view's right edge)."""
    import dataclasses

    from pointmap.geometry.cameras import project

    d, _, _ = tiny
    recon = dataclasses.replace(d["recon"], map_sizes=[(96, 72), (61, 72), (96, 41)])
    lv = (40, 30)
    Ks = fit_module._level_K(recon, recon.K_map.double(), lv)
    for i, (vw, vh) in enumerate(recon.map_sizes):
        img = fit_module._level_view(recon, recon.images, i, lv, fit_module._resize_image)
        lh, lw = img.shape[:2]
        # the view's bottom-right corner (its last pixel's far edge, at a depth of 1) lands on the image's
        corner = torch.linalg.solve(recon.K_map[i].double(), torch.tensor([vw - 0.5, vh - 0.5, 1.0],
                                                                          dtype=torch.float64))
        uv = project(corner[None], Ks[i])[0][0]
        assert torch.allclose(uv, torch.tensor([lw - 0.5, lh - 0.5], dtype=torch.float64), atol=1e-9), (i, uv, lw, lh)
    assert fit_module._level_view(recon, recon.images, 1, lv, fit_module._resize_image).shape[1] == 25


def test_a_fit_renders_aligns_and_evaluates_from_rigid_poses_only(tiny):
    from pointmap.splat import evaluate_views

    d, _, res = tiny
    K, img = d["K"], d["test_images"][0]
    scaled, no_last_row, mirror = torch.eye(4), torch.eye(4), torch.eye(4)
    scaled[:3, :3] *= 2.0            # a similarity: rendered as if the camera had moved
    no_last_row[3, 3] = 0.0
    mirror[2, 2] = -1.0              # det -1: rendered blank
    for T in (scaled, no_last_row, mirror):
        with pytest.raises(ShapeError, match=r"cam2world expected a finite \[4, 4\] cam2world, rigid \[R t; 0 0 0 1\]"):
            res.render(T, K, 96, 72)
        with pytest.raises(ShapeError, match=r"cam2world_init expected a finite \[4, 4\] cam2world, rigid"):
            res.align_view(img, T, K, steps=1)
        with pytest.raises(ShapeError, match=r"evaluate_views: cam2world expected rigid \[R t; 0 0 0 1\] .*"
                                             r"got cam2world\[1\] = "):
            evaluate_views(res, [img, img], torch.stack([d["test_c2w_gt"][0], T]), torch.stack([K, K]), quiet=True)
    # a rigid pose renders the photograph
    assert psnr(res.render(d["test_c2w_gt"][0], K, 96, 72), img) > 20


def test_align_view_and_evaluate_views_refuse_a_photograph_with_nan_pixels(tiny):
    from pointmap.splat import evaluate_views

    d, _, res = tiny
    img, init, K = d["test_images"][0].clone(), d["test_c2w_init"][0], d["K"]
    img[3, 4, 1] = float("nan")      # passed the [0, 1] range check: min and max are NaN-blind
    with pytest.raises(ShapeError, match=r"image values expected finite, in \[0, 1\] .*got 1 pixels with NaN"):
        res.align_view(img, init, K, steps=1)
    with pytest.raises(ShapeError, match="test image 0 values expected finite"):
        evaluate_views(res, [img], init[None], K[None], align_steps=0, quiet=True)  # scored NaN


def test_evaluate_views_checks_every_image_and_name_before_it_aligns_or_writes_anything(tiny, tmp_path):
    from pointmap.splat import evaluate_views

    d, _, res = tiny
    good, init, K = d["test_images"][0], d["test_c2w_init"][0], d["K"]
    two = (torch.stack([init, init]), torch.stack([K, K]))
    with pytest.raises(ShapeError, match="test image 1 values expected"):
        evaluate_views(res, [good, good * 255], *two, tmp_path / "out", quiet=True)  # 0-255 floats
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    with pytest.raises(ShapeError, match=r"names expected 2 strings \(one per test image\), got \['a'\]"):
        evaluate_views(res, [good, good], *two, names=["a"], quiet=True)
    with pytest.raises(ShapeError, match="expected a fit .*got Gaussians"):
        evaluate_views(res.gaussians, [good], init[None], K[None], quiet=True)


def test_align_view_and_evaluate_views_refuse_step_counts_out_of_their_range(tiny):
    from pointmap.splat import evaluate_views

    d, _, res = tiny
    img, init, K = d["test_images"][0], d["test_c2w_init"][0], d["K"]
    for kw, message in [({"steps": 2.5}, "steps expected an int >= 0, got 2.5"),  # TypeErrors before
                        ({"steps": "3"}, "steps expected an int >= 0, got '3'"),
                        ({"max_side": 8}, "max_side expected an int >= 16"),
                        ({"lr_rot": float("nan")}, "lr_rot expected a finite rate >= 0, got nan"),
                        ({"lr_trans": -1.0}, "lr_trans expected a finite rate >= 0 .*got -1.0")]:
        with pytest.raises(ShapeError, match="align_view: " + message):
            res.align_view(img, init, K, **kw)
    with pytest.raises(ShapeError, match="align_steps expected an int >= 0 .*got -5"):  # was accepted, as 0
        evaluate_views(res, [img], init[None], K[None], align_steps=-5, quiet=True)
    assert torch.allclose(res.align_view(img, init, K, steps=0), init, atol=1e-6)


@pytest.mark.parametrize("background", [[2.0, 2.0, 2.0], [0.5, 0.5], [0.0, float("nan"), 0.0], "white"])
def test_fit_and_render_refuse_a_background_that_is_no_colour(tiny, background):
    d, g, res = tiny
    with pytest.raises(ShapeError, match=r"fit: background expected an RGB colour \[3\] in \[0, 1\]"):
        fit(d["recon"], g, steps=1, progress=False, background=background)
    with pytest.raises(ShapeError, match=r"background expected an RGB colour \[3\] in \[0, 1\]"):
        res.render(res.cam2world[0], d["K"], 16, 12, background=background)


def test_a_fit_that_diverges_stops_naming_the_step_instead_of_returning_nan_gaussians():
    from tests.splat.test_splat_init import _plane_recon

    recon = _plane_recon()
    g = init_from(recon, max_gaussians=300)
    # a log-scale rate of 200 takes the scales to inf in one step: the fit went on, returned NaN Gaussians and
    # save_ply wrote a file load_ply refuses
    with pytest.raises(ShapeError, match=r"fit: the step left the Gaussians or the poses NaN or inf at step 0 "
                                         r"\(view view_00\d.png; the last finite loss was 0\.\d+\): the "
                                         r"optimisation diverged"):
        fit(recon, g, steps=6, progress=False, lr={"scales": 200.0}, coarse_frac=0.0)
    ok = fit(recon, g, steps=6, progress=False, coarse_frac=0.0)
    assert len(ok.history) == 6 and bool(torch.isfinite(ok.gaussians.means).all())
