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
    """The prior edge by edge, from the angles themselves (acos) and the chord 2 sin(theta / 2) (without the
    baseline floor: the tests that compare give the prior a negligible one, or baselines far above it)."""
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
    prior = HeadPrior(i, j, noisy, score, 0.7, 10.0, 20.0, dtype=torch.float64, baseline_floor=1e-9)
    assert float(prior.loss(c2w)) == pytest.approx(_reference(c2w, i, j, noisy, score, 0.7, 10.0, 20.0), rel=1e-9)


def test_the_prior_is_zero_with_zero_gradient_where_cameras_and_heads_agree():
    n = 4
    c2w = _cameras(n, 5)
    i, j = _edges(n)
    T = torch.linalg.inv(c2w[i]) @ c2w[j]
    T[:, :3, 3] *= 0.6  # the heads' baselines come out short: only directions count
    prior = HeadPrior(i, j, T, torch.ones(len(i), dtype=torch.float64), 1.0, 10.0, 20.0, dtype=torch.float64,
                      baseline_floor=1e-9)
    x = c2w.clone().requires_grad_(True)
    loss = prior.loss(x)
    loss.backward()
    assert float(loss.detach()) < 1e-20 and float(x.grad.abs().max()) < 1e-9
    # one camera turned by 5 degrees: the loss is that rotation's share (and the directions it turns), and it grows
    # with the turn
    turned = c2w.clone()
    turned[0, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, math.radians(5), 0.0], dtype=torch.float64)) @ c2w[0, :3, :3]
    turned2 = c2w.clone()
    turned2[0, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, math.radians(10), 0.0], dtype=torch.float64)) @ c2w[0, :3, :3]
    assert 0 < float(prior.loss(turned)) < float(prior.loss(turned2))
    assert float(prior.loss(turned)) == pytest.approx(_reference(turned, i, j, T, torch.ones(len(i)), 1.0, 10.0, 20.0),
                                                      rel=1e-6)


def test_edges_with_unusable_transforms_zero_scores_or_two_known_cameras_are_left_out():
    n = 4
    c2w = _cameras(n, 7)
    i, j = _edges(n)
    T = _cameras(len(i), 8)  # heads that disagree with the cameras
    T[1, 0, 0] = float("nan")  # edge (0, 2)
    T[2, :3, 3] = 0.0  # (0, 3): no direction
    score = torch.rand(len(i), dtype=torch.float64, generator=torch.Generator().manual_seed(9)) + 0.2
    score[4] = 0.0  # (1, 2)
    pose_free = torch.tensor([False, False, True, True])  # cameras 0 and 1 known: edges (0, 1), (1, 0) cannot move
    prior = HeadPrior(i, j, T, score, 1.0, 10.0, 20.0, dtype=torch.float64, pose_free=pose_free, baseline_floor=1e-9)
    keep = torch.ones(len(i), dtype=torch.bool)
    keep[[1, 2, 4]] = False
    keep &= pose_free[i] | pose_free[j]
    assert prior.num_edges == int(keep.sum()) == len(i) - 5
    assert float(prior.loss(c2w)) == pytest.approx(_reference(c2w, i[keep], j[keep], T[keep], score[keep], 1.0, 10.0,
                                                              20.0), rel=1e-9)


def test_a_baseline_far_below_the_floor_has_a_direction_term_that_fades_instead_of_stiffening():
    """Two cameras 1e-6 apart (a pan) and a head that points elsewhere: the gradient on the centre stays bounded
    (it would be ~1e6 times the direction term's pull without the floor), and at a baseline well above the floor the
    term is the reference's."""
    c2w = _cameras(2, 11)
    i, j = torch.tensor([0]), torch.tensor([1])
    T = torch.linalg.inv(c2w[i]) @ c2w[j]
    T[0, :3, 3] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    prior = HeadPrior(i, j, T, torch.ones(1, dtype=torch.float64), 1.0, 10.0, 20.0, dtype=torch.float64)
    close = c2w.clone()
    close[1, :3, 3] = close[0, :3, 3] + 1e-6 * torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = close.clone().requires_grad_(True)
    prior.loss(x).backward()
    assert float(x.grad[:, :3, 3].norm()) < 100
    far = c2w.clone()
    far[1, :3, 3] = far[0, :3, 3] + 100 * (c2w[1, :3, 3] - c2w[0, :3, 3]) / (c2w[1, :3, 3] - c2w[0, :3, 3]).norm()
    assert float(prior.loss(far)) == pytest.approx(_reference(far, i, j, T, torch.ones(1), 1.0, 10.0, 20.0), rel=1e-4)


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


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_with_true_heads_and_turned_pointmaps_the_prior_keeps_the_cameras_near_the_heads(optimizer):
    sc, preds, heads = _scene_with_true_heads(8.0)
    align = lambda ps, **kw: global_align(views_of(sc), ps, config=AlignConfig(quiet=True, niter=150,  # noqa: E731
                                                                                  optimizer=optimizer, **kw))
    free = align(heads, head_prior=0.0)
    held = align(heads, head_prior=1.0)
    rot_free = pose_errors(free.cam2world.numpy(), sc["cam2world"])[0]
    rot_held = pose_errors(held.cam2world.numpy(), sc["cam2world"])[0]
    assert rot_held < 0.5 * rot_free, (rot_held, rot_free)
    assert held.info["align"]["head_prior_edges"] == 12 and free.info["align"]["head_prior_edges"] == 0
    assert 0 < held.info["align"]["head_prior_loss"] <= held.info["align"]["final_loss"]
    assert free.info["align"]["head_prior_loss"] == 0.0
    # pose_head=False (the Procrustes start) and models without a head have no prior
    assert align(heads, head_prior=1.0, pose_head=False).info["align"]["head_prior_edges"] == 0
    assert align(preds, head_prior=1.0).info["align"]["head_prior_edges"] == 0


def test_the_start_alone_reports_the_priors_share_and_known_cameras_stay_exactly_where_given():
    sc, _, heads = _scene_with_true_heads(8.0)
    start = global_align(views_of(sc), heads, config=AlignConfig(quiet=True, optimizer="none", head_prior=1.0))
    assert start.info["align"]["iterations"] == 0 and start.info["align"]["head_prior_loss"] < 1e-6  # true heads
    known = torch.from_numpy(sc["cam2world"][:2]).float()
    r = global_align(views_of(sc), heads, cam2world={0: known[0], 1: known[1]},
                     config=AlignConfig(quiet=True, niter=50, head_prior=1.0))
    assert torch.equal(r.cam2world[:2], known)
    assert r.info["align"]["head_prior_edges"] == 10  # 12 directed edges less the two between the known cameras


@pytest.mark.parametrize("bad", [{"head_prior": -0.1}, {"head_prior": float("nan")}, {"head_prior_deg": (10.0,)},
                                 {"head_prior_deg": (0.0, 20.0)}, {"head_prior_deg": (10.0, 180.0)},
                                 {"head_prior_deg": "10,20"}])
def test_a_bad_head_prior_setting_is_refused_with_what_was_expected(bad):
    with pytest.raises(ShapeError, match=r"AlignConfig\.head_prior.* expected .*, got "):
        AlignConfig(**bad)


def test_head_prior_widths_given_as_a_list_are_kept_as_a_tuple():
    cfg = AlignConfig(head_prior_deg=[5, 30])
    assert cfg.head_prior_deg == (5.0, 30.0) and isinstance(hash(cfg), int)


def test_the_rotation_residual_is_the_squared_chord_of_the_angle_between_camera_and_head():
    c2w = _cameras(2, 12)
    turn = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    T = torch.linalg.inv(c2w[:1]) @ c2w[1:]
    T[0, :3, :3] = T[0, :3, :3] @ turn  # the head's rotation off by ``turn``
    prior = HeadPrior(torch.tensor([0]), torch.tensor([1]), T, torch.ones(1, dtype=torch.float64), 1.0, 10.0, 20.0,
                      dtype=torch.float64)
    rot, dirs = prior.residuals(c2w)
    assert float(rot[0]) == pytest.approx(chord(math.degrees(float(rotation_angle(turn)))) ** 2, rel=1e-12)
    assert float(dirs[0]) < 1e-8  # the direction is the head's (the floor shortens u by ~1e-5 of |u|)
