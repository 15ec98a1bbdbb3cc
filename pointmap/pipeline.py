"""``reconstruct``: photos -> Reconstruction in one call (load_images -> make_pairs -> predict_pairs ->
global_align -> refine_epipolar [-> refine_matches]), with a cost estimate printed before the long steps start."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pointmap.align.edges import choose_stride, sample_index
from pointmap.align.optimize import AlignConfig, check_cameras, global_align
from pointmap.errors import GraphError, PointmapError, ShapeError, is_int
from pointmap.io.points import check_conf_filter, confidence_mask
from pointmap.reconstruction import to_canvas

# Measured on the 2-core development VM (docs/alignment.md, "Benchmarks"); rough, CPU only.
ALIGN_SECONDS_PER_EDGE_PIXEL_ITER = 6e-8
FUSE_SECONDS_PER_EDGE_PIXEL = 1.2e-7
# info["pipeline"]["seconds"]'s keys, as the report names them
STAGE_NAMES = {"retrieval": "pair retrieval", "inference": "inference", "alignment": "alignment",
               "epipolar": "pose refinement on matches", "sparse": "sparse refinement"}
# Inference: the network's FLOPs (counted by torch on the meta device) at a CPU rate that grows with the width.
# Both anchors measured on 2 threads of the 2-core VM (docs/benchmarks.md): the shipped `small` (256-wide encoder)
# in `reconstruct`, 71 GFLOP/s at 4, 8 and 16 images (bench_pipeline.py, session 39); the official-size
# dust3r_512_dpt (1024-wide), 184 GFLOP/s over 8 images (bench_inference.py, session 2).
CPU_GFLOPS_AT_256 = 71.0
CPU_GFLOPS_WIDTH_EXPONENT = math.log(184.0 / 71.0) / math.log(1024 / 256)
# The pose refinement on matches (refine_epipolar before its depth re-fit): coarse matching and the pose fit, per
# pair and per coarse cell (196 at 224 px); the shipped `small` on 4-16 views of three rendered scenes, 0.030-0.075
# s per pair at 224 px (/tmp measurement of session 41, docs/benchmarks.md's bench_pipeline section).
EPIPOLAR_SECONDS_PER_PAIR_CELL = 0.055 / 196


def auto_graph(n_images: int, sequential: bool = False) -> str:
    """complete up to 12 images (<= 66 pairs); logwin-3 up to 40 (offsets 1, 2, 4: short and long
    range, ~3N pairs); logwin-4 beyond (offsets up to 8, ~4N pairs). ``sequential`` (frames of a video, in
    time order): the same windows without the wrap-around pairs of the last frames with the first."""
    if n_images <= 12:
        return "complete"
    graph = "logwin-3" if n_images <= 40 else "logwin-4"
    return f"{graph}-noncyclic" if sequential else graph


@functools.lru_cache(maxsize=16)
def inference_gflop(cfg, hw: tuple) -> tuple[float, float]:
    """(GFLOP to encode one image, GFLOP to decode one ordered pair and run its heads) of a model of ``cfg`` on
    ``hw`` images, counted by torch's FlopCounterMode on a copy built on the meta device: no weights, no compute
    (about a second for the official-size model)."""
    from torch.utils.flop_counter import FlopCounterMode

    from pointmap.model import PointmapNet

    with torch.device("meta"):
        net = PointmapNet(cfg).requires_grad_(False)
    img = torch.empty(1, 3, *hw, device="meta")
    with FlopCounterMode(display=False) as fc:
        enc = net._encode(img)  # encode() checks the pixel range, which meta tensors do not hold
    per_image = fc.get_total_flops()
    with FlopCounterMode(display=False) as fc:
        net.decode_pair(enc, enc)
    return per_image / 1e9, fc.get_total_flops() / 1e9


def check_stages(epipolar, refine) -> None:
    """PointmapError unless ``epipolar`` is True, False or an ``EpipolarConfig`` and ``refine`` True, False or a
    ``SparseConfig`` (``reconstruct``'s stage arguments, checked before any inference)."""
    from pointmap.align.epipolar import EpipolarConfig
    from pointmap.align.sparse import SparseConfig

    if not isinstance(epipolar, (bool, EpipolarConfig)):
        raise PointmapError(f"epipolar expected True, False or an EpipolarConfig, got {type(epipolar).__name__}")
    if not isinstance(refine, (bool, SparseConfig)):
        raise PointmapError(f"refine expected True, False or a SparseConfig, got {type(refine).__name__}")


def estimate_cost(n_images: int, n_pairs: int, map_hw: tuple, model=None, config: AlignConfig | None = None,
                  device: str = "cpu", epipolar=False, refine=False, retrieval: bool = False) -> dict:
    """Rough time (s) and peak memory (GB) of inference and alignment, before running them. ``model``: anything
    with a ``cfg`` (a PointmapNet or an ONNX export; None: the official-size dust3r_512_dpt). Inference counts
    each image encoded once and each pair decoded in both orders, as ``predict_pairs`` runs them, at a CPU rate
    measured on 2 threads. ``epipolar``: False, True or an ``EpipolarConfig``, as ``reconstruct`` takes it; for a
    model with descriptors, the alignment time then includes the pose refinement on matches (per pair and coarse
    cell) and its depth re-fit (a second dense alignment, unless the config's ``refit_depth`` is off).
    ``retrieval`` (the ``retrieval-K`` graph): inference also counts its similarity, every image pair's patch tokens
    compared (``image_similarity``; the images are encoded once, for the similarity and the pairs alike).
    Memory counts the predictions ``reconstruct`` keeps (``predictions_gb``: both pointmaps and confidences of every
    directed pair in float32, and, for a model with descriptors when ``epipolar`` or ``refine`` will match on
    them, both descriptor maps and their confidences: 2 x (desc_dim + 1) more floats per pixel, 6x the pointmaps'
    share at MASt3R's desc_dim 24), the alignment's subsampled stack and its chunked work, and the images."""
    from pointmap.align.epipolar import EpipolarConfig
    from pointmap.model import PRESETS, ModelConfig

    check_stages(epipolar, refine)
    if not (is_int(n_images) and n_images >= 1 and is_int(n_pairs) and n_pairs >= 0):
        raise PointmapError(f"estimate_cost expected n_images >= 1 and n_pairs >= 0 (integers), got {n_images!r} "
                            f"and {n_pairs!r}")
    if not (isinstance(map_hw, (tuple, list)) and len(map_hw) == 2 and all(is_int(x) and x >= 1 for x in map_hw)):
        raise ShapeError(f"map_hw expected (height, width) in pixels, two integers >= 1, got {map_hw!r}")
    if config is not None and not isinstance(config, AlignConfig):
        raise PointmapError(f"estimate_cost expected config an AlignConfig (or None), got {type(config).__name__}")
    cfg = config or AlignConfig()
    h, w = map_hw
    E = 2 * n_pairs
    P = h * w
    rows, cols = sample_index(h, w, choose_stride([map_hw], cfg.max_opt_pixels, cfg.stride))
    P_opt = len(rows) * len(cols)
    arch = getattr(model, "cfg", None)
    arch = arch if isinstance(arch, ModelConfig) else PRESETS["dust3r_512_dpt"]
    p = arch.patch_size
    per_image, per_pair = inference_gflop(arch, (max(p, h // p * p), max(p, w // p * p)))
    rate = CPU_GFLOPS_AT_256 * (arch.enc_dim / 256) ** CPU_GFLOPS_WIDTH_EXPONENT
    if str(device).startswith("cuda"):
        rate *= 100.0
    gflop = n_images * per_image + 2 * n_pairs * per_pair
    if retrieval:  # T x T token products of D per image pair (the encodings are shared with the pairs)
        tokens = max(1, h // p) * max(1, w // p)
        gflop += 2 * tokens * tokens * arch.enc_dim * n_images * (n_images - 1) / 2 / 1e9
    infer_s = gflop / rate
    dense_s = (ALIGN_SECONDS_PER_EDGE_PIXEL_ITER * E * P_opt * cfg.niter
               + FUSE_SECONDS_PER_EDGE_PIXEL * E * P * (1 + cfg.fuse_iters))
    align_s = dense_s
    if epipolar and arch.desc_dim > 0:  # refine_epipolar skips a model without descriptors
        ecfg = epipolar if isinstance(epipolar, EpipolarConfig) else EpipolarConfig(patch=p)
        align_s += EPIPOLAR_SECONDS_PER_PAIR_CELL * n_pairs * max(1, h // ecfg.patch) * max(1, w // ecfg.patch)
        align_s += dense_s if ecfg.refit_depth else 0.0
    kept = 8 + (2 * (arch.desc_dim + 1) if arch.desc_dim > 0 and (epipolar or refine) else 0)
    preds_bytes = E * P * 4 * kept         # two pointmaps + two confidences (+ descriptors), float32
    stack_bytes = E * P_opt * 4 * 8
    chunk_bytes = min(cfg.max_chunk_pixels, E * P_opt) * 4 * 40
    return {"pairs": n_pairs, "directed_edges": E, "inference_seconds": infer_s,
            "align_seconds": align_s,
            "predictions_gb": preds_bytes / 1e9,
            "memory_gb": (preds_bytes + stack_bytes + chunk_bytes + n_images * P * 200) / 1e9}


def masks_to_maps(masks, views) -> list:
    """Per-image masks (True = keep) at the ORIGINAL size (H, W) or at the map size -> one [h, w] bool map per
    image, at its own map size."""
    from pointmap.align.inputs import as_mask

    if not hasattr(masks, "__len__") or isinstance(masks, (str, bytes)):
        raise ShapeError(f"masks expected a list of per-image masks, got {type(masks).__name__}")
    if isinstance(masks, dict):  # iterated, a dict gives its keys: each image index read as a mask
        raise ShapeError("masks expected a list of per-image masks, got dict (one mask per image, in the images' "
                         "order; K and cam2world are the ones keyed by image index)")
    if len(masks) != len(views):
        raise ShapeError(f"masks expected one per image ({len(views)}), got {len(masks)}")
    out = []
    for k, (m, v) in enumerate(zip(masks, views)):
        m = as_mask(m, f"mask {k}")
        h, w = v.shape
        W, H = v.original_size
        if tuple(m.shape) == (h, w):
            out.append(m)
            continue
        if tuple(m.shape) != (H, W):
            got = f"{m.shape[1]}x{m.shape[0]}" if m.ndim == 2 else f"an array of shape {list(m.shape)} (one channel " \
                "[H, W] expected)"
            raise ShapeError(f"mask {k} (of image {v.name}) expected the image's original size {W}x{H} or the "
                             f"network's map size {w}x{h} (width x height), got {got}")
        sx, sy, left, top = v.map_from_original
        u = ((torch.arange(w) + 0.5 + left) / sx - 0.5).round().long().clamp(0, W - 1)
        vv = ((torch.arange(h) + 0.5 + top) / sy - 0.5).round().long().clamp(0, H - 1)
        out.append(m[vv][:, u])
    empty = [k for k, m in enumerate(out) if not bool(m.any())]
    if empty:  # refused before inference: every pair of such an image would be dropped, the graph then split
        raise ShapeError(f"mask(s) of image(s) {', '.join(views[k].name or str(k) for k in empty)} keep no pixel of "
                         f"the network's view (the crop it sees): nothing of those images could be reconstructed")
    return out


def check_known_inputs(views, K, cam2world, pose_mask, shared_focal) -> None:
    """What ``global_align`` would refuse about the known intrinsics and poses, and ``shared_focal``'s
    preconditions, checked on the prepared views before any pair is inferred."""
    import warnings

    from pointmap.align.inputs import camera_index, parse_known_K, parse_known_poses, parse_views

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # duplicate names or images: global_align warns once, later
        info = parse_views(views)
    _, K_known, fx, *_ = parse_known_K(K, len(views), info)
    parse_known_poses(cam2world, len(views), pose_mask)
    check_cameras(camera_index(shared_focal, len(views)), info.original_sizes, info.map_from_original, K_known, fx)


def reconstruct(model, paths_or_arrays, graph="auto", *, size: int | None = None, batch_size: int = 8,
                K=None, cam2world=None, pose_mask=None, masks=None, min_conf: float | None = None,
                conf_percentile: float | None = None, align: AlignConfig | None = None, refine=False,
                epipolar=True, quiet: bool = False, device: str = "cpu", cache=None, whole: bool = False):
    """Photos to a Reconstruction.

    graph: "auto" (see ``auto_graph``), any ``make_pairs`` name ("complete", "swin-3", "logwin-3", ...), or
        "retrieval-K": each image with the K others most alike by their encoder tokens (``image_similarity``: the
        share that are mutual nearest neighbours), plus the spanning tree that keeps the graph connected
        (``pairs_from_similarity``; for photos in no particular order), or a list / [M, 2] array of (i, j) image
        index pairs (``pairs_from_list``: connected; recorded as the graph "given")
    size: network input size (``load_images``); None: the size the model was trained at (512 when unknown).
        Images of different sizes or orientations (portrait among landscape) are each resized and cropped by
        ``load_images``'s rule (at 224 a centred square; at 512 their own aspect's crop), each pair is inferred at
        its images' own shapes, and the Reconstruction holds the views on one canvas (``recon.map_sizes``; the
        padding is never a point)
    whole: every photograph at its own shape, even at 224 (``load_images(whole=True)``: the long side to ``size``,
        224 x 160 for a 4:3 landscape, instead of the square crop that drops a quarter of it); recorded, so that
        ``pointmap.localization`` prepares new photographs alike
    K / cam2world / pose_mask: known intrinsics (ORIGINAL pixels) / poses, as ``global_align`` takes them
    masks: optional per-image bool masks (True = keep), original or map size; masked pixels are left
        out of the alignment and of the exports
    min_conf / conf_percentile: confidence filter of the output points (absolute raw confidence, and/or
        keep conf >= that percentile); stored in ``recon.masks`` and applied by ``recon.save``
    epipolar: True (default), False or an ``EpipolarConfig``: poses refined on the model's coarse matches after
        alignment, then the depths re-fitted with them held (``pointmap.align.epipolar``; models with descriptors:
        on 1,008 held-out camera pairs of v26a, the model shipped in session 30, RRA@15 / RTA@15 55.8 / 10.6 ->
        58.7 / 15.7%, docs/alignment.md)
    refine: False, True or a ``SparseConfig``: second stage on reciprocal matches (needs descriptors
        or pointmaps; uses ``pm.match``)
    cache: a directory (or a ``pointmap.cache.PredictionCache``) where pair predictions are kept: a run with the
        same model and input pixels reads them instead of running the network (``predict_pairs``), e.g. to align
        again with other settings or after adding images; the counts are in ``info["pipeline"]["cache"]``. The
        model's weights are hashed once, at the start: do not change them from another thread during the run
    """
    from pointmap.checkpoint import model_input_size
    from pointmap.errors import ShapeError, check_model_device, is_int
    from pointmap.images import load_images
    from pointmap.inference import predict_pairs
    from pointmap.pairs import make_pairs, parse_graph

    # a name refused before any image is read (a pair list is checked against N once the images are counted)
    kind, graph_k, _ = parse_graph(graph, auto=True) if isinstance(graph, str) else (None, None, None)
    if align is not None and not isinstance(align, AlignConfig):
        raise PointmapError(f"align expected an AlignConfig (or None), got {type(align).__name__}")
    check_stages(epipolar, refine)
    if not isinstance(quiet, bool):  # AlignConfig refused it as its own field, or a given one's quiet=True hid it
        raise PointmapError(f"reconstruct expected quiet True or False, got {quiet!r}")
    device = check_model_device(model, device, "reconstruct")  # a missing GPU refused before any image is read
    if not (is_int(batch_size) and batch_size >= 1):
        raise ShapeError(f"batch_size expected an int >= 1, got {batch_size!r}")
    check_conf_filter(min_conf, conf_percentile)
    if cache is not None:  # the path checked and the model fingerprinted before any image is read
        from pointmap.cache import PredictionCache

        if isinstance(cache, PredictionCache):
            cache.check(model)
        else:
            cache = PredictionCache(cache, model)
        counts = cache.hits, cache.misses  # this run's are the difference (a cache may serve many runs)
    if not isinstance(paths_or_arrays, (str, Path, np.ndarray)) and hasattr(paths_or_arrays, "__iter__"):
        paths_or_arrays = list(paths_or_arrays)  # an iterator is read twice: the images, then their sources
    # quiet=True silences a given AlignConfig's progress too (it printed 44 lines under quiet=True)
    cfg = AlignConfig(quiet=quiet) if align is None else dataclasses.replace(align, quiet=align.quiet or quiet)
    size = model_input_size(model) if size is None else size
    views = load_images(paths_or_arrays, size=size, whole=whole)
    n = len(views)
    if n < 2:
        raise GraphError(f"reconstruct needs at least 2 images, got {n}")
    check_known_inputs(views, K, cam2world, pose_mask, cfg.shared_focal)  # refused now, not after inference
    from pointmap.align.epipolar import EpipolarConfig

    user_masks = masks_to_maps(masks, views) if masks is not None else None  # refused now, not after inference
    seconds = {}  # each stage's measured wall time, beside the estimate
    clock = time.perf_counter()

    def lap(stage):
        nonlocal clock
        now = time.perf_counter()
        seconds[stage] = round(now - clock, 3)
        clock = now

    retrieval = kind == "retrieval"
    encodings = None  # the retrieval's, reused by predict_pairs
    if not isinstance(graph, str):  # the caller's own pairs (e.g. an external retrieval's)
        from pointmap.pairs import pairs_from_list

        pairs, graph = pairs_from_list(n, graph), "given"
    elif retrieval:  # pairs by the images' similarity (an unordered photo collection)
        from pointmap.inference import encode_views, image_similarity
        from pointmap.pairs import pairs_from_similarity

        # each image encoded once: the similarity's tokens are the ones predict_pairs decodes
        encodings = encode_views(model, [v.img for v in views], batch_size, device)
        pairs = pairs_from_similarity(image_similarity(model, views, encodings=encodings), graph_k)
        lap("retrieval")
    else:
        graph = auto_graph(n) if graph == "auto" else graph
        pairs = make_pairs(n, graph)
    largest = max((v.shape for v in views), key=lambda hw: hw[0] * hw[1])  # images of several sizes: the upper bound
    cost = estimate_cost(n, len(pairs), largest, model, cfg, device, epipolar, refine, retrieval)
    # descriptors are kept only for the stages that match on them (6x the pointmaps' memory at MASt3R's desc_dim 24)
    keep_desc = bool(epipolar) or bool(refine)
    if cache is not None:  # pairs already on disk cost a read, not the network: the estimate says so
        from pointmap.inference import directed, wants_desc

        cached = cache.present([v.img for v in views], directed(pairs), desc=wants_desc(model, keep_desc))
        cost["cached_pairs"] = cached
        cost["inference_seconds"] *= 1 - cached / (2 * len(pairs))
    if not quiet:
        hits = f" ({cost['cached_pairs']} of {2 * len(pairs)} directed pairs in the cache)" if cache is not None else ""
        print(f"pointmap: {n} images, graph {graph}: {len(pairs)} pairs; estimated inference "
              f"~{_fmt_s(cost['inference_seconds'])}{hits}, alignment ~{_fmt_s(cost['align_seconds'])}, "
              f"peak memory ~{cost['memory_gb']:.1f} GB (rough)", file=sys.stderr)
    clock = time.perf_counter()  # the inference's lap starts here, after the estimate was printed
    with contextlib.nullcontext() if cache is None else cache._vouched(model):  # checked above: hashed once
        preds = predict_pairs(model, views, pairs, batch_size=batch_size, device=device, quiet=quiet,
                              keep_desc=keep_desc, encodings=encodings, cache=cache)
    del encodings
    lap("inference")
    if user_masks is not None:
        preds = {(i, j): _mask_pred(p, user_masks[i], user_masks[j]) for (i, j), p in preds.items()}
    recon = global_align(views, preds, K=K, cam2world=cam2world, config=cfg, pose_mask=pose_mask)
    lap("alignment")
    if epipolar:
        from pointmap.align.epipolar import refine_epipolar

        ecfg = epipolar if isinstance(epipolar, EpipolarConfig) else \
            EpipolarConfig(patch=int(getattr(getattr(model, "cfg", None), "patch_size", 16)))
        recon = refine_epipolar(views, preds, recon, config=ecfg, align=cfg)
        lap("epipolar")
        rep = recon.info["epipolar"]
        if not quiet:
            if rep["applied"]:
                refit = "depths re-fitted to them" if "align_refit" in recon.info else "depths as aligned"
                note = f"{rep['matches']} matches, {rep['inliers_before']} -> {rep['inliers_after']} within the " \
                       f"threshold; {refit}"
            else:
                note = f"skipped: {rep['reason']}"
            print(f"pointmap: poses refined on the model's matches ({note})", file=sys.stderr)
    if refine:
        from pointmap.align.sparse import SparseConfig, refine_matches
        from pointmap.matching import match

        scfg = refine if isinstance(refine, SparseConfig) else SparseConfig(quiet=quiet)
        matches = {}
        for i, j in pairs:
            m = match(preds[(i, j)])
            matches[(i, j)] = m
        # the known poses and intrinsics stay as given, a shared focal as aligned (refine_matches' defaults: the
        # sparse stage's per-image focal factors would split it)
        recon = refine_matches(recon, matches, config=scfg)
        lap("sparse")
    # the percentile is taken over the pixels the user's masks keep (masked pixels, confidence 0, would drag it
    # down), on the views' own pixels (not a canvas's padding)
    within = recon.regions
    if user_masks is not None:
        within = within & to_canvas(user_masks, fill=False)[0]
    keep = confidence_mask(recon.conf, min_conf, conf_percentile, within=within)
    if not keep.any() and within.any():
        import warnings

        c = recon.conf[within & torch.isfinite(recon.conf)]
        span = f"{c.min().item():.3g} to {c.max().item():.3g}" if c.numel() else "none finite"
        warnings.warn(f"reconstruct: the confidence filter (min_conf={min_conf}, conf_percentile={conf_percentile}) "
                      f"keeps none of the {int(within.sum())} pixels (their confidences: {span}); the poses stand, the "
                      f"point cloud is empty: lower min_conf", stacklevel=2)
    recon.masks = keep
    # the photographs' files (None for arrays): the COLMAP export copies them beside its model
    recon.info["sources"] = [str(Path(src).resolve()) if isinstance(src, (str, Path)) else None
                             for src in paths_or_arrays]
    recon.info["pipeline"] = {"size": size, "whole": whole, "graph": graph, "pairs": len(pairs), "pair_list": [list(p) for p in pairs],
                              "estimate": cost, "min_conf": min_conf,
                              "conf_percentile": conf_percentile, "refined": bool(refine),
                              "epipolar": bool(recon.info.get("epipolar", {}).get("applied", False)),
                              "seconds": seconds,
                              "cache": None if cache is None else {"dir": str(cache.dir),
                                                                   "hits": cache.hits - counts[0],
                                                                   "misses": cache.misses - counts[1]}}
    if not quiet:
        print("pointmap: took " + ", ".join(f"{STAGE_NAMES[k]} {_fmt_s(v)}" for k, v in seconds.items()),
              file=sys.stderr)
    return recon


def _mask_pred(pred, m1, m2):
    from dataclasses import replace

    masked = dict(conf1=pred.conf1 * m1[None].to(pred.conf1.dtype), conf2=pred.conf2 * m2[None].to(pred.conf2.dtype))
    if pred.desc_conf1 is not None:  # matching (``refine``) weighs by the descriptor confidence
        masked.update(desc_conf1=pred.desc_conf1 * m1[None].to(pred.desc_conf1.dtype),
                      desc_conf2=pred.desc_conf2 * m2[None].to(pred.desc_conf2.dtype))
    return replace(pred, **masked)


def _fmt_s(s: float) -> str:
    return f"{s:.1f} s" if s < 10 else f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"
