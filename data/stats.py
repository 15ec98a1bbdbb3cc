"""What a rendered pair set holds: ``python -m data.stats ROOT [ROOT ...] [--split S] [--json]``.

Reads only the scenes' metadata (no image is decoded) and prints, one column per root, the shares a training
set and a held-out set should be compared on before any training: scene kinds, low-texture scenes, the camera
move that made each pair's later view, the rotation between the two cameras (binned as ``training.evaluate``
scores it), their co-visible overlap, and how often the two views have different focal lengths. A training set
whose rotation histogram sits well left of the held-out one's cannot be expected to score wide-baseline pairs
(docs/data.md).

Statistics are over pairs as ``data.datasets.PairDataset`` stores them: the pairs (i, j), i < j, the engine kept,
each once, in the stored order. The loader's random order swap (view j served first, with probability
``swap_p``) changes none of kind, low-texture, rotation, overlap (the smaller of the two directions) and focal
ratio, which are the same either way round; "view 2 by move" counts the move stored with view j, the stored
order's view 2, whichever view the loader serves second. That move is how view j was made from its own reference
view (its ``ref``), which is the pair's view i only when ``ref == i``: in a set of three or more views a pair can
join view j to a view it was not made from (two views made from a third one, or view j made from a view made from
view i). So the statistic says which moves made the views that ended up as a pair's later view, not the motion
between the pair's two views (the rotation and overlap statistics measure that).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np

ROTATION_BINS = (0.0, 15.0, 30.0, 45.0, 90.0, 180.0)  # degrees; the last bin includes 180
OVERLAP_BINS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the smaller of the two views' co-visible fractions
KINDS = ("room", "cluster", "courtyard")
FOCAL_RATIO = 1.01  # above this, the two views' focal lengths count as different


def pair_records(root, split: str = "all", verify: bool = False) -> dict:
    """Per-pair arrays of a ``--kind pairs`` root: ``kind`` (str), ``low_texture`` (bool), ``move`` (str, the move stored with
    view j: how it was made from its own reference view, not necessarily from view i), ``rotation_deg``, ``overlap`` (min of the two directions), ``focal_ratio`` (>= 1), ``scene`` (int);
    plus ``scenes`` (the number of distinct scenes). ShardError (one line) for a root that is not a pair set."""
    from data.datasets import PairDataset, camera_rotations_deg, pair_views

    ds = PairDataset(root, size=64, augment=False, split=split, verify=verify)
    cols: dict[str, list] = {k: [] for k in ("kind", "low_texture", "move", "overlap", "focal_ratio", "scene")}
    views = []
    for meta, i, j in pair_views(ds):
        vi, vj = meta["views"][i], meta["views"][j]
        views.append((vi, vj))
        fi, fj = float(vi["K"][0][0]), float(vj["K"][0][0])
        cols["kind"].append(str(meta.get("kind", "?")))
        cols["low_texture"].append(bool(meta.get("low_texture", False)))
        cols["move"].append(str(vj.get("move", "?")))
        ov = meta.get("overlap")
        cols["overlap"].append(min(float(ov[i][j]), float(ov[j][i])) if ov is not None else math.nan)
        cols["focal_ratio"].append(max(fi, fj) / min(fi, fj))
        cols["scene"].append(int(meta["scene"]))
    out = {k: np.asarray(v) for k, v in cols.items()}
    out["rotation_deg"] = camera_rotations_deg(views)
    out["scenes"] = len(set(cols["scene"]))
    return out


def _bin_labels(edges) -> list[str]:
    return [f"{lo:g}-{hi:g}" for lo, hi in itertools.pairwise(edges)]


def _shares(values: np.ndarray, edges) -> list[float]:
    """Percent of ``values`` in each bin [lo, hi), the last bin closed; NaNs count in no bin."""
    idx = np.clip(np.searchsorted(np.asarray(edges), values, side="right") - 1, 0, len(edges) - 2)
    ok = np.isfinite(values)
    return [100.0 * float(np.mean(ok & (idx == b))) for b in range(len(edges) - 1)]


def summarize(rec: dict) -> dict:
    """Ordered {statistic: value}: counts, then percentages of pairs, then medians."""
    n = len(rec["rotation_deg"])

    def pct(mask) -> float:
        return 100.0 * float(np.mean(mask))

    out = {"scenes": rec["scenes"], "pairs": n}
    for kind in KINDS:
        out[f"kind {kind} %"] = pct(rec["kind"] == kind)
    out["low-texture %"] = pct(rec["low_texture"])
    for move in sorted(set(rec["move"].tolist())):
        out[f"view 2 by move {move} %"] = pct(rec["move"] == move)
    for label, share in zip(_bin_labels(ROTATION_BINS), _shares(rec["rotation_deg"], ROTATION_BINS)):
        out[f"rotation {label} deg %"] = share
    out["median rotation deg"] = float(np.median(rec["rotation_deg"]))
    for label, share in zip(_bin_labels(OVERLAP_BINS), _shares(rec["overlap"], OVERLAP_BINS)):
        out[f"overlap {label} %"] = share
    out["median overlap"] = float(np.nanmedian(rec["overlap"])) if np.isfinite(rec["overlap"]).any() else math.nan
    out[f"focal ratio > {FOCAL_RATIO:g} %"] = pct(rec["focal_ratio"] > FOCAL_RATIO)
    return out


def _cell(statistic: str, v) -> str:
    """A table cell: counts as integers, overlaps to 0.01, percentages and angles to 0.1; "-" for none or NaN."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, int):
        return f"{v:d}"
    return f"{v:.2f}" if statistic == "median overlap" else f"{v:.1f}"


def format_table(names: list[str], summaries: list[dict]) -> str:
    """Markdown table, one row per statistic (the union, in first-seen order), one column per set."""
    rows: list[str] = []
    for s in summaries:
        rows += [k for k in s if k not in rows]
    lines = ["| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for r in rows:
        lines.append(f"| {r} | " + " | ".join(_cell(r, s.get(r)) for s in summaries) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from data.shards import ShardError

    p = argparse.ArgumentParser(prog="python -m data.stats", description=__doc__.split("\n\n")[0])
    p.add_argument("roots", nargs="+", help="pair sets rendered with --kind pairs")
    p.add_argument("--split", default="all", choices=("all", "train", "val"))
    p.add_argument("--verify", action="store_true", help="check every shard's sha256 first (slow)")
    p.add_argument("--json", action="store_true", help="one JSON object {root: statistics} instead of the table")
    a = p.parse_args(argv)
    summaries = []
    for root in a.roots:
        if not Path(root).is_dir():
            print(f"error: {root} is not a directory (expected a pair set rendered with --kind pairs)",
                  file=sys.stderr)
            return 2
        try:
            summaries.append(summarize(pair_records(root, a.split, a.verify)))
        except KeyError as e:
            print(f"error: {root}: scene metadata without {e} (not written by `python -m data.render`?)",
                  file=sys.stderr)
            return 2
        except (ShardError, ValueError) as e:
            print(f"error: {e}" if str(root) in str(e) else f"error: {root}: {e}", file=sys.stderr)
            return 2
    names = [Path(r).name or str(r) for r in a.roots]
    if a.json:
        print(json.dumps(dict(zip(a.roots, summaries))))
    else:
        print(format_table(names, summaries))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
