"""An on-disk cache of pair predictions, so a reconstruction can be run again (other alignment settings, a crash
after hours of inference, more images added to a set) without running the network on pairs it already saw.

One safetensors file per directed pair, named by a SHA-256 over the model's weights and both input images
(their shapes and float32 pixels): a different model, size, crop or image is a different key, never a stale
hit. Files are written atomically; an unreadable or foreign file is reported and counted as a miss (the
prediction is recomputed and the file replaced), never trusted.

    cache = PredictionCache("~/.cache/pointmap/preds", model)
    preds = pm.predict_pairs(model, views, pairs, cache=cache)   # second run: no network call
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import fields
from pathlib import Path

import torch

from pointmap.atomic import atomic_path
from pointmap.errors import CheckpointError, PointmapError
from pointmap.prediction import PairPrediction

log = logging.getLogger(__name__)

FORMAT = "pointmap-pair-prediction"
VERSION = "1"


def model_fingerprint(model) -> str:
    """SHA-256 (hex) of what the model computes with: a PyTorch model's parameters and buffers (names, dtypes,
    shapes, bytes) with its architecture, or an ONNX export's graph files and metadata. CheckpointError for
    anything else."""
    h = hashlib.sha256()
    cfg = getattr(model, "cfg", None)
    h.update(repr(cfg.to_dict() if hasattr(cfg, "to_dict") else cfg).encode())
    if isinstance(model, torch.nn.Module):
        for name, t in sorted(model.state_dict().items()):
            t = t.detach().cpu().contiguous()
            h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
            h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        return h.hexdigest()
    path = getattr(model, "path", None)
    if path is not None and Path(path).is_dir():  # an ONNX export: its graphs and sidecar
        files = sorted(p for p in Path(path).iterdir() if p.is_file() and p.suffix in (".onnx", ".json", ".data"))
        if files:
            for p in files:
                h.update(p.name.encode())
                with open(p, "rb") as f:
                    for block in iter(lambda: f.read(1 << 20), b""):
                        h.update(block)
            return h.hexdigest()
    raise CheckpointError(f"a prediction cache needs a PyTorch model or an ONNX export directory to fingerprint, "
                          f"got {type(model).__name__}")


def image_digest(img: torch.Tensor) -> bytes:
    """SHA-256 of a [3, H, W] image's shape and float32 pixels."""
    t = img.detach().to("cpu", torch.float32).contiguous()
    h = hashlib.sha256(f"{tuple(t.shape)}|".encode())
    h.update(t.numpy().tobytes())
    return h.digest()


class PredictionCache:
    """Pair predictions on disk under ``root/<model fingerprint[:16]>/``. ``hits`` and ``misses`` count lookups
    (``predict_pairs`` reports them); ``fingerprint`` is the model's (``model_fingerprint``). ``dtype``: what new
    files hold: float32 (read back bit for bit; at 224 x 224 about 8 MB per directed pair with 16-dim
    descriptors, 1.6 MB without) or float16 (half that; read back as float32)."""

    def __init__(self, root, model, dtype=torch.float32) -> None:
        if dtype not in (torch.float32, torch.float16):
            raise PointmapError(f"cache dtype expected torch.float32 or torch.float16, got {dtype}")
        if not isinstance(root, (str, Path)):
            raise PointmapError(f"cache expected a directory path, got {type(root).__name__}")
        root = Path(root).expanduser()
        if root.exists() and not root.is_dir():
            raise PointmapError(f"cache expected a directory, got {str(root)!r}, which is a file")
        self.fingerprint = model_fingerprint(model)
        self.dir = root / self.fingerprint[:16]
        self.hits = self.misses = 0
        self.dtype = dtype

    def __repr__(self) -> str:
        return f"PredictionCache({str(self.dir)!r}, hits={self.hits}, misses={self.misses})"

    def key(self, digest1: bytes, digest2: bytes) -> str:
        """The file name stem of the pair (view 1, view 2), from ``image_digest`` of each (order matters)."""
        return hashlib.sha256(self.fingerprint.encode() + digest1 + digest2).hexdigest()

    def path(self, key: str) -> Path:
        return self.dir / f"{key}.safetensors"

    def get(self, key: str, shape1: tuple, shape2: tuple, need_desc: bool) -> PairPrediction | None:
        """The cached prediction (batch of one, float32, CPU), or None: absent, written without the descriptors
        ``need_desc`` asks for, or unreadable (logged). ``shape1``/``shape2``: the images' (H, W), checked."""
        from safetensors import SafetensorError, safe_open

        path = self.path(key)
        if not path.exists():
            self.misses += 1
            return None
        try:
            with safe_open(str(path), framework="pt") as f:
                meta = f.metadata() or {}
                if meta.get("format") != FORMAT or meta.get("key") != key:
                    raise ValueError(f"not a pointmap pair prediction for this key (metadata {meta})")
                if meta.get("version") != VERSION:
                    raise ValueError(f"format version {meta.get('version')!r}, this library reads {VERSION}")
                tensors = {name: f.get_tensor(name) for name in f.keys()}
            pred = PairPrediction(**{fl.name: None if fl.name not in tensors else tensors[fl.name].float()
                                     for fl in fields(PairPrediction)})
            if tuple(pred.pts1_cam1.shape[:3]) != (1, *shape1) or tuple(pred.pts2_cam1.shape[:3]) != (1, *shape2):
                raise ValueError(f"its maps are {list(pred.pts1_cam1.shape[1:3])} and {list(pred.pts2_cam1.shape[1:3])}, "
                                 f"the images {list(shape1)} and {list(shape2)}")
        except (SafetensorError, OSError, ValueError, TypeError, PointmapError) as e:
            log.warning("prediction cache: %s is unreadable (%s); the pair is predicted again", path,
                        str(e).splitlines()[0][:200])
            self.misses += 1
            return None
        if need_desc and not pred.has_desc:
            self.misses += 1
            return None
        self.hits += 1
        return pred

    def put(self, key: str, pred: PairPrediction) -> Path:
        """Write one pair's prediction (batch of one) atomically, in the cache's ``dtype``."""
        from safetensors.torch import save_file

        if pred.batch_size != 1:
            raise PointmapError(f"the cache stores one pair per file, got a batch of {pred.batch_size}")
        tensors = {fl.name: getattr(pred, fl.name).detach().to("cpu", self.dtype).contiguous()
                   for fl in fields(pred) if getattr(pred, fl.name) is not None}
        path = self.path(key)
        with atomic_path(path) as tmp:
            save_file(tensors, str(tmp), metadata={"format": FORMAT, "version": VERSION, "key": key})
        return path
