"""Contact sheet of one shard: ``python -m data.preview SHARD.tar -o out.png``.

One row per pair (or per view set for ``--kind views`` shards): RGB of both views, their depth
(turbo colour map, black = background), valid masks, and correspondences drawn as lines between the
two images (a random sample of co-visible pixels).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from data.geom import decode_corr
from data.shards import ShardError, ShardReader
from pointmap.errors import is_int

TILE = 160


def _fit(img, tile=TILE):
    """Resize keeping the aspect ratio into a tile x tile box (padded with dark grey)."""
    h, w = img.shape[:2]
    s = tile / max(h, w)
    nh, nw = max(1, round(h * s)), max(1, round(w * s))
    r = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)
    out = np.full((tile, tile, 3), 40, np.uint8)
    y0, x0 = (tile - nh) // 2, (tile - nw) // 2
    out[y0:y0 + nh, x0:x0 + nw] = r
    return out, s, x0, y0


def depth_to_color(depth):
    valid = depth > 0
    out = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        inv = np.zeros_like(depth)
        inv[valid] = 1.0 / depth[valid]
        lo, hi = np.percentile(inv[valid], [1, 99])
        n = np.clip((inv - lo) / max(hi - lo, 1e-9), 0, 1)
        col = cv2.applyColorMap((n * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        out[valid] = col[valid]
    return out


def _lines(rgb1, rgb2, corr, rng, n=40):
    t1, s1, x1, y1 = _fit(rgb1)
    t2, s2, x2, y2 = _fit(rgb2)
    canvas = np.concatenate([t1, t2], 1).copy()
    ys, xs = np.nonzero(np.isfinite(corr).all(-1))
    if len(xs):
        pick = rng.choice(len(xs), min(n, len(xs)), replace=False)
        for k in pick:
            u, v = corr[ys[k], xs[k]]
            p1 = (int(round((xs[k] + 0.5) * s1 - 0.5 + x1)), int(round((ys[k] + 0.5) * s1 - 0.5 + y1)))
            p2 = (int(round((u + 0.5) * s2 - 0.5 + x2 + TILE)), int(round((v + 0.5) * s2 - 0.5 + y2)))
            col = tuple(int(c) for c in rng.integers(60, 256, 3))
            cv2.line(canvas, p1, p2, col, 1, cv2.LINE_AA)
            cv2.circle(canvas, p1, 2, col, -1)
            cv2.circle(canvas, p2, 2, col, -1)
    return canvas


def _label(tile, text):
    cv2.putText(tile, text, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def contact_sheet(shard_path, *, max_rows: int = 8, seed: int = 0) -> np.ndarray:
    """The contact sheet image (uint8 RGB) of a shard: at most ``max_rows`` rows (an int >= 1), pairs and
    correspondence lines drawn with ``seed`` (an int >= 0); ValueError naming the argument otherwise."""
    if not (is_int(max_rows) and max_rows >= 1):
        raise ValueError(f"max_rows expected an int >= 1, got {max_rows!r}")
    if not (is_int(seed) and seed >= 0):
        raise ValueError(f"seed expected an int >= 0, got {seed!r}")
    reader = ShardReader(shard_path)
    rng = np.random.default_rng(seed)
    rows = []
    for scene in reader.scenes():
        meta = reader.meta(scene)
        pairs = meta["pairs"] if meta["pairs"] else [[0, min(1, len(meta["views"]) - 1)]]
        i, j = pairs[int(rng.integers(len(pairs)))]
        rgb1 = reader.read_png(f"{scene}/view-{i}.png")
        rgb2 = reader.read_png(f"{scene}/view-{j}.png")
        d1 = reader.read_npz(f"{scene}/view-{i}.npz")["depth_z"]
        d2 = reader.read_npz(f"{scene}/view-{j}.npz")["depth_z"]
        name = f"{scene}/pair-{i}-{j}.npz"
        corr = decode_corr(reader.read_npz(name)["corr_12"]) if name in reader.index else None
        ov = meta["overlap"][i][j]
        tiles = [_label(_fit(rgb1)[0], f"{meta['kind']} {scene[-4:]} v{i}"), _label(_fit(rgb2)[0], f"v{j} ({meta['views'][j]['move']})"),
                 _label(_fit(depth_to_color(d1))[0], f"depth {d1[d1 > 0].min() if (d1 > 0).any() else 0:.2f}-{d1.max():.1f} m"),
                 _fit(depth_to_color(d2))[0],
                 _label(_fit(np.repeat(((d1 > 0) * 255).astype(np.uint8)[..., None], 3, -1))[0], "valid"),
                 _fit(np.repeat(((d2 > 0) * 255).astype(np.uint8)[..., None], 3, -1))[0]]
        if corr is not None:
            tiles.append(_label(_lines(rgb1, rgb2, corr, rng), f"overlap {ov:.2f}"))
        row = np.concatenate(tiles, 1)
        rows.append(row)
        if len(rows) >= max_rows:
            break
    if not rows:
        raise ShardError(f"{shard_path} holds no scenes")
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 2), (0, width - r.shape[1]), (0, 0))) for r in rows]
    return np.concatenate(rows, 0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m data.preview", description=__doc__.split("\n\n")[0])
    p.add_argument("shard", help="a shard-NNNNNN.tar file")
    p.add_argument("-o", "--out", required=True, help="output PNG")
    p.add_argument("--rows", type=int, default=8)
    p.add_argument("--seed", type=int, default=0, help="which pairs and correspondences are drawn (an int >= 0)")
    args = p.parse_args(argv)
    if args.rows < 1:
        p.error(f"--rows expected >= 1, got {args.rows}")
    if args.seed < 0:
        p.error(f"--seed expected an int >= 0, got {args.seed}")
    try:
        if not Path(args.shard).is_file():
            raise ShardError(f"{args.shard} is {'a folder' if Path(args.shard).is_dir() else 'missing'}: expected one "
                             "shard-NNNNNN.tar of a dataset")
        sheet = contact_sheet(args.shard, max_rows=args.rows, seed=args.seed)
    except ShardError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from data.shards import write_atomic

    try:  # encoded in memory (the suffix picks the format), then written whole: nothing half-written is left
        ok, buf = cv2.imencode(Path(args.out).suffix or ".png", sheet[..., ::-1])
        if not ok:
            raise OSError("OpenCV cannot encode this file type")
        write_atomic(Path(args.out), buf.tobytes())
    except (OSError, cv2.error) as e:
        print(f"error: could not write {args.out} ({str(e).strip().splitlines()[0] if str(e).strip() else e})",
              file=sys.stderr)
        return 2
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
