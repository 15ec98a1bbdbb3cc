"""Global alignment: pairwise pointmaps -> poses, intrinsics and dense depth (docs/alignment.md)."""

from pointmap.align.epipolar import EpipolarConfig, refine_epipolar
from pointmap.align.gauge import align_to_cameras, scale_to_depth
from pointmap.align.optimize import AlignConfig, global_align
from pointmap.align.sparse import SparseConfig, refine_matches

__all__ = ["AlignConfig", "EpipolarConfig", "SparseConfig", "align_to_cameras", "global_align", "refine_epipolar",
           "refine_matches", "scale_to_depth"]
