"""Where a model's two-view poses fail: per-pair results broken down by the pairs' true geometry.

A card says RRA@15 67% and RTA@15 19%; it does not say which pairs the directions are lost on. This script joins
one or more per-pair CSVs (``--per-pair`` of ``python -m training.evaluate``, ``benchmarks/bench_pose.py``, or
``benchmarks/model_card.sh MODEL DATA THREADS PER_PAIR.csv``) with the ground truth of the held-out sets they
were measured on, and prints, per band of each property, the pairs, RRA@tol, RTA@tol of the pointmaps' pose and
of the pose the pipeline reports (``pm.pair_pose``), and the median direction error of each model:

- ``baseline``: the distance between the two camera centres over the median depth of view 1 as rendered (the
  ratio that decides how well a translation direction is defined; ``bench_pose.py``'s "short baseline" category
  is its first two bands, measured on the evaluated crop, so its counts can differ by a few pairs);
- ``rotation``: the true rotation angle between the cameras (``paired.py``'s bins);
- ``move``: the data engine's camera move that made the pair (``data/cameras.py``: small, medium, wide, zoom,
  slide, pan; ``composed`` when neither view was drawn from the other, ``unknown`` for sets rendered before moves
  were recorded);
- ``scene``: the scene kind and whether it is low-texture.

A set's rows are matched to its pairs by index, as the evaluation wrote them; where a row records the true rotation
the script checks it against the set's, so a file measured on another set fails instead of being misread.

    python benchmarks/breakdown.py v65h.csv [v66h.csv] --data eval_s424242 eval_p4_s434343 [--names v65h v66h]
        [--tol 15] [--by baseline rotation move scene]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.paired import ROTATION_EDGES, PairedError, read_per_pair  # noqa: E402

BASELINE_EDGES = (0.0, 0.05, 0.1, 0.2, 0.4, 0.8, math.inf)
BREAKDOWNS = ("baseline", "rotation", "move", "scene")
TRUE_ROT_TOL = 0.01  # degrees: a per-pair file's true rotation (written at full precision) against the set's


class BreakdownError(ValueError):
    """A data directory or per-pair file that cannot be joined."""


def _band(x: float, edges) -> str:
    for lo, hi in zip(edges[:-1], edges[1:]):
        if lo <= x < hi:
            return f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">= {lo:g}"
    return f">= {edges[-1]:g}" if x >= edges[-1] else "nan"


def pair_geometry(root) -> list[dict]:
    """The true geometry of every pair of a held-out pairs set, in the order the evaluation numbers them:
    ``{"baseline": |c2 - c1| / the median depth of view 1 as rendered, "rotation": degrees, "move", "kind",
    "low_texture"}``."""
    from data.datasets import PairDataset, camera_rotations_deg, pair_views
    from data.shards import ShardError

    try:
        ds = PairDataset(root, size=224, augment=False, split="all", verify=False)
    except (ShardError, OSError, ValueError) as e:
        raise BreakdownError(f"{root}: {e}") from None
    metas = [meta for meta, _, _ in pair_views(ds)]
    rot = camera_rotations_deg((m["views"][i], m["views"][j]) for m, (_, _, i, j) in zip(metas, ds.items))
    median_depth: dict[tuple, float] = {}  # a view is in several pairs: its depth is decoded once
    out = []
    for (k, scene, i, j), meta, angle in zip(ds.items, metas, rot):
        vi, vj = meta["views"][i], meta["views"][j]
        if (k, scene, i) not in median_depth:
            depth = ds._store.reader(k).read_npz(f"{scene}/view-{i}.npz")["depth_z"]
            valid = depth[np.isfinite(depth) & (depth > 0)]
            median_depth[k, scene, i] = float(np.median(valid)) if valid.size else math.nan
        centres = np.asarray(vj["cam2world"], np.float64)[:3, 3] - np.asarray(vi["cam2world"], np.float64)[:3, 3]
        base = float(np.linalg.norm(centres)) / median_depth[k, scene, i]
        if "move" not in vj or "move" not in vi:
            move = "unknown"
        elif vj.get("ref") == i:
            move = vj["move"]
        elif vi.get("ref") == j:
            move = vi["move"]
        else:
            move = "composed"
        out.append({"baseline": base, "rotation": float(angle), "move": move, "kind": meta.get("kind", "?"),
                    "low_texture": bool(meta.get("low_texture", False))})
    return out


def label(geom: dict, by: str) -> str:
    """The band of one pair's geometry under breakdown ``by``."""
    if by == "baseline":
        return _band(geom["baseline"], BASELINE_EDGES)
    if by == "rotation":
        return _band(geom["rotation"], ROTATION_EDGES)
    if by == "move":
        return geom["move"]
    if by == "scene":
        return f"{geom['kind']}, {'low-texture' if geom['low_texture'] else 'textured'}"
    raise ValueError(f"breakdown expected one of {BREAKDOWNS}, got {by!r}")


def join(results: dict, geometry: dict) -> list[tuple[dict, tuple]]:
    """(geometry, errors) of every row of a per-pair file (``paired.read_per_pair``) whose set is in ``geometry``
    (``{set name: pair_geometry(...)}``); BreakdownError when a row's pair is not in its set, when its recorded
    true rotation disagrees with the set's, or when no row belongs to any of the sets."""
    out = []
    for (s, idx), errs in sorted(results.items()):
        if s not in geometry:
            continue
        g = geometry[s]
        if not 0 <= idx < len(g):
            raise BreakdownError(f"pair {idx} of set {s!r} is not in that set ({len(g)} pairs)")
        if math.isfinite(errs[2]) and abs(errs[2] - g[idx]["rotation"]) > TRUE_ROT_TOL:
            raise BreakdownError(f"pair {idx} of set {s!r}: the file records a true rotation of {errs[2]:.3f} "
                                 f"degrees, the set's is {g[idx]['rotation']:.3f}: measured on another set?")
        out.append((g[idx], errs))
    if not out:
        raise BreakdownError(f"no row belongs to the sets {sorted(geometry)}")
    return out


def summarise(rows: list[tuple[dict, tuple]], by: str, tol: float = 15.0) -> dict:
    """{band: {"pairs", "rra", "rta", "pipe_rta", "dir_med"}} of joined rows (rates in %, NaN where undefined; a
    NaN direction error, a direction the truth does not define, counts as neither hit nor miss)."""
    groups: dict[str, list] = {}
    for g, e in rows:
        groups.setdefault(label(g, by), []).append(e)
    out = {}
    for band, errs in groups.items():
        e = np.asarray(errs, np.float64)

        def rate(col):
            v = e[:, col][np.isfinite(e[:, col])]
            return float(100.0 * np.mean(v < tol)) if v.size else math.nan

        d = e[:, 1][np.isfinite(e[:, 1])]
        out[band] = {"pairs": len(errs), "rra": rate(0), "rta": rate(1), "pipe_rta": rate(4),
                     "dir_med": float(np.median(d)) if d.size else math.nan}
    return out


def _order(bands, by):
    if by in ("baseline", "rotation"):
        edges = BASELINE_EDGES if by == "baseline" else ROTATION_EDGES
        names = [_band(lo, edges) for lo in edges[:-1]]
        return [b for b in names if b in bands] + sorted(b for b in bands if b not in names)
    return sorted(bands)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv", type=Path, nargs="+", help="per-pair CSVs, one per model")
    p.add_argument("--data", type=Path, nargs="+", required=True,
                   help="the held-out sets the files were measured on (a row's set is its directory's name)")
    p.add_argument("--names", nargs="+", default=None, help="the models' names (default: the files' stems)")
    p.add_argument("--tol", type=float, default=15.0, help="degrees: the RRA / RTA threshold (default 15)")
    p.add_argument("--by", nargs="+", default=list(BREAKDOWNS), choices=BREAKDOWNS, help="the breakdowns to print")
    a = p.parse_args(argv)
    if not a.tol > 0:
        p.error(f"--tol expected > 0, got {a.tol}")
    names = a.names or [c.stem for c in a.csv]
    if len(names) != len(a.csv):
        p.error(f"--names expected {len(a.csv)} names (one per CSV), got {len(names)}")
    set_names = [d.resolve().name for d in a.data]
    if len(set(set_names)) != len(set_names):
        p.error(f"--data expected sets with distinct directory names (a per-pair row names its set by it), got "
                f"{', '.join(map(str, a.data))}")
    try:
        geometry = {n: pair_geometry(d) for n, d in zip(set_names, a.data)}
        joined = [join(read_per_pair(c), geometry) for c in a.csv]
    except (PairedError, BreakdownError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t = f"{a.tol:g}"
    for by in a.by:
        tables = [summarise(j, by, a.tol) for j in joined]
        bands = _order(set().union(*tables), by)
        head = " | ".join(f"{n} RRA@{t} | {n} RTA@{t} | {n} pipeline RTA@{t} | {n} median dir" for n in names)
        print(f"\n| {by} | pairs | {head} |")
        print("|---|---|" + "---|" * (4 * len(names)))
        for band in bands:
            cells, counts = [], []
            for tab in tables:
                r = tab.get(band)
                if r is None:
                    cells.append("- | - | - | -")
                    continue
                counts.append(r["pairs"])
                cells.append(" | ".join("-" if math.isnan(r[k]) else f"{r[k]:.1f}"
                                        for k in ("rra", "rta", "pipe_rta", "dir_med")))
            n = str(counts[0]) if len(set(counts)) == 1 else " / ".join(map(str, counts))
            print(f"| {band} | {n} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
