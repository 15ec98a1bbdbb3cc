"""The network: config + presets, blocks, heads, PointmapNet, and the cross-view-completion model."""

from pointmap.model.config import PRESETS, ModelConfig
from pointmap.model.net import Encoded, PointmapNet

__all__ = ["PRESETS", "Encoded", "ModelConfig", "PointmapNet"]
