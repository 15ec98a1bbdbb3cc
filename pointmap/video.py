"""Frames from a video for reconstruction: one frame per window of ``stride`` frames, the sharpest of its window
(variance of the Laplacian: motion blur is what hand-held video suffers most), written as images that the
rest of the pipeline reads like photographs."""

from __future__ import annotations

import contextlib
import math
import os
import sys
from pathlib import Path

import numpy as np

from pointmap.atomic import atomic_path
from pointmap.errors import ImageError, is_int

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")


def is_video(path) -> bool:
    """A path with a video suffix (``VIDEO_SUFFIXES``, any case) that is not a directory."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES and not Path(path).is_dir()


def sharpness(frame_bgr: np.ndarray) -> float:
    """Variance of the Laplacian of the grey frame: higher is sharper. ``frame_bgr``: HxWx3 BGR (or HxWx4 BGRA),
    uint8 or uint16, as OpenCV decodes frames; ImageError for anything else."""
    import cv2

    if not (isinstance(frame_bgr, np.ndarray) and frame_bgr.ndim == 3 and frame_bgr.shape[2] in (3, 4)
            and frame_bgr.size > 0 and frame_bgr.dtype in (np.uint8, np.uint16)):
        got = (f"shape {tuple(frame_bgr.shape)} {frame_bgr.dtype}" if isinstance(frame_bgr, np.ndarray)
               else type(frame_bgr).__name__)
        raise ImageError(f"sharpness expected an HxWx3 BGR frame (or HxWx4 BGRA) of uint8 or uint16, got {got}")
    return float(cv2.Laplacian(cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var())


def extract_frames(video, out_dir, *, stride: int | None = None, max_frames: int = 30,
                   pick_sharpest: bool = True, with_times: bool = False) -> list:
    """Write frames of ``video`` to ``out_dir`` as ``<stem>_<frame index>.png`` and return their paths in time order.

    ``stride``: one frame per window of that many frames (default: the smallest stride giving at most
    ``max_frames`` frames); the frame kept in each window is its sharpest when ``pick_sharpest`` (else the first).
    Without a stride the frame count comes from the container (``count_frames``) and is checked while reading:
    a file holding more frames than its header states (the read stops once ``max_frames`` windows are full, the
    rest is counted by grabbing) or fewer (truncated, or an over-stated header) is read again at the stride its
    true count gives, the first pass's frames that the second does not keep removed. Memory holds one window's
    best frame, whatever the video's length.
    ``with_times``: (path, seconds) pairs instead, each frame's presentation time as the container gives it
    (right for the variable frame rates phones record), else its index over the stated frame rate when the
    container's times are missing or not increasing, else None (no rate stated either).
    ImageError when the file cannot be decoded or holds no frame; every image is written atomically as soon as
    its window closes."""
    if not isinstance(video, (str, os.PathLike)) or not isinstance(out_dir, (str, os.PathLike)):
        raise ImageError(f"extract_frames expected a video path and a folder path, got {video!r} and {out_dir!r}")
    video = Path(video)
    if not video.is_file():
        raise ImageError(f"video not found: {video}")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ImageError(f"extract_frames expected a folder for the frames, got {out_dir}, which is a file")
    if stride is not None and not (is_int(stride) and stride >= 1):
        raise ImageError(f"stride expected a positive integer, got {stride!r}")
    if not (is_int(max_frames) and max_frames >= 1):
        raise ImageError(f"max_frames expected an integer >= 1, got {max_frames!r}")
    for name, flag in (("pick_sharpest", pick_sharpest), ("with_times", with_times)):
        if not isinstance(flag, bool):  # as every other flag check in pointmap
            raise ImageError(f"{name} expected True or False, got {flag!r}")
    out_dir = Path(out_dir)
    if stride is not None:
        kept, _, fps = _read_windows(video, out_dir, stride, pick_sharpest, None)
    else:
        stated = count_frames(video)
        step = max(1, math.ceil(stated / max_frames))
        kept, total, fps = _read_windows(video, out_dir, step, pick_sharpest, step * max_frames)
        true_step = max(1, math.ceil(total / max_frames))
        if true_step != step:  # the header was wrong: once more at the true count's stride
            first = kept
            kept, _, fps = _read_windows(video, out_dir, true_step, pick_sharpest, None)
            for stale in {p for p, _, _ in first} - {p for p, _, _ in kept}:
                stale.unlink(missing_ok=True)
    if not kept:
        raise ImageError(f"no frame could be decoded from {video}")
    paths = [p for p, _, _ in kept]
    if not with_times:
        return paths
    return list(zip(paths, _frame_seconds([(i, t) for _, i, t in kept], fps)))


def _read_windows(video: Path, out_dir: Path, stride: int, pick_sharpest: bool, limit: int | None):
    """One pass over ``video``: the best frame of each window of ``stride`` frames written to ``out_dir``.
    Returns ([(path, frame index, container seconds)], the frames in the file, its stated frame rate). With
    ``limit``, the pass stops writing after that many frames when the file holds more, and counts the rest by
    grabbing (the total is what the caller's stride was wrong about)."""
    import cv2

    kept: list[tuple[Path, int, float]] = []

    def write(index: int, seconds: float, frame: np.ndarray) -> None:  # one window's frame, written as it closes
        path = out_dir / f"{video.stem}_{index:06d}.png"
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), frame):
                raise ImageError(f"could not write frame {index} of {video} to {path}")
        kept.append((path, index, seconds))

    cap = _open(video)
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        best: tuple[float, int, float, np.ndarray] | None = None  # only the current window's best frame is held
        index = 0
        while True:
            if limit is not None and index == limit and cap.grab():  # more frames than the header said
                index += 1
                while cap.grab():
                    index += 1
                return kept, index, fps
            ok, frame = cap.read()
            if not ok:
                break
            score = sharpness(frame) if pick_sharpest else -float(index % stride)
            if best is None or score > best[0]:
                best = (score, index, float(cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0, frame)
            index += 1
            if index % stride == 0:
                write(*best[1:])
                best = None
        if best is not None:
            write(*best[1:])
    finally:
        cap.release()
    return kept, index, fps


def _frame_seconds(kept: list[tuple[int, float]], fps: float) -> list[float | None]:
    """The kept frames' times: the container's when finite and increasing, else index / ``fps``, else None."""
    seconds = [t for _, t in kept]
    if all(math.isfinite(t) and t >= 0 for t in seconds) and all(b > a for a, b in zip(seconds, seconds[1:])):
        return seconds
    if math.isfinite(fps) and fps > 0:
        return [i / fps for i, _ in kept]
    return [None] * len(kept)


def count_frames(video) -> int:
    """Frames in ``video``: the container's count when it states one, else counted by grabbing every frame
    without decoding it (browser-recorded .webm files often state none). ImageError when it cannot be opened."""
    import cv2

    cap = _open(video)
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if n > 0:
            return n
        n = 0
        while cap.grab():
            n += 1
        return n
    finally:
        cap.release()


def _open(video):
    """An opened ``cv2.VideoCapture`` (the caller releases it); ImageError when OpenCV cannot open the file."""
    import cv2

    with _ffmpeg_silenced():  # its complaint ("moov atom not found") would come before our one line
        cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        cap.release()
        raise ImageError(f"not a readable video: {video} (OpenCV could not open it)")
    return cap


@contextlib.contextmanager
def _ffmpeg_silenced():
    """File descriptor 2 onto /dev/null for the duration: FFmpeg, inside OpenCV, writes its own messages about a
    file it cannot parse straight to it, past Python's sys.stderr. Left as it is where it cannot be redirected."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
