"""pointmap: feed-forward 3D reconstruction (DUSt3R/MASt3R family). See docs/ and DESIGN.md."""

from pointmap.errors import (
    CheckpointError, ConventionError, GraphError, ImageError, PointmapError, ShapeError,
)
from pointmap.prediction import PairPrediction
from pointmap.reconstruction import Reconstruction

__version__ = "0.1.0"

__all__ = [
    "CheckpointError", "ConventionError", "GraphError", "ImageError", "PairPrediction", "PointmapError",
    "Reconstruction", "ShapeError", "__version__",
]
