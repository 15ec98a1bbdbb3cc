"""pointmap: feed-forward 3D reconstruction (DUSt3R/MASt3R family). See docs/ (conventions: docs/conventions.md).

    import pointmap as pm
    model = pm.load_model("small")
    views = pm.load_images(["a.jpg", "b.jpg"], size=224)
    preds = pm.predict_pairs(model, views, pm.make_pairs(2))
"""

from importlib import import_module

from pointmap.checkpoint import load_model, save_model
from pointmap.errors import (
    CheckpointError,
    ConventionError,
    GraphError,
    ImageError,
    PointmapError,
    ShapeError,
)
from pointmap.images import View, load_images
from pointmap.inference import predict_pairs
from pointmap.matching import Matches, match, match_coarse
from pointmap.model import PRESETS, ModelConfig, PointmapNet
from pointmap.pairs import check_connected, make_pairs
from pointmap.pose import (
    pair_pose,
    pose_from_essential,
    refine_pose_with_matches,
    relative_pose,
    translation_from_matches,
)
from pointmap.prediction import PairPrediction
from pointmap.reconstruction import Reconstruction

__version__ = "0.1.0"

# heavier parts load on first use
_LAZY = {"global_align": "pointmap.align", "align_to_cameras": "pointmap.align",
         "scale_to_depth": "pointmap.align", "refine_matches": "pointmap.align",
         "AlignConfig": "pointmap.align", "SparseConfig": "pointmap.align",
         "EpipolarConfig": "pointmap.align", "refine_epipolar": "pointmap.align", "reconstruct": "pointmap.pipeline", "splat": "pointmap.splat",
         "io": "pointmap.io", "localize": "pointmap.localization", "Localization": "pointmap.localization"}


def __getattr__(name):
    if name in _LAZY:
        mod = import_module(_LAZY[name])
        return mod if name in ("splat", "io") else getattr(mod, name)
    raise AttributeError(f"module 'pointmap' has no attribute {name!r}")


__all__ = [
    "CheckpointError", "ConventionError", "GraphError", "ImageError", "Matches", "match_coarse", "ModelConfig", "PRESETS",
    "PairPrediction", "PointmapError", "PointmapNet", "Reconstruction", "ShapeError", "View", "__version__",
    "check_connected", "global_align", "load_images", "load_model", "make_pairs", "match", "predict_pairs",
    "reconstruct", "align_to_cameras", "scale_to_depth", "relative_pose", "pair_pose", "pose_from_essential", "translation_from_matches", "refine_pose_with_matches", "save_model", "splat", "io", "refine_matches", "AlignConfig", "SparseConfig",
    "EpipolarConfig", "refine_epipolar", "localize", "Localization",
]
