"""Run a PointmapNet exported by ``python -m export`` through onnxruntime.

``load_onnx(path)`` returns an :class:`OnnxPointmapModel` with the PyTorch model's call contract::

    model = pm.load_model("exports/small")        # a directory written by the exporter, or one .onnx file
    pred = model(img1, img2)                      # [B, 3, H, W] float in [0, 1] -> PairPrediction
    enc = model.encode(img)                       # Encoded(tokens [B, N, enc_dim], grid (h, w), local)
    pred = model.decode_pair(enc1, enc2)          # decoders + heads on cached encoder outputs

Inputs are checked exactly as ``PointmapNet`` checks them (same ShapeError messages); normalisation and
the output transforms are inside the graphs. An export made with ``--split`` has an encoder graph (run
once per image) and a decoder+heads graph (run per pair); a single-graph export still supports
``encode``/``decode_pair`` (so ``pm.predict_pairs`` works), but then re-encodes each image per pair.

onnxruntime is imported lazily: ``import pointmap`` does not need it.
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from pointmap.checkpoint import provenance_ok, warn_if_noncommercial
from pointmap.errors import CheckpointError, ShapeError, is_int
from pointmap.model.config import ModelConfig
from pointmap.model.net import Encoded, PointmapNet
from pointmap.prediction import PairPrediction

log = logging.getLogger(__name__)

# -- the export format (shared with export/, which imports these names) ------------------------------
FORMAT = "pointmap-onnx/1"
SIDECAR = "pointmap_export.json"          # next to the graphs; also embedded in each graph's metadata
METADATA_KEY = "pointmap"                 # ModelProto.metadata_props key holding the sidecar JSON
AFTER_STAMP = ("parity", "files")         # sidecar keys written after the graphs were stamped (not in their metadata)
FULL_GRAPH, ENCODER_GRAPH, DECODER_GRAPH = "model.onnx", "encoder.onnx", "decoder.onnx"
PRED_FIELDS = ("pts1_cam1", "pts2_cam1", "conf1", "conf2", "desc1", "desc2", "desc_conf1", "desc_conf2",
               "cam2_to_cam1", "focal1", "focal2")

PROVIDER_ALIASES = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "trt": "TensorrtExecutionProvider",
    "dml": "DmlExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
}
_AUTO_ORDER = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")


def output_names(cfg: ModelConfig) -> list[str]:
    """Graph outputs of a full or decoder graph, in this order (PairPrediction field names): the pointmaps and
    confidences, the descriptors (models with a descriptor head), the pose head's transform (with a pose head),
    both views' focals (with a focal head)."""
    return list(PRED_FIELDS[:4]) + (list(PRED_FIELDS[4:8]) if cfg.has_desc else []) + \
        (["cam2_to_cam1"] if cfg.pose_head else []) + (["focal1", "focal2"] if cfg.focal_head else [])


def _ort():
    try:
        import onnxruntime
    except ImportError:  # pragma: no cover - depends on the environment
        raise CheckpointError("running an ONNX export needs onnxruntime: pip install 'pointmap[export]'") from None
    return onnxruntime


def resolve_providers(providers=None) -> list:
    """``None``/"cpu" -> CPU; "auto" -> TensorRT, CUDA, CPU (those installed); names or aliases
    ("cuda", "tensorrt") or (name, options) tuples as onnxruntime takes them. CPU is always appended
    as the fallback. Raises CheckpointError for a provider this onnxruntime build does not have."""
    ort = _ort()
    available = ort.get_available_providers()
    if providers is None:
        providers = ["CPUExecutionProvider"]
    elif isinstance(providers, str):
        providers = [p for p in _AUTO_ORDER if p in available] if providers == "auto" else [providers]
    elif not isinstance(providers, (list, tuple)):
        raise CheckpointError(f"providers expected None, 'auto', a provider name or a list of names and "
                              f"(name, options) tuples, got {type(providers).__name__}")
    out = []
    for p in providers:
        if not (isinstance(p, str) or (isinstance(p, tuple) and len(p) == 2 and isinstance(p[0], str)
                                       and isinstance(p[1], (dict, type(None))))):
            raise CheckpointError(f"providers expected provider names and (name, options) tuples, got {p!r}")
        name, opts = (p if isinstance(p, tuple) else (p, None))
        name = PROVIDER_ALIASES.get(str(name).lower(), name)
        if name not in available:
            raise CheckpointError(f"onnxruntime provider {name!r} is not available here; available: {available}")
        out.append((name, opts) if opts else name)
    if "CPUExecutionProvider" not in [p[0] if isinstance(p, tuple) else p for p in out]:
        out.append("CPUExecutionProvider")
    return out


def session_options(threads: int | None = None):
    """Tuned session options: all graph optimisations, sequential execution, ``threads`` intra-op
    threads (default: onnxruntime's choice, one per physical core)."""
    ort = _ort()
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if threads is not None:
        if not is_int(threads) or int(threads) < 1:
            raise ValueError(f"threads expected an int >= 1, got {threads!r}")
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
    so.log_severity_level = 3  # errors only: the dynamo graphs make ORT warn about unused initialisers
    return so


def read_metadata(path) -> dict:
    """The sidecar of an export: from ``DIR/pointmap_export.json`` or from a graph's metadata."""
    path = Path(path)
    if path.is_dir():
        side = path / SIDECAR
        if side.exists():
            try:
                meta = json.loads(side.read_text(encoding="utf-8"))
            except (json.JSONDecodeError, UnicodeDecodeError, OSError) as e:
                raise CheckpointError(f"{side} is not valid JSON (UTF-8): {e}") from None
        else:
            graphs = sorted(path.glob("*.onnx"))
            if not graphs:
                raise CheckpointError(f"{path} holds no .onnx graph and no {SIDECAR}")
            meta = read_metadata(graphs[0])
    else:
        import onnx

        try:
            proto = onnx.load(str(path), load_external_data=False)
        except Exception as e:  # noqa: BLE001 - any parse failure is a bad file
            raise CheckpointError(f"cannot read {path} as an ONNX model (corrupt or truncated?): {e}") from None
        props = {p.key: p.value for p in proto.metadata_props}
        if METADATA_KEY not in props:
            side = path.parent / SIDECAR
            if side.exists():
                return read_metadata(path.parent)
            raise CheckpointError(f"{path} is not a pointmap ONNX export (no '{METADATA_KEY}' metadata, "
                                  f"no {SIDECAR} beside it)")
        try:
            meta = json.loads(props[METADATA_KEY])
        except json.JSONDecodeError as e:
            raise CheckpointError(f"{path}: its '{METADATA_KEY}' metadata is not valid JSON: {e}") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: its export metadata expected a JSON object, got {type(meta).__name__}")
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: unsupported export format {meta.get('format')!r} (expected {FORMAT!r})")
    return meta


def _with_weights(graph: Path) -> list[Path]:
    """The graph file and the external weights files it names (none when its weights are inline)."""
    import onnx
    from onnx.external_data_helper import ExternalDataInfo, uses_external_data

    proto = onnx.load(str(graph), load_external_data=False)
    return [graph] + sorted({graph.parent / ExternalDataInfo(t).location for t in proto.graph.initializer
                             if uses_external_data(t)})


def _sha256(f: Path) -> str:
    """The SHA-256 (hex) of one file, read in 4 MB blocks."""
    import hashlib

    h = hashlib.sha256()
    with open(f, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def file_digests(folder: Path) -> dict:
    """{name: {"bytes", "sha256"}} of every file in ``folder``: what the exporter lists in the sidecar (``files``)
    and ``load_onnx`` checks each graph and weights file it loads against before it computes with them."""
    return {f.name: {"bytes": f.stat().st_size, "sha256": _sha256(f)}
            for f in sorted(p for p in Path(folder).iterdir() if p.is_file())}


def _check_digests(meta: dict, folder: Path, graph: Path) -> None:
    """CheckpointError unless ``graph`` and each weights file it names, where the sidecar's ``files`` lists them
    (files in the export's own folder; exports before session 93 list none and load unchecked, without parsing the
    graph), have the listed size and SHA-256: a graph or weights file truncated, corrupted or replaced since the
    export would otherwise load, and compute with weights the description does not describe."""
    files = meta.get("files")
    if files is None:
        return
    if not (isinstance(files, dict) and all(isinstance(v, dict) and is_int(v.get("bytes"))
                                            and isinstance(v.get("sha256"), str) for v in files.values())):
        raise CheckpointError(f"{folder}: its export metadata's files expected a JSON object of file name -> "
                              f"{{'bytes': int, 'sha256': str}}, got {str(files)[:200]}")
    for f in _with_weights(graph):
        listed = files.get(f.name) if f.parent.resolve() == folder.resolve() else None
        if listed is None:
            continue
        size = f.stat().st_size
        if size != listed["bytes"]:
            raise CheckpointError(f"{f} is {size} bytes where its export lists {listed['bytes']} (truncated or "
                                  "replaced since the export?): export again")
        if _sha256(f) != listed["sha256"]:
            raise CheckpointError(f"{f} does not match the SHA-256 its export lists (corrupted or modified since the "
                                  "export): export again")


def _check_same_export(graph: Path, session, meta: dict) -> None:
    """CheckpointError unless the description ``graph`` carries (stamped by the exporter, read from its loaded
    ``session``; old graphs may carry none) is ``meta``'s, the parity report and the file digests aside (added after
    the stamp): a folder holding graphs of different exports would otherwise run weights the description does not
    describe."""
    try:
        text = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        own = json.loads(text) if text is not None else None
    except Exception:  # noqa: BLE001 - unreadable metadata: read_metadata reports it where it is the source
        return
    if isinstance(own, dict) and {k: v for k, v in own.items() if k not in AFTER_STAMP} != \
            {k: v for k, v in meta.items() if k not in AFTER_STAMP}:
        raise CheckpointError(f"{graph} belongs to another export than the description it was loaded with (created "
                              f"{own.get('provenance', {}).get('created')!r}, the description "
                              f"{meta.get('provenance', {}).get('created')!r}): export again into a folder of its own")


def _check_io(graph: Path, session, meta: dict, file: str) -> None:
    """CheckpointError unless the loaded graph takes the inputs and gives the outputs its description lists (a
    graph without the description's metadata, e.g. from another export, would otherwise fail inside onnxruntime at
    the first call); the pose head's transform may be missing (exports before session 49)."""
    graphs = meta.get("graphs") or {}
    if not isinstance(graphs, dict):
        raise CheckpointError(f"{graph}: its export metadata's graphs expected a JSON object (role -> graph "
                              f"description), got {type(graphs).__name__}")
    listed = next((g for g in graphs.values() if isinstance(g, dict) and g.get("file") == file), None)
    if listed is None:
        return
    ins = [i.name for i in session.get_inputs()]
    outs = {o.name for o in session.get_outputs()}
    missing = [o for o in listed.get("outputs", []) if o not in outs and o != "cam2_to_cam1"]
    if ins != list(listed.get("inputs", ins)) or missing:
        raise CheckpointError(f"{graph} takes inputs {ins} and lacks outputs {missing}, but its export's description "
                              f"lists inputs {listed.get('inputs')}: a graph of another export; export again into a "
                              "folder of its own")


class _ImageBatch:
    """What ``encode`` returns for a single-graph export: the images themselves, encoded later per pair.
    Quacks like Encoded (``tokens``, ``grid``, slicing, ``type(x)(tokens, grid)``)."""

    __slots__ = ("tokens", "grid")

    def __init__(self, tokens: torch.Tensor, grid: tuple) -> None:
        self.tokens, self.grid = tokens, grid

    def __getitem__(self, idx) -> _ImageBatch:
        return _ImageBatch(self.tokens[idx], self.grid)


class OnnxPointmapModel:
    """onnxruntime-backed model with PointmapNet's call contract (see the module docstring).

    Attributes: ``cfg`` (ModelConfig), ``meta`` (the export sidecar), ``split`` (encoder/decoder graphs),
    ``providers`` (the session's providers), ``path``. Tensors go in and come out on the CPU.
    """

    check_images = PointmapNet.check_images  # the same shape and range checks and messages as the PyTorch model
    # (not its dtype and device check, which reads parameters: the runner casts any float images to float32 on
    # the CPU, float64 ones included, which the PyTorch model refuses)
    check_encodings = PointmapNet.check_encodings

    def __init__(self, path, meta: dict, providers=None, threads: int | None = None, graph=None) -> None:
        """``path``: the export's folder; ``graph``: a single-graph export's file when it is not the folder's
        ``model.onnx`` (a lone .onnx file, loaded by its own name)."""
        ort = _ort()
        self.path = Path(path)
        self.meta = meta
        try:
            self.cfg = ModelConfig.from_dict(meta["architecture"])
        except (KeyError, TypeError) as e:
            raise CheckpointError(f"{path}: export metadata has no usable architecture ({e})") from None
        self.split = bool(meta.get("split"))
        self.precision = meta.get("precision", "fp32")
        self.provenance = meta.get("provenance", {})
        if not provenance_ok(self.provenance):
            raise CheckpointError(f"{path}: export metadata's provenance expected a dict with a positive int "
                                  f"image_size (or none), got {self.provenance!r}")
        self._out_names = output_names(self.cfg)
        provs = resolve_providers(providers)
        so = session_options(threads)
        files = [ENCODER_GRAPH, DECODER_GRAPH] if self.split else [FULL_GRAPH]
        self._sessions = {}
        self.graph_files = []  # the graph files loaded (``files_used``)
        for f in files:
            gp = Path(graph) if graph is not None and not self.split else self.path / f
            self.graph_files.append(gp)
            if not gp.exists():
                raise CheckpointError(f"{self.path} is missing {f} (listed as {'split' if self.split else 'full'} export)")
            try:
                self._sessions[f] = ort.InferenceSession(str(gp), sess_options=so, providers=provs)
            except Exception as e:  # noqa: BLE001 - ORT raises several types for a bad graph
                raise CheckpointError(f"onnxruntime cannot load {gp}: {str(e).splitlines()[0][:300]}") from None
            _check_same_export(gp, self._sessions[f], meta)
            _check_io(gp, self._sessions[f], meta, f)
            _check_digests(meta, self.path, gp)  # last: the checks above say more about a graph of another export
        # an export written before the pose head's transform was a graph output (session 49) lacks it: the
        # prediction then has no cam2_to_cam1, and relative_pose falls back to the pointmaps' Procrustes
        have = {o.name for o in self._sessions[files[-1]].get_outputs()}
        self._out_names = [n for n in self._out_names if n in have or n != "cam2_to_cam1"]
        self.providers = next(iter(self._sessions.values())).get_providers()
        wanted = [p[0] if isinstance(p, tuple) else p for p in provs]
        for f, sess in self._sessions.items():  # onnxruntime falls back to the CPU with at most a log line: say so
            got = sess.get_providers()
            if wanted[0] != "CPUExecutionProvider" and got[0] == "CPUExecutionProvider":
                lost = [p for p in wanted if p not in got]
                warnings.warn(f"onnxruntime could not start {lost} for {f} (e.g. a missing CUDA / TensorRT library); "
                              f"it runs on {got}", RuntimeWarning, stacklevel=2)
        warn_if_noncommercial(self, self.path, "these weights (derived from official ones)")
        self._warned_unsplit = False

    def files_used(self) -> list[Path]:
        """The files this runner computes with: the graphs it loaded, their external weights (as each graph names
        them) and the export's sidecar. What a prediction cache fingerprints: two exports side by side in one folder
        (``v1.onnx``, ``v2.onnx``, each loaded by its own name) are two models."""
        out = [f for gp in self.graph_files for f in _with_weights(gp)]
        side = self.path / SIDECAR
        return out + ([side] if side.is_file() else [])

    # -- torch.nn.Module look-alikes, so code written for PointmapNet runs unchanged -------------------
    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def eval(self) -> OnnxPointmapModel:
        return self

    def to(self, *args, **kwargs) -> OnnxPointmapModel:
        """No-op (the session's providers decide where it runs; tensors stay on the CPU)."""
        return self

    def __repr__(self) -> str:
        kind = "split" if self.split else "single graph"
        return f"OnnxPointmapModel({str(self.path)!r}, {kind}, {self.precision}, providers={self.providers})"

    # -- helpers --------------------------------------------------------------------------------------
    @staticmethod
    def _np(t: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())

    def _run(self, graph: str, feeds: dict, names: list[str]) -> list[np.ndarray]:
        return self._sessions[graph].run(names, feeds)

    def _prediction(self, outs: list[np.ndarray]) -> PairPrediction:
        return PairPrediction(**{n: torch.from_numpy(o) for n, o in zip(self._out_names, outs)})

    def _check_pair(self, img1: torch.Tensor, img2: torch.Tensor) -> None:
        self.check_images("img1", img1)
        self.check_images("img2", img2)
        if img1.shape[0] != img2.shape[0]:
            raise ShapeError(f"img1 and img2 need the same batch size, got {img1.shape[0]} and {img2.shape[0]}")

    # -- the PointmapNet contract ---------------------------------------------------------------------
    def __call__(self, img1: torch.Tensor, img2: torch.Tensor) -> PairPrediction:
        return self.forward(img1, img2)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> PairPrediction:
        self._check_pair(img1, img2)
        if not self.split:
            outs = self._run(FULL_GRAPH, {"img1": self._np(img1), "img2": self._np(img2)}, self._out_names)
            return self._prediction(outs)
        if img1.shape[-2:] == img2.shape[-2:]:  # one encoder run for both views, as PointmapNet does
            both = self._encode(torch.cat([img1, img2], dim=0))  # checked above
            B = img1.shape[0]
            return self.decode_pair(both[:B], both[B:])
        return self.decode_pair(self._encode(img1), self._encode(img2))

    def encode(self, img: torch.Tensor):
        """[B, 3, H, W] in [0, 1] -> Encoded(tokens [B, h*w, enc_dim], grid (h, w)), h = H / patch; checked with
        ``check_images`` as PointmapNet.encode is. For a single-graph export this defers the work to
        ``decode_pair``."""
        self.check_images("img", img)
        return self._encode(img)

    def _encode(self, img: torch.Tensor):
        p = self.cfg.patch_size
        grid = (int(img.shape[-2]) // p, int(img.shape[-1]) // p)
        if not self.split:
            if not self._warned_unsplit:
                log.warning("%s is a single-graph export: each image is re-encoded for every pair; "
                            "export with --split to encode once per image", self.path)
                self._warned_unsplit = True
            return _ImageBatch(img, grid)
        names = ["tokens", "local"] if self.cfg.desc_stem else ["tokens"]
        outs = self._run(ENCODER_GRAPH, {"img": self._np(img)}, names)
        B, h, w, C = outs[0].shape
        local = torch.from_numpy(outs[1]).reshape(B, h * w, -1) if self.cfg.desc_stem else None
        return Encoded(torch.from_numpy(outs[0]).reshape(B, h * w, C), (h, w), local)

    def decode_pair(self, enc1, enc2) -> PairPrediction:
        """Decoders and heads on two Encoded batches of equal batch size -> PairPrediction, checked as
        PointmapNet.decode_pair checks them (``check_encodings``)."""
        if isinstance(enc1, _ImageBatch) or isinstance(enc2, _ImageBatch):
            if not (isinstance(enc1, _ImageBatch) and isinstance(enc2, _ImageBatch)):
                raise ShapeError("decode_pair got one deferred and one real encoding; use this model's encode for both")
            self.check_images("enc1", enc1.tokens)  # the images the deferred encodings hold
            self.check_images("enc2", enc2.tokens)
            if enc1.tokens.shape[0] != enc2.tokens.shape[0]:
                raise ShapeError(f"batch sizes differ: {enc1.tokens.shape[0]} and {enc2.tokens.shape[0]}")
            outs = self._run(FULL_GRAPH, {"img1": self._np(enc1.tokens), "img2": self._np(enc2.tokens)},
                             self._out_names)
            return self._prediction(outs)
        if not self.split:
            raise ShapeError(f"{self.path} is a single-graph export: it decodes only its own encode()'s outputs, not "
                             "encoder tokens (export with --split for a decoder graph)")
        self.check_encodings(enc1, enc2)
        feeds = {}
        for k, enc in ((1, enc1), (2, enc2)):
            t, (h, w) = enc.tokens, enc.grid
            feeds[f"tokens{k}"] = self._np(t).reshape(t.shape[0], h, w, t.shape[2])
            if self.cfg.desc_stem:
                feeds[f"local{k}"] = self._np(enc.local).reshape(t.shape[0], h, w, -1)
        return self._prediction(self._run(DECODER_GRAPH, feeds, self._out_names))


def load_onnx(path, providers=None, threads: int | None = None, **kwargs) -> OnnxPointmapModel:
    """Load an export written by ``python -m export``: its directory, or one of its .onnx files.

    providers: None (CPU), "auto" (TensorRT > CUDA > CPU, those installed), or a list of onnxruntime
    provider names / aliases ("cuda", "tensorrt") / (name, options) tuples.
    threads: intra-op threads (default: onnxruntime's choice). Raises CheckpointError with the reason.
    ``device`` (as ``pm.load_model`` passes it), when ``providers`` is not given: "cpu" (the default), "cuda" or
    "cuda:N" (onnxruntime's CUDA provider on GPU N: CheckpointError when this onnxruntime has none, a warning when it
    falls back to the CPU) or "auto" (TensorRT > CUDA > CPU, those installed). Any other device is refused.
    """
    device = kwargs.pop("device", None)
    if kwargs:
        raise TypeError(f"load_onnx got unexpected arguments: {sorted(kwargs)}")
    if providers is None and device is not None:
        dev = str(device)
        if dev == "auto":
            providers = "auto"
        elif dev.startswith("cuda"):  # a CPU-only onnxruntime ran "auto" on the CPU without a word, cuda:3 on GPU 0
            try:
                index = torch.device(dev).index
            except RuntimeError:
                index = -1
            if index is not None and index < 0:
                raise CheckpointError(f"device expected 'cpu', 'cuda', 'cuda:N' or 'auto' for an ONNX export, got {dev!r}")
            providers = [("CUDAExecutionProvider", {"device_id": index or 0})]
        elif dev != "cpu":
            raise CheckpointError(f"an ONNX export runs through onnxruntime on 'cpu', 'cuda', 'cuda:N' or 'auto', got "
                                  f"device {dev!r}")
    path = Path(os.fspath(path))
    if not path.exists():
        raise CheckpointError(f"ONNX export not found: {path}")
    meta = read_metadata(path)
    root = path if path.is_dir() else path.parent
    return OnnxPointmapModel(root, meta, providers=providers, threads=threads, graph=None if path.is_dir() else path)
