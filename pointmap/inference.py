"""Pair inference over many images: each image is encoded ONCE, decoders and heads run batched per pair.

``predict_pairs`` returns both orders of every pair, as global alignment expects.
"""

from __future__ import annotations

import logging
import sys
from collections import defaultdict
from dataclasses import replace

import torch
from tqdm.auto import tqdm

from pointmap.errors import CheckpointError, GraphError, ShapeError, check_model_device, is_int
from pointmap.images import View
from pointmap.pairs import checked_index_pairs
from pointmap.prediction import PairPrediction

log = logging.getLogger(__name__)


def _as_images(views) -> list[torch.Tensor]:
    imgs = []
    for k, v in enumerate(views):
        img = v.img if isinstance(v, View) else v
        if not isinstance(img, torch.Tensor) or img.ndim != 3 or img.shape[0] != 3:
            got = list(img.shape) if isinstance(img, torch.Tensor) else type(img).__name__
            raise ShapeError(f"view {k} expected a View or a [3, H, W] tensor, got {got}")
        imgs.append(img)
    return imgs


def directed(pairs) -> list[tuple[int, int]]:
    """Both orders of every pair, deduplicated, in a stable order."""
    out, seen = [], set()
    for i, j in pairs:
        for e in ((i, j), (j, i)):
            if e not in seen:
                seen.add(e)
                out.append(e)
    return out


@torch.inference_mode()
def encode_views(model, imgs: list[torch.Tensor], batch_size: int = 8, device="cpu", progress=None,
                 caller: str = "encode_views") -> list:
    """Run the encoder once per image, batching images of equal shape. Returns one Encoded per image."""
    if not (is_int(batch_size) and batch_size >= 1):  # pooled_tokens and image_similarity pass theirs here
        raise ShapeError(f"{caller}: batch_size expected an int >= 1, got {batch_size!r}")
    device = check_model_device(model, device, caller)
    by_shape = defaultdict(list)
    for k, img in enumerate(imgs):
        by_shape[tuple(img.shape)].append(k)
    encoded: list = [None] * len(imgs)
    for idx in by_shape.values():
        for s in range(0, len(idx), batch_size):
            chunk = idx[s: s + batch_size]
            enc = model.encode(torch.stack([imgs[k] for k in chunk]).to(device))  # encode checks the batch
            for b, k in enumerate(chunk):
                encoded[k] = enc[b: b + 1]
            if progress is not None:
                progress.update(len(chunk))
    return encoded


@torch.inference_mode()
def pooled_tokens(model, views, batch_size: int = 8, device="cpu") -> torch.Tensor:
    """[N, D] unit vectors: each image's mean encoder token, a global descriptor (``localize`` ranks references by
    its cosine; views: Views or [3, H, W] tensors)."""
    enc = _require_tokens(encode_views(model, _as_images(views), batch_size, device, caller="pooled_tokens"),
                          "pooled_tokens (what localize ranks references by when refs is None)",
                          "export with --split, or give localize its refs")
    return torch.nn.functional.normalize(torch.cat([e.tokens.float().mean(1).cpu() for e in enc]), dim=-1)


def _require_tokens(encodings, caller: str, remedy: str = "export with --split, or use another graph"):
    """``encodings`` unchanged unless they are the images a single-graph ONNX export defers to the pair graph
    (tokens [1, 3, H, W]): then CheckpointError naming ``caller``, which needs the encoder's tokens, and ``remedy``."""
    if isinstance(encodings, (list, tuple)) and any(getattr(getattr(e, "tokens", None), "ndim", 3) == 4
                                                    for e in encodings):
        raise CheckpointError(f"{caller} needs the encoder's tokens, which a single-graph ONNX export does not give "
                              f"(it encodes inside each pair): {remedy}")
    return encodings


def _patch(model) -> int | None:
    """The model's patch size (PyTorch or ONNX runtime), None when it does not say."""
    return getattr(getattr(model, "cfg", None), "patch_size", None)


def wants_desc(model, keep_desc: bool) -> bool:
    """Whether predictions of ``model`` are to carry descriptors: asked for (``keep_desc``) and the model has a
    descriptor head (what ``predict_pairs`` reads from its cache)."""
    return bool(keep_desc) and getattr(getattr(model, "cfg", None), "desc_dim", 0) > 0


def checked_encodings(encodings, imgs: list[torch.Tensor], patch: int | None = None) -> list:
    """``encodings`` (``encode_views``'s output for these images, one per image) checked against the images: one
    entry per image, each a batch of one on the patch grid of its image's shape (``patch``: the model's patch size,
    when known). ShapeError (one line) otherwise."""
    if not isinstance(encodings, (list, tuple)) or len(encodings) != len(imgs):
        got = f"{len(encodings)} entries" if isinstance(encodings, (list, tuple)) else type(encodings).__name__
        raise ShapeError(f"encodings expected encode_views's list, one per image ({len(imgs)}), got {got}")
    grids = {}
    for k, (e, img) in enumerate(zip(encodings, imgs)):
        tokens, grid = getattr(e, "tokens", None), getattr(e, "grid", None)
        if not isinstance(tokens, torch.Tensor) or tokens.ndim != 3 or tokens.shape[0] != 1 or grid is None:
            got = list(tokens.shape) if isinstance(tokens, torch.Tensor) else type(e).__name__
            raise ShapeError(f"encodings[{k}] expected one image's encoding (tokens [1, N, D]), got {got}")
        if tokens.shape[1] != grid[0] * grid[1] or grids.setdefault(tuple(img.shape), tuple(grid)) != tuple(grid) \
                or img.shape[1] % grid[0] or img.shape[2] % grid[1] \
                or img.shape[1] // grid[0] != img.shape[2] // grid[1] \
                or patch is not None and img.shape[1] != grid[0] * patch:
            raise ShapeError(f"encodings[{k}] (grid {tuple(grid)}, {tokens.shape[1]} tokens) is not an encoding of "
                             f"image {k} ({list(img.shape)})")
    return list(encodings)


@torch.inference_mode()
def image_similarity(model, views, batch_size: int = 8, device="cpu", *, encodings=None) -> torch.Tensor:
    """[N, N] symmetric share of each pair's encoder patch tokens that are mutual nearest neighbours (cosine), in
    [0, 1], diagonal 1: what the ``retrieval-K`` graph (``pointmap.pairs.pairs_from_similarity``) pairs by. On 24
    rendered views each of a room, a cluster and a courtyard it follows the cameras' viewing angle (Spearman 0.36 /
    0.52 / 0.51) better than the cosine of the mean tokens ``localize`` ranks references by (0.21 / 0.23 / 0.27;
    ``benchmarks/bench_retrieval.py``). Images of different shapes compare too (their token counts differ).
    ``encodings``: ``encode_views``'s output for these views, reused (``predict_pairs`` takes it too, so an image
    is encoded once for both); None: the views are encoded here."""
    imgs = _as_images(views)
    if encodings is None:
        encodings = encode_views(model, imgs, batch_size, device, caller="image_similarity")
    enc = checked_encodings(_require_tokens(encodings, "image_similarity"), imgs, _patch(model))
    toks = [torch.nn.functional.normalize(e.tokens[0].float().cpu(), dim=-1) for e in enc]  # off the GPU
    del enc
    n = len(toks)
    sim = torch.eye(n, dtype=torch.float64)
    for i in range(n):
        for j in range(i + 1, n):
            c = toks[i] @ toks[j].T
            a, b = c.argmax(1), c.argmax(0)
            mutual = int((b[a] == torch.arange(len(a))).sum())
            sim[i, j] = sim[j, i] = mutual / min(len(toks[i]), len(toks[j]))
    return sim


@torch.inference_mode()
def predict_pairs(model, views, pairs, batch_size: int = 8, *, device="cpu", keep_desc: bool = True,
                  store_dtype=None, quiet: bool = False, encodings=None,
                  cache=None) -> dict[tuple[int, int], PairPrediction]:
    """Predict every pair in both orders.

    views: list of View (from ``load_images``) or [3, H, W] tensors in [0, 1]
    pairs: iterable of (i, j), i != j (e.g. ``make_pairs``); (j, i) is added for each
    Returns {(i, j): PairPrediction} with batch size 1 per entry, on the CPU; ``store_dtype``
    (e.g. torch.float16) shrinks what is kept for many images, ``keep_desc=False`` drops descriptors.
    ``encodings``: ``encode_views``'s output for these views (e.g. kept from ``image_similarity``), used instead
    of encoding them again.
    ``cache``: a directory or a ``pointmap.cache.PredictionCache`` (made for this model): pairs found there (same
    weights and network code, same input pixels) are read instead of predicted, the others are predicted and
    written there, with their descriptors; only the images of pairs not found are encoded.
    """
    imgs = _as_images(views)
    n = len(imgs)
    if n < 2:
        raise GraphError(f"predict_pairs needs at least two views (a pair), got {n}")
    pairs = checked_index_pairs(n, pairs if hasattr(pairs, "shape") else list(pairs))  # an [M, 2] array: its rows
    if not pairs:
        raise GraphError("predict_pairs needs at least one pair")
    if not (is_int(batch_size) and batch_size >= 1):
        raise ShapeError(f"batch_size expected an int >= 1, got {batch_size!r}")
    if store_dtype is not None and not (isinstance(store_dtype, torch.dtype) and store_dtype.is_floating_point):
        raise ShapeError(f"store_dtype expected None or a floating torch dtype (e.g. torch.float16), got "
                         f"{store_dtype!r}")
    device = check_model_device(model, device, "predict_pairs")
    given = None if encodings is None else checked_encodings(encodings, imgs, _patch(model))
    out: dict[tuple[int, int], PairPrediction] = {}
    edges = order = directed(pairs)
    if cache is not None:
        from pointmap.cache import PredictionCache

        if isinstance(cache, PredictionCache):
            cache.check(model)  # made for this model's weights
        else:
            cache = PredictionCache(cache, model)
        want_desc = wants_desc(model, keep_desc)
        keys = cache.keys(imgs, edges)
        for i, j in edges:
            pred = cache.get(keys[(i, j)], tuple(imgs[i].shape[1:]), tuple(imgs[j].shape[1:]), want_desc)
            if pred is not None:
                out[(i, j)] = pred.map(lambda t: t.to(store_dtype)) if store_dtype else pred
        if not quiet:
            print(f"pointmap: prediction cache {cache.dir}: {len(out)} of {len(edges)} directed pairs read, "
                  f"{len(edges) - len(out)} to predict", file=sys.stderr)
        edges = [e for e in edges if e not in out]
    used = sorted({k for e in edges for k in e})
    bar = tqdm(total=len(edges) + (len(used) if given is None else 0), desc="inference", unit="img|pair",
               disable=quiet or not edges or None)
    if given is None:
        enc = dict(zip(used, encode_views(model, [imgs[k] for k in used], batch_size, device, progress=bar)))
    else:
        enc = {k: given[k] for k in used}
    groups = defaultdict(list)  # pairs with the same shapes decode in one batch
    for e in edges:
        groups[(tuple(imgs[e[0]].shape), tuple(imgs[e[1]].shape))].append(e)
    for group in groups.values():
        for s in range(0, len(group), batch_size):
            chunk = group[s: s + batch_size]
            e1 = _stack([enc[i] for i, _ in chunk])
            e2 = _stack([enc[j] for _, j in chunk])
            pred = model.decode_pair(e1, e2)
            if cache is not None:  # with descriptors even when not kept here: a later stage may need them
                pred = pred.map(lambda t: t.cpu())
                for b, e in enumerate(chunk):
                    cache.put(keys[e], pred[b])
            if not keep_desc:
                pred = replace(pred, desc1=None, desc2=None, desc_conf1=None, desc_conf2=None)
            pred = pred.map(lambda t: t.cpu())
            for b, e in enumerate(chunk):
                out[e] = pred[b].map(lambda t: t.to(store_dtype)) if store_dtype else pred[b]
            bar.update(len(chunk))
    bar.close()
    return {e: out[e] for e in order}


def _stack(encs: list):
    first = encs[0]
    if hasattr(first, "cat"):
        return first.cat(encs)
    return type(first)(torch.cat([e.tokens for e in encs], dim=0), first.grid)
