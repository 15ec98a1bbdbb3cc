"""Fast paths against slow obviously-correct references: chunked objective, init, depth fusion."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from align_scene import complete_pairs, gt_preds, make_scene, pose_errors

from pointmap.align.edges import (
    AUTO_SPREAD_CONF,
    build_stack,
    check_preds,
    conf_to_weight,
    resolve_conf_transform,
)
from pointmap.align.fuse import fuse_depth
from pointmap.align.init import edge_similarities, init_mst
from pointmap.align.objective import loss_and_grad, loss_reference
from pointmap.align.params import AlignParams


@pytest.fixture(scope="module")
def setup():
    sc = make_scene(4, 32, 48, seed=31)
    preds = gt_preds(sc, complete_pairs(4), seed=1, noise=0.02)
    keys = check_preds(preds, 4, [(32, 48)] * 4)
    stack = build_stack(preds, keys, [(32, 48)] * 4, stride=2)
    return sc, preds, stack


def _params(stack, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    n, E, P = 4, stack.num_edges, stack.num_pixels
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    c2w[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    f = torch.full((n,), 40.0, dtype=torch.float64)
    params = AlignParams(c2w, torch.tensor([True, False, True, True]), torch.rand(n, P, generator=g, dtype=torch.float64) + 1,
                         f, f, f * 0 + 23.5, f * 0 + 15.5, torch.tensor([True, True, False, True]),
                         torch.rand(E, generator=g, dtype=torch.float64) + 0.5,
                         torch.eye(3, dtype=torch.float64).repeat(E, 1, 1), torch.randn(E, 3, generator=g, dtype=torch.float64),
                         scale_free=True, dtype=dtype)
    with torch.no_grad():
        for p in params.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return params


def _grads(params):
    return {k: (p.grad.clone() if p.grad is not None else torch.zeros_like(p)) for k, p in params.named_parameters()}


@pytest.mark.parametrize("chunk", [1, 3, 5, 100])
def test_chunked_loss_and_gradients_match_reference(setup, chunk):
    _, _, stack = setup
    params = _params(stack)
    s, R, t = params.pw()
    ref = loss_reference(params.world_points(stack.uv.double()), s, R, t, stack)
    ref.backward()
    g_ref = _grads(params)
    params.zero_grad(set_to_none=True)
    s, R, t = params.pw()
    val = loss_and_grad(params.world_points(stack.uv.double()), s, R, t, stack, chunk)
    g = _grads(params)
    assert val == pytest.approx(float(ref.detach()), rel=1e-12)
    for k in g_ref:
        assert torch.allclose(g[k], g_ref[k], rtol=1e-9, atol=1e-14), k
    assert float(g_ref["log_depth"].abs().sum()) > 0  # the test exercises real gradients
    assert float(g_ref["xi"][1].abs().sum()) == 0  # known pose: no gradient
    assert float(g_ref["log_f"][2].abs().sum()) == 0  # known focal: no gradient


def test_the_vectorised_loss_equals_a_per_edge_per_pixel_python_sum(setup):
    """The vectorised residual equals a per-edge, per-pixel Python sum."""
    _, _, stack = setup
    params = _params(stack, seed=1)
    with torch.no_grad():
        X = params.world_points(stack.uv.double())
        s, R, t = params.pw()
        total, count = 0.0, 0
        for e in range(stack.num_edges):
            for img, pred, w in ((stack.i[e], stack.pred_i[e], stack.w_i[e]), (stack.j[e], stack.pred_j[e], stack.w_j[e])):
                for p in range(stack.num_pixels):
                    if w[p] > 0:
                        y = s[e] * (R[e] @ pred[p].double()) + t[e]
                        total += float(w[p]) * float((X[img, p] - y).norm())
                        count += 1
        assert float(loss_reference(X, s, R, t, stack)) == pytest.approx(total / count, rel=1e-9)


def test_confidences_become_weights_by_log_or_minus_one_and_nan_weighs_nothing():
    c = torch.tensor([0.5, 1.0, np.e, float("nan")])
    assert torch.allclose(conf_to_weight(c, "log"), torch.tensor([0.0, 0.0, 1.0, 0.0]))
    assert torch.allclose(conf_to_weight(c, "m1")[2], torch.tensor(np.e - 1, dtype=torch.float32))
    with pytest.raises(ValueError, match="conf_transform"):
        conf_to_weight(c, "bogus")


def test_auto_conf_transform_picks_log_once_a_tenth_of_the_confidences_leave_the_floor(setup):
    _, preds, _ = setup
    keys = sorted(preds)
    n = sum(preds[k].conf1.numel() + preds[k].conf2.numel() for k in keys)

    def with_share(count):  # every confidence at 1 except the first ``count`` pixels (in key order), at the threshold
        out, left = {}, count
        for k in keys:
            c = []
            for x in (preds[k].conf1, preds[k].conf2):
                flat = torch.ones(x.numel(), dtype=x.dtype)
                take = min(left, x.numel())
                flat[:take] = AUTO_SPREAD_CONF
                left -= take
                c.append(flat.reshape(x.shape))
            out[k] = replace(preds[k], conf1=c[0], conf2=c[1])
        return out

    tenth = -(-n // 10)  # ceil: the smallest count that is at least 10%
    assert resolve_conf_transform("auto", with_share(tenth), keys) == "log"
    assert resolve_conf_transform("auto", with_share(tenth - 1), keys) == "id"
    assert resolve_conf_transform("sqrt", with_share(0), keys) == "sqrt"  # explicit names pass through
    with pytest.raises(ValueError, match="conf_transform expected one of"):
        resolve_conf_transform("rank", preds, keys)


def test_auto_conf_transform_counts_only_pixels_alignment_can_weigh(setup):
    """Masked pixels (confidence 0), NaN confidences and NaN points are left out of the count: confidences of 3+
    on the 5% of pixels a mask keeps still read as spread."""
    _, preds, _ = setup
    keys = sorted(preds)
    g = torch.Generator().manual_seed(3)
    masked = {}
    for k in keys:
        p = preds[k]
        keep1, keep2 = (torch.rand(c.shape, generator=g) < 0.05 for c in (p.conf1, p.conf2))
        conf1 = torch.where(keep1, p.conf1, torch.zeros_like(p.conf1))
        conf2 = torch.where(keep2, p.conf2, torch.full_like(p.conf2, float("nan")))
        pts1 = torch.where(keep1[..., None], p.pts1_cam1, torch.full_like(p.pts1_cam1, float("nan")))
        masked[k] = replace(p, conf1=conf1, conf2=conf2, pts1_cam1=pts1)
    assert float(preds[keys[0]].conf1.min()) >= 3.0
    assert resolve_conf_transform("auto", masked, keys) == "log"


def test_init_exact_on_clean_maps():
    sc = make_scene(5, 32, 48, seed=32)
    preds = gt_preds(sc, [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4), (1, 3)], seed=2)
    keys = check_preds(preds, 5, [(32, 48)] * 5)
    stack = build_stack(preds, keys, [(32, 48)] * 5, stride=1)
    K = torch.from_numpy(sc["K"])
    init = init_mst(stack, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2])
    rot, centre, a = pose_errors(init.cam2world.numpy(), sc["cam2world"])
    assert rot < 1e-3 and centre < 1e-5
    assert len(init.tree) == 4
    # batched Procrustes per edge equals one-at-a-time
    from pointmap.align.objective import rays, world_points
    W = world_points(init.depth, rays(stack.uv.double(), K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]), init.cam2world)
    s_b, R_b, t_b = edge_similarities(stack, W, chunk=4)
    s_1, R_1, t_1 = edge_similarities(stack, W, chunk=1)
    assert torch.allclose(s_b, s_1) and torch.allclose(R_b, R_1) and torch.allclose(t_b, t_1)


def _fuse_inputs(sc, preds, keys):
    """fuse_depth's arguments with edge similarities mapping each prediction back to the true world (fit on the
    clean scene points)."""
    from pointmap.geometry.procrustes import weighted_procrustes

    c2w = torch.from_numpy(sc["cam2world"])
    K = torch.from_numpy(sc["K"])
    E = len(keys)
    s, R, t = torch.ones(E, dtype=torch.float64), torch.eye(3, dtype=torch.float64).repeat(E, 1, 1), torch.zeros(E, 3, dtype=torch.float64)
    for e, (i, j) in enumerate(keys):
        src = torch.cat([preds[(i, j)].pts1_cam1[0].reshape(-1, 3), preds[(i, j)].pts2_cam1[0].reshape(-1, 3)]).double()
        dst = torch.from_numpy(np.concatenate([sc["pts_world"][i].reshape(-1, 3), sc["pts_world"][j].reshape(-1, 3)]))
        s[e], R[e], t[e] = weighted_procrustes(src, dst)
    return (preds, keys, [(32, 48)] * 4, c2w, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], s, R, t)


def _pixel_terms(args, k, v, u):
    """Slow reference: image k's pixel (v, u) as its ray and, per edge prediction of it, the point moved into
    camera k's frame and its weight log(conf)."""
    preds, keys, _, c2w, fx, fy, cx, cy, s, R, t = args
    ray = np.array([(u - float(cx[k])) / float(fx[k]), (v - float(cy[k])) / float(fy[k]), 1.0])
    w2c = torch.linalg.inv(c2w[k])
    ys, ws = [], []
    for e, (i, j) in enumerate(keys):
        for side, img in ((0, i), (1, j)):
            if img != k:
                continue
            p = preds[(i, j)]
            pt = (p.pts1_cam1 if side == 0 else p.pts2_cam1)[0, v, u].double()
            c = (p.conf1 if side == 0 else p.conf2)[0, v, u].double()
            ys.append((w2c[:3, :3] @ (s[e] * R[e] @ pt + t[e]) + w2c[:3, 3]).numpy())
            ws.append(float(torch.log(c)))
    return ray, np.array(ys), np.array(ws)


def test_fused_depth_is_the_weighted_least_squares_solution(setup):
    sc, preds, stack = setup
    args = _fuse_inputs(sc, preds, stack.keys)
    depths, confs = fuse_depth(*args, iters=0)
    for v, u in ((7, 30), (0, 0), (31, 47), (16, 5)):
        ray, ys, ws = _pixel_terms(args, 2, v, u)
        assert float(depths[2][v, u]) == pytest.approx((ws * (ys @ ray)).sum() / (ws.sum() * ray @ ray), rel=1e-5)
    assert float(np.median(np.abs(depths[2].numpy() / sc["depth"][2] - 1))) < 0.01
    assert confs[2].shape == (32, 48) and float(confs[2].min()) >= 3.0


def test_each_reweighted_pass_is_one_irls_step_and_the_passes_reach_the_robust_l1_depth():
    sc = make_scene(4, 32, 48, seed=31)
    preds = gt_preds(sc, complete_pairs(4), seed=1, noise=0.05)
    keys = check_preds(preds, 4, [(32, 48)] * 4)
    args = _fuse_inputs(sc, preds, keys)
    d0, d1, d30 = (fuse_depth(*args, iters=n)[0][2] for n in (0, 1, 30))
    assert float((d1 - d0).abs().max()) > 1e-3  # the pass moves depths: the checks below can tell it apart
    for v, u in ((7, 30), (0, 0), (31, 47), (16, 5)):
        ray, ys, ws = _pixel_terms(args, 2, v, u)
        # one pass: weights w / |d0 r - y| at the least-squares depth d0
        w1 = ws / np.linalg.norm(float(d0[v, u]) * ray - ys, axis=1)
        assert float(d1[v, u]) == pytest.approx((w1 * (ys @ ray)).sum() / (w1.sum() * ray @ ray), rel=1e-5)
        # the fixed point minimises sum_e w_e |d r - y_e|: a convex 1-D function, found by ternary search
        cost = lambda d: float((ws * np.linalg.norm(d * ray - ys, axis=1)).sum())  # noqa: E731
        lo, hi = 0.1, 20.0
        for _ in range(200):
            a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
            lo, hi = (lo, b) if cost(a) < cost(b) else (a, hi)
        assert float(d30[v, u]) == pytest.approx((lo + hi) / 2, rel=1e-4)
