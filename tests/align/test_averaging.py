"""Motion averaging (pointmap.align.averaging): each linear problem on exact and corrupted measurements, a dense
least-squares reference, and the alignment's start on the analytic scene (tests/align/align_scene.py)."""

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, pose_errors, views_of

from pointmap.align import AlignConfig, global_align
from pointmap.align.averaging import average_centres, average_log_scales, average_rotations
from pointmap.geometry.rotations import axis_angle_to_matrix, relative_rotation_error_deg
from pointmap.pairs import make_pairs


def _rotations(n, seed):
    rng = np.random.default_rng(seed)
    return axis_angle_to_matrix(torch.from_numpy(rng.normal(size=(n, 3)))).numpy()


def _graph(n, graph="swin-2"):
    und = make_pairs(n, graph)
    i = np.array([a for a, b in und] + [b for a, b in und])
    j = np.array([b for a, b in und] + [a for a, b in und])
    return i, j


def _angle_deg(A, B):
    return float(relative_rotation_error_deg(torch.from_numpy(A), torch.from_numpy(B)).max())


def _rotate(Q, deg, rng):
    axis = rng.normal(size=3)
    return axis_angle_to_matrix(torch.from_numpy(axis * np.radians(deg) / np.linalg.norm(axis))).numpy() @ Q


def test_rotation_averaging_recovers_exact_rotations_in_the_roots_frame():
    n, root = 12, 3
    R = _rotations(n, 0)
    i, j = _graph(n)
    Q = np.swapaxes(R[i], -1, -2) @ R[j]  # j's axes in i's frame
    est, _ = average_rotations(n, i, j, Q, np.ones(len(i)), root)
    assert _angle_deg(est, R[root].T @ R) < 1e-6


def test_rotation_averaging_downweights_a_wrong_edge():
    n, root = 12, 0
    R = _rotations(n, 1)
    i, j = _graph(n)
    Q = np.swapaxes(R[i], -1, -2) @ R[j]
    rng = np.random.default_rng(2)
    Q[4] = _rotate(Q[4], 60.0, rng)  # one measurement 60 degrees off
    robust, weights = average_rotations(n, i, j, Q, np.ones(len(i)), root)
    plain, _ = average_rotations(n, i, j, Q, np.ones(len(i)), root, iters=0)
    truth = R[root].T @ R
    assert _angle_deg(robust, truth) < 0.5 < _angle_deg(plain, truth)
    assert weights[4] < 0.01 * np.median(weights)


def test_rotation_averaging_spreads_noise_that_a_chain_accumulates():
    """On a ring with 5 degrees of noise per measurement, averaging over all edges stays far closer to the truth
    than chaining the measurements along the ring (what a spanning tree does)."""
    n = 40
    R = _rotations(n, 3)
    i, j = _graph(n, "swin-3")
    rng = np.random.default_rng(4)
    Q = np.stack([_rotate(q, 5.0, rng) for q in np.swapaxes(R[i], -1, -2) @ R[j]])
    est, _ = average_rotations(n, i, j, Q, np.ones(len(i)), 0)
    chain = [np.eye(3)]
    for k in range(1, n):
        e = int(np.flatnonzero((i == k - 1) & (j == k))[0])
        chain.append(chain[-1] @ Q[e])
    truth = R[0].T @ R
    assert _angle_deg(est, truth) < 0.5 * _angle_deg(np.stack(chain), truth)


def test_one_chordal_solve_equals_a_dense_least_squares_reference():
    """iters=0 is one weighted linear solve of sum_e w_e ||R_j - R_i Q_e||^2 (R_root = I) through sparse normal
    equations, then a projection: the same as numpy's dense lstsq over the 9 entries of every free R."""
    n, root = 7, 2
    i, j = _graph(n, "complete")
    rng = np.random.default_rng(5)
    R = _rotations(n, 6)
    Q = np.stack([_rotate(q, 10.0, rng) for q in np.swapaxes(R[i], -1, -2) @ R[j]])
    w = rng.uniform(0.5, 2.0, len(i))
    est, _ = average_rotations(n, i, j, Q, w, root, iters=0)
    free = [k for k in range(n) if k != root]
    A = np.zeros((9 * len(i), 9 * len(free)))
    b = np.zeros(9 * len(i))
    for e, (a, c) in enumerate(zip(i, j)):
        sw = np.sqrt(w[e])
        for r in range(3):  # row r of R_c - R_a Q_e = 0, entry by entry
            for col in range(3):
                row = 9 * e + 3 * r + col
                if c != root:
                    A[row, 9 * free.index(c) + 3 * r + col] += sw
                else:
                    b[row] -= sw * np.eye(3)[r, col]
                for k in range(3):
                    if a != root:
                        A[row, 9 * free.index(a) + 3 * r + k] -= sw * Q[e][k, col]
                    else:
                        b[row] += sw * np.eye(3)[r, k] * Q[e][k, col]
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    ref = np.repeat(np.eye(3)[None], n, 0)
    for c, k in enumerate(free):
        U, _, Vt = np.linalg.svd(x[9 * c:9 * c + 9].reshape(3, 3))
        ref[k] = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    assert _angle_deg(est, ref) < 1e-6


def test_scale_and_centre_averaging_recover_exact_values_and_resist_an_outlier():
    n, root = 10, 1
    i, j = _graph(n, "swin-3")
    rng = np.random.default_rng(7)
    log_lam = rng.normal(size=n)
    log_lam -= log_lam[root]
    C = rng.normal(size=(n, 3))
    C -= C[root]
    ratio = log_lam[j] - log_lam[i]
    d = C[j] - C[i]
    assert np.allclose(average_log_scales(n, i, j, ratio, np.ones(len(i)), root), log_lam, atol=1e-8)
    assert np.allclose(average_centres(n, i, j, d, np.ones(len(i)), root), C, atol=1e-8)
    ratio[3] += 1.0
    d[5] += 3.0 * np.linalg.norm(d[5])
    assert np.abs(average_log_scales(n, i, j, ratio, np.ones(len(i)), root) - log_lam).max() < 0.02
    assert np.abs(average_centres(n, i, j, d, np.ones(len(i)), root) - C).max() < 0.02
    for units in (1e-3, 100.0):  # residuals count relative to each edge's baseline: the units change nothing
        assert np.allclose(average_centres(n, i, j, units * d, np.ones(len(i)), root),
                           units * average_centres(n, i, j, d, np.ones(len(i)), root), rtol=1e-9, atol=1e-12 * units)


@pytest.mark.parametrize("graph", ["complete", "swin-2", "oneref-0"])
def test_averaging_start_is_exact_on_noise_free_pointmaps(graph):
    """Every graph shape, a star of pairs with one reference image included (per-edge scales would leave it
    undetermined: the image scales are averaged first)."""
    sc = make_scene(6, 32, 48, seed=1)
    preds = gt_preds(sc, make_pairs(6, graph), seed=2)
    recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer="none", init="averaging"))
    rot, centre, _ = pose_errors(recon.cam2world.numpy(), sc["cam2world"])
    assert rot < 0.05 and centre < 0.002, (rot, centre)


def test_averaging_start_beats_the_spanning_tree_on_a_noisy_ring():
    """16 cameras, each paired with the next two, 8 degrees of pose noise per prediction: the averaged start is
    closer to the truth than the tree's, and the alignment from it ends no worse."""
    sc = make_scene(16, 24, 32, seed=0, focal_range=(24.0, 30.0))
    preds = gt_preds(sc, make_pairs(16, "swin-2"), seed=2, pair_rot_deg=8.0, noise=0.02)
    out = {}
    for init in ("mst", "averaging"):
        for opt in ("none", "adam"):
            recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer=opt, init=init))
            out[init, opt] = pose_errors(recon.cam2world.numpy(), sc["cam2world"])[0], recon.info["align"]
    assert out["averaging", "none"][0] < 0.7 * out["mst", "none"][0], out
    assert out["averaging", "adam"][0] <= out["mst", "adam"][0] + 0.5, out
    assert out["averaging", "adam"][1]["final_loss"] < out["averaging", "none"][1]["init_loss"]


def test_unknown_init_name_is_refused():
    with pytest.raises(ValueError, match="init"):
        AlignConfig(init="tree")


def _stack(sc, pairs):
    from pointmap.align.edges import build_stack, check_preds

    n, shape = len(sc["K"]), sc["depth"].shape[1:]
    preds = gt_preds(sc, pairs, seed=2)
    return build_stack(preds, check_preds(preds, n, [shape] * n), [shape] * n, stride=1)


def _intrinsics(sc):
    K = torch.from_numpy(sc["K"])
    return K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]


def test_averaging_start_refuses_an_image_reached_only_by_unusable_edges():
    """Connectivity counts only the edges whose relative motion is usable: an image tied to the rest by zero-weight
    edges alone would otherwise come out wherever the solver's ridge leaves it."""
    from pointmap.align.averaging import init_averaging
    from pointmap.errors import GraphError

    sc = make_scene(4, 24, 32, seed=0)
    stack = _stack(sc, make_pairs(4, "swin-1-noncyclic"))
    stack.score[(stack.i == 3) | (stack.j == 3)] = 0.0
    with pytest.raises(GraphError, match="usable relative motion.*disconnected"):
        init_averaging(stack, *_intrinsics(sc))


def test_a_failed_averaging_falls_back_to_the_spanning_tree_with_a_warning(monkeypatch):
    import pointmap.align.averaging as averaging

    real = averaging.edge_motions

    def broken(stack, own, chunk=64, **kw):
        Q, t, s, sigma = real(stack, own, chunk, **kw)
        bad = (stack.i == 3) | (stack.j == 3)
        return torch.where(bad[:, None, None], torch.nan, Q), t, s, sigma

    monkeypatch.setattr(averaging, "edge_motions", broken)
    sc = make_scene(4, 24, 32, seed=0)
    preds = gt_preds(sc, make_pairs(4, "swin-1-noncyclic"), seed=2)
    with pytest.warns(UserWarning, match="motion-averaging start failed"):
        recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer="none"))
    assert recon.info["align"]["init"].startswith("mst (averaging failed")
    assert pose_errors(recon.cam2world.numpy(), sc["cam2world"])[0] < 0.05  # the tree's exact start


def test_negative_confidences_count_nothing_in_the_pair_scores_so_the_averaging_start_stands():
    """A block of negative confidence in every pair's first map weighs nothing in the pixel weights; in the pairs'
    scores (mean conf1 x mean conf2) it made every score negative, and the averaging start gave up for the tree."""
    import warnings

    sc = make_scene(4, 32, 48, seed=3)
    preds = gt_preds(sc, complete_pairs(4), seed=4)
    for p in preds.values():
        p.conf1[0, :12, :16] = -50.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback and no warning
        recon = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, niter=0))
    assert recon.info["align"]["init"] == "averaging"
    assert pose_errors(recon.cam2world.numpy(), sc["cam2world"])[0] < 0.05


def test_the_report_names_the_start_and_its_root():
    sc = make_scene(4, 24, 32, seed=0)
    preds = gt_preds(sc, complete_pairs(4), seed=2)
    for init in ("averaging", "mst"):
        rep = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer="none", init=init)).info["align"]
        assert rep["init"] == init and 0 <= rep["root"] < 4


def test_complete_graph_start_agrees_with_the_tree_when_predictions_are_exact():
    sc = make_scene(5, 24, 32, seed=3)
    preds = gt_preds(sc, complete_pairs(5), seed=2)
    a = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer="none", init="averaging"))
    b = global_align(views_of(sc), preds, config=AlignConfig(quiet=True, optimizer="none", init="mst"))
    assert torch.allclose(a.cam2world, b.cam2world, atol=1e-3)


def test_the_averaging_start_takes_each_edges_motion_from_the_pose_head_when_the_predictions_carry_one():
    """Every prediction's view-2 map is turned 8 degrees about view 1 (the Procrustes of the maps is off) while its
    pose head has the true transform: the start from the heads is exact, the start from the maps is not, and
    pose_head=False (or a model without a head) gives the maps' start."""
    from dataclasses import replace

    sc = make_scene(4, 24, 32, seed=0)
    preds = gt_preds(sc, complete_pairs(4), seed=2, pair_rot_deg=8.0)
    c2w, pw = sc["cam2world"], sc["pts_world"]
    heads = {}
    for (i, j), p in preds.items():
        w2c = np.linalg.inv(c2w[i])
        own1 = pw[i] @ w2c[:3, :3].T + w2c[:3, 3]
        s = float(p.pts1_cam1.double().norm() / torch.from_numpy(own1).norm())  # the prediction's scale
        T = torch.from_numpy(w2c @ c2w[j])
        T[:3, 3] *= s
        heads[(i, j)] = replace(p, cam2_to_cam1=T[None].float())
    start = lambda ps, **kw: global_align(views_of(sc), ps, config=AlignConfig(quiet=True, optimizer="none",  # noqa: E731
                                                                                  **kw)).cam2world.numpy()
    rot_head, centre_head, _ = pose_errors(start(heads), c2w)
    rot_maps, centre_maps, _ = pose_errors(start(heads, pose_head=False), c2w)
    assert rot_head < 0.05 and centre_head < 1e-3  # 0.011 degrees, 2e-8 of the scene (the solver's ridge)
    assert rot_maps > 1.0 and centre_maps > 0.01  # 4.5 degrees, 3% of the scene
    assert np.allclose(start(preds), start(heads, pose_head=False))
