"""Generation at scale: scenes -> rendered view sets -> shards (run as ``python -m data.render``).

Scene ``i`` of a run with seed ``s`` is drawn from ``np.random.default_rng([s, i])`` alone, so any
shard can be rendered on any machine, in any order, by any worker, and comes out byte-identical.
Shard ``k`` holds scenes ``[k * shard_size, (k + 1) * shard_size)``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import queue
import re
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from data.cameras import MOVES, CameraConfig, DegenerateScene, sample_views
from data.geom import CORR_MAX, MAX_SIDE, encode_corr
from data.scene import SCENE_VERSIONS, make_scene
from data.shards import (
    FORMAT,
    ShardError,
    ShardReader,
    completed_shards,
    json_bytes,
    load_json,
    npz_bytes,
    png_bytes,
    save_manifest,
    scene_metas,
    sha256_file,
    shard_name,
    sidecar_name,
    sidecar_problem,
    write_atomic,
    write_shard,
)
from pointmap.errors import is_int

# Seeds in this range are reserved for held-out evaluation sets (data.heldout); training runs refuse them.
RESERVED_SEEDS = range(2**31 - 1000, 2**31)
# The scenes a run draws from its seeds (data.scene.SCENE_VERSIONS), stored in config.json: a run resumes, and a
# held-out set renders again, with its own version (--generator-version); datasets read shards of every version.
# 2: small objects stacked only on the flat tops they were drawn for (1 could put them on the chair placed next).
GENERATOR_VERSION = SCENE_VERSIONS[-1]
SCENE_ATTEMPTS = 8
MAX_VIEWS = 64  # views per scene
# the longest image side --kind pairs can store: correspondences are stored as 1/64-px fixed point of c + 0.5 up to
# CORR_MAX (data.geom), and a correspondence may reach the far edge of a side S (c + 0.5 up to S): 1008
MAX_PAIR_SIZE = int(CORR_MAX) // 16 * 16


@dataclass(frozen=True)
class GenConfig:
    kind: str = "pairs"            # "pairs": corr stored for every accepted pair; "views": N-view sets
    scenes: int = 100
    views: int = 4                 # views rendered per scene
    size: int = 224                # long image side
    shard_size: int = 16           # scenes per shard
    seed: int = 0
    low_texture_share: float = 0.15
    overlap_lo: float = 0.15
    overlap_hi: float = 0.95
    version: int = GENERATOR_VERSION
    format: str = FORMAT
    photo_share: float = 0.0       # share of textures cut from photographs (0: procedural only)
    photo_dirs: tuple = ()         # where the photographs are (default: data.textures.DEFAULT_PHOTO_DIRS)
    photo_fingerprint: str = ""    # of the collection used (filled by generate; checked on resume)
    moves: tuple = ()              # camera move weights in data.cameras.MOVES order; () = CameraConfig's default
    same_camera: float = 0.0       # share of scenes whose views share one camera's intrinsics (CameraConfig)

    def __post_init__(self):
        if self.kind not in ("pairs", "views"):
            raise ValueError(f"kind expected 'pairs' or 'views', got {self.kind!r}")
        for name, lo in (("scenes", 1), ("views", 2 if self.kind == "pairs" else 1), ("size", 32), ("shard_size", 1)):
            v = getattr(self, name)
            if not is_int(v) or v < lo:  # a numpy integer is one, a bool is not
                raise ValueError(f"{name} expected an int >= {lo}, got {v!r}")
            object.__setattr__(self, name, int(v))  # (frozen) a numpy int stored as the int JSON writes
        if self.views > MAX_VIEWS:  # every pair of a scene's views is stored: the count grows as views squared
            raise ValueError(f"views expected at most {MAX_VIEWS} per scene, got {self.views}")
        if self.size % 16 or self.size > MAX_SIDE:  # (a larger one failed after config.json was written)
            raise ValueError(f"size expected a multiple of 16 up to {MAX_SIDE} (the renderer's largest side), got "
                             f"{self.size}")
        if self.version not in SCENE_VERSIONS:
            raise ValueError(f"version expected a generator version of {SCENE_VERSIONS}, got {self.version!r}")
        if self.kind == "pairs" and self.size > MAX_PAIR_SIZE:  # refused before anything is rendered or written
            raise ValueError(f"size expected at most {MAX_PAIR_SIZE} with kind 'pairs' (correspondences are stored as "
                             f"1/64-px fixed point up to pixel {CORR_MAX - 0.5:.2f}, data.geom.CORR_MAX), got {self.size}")
        if not is_int(self.seed) or self.seed < 0 or self.seed >= 2**31:
            raise ValueError(f"seed expected an int in [0, 2**31), got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))
        if not 0 <= self.low_texture_share <= 1:
            raise ValueError(f"low_texture_share expected in [0, 1], got {self.low_texture_share}")
        if not 0 <= self.photo_share <= 1:
            raise ValueError(f"photo_share expected in [0, 1], got {self.photo_share}")
        if not 0 <= self.overlap_lo <= self.overlap_hi <= 1:
            raise ValueError(f"overlap expected 0 <= lo <= hi <= 1, got {self.overlap_lo}, {self.overlap_hi}")
        self.camera()  # raises ValueError for wrong move weights or a same_camera share outside [0, 1]

    @property
    def n_shards(self) -> int:
        return (self.scenes + self.shard_size - 1) // self.shard_size

    def camera(self) -> CameraConfig:
        extra = {"move_weights": tuple(self.moves)} if self.moves else {}
        return CameraConfig(overlap=(self.overlap_lo, self.overlap_hi), same_camera=self.same_camera, **extra)

    def photos(self):
        """The PhotoCollection of this run, or None when photos are off."""
        if self.photo_share <= 0:
            return None
        from data.textures import DEFAULT_PHOTO_DIRS, photo_collection

        photos = photo_collection(self.photo_dirs or DEFAULT_PHOTO_DIRS)
        if self.photo_fingerprint and photos.fingerprint != self.photo_fingerprint:
            raise ValueError(f"photo collection {list(photos.dirs)} has fingerprint {photos.fingerprint}, but this "
                             f"run was made with {self.photo_fingerprint}: the photographs differ")
        return photos

    def to_dict(self) -> dict:
        """The stored configuration; photo fields only when photos are on (older runs keep resuming)."""
        d = asdict(self)
        d["photo_dirs"] = list(d["photo_dirs"])
        if self.photo_share <= 0:
            for k in ("photo_share", "photo_dirs", "photo_fingerprint"):
                d.pop(k)
        if self.moves:
            d["moves"] = list(self.moves)
        else:
            d.pop("moves")
        if self.same_camera <= 0:
            d.pop("same_camera")
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GenConfig:
        d = dict(d)
        if "photo_dirs" in d:
            d["photo_dirs"] = tuple(d["photo_dirs"])
        if "moves" in d:
            d["moves"] = tuple(d["moves"])
        return cls(**d)


def scene_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index)])


def render_scene(index: int, cfg: GenConfig, renderer):
    """Draw scene ``index`` and render its view set. Returns (tar members, meta)."""
    rng = scene_rng(cfg.seed, index)
    cam = cfg.camera()
    for attempt in range(SCENE_ATTEMPTS):
        scene = make_scene(rng, low_texture_share=cfg.low_texture_share, photos=cfg.photos(),
                           photo_share=cfg.photo_share, version=cfg.version)
        try:
            vs = sample_views(rng, scene, renderer, cfg.views, cfg.size, cam)
        except DegenerateScene:
            continue
        pairs = vs.pairs(cfg.overlap_lo, cfg.overlap_hi)
        if cfg.kind == "pairs" and not pairs:
            continue
        break
    else:  # the views are drawn to overlap within --overlap (CameraConfig) and pairs kept within it: a narrow range
        # is the usual cause, a degenerate scene drawn eight times in a row the rare one
        raise ValueError(f"scene {index}: no usable scene in {SCENE_ATTEMPTS} attempts (seed {cfg.seed}): no view set "
                         f"overlapped within --overlap {cfg.overlap_lo} {cfg.overlap_hi}; widen it")
    prefix = f"scene-{index:08d}"
    v0 = vs.views[0]
    meta = {
        "format": FORMAT, "scene": index, "seed": cfg.seed, "kind": scene.kind, "low_texture": scene.low_texture,
        "attempt": attempt, "width": v0.width, "height": v0.height,
        "views": [{"K": v.K.tolist(), "cam2world": v.cam2world.tolist(), "move": v.move, "ref": v.ref}
                  for v in vs.views],
        "overlap": np.round(vs.overlap, 6).tolist(), "pairs": [list(p) for p in pairs],
    }
    members = [(f"{prefix}/meta.json", json_bytes(meta))]
    for k, v in enumerate(vs.views):
        members.append((f"{prefix}/view-{k}.png", png_bytes(v.rgb)))
        members.append((f"{prefix}/view-{k}.npz", npz_bytes({"depth_z": v.depth.astype(np.float32)})))
    if cfg.kind == "pairs":
        for i, j in pairs:
            members.append((f"{prefix}/pair-{i}-{j}.npz",
                            npz_bytes({"corr_12": encode_corr(vs.corr(i, j)), "corr_21": encode_corr(vs.corr(j, i))})))
    return members, meta


def render_shard(shard: int, cfg: GenConfig, out: Path, renderer, progress=None) -> dict:
    """Render all scenes of one shard and write it atomically (tar first, then its sidecar)."""
    lo = shard * cfg.shard_size
    hi = min(lo + cfg.shard_size, cfg.scenes)
    members, n_pairs, n_views = [], 0, 0
    for i in range(lo, hi):
        m, meta = render_scene(i, cfg, renderer)
        members += m
        n_pairs += len(meta["pairs"])
        n_views += len(meta["views"])
        if progress is not None:
            progress(1)
    return write_shard(out, shard, members, (lo, hi), n_pairs, n_views, seed=cfg.seed)


def shard_is_complete(out: Path, shard: int, seed: int | None = None) -> bool:
    """Shard ``shard`` of ``out`` is there, whole, and this run's: its sidecar is its own (``sidecar_problem``: its
    index, its file name, its tar's name, and its format and seed where recorded), its tar matches the sidecar's
    size and sha256, and, when ``seed`` is given, no scene in it was made with another seed (``scene_metas``)."""
    side, tar = out / sidecar_name(shard), out / shard_name(shard)
    if not (side.is_file() and tar.is_file()):
        return False
    try:
        entry = load_json(side)
        if sidecar_problem(side, entry, seed) is not None:
            return False
    except (OSError, ValueError, KeyError, TypeError, ShardError):
        return False
    if not (tar.stat().st_size == entry.get("bytes") and sha256_file(tar) == entry.get("sha256")):
        return False
    try:
        return scene_metas(ShardReader(tar), entry, seed)[1] is None
    except ShardError:
        return False


def write_manifest(out: Path, cfg: GenConfig) -> dict:
    """Rebuild ``manifest.json`` from the sidecars present (deterministic content, no timestamps)."""
    entries, _ = completed_shards(out, verify=False, warn=False, seed=cfg.seed)
    return save_manifest(out, cfg.to_dict(), entries, complete=len(entries) == cfg.n_shards)


def prepare_out(out: Path, cfg: GenConfig) -> None:
    """Create ``out`` with ``config.json``, or check an existing one matches (resume needs the same config); one
    without a shard yet is replaced. ShardError for a config.json that is not a data.render dataset's."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError, PermissionError) as e:
        raise ValueError(f"--out expected a folder for the dataset, got {str(out)!r}: {e.strerror}") from None
    path = out / "config.json"
    want = cfg.to_dict()
    if path.exists():
        have = load_json(path)
        if have.get("format") != FORMAT:  # e.g. a model folder's config.json
            raise ShardError(f"{out}/config.json is not a data.render dataset's (its format is "
                             f"{have.get('format')!r}, not {FORMAT!r}): use a new --out directory")
        # a run that failed before its first shard (a scene it could not make, a size the renderer refuses) left
        # only its config.json: the corrected command replaces it
        started = any(p.name.startswith("shard-") for p in out.iterdir())
        if started and have.get("version") != want["version"]:
            raise ShardError(f"{out} was rendered by generator version {have.get('version')!r}, this run asks for "
                             f"version {want['version']} (other scenes from the same seeds): resume it with "
                             f"--generator-version {have.get('version')!r}, or use a new --out")
        if started and have != want:
            diff = {k: (have.get(k), want.get(k)) for k in set(have) | set(want) if have.get(k) != want.get(k)}
            raise ShardError(f"{out} holds shards of another configuration (existing vs requested: {diff}); "
                             "use a new --out directory")
        if have != want:
            write_atomic(path, json_bytes(want))
    else:
        write_atomic(path, json_bytes(want))
    _remove_stale_temps(out)


def _remove_stale_temps(out: Path) -> None:
    """Delete temporary files left by killed writers on this host (their process no longer exists)."""
    import socket
    host = socket.gethostname()
    # the whole name: ``.NAME.tmp-HOST-PID`` (data.shards._tmp_path); a glob on ``HOST-*`` also matched another
    # host whose name starts with this one's (``vm-2`` for ``vm``) and deleted its temp files in flight
    pattern = re.compile(rf"\..+\.tmp-{re.escape(host)}-(\d+)")
    for tmp in out.glob(".*.tmp-*"):
        m = pattern.fullmatch(tmp.name)
        if m is None:
            continue
        pid = int(m.group(1))
        try:
            os.kill(pid, 0)
            alive = pid != os.getpid()
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive:
            tmp.unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------------
# workers

_Q = None


def _worker_init(q):
    global _Q
    _Q = q
    import cv2
    cv2.setNumThreads(1)
    # one worker per core: Mesa's llvmpipe rasterises in the worker's own thread rather than in one
    # thread per core of its own (same pixels; less contention). An explicit LP_NUM_THREADS wins.
    os.environ.setdefault("LP_NUM_THREADS", "0")


def _pool_context():
    """Workers are forked (they start at once, everything imported) while this process has not touched
    OpenGL, and spawned otherwise: a forked child must not inherit a live EGL display and context."""
    gl = "pyrender" in sys.modules or "OpenGL" in sys.modules
    return mp.get_context("spawn" if gl or "fork" not in mp.get_all_start_methods() else "fork")


def _worker_shard(args):
    shard, cfg_dict, out = args
    from data.render import get_renderer
    cfg = GenConfig.from_dict(cfg_dict)
    return render_shard(shard, cfg, Path(out), get_renderer(), progress=lambda n: _Q.put(n))


def generate(out, cfg: GenConfig, *, shards: range | None = None, workers: int = 1, progress: bool = True,
             log=print) -> dict:
    """Render the shards in ``shards`` (default: all) that are not complete yet; returns the manifest."""
    from tqdm import tqdm
    out = Path(out)
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers expected an int >= 1, got {workers!r}")
    prepare_out(out, cfg)
    shards = range(cfg.n_shards) if shards is None else shards
    if len(shards) and (shards.start < 0 or shards.stop > cfg.n_shards):
        raise ValueError(f"shard range {shards.start}:{shards.stop} outside 0:{cfg.n_shards}")
    todo = [s for s in shards if not shard_is_complete(out, s, cfg.seed)]
    skipped = len(shards) - len(todo)
    n_scenes = sum(min((s + 1) * cfg.shard_size, cfg.scenes) - s * cfg.shard_size for s in todo)
    if skipped and log:
        log(f"resume: {skipped} of {len(shards)} shards already complete, {len(todo)} to render")
    bar = tqdm(total=n_scenes, unit="scene", disable=not progress, dynamic_ncols=True, desc="render")
    t0 = time.time()
    pairs = 0
    try:
        if workers == 1 or len(todo) <= 1:
            from data.render import get_renderer
            r = get_renderer()
            for s in todo:
                pairs += render_shard(s, cfg, out, r, progress=bar.update)["pairs"]
                bar.set_postfix(pairs=pairs)
        else:
            # an executor, not a multiprocessing.Pool: a Pool replaces a worker that died (the OOM killer, a Mesa
            # crash) and waits forever for the shard it held; the executor fails with BrokenProcessPool
            from concurrent.futures import ProcessPoolExecutor
            from concurrent.futures.process import BrokenProcessPool

            ctx = _pool_context()
            q = ctx.Queue()
            pool = ProcessPoolExecutor(min(workers, len(todo)), mp_context=ctx, initializer=_worker_init,
                                       initargs=(q,))
            try:
                pending = {pool.submit(_worker_shard, (s, cfg.to_dict(), str(out))) for s in todo}
                while pending:
                    try:
                        bar.update(q.get(timeout=0.2))
                    except queue.Empty:
                        pass
                    for f in [f for f in pending if f.done()]:
                        try:
                            pairs += f.result()["pairs"]  # re-raises a worker's exception here
                        except BrokenProcessPool:
                            raise ShardError("a render worker died (killed, or out of memory?): the shards it "
                                             "finished are kept; run the same command again to resume") from None
                        bar.set_postfix(pairs=pairs)
                        pending.remove(f)
                while True:
                    try:
                        bar.update(q.get_nowait())
                    except queue.Empty:
                        break
            except BaseException:  # an error or ^C: the other workers stop now, not after their shards
                for proc in list((getattr(pool, "_processes", None) or {}).values()):
                    if proc.is_alive():
                        proc.terminate()
                raise
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
    manifest = write_manifest(out, cfg)
    dt = time.time() - t0
    if log and todo:
        log(f"rendered {len(todo)} shards, {n_scenes} scenes, {pairs} pairs in {dt:.1f} s "
            f"({pairs / max(dt, 1e-9):.1f} pairs/s); dataset now has {manifest['pairs']} pairs in "
            f"{len(manifest['shards'])}/{cfg.n_shards} shards")
    return manifest


def parse_shards(text: str | None, n: int) -> range:
    if text is None:
        return range(n)
    try:
        a, b = text.split(":")
        lo = int(a) if a else 0
        hi = int(b) if b else n
    except ValueError:
        raise ValueError(f"--shards expected A:B (e.g. 0:10, 10:), got {text!r}") from None
    if not 0 <= lo <= hi <= n:
        raise ValueError(f"--shards {text} outside the run's 0:{n} shards")
    return range(lo, hi)


def build_parser():
    p = argparse.ArgumentParser(prog="python -m data.render", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output directory (created; re-running resumes)")
    p.add_argument("--kind", choices=("pairs", "views"), default="pairs")
    p.add_argument("--scenes", type=int, required=True, help="number of scenes")
    p.add_argument("--views", type=int, default=4, help="views rendered per scene (pairs: all good pairs among them)")
    p.add_argument("--size", type=int, default=224, help="long image side in pixels (multiple of 16)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--shard-size", type=int, default=16, help="scenes per shard")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--shards", default=None, help="A:B: render only shards A..B-1 (cluster job arrays)")
    p.add_argument("--low-texture-share", type=float, default=0.15)
    p.add_argument("--overlap", type=float, nargs=2, default=(0.15, 0.95), metavar=("LO", "HI"))
    p.add_argument("--photo-share", type=float, default=0.0,
                   help="share of textures cut from photographs (needs a collection, see --photo-dirs)")
    p.add_argument("--photo-dirs", nargs="+", default=None,
                   help="directories of photographs (searched recursively) or glob patterns (default: "
                        "/usr/share/backgrounds/mate/nature '/usr/share/backgrounds/*_by_*.jpg' from the Debian "
                        "packages mate-backgrounds and lomiri-wallpapers-16.04)")
    p.add_argument("--moves", default=None,
                   help="camera move weights, e.g. small=0.15,medium=0.15,wide=0.1,zoom=0.1,slide=0.35,pan=0.15 "
                        "(moves not named get 0; default small=0.3,medium=0.25,wide=0.3,zoom=0.15; data/cameras.py)")
    p.add_argument("--same-camera-share", type=float, default=0.0,
                   help="share of scenes whose views are all taken with one camera (view 0's intrinsics); "
                        "the rest draw a field of view per view (data/cameras.py; default 0: renders as "
                        "before)")
    p.add_argument("--generator-version", dest="generator_version", type=int, default=GENERATOR_VERSION,
                   help=f"the scenes' generator version, one of {SCENE_VERSIONS} (default {GENERATOR_VERSION}, the "
                        "latest): an older one renders (or resumes) a dataset made with it, scene for scene")
    p.add_argument("--quiet", action="store_true")
    return p


def parse_moves(text: str | None) -> tuple:
    """``name=weight,...`` -> weights in MOVES order; () for None (the default weights)."""
    if text is None:
        return ()
    weights, seen = dict.fromkeys(MOVES, 0.0), set()
    for part in text.split(","):
        name, eq, value = part.partition("=")
        name = name.strip()
        if name not in weights or not eq:
            raise ValueError(f"--moves expected name=weight pairs with names from {MOVES}, got {part!r}")
        if name in seen:
            raise ValueError(f"--moves names {name!r} twice in {text!r}")
        seen.add(name)
        try:
            weights[name] = float(value)
        except ValueError:
            raise ValueError(f"--moves weight of {name!r} expected a number, got {value!r}") from None
    values = list(weights.values())
    if not all(math.isfinite(v) and v >= 0 for v in values) or sum(values) <= 0:
        raise ValueError(f"--moves expected finite non-negative weights, not all 0, got {text!r}")
    out = tuple(weights[m] for m in MOVES)
    return () if out == tuple(CameraConfig().move_weights) else out  # the default: stored as such


def main(argv=None, *, _allow_reserved: bool = False) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.seed in RESERVED_SEEDS and not _allow_reserved:
            raise ValueError(f"seed {args.seed} is reserved for held-out evaluation sets "
                             f"({RESERVED_SEEDS.start}..{RESERVED_SEEDS.stop - 1}); pick another")
        cfg = GenConfig(kind=args.kind, scenes=args.scenes, views=args.views, size=args.size,
                        shard_size=args.shard_size, seed=args.seed, low_texture_share=args.low_texture_share,
                        overlap_lo=args.overlap[0], overlap_hi=args.overlap[1], photo_share=args.photo_share,
                        photo_dirs=tuple(args.photo_dirs or ()), moves=parse_moves(args.moves),
                        same_camera=args.same_camera_share, version=args.generator_version)
        if cfg.photo_share > 0:
            try:
                fingerprint = cfg.photos().fingerprint
            except FileNotFoundError as e:
                raise ValueError(str(e)) from None
            cfg = replace(cfg, photo_dirs=cfg.photo_dirs or cfg.photos().dirs, photo_fingerprint=fingerprint)
        shards = parse_shards(args.shards, cfg.n_shards)
        if args.workers < 1:
            raise ValueError(f"--workers expected >= 1, got {args.workers}")
        generate(args.out, cfg, shards=shards, workers=args.workers, progress=not args.quiet,
                 log=None if args.quiet else (lambda s: print(s, file=sys.stderr)))
    except (ValueError, ShardError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
