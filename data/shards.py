"""Shards on disk: deterministic, atomic, checksummed (format described in docs/data.md).

A dataset directory holds ``config.json`` (how it was generated), ``shard-NNNNNN.tar`` files (plain
uncompressed tar, members in a fixed order with zeroed metadata), one ``shard-NNNNNN.json`` sidecar
per completed shard (its sha256, size and counts: the sidecar is written after the tar, so a shard
counts as complete only when both exist and agree), and ``manifest.json`` (config + every sidecar,
rebuilt at the end of each run). Images are PNG, arrays ``.npz`` written with fixed zip metadata, so
the same inputs give the same bytes.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import socket
import tarfile
import warnings
import zipfile
from pathlib import Path

import cv2
import numpy as np

from pointmap.errors import PointmapError, is_int

FORMAT = "pointmap-synth/1"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class ShardError(PointmapError):
    """A shard or dataset directory is missing, corrupt (checksum mismatch) or of another config."""


def shard_name(index: int) -> str:
    return f"shard-{index:06d}.tar"


def sidecar_name(index: int) -> str:
    return f"shard-{index:06d}.json"


# ---------------------------------------------------------------------------------------------------
# deterministic encoders / decoders


def png_bytes(rgb: np.ndarray) -> bytes:
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise PointmapError(f"png_bytes expected uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:  # pragma: no cover
        raise PointmapError("PNG encoding failed")
    return buf.tobytes()


def read_png(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ShardError("a PNG member could not be decoded")
    return np.ascontiguousarray(img[..., ::-1])


def npz_bytes(arrays: dict) -> bytes:
    """A standard ``.npz`` (readable by ``np.load``) with fixed zip metadata: same arrays, same bytes."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compresslevel=1)
    return out.getvalue()


def read_npz(data: bytes) -> dict:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def json_bytes(obj) -> bytes:
    return (json.dumps(obj, sort_keys=True, indent=1) + "\n").encode()


# ---------------------------------------------------------------------------------------------------
# atomic writes


def _tmp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{socket.gethostname()}-{os.getpid()}")


def write_atomic(path, data: bytes) -> None:
    """Write ``data`` to a temporary file next to ``path``, fsync, then ``os.replace``: readers see
    the old file or the complete new one, never a torn one."""
    path = Path(path)
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def tar_bytes(members: list) -> bytes:
    """An uncompressed tar of (name, bytes) members in the given order, with zeroed metadata."""
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w", format=tarfile.USTAR_FORMAT) as tf:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = 0
            info.mode = 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            tf.addfile(info, io.BytesIO(data))
    return out.getvalue()


def write_shard(out, index: int, members: list, scenes: tuple, pairs: int, views: int, *, seed=None) -> dict:
    """Write shard ``index`` of ``out`` atomically, its tar first, then its sidecar (what ``completed_shards``
    reads). ``members``: (name, bytes) as ``tar_bytes`` takes them; ``scenes``: its [lo, hi) scene range; ``seed``:
    the run's seed (config.json's), recorded with the format so a shard copied in from another run is told apart.
    Returns the sidecar entry."""
    out = Path(out)
    data = tar_bytes(members)
    write_atomic(out / shard_name(index), data)
    entry = {"index": index, "name": shard_name(index), "sha256": sha256_bytes(data), "bytes": len(data),
             "scenes": list(scenes), "pairs": pairs, "views": views, "format": FORMAT}
    if seed is not None:
        entry["seed"] = seed
    write_atomic(out / sidecar_name(index), json_bytes(entry))
    return entry


def save_manifest(out, config: dict, entries: list, complete: bool) -> dict:
    """Write ``out/manifest.json`` atomically for the shards ``entries`` (``write_shard``'s sidecar entries) made
    with ``config``; deterministic content, no timestamps. Returns the manifest."""
    manifest = {"format": FORMAT, "config": config, "complete": complete, "shards": entries,
                "pairs": sum(e["pairs"] for e in entries), "views": sum(e["views"] for e in entries)}
    write_atomic(Path(out) / "manifest.json", json_bytes(manifest))
    return manifest


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------------
# reading


class ShardReader:
    """Random access to the members of one shard tar (index built once, then seek + read)."""

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_file():
            raise ShardError(f"shard {self.path} does not exist")
        self.index: dict[str, tuple[int, int]] = {}
        try:
            with tarfile.open(self.path, "r:") as tf:
                for m in tf:
                    if m.isfile():
                        self.index[m.name] = (m.offset_data, m.size)
        except tarfile.TarError as e:
            raise ShardError(f"shard {self.path} is not a readable tar: {e}") from e

    def names(self):
        return list(self.index)

    def read(self, name: str) -> bytes:
        if name not in self.index:
            raise ShardError(f"shard {self.path} has no member {name!r}")
        off, size = self.index[name]
        with open(self.path, "rb") as f:
            f.seek(off)
            data = f.read(size)
        if len(data) != size:
            raise ShardError(f"shard {self.path} is truncated at member {name!r}")
        return data

    def read_npz(self, name: str) -> dict:
        """Member ``name`` decoded as an ``.npz``; ShardError naming the shard and the member when it cannot be (a
        shard that passed its checksum can still have been written wrong)."""
        data = self.read(name)  # its own ShardError (no such member, truncated) names both already
        try:
            return read_npz(data)
        except Exception as e:  # noqa: BLE001 - zip, zlib and numpy format errors alike: one message
            raise ShardError(f"shard {self.path}: member {name!r} is not a readable .npz "
                             f"({e.__class__.__name__}: {e})") from None

    def read_png(self, name: str) -> np.ndarray:
        """Member ``name`` decoded as an RGB PNG; ShardError naming the shard and the member when it cannot be."""
        data = self.read(name)
        try:
            return read_png(data)
        except ShardError as e:  # read_png's own "could not be decoded", which names neither
            raise ShardError(f"shard {self.path}: member {name!r}: {e}") from None
        except Exception as e:  # noqa: BLE001 - OpenCV's own errors (an empty member): one message
            raise ShardError(f"shard {self.path}: member {name!r} is not a readable PNG "
                             f"({e.__class__.__name__}: {str(e).strip().splitlines()[-1] if str(e).strip() else e})") from None

    def scenes(self) -> list[str]:
        """Scene prefixes (``scene-XXXXXXXX``) in stored order."""
        seen = []
        for n in self.index:
            p = n.split("/", 1)[0]
            if p.startswith("scene-") and (not seen or seen[-1] != p):
                seen.append(p)
        return seen

    def meta(self, scene: str) -> dict:
        """Scene ``scene``'s ``meta.json``, a JSON object; ShardError naming the shard and the member when it is not
        UTF-8 JSON or not an object."""
        name = f"{scene}/meta.json"
        data = self.read(name)
        try:
            value = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ShardError(f"shard {self.path}: member {name!r} is not valid UTF-8 JSON "
                             f"({e.__class__.__name__}: {e})") from None
        if not isinstance(value, dict):
            raise ShardError(f"shard {self.path}: member {name!r} expected a JSON object, got "
                             f"{type(value).__name__}")
        return value


def load_json(path) -> dict:
    """The JSON object in ``path`` (a dataset's config.json, a shard's sidecar); ShardError naming the file when it
    is not valid JSON or not an object."""
    with open(path) as f:
        try:
            value = json.load(f)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ShardError(f"{path} is not valid JSON ({e})") from None
    if not isinstance(value, dict):
        raise ShardError(f"{path} expected a JSON object, got {type(value).__name__}")
    return value


def sidecar_problem(side, entry: dict, seed=None) -> str | None:
    """Why the sidecar file ``side`` (its JSON object ``entry``) does not describe a shard of its own folder's run,
    or None. Its ``index`` must be an int >= 0, its own file name ``sidecar_name(index)`` and its ``name``
    ``shard_name(index)``: a sidecar copied under another name (a stray copy of shard 0 as ``shard-000007.json``)
    or naming a tar elsewhere describes another shard. ``format`` and ``seed``, which newer sidecars record, must
    be this format and ``seed`` (config.json's; None: not checked) when present; sidecars written before they were
    recorded are accepted. KeyError when ``index`` or ``name`` is missing."""
    side = Path(side)
    index, name = entry["index"], entry["name"]
    if not is_int(index) or index < 0:
        return f"{side.name}: index expected an int >= 0, got {index!r}"
    if side.name != sidecar_name(index):
        return (f"{side.name}: describes shard {index}, whose sidecar is {sidecar_name(index)}, not {side.name} "
                "(a stray or renamed copy)")
    if name != shard_name(index):
        return f"{side.name}: tar name expected {shard_name(index)!r} (shard {index}), got {name!r}"
    if "format" in entry and entry["format"] != FORMAT:
        return f"{side.name}: format expected {FORMAT!r}, got {entry['format']!r}"
    if seed is not None and "seed" in entry and entry["seed"] != seed:
        return (f"{side.name}: made by a run with seed {entry['seed']!r}, but config.json has seed {seed!r} "
                "(a shard of another run)")
    return None


def scene_metas(reader: ShardReader, entry: dict, seed=None) -> tuple[list[tuple[str, dict]], str | None]:
    """``(scene, meta)`` of every scene in the shard ``reader`` (stored order) whose sidecar is ``entry``, and why the
    shard does not belong to the run with ``seed`` (config.json's; None: not checked), or None: a scene whose
    ``meta.json`` carries another ``seed``, or a scene index outside the sidecar's ``scenes`` [lo, hi). (A shard
    rendered by another run and given a sidecar, or renamed, passes its checksum; its scenes tell.) ShardError for
    a ``meta.json`` that cannot be read."""
    out = []
    lo_hi = entry.get("scenes")
    span = tuple(lo_hi) if isinstance(lo_hi, list) and len(lo_hi) == 2 and all(is_int(v) for v in lo_hi) else None
    for scene in reader.scenes():
        meta = reader.meta(scene)
        if seed is not None and "seed" in meta and meta["seed"] != seed:
            return out, (f"{reader.path.name}: {scene} was made with seed {meta['seed']!r}, but config.json has seed "
                         f"{seed!r} (a shard of another run)")
        index = meta.get("scene")
        if span is not None and is_int(index) and not span[0] <= index < span[1]:
            return out, (f"{reader.path.name}: {scene} is scene {index}, outside its sidecar's scenes "
                         f"[{span[0]}, {span[1]}) (a shard renamed from another index)")
        out.append((scene, meta))
    return out, None


def completed_shards(root, *, verify: bool = True, warn: bool = True, seed=None) -> tuple[list[dict], list[str]]:
    """Sidecars of the shards in ``root`` that are complete and (if ``verify``) match their sha256.

    Returns (good entries sorted by index, problems). Problems (missing tar, size or checksum
    mismatch, unreadable sidecar, a sidecar that is not its own shard's or, when ``seed`` is given, records
    another run's seed: ``sidecar_problem``) are reported with a warning and the shard is left out.
    """
    root = Path(root)
    good, problems = [], []
    for side in sorted(root.glob("shard-*.json")):
        try:
            entry = load_json(side)
            missing = sorted({"index", "name", "bytes", "sha256"} - set(entry))
            if missing:
                raise KeyError(", ".join(missing))
            problem = sidecar_problem(side, entry, seed)
        except (OSError, ValueError, KeyError, TypeError, ShardError) as e:
            problems.append(f"{side.name}: unreadable sidecar ({e.__class__.__name__}: {e})")
            continue
        if problem is not None:
            problems.append(f"{problem}; not used")
            continue
        tar = root / entry["name"]
        if not tar.is_file():
            problems.append(f"{entry['name']}: listed but missing")
            continue
        if tar.stat().st_size != entry["bytes"]:
            problems.append(f"{entry['name']}: size {tar.stat().st_size} != {entry['bytes']} in its sidecar")
            continue
        if verify and sha256_file(tar) != entry["sha256"]:
            problems.append(f"{entry['name']}: sha256 mismatch (corrupt or modified); not used")
            continue
        good.append(entry)
    if warn:
        for p in problems:
            warnings.warn(f"{root}: shard skipped: {p}", stacklevel=2)
    good.sort(key=lambda e: e["index"])
    return good, problems
