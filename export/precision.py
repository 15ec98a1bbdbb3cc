"""int8 variant of an exported graph, converted in place (fp16 is exported directly: export/graphs.py).

int8 is onnxruntime dynamic quantisation: MatMul weights to signed int8 (per output channel),
activations quantised on the fly (uint8). Convolutions stay float32 (onnxruntime's ConvInteger is slow
on CPUs), so the patch embedding and the DPT head are not quantised; the transformer, where the time
goes, is.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from pointmap.errors import CheckpointError


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


def quantize_int8(path, *, external: bool = False, per_channel: bool = True) -> None:
    """Dynamic int8 quantisation of the MatMul weights of the graph at ``path`` (in place)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    path = Path(path)
    tmp = path.with_name(path.stem + ".int8.onnx")
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # quantize_dynamic logs a generic "consider pre-processing" warning
    try:
        quantize_dynamic(str(path), str(tmp), op_types_to_quantize=["MatMul", "Gemm"], per_channel=per_channel,
                         weight_type=QuantType.QInt8, use_external_data_format=external,
                         extra_options={"MatMulConstBOnly": True})
    except Exception as e:
        raise CheckpointError(f"int8 quantisation of {path.name} failed: {type(e).__name__}: {e}") from e
    finally:
        root.setLevel(level)
    data = path.with_name(path.name + ".data")
    if data.exists():
        data.unlink()
    os.replace(tmp, path)
    tmp_data = tmp.with_name(tmp.name + ".data")
    if tmp_data.exists():  # keep the '<graph>.onnx.data' naming: re-save so the references follow
        import onnx

        proto = onnx.load(str(path))  # reads the external data from beside the graph
        _save(proto, path, external=True)
        tmp_data.unlink()
