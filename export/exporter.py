"""torch -> ONNX: export the graphs, convert precision, check parity, write the sidecar, atomically.

``export_model(model, out_dir)`` is the library entry point; ``python -m export`` wraps it.
The output directory holds ``model.onnx`` (or ``encoder.onnx`` + ``decoder.onnx`` with ``split=True``),
``<graph>.onnx.data`` files when the weights pass 2 GB, and ``pointmap_export.json`` (also embedded in
each graph's metadata under the key ``pointmap``), which ``pointmap.runtime.onnx.load_onnx`` reads.
"""

from __future__ import annotations

import contextlib
import copy
import datetime as _dt
import io
import json
import logging
import os
import shutil
import time
import warnings
from pathlib import Path

import torch

from export.graphs import graph_specs
from pointmap.checkpoint import provenance_keeping_licence
from pointmap.errors import CheckpointError, is_int
from pointmap.model.net import PointmapNet
from pointmap.runtime.onnx import FORMAT, METADATA_KEY, SIDECAR, file_digests

log = logging.getLogger(__name__)

DEFAULT_OPSET = 18
PROTO_LIMIT = 2 * 1024**3 - 64 * 1024**2  # protobuf's 2 GB limit, with room for the graph itself


def _versions() -> dict:
    import onnx
    import onnxruntime

    out = {"torch": torch.__version__, "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__}
    try:
        import onnxscript

        out["onnxscript"] = onnxscript.__version__
    except ImportError:  # pragma: no cover
        pass
    try:
        from importlib.metadata import version

        out["pointmap"] = version("pointmap")
    except Exception:  # noqa: BLE001 - not installed as a distribution (running from the repo)
        out["pointmap"] = "unknown"
    return out


def param_bytes(model: torch.nn.Module) -> int:
    return sum(t.numel() * t.element_size() for t in model.state_dict().values())


def _rename_dims(ir_model, spec: dict) -> None:
    """Give every graph input/output dimension a readable name (torch.export writes '16*s7' etc.)."""
    import onnx_ir as ir

    names = {**spec["inputs"], **spec["outputs"]}
    for v in list(ir_model.graph.inputs) + list(ir_model.graph.outputs):
        dims = names.get(v.name)
        if dims is None or v.shape is None or len(v.shape) != len(dims):
            continue
        v.shape = ir.Shape([ir.SymbolicDim(d) if isinstance(d, str) else int(d) for d in dims])


def fold_weight_transposes(ir_model) -> int:
    """Replace ``Transpose(initializer)`` by a transposed initializer.

    The encoder runs twice in the single graph, so each weight has two consumers and the exporter's
    optimiser leaves ``MatMul(x, Transpose(W))`` in place; onnxruntime would fold it at load time, but
    int8 quantisation only quantises MatMuls whose weight is an initializer. Returns the number folded."""
    import numpy as np
    import onnx_ir as ir

    graph = ir_model.graph
    folded = 0
    made: dict = {}  # (weight, perm) -> its transposed initializer: a weight read by two Transposes is folded once
    for node in list(graph):
        if node.op_type != "Transpose" or node.domain not in ("", "ai.onnx"):
            continue
        src = node.inputs[0]
        if src is None or not src.is_initializer() or src.const_value is None:
            continue
        perm = node.attributes.get("perm")
        axes = tuple(perm.as_ints()) if perm is not None else None
        new = made.get((src.name, axes))
        if new is None:
            arr = np.ascontiguousarray(np.transpose(src.const_value.numpy(), axes))
            name = f"{src.name}.T"
            while name in graph.initializers:
                name += "_"
            new = ir.Value(name=name, shape=ir.Shape(arr.shape), type=src.type, const_value=ir.tensor(arr, name=name))
            graph.register_initializer(new)
            made[(src.name, axes)] = new
        node.outputs[0].replace_all_uses_with(new)
        graph.remove(node, safe=True)
        if not src.uses() and not src.is_graph_output():
            graph.initializers.pop(src.name)
        folded += 1
    return folded


def export_graphs(model: PointmapNet, tmp: Path, *, split: bool, opset: int, external: bool,
                  fp16: bool = False, quiet: bool = True) -> list[dict]:
    """Export the graph(s) of ``model`` into ``tmp``; returns the specs with measured export seconds.
    fp16: backbone (patch embedding, encoder, decoders) in float16, heads and all inputs/outputs float32."""
    if fp16:
        from export.graphs import half_backbone

        model = half_backbone(model)
    specs = graph_specs(model, split, torch.float16 if fp16 else torch.float32)
    for spec in specs:
        t0 = time.perf_counter()
        chatter = contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext()
        noisy = logging.getLogger("torch.onnx._internal.exporter._registration")  # "torchvision is not installed"
        level = noisy.level
        with warnings.catch_warnings(), chatter:
            warnings.simplefilter("ignore")
            if quiet:
                noisy.setLevel(logging.ERROR)
            try:
                prog = torch.onnx.export(
                    spec["wrapper"].eval(), spec["args"], dynamo=True, opset_version=opset,
                    input_names=list(spec["inputs"]), output_names=list(spec["outputs"]),
                    dynamic_shapes=spec["dynamic_shapes"], optimize=True, verbose=False,
                )
            except Exception as e:
                raise CheckpointError(f"ONNX export of the {spec['role']} graph failed: "
                                      f"{type(e).__name__}: {str(e).splitlines()[0][:400]}") from e
            finally:
                noisy.setLevel(level)
        _rename_dims(prog.model, spec)
        fold_weight_transposes(prog.model)
        got = dict(prog.model.opset_imports)  # onnx_ir: {domain: version}
        if got.get("", opset) != opset:  # the exporter converts only where it can, and says so only in a log
            raise CheckpointError(f"ONNX export of the {spec['role']} graph asked for opset {opset} and got "
                                  f"{got.get('')}: the exporter could not convert it; ask for {got.get('')}")
        path = tmp / spec["file"]
        prog.save(str(path), external_data=external)
        spec["export_seconds"] = round(time.perf_counter() - t0, 1)
        log.info("exported %s in %.1f s", path.name, spec["export_seconds"])
    return specs


def stamp(graph: Path, meta: dict) -> None:
    """Embed the sidecar JSON in a graph's metadata (weights kept where they are: external or inline)."""
    import onnx

    proto = onnx.load(str(graph), load_external_data=False)
    del proto.metadata_props[:]
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    proto.producer_name = "pointmap-export"
    onnx.save(proto, str(graph))


def _foreign_files(folder: Path) -> list[str]:
    """What a folder holds beside an export's own files: a user's notes, a TensorRT engine cache, results saved as
    ``.data``. Replacing the export would delete them. Its own are the sidecar and the files the sidecar lists
    (``files``, since session 93), or for an older export (or an unreadable sidecar) every graph and ``.data`` file."""
    try:
        listed = json.loads((folder / SIDECAR).read_text(encoding="utf-8")).get("files")
    except (OSError, ValueError, AttributeError):  # no sidecar, not JSON (UTF-8), or not an object
        listed = None
    if not isinstance(listed, dict):
        listed = None

    def own(p: Path) -> bool:
        return p.is_file() and (p.name == SIDECAR or (p.name in listed if listed is not None
                                                      else p.suffix in (".onnx", ".data")))

    return sorted(p.name for p in folder.iterdir() if not own(p))


def _replaceable(out: Path) -> None:
    """CheckpointError unless ``out`` is absent, an empty folder, or an export holding nothing else."""
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return
    if not (out.is_dir() and (out / SIDECAR).exists()):
        raise CheckpointError(f"{out} exists and is not a pointmap export: refusing to overwrite it")
    if foreign := _foreign_files(out):
        raise CheckpointError(f"{out} is an export that also holds {foreign[:5]}, which replacing it would delete: "
                              "move them, or export to another folder")


def _atomic_publish(tmp: Path, out: Path) -> None:
    """Move the finished temp dir to ``out``; an existing export there (and nothing else) is replaced. The old
    export is put back if the new one cannot be moved in."""
    _replaceable(out)
    if out.exists():
        if not any(out.iterdir()):
            out.rmdir()
        else:
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
            try:
                os.replace(tmp, out)
            except BaseException:
                os.replace(old, out)
                raise
            shutil.rmtree(old, ignore_errors=True)
            return
    os.replace(tmp, out)


def check_target(out_dir, opset: int) -> Path:
    """The export's folder (new, empty, or an earlier export holding nothing else, which is replaced) and opset
    checked; the folder as a Path. ``python -m export`` calls it before the model loads."""
    import onnx

    top = onnx.defs.onnx_opset_version()
    if not (is_int(opset) and 18 <= opset <= top):
        raise ValueError(f"opset expected an int from 18 (the dynamo exporter's own; it cannot convert down to 17) to "
                         f"{top} (the newest this onnx knows), got {opset!r}")
    if not str(out_dir).strip():
        raise ValueError("out_dir expected a folder to export to, got an empty path")
    out = Path(out_dir).resolve()  # '.' has no name to stage beside; a symlink's target is the folder replaced
    _replaceable(out)
    return out


def export_model(model: PointmapNet, out_dir, *, split: bool = False, opset: int = DEFAULT_OPSET,
                 fp16: bool = False, quantize: str | None = None, parity: str = "standard",
                 provenance: dict | None = None, external_data: bool | None = None, quiet: bool = True) -> dict:
    """Export ``model`` to ``out_dir`` (written atomically) and return the sidecar dict.

    split: encoder graph + decoder/heads graph instead of one graph.
    fp16: encoder and decoders exported in float16, heads and output transforms in float32, inputs and
    outputs float32. quantize="int8": onnxruntime dynamic quantisation of the MatMul weights of the
    exported fp32 graph(s). Only one of the two.
    parity: "full" (224x224, 512x384, 384x512 at batch 1 and 3, plus a mixed-orientation pair),
    "standard" (the three resolutions at batch 1, 224x224 at batch 3), "quick" (224x224, batch 1), or
    "none". fp32 exports must pass max|onnx - torch| <= 1e-4 (1 + max|torch|) per output, or
    CheckpointError is raised and nothing is written; fp16/int8 record their error instead.
    external_data: None = only when the weights exceed protobuf's 2 GB limit.
    """
    from export.parity import PARITY_CASES, check_parity
    from export.precision import quantize_int8

    if not isinstance(model, PointmapNet):
        raise CheckpointError(f"export needs a PointmapNet (PyTorch) model, got {type(model).__name__}")
    for name, flag in (("split", split), ("fp16", fp16), ("quiet", quiet)):
        if not isinstance(flag, bool):  # split="no" would write a split export recorded as "split": "no"
            raise ValueError(f"{name} expected True or False, got {flag!r}")
    if external_data is not None and not isinstance(external_data, bool):
        raise ValueError(f"external_data expected True or False (or None: only past protobuf's 2 GB limit), "
                         f"got {external_data!r}")
    if fp16 and quantize:
        raise ValueError("choose one of fp16 and quantize, not both")
    if quantize not in (None, "int8"):
        raise ValueError(f"quantize expected None or 'int8', got {quantize!r}")
    if not isinstance(parity, str) or (parity not in PARITY_CASES and parity != "none"):
        raise ValueError(f"parity expected one of {sorted(PARITY_CASES) + ['none']}, got {parity!r}")
    out = check_target(out_dir, opset)
    opset = int(opset)  # a NumPy int is an opset too; the sidecar and torch's exporter get a Python int
    prov = provenance_keeping_licence(model, provenance)  # checked (JSON values) before minutes of export
    model = copy.deepcopy(model).float().eval().cpu()  # the caller's model keeps its mode, dtype and device
    new_dirs = [d for d in (out.parent, *out.parent.parents) if not d.exists()]  # innermost first
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    nbytes = param_bytes(model)
    external = external_data if external_data is not None else nbytes > PROTO_LIMIT  # a bool: checked above
    precision = "fp16" if fp16 else "int8" if quantize else "fp32"
    published = False
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        specs = export_graphs(model, tmp, split=split, opset=opset, external=external, fp16=fp16, quiet=quiet)
        if quantize:
            for spec in specs:
                t0 = time.perf_counter()
                quantize_int8(tmp / spec["file"], external=external)
                spec["convert_seconds"] = round(time.perf_counter() - t0, 1)
        meta = {
            "format": FORMAT,
            "architecture": model.cfg.to_dict(),
            "split": split,
            "precision": precision,
            "opset": opset,
            "preprocessing": {
                "input": "RGB float32 [B, 3, H, W] in [0, 1]; H and W positive multiples of patch_size "
                         "(each view may have its own size); the mean/std normalisation is inside the graph",
                "patch_size": model.cfg.patch_size, "mean": list(model.cfg.img_mean), "std": list(model.cfg.img_std),
            },
            "postprocessing": "inside the graph: points exp-normalised (depth_mode), conf = vmin + exp (conf_mode), "
                              "descriptors unit-norm; all outputs channels-last (docs/conventions.md)",
            "graphs": {s["role"]: {"file": s["file"], "inputs": s["inputs"], "outputs": s["outputs"],
                                   "dtype_io": "float32", "external_data": external} for s in specs},
            "provenance": {
                **prov,
                "exporter": "torch.onnx.export(dynamo=True)", "created": _dt.datetime.now(_dt.timezone.utc)
                .isoformat(timespec="seconds"), "versions": _versions(), "parameters_bytes_fp32": nbytes,
                "export_seconds": {s["role"]: s["export_seconds"] for s in specs},
                **({"convert_seconds": {s["role"]: s["convert_seconds"] for s in specs}} if quantize else {}),
            },
        }
        for spec in specs:  # the graphs carry their description even when copied alone
            stamp(tmp / spec["file"], meta)
        if parity != "none":
            from pointmap.runtime.onnx import load_onnx

            runner = load_onnx(tmp)
            report = check_parity(model, runner, PARITY_CASES[parity], strict=precision == "fp32")
            meta["parity"] = report
            del runner
            if not report["passed"]:
                worst = max(report["cases"], key=lambda c: c["worst_ratio"])
                raise CheckpointError(
                    f"ONNX parity check failed: worst {worst['worst_output']} at {worst['case']} differs by "
                    f"{worst['worst_ratio']:.3g}x the tolerance 1e-4 (1 + max|ref|); nothing was written")
        meta["files"] = file_digests(tmp)  # every graph and weights file, checked by load_onnx
        (tmp / SIDECAR).write_text(json.dumps(meta, indent=2) + "\n")
        _atomic_publish(tmp, out)
        published = True
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not published:  # a failed export leaves no folder it made either ("nothing was written")
            for d in new_dirs:
                try:
                    d.rmdir()
                except OSError:  # not empty (something else wrote there meanwhile) or not ours to remove
                    break
    return meta
