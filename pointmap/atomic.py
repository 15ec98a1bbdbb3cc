"""Atomic file writes, the one mechanism every writer of the library uses: the data goes to a temporary
file next to the target, is flushed to disk, and is renamed onto the target in one step, so a crash never
leaves a half-written file behind. The result is an ordinary file (0666 minus the umask), not the
owner-only file ``mkstemp`` creates."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path):
    """``with atomic_path(p) as tmp: library.save(..., tmp)``: a temporary path with ``p``'s suffix (some
    writers choose the format from it); it replaces ``p`` only if the block succeeds, else it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextmanager
def atomic_open(path, mode: str = "wb"):
    """``with atomic_open(p) as f: f.write(...)``; the file appears at ``p`` only if the block succeeds."""
    if not mode.startswith("w"):
        raise ValueError(f"atomic_open expected a write mode ('w' or 'wb'), got {mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode, encoding=None if "b" in mode else "utf-8") as f:
        yield f  # text as UTF-8 whatever the locale (COLMAP, TUM and JSON readers expect it)


def write_bytes(path, data: bytes) -> Path:
    with atomic_open(path, "wb") as f:
        f.write(data)
    return Path(path)
