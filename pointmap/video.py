"""Frames from a video for reconstruction: one frame per window of ``stride`` frames, the sharpest of its window
(variance of the Laplacian: motion blur is what hand-held video suffers most), written as images that the
rest of the pipeline reads like photographs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pointmap.atomic import atomic_path
from pointmap.errors import ImageError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")


def is_video(path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def sharpness(frame_bgr: np.ndarray) -> float:
    """Variance of the Laplacian of the grey frame: higher is sharper."""
    import cv2

    return float(cv2.Laplacian(cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var())


def extract_frames(video, out_dir, *, stride: int | None = None, max_frames: int = 30,
                   pick_sharpest: bool = True) -> list[Path]:
    """Write frames of ``video`` to ``out_dir`` as ``<stem>_<frame index>.png`` and return their paths in time order.

    ``stride``: one frame per window of that many frames (default: the smallest stride giving at most
    ``max_frames`` frames, from the frame count the container reports); the frame kept in each window is its
    sharpest when ``pick_sharpest`` (else the first). ImageError when the file cannot be decoded or holds no
    frame; every image is written atomically."""
    import cv2

    video = Path(video)
    if not video.is_file():
        raise ImageError(f"video not found: {video}")
    if stride is not None and (not isinstance(stride, int) or stride < 1):
        raise ImageError(f"stride expected a positive integer, got {stride!r}")
    if not isinstance(max_frames, int) or max_frames < 2:
        raise ImageError(f"max_frames expected an integer >= 2, got {max_frames!r}")
    cap = cv2.VideoCapture(str(video))
    try:
        if not cap.isOpened():
            raise ImageError(f"not a readable video: {video} (OpenCV could not open it)")
        if stride is None:
            total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            stride = max(1, math.ceil(total / max_frames)) if total > 0 else 1
        kept: list[tuple[int, np.ndarray]] = []
        best: tuple[float, int, np.ndarray] | None = None
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            score = sharpness(frame) if pick_sharpest else -float(index % stride)
            if best is None or score > best[0]:
                best = (score, index, frame)
            index += 1
            if index % stride == 0:
                kept.append(best[1:])
                best = None
        if best is not None:
            kept.append(best[1:])
    finally:
        cap.release()
    if not kept:
        raise ImageError(f"no frame could be decoded from {video}")
    out_dir = Path(out_dir)
    paths = []
    for i, frame in kept:
        path = out_dir / f"{video.stem}_{i:06d}.png"
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), frame):
                raise ImageError(f"could not write frame {i} of {video} to {path}")
        paths.append(path)
    return paths
