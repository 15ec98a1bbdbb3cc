"""New photographs posed in an existing reconstruction's world (relocalisation): the frames of a video between
its keyframes, a photograph taken later, a test view to evaluate novel-view synthesis on.

Each query is paired with reference views of the reconstruction (given, or the most similar by their encoder
tokens); for each pair the network's pointmaps give the query's pose in the reference camera's frame
(``pair_pose``: both passes' pose, the pose head's transforms or Procrustes for models without one, refined on the
model's matches with the reference's K and the query's, known or the focal from its own pointmap), and the
reference's depth
in the reconstruction gives the scale: the pair's view-1 depth is matched to it (median ratio), so the pose
lands in the reconstruction's world and units. The references are tried in order (the most similar first) and
the first that gives a pose is kept: the others are fallbacks. (Confidences are not comparable across pairs:
a view paired with its own reference frame scored lower than with a neighbour on the demo room.)
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from pointmap.errors import GraphError, PointmapError, ShapeError, is_int
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K
from pointmap.images import View, load_images
from pointmap.reconstruction import K_to_map, K_to_original, Reconstruction


@dataclass
class Localization:
    """Poses of M query photographs in a reconstruction's world.

    cam2world: [M, 4, 4] OpenCV camera-to-world in the reconstruction's world and units
    K:         [M, 3, 3] intrinsics in the queries' ORIGINAL pixels (given, or estimated)
    ref:       [M] index of the reconstruction view each pose was found against (-1: not posed; its pose,
               K, conf and scale are then NaN)
    conf:      [M] median confidence of the query's pixels in that pair (low: little shared content)
    scale:     [M] reconstruction units per unit of that pair's prediction (from the reference's depth)
    names:     the queries' names
    """
    cam2world: torch.Tensor
    K: torch.Tensor
    ref: list
    conf: list
    scale: list
    names: list

    def __len__(self) -> int:
        return len(self.names)

    def subset(self, keep: list) -> Localization:
        """The queries at indices ``keep``, in that order; or where ``keep``, len(self) bools, is True."""
        keep = _plain(keep)
        if isinstance(keep, list) and keep and all(isinstance(b, bool) for b in keep):  # a mask, not 0 / 1
            if len(keep) != len(self):
                raise ShapeError(f"subset expected query indices or a mask of {len(self)} bools, "
                                 f"got {len(keep)} bools")
            keep = [k for k, b in enumerate(keep) if b]
        return Localization(self.cam2world[keep], self.K[keep], [self.ref[k] for k in keep],
                            [self.conf[k] for k in keep], [self.scale[k] for k in keep], [self.names[k] for k in keep])


QUERY_CHUNK = 8  # queries predicted together by localize (their pairs' descriptors held in memory)

def reference_views(recon: Reconstruction) -> list[View]:
    """The reconstruction's own network inputs as Views (the pixel grid its depth maps live on)."""
    return [View(img=recon.crop(recon.images, k).permute(2, 0, 1).float().contiguous(), original_size=tuple(recon.original_sizes[k]),
                 map_from_original=tuple(float(x) for x in recon.map_from_original[k]), name=recon.names[k], index=k)
            for k in range(len(recon))]


def query_views(recon: Reconstruction, images) -> list[View]:
    """``images`` prepared for the network as ``recon``'s own were: at the size ``reconstruct`` recorded
    (``info["pipeline"]["size"]``, whole or cropped as ``["whole"]`` says; for a hand-made reconstruction, the long
    side of its maps). Views (from an
    earlier call) are returned as they are."""
    images = list(images)
    if images and all(isinstance(v, View) for v in images):
        return images
    pipeline = recon.info.get("pipeline") or {}
    size = pipeline.get("size") or max(max(s) for s in recon.map_sizes)
    return load_images(images, size=int(size), square_ok=any(vw == vh for vw, vh in recon.map_sizes),
                       whole=bool(pipeline.get("whole", False)))


@torch.inference_mode()
def rank_references(model, refs: list[View], queries: list[View], n_refs: int, *, device="cpu") -> list[list[int]]:
    """For each query, the ``n_refs`` reference indices whose mean encoder token is most similar (cosine)."""
    from pointmap.inference import pooled_tokens

    sim = pooled_tokens(model, queries, device=device) @ pooled_tokens(model, refs, device=device).T
    return sim.topk(min(n_refs, len(refs)), dim=1).indices.tolist()


def depth_scale(recon: Reconstruction, ref: int, pred, min_conf: float = 0.0) -> float:
    """Reconstruction units per prediction unit: the median over the reference's valid pixels of its depth in the
    reconstruction over the pair's view-1 depth (same pixel grid). NaN when fewer than 16 pixels agree."""
    z_pred = pred.pts1_cam1[0, ..., 2].double()
    z_rec = recon.crop(recon.depth_z, ref).double()
    if z_pred.shape != z_rec.shape:
        raise ShapeError(f"the pair's view-1 map is {list(z_pred.shape)} but reference {ref}'s depth is "
                         f"{list(z_rec.shape)}: the reference must be paired at its own network size")
    ok = recon.crop(recon.valid(min_conf), ref) & (z_pred > 0) & torch.isfinite(z_pred)
    if int(ok.sum()) < 16:
        return float("nan")
    return float((z_rec[ok] / z_pred[ok]).median())


def pose_against(recon: Reconstruction, ref: int, pred, pred_reverse, K_map=None, *,
                 patch: int = 16) -> tuple[torch.Tensor, torch.Tensor, float]:
    """(cam2world [4, 4] float64 in the reconstruction's world, K [3, 3] at the query's map resolution, scale) of
    the query seen as view 2 of ``pred`` (reference ``ref`` as view 1) and view 1 of ``pred_reverse``. A pose
    that cannot be found is NaN."""
    from pointmap.geometry.cameras import intrinsics
    from pointmap.pose import focal_from_prediction, pair_pose

    s = depth_scale(recon, ref, pred)
    h, w = pred.pts2_cam1.shape[1:3]
    # the pair's pose as `pointmap pair` gives it, with the reference's intrinsics and the query's when known
    rel = pair_pose(pred, pred_reverse, recon.K_map[ref].double(), K_map, patch=patch)[0].double()
    if K_map is None:
        K_map = intrinsics(float(focal_from_prediction(pred_reverse)[0]), (w - 1) / 2, (h - 1) / 2, dtype=torch.float64)
    rel[:3, 3] *= s
    return recon.cam2world[ref].double() @ rel, K_map.double(), s


def warn_mixed_intrinsics(recon: Reconstruction, query_K_given: bool) -> None:
    """A warning when the queries' intrinsics are of another kind than the reconstruction's (as its alignment
    records them: ``info["align"]["known_K_indices"]``): given for the queries while the reconstruction's focals were
    estimated, or estimated while all of the reconstruction's were given. A query posed with intrinsics of the other
    kind came out worse on held-out scenes (docs/alignment.md, relocalisation: benchmarks/bench_localize.py)."""
    import warnings

    align = recon.info.get("align") if isinstance(recon.info, dict) else None
    known = align.get("known_K_indices") if isinstance(align, dict) else None
    if not isinstance(known, list):  # a hand-made reconstruction: nothing recorded
        return
    if query_K_given and not known:
        warnings.warn("localize: the queries' intrinsics are given but the reconstruction's focals were estimated; "
                      "its world is shaped by their error, and known query intrinsics posed worse in it than the "
                      "queries' own estimates (docs/alignment.md): leave them out, or give the reconstruction its "
                      "intrinsics too", stacklevel=3)
    elif not query_K_given and len(known) == len(recon):
        warnings.warn("localize: the reconstruction was given its intrinsics but the queries' are estimated; give "
                      "theirs too (K; pointmap localize --focal / --cameras): queries posed with estimated focals in "
                      "a reconstruction of known ones came out worse (docs/alignment.md)", stacklevel=3)


def localize(model, recon: Reconstruction, images, refs=None, *, K=None, n_refs: int = 2, device="cpu",
             batch_size: int = 8, quiet: bool = False) -> Localization:
    """Pose the photographs ``images`` (paths or HxWx3 uint8 arrays, or the Views ``query_views`` made of them) in
    ``recon``'s world.

    refs: per query, the reconstruction views to pair it with, in order of preference (e.g. the nearest keyframe
        of a video frame, then the next); default: the ``n_refs`` most similar views by their encoder tokens, the
        most similar first. The first reference whose pair gives a pose is used.
    K: the queries' intrinsics in their ORIGINAL pixels, [3, 3] for all or [M, 3, 3]; default: estimated.
    The queries are prepared at the reconstruction's network size. Raises PointmapError for an empty
    reconstruction or query list, references out of range, wrong K, and when no query can be posed.
    """
    from tqdm import tqdm

    from pointmap.errors import check_model_device
    from pointmap.inference import predict_pairs

    device = check_model_device(model, device, "localize")
    if not isinstance(recon, Reconstruction) or len(recon) == 0:
        raise PointmapError(f"localize expected a Reconstruction with at least one view, got {type(recon).__name__}")
    from pointmap.images import _as_list

    images = list(_as_list(images, "localize"))  # one image (a path, an array) is a list of one, as load_images takes
    if not images:
        raise PointmapError("localize expected a non-empty list of images (paths or arrays)")
    patch = getattr(getattr(model, "cfg", None), "patch_size", 16)
    odd = [f"view {k}: {vw}x{vh}" for k, (vw, vh) in enumerate(recon.map_sizes) if vw % patch or vh % patch]
    if odd:  # the references go through the network at their map size (a hand-made reconstruction's maps, say)
        raise ShapeError(f"localize pairs the queries with the reconstruction's views at their map size, which must "
                         f"be a multiple of the model's patch size {patch}; got {', '.join(odd[:3])}")
    queries = query_views(recon, images)
    m, n = len(queries), len(recon)
    if K is not None:
        try:
            K = torch.as_tensor(K, dtype=torch.float64)
        except (TypeError, ValueError):  # ragged or non-numeric: said with the layout expected
            raise ShapeError(f"K expected [3, 3] or [{m}, 3, 3] intrinsics {K_LAYOUT}, got {K!r}") from None
        one = K.shape == (3, 3)
        K = K.expand(m, 3, 3) if one else K
        if tuple(K.shape) != (m, 3, 3):
            raise ShapeError(f"K expected [3, 3] or [{m}, 3, 3] intrinsics {K_LAYOUT}, "
                             f"finite with positive focals, got {K.tolist() if K.numel() <= 9 else list(K.shape)}")
        bad = (~is_pinhole_K(K)).nonzero().flatten().tolist()
        if bad:  # the right shape: say which query's K is wrong, with its values
            which = "" if one else f"K[{bad[0]}] = "
            more = f" (and the K of queries {bad[1:]})" if len(bad) > 1 and not one else ""
            raise ShapeError(f"K expected [3, 3] or [{m}, 3, 3] intrinsics {K_LAYOUT}, finite with positive focals, "
                             f"got {which}{K[bad[0]].tolist()}{more}")
    warn_mixed_intrinsics(recon, K is not None)
    refs_views = reference_views(recon)
    if refs is None:
        if not (is_int(n_refs) and n_refs >= 1):
            raise PointmapError(f"n_refs expected an int >= 1, got {n_refs!r}")
        refs = rank_references(model, refs_views, queries, n_refs, device=device)
    refs = _plain(refs)
    if is_int(refs):  # one reference for one query, as one image is a list of one
        refs = [refs]
    if not isinstance(refs, (list, tuple)):
        raise GraphError(f"refs expected, for each of the {m} queries, a list of view indices, got {refs!r}")
    refs = [_plain(r) for r in refs]  # e.g. an argmax's 0-d tensors, or a row of a [M, k] array
    refs = [[int(r)] if is_int(r) else [int(k) if is_int(k) else k for k in r]
            if hasattr(r, "__iter__") and not isinstance(r, (str, bytes)) else r for r in refs]
    if len(refs) != m or any(not isinstance(r, list) or not r or any(not is_int(k) or not 0 <= k < n
                                                                     for k in r) for r in refs):
        raise GraphError(f"refs expected, for each of the {m} queries, a non-empty list of view indices in 0..{n - 1}, "
                         f"got {refs}")
    views = refs_views + [replace(q, index=n + k) for k, q in enumerate(queries)]
    out = torch.full((m, 4, 4), float("nan"), dtype=torch.float64)
    K_orig = K.clone() if K is not None else torch.full((m, 3, 3), float("nan"), dtype=torch.float64)
    used, confs, scales = [-1] * m, [float("nan")] * m, [float("nan")] * m
    chunks = range(0, m, QUERY_CHUNK)  # the descriptors pair_pose matches on are kept for a chunk of queries at a time
    for start in tqdm(chunks, desc="localize", unit=f"{QUERY_CHUNK} queries", disable=quiet or len(chunks) == 1 or None):
        chunk = range(start, min(m, start + QUERY_CHUNK))
        pairs = sorted({(r, n + k) for k in chunk for r in refs[k]})
        preds = predict_pairs(model, views, pairs, batch_size, device=device, keep_desc=True,
                              quiet=quiet or m > QUERY_CHUNK)
        for k in chunk:
            mfo = torch.tensor([queries[k].map_from_original], dtype=torch.float64)
            K_map = None if K is None else K_to_map(K[k:k + 1], mfo)[0]
            for r in refs[k]:
                pred, rev = preds[(r, n + k)], preds[(n + k, r)]
                T, Km, s = pose_against(recon, r, pred, rev, K_map, patch=patch)
                if torch.isfinite(T).all() and torch.isfinite(Km).all():
                    out[k], used[k], scales[k] = T, r, s
                    confs[k] = float(pred.conf2[0].float().median())
                    if K is None:  # estimated on the maps: reported in the query's own pixels
                        K_orig[k] = K_to_original(Km[None], mfo)[0]
                    break
    if all(u < 0 for u in used):
        raise PointmapError(f"none of the {m} queries could be posed: their pairs with the references share too "
                            "little (no valid depth or pose); give references that see the same scene")
    K_orig[torch.tensor(used) < 0] = float("nan")  # an unposed query's K is NaN too, given or not
    return Localization(out, K_orig, used, confs, scales, [q.name for q in queries])


def _plain(x):
    """A tensor's or an array's contents as Python numbers and lists (``.tolist()``); anything else as it is."""
    return x.tolist() if hasattr(x, "tolist") and hasattr(x, "ndim") else x
