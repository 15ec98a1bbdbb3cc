"""Your own scenes as a training set: ``python -m training.prepare SCENE [SCENE ...] --out DATA/custom``.

A scene folder holds its photographs (the folder's images, or those of its ``images/``), one depth map per
photograph in ``depth/`` or ``depths/`` named by the photograph's stem (``.npy``: float z-depth in the cameras'
units; ``.png``: 16-bit, times ``--depth-png-scale``, millimetres by default; 0, NaN or negative = no depth; any
resolution of the photograph's aspect ratio), and its cameras: a nerfstudio ``transforms.json`` or a COLMAP model
(``sparse/0``), read as ``pointmap reconstruct --cameras`` reads them (OpenCV axes, cam2world, pixel centres at
integers; docs/conventions.md). Photographs without a camera or a depth map are left out, with a note.

The output is the data engine's shard format (docs/data.md, "Shard format"), so ``training.train --data`` and
``data.PairDataset`` read it unchanged and ``python -m data.preview`` draws its correspondences. The views of a
scene are paired by co-visibility, as rendered scenes are: a pair is kept when each view sees between
``--overlap`` lo and hi of the other's pixels with depth, by a depth test with relative tolerance ``--depth-tol``
(``data.geom.correspondences``; real depth is noisier than rendered depth's 0.005). A scene where no pair
qualifies is diagnosed before it is skipped: its nearest view pairs are re-tested with the cameras inverted (a
world-to-camera file), in OpenGL axes, and with the depth in other units, and the reading that makes them overlap
is named. The numbers that matter (pairs kept, their overlap, the share of pixels with depth) are printed per
scene: a dataset whose conventions are wrong shows it here, not after hours of training.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from data.geom import correspondences, encode_corr, invert_rigid, overlap
from data.shards import (
    FORMAT,
    json_bytes,
    load_json,
    npz_bytes,
    png_bytes,
    save_manifest,
    sidecar_name,
    write_atomic,
    write_shard,
)
from pointmap.errors import PointmapError
from pointmap.io.depth import depth_file, read_depth, same_aspect

DEPTH_DIRS = ("depth", "depths")
OPENGL_AXES = np.diag([1.0, -1.0, -1.0, 1.0])
# readings of a scene's files tried when no pair of views overlaps: (name, cam2world map, depth factor)
READINGS = (
    ("as given", lambda T: T, 1.0),
    ("the poses inverted (a world-to-camera file)", invert_rigid, 1.0),
    ("the cameras in OpenGL axes (y up, z backwards)", lambda T: T @ OPENGL_AXES, 1.0),
    ("the depth x 0.001 (millimetres read as metres)", lambda T: T, 1e-3),
    ("the depth x 1000", lambda T: T, 1e3),
)


def find_cameras(scene: Path) -> Path:
    """The scene's ``transforms.json`` or COLMAP model folder. PointmapError when it has neither."""
    if (scene / "transforms.json").is_file():
        return scene / "transforms.json"
    for folder in (scene / "sparse" / "0", scene / "sparse"):
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    raise PointmapError(f"{scene}: expected a transforms.json or a COLMAP model (sparse/0/cameras.bin) for its "
                        "cameras")


def load_scene(scene, max_side: int = 512, png_scale: float = 1e-3, say=print) -> list[dict]:
    """The scene's views: [{"name", "rgb" uint8 [H, W, 3], "depth" float32 [H, W], "K" [3, 3], "cam2world"
    [4, 4]}], every photograph with a camera and a depth map, resized so its long side is at most ``max_side``
    (K exactly: pixel centres at integers), the depth resampled to the photograph's pixels (nearest)."""
    import cv2

    from pointmap.cli import cameras_from_file, expand_images
    from pointmap.images import read_rgb

    scene = Path(scene)
    if not scene.is_dir():
        raise PointmapError(f"a scene expected a folder, got {str(scene)!r}")
    cameras = find_cameras(scene)
    images = expand_images([str(scene)])
    K, cam2world, distortions = cameras_from_file(str(cameras), images, poses=True)
    if distortions:
        names = ", ".join(Path(images[k]).name for k in sorted(distortions)[:3])
        raise PointmapError(f"{scene}: {len(distortions)} photograph(s) with lens distortion ({names}, ...): "
                            "undistort the photographs and depth maps first (pointmap.undistort), then give "
                            "pinhole cameras")
    views, left_out, target = [], [], None
    for k, path in enumerate(images):
        name = Path(path).name
        depth_path = depth_file([scene / f for f in DEPTH_DIRS], Path(path).stem)
        if K is None or k not in K or k not in cam2world or depth_path is None:
            left_out.append(f"{name} ({'no camera' if K is None or k not in K or k not in cam2world else 'no depth'})")
            continue
        rgb = read_rgb(path)
        h, w = rgb.shape[:2]
        depth = read_depth(depth_path, png_scale)
        dh, dw = depth.shape
        if not same_aspect((dw, dh), (w, h)):
            raise PointmapError(f"{depth_path}: {dw}x{dh} is not the aspect ratio of {name} ({w}x{h})")
        Ki = np.asarray(K[k], np.float64).copy()
        if target is None:  # the scene's stored size: the first view's, its long side at most max_side
            s = min(1.0, max_side / max(h, w))
            target = (max(1, round(w * s)), max(1, round(h * s)))
        elif not same_aspect(target, (w, h)):  # PairDataset crops both views of a pair alike
            raise PointmapError(f"{scene}: {name} is {w}x{h}, another shape than the scene's first photograph "
                                f"(stored {target[0]}x{target[1]}): a scene's photographs need one aspect ratio")
        nw, nh = target  # every view of the scene at one size (K scaled per axis)
        if (nw, nh) != (w, h):
            rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
            sx, sy = nw / w, nh / h  # pixel centres at integers: u' = (u + 0.5) s - 0.5
            Ki[0, 0] *= sx
            Ki[0, 2] = (Ki[0, 2] + 0.5) * sx - 0.5
            Ki[1, 1] *= sy
            Ki[1, 2] = (Ki[1, 2] + 0.5) * sy - 0.5
        if depth.shape != (nh, nw):
            # the source pixel under each output pixel's centre (INTER_NEAREST reads floor(x s): up to half a
            # pixel off the resized image and K)
            depth = cv2.resize(depth, (nw, nh), interpolation=cv2.INTER_NEAREST_EXACT)
        views.append({"name": name, "rgb": np.ascontiguousarray(rgb), "depth": depth, "K": Ki,
                      "cam2world": np.asarray(cam2world[k], np.float64)})
    if left_out:
        say(f"{scene}: left out {len(left_out)} photograph(s): {', '.join(left_out[:5])}"
            f"{', ...' if len(left_out) > 5 else ''}")
    return views


def overlaps(views: list[dict], tol: float, stride: int = 4, reading=READINGS[0]) -> np.ndarray:
    """[V, V]: row i, the share of view i's pixels with depth that view j sees (``data.geom.overlap``), the
    diagonal 1; under ``reading`` (one of ``READINGS``: how the files' poses and depth are taken)."""
    _, pose, factor = reading
    n = len(views)
    ov = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i != j:
                a, b = views[i], views[j]
                ov[i, j] = overlap(a["depth"] * factor, a["K"], pose(a["cam2world"]), b["depth"] * factor, b["K"],
                                   pose(b["cam2world"]), stride=stride, rel_tol=tol)
    return ov


def pairs_of(ov: np.ndarray, lo: float, hi: float, per_view: int = 0) -> list[tuple[int, int]]:
    """(i < j) whose overlap is >= lo both ways and whose smaller one is <= hi (the rendered sets' rule); with
    ``per_view`` > 0 only each view's ``per_view`` partners of largest overlap among those (the union: a scene of
    V views gives at most V x per_view pairs, not V^2 / 2)."""
    n = len(ov)
    ok = [(i, j) for i in range(n) for j in range(i + 1, n) if lo <= min(ov[i, j], ov[j, i]) <= hi]
    if per_view <= 0:
        return ok
    keep = set()
    for v in range(n):
        mine = sorted((p for p in ok if v in p), key=lambda p: (-min(ov[p[0], p[1]], ov[p[1], p[0]]), p))
        keep.update(mine[:per_view])
    return sorted(keep)


def diagnose(views: list[dict], tol: float, lo: float, n_pairs: int = 6) -> str:
    """Why no pair overlaps: each ``READINGS`` entry on the ``n_pairs`` view pairs with the nearest camera
    centres, their mean overlap (the smaller of both ways); the best reading named when it beats the given one."""
    centres = np.array([v["cam2world"][:3, 3] for v in views])
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    iu = np.triu_indices(len(views), 1)
    order = np.argsort(dist[iu])[:n_pairs]
    near = [(int(iu[0][q]), int(iu[1][q])) for q in order]
    scores = []
    for reading in READINGS:
        sub = [views[k] for k in sorted({k for p in near for k in p})]
        index = {k: m for m, k in enumerate(sorted({k for p in near for k in p}))}
        ov = overlaps(sub, tol, stride=8, reading=reading)
        scores.append(float(np.mean([min(ov[index[i], index[j]], ov[index[j], index[i]]) for i, j in near])))
    best = int(np.argmax(scores))
    text = (f"no pair of views overlaps by {lo:.2f} or more; on the {len(near)} nearest pairs the mean overlap is "
            f"{scores[0]:.3f} as given")
    if best != 0 and scores[best] > max(2 * scores[0], lo / 2):
        text += f", {scores[best]:.3f} with {READINGS[best][0]}: check the files' convention"
    else:
        text += " and no other reading of the files does better (too little overlap, or wrong depth / cameras)"
    return text


def scene_members(index: int, views: list[dict], pairs, ov, seed: int, source: str,
                  tol: float = 0.005) -> tuple[list, dict]:
    """Tar members and meta.json of one scene, as ``data.generate.render_scene`` writes them."""
    prefix = f"scene-{index:08d}"
    h, w = views[0]["depth"].shape
    meta = {"format": FORMAT, "scene": index, "seed": seed, "kind": "custom", "low_texture": False, "attempt": 0,
            "width": w, "height": h, "source": source,
            "views": [{"K": v["K"].tolist(), "cam2world": v["cam2world"].tolist(), "move": "custom", "ref": 0,
                       "file": v["name"]} for v in views],
            "overlap": np.round(ov, 6).tolist(), "pairs": [list(p) for p in pairs]}
    members = [(f"{prefix}/meta.json", json_bytes(meta))]
    for k, v in enumerate(views):
        members.append((f"{prefix}/view-{k}.png", png_bytes(v["rgb"])))
        members.append((f"{prefix}/view-{k}.npz", npz_bytes({"depth_z": v["depth"]})))
    for i, j in pairs:
        a, b = views[i], views[j]
        c12 = correspondences(a["depth"], a["K"], a["cam2world"], b["depth"], b["K"], b["cam2world"], rel_tol=tol)[0]
        c21 = correspondences(b["depth"], b["K"], b["cam2world"], a["depth"], a["K"], a["cam2world"], rel_tol=tol)[0]
        members.append((f"{prefix}/pair-{i}-{j}.npz", npz_bytes({"corr_12": encode_corr(c12),
                                                                 "corr_21": encode_corr(c21)})))
    return members, meta


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m training.prepare", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", nargs="+", help="scene folders (photographs, depth/, transforms.json or sparse/0)")
    p.add_argument("--out", required=True, help="the dataset folder to write (training.train --data OUT)")
    p.add_argument("--max-side", type=int, default=512, help="long side of the stored views, pixels (default 512)")
    p.add_argument("--depth-png-scale", "--png-depth-scale", dest="depth_png_scale", type=float, default=1e-3,
                   help="scene units per unit of a 16-bit depth PNG (default 0.001: millimetres to metres; the name "
                        "pointmap reconstruct uses, --png-depth-scale is kept as an alias)")
    p.add_argument("--overlap", default="0.15,0.95", help="lo,hi: the pairs kept (default 0.15,0.95, as rendered)")
    p.add_argument("--depth-tol", type=float, default=0.02,
                   help="relative depth agreement of a co-visible pixel (default 0.02; rendered sets use 0.005)")
    p.add_argument("--pairs-per-view", type=int, default=8,
                   help="keep each view's N partners of largest overlap (default 8; 0: every qualifying pair, which "
                   "grows as views^2: 1.5 MB of correspondences per pair at 512 px)")
    p.add_argument("--shard-size", type=int, default=4, help="scenes per shard (default 4)")
    p.add_argument("--seed", type=int, default=0, help="the train / val split's seed (PairDataset)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        lo, hi = (float(x) for x in args.overlap.split(","))
        if not 0 <= lo <= hi <= 1:
            raise ValueError
    except ValueError:
        print(f"error: --overlap expected lo,hi with 0 <= lo <= hi <= 1, got {args.overlap!r}", file=sys.stderr)
        return 2
    bad = [f"--{k.replace('_', '-')} expected > 0, got {getattr(args, k)}"
           for k in ("max_side", "depth_png_scale", "depth_tol", "shard_size") if not getattr(args, k) > 0]
    if args.max_side > 1023:  # stored correspondences are 1/64-px fixed point in 16 bits (data.geom.CORR_MAX)
        bad.append(f"--max-side expected <= 1023 (the shards' correspondence format), got {args.max_side}")
    if bad:
        print("error: " + "; ".join(bad), file=sys.stderr)
        return 2
    resolved = [str(Path(s).resolve()) for s in args.scenes]
    twice = sorted({s for s, r in zip(args.scenes, resolved) if resolved.count(r) > 1})
    if twice:  # (a shell glob and a name of the same folder): its pairs would be stored, and trained on, twice
        print(f"error: the scenes name the same folder more than once ({', '.join(twice)}): its pairs would count "
              "twice", file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.pairs_per_view < 0:
        print(f"error: --pairs-per-view expected >= 0 (0: all), got {args.pairs_per_view}", file=sys.stderr)
        return 2
    config = {"kind": "pairs", "source": "training.prepare", "seed": args.seed, "max_side": args.max_side,
              "pairs_per_view": args.pairs_per_view,
              "png_depth_scale": args.depth_png_scale, "overlap": [lo, hi], "depth_tol": args.depth_tol,
              "shard_size": args.shard_size, "scenes": resolved}
    if (out / "config.json").is_file() and load_json(out / "config.json") != config:
        print(f"error: {out} holds a dataset of other scenes or settings: use a new --out", file=sys.stderr)
        return 2
    if out.exists() and not out.is_dir():
        print(f"error: --out expected a folder, got {str(out)!r}, which is a file", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "config.json", json_bytes(config))
    from tqdm.auto import tqdm

    kept, problems, pending, shards = 0, [], [], []

    def flush():
        if not pending:
            return
        shards.append(write_shard(out, len(shards), [m for ms, _ in pending for m in ms],
                                  (pending[0][1]["scene"], pending[-1][1]["scene"] + 1),
                                  sum(len(m["pairs"]) for _, m in pending), sum(len(m["views"]) for _, m in pending)))
        pending.clear()

    for scene in tqdm(args.scenes, desc="scenes", unit="scene"):
        try:
            views = load_scene(scene, args.max_side, args.depth_png_scale, say=tqdm.write)
        except PointmapError as e:
            problems.append(str(e))
            tqdm.write(f"skipped: {e}")
            continue
        if len(views) < 2:
            problems.append(f"{scene}: {len(views)} usable view(s); a scene needs 2")
            tqdm.write(f"skipped: {problems[-1]}")
            continue
        ov = overlaps(views, args.depth_tol)
        pairs = pairs_of(ov, lo, hi, args.pairs_per_view)
        if not pairs:
            problems.append(f"{scene}: {diagnose(views, args.depth_tol, lo)}")
            tqdm.write(f"skipped: {problems[-1]}")
            continue
        with_depth = np.mean([float((v["depth"] > 0).mean()) for v in views])
        mean_ov = np.mean([min(ov[i, j], ov[j, i]) for i, j in pairs])
        tqdm.write(f"{scene}: {len(views)} views, {len(pairs)} pairs (mean overlap {mean_ov:.2f}), "
                   f"{100 * with_depth:.0f}% of pixels with depth")
        pending.append(scene_members(kept, views, pairs, ov, args.seed, str(Path(scene).resolve()), args.depth_tol))
        kept += 1
        if len(pending) == args.shard_size:
            flush()
    flush()
    for stale in sorted(out.glob("shard-*.tar")):  # shards of an earlier run of these settings beyond this one's
        if stale.stem.split("-")[1].isdigit() and int(stale.stem.split("-")[1]) >= len(shards):
            stale.unlink()
            (out / sidecar_name(int(stale.stem.split("-")[1]))).unlink(missing_ok=True)
    manifest = save_manifest(out, config, shards, complete=True)
    print(f"{out}: {kept} scene(s), {manifest['views']} views, {manifest['pairs']} pairs in {len(shards)} shard(s); "
          f"{len(problems)} scene(s) skipped")
    if not kept:
        print("error: no scene could be used:\n  " + "\n  ".join(problems), file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
