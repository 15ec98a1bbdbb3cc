"""The pose heads' prior on the cameras of dense alignment (pointmap.align.head_prior): against a per-edge reference
in plain angles, zero where cameras and heads agree, and in global_align, pulling the cameras toward true heads
when the pointmaps are turned."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, pose_errors, views_of

from pointmap.align import AlignConfig, global_align
from pointmap.align.head_prior import HeadPrior, chord
from pointmap.errors import ShapeError
from pointmap.geometry.rotations import axis_angle_to_matrix, rotation_angle


def _cameras(n, seed):
    g = torch.Generator().manual_seed(seed)
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    c2w[:, :3, :3] = axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=torch.float64))
    c2w[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return c2w


def _edges(n):
    i = torch.tensor([a for a in range(n) for b in range(n) if a != b])
    j = torch.tensor([b for a in range(n) for b in range(n) if a != b])
    return i, j


def _reference(c2w, i, j, T, score, weight, rot_deg, dir_deg):
    """The prior edge by edge, from the angles themselves (acos) and the chord 2 sin(theta / 2)."""
    rho = lambda theta, s_deg: chord(s_deg) ** 2 * math.log1p((2 * math.sin(theta / 2)) ** 2 / chord(s_deg) ** 2)  # noqa: E731
    total, wsum = 0.0, float(score.sum())
    for e in range(len(i)):
        a, b = int(i[e]), int(j[e])
        rel = np.linalg.inv(c2w[a].numpy()) @ c2w[b].numpy()  # camera b -> camera a, as the heads'
        cos = (np.trace(T[e, :3, :3].numpy().T @ rel[:3, :3]) - 1) / 2
        theta = math.acos(max(-1.0, min(1.0, cos)))
        u, v = rel[:3, 3], T[e, :3, 3].numpy()
        phi = math.acos(max(-1.0, min(1.0, float(u @ v / np.linalg.norm(u) / np.linalg.norm(v)))))
        total += float(score[e]) / wsum * (rho(theta, rot_deg) + rho(phi, dir_deg))
    return weight * total


def test_the_prior_equals_a_per_edge_reference_in_plain_angles():
    n = 5
    c2w = _cameras(n, 0)
    i, j = _edges(n)
    noisy = _cameras(len(i), 1)  # heads that disagree with the cameras by large and small amounts
    noisy[:, :3, 3] *= torch.rand(len(i), 1, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) + 0.1
    score = torch.rand(len(i), dtype=torch.float64, generator=torch.Generator().manual_seed(3)) + 0.2
    prior = HeadPrior(i, j, noisy, score, 0.7, 10.0, 20.0, dtype=torch.float64)
    assert float(prior.loss(c2w)) == pytest.approx(_reference(c2w, i, j, noisy, score, 0.7, 10.0, 20.0), rel=1e-9)


def test_the_prior_is_zero_with_zero_gradient_where_cameras_and_heads_agree():
    n = 4
    c2w = _cameras(n, 5)
    i, j = _edges(n)
    T = torch.linalg.inv(c2w[i]) @ c2w[j]
    T[:, :3, 3] *= 0.6  # the heads' baselines come out short: only directions count
    prior = HeadPrior(i, j, T, torch.ones(len(i), dtype=torch.float64), 1.0, 10.0, 20.0, dtype=torch.float64)
    x = c2w.clone().requires_grad_(True)
    loss = prior.loss(x)
    loss.backward()
    assert float(loss.detach()) < 1e-20 and float(x.grad.abs().max()) < 1e-9
    # one camera turned by 5 degrees: the loss is that rotation's share, and it grows with the turn
    turned = c2w.clone()
    turned[0, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, math.radians(5), 0.0], dtype=torch.float64)) @ c2w[0, :3, :3]
    turned2 = c2w.clone()
    turned2[0, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, math.radians(10), 0.0], dtype=torch.float64)) @ c2w[0, :3, :3]
    assert 0 < float(prior.loss(turned)) < float(prior.loss(turned2))


def test_edges_with_unusable_transforms_or_zero_scores_are_left_out():
    n = 3
    c2w = _cameras(n, 7)
    i, j = _edges(n)
    T = torch.linalg.inv(c2w[i]) @ c2w[j]
    T[0, 0, 0] = float("nan")
    T[1, :3, 3] = 0.0  # no direction
    score = torch.ones(len(i), dtype=torch.float64)
    score[2] = 0.0
    prior = HeadPrior(i, j, T, score, 1.0, 10.0, 20.0, dtype=torch.float64)
    assert prior.num_edges == len(i) - 3
    assert math.isfinite(float(prior.loss(c2w)))


def _scene_with_true_heads(pair_rot_deg):
    """Every prediction's view-2 map turned about view 1 by ``pair_rot_deg`` while its head holds the true
    transform (at the prediction's scale)."""
    sc = make_scene(4, 24, 32, seed=0)
    preds = gt_preds(sc, complete_pairs(4), seed=2, pair_rot_deg=pair_rot_deg)
    c2w, pw = sc["cam2world"], sc["pts_world"]
    heads = {}
    for (i, j), p in preds.items():
        w2c = np.linalg.inv(c2w[i])
        own1 = pw[i] @ w2c[:3, :3].T + w2c[:3, 3]
        s = float(p.pts1_cam1.double().norm() / torch.from_numpy(own1).norm())
        T = torch.from_numpy(w2c @ c2w[j])
        T[:3, 3] *= s
        heads[(i, j)] = replace(p, cam2_to_cam1=T[None].float())
    return sc, preds, heads


def test_with_true_heads_and_turned_pointmaps_the_prior_keeps_the_cameras_near_the_heads():
    sc, preds, heads = _scene_with_true_heads(8.0)
    align = lambda ps, **kw: global_align(views_of(sc), ps, config=AlignConfig(quiet=True, niter=150, **kw))  # noqa: E731
    free = align(heads)
    held = align(heads, head_prior=1.0)
    rot_free = pose_errors(free.cam2world.numpy(), sc["cam2world"])[0]
    rot_held = pose_errors(held.cam2world.numpy(), sc["cam2world"])[0]
    assert rot_held < 0.5 * rot_free, (rot_held, rot_free)
    assert held.info["align"]["head_prior_edges"] == 12 and free.info["align"]["head_prior_edges"] == 0
    # pose_head=False (the Procrustes start) and models without a head have no prior
    assert align(heads, head_prior=1.0, pose_head=False).info["align"]["head_prior_edges"] == 0
    assert align(preds, head_prior=1.0).info["align"]["head_prior_edges"] == 0


@pytest.mark.parametrize("bad", [{"head_prior": -0.1}, {"head_prior": float("nan")}, {"head_prior_deg": (10.0,)},
                                 {"head_prior_deg": (0.0, 20.0)}, {"head_prior_deg": (10.0, 180.0)},
                                 {"head_prior_deg": "10,20"}])
def test_a_bad_head_prior_setting_is_refused_with_what_was_expected(bad):
    with pytest.raises(ShapeError, match="head_prior"):
        AlignConfig(**bad)


def test_the_chord_of_an_angle_is_the_residual_of_a_rotation_by_that_angle():
    R = axis_angle_to_matrix(torch.tensor([[0.3, -0.2, 0.5]], dtype=torch.float64))
    theta = float(rotation_angle(R)[0])
    assert float((R[0] - torch.eye(3, dtype=torch.float64)).square().sum() / 2) == pytest.approx(
        chord(math.degrees(theta)) ** 2, rel=1e-12)
