"""Atomic file writes for the exporters (the mechanism lives in ``pointmap.atomic``)."""

from pointmap.atomic import atomic_open, atomic_path, write_bytes

__all__ = ["atomic_open", "atomic_path", "write_bytes"]
