"""Pair predictions gathered for alignment: validation, weights, scores and optimisation-resolution stacks.

Every directed edge e = (i, j) carries image i's points (``pred_i``) and image j's points (``pred_j``),
both in image i's camera frame up to an unknown similarity (the network's scale normalisation).
For optimisation the maps are subsampled with a stride and padded to a common pixel count ``P`` so all
edges stack into dense tensors ``[E, P, 3]``; padded or unusable pixels carry weight 0.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from pointmap.errors import GraphError, ShapeError, is_int
from pointmap.prediction import check_prediction

CONF_TRANSFORMS = ("log", "m1", "sqrt", "id")
# 'auto': log(conf) when the confidences spread above 1, conf itself when they sit at the floor
AUTO_SPREAD_CONF = 1.1     # a confidence at least this high counts as "above the floor"
AUTO_SPREAD_SHARE = 0.1    # ... and log is chosen when at least this share of the usable pixels' confidences is


def conf_to_weight(conf: torch.Tensor, transform: str = "log") -> torch.Tensor:
    """Residual weights from confidences: 'log' (DUSt3R default, log(conf), 0 for conf <= 1),
    'm1' (conf - 1), 'sqrt', or 'id' (conf itself). Never negative. ('auto' is resolved to one of these
    by ``resolve_conf_transform`` before weights are made.)"""
    if transform == "log":
        w = torch.log(conf.clamp_min(1.0))
    elif transform == "m1":
        w = conf - 1.0
    elif transform == "sqrt":
        w = conf.clamp_min(0).sqrt()
    elif transform == "id":
        w = conf
    else:
        raise ValueError(f"conf_transform expected one of {CONF_TRANSFORMS} (or 'auto' in AlignConfig), "
                         f"got {transform!r}")
    return torch.nan_to_num(w, nan=0.0, posinf=0.0).clamp_min(0.0)


def _valid_points(pts: torch.Tensor) -> torch.Tensor:
    return torch.isfinite(pts).all(-1)


@dataclass
class EdgeStack:
    """Directed edges at the optimisation resolution.

    i, j:      [E] long image indices
    pred_i:    [E, P, 3] image i's points in i's frame (prediction scale); pred_j likewise for image j
    w_i, w_j:  [E, P] weights (0 on padding / invalid pixels)
    uv:        [N, P, 2] map-pixel coordinates (full map resolution) of each image's sampled pixels
    pix_valid: [N, P] bool, real (non-padding) pixels
    score:     [E] edge score mean(conf_i) * mean(conf_j)
    stride:    subsampling stride used
    T:         [E, 4, 4] float64 the pose head's transform of each edge (camera j -> camera i, prediction scale)
               when every prediction carries one (``PairPrediction.cam2_to_cam1``), else None
    """

    i: torch.Tensor
    j: torch.Tensor
    pred_i: torch.Tensor
    pred_j: torch.Tensor
    w_i: torch.Tensor
    w_j: torch.Tensor
    uv: torch.Tensor
    pix_valid: torch.Tensor
    score: torch.Tensor
    stride: int
    keys: list
    num_terms: float | None = None
    T: torch.Tensor | None = None

    @property
    def num_edges(self) -> int:
        return int(self.i.shape[0])

    @property
    def num_pixels(self) -> int:
        return int(self.uv.shape[1])


def sample_index(h: int, w: int, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows and columns kept by stride-``stride`` subsampling (centre of each cell); a side no longer than half the
    stride keeps its middle pixel (the cell's centre would lie beyond it: no pixel, or a raw error from arange)."""
    def keep(n: int) -> torch.Tensor:
        off = stride // 2
        return torch.arange(off if off < n else (n - 1) // 2, n, stride)

    return keep(h), keep(w)


def check_preds(preds: dict, n_images: int, shapes: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Validate the prediction dict; returns the sorted directed edge keys (self-pairs dropped)."""
    if not isinstance(preds, dict) or not preds:
        raise GraphError("preds expected a non-empty dict {(i, j): PairPrediction}, got "
                         f"{type(preds).__name__} with {len(preds) if hasattr(preds, '__len__') else '?'} entries")
    keys = []
    for key, p in preds.items():
        if not (isinstance(key, tuple) and len(key) == 2 and is_int(key[0]) and is_int(key[1])):
            raise GraphError(f"preds keys expected (i, j) tuples of image indices (integers), got {key!r}")
        check_prediction(p, f"preds[{key}]")
        i, j = int(key[0]), int(key[1])
        if not (0 <= i < n_images and 0 <= j < n_images):
            raise GraphError(f"pair {key} refers to an image outside 0..{n_images - 1}")
        if i == j:
            warnings.warn(f"pair {key} pairs an image with itself; it carries no pose information and is "
                          "ignored", stacklevel=3)
            continue
        if p.batch_size != 1:
            raise ShapeError(f"pair {key}: expected batch size 1 per pair, got {p.batch_size}")
        for name, pts, n in (("pts1_cam1", p.pts1_cam1, i), ("pts2_cam1", p.pts2_cam1, j)):
            if tuple(pts.shape[1:3]) != tuple(shapes[n]):
                raise ShapeError(f"pair {key}: {name} is {list(pts.shape[1:3])} but image {n} is "
                                 f"{list(shapes[n])} (h, w)")
        keys.append((i, j))
    return sorted(keys)


def resolve_conf_transform(transform: str, preds: dict, keys: list) -> str:
    """``transform`` itself, or for 'auto': 'log' when at least AUTO_SPREAD_SHARE of the usable pixels of the
    ``keys`` predictions (finite points, finite confidence > 0) have a confidence of AUTO_SPREAD_CONF or more,
    else 'id'.

    log(conf) is DUSt3R's weighting for confidences that spread above their floor of 1 (the official models'
    do: the demos threshold them at 1.5 and 3). A model whose confidences all sit at the floor (ours up to v23a,
    session 24: below 1.03 on held-out scenes; since v24a most pixels are at 1.1 or more) would get weights of
    1e-5 that are float32 rounding noise, and global alignment worse than its own pairwise poses
    (docs/alignment.md, measured); conf itself then weighs the pixels (nearly) uniformly.
    """
    if transform != "auto":
        if transform not in CONF_TRANSFORMS:
            raise ValueError(f"conf_transform expected one of {CONF_TRANSFORMS} (or 'auto'), got {transform!r}")
        return transform
    above = total = 0
    for key in keys:
        p = preds[key]
        for c, pts in ((p.conf1, p.pts1_cam1), (p.conf2, p.pts2_cam1)):
            c = c.detach()
            # pixels alignment can weigh: finite points, finite confidence above 0 (masks set it to 0)
            usable = torch.isfinite(c) & (c > 0) & torch.isfinite(pts.detach()).all(-1)
            above += int((usable & (c >= AUTO_SPREAD_CONF)).sum())
            total += int(usable.sum())
    return "log" if total and above >= AUTO_SPREAD_SHARE * total else "id"


def build_stack(preds: dict, keys: list, shapes: list[tuple[int, int]], stride: int,
                conf_transform: str = "log", dtype=torch.float32) -> EdgeStack:
    """Subsample, weight and stack the predictions of ``keys`` (directed edges)."""
    n = len(shapes)
    idx = [sample_index(h, w, stride) for h, w in shapes]
    counts = [len(r) * len(c) for r, c in idx]
    P = max(counts)
    uv = torch.zeros(n, P, 2, dtype=dtype)
    pix_valid = torch.zeros(n, P, dtype=torch.bool)
    for k, (rows, cols) in enumerate(idx):
        vv, uu = torch.meshgrid(rows.to(dtype), cols.to(dtype), indexing="ij")
        uv[k, :counts[k]] = torch.stack([uu, vv], -1).reshape(-1, 2)
        pix_valid[k, :counts[k]] = True
    E = len(keys)
    pred_i = torch.zeros(E, P, 3, dtype=dtype)
    pred_j = torch.zeros(E, P, 3, dtype=dtype)
    w_i = torch.zeros(E, P, dtype=dtype)
    w_j = torch.zeros(E, P, dtype=dtype)
    score = torch.zeros(E, dtype=torch.float64)
    for e, (i, j) in enumerate(keys):
        p = preds[(i, j)]
        for img, pts, conf, out_p, out_w in ((i, p.pts1_cam1[0], p.conf1[0], pred_i, w_i),
                                              (j, p.pts2_cam1[0], p.conf2[0], pred_j, w_j)):
            rows, cols = idx[img]
            sub = pts.detach()[rows][:, cols].reshape(-1, 3).to(dtype)
            c = conf.detach()[rows][:, cols].reshape(-1).to(dtype)
            ok = _valid_points(sub) & torch.isfinite(c)
            out_p[e, :counts[img]] = torch.where(ok[:, None], sub, torch.zeros_like(sub))
            out_w[e, :counts[img]] = torch.where(ok, conf_to_weight(c, conf_transform), torch.zeros_like(c))
        # the pair's score (DUSt3R's mean conf1 x mean conf2) counts the pixels whose points alignment can use:
        # a pair with a few usable points and full confidences elsewhere would otherwise lead the spanning tree.
        # A negative confidence counts 0, as it weighs nothing in the pixel weights: a block of them made every
        # score negative and the averaging start gave up ("all weights zero") for the spanning tree
        c1, c2 = (torch.where(torch.isfinite(c) & _valid_points(pts.detach()[0].double()), c.clamp(min=0),
                              torch.zeros_like(c)).mean()
                  for c, pts in ((p.conf1.detach().double()[0], p.pts1_cam1), (p.conf2.detach().double()[0], p.pts2_cam1)))
        score[e] = c1 * c2
    heads = [preds[k].cam2_to_cam1 for k in keys]
    T = None if any(h is None for h in heads) else torch.cat([h.detach().to("cpu", torch.float64) for h in heads])
    return EdgeStack(i=torch.tensor([k[0] for k in keys]), j=torch.tensor([k[1] for k in keys]),
                     pred_i=pred_i, pred_j=pred_j, w_i=w_i, w_j=w_j, uv=uv, pix_valid=pix_valid,
                     score=score, stride=stride, keys=list(keys), T=T)


def drop_empty_edges(stack: EdgeStack, conf_transform: str = "log") -> EdgeStack:
    """Remove edges whose weights are all zero (masked out, or every confidence <= 1 under 'log'), with a
    warning; ``conf_transform`` is the one the weights were made with (named in the messages)."""
    alive = (stack.w_i.sum(1) > 0) & (stack.w_j.sum(1) > 0)
    if bool(alive.all()):
        return stack
    why = (f"no finite points, or every confidence <= 1 under conf_transform={conf_transform!r} "
           "(conf_transform='id' weighs them), or masked out" if conf_transform in ("log", "m1") else
           "confidence <= 0 (masked out) or not finite, or no finite points")
    if not bool(alive.any()):
        raise GraphError(f"every pair has zero weight in view 1 or view 2 ({why}); nothing to align")
    dead = [stack.keys[e] for e in range(stack.num_edges) if not alive[e]]
    warnings.warn(f"{len(dead)} pair(s) have zero weight in a view ({why}) and are ignored: "
                  f"{dead[:8]}{' ...' if len(dead) > 8 else ''}", stacklevel=3)
    keep = alive.nonzero()[:, 0]
    return EdgeStack(i=stack.i[keep], j=stack.j[keep], pred_i=stack.pred_i[keep], pred_j=stack.pred_j[keep],
                     w_i=stack.w_i[keep], w_j=stack.w_j[keep], uv=stack.uv, pix_valid=stack.pix_valid,
                     score=stack.score[keep], stride=stack.stride, keys=[stack.keys[e] for e in keep.tolist()],
                     T=None if stack.T is None else stack.T[keep])


def check_connected(n_images: int, keys: list) -> None:
    """Raise GraphError naming the components if the (undirected) pair graph is not connected."""
    parent = list(range(n_images))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in keys:
        parent[find(i)] = find(j)
    comps: dict[int, list] = {}
    for a in range(n_images):
        comps.setdefault(find(a), []).append(a)
    if len(comps) > 1:
        groups = sorted(comps.values(), key=lambda g: g[0])
        shown = "; ".join(str(g[:10]) + ("..." if len(g) > 10 else "") for g in groups[:5])
        shown += f"; and {len(groups) - 5} more" if len(groups) > 5 else ""
        raise GraphError(f"the pair graph is disconnected: {len(groups)} groups of images share no pair "
                         f"({shown}). Add pairs linking them (e.g. graph='complete' or a larger window).")


def choose_stride(shapes: list[tuple[int, int]], max_opt_pixels: int | None, stride: int | None) -> int:
    """Stride giving at most ``max_opt_pixels`` sampled pixels per image (None/0 = full resolution)."""
    if stride is not None:
        if stride < 1:
            raise ValueError(f"stride expected >= 1, got {stride}")
        return int(stride)
    if not max_opt_pixels:
        return 1
    # the smallest stride that fits, counted as sample_index keeps them (cell centres: a square root of the area
    # ratio is off both ways, e.g. a 176 x 960 map at 1000 pixels kept 1036, an 8 x 78 one at 17 kept 11 of 13)
    sides = set(shapes)
    stride = 1
    while stride < max(max(s) for s in sides) and max(
            len(r) * len(c) for r, c in (sample_index(h, w, stride) for h, w in sides)) > max_opt_pixels:
        stride += 1
    return stride
