"""The dense alignment objective (DUSt3R's) with a chunked, memory-capped evaluator.

For every directed edge e = (i, j) with similarity S_e = s_e [R_e | t_e] (prediction frame -> world):

    L = sum_e sum_p w_i[e, p] ||X_i[p] - S_e pred_i[e, p]|| + w_j[e, p] ||X_j[p] - S_e pred_j[e, p]||
        / (number of weighted terms)

with X_n the world points of image n from its depth, intrinsics and cam2world. ``loss_and_grad`` evaluates
it over edge chunks: the per-image world points and per-edge similarities are computed once, detached
into leaves, each chunk's loss is back-propagated into those leaves, and the accumulated leaf gradients
are pushed through the parameters in one last backward. Peak memory is then O(N P + chunk P), not O(E P).
``loss_reference`` is the plain unchunked version used to test it.
"""

from __future__ import annotations

import torch

from pointmap.align.edges import EdgeStack


def rays(uv: torch.Tensor, fx, fy, cx, cy) -> torch.Tensor:
    """Camera-frame rays with z = 1 for pixels uv [N, P, 2] and per-image fx, fy, cx, cy [N]."""
    x = (uv[..., 0] - cx[:, None]) / fx[:, None]
    y = (uv[..., 1] - cy[:, None]) / fy[:, None]
    return torch.stack([x, y, torch.ones_like(x)], -1)


def world_points(depth: torch.Tensor, ray: torch.Tensor, cam2world: torch.Tensor) -> torch.Tensor:
    """depth [N, P] * ray [N, P, 3] moved by cam2world [N, 4, 4] -> [N, P, 3]."""
    pts_cam = depth[..., None] * ray
    return pts_cam @ cam2world[:, :3, :3].transpose(-1, -2) + cam2world[:, None, :3, 3]


def chunk_residual_sum(pts_world: torch.Tensor, s: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                       stack: EdgeStack, sl: slice) -> torch.Tensor:
    """Weighted sum of distances for the edges in ``sl`` (s [e], R [e, 3, 3], t [e, 3] already sliced)."""
    i, j = stack.i[sl], stack.j[sl]
    sR = s[:, None, None] * R
    total = pts_world.new_zeros(())
    for idx, pred, w in ((i, stack.pred_i[sl], stack.w_i[sl]), (j, stack.pred_j[sl], stack.w_j[sl])):
        pred, w = pred.to(sR.dtype), w.to(sR.dtype)  # no-op in the float32 optimiser
        aligned = torch.baddbmm(t[:, None, :], pred, sR.transpose(-1, -2))
        diff = pts_world.index_select(0, idx) - aligned
        # sqrt of a shifted square: the gradient stays finite at an exact zero residual
        dist = (diff.square().sum(-1) + 1e-20).sqrt()
        total = total + (w * dist).sum()
    return total


def num_terms(stack: EdgeStack) -> float:
    """Normaliser: number of weighted pixel terms (constant over iterations; cached on the stack)."""
    if stack.num_terms is None:
        stack.num_terms = float((stack.w_i > 0).sum() + (stack.w_j > 0).sum())
    return stack.num_terms


def loss_reference(pts_world, s, R, t, stack: EdgeStack) -> torch.Tensor:
    """Unchunked loss, differentiable end to end (the obviously-correct reference)."""
    return chunk_residual_sum(pts_world, s, R, t, stack, slice(0, stack.num_edges)) / num_terms(stack)


def loss_and_grad(pts_world: torch.Tensor, s: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                  stack: EdgeStack, chunk_edges: int) -> float:
    """Evaluate the loss by chunks of ``chunk_edges`` edges and back-propagate into whatever
    ``pts_world``, ``s``, ``R``, ``t`` were computed from. Returns the loss value."""
    norm = num_terms(stack)
    outs = [pts_world, s, R, t]
    leaves = [x.detach().requires_grad_(x.requires_grad) for x in outs]
    total = 0.0
    E = stack.num_edges
    for start in range(0, E, chunk_edges):
        sl = slice(start, min(E, start + chunk_edges))
        lw, ls, lR, lt = leaves
        loss = chunk_residual_sum(lw, ls[sl], lR[sl], lt[sl], stack, sl) / norm
        if loss.requires_grad:
            loss.backward()
        total += float(loss.detach())
    pairs = [(o, lf.grad) for o, lf in zip(outs, leaves) if o.requires_grad and lf.grad is not None]
    if pairs:
        torch.autograd.backward([p[0] for p in pairs], [p[1] for p in pairs])
    return total


def chunk_size_for(stack: EdgeStack, max_chunk_pixels: int) -> int:
    """Edges per chunk so that one chunk holds at most ``max_chunk_pixels`` edge-pixels (>= 1)."""
    return max(1, min(stack.num_edges, int(max_chunk_pixels // max(1, stack.num_pixels))))
