"""Reciprocal nearest-neighbour matching on descriptors (MASt3R) or pointmaps (DUSt3R).

``reciprocal_nn_bruteforce`` is the obviously-correct reference (all mutual nearest neighbours);
``reciprocal_nn_fast`` iterates forward/backward NN from a subsampled grid of seeds and keeps the seeds
that reach a fixed point, which are exactly mutual NN pairs: its result is a subset of the reference,
and equals it when every pixel is a seed (tested), up to float32 rounding of near-tied distances (the fast
path works in float32, the reference in float64; ``match`` centres pointmaps first so that L2 distances
between far-from-origin points do not lose their digits to the squared norms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pointmap.errors import ShapeError, is_int, is_number
from pointmap.prediction import PairPrediction, check_prediction


@dataclass
class Matches:
    """xy1 [M, 2], xy2 [M, 2] pixel coordinates (u, v) in view 1 / view 2; score [M] (higher is better)."""

    xy1: torch.Tensor
    xy2: torch.Tensor
    score: torch.Tensor

    def __len__(self) -> int:
        return int(self.xy1.shape[0])


# similarity entries computed at once (128 MB in float32): a block of query rows against the whole other view. A
# fixed 4,096 rows took 3.2 GB against a 512 x 384 view and could not be allocated at size 1024
BLOCK_ENTRIES = 2 ** 25


def block_rows(n_db: int, chunk: int | None = None) -> int:
    """Query rows per similarity block against ``n_db`` rows: ``chunk`` when given, else as many as keep a block
    within ``BLOCK_ENTRIES`` (at least one)."""
    return chunk if chunk is not None else max(1, BLOCK_ENTRIES // max(1, n_db))


def nearest(query: torch.Tensor, db: torch.Tensor, metric: str, chunk: int | None = None) -> torch.Tensor:
    """Index in ``db`` [N, D] of the nearest neighbour of each ``query`` [M, D] row, computed in blocks of
    ``chunk`` rows (default: ``block_rows``).

    metric 'dot': largest dot product (unit descriptors); 'l2': smallest Euclidean distance.
    """
    out = torch.empty(query.shape[0], dtype=torch.long, device=query.device)
    db_sq = (db * db).sum(-1) if metric == "l2" else None
    chunk = block_rows(db.shape[0], chunk)
    for s in range(0, query.shape[0], chunk):
        q = query[s: s + chunk]
        sim = q @ db.T
        if metric == "l2":
            sim = 2 * sim - db_sq  # argmax of -(|q|^2 - 2 q.d + |d|^2)
        out[s: s + chunk] = sim.argmax(-1)
    return out


def reciprocal_nn_bruteforce(f1: torch.Tensor, f2: torch.Tensor, metric: str = "dot", chunk: int | None = None):
    """All mutual nearest neighbours between f1 [N1, D] and f2 [N2, D]: (idx1 [M], idx2 [M]), sorted by idx1.

    Exhaustive in float64 (row blocks of ``chunk`` rows, default ``block_rows``, only bound the memory).
    """
    a, b = f1.double(), f2.double()

    def best(q, db):
        out = torch.empty(q.shape[0], dtype=torch.long, device=q.device)
        rows = block_rows(db.shape[0], chunk)
        for s in range(0, q.shape[0], rows):
            sim = q[s: s + rows] @ db.T if metric == "dot" else -torch.cdist(q[s: s + rows], db)
            out[s: s + rows] = sim.argmax(1)
        return out

    nn12, nn21 = best(a, b), best(b, a)
    idx1 = torch.arange(f1.shape[0], device=f1.device)
    keep = nn21[nn12] == idx1
    return idx1[keep], nn12[keep]


def reciprocal_nn_fast(f1: torch.Tensor, f2: torch.Tensor, seeds: torch.Tensor, metric: str = "dot",
                       max_iter: int = 10):
    """Mutual NN pairs reached from ``seeds`` (indices into f1) within ``max_iter`` round trips."""
    cur = seeds.clone()
    done1, done2 = [], []
    for _ in range(max_iter):
        if cur.numel() == 0:
            break
        fwd = nearest(f1[cur], f2, metric)
        back = nearest(f2[fwd], f1, metric)
        conv = back == cur
        done1.append(cur[conv])
        done2.append(fwd[conv])
        cur = torch.unique(back[~conv])
    if not done1:
        return seeds[:0], seeds[:0]
    i1, i2 = torch.cat(done1), torch.cat(done2)
    key = torch.unique(i1 * f2.shape[0] + i2)  # deduplicate, sorted by idx1
    return key // f2.shape[0], key % f2.shape[0]


def match(pred: PairPrediction, *, subsample: int = 8, max_iter: int = 10, use: str = "auto",
          min_conf: float | None = None, border: int = 0, bruteforce: bool = False) -> Matches:
    """Reciprocal matches between the two views of a single-pair prediction (batch size 1).

    use: 'desc' (descriptors, dot product), 'pts' (pointmaps in view 1's frame, L2), or 'auto'
    (descriptors when the model has them). subsample: seed grid step of the fast path (1 seeds every
    pixel). min_conf drops pixels whose confidence is below it; border drops matches that close to the
    image border. Score: sqrt(conf1 * conf2) of the matched pixels (descriptor confidences for 'desc').
    """
    check_prediction(pred)
    if pred.batch_size != 1:
        raise ShapeError(f"match expects a single pair (batch size 1), got batch size {pred.batch_size}; "
                         f"use pred[i] to pick one")
    for name, v, low in (("subsample", subsample, 1), ("max_iter", max_iter, 1), ("border", border, 0)):
        if not (is_int(v) and v >= low):
            raise ShapeError(f"match: {name} expected an int >= {low}, got {v!r}")
    if min_conf is not None and not (is_number(min_conf) and math.isfinite(min_conf)):
        raise ShapeError(f"match: min_conf expected a finite number or None, got {min_conf!r}")
    if use == "auto":
        use = "desc" if pred.has_desc else "pts"
    if use == "desc" and not pred.has_desc:
        raise ShapeError("use='desc' needs a model with a descriptor head (MASt3R-style); use 'pts'")
    if use not in ("desc", "pts"):
        raise ShapeError(f"use expected 'auto', 'desc' or 'pts', got {use!r}")
    if use == "desc":
        m1, m2, c1, c2, metric = pred.desc1[0], pred.desc2[0], pred.desc_conf1[0], pred.desc_conf2[0], "dot"
    else:
        m1, m2, c1, c2, metric = pred.pts1_cam1[0], pred.pts2_cam1[0], pred.conf1[0], pred.conf2[0], "l2"
    H1, W1, _ = m1.shape
    H2, W2, _ = m2.shape
    f1, f2 = m1.reshape(-1, m1.shape[-1]).float(), m2.reshape(-1, m2.shape[-1]).float()
    valid1 = torch.isfinite(f1).all(-1)
    valid2 = torch.isfinite(f2).all(-1)
    if min_conf is not None:
        valid1 &= c1.reshape(-1) >= min_conf
        valid2 &= c2.reshape(-1) >= min_conf
    ids1, ids2 = valid1.nonzero()[:, 0], valid2.nonzero()[:, 0]
    g1, g2 = f1[ids1], f2[ids2]
    if g1.shape[0] == 0 or g2.shape[0] == 0:
        empty = torch.zeros(0, 2, device=f1.device)
        return Matches(empty, empty.clone(), torch.zeros(0, device=f1.device))
    if metric == "l2":  # distances do not change with a common shift; the fast path's float32 keeps its digits
        centre = torch.cat([g1, g2]).mean(0)
        g1, g2 = g1 - centre, g2 - centre
    if bruteforce:
        a, b = reciprocal_nn_bruteforce(g1, g2, metric)
    else:
        s = max(int(subsample), 1)
        dev = f1.device
        # half a step in from the corner, but inside a map narrower than that (else it would have no seed at all)
        ys, xs = torch.meshgrid(torch.arange(min(s // 2, H1 - 1), H1, s, device=dev),
                                torch.arange(min(s // 2, W1 - 1), W1, s, device=dev), indexing="ij")
        seed_pix = (ys * W1 + xs).reshape(-1)
        lookup = torch.full((H1 * W1,), -1, dtype=torch.long, device=dev)
        lookup[ids1] = torch.arange(ids1.numel(), device=dev)
        seeds = lookup[seed_pix]
        a, b = reciprocal_nn_fast(g1, g2, seeds[seeds >= 0], metric, max_iter)
    p1, p2 = ids1[a], ids2[b]
    xy1 = torch.stack([p1 % W1, p1 // W1], -1).float()
    xy2 = torch.stack([p2 % W2, p2 // W2], -1).float()
    score = (c1.reshape(-1)[p1].float() * c2.reshape(-1)[p2].float()).sqrt()
    if border > 0:
        ok = ((xy1[:, 0] >= border) & (xy1[:, 0] < W1 - border) & (xy1[:, 1] >= border) & (xy1[:, 1] < H1 - border)
              & (xy2[:, 0] >= border) & (xy2[:, 0] < W2 - border) & (xy2[:, 1] >= border) & (xy2[:, 1] < H2 - border))
        xy1, xy2, score = xy1[ok], xy2[ok], score[ok]
    return Matches(xy1, xy2, score)


def cell_descriptors(desc: torch.Tensor, patch: int) -> torch.Tensor:
    """[B, H, W, D] pixel descriptors -> [B, H/patch * W/patch, D] unit cell descriptors (row-major cells):
    the mean over each ``patch`` x ``patch`` cell, re-normalised. H and W must be multiples of ``patch``."""
    f = torch.nn.functional.avg_pool2d(desc.float().permute(0, 3, 1, 2), patch)
    return torch.nn.functional.normalize(f.flatten(2).transpose(1, 2), dim=-1)


def match_coarse(pred: PairPrediction, patch: int = 16, refine: bool = True) -> Matches:
    """Reciprocal matches between patch cells (batch size 1): descriptors averaged over each ``patch`` x
    ``patch`` cell and re-normalised, mutual nearest neighbours by dot product (all cells, brute force).

    Coarse to fine: xy1 is the centre pixel (``patch // 2``) of a view-1 cell; xy2 is the centre pixel of the
    matched view-2 cell (the same ``patch // 2`` offset), or with ``refine`` the pixel whose descriptor best matches
    xy1's within that cell grown by half a cell on each side (cell centres alone cap PnP at a few degrees). Score: sqrt of the two cells' mean
    descriptor confidences. Coarser than ``match`` (one match per cell at most) but robust when pixel
    descriptors are not yet distinctive: the cell descriptor is what the coarse matching loss
    (training.losses.patch_matching_loss) trains.
    """
    check_prediction(pred)
    if pred.batch_size != 1:
        raise ShapeError(f"match_coarse expects a single pair (batch size 1), got batch size {pred.batch_size}")
    if not pred.has_desc:
        raise ShapeError("match_coarse needs a model with a descriptor head (MASt3R-style)")
    if not is_int(patch):
        raise ShapeError(f"match_coarse: patch expected an int >= 1, got {patch!r}")
    d1, d2 = pred.desc1[0].float(), pred.desc2[0].float()
    (H1, W1), (H2, W2) = d1.shape[:2], d2.shape[:2]
    if patch < 1 or H1 % patch or W1 % patch or H2 % patch or W2 % patch:
        raise ShapeError(f"descriptor maps {H1}x{W1} and {H2}x{W2} must be multiples of patch={patch}")

    w1, w2 = W1 // patch, W2 // patch
    f1, f2 = cell_descriptors(d1[None], patch)[0], cell_descriptors(d2[None], patch)[0]
    s1 = torch.nn.functional.avg_pool2d(pred.desc_conf1.float()[:, None], patch).reshape(-1)  # mean confidences
    s2 = torch.nn.functional.avg_pool2d(pred.desc_conf2.float()[:, None], patch).reshape(-1)
    ok1, ok2 = torch.isfinite(f1).all(-1).nonzero()[:, 0], torch.isfinite(f2).all(-1).nonzero()[:, 0]
    if ok1.numel() == 0 or ok2.numel() == 0:
        empty = torch.zeros(0, 2)
        return Matches(empty, empty.clone(), torch.zeros(0))
    a, b = reciprocal_nn_bruteforce(f1[ok1], f2[ok2], "dot")
    c1, c2 = ok1[a], ok2[b]

    xy1 = torch.stack([(c1 % w1) * patch, (c1 // w1) * patch], -1) + patch // 2
    xy2 = (torch.stack([(c2 % w2) * patch, (c2 // w2) * patch], -1) + patch // 2).float()
    if refine:
        xy2 = _refine_in_cells(d1[xy1[:, 1], xy1[:, 0]], d2, c2, w2, patch)
    return Matches(xy1.float(), xy2, (s1[c1] * s2[c2]).clamp_min(0).sqrt())


def _refine_in_cells(q: torch.Tensor, d2: torch.Tensor, cells: torch.Tensor, w2: int, patch: int) -> torch.Tensor:
    """For each query descriptor q[k] [M, D], the pixel (u, v) of d2 [H, W, D] with the highest dot product in
    view-2 cell ``cells[k]`` grown by patch // 2 on each side (clipped to the image), among its finite pixels."""
    H, W = d2.shape[:2]
    half = patch // 2
    off = torch.arange(-half, patch + half)
    top, left = (cells // w2) * patch, (cells % w2) * patch
    rows = (top[:, None] + off).clamp(0, H - 1)   # [M, S]
    cols = (left[:, None] + off).clamp(0, W - 1)  # [M, S]
    win = d2[rows[:, :, None], cols[:, None, :]]  # [M, S, S, D]
    sim = (win * q[:, None, None, :]).sum(-1).flatten(1)  # [M, S*S]
    # a non-finite pixel of a neighbouring cell in the grown window never wins (the cell's own are finite)
    sim = sim.masked_fill(~torch.isfinite(win).all(-1).flatten(1), -math.inf)
    best = sim.argmax(1)
    S = off.numel()
    r, c = best // S, best % S
    ar = torch.arange(len(cells))
    return torch.stack([cols[ar, c], rows[ar, r]], -1).float()
