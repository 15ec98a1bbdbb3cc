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

import contextlib
import contextvars
import functools
import hashlib
import logging
from dataclasses import fields
from pathlib import Path

import torch

from pointmap.atomic import atomic_path
from pointmap.errors import CheckpointError, PointmapError
from pointmap.model.net import autocast_on
from pointmap.prediction import PairPrediction

log = logging.getLogger(__name__)

FORMAT = "pointmap-pair-prediction"
VERSION = "4"  # 3: pose-head models also store cam2_to_cam1 (session 49); 4: focal1 / focal2 (session 56); older
# files are misses


@functools.lru_cache(maxsize=1)
def code_digest() -> bytes:
    """SHA-256 of the library code that turns weights into predictions (``pointmap/model``, the geometry its forward
    pass calls, the ONNX runner, the prediction contract): an edit to the network's code is another key, as other
    weights are."""
    root = Path(__file__).parent
    files = (sorted((root / "model").rglob("*.py")) + sorted((root / "geometry").rglob("*.py"))
             + [root / "runtime" / "onnx.py", root / "prediction.py"])
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.digest()


def model_fingerprint(model) -> str:
    """SHA-256 (hex) of what the model computes with: the library's network code (``code_digest``), a PyTorch
    model's parameters and buffers, non-persistent ones too (names, dtypes, shapes, bytes) with its architecture,
    or the files an ONNX runner loaded (``files_used``: its graphs, their weights, the export's metadata).
    CheckpointError for anything else."""
    h = hashlib.sha256(code_digest())
    cfg = getattr(model, "cfg", None)
    h.update(repr(cfg.to_dict() if hasattr(cfg, "to_dict") else cfg).encode())
    if isinstance(model, torch.nn.Module):
        tensors = sorted(model.state_dict().items())
        # and the buffers state_dict leaves out (persistent=False: PointmapNet's img_mean / img_std, the normalisation
        # every image goes through), so an in-place change to them is another model; module by module under their own
        # names (torch names no public list of them), so a wrapper of a model fingerprints as that model
        tensors += [(f"~{name}", module._buffers[name]) for module in model.modules()
                    for name in sorted(getattr(module, "_non_persistent_buffers_set", ()))
                    if module._buffers.get(name) is not None]
        for name, t in tensors:
            t = t.detach().cpu().contiguous()
            h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        # and the rotary tables' base as each module runs it (``.rope``; in no weight), should a caller have given a
        # model tables of another base than its config says
        bases = [m.rope.base for m in model.modules() if hasattr(getattr(m, "rope", None), "base")]
        h.update(f"|rope {bases}|".encode())
        return h.hexdigest()
    if callable(getattr(model, "files_used", None)):  # an ONNX export: the graphs loaded, their weights, the sidecar
        for p in model.files_used():
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

# (cache, model) pairs whose check ``PredictionCache._vouched`` skips in the current context (thread, task)
_VOUCHED: contextvars.ContextVar[tuple] = contextvars.ContextVar("pointmap_cache_vouched", default=())


class PredictionCache:
    """Pair predictions on disk under ``root/<model fingerprint[:16]>/``, for the model it was made with.
    ``hits`` and ``misses`` count lookups (``predict_pairs`` reports them); ``fingerprint`` is the model's
    (``model_fingerprint``); ``check(model)`` refuses another model, or this one after its weights changed. ``dtype``: what new files hold: float32 (read back bit for bit; at 224 x 224 about 8 MB per directed
    pair with 16-dim descriptors, 1.6 MB without) or float16 (half that, read back as float32; confidences clamped
    to float16's range). A float32 cache takes a float16 file as a miss and rewrites it. A file whose tensors do
    not match the checksum in its header is a miss too. A write that fails (disk full, permissions) is logged once
    and the cache stops writing: it is an optimisation, never a reason to lose the predictions."""

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
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise PointmapError(f"cache expected a directory it can write, got {str(root)!r}: {e.strerror}") from None
        self.hits = self.misses = 0
        self.dtype = dtype
        self.writable = True
        self._autocast_logged = False

    @contextlib.contextmanager
    def _vouched(self, model):
        """Private: within the block, in this thread (a context variable; nested blocks restore the outer state),
        ``check(model)`` passes without hashing. Only for a caller that has just run ``check(model)`` itself (or
        made this cache from ``model``) and runs nothing that changes the weights before the block ends:
        ``reconstruct`` checks once before reading the images and vouches for the model to its own
        ``predict_pairs`` call, which would otherwise hash it again (seconds for a 2 GB model). Weights changed by
        another thread or an ONNX export's files rewritten meanwhile are not seen inside the block."""
        token = _VOUCHED.set(_VOUCHED.get() + ((self, model),))
        try:
            yield self
        finally:
            _VOUCHED.reset(token)

    def __repr__(self) -> str:
        return f"PredictionCache({str(self.dir)!r}, hits={self.hits}, misses={self.misses})"

    def check(self, model) -> None:
        """PointmapError unless ``model`` computes what this cache was made for: its weights hashed again (edits
        through ``.data`` escape PyTorch's version counters, so nothing cheaper is sure; 0.05 s for ``small``),
        except inside ``reconstruct``'s own ``_vouched`` block after it checked."""
        if any(c is self and m is model for c, m in _VOUCHED.get()):
            return
        if model_fingerprint(model) != self.fingerprint:
            raise PointmapError("this prediction cache was made for other weights than the model given (another "
                                "model, or this one changed since): make a PredictionCache for the model")

    def key(self, digest1: bytes, digest2: bytes) -> str:
        """The file name stem of the pair (view 1, view 2), from ``image_digest`` of each (order matters)."""
        return hashlib.sha256(self.fingerprint.encode() + digest1 + digest2).hexdigest()

    def path(self, key: str) -> Path:
        return self.dir / f"{key}.safetensors"

    def keys(self, imgs, edges) -> dict:
        """{(i, j): key} for the directed pairs ``edges`` into ``imgs`` ([3, H, W] tensors), each image hashed once."""
        digests = {k: image_digest(imgs[k]) for k in sorted({k for e in edges for k in e})}
        return {(i, j): self.key(digests[i], digests[j]) for i, j in edges}

    def present(self, imgs, edges, desc: bool = False) -> int:
        """How many of the directed pairs ``edges`` ((i, j) into ``imgs``, [3, H, W] tensors) have a file here
        whose header ``get`` would take (this library's format and version, the pair's key, the descriptors
        ``desc`` asks for, the cache's precision or better); only a file corrupted inside fails later."""
        from safetensors import SafetensorError, safe_open

        n = 0
        for key in self.keys(imgs, edges).values():
            try:
                with safe_open(str(self.path(key)), framework="pt") as f:
                    n += self._unusable(f, key, desc) is None
            except (SafetensorError, OSError, ValueError):
                pass
        return n

    def _unusable(self, f, key: str, desc: bool) -> tuple[bool, str] | None:
        """Why the open cache file ``f`` cannot serve the pair ``key`` (``desc``: with descriptors), as (foreign,
        reason): foreign True for a file that is not this cache's (logged as unreadable), False for one this cache
        must recompute (no descriptors, lower precision); None when it can serve it."""
        meta = f.metadata() or {}
        if meta.get("format") != FORMAT or meta.get("key") != key:
            return True, f"not a pointmap pair prediction for this key (metadata {meta})"
        if meta.get("version") != VERSION:
            return True, f"format version {meta.get('version')!r}, this library reads {VERSION}"
        if desc and "desc1" not in f.keys():
            return False, "no descriptors"
        if meta.get("dtype") == "float16" and self.dtype == torch.float32:
            return False, "float16, this cache writes float32"
        return None

    def get(self, key: str, shape1: tuple, shape2: tuple, desc: bool) -> PairPrediction | None:
        """The cached prediction (batch of one, float32, CPU), or None: absent, without the descriptors ``desc``
        asks for, of lower precision than this cache writes, or unreadable (logged). Without ``desc`` only the
        pointmaps and confidences are read. ``shape1``/``shape2``: the images' (H, W), checked."""
        from safetensors import SafetensorError, safe_open

        path = self.path(key)
        if not path.exists():
            self.misses += 1
            return None
        try:
            with safe_open(str(path), framework="pt") as f:
                why = self._unusable(f, key, desc)
                if why is not None and why[0]:
                    raise ValueError(why[1])
                if why is not None:
                    self.misses += 1
                    return None
                meta = f.metadata()
                tensors = {name: f.get_tensor(name) for name in f.keys()}  # all of them: the checksum covers all
            if tensors_checksum(tensors) != meta.get("sha256"):
                raise ValueError("its tensors do not match the checksum in its header (corrupted)")
            pred = PairPrediction(**{fl.name: None if fl.name not in tensors or (not desc and "desc" in fl.name)
                                     else tensors[fl.name].float() for fl in fields(PairPrediction)})
            if tuple(pred.pts1_cam1.shape[:3]) != (1, *shape1) or tuple(pred.pts2_cam1.shape[:3]) != (1, *shape2):
                raise ValueError(f"its maps are {list(pred.pts1_cam1.shape[1:3])} and {list(pred.pts2_cam1.shape[1:3])}, "
                                 f"the images {list(shape1)} and {list(shape2)}")
        except (SafetensorError, OSError, ValueError, TypeError, RuntimeError, PointmapError) as e:
            log.warning("prediction cache: %s is unreadable (%s); the pair is predicted again", path,
                        str(e).splitlines()[0][:200])
            self.misses += 1
            return None
        self.hits += 1
        return pred

    def put(self, key: str, pred: PairPrediction) -> Path | None:
        """Write one pair's prediction (batch of one) atomically, in the cache's ``dtype``; None when writing
        failed (logged once; no later write is tried) or the prediction was made under ``torch.autocast`` (logged
        once; a later prediction in full precision is written)."""
        from safetensors.torch import save_file

        if pred.batch_size != 1:
            raise PointmapError(f"the cache stores one pair per file, got a batch of {pred.batch_size}")
        if not self.writable:
            return None
        if any(autocast_on(d) for d in ("cpu", "cuda")):  # lower precision than the key says
            if not self._autocast_logged:
                log.warning("prediction cache: predictions made under torch.autocast are not stored (the key holds "
                            "the weights and pixels, not the precision)")
                self._autocast_logged = True
            return None
        big = torch.finfo(self.dtype).max
        tensors = {fl.name: getattr(pred, fl.name).detach().to("cpu", torch.float32).clamp(-big, big)
                   .to(self.dtype).contiguous() for fl in fields(pred) if getattr(pred, fl.name) is not None}
        meta = {"format": FORMAT, "version": VERSION, "key": key, "dtype": str(self.dtype).removeprefix("torch."),
                "sha256": tensors_checksum(tensors)}
        from safetensors import SafetensorError

        path = self.path(key)
        try:
            with atomic_path(path) as tmp:
                save_file(tensors, str(tmp), metadata=meta)
        except (OSError, SafetensorError) as e:  # safetensors reports a full disk as its own error
            log.warning("prediction cache: cannot write %s (%s); the cache stops writing for this run", path,
                        getattr(e, "strerror", None) or str(e).splitlines()[0][:200])
            self.writable = False
            return None
        return path


def tensors_checksum(tensors: dict) -> str:
    """SHA-256 over the tensors' names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()
