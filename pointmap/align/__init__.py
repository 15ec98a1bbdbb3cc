"""Global alignment: pairwise pointmaps -> poses, intrinsics and dense depth (docs/alignment.md)."""

from pointmap.align.optimize import AlignConfig, global_align

__all__ = ["AlignConfig", "global_align"]
