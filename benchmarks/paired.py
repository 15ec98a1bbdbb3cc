"""Two models on the same pairs, pair by pair: is a difference between their cards real or a draw?

A card's aggregate (RRA@15 57.6% vs 61.2%, a median direction error of 25 vs 45 degrees) does not say whether
the two models differ on the same pairs or trade wins at random. This script joins two per-pair files (written
by ``--per-pair CSV`` of ``python -m training.evaluate``, ``benchmarks/bench_pose.py`` and
``benchmarks/bench_real.py``, or by ``benchmarks/model_card.sh MODEL DATA THREADS PER_PAIR.csv``; ``bench_ga.py``
writes one per alignment method) on
(set, pair) and prints, per set and over all sets:

- for rotation and translation direction within ``--tol`` degrees (of the pose from the pointmaps and, where both
  files hold it, of the pose the pipeline reports, ``pm.pair_pose``): the pairs each model gets and the other
  misses (the discordant pairs) and McNemar's exact two-sided p-value (binomial on the discordant pairs: the
  chance of a split at least this uneven if the two models were equally good);
- for the errors themselves: the median of B's error minus A's over the pairs, the pairs where B is lower /
  higher, and the sign test's exact two-sided p-value.

Two breakdowns on request: ``--by-rotation`` repeats the pooled comparison within bins of the pairs' true
rotation (0-15, 15-30, 30-45, 45-60, over 60 degrees: where a gain or a loss sits, narrow pairs or wide ones), and
``--scene-size N`` compares the models scene by scene: each set's pairs taken N at a time in their order (a
scene of V views has V (V - 1) / 2 camera pairs, which ``bench_ga.py`` writes in a row: 6 for the card sets' 4
views), each scene's mean rotation and direction error, and the sign test over scenes (a model better on a
few scenes by much and worse on many by little shows here, not in the pair counts).

A small p (say < 0.05) says the difference is unlikely to be a draw of these pairs; it says nothing about the
draw of the training run that made each model (two runs of one recipe differ too).

    python benchmarks/paired.py v17.csv v21.csv --names v17 v21 [--tol 15] [--by-rotation] [--scene-size 6]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from training.evaluate import PER_PAIR_HEADER, read_per_pair_csv  # noqa: E402


class PairedError(ValueError):
    """A per-pair file that cannot be read or two files that share no pairs."""


def read_per_pair(path) -> dict:
    """{(set, pair): (rot_err, dir_err, true_rot, pair_rot_err, pair_dir_err)} of a per-pair CSV (a file written
    before the pipeline's columns existed reads them as NaN); PairedError for anything else."""
    path = Path(path)
    try:
        width, rows, _ = read_per_pair_csv(path)
    except (OSError, UnicodeDecodeError) as e:
        raise PairedError(f"{path}: cannot read a per-pair CSV ({e})") from e
    except ValueError as e:  # a foreign header
        raise PairedError(str(e)) from None
    header = ",".join(PER_PAIR_HEADER[:width])
    out = {}
    for n, r in enumerate(rows, start=2):
        if not r:
            continue
        try:
            if len(r) != width:
                raise ValueError(f"{len(r)} fields")
            key = (r[0], int(r[1]))
            vals = tuple(float(x) for x in r[2:]) + (math.nan,) * (len(PER_PAIR_HEADER) - width)
        except ValueError as e:
            raise PairedError(f"{path}, line {n}: expected {header}, got {','.join(r)!r} ({e})") from e
        if key in out:
            raise PairedError(f"{path}, line {n}: pair {key[1]} of set {key[0]!r} appears twice")
        out[key] = vals
    return out


def read_conditions(path) -> dict:
    """{set: the measurement conditions it was written under} of a per-pair CSV (``evaluate.measurement_conditions``
    fields; a set written before session 89 has none); PairedError when the file is not a per-pair CSV."""
    try:
        return read_per_pair_csv(Path(path))[2]
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise PairedError(f"{path}: cannot read a per-pair CSV ({e})") from e


def binomial_two_sided(k: int, n: int) -> float:
    """Exact two-sided p-value of k successes in n fair coin flips (1.0 for n = 0): twice the smaller tail,
    capped at 1."""
    if not 0 <= k <= n:
        raise ValueError(f"k expected in [0, n], got k={k}, n={n}")
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(k, n - k) + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def _median(values: list) -> float:
    v = sorted(values)
    mid = len(v) // 2
    return float("nan") if not v else v[mid] if len(v) % 2 else (v[mid - 1] + v[mid]) / 2


def compare_errors(a: list, b: list, tol: float) -> dict:
    """Paired comparison of two models' errors (degrees) on the same pairs. NaN errors (a direction that is
    not defined) drop the pair from this comparison. Returns {"pairs", "a_median", "b_median", "a_hits", "b_hits",
    "a_only", "b_only", "mcnemar_p", "median_diff" (B - A), "b_lower", "b_higher", "sign_p"}."""
    if len(a) != len(b):
        raise ValueError(f"a and b expected the same pairs, got {len(a)} and {len(b)} errors")
    both = [(x, y) for x, y in zip(a, b) if math.isfinite(x) and math.isfinite(y)]
    a_only = sum(x < tol <= y for x, y in both)
    b_only = sum(y < tol <= x for x, y in both)
    diffs = sorted(y - x for x, y in both)
    lower, higher = sum(d < 0 for d in diffs), sum(d > 0 for d in diffs)
    return {"pairs": len(both), "a_median": _median([x for x, _ in both]), "b_median": _median([y for _, y in both]),
            "a_hits": sum(x < tol for x, _ in both), "b_hits": sum(y < tol for _, y in both),
            "a_only": a_only, "b_only": b_only, "mcnemar_p": binomial_two_sided(min(a_only, b_only), a_only + b_only),
            "median_diff": _median(diffs), "b_lower": lower, "b_higher": higher,
            "sign_p": binomial_two_sided(min(lower, higher), lower + higher)}


def paired(a: dict, b: dict, tol: float = 15.0) -> tuple[dict, list]:
    """({(set, error): compare_errors(...)} over the pairs both files hold, per set and for the set "all";
    [notes on pairs held by one file only]). PairedError when no pair is shared. The errors: "rotation" and
    "direction" of the pose from the pointmaps, then "pipeline rotation" and "pipeline direction" (the pose
    ``pm.pair_pose`` reports) for the sets where both files hold them."""
    if any(k[0] == "all" for k in (*a, *b)):
        raise PairedError("a set named 'all' clashes with the pooled row; rename it")
    shared = _shared(a, b)
    notes = []
    for name, mine, other in (("A", a, b), ("B", b, a)):
        alone = sorted({s for s, _ in set(mine) - set(other)})
        for s in alone:
            n = sum(1 for k in mine if k[0] == s and k not in other)
            notes.append(f"{name} alone holds {n} pairs of {s} (left out)")
    out = {}
    for s in sorted({k[0] for k in shared}) + ["all"]:
        keys = [k for k in shared if s == "all" or k[0] == s]
        for col, what in ERRORS:
            r = compare_errors([a[k][col] for k in keys], [b[k][col] for k in keys], tol)
            if col < 3 or r["pairs"]:
                out[(s, what)] = r
    return out, notes


ROTATION_EDGES = (0.0, 15.0, 30.0, 45.0, 60.0, 180.0)
ERRORS = ((0, "rotation"), (1, "direction"), (3, "pipeline rotation"), (4, "pipeline direction"))


def _shared(a: dict, b: dict) -> list:
    shared = sorted(set(a) & set(b))
    if not shared:
        raise PairedError(f"the two files share no (set, pair): sets {sorted({s for s, _ in a})} and "
                          f"{sorted({s for s, _ in b})}")
    return shared


def by_true_rotation(a: dict, b: dict, tol: float = 15.0, edges=ROTATION_EDGES) -> dict:
    """{(bin label, error): compare_errors(...)} over the pairs both files hold, all sets pooled, binned by the
    pair's true rotation (degrees; a bin holds lo <= true < hi, the last one hi too); pairs whose true rotation
    is unknown (NaN) are left out. PairedError when the two files give a shared pair different true rotations
    (more than 0.01 degrees apart: files of different pairs under the same names)."""
    if len(edges) < 2 or any(not lo < hi for lo, hi in zip(edges, edges[1:])):
        raise ValueError(f"edges expected at least two increasing values, got {list(edges)}")
    shared = _shared(a, b)
    for k in shared:
        ta, tb = a[k][2], b[k][2]
        if math.isfinite(ta) and math.isfinite(tb) and abs(ta - tb) > 0.01:
            raise PairedError(f"pair {k[1]} of {k[0]}: true rotations {ta:.3f} and {tb:.3f} differ; the two files "
                              "are not of the same pairs")
    out = {}
    for i, (lo, hi) in enumerate(zip(edges, edges[1:])):
        last = i == len(edges) - 2
        keys = [k for k in shared if lo <= a[k][2] < hi or (last and a[k][2] == hi)]
        label = f"{lo:g}-{hi:g}"
        for col, what in ERRORS:
            r = compare_errors([a[k][col] for k in keys], [b[k][col] for k in keys], tol)
            if col < 3 or r["pairs"]:
                out[(label, what)] = r
    return out


def by_scene(a: dict, b: dict, size: int) -> dict:
    """{(set, error): compare_errors(...) of the scenes' mean errors} per set and for "all": each set's shared
    pairs in index order taken ``size`` at a time (pair k in scene k // size), a scene's error the mean over its
    pairs (a scene with an undefined error in either file is left out of that error's comparison). The hit
    counts compare the means against the tolerance 15; read the sign test. PairedError when a set's shared pairs
    are not whole scenes of ``size`` (pairs missing, or scenes of another view count)."""
    if not isinstance(size, int) or size < 1:
        raise ValueError(f"size expected an int >= 1 (camera pairs per scene), got {size!r}")
    shared = _shared(a, b)
    scenes: dict = {}
    for k in shared:
        scenes.setdefault((k[0], k[1] // size), []).append(k)
    for (s, n), keys in scenes.items():
        if [k[1] for k in keys] != list(range(n * size, n * size + size)):
            raise PairedError(f"set {s}: scene {n} expected pairs {n * size}..{n * size + size - 1} in both files, "
                              f"got {[k[1] for k in keys]}; is --scene-size right?")
    out = {}
    for s in sorted({k[0] for k in shared}) + ["all"]:
        groups = [keys for (name, _), keys in sorted(scenes.items()) if s == "all" or name == s]
        for col, what in ERRORS:
            ma = [sum(a[k][col] for k in g) / len(g) for g in groups]
            mb = [sum(b[k][col] for k in g) / len(g) for g in groups]
            r = compare_errors(ma, mb, 15.0)
            if col < 3 or r["pairs"]:
                out[(s, what)] = r
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", type=Path, help="model A's per-pair CSV")
    p.add_argument("b", type=Path, help="model B's per-pair CSV")
    p.add_argument("--names", nargs=2, default=None, metavar=("A", "B"), help="the two models' names")
    p.add_argument("--tol", type=float, default=15.0, help="degrees: the RRA / RTA threshold (default 15)")
    p.add_argument("--by-rotation", dest="by_rotation", action="store_true",
                   help="also compare within bins of the pairs' true rotation (all sets pooled)")
    p.add_argument("--scene-size", dest="scene_size", type=int, default=None, metavar="N",
                   help="also compare scene by scene, each set's pairs taken N at a time (6 for 4-view scenes)")
    args = p.parse_args(argv)
    if not args.tol > 0:
        p.error(f"--tol expected > 0, got {args.tol}")
    if args.scene_size is not None and args.scene_size < 1:
        p.error(f"--scene-size expected an int >= 1, got {args.scene_size}")
    na, nb = args.names or (args.a.stem, args.b.stem)
    try:
        a, b = read_per_pair(args.a), read_per_pair(args.b)
        res, notes = paired(a, b, args.tol)
        bins = by_true_rotation(a, b, args.tol) if args.by_rotation else None
        scenes = by_scene(a, b, args.scene_size) if args.scene_size else None
    except PairedError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t = f"{args.tol:g}"
    print(f"| set | error | pairs | {na} within {t} | {nb} within {t} | {na} only | {nb} only | McNemar p | "
          f"median {nb} - {na} | {nb} lower / higher | sign p |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (s, what), r in res.items():
        print(f"| {s} | {what} | {r['pairs']} | {r['a_hits']} | {r['b_hits']} | {r['a_only']} | {r['b_only']} | "
              f"{r['mcnemar_p']:.3g} | {r['median_diff']:+.1f} | {r['b_lower']} / {r['b_higher']} | "
              f"{r['sign_p']:.3g} |")
    if bins is not None:
        print(f"\nBy true rotation (degrees), all sets pooled:\n\n| true rotation | error | pairs | {na} within {t} | "
              f"{nb} within {t} | McNemar p | median {na} / {nb} | median {nb} - {na} | sign p |")
        print("|---|---|---|---|---|---|---|---|---|")
        for (label, what), r in bins.items():
            print(f"| {label} | {what} | {r['pairs']} | {r['a_hits']} | {r['b_hits']} | {r['mcnemar_p']:.3g} | "
                  f"{r['a_median']:.1f} / {r['b_median']:.1f} | {r['median_diff']:+.1f} | {r['sign_p']:.3g} |")
    if scenes is not None:
        print(f"\nScene by scene ({args.scene_size} pairs each), the mean error over a scene's pairs:\n\n"
              f"| set | error | scenes | {nb} lower / higher | median {nb} - {na} | sign p |")
        print("|---|---|---|---|---|---|")
        for (s, what), r in scenes.items():
            print(f"| {s} | {what} | {r['pairs']} | {r['b_lower']} / {r['b_higher']} | {r['median_diff']:+.2f} | "
                  f"{r['sign_p']:.3g} |")
    for n in notes:
        print(f"\nnote: {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
