"""Parsing what users pass to ``global_align``: views, known intrinsics, known poses."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from pointmap.errors import ConventionError, GraphError, ShapeError, is_int
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K, is_rigid
from pointmap.reconstruction import K_to_map, check_colour_range


@dataclass
class ViewInfo:
    images: list              # [h, w, 3] float32 in [0, 1] per image
    shapes: list              # (h, w) per image
    map_from_original: torch.Tensor  # [N, 4]
    original_sizes: list      # (W, H) per image
    names: list


def parse_views(views) -> ViewInfo:
    """Accept View objects (pointmap.images), or plain [3, h, w] tensors / arrays."""
    if views is None or len(views) == 0:
        raise GraphError("global_align expected a list of views (pm.load_images output), got none")
    images, shapes, mfo, sizes, names = [], [], [], [], []
    for k, v in enumerate(views):
        img = v.img if hasattr(v, "img") else v
        img = torch.as_tensor(np.asarray(img) if not torch.is_tensor(img) else img)
        img = img.float() / 255 if img.dtype == torch.uint8 else img.float()
        if img.ndim != 3 or img.shape[0] != 3:
            raise ShapeError(f"view {k}: expected an image [3, h, w], got {list(img.shape)}")
        if not bool(torch.isfinite(img).all()):
            raise ShapeError(f"view {k}: expected a finite image, got NaN or inf pixels")
        check_colour_range(img, f"view {k}")
        h, w = int(img.shape[1]), int(img.shape[2])
        images.append(img.permute(1, 2, 0).clamp(0, 1))
        shapes.append((h, w))
        mfo.append(tuple(float(x) for x in getattr(v, "map_from_original", (1.0, 1.0, 0.0, 0.0))))
        sizes.append(tuple(int(x) for x in getattr(v, "original_size", (w, h))))
        name = getattr(v, "name", None)  # a plain tensor has a .name too (None, for named dimensions)
        names.append(name if isinstance(name, str) and name else f"view_{k:03d}.png")
    if len(set(names)) != len(names):
        seen = {}
        for k, nm in enumerate(names):
            seen.setdefault(nm, []).append(k)
        dup = {nm: ks for nm, ks in seen.items() if len(ks) > 1}
        warnings.warn(f"duplicate image names {dup}; COLMAP export needs unique names, so later ones get "
                      "a suffix", stacklevel=3)
        taken = set(names)
        for nm, ks in dup.items():
            r = 0
            for k in ks[1:]:
                stem, dot, ext = nm.rpartition(".")
                while True:  # a suffix no other image has (x/a.png, y/a.png beside a real a_1.png)
                    r += 1
                    new = f"{stem}_{r}.{ext}" if dot else f"{nm}_{r}"
                    if new not in taken:
                        break
                names[k] = new
                taken.add(new)
    _warn_duplicate_images(images)
    return ViewInfo(images, shapes, torch.tensor(mfo, dtype=torch.float64), sizes, names)


def _warn_duplicate_images(images: list) -> None:
    by_shape: dict = {}
    for k, im in enumerate(images):
        by_shape.setdefault(tuple(im.shape), []).append(k)
    dups = []
    for ks in by_shape.values():
        for a_pos, a in enumerate(ks):
            for b in ks[a_pos + 1:]:
                if torch.equal(images[a], images[b]):
                    dups.append((a, b))
    if dups:
        warnings.warn(f"identical images {dups[:8]}: duplicates add no parallax (zero baseline between them); "
                      "their cameras will coincide", stacklevel=4)


def _tensor_or_none(x) -> torch.Tensor | None:
    """``x`` (a tensor, an array, nested lists) as a tensor; None when it is none of those (strings, None)."""
    try:
        return x if torch.is_tensor(x) else torch.as_tensor(np.asarray(x))
    except (TypeError, ValueError, RuntimeError):
        return None


def as_mask(x, name: str) -> torch.Tensor:
    """A bool tensor of ``x``: bools, integers (nonzero = keep, e.g. a 0 / 255 mask image) or floats 0.0 / 1.0;
    ShapeError naming ``name`` for anything else (strings; fractions and NaN, which ``.bool()`` would make True)."""
    t = _tensor_or_none(x)
    if t is not None and (t.dtype == torch.bool or not (t.is_floating_point() or t.is_complex())):
        return t != 0
    if t is not None and t.is_floating_point() and bool(((t == 0) | (t == 1)).all()):
        return t != 0
    raise ShapeError(f"{name} expected bools (True = keep), integers (nonzero = keep) or 0.0 / 1.0, got "
                     f"{type(x).__name__} {str(x)[:60]}")


def _as_tensor(x, name: str, finite: bool = True) -> torch.Tensor:
    """A real tensor of ``x`` (tensor, array, nested lists); ShapeError naming ``name`` for anything else, or for
    NaN / inf with ``finite``."""
    t = _tensor_or_none(x)
    if t is None or not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise ShapeError(f"{name} expected numbers (a tensor or an array), got {type(x).__name__} {str(x)[:60]}")
    if finite and not torch.isfinite(t).all():
        raise ShapeError(f"{name} contains NaN or inf")
    return t


def _image_index(i, n: int, name: str) -> int:
    """A dict key of known K / poses as an image index; ShapeError for a non-integer or out-of-range one."""
    if not is_int(i):
        raise ShapeError(f"{name}: keys expected integer image indices, got {type(i).__name__} {i!r}")
    if not 0 <= int(i) < n:
        raise ShapeError(f"{name}: image index {i} outside 0..{n - 1}")
    return int(i)


def camera_index(shared_focal, n: int) -> torch.Tensor:
    """[n] int64 camera of each image, numbered 0.. in order of first appearance, from ``AlignConfig.shared_focal``:
    True: one camera; False: one per image; a sequence of n camera labels (ints): the images of one label share a
    focal. ShapeError for a sequence of another length."""
    if isinstance(shared_focal, bool):
        return torch.zeros(n, dtype=torch.long) if shared_focal else torch.arange(n)
    if len(shared_focal) != n:
        raise ShapeError(f"AlignConfig.shared_focal expected True, False or a camera label per image ({n}), got "
                         f"{len(shared_focal)} labels: {list(shared_focal)[:8]}")
    first = {}
    return torch.tensor([first.setdefault(c, len(first)) for c in shared_focal], dtype=torch.long)


def parse_known_K(K, n: int, info: ViewInfo):
    """Known intrinsics in ORIGINAL pixels -> (K_orig [N,3,3] float64 or None rows, known mask [N],
    fx, fy, cx, cy [N] in map pixels (NaN where unknown)). K: None, [3, 3], [N, 3, 3] or {i: [3, 3]}."""
    per = [None] * n
    if K is None:
        pass
    elif isinstance(K, dict):
        for i, k in K.items():
            per[_image_index(i, n, "K")] = _as_tensor(k, f"K[{i}]")
    else:
        Kt = _as_tensor(K, "K")
        if tuple(Kt.shape) == (3, 3):
            per = [Kt] * n
        elif tuple(Kt.shape) == (n, 3, 3):
            per = list(Kt)
        else:
            raise ShapeError(f"K expected [3, 3] (shared), [{n}, 3, 3] or a dict {{index: [3, 3]}}, "
                             f"got {list(Kt.shape)}")
    known = torch.tensor([k is not None for k in per])
    fx = torch.full((n,), float("nan"), dtype=torch.float64)
    fy, cx, cy = fx.clone(), fx.clone(), fx.clone()
    for i, k in enumerate(per):
        if k is None:
            continue
        k = k.double()
        if tuple(k.shape) != (3, 3):
            raise ShapeError(f"K[{i}] expected [3, 3], got {list(k.shape)}")
        if not bool(is_pinhole_K(k)):
            raise ConventionError(f"K[{i}] expected {K_LAYOUT} in pixels, finite with "
                                  f"positive focals (a transposed K puts cx, cy in the bottom row), got {k.tolist()}")
        Km = K_to_map(k, info.map_from_original[i])
        fx[i], fy[i], cx[i], cy[i] = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]
    return per, known, fx, fy, cx, cy


def parse_known_poses(cam2world, n: int, pose_mask=None) -> dict:
    """Known poses -> {index: [4, 4] tensor as given}. cam2world: None, [N, 4, 4] (all, or those in
    ``pose_mask``) or {i: [4, 4]}. Checks that each is rigid (orthonormal rotation, det +1)."""
    if cam2world is None:
        if pose_mask is not None:
            raise ShapeError("pose_mask given without cam2world")
        return {}
    if isinstance(cam2world, dict):
        if pose_mask is not None:
            raise ShapeError("pose_mask expected only with a [N, 4, 4] cam2world; a dict's keys already say which "
                             "poses are known")
        out = {_image_index(i, n, "cam2world"): _as_tensor(T, f"cam2world[{i}]") for i, T in cam2world.items()}
    else:
        T = _as_tensor(cam2world, "cam2world", finite=False)  # rows pose_mask leaves out may be NaN placeholders
        if tuple(T.shape) != (n, 4, 4):
            raise ShapeError(f"cam2world expected [{n}, 4, 4] or a dict {{index: [4, 4]}}, got {list(T.shape)}")
        mask = torch.ones(n, dtype=torch.bool) if pose_mask is None else as_mask(pose_mask, "pose_mask")
        if tuple(mask.shape) != (n,):
            raise ShapeError(f"pose_mask expected [{n}] bool, got {list(mask.shape)}")
        out = {i: _as_tensor(T[i], f"cam2world[{i}]") for i in range(n) if mask[i]}
    for i, T in out.items():  # indices are in range: dict keys were checked by _image_index
        if tuple(T.shape) != (4, 4):
            raise ShapeError(f"cam2world[{i}] expected [4, 4], got {list(T.shape)}")
        if not bool(is_rigid(T)):
            raise ConventionError(f"cam2world[{i}] is not a rigid transform (rotation must be orthonormal "
                                  "with det +1, last row 0 0 0 1); pass OpenCV camera-to-world matrices")
    check_pose_origin(out)
    return out


def check_pose_origin(known: dict) -> None:
    """ConventionError when the known cameras lie so far from the origin, for their spread, that float32 (what
    the alignment and the Reconstruction hold poses and points in) would round their positions by more than 1e-3
    of that spread (one known camera fixes no scale, and the scene is then about one unit across: 1e-3 unit).
    Georeferenced poses (UTM, ECEF: millions of metres) are the case: with them the alignment's depths came out
    31% wrong and its free cameras metres off, without a word. Subtracting an offset first fixes it."""
    if not known:
        return
    centres = torch.stack([T[:3, 3].double() for T in known.values()])
    far = float(centres.abs().max())
    spread = float(torch.cdist(centres, centres).max()) if len(known) > 1 else 0.0
    if spread <= 1e-6 * max(1.0, far):  # one camera, or coincident centres (a tripod): no scale is fixed, and the
        spread = 1.0  # scene is then about one unit across
    rounding = far * 2.0 ** -24
    if rounding > 1e-3 * spread:
        offset = ", ".join(f"{x:.6g}" for x in centres.mean(0).tolist())
        raise ConventionError(f"known poses lie up to {far:.6g} units from the origin against a spread of "
                              f"{spread:.4g}: float32 (the alignment's precision) would round their positions by "
                              f"~{rounding:.2g} units; subtract an offset from the poses' translations (e.g. their "
                              f"mean centre, {offset}) and add it back to the outputs")
