"""Choosing which pixels of a reconstruction become exported points (confidence thresholds, masks)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pointmap.errors import ShapeError, check_seed, is_int, is_number


def check_conf_filter(min_conf, percentile, names=("min_conf", "conf_percentile")) -> None:
    """ShapeError (a ValueError) unless ``min_conf`` is None or a finite number and ``percentile`` None or a number
    in [0, 100) (a 0-d tensor or array counts as its number); ``names`` are what the messages call them (the CLI's
    flags, the API's arguments)."""
    def scalar(x):
        return x.item() if getattr(x, "ndim", None) == 0 and hasattr(x, "item") else x

    min_conf, percentile = scalar(min_conf), scalar(percentile)
    if min_conf is not None and not (is_number(min_conf) and math.isfinite(min_conf)):
        raise ShapeError(f"{names[0]} expected a finite confidence, got {min_conf!r}")
    if percentile is not None and not (is_number(percentile) and 0 <= percentile < 100):
        raise ShapeError(f"{names[1]} expected a percentile in [0, 100), got {percentile!r}")


def confidence_mask(conf: torch.Tensor, min_conf: float | None = None,
                    percentile: float | None = None, within: torch.Tensor | None = None) -> torch.Tensor:
    """[N, h, w] bool. ``min_conf``: absolute, keep conf > min_conf (raw network confidence, >= 1; the
    official demos use 3 for DUSt3R and 1.5 for MASt3R). ``percentile`` in [0, 100): relative, keep
    conf >= that percentile of the finite confidences over all images together (50 keeps the most confident half
    of the scene's pixels, so a less confident image keeps fewer). Both may be combined (a pixel must pass both).
    ``within`` ([N, h, w] bool, e.g. depth present and inside the user's masks): the only pixels kept, and the
    only ones the percentile is taken over (50 keeps half of them, however many pixels a mask removed)."""
    check_conf_filter(min_conf, percentile, ("min_conf", "percentile"))
    eligible = torch.isfinite(conf)  # the pixels the percentile is taken over
    if within is not None:
        if not isinstance(within, torch.Tensor) or within.shape != conf.shape or within.dtype != torch.bool:
            raise ShapeError(f"within expected a bool tensor of conf's shape {tuple(conf.shape)}, got "
                             f"{type(within).__name__} {tuple(getattr(within, 'shape', ()))} "
                             f"{getattr(within, 'dtype', '')}")
        eligible &= within
    keep = eligible.clone()
    if min_conf is not None:
        keep &= conf > min_conf
    if percentile is not None:
        vals = conf[eligible].double()
        if vals.numel():
            thr = float(np.percentile(vals.numpy(), percentile))
            keep &= conf >= thr
    return keep


def check_point_cap(cap, name: str) -> None:
    """ShapeError unless ``cap`` is None (no cap) or an int >= 1: 0 would write an empty cloud (an empty points3D
    stops 3DGS trainers) and a negative one kept all but a few points."""
    if cap is not None and not (is_int(cap) and cap >= 1):
        raise ShapeError(f"{name} expected None (all points) or an int >= 1, got {cap!r}")


@dataclass
class PointSet:
    xyz: np.ndarray        # [M, 3] float64 world
    rgb: np.ndarray        # [M, 3] uint8
    conf: np.ndarray       # [M] float32
    image: np.ndarray      # [M] int: source image
    uv_map: np.ndarray     # [M, 2] float: source pixel (map resolution)


def select_points(recon, min_conf: float | None = None, conf_percentile: float | None = None,
                  max_points: int | None = None, seed: int = 0) -> PointSet:
    """Valid pixels (depth > 0, inside recon.masks, confidence thresholds) as a point set; a random
    subset of ``max_points`` if given."""
    check_point_cap(max_points, "max_points")
    seed = check_seed(seed)
    keep = confidence_mask(recon.conf, min_conf, conf_percentile, within=recon.valid())
    n_idx, v, u = keep.nonzero(as_tuple=True)
    if max_points is not None and len(n_idx) > max_points:
        g = torch.Generator().manual_seed(seed)
        sel = torch.randperm(len(n_idx), generator=g)[:max_points].sort().values
        n_idx, v, u = n_idx[sel], v[sel], u[sel]
    pts = recon.pts_world.double() if recon.depth_z.dtype != torch.float64 else recon.pts_world
    xyz = pts[n_idx, v, u].numpy()
    rgb = (recon.images[n_idx, v, u].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    return PointSet(xyz=xyz, rgb=rgb, conf=recon.conf[n_idx, v, u].numpy().astype(np.float32),
                    image=n_idx.numpy(), uv_map=torch.stack([u, v], -1).numpy().astype(np.float64))
