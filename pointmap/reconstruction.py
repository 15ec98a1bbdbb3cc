"""Reconstruction: a scene made of N posed views with dense depth (a public contract: docs/conventions.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from pointmap.errors import ShapeError, is_int, is_number
from pointmap.geometry.cameras import (
    K_LAYOUT,
    depth_to_points_world,
    is_pinhole_K,
    is_rigid,
    similarity_on_cam2world,
)

_REQUIRED = ("images", "cam2world", "K", "depth_z", "conf")


def check_colour_range(img: torch.Tensor, what: str, tol: float = 0.01) -> None:
    """ShapeError unless a float image's colours lie in [0, 1] (up to ``tol``): 0-255 floats would be clamped to
    white without a word."""
    if img.numel() and (float(img.min()) < -tol or float(img.max()) > 1 + tol):
        raise ShapeError(f"{what}: expected colours in [0, 1], got values from {float(img.min()):.4g} to "
                         f"{float(img.max()):.4g} (0-255 images: divide by 255, or pass uint8)")


@dataclass
class Reconstruction:
    """Posed views with depth, confidence and colour; buildable by hand (e.g. from ground truth).

    images:    [N, h, w, 3] float in [0, 1] (the maps' resolution, i.e. the network input; with ``map_sizes``,
        the canvas)
    cam2world: [N, 4, 4] OpenCV camera-to-world
    K:         [N, 3, 3] intrinsics in ORIGINAL image pixels (see ``map_from_original``)
    depth_z:   [N, h, w] z-depth, 0 = no value
    conf:      [N, h, w] confidence (>= 1 for network output; anything > 0 when hand-made)
    map_from_original: [N, 4] (sx, sy, left, top): a map pixel u_map = (u_orig + 0.5) * sx - 0.5 - left;
        identity (1, 1, 0, 0) when the maps are at the original resolution (the default)
    original_sizes: list of (width, height) of the original images; defaults to each view's map size
    names: image names (file names for COLMAP export); default ``view_000.png`` ...
    masks: optional [N, h, w] bool, pixels to keep (e.g. user masks); None keeps all
    map_sizes: (width, height) of each view's own map, anchored at the top-left of the [h, w] canvas that
        images of different sizes (portrait among landscape) share; the canvas pixels outside it are padding
        (``global_align`` leaves depth 0 and confidence 0 there; whatever a hand-made one holds is ignored): never
        valid, left out of every export and of the Gaussian fit. None: every view fills the canvas
    """

    images: torch.Tensor
    cam2world: torch.Tensor
    K: torch.Tensor
    depth_z: torch.Tensor
    conf: torch.Tensor
    map_from_original: torch.Tensor | None = None
    original_sizes: list | None = None
    names: list | None = None
    masks: torch.Tensor | None = None
    map_sizes: list | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("images", "cam2world", "K", "depth_z", "conf", "map_from_original", "masks"):
            t = getattr(self, name)
            if isinstance(t, np.ndarray):  # arrays are taken as they are; anything else is a mistake
                setattr(self, name, torch.from_numpy(np.ascontiguousarray(t)))  # negative strides: img[..., ::-1]
            elif isinstance(t, torch.Tensor) and t.requires_grad:  # a result, not a graph: exports call .numpy()
                setattr(self, name, t.detach())
            elif not isinstance(t, torch.Tensor) and (t is not None or name in _REQUIRED):
                raise ShapeError(f"{name} expected a torch.Tensor (or numpy array), got {type(t).__name__}")
        n, h, w = self.depth_z.shape if self.depth_z.ndim == 3 else (None, None, None)
        if n is None:
            raise ShapeError(f"depth_z expected [N, h, w], got {list(self.depth_z.shape)}")
        if n == 0:
            raise ShapeError("a Reconstruction expected at least one view, got depth_z of shape "
                             f"{list(self.depth_z.shape)}")
        if h == 0 or w == 0:
            raise ShapeError(f"depth_z expected maps of at least one pixel, got {list(self.depth_z.shape)}")
        for name in ("cam2world", "K", "depth_z", "conf"):  # real numbers (complex or bool ones are a mistake)
            t = getattr(self, name)
            if not t.is_floating_point():
                raise ShapeError(f"{name} expected a floating-point tensor, got {t.dtype}")
        if self.info is None:
            self.info = {}
        if not isinstance(self.info, dict):
            raise ShapeError(f"info expected a dict (JSON-able metadata), got {type(self.info).__name__}")
        checks = {"images": (self.images, (n, h, w, 3)), "cam2world": (self.cam2world, (n, 4, 4)),
                  "K": (self.K, (n, 3, 3)), "conf": (self.conf, (n, h, w))}
        for name, (t, shape) in checks.items():
            if tuple(t.shape) != shape:
                raise ShapeError(f"{name} expected {list(shape)}, got {list(t.shape)}")
        if self.images.dtype == torch.uint8:  # 0-255 colours: stored as floats in [0, 1] like every other
            self.images = self.images.float() / 255
        if not self.images.is_floating_point():
            raise ShapeError(f"images expected floats in [0, 1] (or uint8), got {self.images.dtype}")
        for name in ("images", "cam2world", "K", "depth_z", "conf"):
            t = getattr(self, name)
            if not torch.isfinite(t).all():
                raise ShapeError(f"{name} contains NaN or inf values")
        check_colour_range(self.images, "images")
        for name in ("depth_z", "conf"):  # 0 marks "no value"; below it is a mistake (e.g. a disparity map)
            t = getattr(self, name)
            if t.numel() and float(t.min()) < 0:
                raise ShapeError(f"{name} expected values >= 0 (0: no value), got a minimum of {float(t.min()):.4g}")
        if self.map_from_original is None:
            self.map_from_original = torch.tensor([[1.0, 1.0, 0.0, 0.0]]).repeat(n, 1)
        if tuple(self.map_from_original.shape) != (n, 4):
            raise ShapeError(f"map_from_original expected [{n}, 4], got {list(self.map_from_original.shape)}")
        mfo = self.map_from_original
        if not (bool(torch.isfinite(mfo).all()) and bool((mfo[:, :2] > 0).all())):
            raise ShapeError(f"map_from_original expected finite rows (sx, sy, left, top) with sx, sy > 0, got "
                             f"{mfo.tolist()}")
        sizes = [(w, h)] * n if self.map_sizes is None else self.map_sizes
        if not (hasattr(sizes, "__len__") and len(sizes) == n and all(
                hasattr(s, "__len__") and len(s) == 2 and all(is_int(x) for x in s) and 0 < s[0] <= w and 0 < s[1] <= h
                for s in sizes)):
            raise ShapeError(f"map_sizes expected {n} (width, height) pairs of ints within the {w}x{h} canvas, got "
                             f"{list(sizes)[:4] if hasattr(sizes, '__len__') else type(sizes).__name__}")
        self.map_sizes = [(int(a), int(b)) for a, b in sizes]
        if self.original_sizes is None:
            if not bool((mfo == torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=mfo.dtype)).all()):
                raise ShapeError("original_sizes expected with a map_from_original that resizes or crops: the "
                                 "photographs' (width, height) cannot be the maps' sizes then (every export's "
                                 "cameras would be wrong)")
            self.original_sizes = list(self.map_sizes)
        if not hasattr(self.original_sizes, "__len__") or len(self.original_sizes) != n or not all(
                hasattr(s, "__len__") and len(s) == 2 and all(is_int(x) and x > 0 for x in s)
                for s in self.original_sizes):
            got = self.original_sizes
            raise ShapeError(f"original_sizes expected {n} (width, height) pairs of positive ints, got "
                             f"{list(got)[:4] if hasattr(got, '__len__') else type(got).__name__}")
        if self.names is None:
            self.names = [f"view_{i:03d}.png" for i in range(n)]
        if isinstance(self.names, str):  # list("ab") would name two views "a" and "b"
            raise ShapeError(f"names expected {n} non-empty strings, got the single string {self.names!r}")
        self.names = list(self.names)
        if len(self.names) != n or not all(isinstance(nm, str) and nm for nm in self.names):
            raise ShapeError(f"names expected {n} non-empty strings, got {self.names!r}")
        if len(set(self.names)) != n:
            dup = sorted({nm for nm in self.names if self.names.count(nm) > 1})
            raise ShapeError(f"names expected to be unique (COLMAP export keys images by name), got {dup} twice or more")
        if self.masks is not None and tuple(self.masks.shape) != (n, h, w):
            raise ShapeError(f"masks expected [{n}, {h}, {w}], got {list(self.masks.shape)}")
        if self.masks is not None and self.masks.dtype != torch.bool:
            raise ShapeError(f"masks expected dtype bool (True: keep the pixel), got {self.masks.dtype}")
        pinhole = is_pinhole_K(self.K)
        if not bool(pinhole.all()):
            bad = [int(i) for i in (~pinhole).nonzero().flatten()]
            raise ShapeError(f"K expected finite pinhole intrinsics {K_LAYOUT} with fx, fy > 0, got "
                             f"K[{bad[0]}] = {self.K[bad[0]].tolist()}"
                             f"{f' (views {bad})' if len(bad) > 1 else ''}")
        rigid = is_rigid(self.cam2world)
        if not bool(rigid.all()):
            k = int((~rigid).nonzero()[0])
            raise ShapeError(f"cam2world expected rigid [R t; 0 0 0 1] matrices (R a rotation), got "
                             f"cam2world[{k}] = {self.cam2world[k].tolist()}")

    def __len__(self) -> int:
        return int(self.depth_z.shape[0])

    @property
    def padded(self) -> bool:
        """Whether some view is smaller than the canvas (images of different sizes)."""
        h, w = self.depth_z.shape[1:]
        return any(s != (w, h) for s in self.map_sizes)

    @property
    def regions(self) -> torch.Tensor:
        """[N, h, w] bool: each view's own pixels (False on the canvas's padding; all True unless ``padded``)."""
        n, h, w = self.depth_z.shape
        out = torch.zeros(n, h, w, dtype=torch.bool)
        for k, (vw, vh) in enumerate(self.map_sizes):
            out[k, :vh, :vw] = True
        return out

    def crop(self, maps: torch.Tensor, k: int) -> torch.Tensor:
        """View ``k``'s own pixels of a per-view canvas map ``maps`` [N, h, w, ...] (e.g. ``recon.images``):
        [h_k, w_k, ...]."""
        vw, vh = self.map_sizes[k]
        return maps[k, :vh, :vw]

    @property
    def K_map(self) -> torch.Tensor:
        """[N, 3, 3] intrinsics at the maps' resolution (derived from K and map_from_original)."""
        return K_to_map(self.K, self.map_from_original)

    @property
    def pts_world(self) -> torch.Tensor:
        """[N, h, w, 3] world points of every pixel (meaningless where depth_z == 0)."""
        return depth_to_points_world(self.depth_z, self.K_map.to(self.depth_z.dtype),
                                     self.cam2world.to(self.depth_z.dtype))

    @property
    def colors(self) -> torch.Tensor:
        """[N, h, w, 3] colours in [0, 1]."""
        return self.images

    def valid(self, min_conf: float = 0.0, *, masked: bool = True) -> torch.Tensor:
        """[N, h, w] bool: depth present, confidence above ``min_conf``, inside the user mask (unless ``masked`` is
        False) and the view's own pixels (``regions``)."""
        ok = (self.depth_z > 0) & (self.conf > min_conf)
        if masked and self.masks is not None:
            ok = ok & self.masks
        if self.padded:
            ok = ok & self.regions
        return ok

    def transformed(self, scale: float, R, t) -> Reconstruction:
        """The same reconstruction in another world: x -> scale * R x + t (R a rotation [3, 3], t [3], scale > 0).
        Camera centres and orientations move with the world, depths scale by ``scale``; intrinsics, images and
        confidences are unchanged. ``info["transformed"]`` records the similarity from the original world (this
        one composed with any recorded before, in float64). cam2world keeps its dtype: float32 holds about 7
        digits, so a georeferencing offset of 4e6 units is rounded to ~0.25 units; add such an offset to the
        exported files in float64 instead."""
        from dataclasses import replace

        R = torch.as_tensor(R, dtype=torch.float64)
        t = torch.as_tensor(t, dtype=torch.float64)
        if not (is_number(scale) or (isinstance(scale, torch.Tensor) and scale.numel() == 1
                                     and scale.dtype != torch.bool)):
            raise ShapeError(f"transformed expected scale > 0, a real number, got {scale!r}")
        scale = float(scale)
        if tuple(R.shape) != (3, 3) or tuple(t.shape) != (3,) or not (
                0 < scale < math.inf and torch.isfinite(R).all() and torch.isfinite(t).all()):
            raise ShapeError(f"transformed expected scale > 0, R [3, 3] and t [3], finite; got {scale}, "
                             f"{list(R.shape)}, {list(t.shape)}")
        if not torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-5) or float(torch.det(R)) < 0:
            raise ShapeError(f"transformed expected R to be a rotation, got {R.tolist()}")
        c2w = similarity_on_cam2world(self.cam2world.double(), scale, R, t)
        total_s, total_R, total_t = scale, R, t
        if "transformed" in self.info:  # x -> s2 R2 (s1 R1 x + t1) + t2
            prev = self.info["transformed"]
            R1, t1 = torch.tensor(prev["R"], dtype=torch.float64), torch.tensor(prev["t"], dtype=torch.float64)
            total_s, total_R, total_t = scale * float(prev["scale"]), R @ R1, scale * R @ t1 + t
        return replace(self, cam2world=c2w.to(self.cam2world.dtype), depth_z=self.depth_z * scale,
                       info={**self.info, "transformed": {"scale": total_s, "R": total_R.tolist(),
                                                          "t": total_t.tolist()}})

    def save(self, out_dir, formats=("ply", "glb", "colmap", "npz"), **kwargs):
        """Write the reconstruction in the given formats under ``out_dir``; returns the paths written."""
        from pointmap.io import save_reconstruction

        return save_reconstruction(self, out_dir, formats=formats, **kwargs)


def to_canvas(maps: list, fill=0) -> tuple[torch.Tensor, list]:
    """Per-view maps [h_k, w_k, ...] of possibly different sizes -> one [N, h, w, ...] tensor (h, w the largest
    of each), each map at the top-left (so its pixel coordinates, and its intrinsics, stay as they were) and
    ``fill`` elsewhere; with the (width, height) of each, ``Reconstruction.map_sizes``."""
    if not maps:
        raise ShapeError("to_canvas expected at least one map, got none")
    if not all(isinstance(m, torch.Tensor) and m.ndim >= 2 for m in maps):
        raise ShapeError(f"to_canvas expected maps as tensors [h_k, w_k, ...], got "
                         f"{[tuple(getattr(m, 'shape', ())) or type(m).__name__ for m in maps][:4]}")
    if len({(m.dtype, tuple(m.shape[2:])) for m in maps}) != 1:
        raise ShapeError(f"to_canvas expected maps of one dtype and trailing shape, got "
                         f"{sorted({(str(m.dtype), tuple(m.shape)) for m in maps})[:4]}")
    sizes = [(int(m.shape[1]), int(m.shape[0])) for m in maps]
    h, w = max(s[1] for s in sizes), max(s[0] for s in sizes)
    if all(s == (w, h) for s in sizes):
        return torch.stack(maps), sizes
    out = torch.full((len(maps), h, w, *maps[0].shape[2:]), fill, dtype=maps[0].dtype)
    for k, m in enumerate(maps):
        out[k, :m.shape[0], :m.shape[1]] = m
    return out, sizes


def K_to_map(K: torch.Tensor, map_from_original: torch.Tensor) -> torch.Tensor:
    """Intrinsics in original pixels -> at the map resolution (see Reconstruction.map_from_original)."""
    sx, sy, left, top = map_from_original.to(K.dtype).unbind(-1)
    out = K.clone()
    out[..., 0, 0] = K[..., 0, 0] * sx
    out[..., 1, 1] = K[..., 1, 1] * sy
    out[..., 0, 1] = K[..., 0, 1] * sx
    out[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5 - left
    out[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5 - top
    return out


def K_to_original(K_map: torch.Tensor, map_from_original: torch.Tensor) -> torch.Tensor:
    """Inverse of ``K_to_map``."""
    sx, sy, left, top = map_from_original.to(K_map.dtype).unbind(-1)
    out = K_map.clone()
    out[..., 0, 0] = K_map[..., 0, 0] / sx
    out[..., 1, 1] = K_map[..., 1, 1] / sy
    out[..., 0, 1] = K_map[..., 0, 1] / sx
    out[..., 0, 2] = (K_map[..., 0, 2] + 0.5 + left) / sx - 0.5
    out[..., 1, 2] = (K_map[..., 1, 2] + 0.5 + top) / sy - 0.5
    return out
