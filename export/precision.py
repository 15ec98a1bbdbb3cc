"""Reduced-precision variants of an exported graph, converted in place.

* fp16: weights and activations in float16 with float32 graph inputs/outputs; the ops whose range or
  precision float16 cannot hold stay float32: the RoPE angle tables (Range, Cos, Sin: positions times
  frequencies), the output transforms (Exp: exp-normalised depth and confidences overflow float16 past
  ~11; ReduceL2: norms of points / descriptors), plus onnxconverter-common's own block list (Resize, ...).
  Mainly for GPUs: on a CPU onnxruntime runs most float16 ops through inserted casts.
* int8: onnxruntime dynamic quantisation: MatMul weights to signed int8 (per output channel),
  activations quantised on the fly (uint8). Convolutions stay float32 (onnxruntime's ConvInteger is slow
  on CPUs), so the DPT head is not quantised; the transformer, where the time goes, is.
"""

from __future__ import annotations

import os
from pathlib import Path

from pointmap.errors import CheckpointError

FP16_KEEP_FP32 = ["Range", "Cos", "Sin", "Exp", "ReduceL2", "Erf"]


def _save(proto, path: Path, external: bool) -> None:
    import onnx

    data = path.with_name(path.name + ".data")
    if data.exists():
        data.unlink()
    if external:
        onnx.save_model(proto, str(path), save_as_external_data=True, all_tensors_to_one_file=True,
                        location=data.name, size_threshold=1024)
    else:
        onnx.save_model(proto, str(path))


def convert_fp16(path, *, external: bool = False) -> None:
    """Rewrite the graph at ``path`` in float16 (float32 inputs and outputs kept)."""
    import onnx

    try:
        from onnxconverter_common import float16
    except ImportError:
        raise CheckpointError("--fp16 needs onnxconverter-common: pip install onnxconverter-common") from None
    path = Path(path)
    proto = onnx.load(str(path))
    block = sorted(set(float16.DEFAULT_OP_BLOCK_LIST) | set(FP16_KEEP_FP32))
    half = float16.convert_float_to_float16(proto, keep_io_types=True, op_block_list=block,
                                            disable_shape_infer=external)
    _save(half, path, external)


def quantize_int8(path, *, external: bool = False, per_channel: bool = True) -> None:
    """Dynamic int8 quantisation of the MatMul weights of the graph at ``path`` (in place)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    path = Path(path)
    tmp = path.with_name(path.stem + ".int8.onnx")
    try:
        quantize_dynamic(str(path), str(tmp), op_types_to_quantize=["MatMul", "Gemm"], per_channel=per_channel,
                         weight_type=QuantType.QInt8, use_external_data_format=external,
                         extra_options={"MatMulConstBOnly": True})
    except Exception as e:
        raise CheckpointError(f"int8 quantisation of {path.name} failed: {type(e).__name__}: {e}") from e
    data = path.with_name(path.name + ".data")
    if data.exists():
        data.unlink()
    os.replace(tmp, path)
    tmp_data = tmp.with_name(tmp.name + ".data")
    if tmp_data.exists():  # keep the '<graph>.onnx.data' naming: re-save so the references follow
        import onnx

        proto = onnx.load(str(path), base_dir=str(path.parent))
        _save(proto, path, external=True)
        tmp_data.unlink()
