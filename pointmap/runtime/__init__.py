"""Runtimes other than PyTorch eager. ``pointmap.runtime.onnx``: exported graphs through onnxruntime.

onnxruntime is imported only when an export is loaded (``pm.load_model(DIR)`` or ``load_onnx``).
"""

from pointmap.runtime.onnx import OnnxPointmapModel, load_onnx

__all__ = ["OnnxPointmapModel", "load_onnx"]
