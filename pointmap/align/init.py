"""Initialisation by a maximum spanning tree over pair scores (what DUSt3R's ``init='mst'`` does).

1. Edge score: mean(conf_i) * mean(conf_j); the spanning tree maximising it (scipy MST on negated
   scores over undirected pairs, keeping the better of the two directions).
2. Each image's own pointmap: the ``pred_i`` of its best-scoring edge where it is the first view; its
   focal by Weiszfeld on that map (unless known).
3. From the root (image 0 of the strongest tree edge; world = its camera frame), walk the tree: an
   edge touching a placed image k is aligned onto k's world points by confidence-weighted similarity
   Procrustes, which places the new image's points; the new image's pose and depth scale come from a
   Procrustes of its own pointmap onto those points.
4. Every edge's similarity: Procrustes of both its maps onto the two images' world points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pointmap.align.edges import EdgeStack
from pointmap.align.objective import rays, world_points
from pointmap.errors import GraphError
from pointmap.geometry.procrustes import weighted_procrustes


@dataclass
class InitResult:
    cam2world: torch.Tensor   # [N, 4, 4] float64
    depth: torch.Tensor       # [N, P] z-depth at the stack's pixels, float64
    pw_s: torch.Tensor        # [E]
    pw_R: torch.Tensor        # [E, 3, 3]
    pw_t: torch.Tensor        # [E, 3]
    tree: list                # [(k_placed, m_new, edge_index)] of the tree start; [] for motion averaging
    root: int


def spanning_tree(n_images: int, stack: EdgeStack) -> tuple[list, int]:
    """Maximum spanning tree over undirected pairs; returns ([(a, b, best_edge)], first_edge_image)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    best: dict[tuple[int, int], int] = {}
    for e in range(stack.num_edges):
        a, b = int(stack.i[e]), int(stack.j[e])
        key = (min(a, b), max(a, b))
        if key not in best or stack.score[e] > stack.score[best[key]]:
            best[key] = e
    keys = list(best)
    scores = np.array([float(stack.score[best[k]]) for k in keys])
    # scipy drops explicit zeros and minimises: use a positive decreasing function of the score
    cost = (scores.max() + 1.0) - scores + 1e-6
    rows = [k[0] for k in keys]
    cols = [k[1] for k in keys]
    mst = minimum_spanning_tree(coo_matrix((cost, (rows, cols)), shape=(n_images, n_images)).tocsr()).tocoo()
    tree = sorted(((int(a), int(b), best[(min(a, b), max(a, b))]) for a, b in zip(mst.row, mst.col)),
                  key=lambda x: -float(stack.score[x[2]]))
    if len(tree) != n_images - 1:
        raise GraphError(f"the pair graph is disconnected: a spanning tree over {n_images} images has "
                         f"{len(tree)} edges instead of {n_images - 1}")
    return tree, int(stack.i[tree[0][2]])


def own_maps(n_images: int, stack: EdgeStack) -> list[int]:
    """Index of the best-scoring edge in which each image is the first view (its own camera frame)."""
    own = [-1] * n_images
    for e in range(stack.num_edges):
        i = int(stack.i[e])
        if own[i] < 0 or stack.score[e] > stack.score[own[i]]:
            own[i] = e
    missing = [n for n in range(n_images) if own[n] < 0]
    if missing:
        raise GraphError(f"images {missing[:10]} have no pair left in which they come first, so no pointmap in "
                         "their own camera frame exists: pass both orders (i, j) and (j, i) as predict_pairs does, "
                         "or, when both were given, their first-view maps held no usable point (all NaN or inf, "
                         "or confidence 0: masked) and those pairs were dropped")
    return own


def own_depth_ok(stack: EdgeStack, own: list[int]) -> torch.Tensor:
    """[N, P] bool: the pixels whose own-frame map (``own_maps``) has a point in front of the camera (the stack
    holds 0 where the prediction was NaN or inf; an ``expm1`` head can also put points behind)."""
    return (stack.pred_i[torch.as_tensor(own, dtype=torch.long)][..., 2] > 0) & stack.pix_valid


def fill_unseen_depth(depth: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """``depth`` [N, P] with each image's pixels outside ``ok`` set to the median of its pixels inside (a start
    the optimisation moves by the other pairs' maps), instead of the 1e-8 a clamp would leave there."""
    out = depth.clone()
    for m in range(depth.shape[0]):
        if bool(ok[m].any()) and not bool(ok[m].all()):
            out[m, ~ok[m]] = depth[m, ok[m]].median()
    return out


def depth_from_edges(stack: EdgeStack, depth: torch.Tensor, ok: torch.Tensor, cam2world: torch.Tensor,
                     pw_s: torch.Tensor, pw_R: torch.Tensor, pw_t: torch.Tensor) -> torch.Tensor:
    """``depth`` [N, P] with each image's pixels outside ``ok`` (no point of its own map there) taken from the
    other pairs' maps of that image instead: each edge's points moved into the world by its similarity, then
    into the image's camera, their z averaged by the edges' weights (pixels no edge sees in front keep theirs)."""
    out = depth.clone()
    if bool((ok | ~stack.pix_valid).all()):  # every image's own map has all its points: nothing to fill
        return out
    world2cam = torch.linalg.inv(cam2world)
    num = torch.zeros_like(depth)
    den = torch.zeros_like(depth)
    for e in range(stack.num_edges):
        for m, pred, w in ((int(stack.i[e]), stack.pred_i[e], stack.w_i[e]), (int(stack.j[e]), stack.pred_j[e],
                                                                                stack.w_j[e])):
            miss = ~ok[m] & (w > 0)
            if not bool(miss.any()):
                continue
            X = pw_s[e] * pred[miss].to(depth.dtype) @ pw_R[e].T + pw_t[e]  # world
            z = X @ world2cam[m, 2, :3] + world2cam[m, 2, 3]
            front = z > 0
            idx = miss.nonzero()[:, 0][front]
            num[m, idx] += w[miss][front].to(depth.dtype) * z[front]
            den[m, idx] += w[miss][front].to(depth.dtype)
    seen = den > 0
    out[seen] = num[seen] / den[seen]
    return out


def _procrustes(src, dst, w, what: str):
    """weighted_procrustes of one problem, refused (GraphError) when it has no weighted pixel."""
    s, R, t = weighted_procrustes(src, dst, w)
    if not bool(torch.isfinite(s)):
        raise GraphError(f"{what} has no pixel with a positive confidence weight to place it by (its confidences "
                         "all map to weight 0 under the alignment's conf_transform, or its points are invalid)")
    return s, R, t


def init_mst(stack: EdgeStack, fx, fy, cx, cy) -> InitResult:
    """Initial cam2world, depth (at the stack's pixels) and edge similarities; intrinsics as given [N]."""
    n = stack.uv.shape[0]
    dt = torch.float64
    tree, root = spanning_tree(n, stack)
    own = own_maps(n, stack)
    ray = rays(stack.uv.to(dt), fx.to(dt), fy.to(dt), cx.to(dt), cy.to(dt))
    cam2world = torch.eye(4, dtype=dt).repeat(n, 1, 1)
    depth = torch.ones(n, stack.num_pixels, dtype=dt)
    placed = torch.zeros(n, dtype=torch.bool)
    pts_world = torch.zeros(n, stack.num_pixels, 3, dtype=dt)

    def place(m: int, target: torch.Tensor, w_target: torch.Tensor):
        """Pose + depth of image m from its own map aligned onto world points ``target``."""
        e = own[m]
        own_pts = stack.pred_i[e].to(dt)
        w = stack.w_i[e].to(dt) * w_target
        s, R, t = _procrustes(own_pts, target, w, f"image {m}'s own pointmap")
        cam2world[m, :3, :3] = R
        cam2world[m, :3, 3] = t
        depth[m] = fill_unseen_depth((s * own_pts[:, 2]).clamp_min(1e-8)[None], ok[m:m + 1])[0]
        pts_world[m] = world_points(depth[m:m + 1], ray[m:m + 1], cam2world[m:m + 1])[0]
        placed[m] = True

    ok = own_depth_ok(stack, own)
    # root: identity pose, depth = its own map's z
    depth[root] = fill_unseen_depth(stack.pred_i[own[root]][:, 2].to(dt).clamp_min(1e-8)[None], ok[root:root + 1])[0]
    pts_world[root] = world_points(depth[root:root + 1], ray[root:root + 1], cam2world[root:root + 1])[0]
    placed[root] = True
    pending = list(tree)
    while pending:
        for k_idx, (a, b, e) in enumerate(pending):
            if placed[a] != placed[b]:
                break
        else:  # cannot happen for a spanning tree
            raise GraphError("internal: spanning tree walk stalled")
        pending.pop(k_idx)
        i, j = int(stack.i[e]), int(stack.j[e])
        k = i if placed[i] else j
        m = j if k == i else i
        pred_k, w_k = (stack.pred_i[e], stack.w_i[e]) if k == i else (stack.pred_j[e], stack.w_j[e])
        pred_m, w_m = (stack.pred_j[e], stack.w_j[e]) if k == i else (stack.pred_i[e], stack.w_i[e])
        w_placed = w_k.to(dt) * ok[k].to(dt)  # the placed image's own points, not its filled-in starts
        s, R, t = _procrustes(pred_k.to(dt), pts_world[k], w_placed if bool(w_placed.sum() > 0) else w_k.to(dt),
                              f"pair ({i}, {j})'s pointmap of image {k}")
        target = s * pred_m.to(dt) @ R.T + t
        place(m, target, w_m.to(dt))

    pw_s, pw_R, pw_t = edge_similarities(stack, pts_world, ok)
    depth = depth_from_edges(stack, depth, ok, cam2world, pw_s, pw_R, pw_t)
    return InitResult(cam2world=cam2world, depth=depth, pw_s=pw_s, pw_R=pw_R, pw_t=pw_t, tree=tree, root=root)


def edge_similarities(stack: EdgeStack, pts_world: torch.Tensor, ok: torch.Tensor | None = None, chunk: int = 64):
    """Per-edge similarity fitting both maps onto the current world points (batched Procrustes); ``ok`` [N, P]:
    the world points to fit onto (``own_depth_ok``; the others are starts, not evidence), unless that leaves an
    edge no weight."""
    dt = pts_world.dtype
    out_s, out_R, out_t = [], [], []
    for start in range(0, stack.num_edges, chunk):
        sl = slice(start, start + chunk)
        src = torch.cat([stack.pred_i[sl], stack.pred_j[sl]], 1).to(dt)
        dst = torch.cat([pts_world[stack.i[sl]], pts_world[stack.j[sl]]], 1)
        w = torch.cat([stack.w_i[sl], stack.w_j[sl]], 1).to(dt)
        if ok is not None:  # an edge left without weight keeps all its pixels (a start, however poor)
            masked = w * torch.cat([ok[stack.i[sl]], ok[stack.j[sl]]], 1).to(dt)
            w = torch.where((masked.sum(1) > 0)[:, None], masked, w)
        s, R, t = weighted_procrustes(src, dst, w)
        out_s.append(s)
        out_R.append(R)
        out_t.append(t)
    return torch.cat(out_s), torch.cat(out_R), torch.cat(out_t)
