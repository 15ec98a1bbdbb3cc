import math

import pytest
import torch

from pointmap import Reconstruction
from pointmap.errors import ShapeError
from pointmap.splat import init_from


def _plane_recon(n=2, W=32, H=24, shift=0.2, conf=None):
    """Views of the plane z = 3 from cameras translated along x (all poses exact)."""
    f = 30.0
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.arange(n) * shift
    depth = torch.full((n, H, W), 3.0)
    img = torch.rand(n, H, W, 3, generator=torch.Generator().manual_seed(0))
    conf = torch.ones(n, H, W) * 2 if conf is None else conf
    return Reconstruction(images=img, cam2world=c2w, K=K.expand(n, 3, 3).clone(), depth_z=depth, conf=conf)


def test_covisibility_drops_points_explained_by_earlier_views():
    recon = _plane_recon()
    g_all = init_from(recon, max_gaussians=None, covisibility=False)
    g = init_from(recon, max_gaussians=None)
    assert len(g_all) == 2 * 32 * 24
    # the second camera is shifted by 0.2 at depth 3 with f=30: 2 pixel columns are new
    assert 32 * 24 + 2 * 24 <= len(g) <= 32 * 24 + 4 * 24
    assert torch.allclose(g.means[:, 2], torch.full((len(g),), 3.0), atol=1e-5)


def test_views_go_by_confidence_pixels_below_min_conf_are_dropped_and_the_budget_and_attributes_hold():
    conf = torch.ones(2, 24, 32) * 2
    conf[1] = 5.0                     # view 1 is more confident: it goes first and keeps all pixels
    conf[0, :, :16] = 0.5             # below the threshold
    recon = _plane_recon(conf=conf)
    g = init_from(recon, max_gaussians=None, min_conf=1.0)
    assert g.info["view_order"] == [1, 0]
    # view 0's confident right half is all seen by view 1; the 2 new columns it adds without a threshold lie in its
    # left half, below the threshold: only view 1's pixels survive
    assert g.info["points_valid"] == 32 * 24 + 16 * 24
    assert len(g) == 32 * 24
    assert len(init_from(recon, max_gaussians=None, min_conf=0.0)) == 32 * 24 + 2 * 24
    g2 = init_from(recon, max_gaussians=300)
    assert 0 < len(g2) <= 300
    g3 = init_from(recon, max_gaussians=300, downsample="conf")
    assert len(g3) == 300
    assert torch.allclose(g2.opacities, torch.full((len(g2),), 0.1))
    assert torch.equal(g2.quats[:, 0], torch.ones(len(g2)))
    s = g2.scales
    assert bool((s > 0).all()) and torch.allclose(s[:, 0], s[:, 1])
    # spacing of ~300 points on the visible plane patch (about 3.3 x 2.5 units)
    assert 0.05 < float(s[:, 0].median()) < 0.5
    assert g2.conf is not None and len(g2.conf) == len(g2)


def test_each_gaussian_takes_the_colour_of_its_pixel():
    recon = _plane_recon(n=1)
    g = init_from(recon, max_gaussians=None)
    # pixel (u, v) unprojects to x = (u - cx) * 3 / f; recover u, v and compare colours
    u = torch.round(g.means[:, 0] * 30 / 3 + 15.5).long()
    v = torch.round(g.means[:, 1] * 30 / 3 + 11.5).long()
    assert torch.allclose(g.colors, recon.images[0][v, u], atol=1e-5)
    assert not math.isnan(float(g.sh_dc.sum()))


def test_a_foreign_input_an_empty_selection_and_bad_options_are_refused():
    recon = _plane_recon()
    with pytest.raises(ShapeError, match="Reconstruction"):
        init_from("not a recon")
    with pytest.raises(ShapeError, match="no pixel of the reconstruction has depth > 0 and confidence > 100.0"):
        init_from(recon, min_conf=100.0)
    recon.masks = torch.zeros(recon.depth_z.shape, dtype=torch.bool)  # a confidence filter that kept nothing
    with pytest.raises(ShapeError, match=r"masks \(recon.masks\) keep none of its pixels with depth"):
        init_from(recon)
    with pytest.raises(ShapeError, match="downsample"):
        init_from(recon, downsample="grid")
    recon.masks = None
    for bad in ("0.5", 1.0, float("nan")):
        with pytest.raises(ShapeError, match="opacity must be a number in \\(0, 1\\)"):
            init_from(recon, opacity=bad)


def test_splat_tests_run_single_threaded():
    assert torch.get_num_threads() == 1


def test_init_refuses_a_fractional_budget_and_a_seed_neither_generator_takes():
    recon = _plane_recon()
    for kw, message in [({"max_gaussians": 2.5}, "max_gaussians expected an int >= 1 or None, got 2.5"),
                        ({"max_gaussians": 0}, "got 0"), ({"seed": -3}, "seed expected an int in .*got -3"),
                        ({"seed": 0.5}, "seed expected an int")]:
        with pytest.raises(ShapeError, match=message):
            init_from(recon, **kw)
    # the same seed, the same subset; another seed, another (the confidence-weighted draw)
    a, b = init_from(recon, max_gaussians=100, seed=3), init_from(recon, max_gaussians=100, seed=3)
    assert torch.equal(a.means, b.means) and 0 < len(a) <= 100
    c, d = (init_from(recon, max_gaussians=100, downsample="conf", seed=s) for s in (3, 4))
    assert len(c) == len(d) == 100 and not torch.equal(c.means, d.means)


def test_voxel_downsampling_keeps_to_the_budget_down_to_a_single_gaussian():
    recon = _plane_recon()  # float32 points divided by their own extent put the far corner in a second voxel
    for m in (1, 2, 3, 5, 40):
        g = init_from(recon, max_gaussians=m)
        assert 1 <= len(g) <= m, (m, len(g))
    assert len(init_from(recon, max_gaussians=1)) == 1  # was 2


def test_init_refuses_a_min_conf_or_covis_tol_it_cannot_use():
    recon = _plane_recon()
    for kw, message in [({"min_conf": "1"}, "min_conf expected a finite confidence, got '1'"),  # a TypeError
                        ({"min_conf": float("nan")}, "min_conf expected a finite confidence, got nan"),
                        ({"covis_tol": -1.0}, "covis_tol expected a finite relative depth tolerance > 0, got -1.0"),
                        ({"covis_tol": 0}, "covis_tol expected .* got 0"), ({"covis_tol": "0.01"}, "got '0.01'")]:
        with pytest.raises(ShapeError, match=message):
            init_from(recon, max_gaussians=None, **kw)
    # a negative tolerance kept every point of both views: no pixel pruned (1536); 1% prunes the shared ones
    assert len(init_from(recon, max_gaussians=None, covis_tol=0.01)) < 2 * 32 * 24
