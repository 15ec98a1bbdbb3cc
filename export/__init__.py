"""torch -> ONNX export of PointmapNet, with parity and speed checks (``python -m export --help``).

    from export import export_model
    meta = export_model(model, "exports/small", split=True)      # writes the graphs + pointmap_export.json
    runner = pm.load_model("exports/small")                      # onnxruntime, PointmapNet's call contract

Depends on pointmap (never the reverse): the runtime half lives in ``pointmap.runtime.onnx``.
"""

from export.exporter import DEFAULT_OPSET, export_model
from export.graphs import DecoderGraph, EncoderGraph, FullGraph
from export.parity import PARITY_CASES, check_parity

__all__ = ["DEFAULT_OPSET", "PARITY_CASES", "DecoderGraph", "EncoderGraph", "FullGraph", "check_parity",
           "export_model", "resolve_model"]


def resolve_model(spec: str, seed: int = 0):
    """``preset:NAME`` -> PointmapNet(PRESETS[NAME]) with random weights (seeded); anything else goes to
    ``pointmap.load_model`` (a shipped model name or a checkpoint path) and must give a PyTorch model."""
    import torch

    from pointmap.checkpoint import load_model
    from pointmap.errors import CheckpointError, check_seed
    from pointmap.model import PRESETS, PointmapNet

    if spec.startswith("preset:"):
        name = spec[len("preset:"):]
        if name not in PRESETS:
            raise CheckpointError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
        torch.manual_seed(check_seed(seed))
        model = PointmapNet(PRESETS[name]).eval()
        model.provenance = {"source": spec, "weights": f"random (torch.manual_seed({seed}))"}
        return model
    model = load_model(spec)
    if not isinstance(model, PointmapNet):
        raise CheckpointError(f"{spec} is already an ONNX export; give a PyTorch checkpoint or preset")
    model.provenance = {**(getattr(model, "provenance", None) or {}), "source_spec": spec}
    return model
