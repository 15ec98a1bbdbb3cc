"""TUM RGB-D trajectory export (``trajectory.txt``), the format trajectory tools (evo, the TUM scripts) read:
one line per image, ``timestamp tx ty tz qx qy qz qw``, the camera-to-world pose (camera centre and orientation,
OpenCV camera axes as everywhere in pointmap), the quaternion scalar last. The timestamp is the image's time in
seconds: ``timestamps`` when given, else ``recon.info["timestamps"]`` when it holds them (``pointmap reconstruct``
records a video's frame times there), else the image's index."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pointmap.io.atomic import atomic_open
from pointmap.io.colmap import rotation_to_quaternion


def tum_timestamps(recon, timestamps=None) -> np.ndarray:
    """[N] float64: ``timestamps``, else ``recon.info["timestamps"]``, else the image indices. ValueError unless
    one finite number per image."""
    n = len(recon)
    if timestamps is None:
        timestamps = (getattr(recon, "info", None) or {}).get("timestamps")
    try:
        ts = np.arange(n, dtype=np.float64) if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"timestamps expected {n} finite numbers (one per image), got {timestamps!r}") from None
    if ts.shape != (n,) or not np.isfinite(ts).all():
        raise ValueError(f"timestamps expected {n} finite numbers (one per image), got shape {ts.shape}")
    times, counts = np.unique(ts, return_counts=True)
    if (counts > 1).any():  # trajectory tools associate poses by time: two at one time are ambiguous
        raise ValueError(f"timestamps expected one distinct time per image, got {times[counts > 1][:3].tolist()} "
                         "more than once")
    return ts


def write_tum(recon, path, timestamps=None) -> Path:
    """Write ``recon``'s cam2world poses to ``path`` in TUM format, one line per image in time order (distinct
    times: ``tum_timestamps``); returns the path."""
    ts = tum_timestamps(recon, timestamps)
    c2w = recon.cam2world.double().numpy()
    with atomic_open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes) written by pointmap\n")
        for k in np.argsort(ts, kind="stable"):  # in time order, as trajectory tools expect
            t, T = ts[k], c2w[k]
            w, x, y, z = rotation_to_quaternion(T[:3, :3])
            f.write(f"{t:.6f} {T[0, 3]:.9g} {T[1, 3]:.9g} {T[2, 3]:.9g} {x:.9g} {y:.9g} {z:.9g} {w:.9g}\n")
    return Path(path)
