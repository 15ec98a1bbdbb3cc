"""Motion averaging: the alignment's initial poses and depths from every edge at once.

The spanning-tree start (``init.init_mst``) chains one edge per image, so the pose error of each tree edge moves
every image behind it: on ``benchmarks/bench_align.py``'s 100-image ring with 8 degrees of pose noise per pair, the
tree start is 37 degrees off at worst and the dense alignment, started there, ends 27 degrees off; from this start,
15 and 14 (docs/alignment.md). Every
directed edge e = (i, j) measures image j's camera in image i's frame, and averaging those measurements over all
edges spreads the error instead of accumulating it. Three linear least-squares problems, each reweighted a few
times by a Cauchy function of its residuals (iteratively reweighted least squares), on the edge scores:

1. rotations: Procrustes of image j's own map (its best edge as first view) onto the edge's map of j gives Q_e,
   j's camera axes in i's frame (with a pose head, the edge's own transform gives Q_e and the direction of t_e
   below: the Procrustes compares two passes' regressions of j, whose disagreement turns short baselines,
   session 49); minimise sum_e w_e ||R_j - R_i Q_e||_F^2 (chordal, linear, one solve per row of R) with the
   root image's R = I, then project each R onto SO(3);
2. scales: each image's own map has an unknown scale lambda in world units; the edge's map of i is sigma_e times
   i's own map and its map of j is s_e times j's (the same Procrustes), so log lambda_j - log lambda_i =
   log(s_e / sigma_e), with lambda_root = 1. The edge's own scale is then m_e = lambda_i / sigma_e;
3. centres: the same Procrustes puts j's centre at t_e in i's frame at the edge's scale, so C_j - C_i =
   m_e R_i t_e, with C_root = 0. Scales first make this well posed on any connected graph (a star of pairs with
   one reference image included), which per-edge unknown scales would not be.

Depths are each image's own map's z at its scale lambda. The result feeds the same edge similarities and
dense optimisation as the tree start.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pointmap.align.edges import EdgeStack, check_connected
from pointmap.align.init import (
    InitResult,
    depth_from_edges,
    edge_similarities,
    fill_unseen_depth,
    own_depth_ok,
    own_maps,
)
from pointmap.align.objective import rays, world_points
from pointmap.errors import GraphError
from pointmap.geometry.cameras import head_translation
from pointmap.geometry.procrustes import weighted_procrustes
from pointmap.geometry.rotations import project_to_rotation, rotation_angle

ROT_SIGMA_DEG = 5.0      # Cauchy scale of an edge's rotation residual
SCALE_SIGMA = 0.1        # ... of its log-scale residual
CENTRE_SIGMA = 0.2       # ... of its centre residual, relative to the edge's baseline
IRLS_ITERS = 4


def edge_motions(stack: EdgeStack, own: list[int], chunk: int = 64, pose_head: bool = True):
    """Per directed edge e = (i, j): (Q [E, 3, 3] j's axes in i's frame, t [E, 3] j's centre in i's frame at the
    edge's scale, s [E] the edge's map of j over j's own map, sigma [E] the edge's map of i over i's own map), all
    float64. Non-finite where a Procrustes failed. From the Procrustes of j's own map onto the edge's, except,
    when the stack has the pose head's transforms (``stack.T``) and ``pose_head``, Q and t's direction: those are
    the head's (t keeps the Procrustes' length: the head's baselines come out short, session 49)."""
    dt = torch.float64
    own_t = torch.as_tensor(own, dtype=torch.long)
    Q, t, s, sigma = [], [], [], []
    for start in range(0, stack.num_edges, chunk):
        sl = slice(start, start + chunk)
        i, j = stack.i[sl], stack.j[sl]
        oj, oi = own_t[j], own_t[i]
        src, w_src = stack.pred_i[oj].to(dt), stack.w_i[oj].to(dt)
        s_e, R_e, t_e = weighted_procrustes(src, stack.pred_j[sl].to(dt), w_src * stack.w_j[sl].to(dt))
        Q.append(R_e)
        t.append(t_e)
        s.append(s_e)
        # the edge's map of i against i's own map: the same camera frame, only the scale differs
        p, q = stack.pred_i[sl].to(dt), stack.pred_i[oi].to(dt)
        w = stack.w_i[sl].to(dt) * stack.w_i[oi].to(dt)
        sigma.append((w * (p * q).sum(-1)).sum(-1) / (w * q.square().sum(-1)).sum(-1).clamp_min(1e-30))
    Q, t, s, sigma = torch.cat(Q), torch.cat(t), torch.cat(s), torch.cat(sigma)
    if pose_head and stack.T is not None:  # the head's rotation and direction, the maps' baseline length
        Q = stack.T[:, :3, :3].clone()
        t = head_translation(stack.T[:, :3, 3], t)
    return Q, t, s, sigma


def _cauchy(r: np.ndarray, sigma: float) -> np.ndarray:
    return 1.0 / (1.0 + (r / sigma) ** 2)


def _solve(rows, cols, vals, n_rows: int, n_cols: int, rhs: np.ndarray, w_rows: np.ndarray) -> np.ndarray:
    """Weighted least squares min sum_r w_r (A x - b)_r^2 through the sparse normal equations; rhs [R, k]."""
    from scipy.sparse import csr_matrix, diags
    from scipy.sparse.linalg import splu

    A = csr_matrix((vals, (rows, cols)), shape=(n_rows, n_cols))
    AtW = A.T @ diags(w_rows)
    N = (AtW @ A).tocsc()
    N = N + 1e-12 * float(np.abs(N.diagonal()).max() or 1.0) * diags(np.ones(n_cols), format="csc")
    return splu(N).solve(np.asarray(AtW @ rhs))


def _difference_rows(n: int, i: np.ndarray, j: np.ndarray, root: int):
    """Sparse (rows, cols, vals) of x_j - x_i, one row per edge, over the unknowns of every image but ``root``
    (held at 0: its column is dropped)."""
    col = {k: c for c, k in enumerate(k for k in range(n) if k != root)}
    rows, cols, vals = [], [], []
    for e in range(len(i)):
        for k, v in ((int(j[e]), 1.0), (int(i[e]), -1.0)):
            if k != root:
                rows.append(e)
                cols.append(col[k])
                vals.append(v)
    return rows, cols, vals


def average_rotations(n: int, i: np.ndarray, j: np.ndarray, Q: np.ndarray, w: np.ndarray, root: int,
                      iters: int = IRLS_ITERS, sigma_deg: float = ROT_SIGMA_DEG) -> tuple[np.ndarray, np.ndarray]:
    """World-from-camera rotations [n, 3, 3] with R_root = I that best satisfy R_j = R_i Q_e (chordal, IRLS);
    also the final per-edge weights."""
    free = [k for k in range(n) if k != root]
    col = {k: c for c, k in enumerate(free)}
    E = len(i)
    rows, cols, vals = [], [], []
    rhs = np.zeros((3 * E, 3))
    for e in range(E):
        # one row a of R at a time: x_j - Q_e^T x_i = 0, with x_k = R_k[a, :]
        for r in range(3):
            re = 3 * e + r
            for k, block in ((int(j[e]), np.eye(3)[r]), (int(i[e]), -Q[e].T[r])):
                if k == root:  # x_root = e_a: move to the right-hand side (one column per row a)
                    rhs[re] -= block
                else:
                    for c in range(3):
                        if block[c] != 0:
                            rows.append(re)
                            cols.append(3 * col[k] + c)
                            vals.append(block[c])
    weights = w.copy()
    R = np.repeat(np.eye(3)[None], n, 0)
    for _ in range(iters + 1):
        x = _solve(rows, cols, vals, 3 * E, 3 * len(free), rhs, np.repeat(weights, 3))  # [3 (n-1), 3]
        for k in free:
            R[k] = x[3 * col[k]:3 * col[k] + 3].T  # column a holds row a of R_k
        R = project_to_rotation(torch.from_numpy(R)).numpy()
        res = np.degrees(rotation_angle(torch.from_numpy(np.swapaxes(R[j], -1, -2) @ R[i] @ Q)).numpy())
        weights = w * _cauchy(res, sigma_deg)
    return R, weights


def average_log_scales(n: int, i: np.ndarray, j: np.ndarray, log_ratio: np.ndarray, w: np.ndarray, root: int,
                       iters: int = IRLS_ITERS, sigma: float = SCALE_SIGMA) -> np.ndarray:
    """log lambda [n] with lambda_root = 1 best satisfying log lambda_j - log lambda_i = log_ratio_e (IRLS)."""
    free, E = [k for k in range(n) if k != root], len(i)
    rows, cols, vals = _difference_rows(n, i, j, root)
    weights = w.copy()
    out = np.zeros(n)
    for _ in range(iters + 1):
        x = _solve(rows, cols, vals, E, len(free), log_ratio[:, None], weights)[:, 0]
        out[free] = x
        weights = w * _cauchy(out[j] - out[i] - log_ratio, sigma)
    return out


def average_centres(n: int, i: np.ndarray, j: np.ndarray, d: np.ndarray, w: np.ndarray, root: int,
                    iters: int = IRLS_ITERS, sigma: float = CENTRE_SIGMA) -> np.ndarray:
    """Camera centres [n, 3] with C_root = 0 best satisfying C_j - C_i = d_e (IRLS, residuals relative to
    the edge's baseline)."""
    free, E = [k for k in range(n) if k != root], len(i)
    rows, cols, vals = _difference_rows(n, i, j, root)
    base = np.linalg.norm(d, axis=1)
    floor = 1e-3 * float(np.median(base[w > 0] if (w > 0).any() else base)) + 1e-30
    weights = w.copy()
    C = np.zeros((n, 3))
    for _ in range(iters + 1):
        C[free] = _solve(rows, cols, vals, E, len(free), d, weights)  # the three coordinates share the system
        res = np.linalg.norm(C[j] - C[i] - d, axis=1) / np.maximum(base, floor)
        weights = w * _cauchy(res, sigma)
    return C


def init_averaging(stack: EdgeStack, fx, fy, cx, cy, pose_head: bool = True) -> InitResult:
    """The alignment's start from motion averaging (module docstring); intrinsics as given [N]; ``pose_head``:
    the edges' relative motions from the pose head's transforms when the stack has them. GraphError for
    a graph that cannot be averaged: not connected, or not connected by the edges whose relative motion came out
    usable (finite, positive scales); an image never first in a pair; a non-finite result."""
    n = stack.uv.shape[0]
    dt = torch.float64
    own = own_maps(n, stack)
    Q, t, s, sigma = edge_motions(stack, own, pose_head=pose_head)
    i, j = stack.i.numpy(), stack.j.numpy()
    w = stack.score.double().numpy().copy()
    ok = (torch.isfinite(Q).flatten(1).all(1) & torch.isfinite(t).all(1) & (s > 0) & (sigma > 0)).numpy()
    ok &= np.isfinite(w) & (w > 0)
    w[~ok] = 0.0
    if not (w > 0).any():
        raise GraphError("motion averaging: no edge gave a usable relative motion (all weights zero)")
    try:
        check_connected(n, [stack.keys[e] for e in np.flatnonzero(w > 0)])
    except GraphError as err:
        raise GraphError(f"motion averaging over the edges with a usable relative motion: {err}") from None
    # unusable edges (weight 0) get a neutral motion, so that no NaN reaches the normal equations
    Q = np.where(ok[:, None, None], Q.numpy(), np.eye(3))
    t = np.where(ok[:, None], t.numpy(), 0.0)
    s, sigma = np.where(ok, s.numpy(), 1.0), np.where(ok, sigma.numpy(), 1.0)
    root = int(i[int(np.argmax(w))])
    R = average_rotations(n, i, j, Q, w, root)[0]
    log_lam = average_log_scales(n, i, j, np.log(s / sigma), w, root)
    m = np.exp(log_lam[i]) / sigma  # each edge's scale in world units
    d = m[:, None] * np.einsum("eab,eb->ea", R[i], t)
    C = average_centres(n, i, j, d, w, root)
    if not (np.isfinite(R).all() and np.isfinite(C).all() and np.isfinite(log_lam).all()):
        raise GraphError("motion averaging produced non-finite poses")
    cam2world = torch.eye(4, dtype=dt).repeat(n, 1, 1)
    cam2world[:, :3, :3] = torch.from_numpy(R)
    cam2world[:, :3, 3] = torch.from_numpy(C)
    own_t = torch.as_tensor(own, dtype=torch.long)
    lam = torch.from_numpy(np.exp(log_lam))
    ok = own_depth_ok(stack, own)
    depth = fill_unseen_depth((lam[:, None] * stack.pred_i[own_t][..., 2].to(dt)).clamp_min(1e-8), ok)
    ray = rays(stack.uv.to(dt), fx.to(dt), fy.to(dt), cx.to(dt), cy.to(dt))
    pts_world = world_points(depth, ray, cam2world)
    pw_s, pw_R, pw_t = edge_similarities(stack, pts_world, ok)
    depth = depth_from_edges(stack, depth, ok, cam2world, pw_s, pw_R, pw_t)
    if not (math.isfinite(float(pw_s.sum())) and bool((pw_s > 0).all())):
        raise GraphError("motion averaging produced degenerate edge similarities")
    return InitResult(cam2world=cam2world, depth=depth, pw_s=pw_s, pw_R=pw_R, pw_t=pw_t, tree=[], root=root)
