"""The ship rule of docs/models.md, checked from the files a card run writes: does a candidate replace the
shipped model?

    bash benchmarks/model_card.sh OLD.safetensors DATA 1 old_pairs.csv > old.txt
    bash benchmarks/model_card.sh NEW.safetensors DATA 1 new_pairs.csv > new.txt
    python benchmarks/bench_ga.py --model OLD.safetensors --data ... --settings auto+E --per-pair old_ga  # optional,
    python benchmarks/bench_ga.py --model NEW.safetensors --data ... --settings auto+E --per-pair new_ga  # likewise
    python benchmarks/ship_rule.py --incumbent old.txt old_pairs.csv --candidate new.txt new_pairs.csv \\
        [--ga old_ga-GA_auto+E.csv new_ga-GA_auto+E.csv] [--names v49h v52h]

The rule (docs/training-log.md, session 42), one row per criterion; the candidate ships when the count passes and
no other criterion fails:

1. **count**: the candidate's exact count (rotations + directions within 15 degrees, of the pointmaps' pose and of
   the pipeline's, over the four card sets: ``compare_cards.exact_count``), plus (with ``--ga``, since session 88)
   its global alignment's rotations + directions within 15 degrees over the camera pairs (``ga_count``), exceeds
   the incumbent's;
2. **pair by pair**: none of ``paired.py``'s four pooled McNemar tests (rotation, direction, the pipeline's
   rotation and direction, over every shared pair) goes against the candidate at p < 0.05;
3. **depth**: the candidate's AbsRel, averaged over the eval sets both cards hold, is at most 0.01 above the
   incumbent's;
4. **global alignment** (with ``--ga``): neither rotations nor directions within 15 degrees are significantly fewer
   (McNemar p < 0.05) over the camera pairs both files hold;
5. **real photographs**: not every real set (``real_*`` in the per-pair files) has the candidate's directions worse
   by more than 15 degrees (the median over the set's pairs of the candidate's error minus the incumbent's).

The shipped model's own files are committed in ``benchmarks/baselines/small/`` (its card, per-pair CSV and
global-alignment per-pair CSV, with the SHA-256 of the weights they were measured on), so that a fresh machine
with the held-out sets re-rendered compares a candidate without carding the incumbent again:

    python benchmarks/ship_rule.py --incumbent shipped --candidate new.txt new_pairs.csv --ga new_ga-GA_auto+E.csv

refuses a baseline whose recorded hash is not the shipped file's (a ship that did not update it). Per-pair files
measured under different conditions (torch's thread count, package versions: each set's ``# conditions`` row,
session 89) are refused too: card the candidate as the baseline was carded. When a candidate
ships, ``--record`` writes its files there (after the weights are copied into the package).

A criterion reads "not checked" when its files or sets are missing (no ``--ga``, no ``real_*`` set, cards without
eval sets), and then blocks the ship unless ``--partial`` is given. Nothing here runs a model. Exit status: 0 when
the candidate ships, 1 when it does not, 2 for input that cannot be read.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.compare_cards import CARD_SETS, EVAL_SETS, exact_count, parse_card  # noqa: E402
from benchmarks.paired import paired, read_conditions, read_per_pair  # noqa: E402
from data.shards import sha256_file  # noqa: E402
from pointmap.atomic import write_bytes  # noqa: E402

ALPHA = 0.05          # McNemar's significance level
ABSREL_SLACK = 0.01   # the depth criterion's allowance
REAL_DIR_SLACK = 15.0  # degrees: a real set is "worse" beyond this median direction loss
POOLED = ("rotation", "direction", "pipeline rotation", "pipeline direction")
ROOT = Path(__file__).resolve().parents[1]
SHIPPED_WEIGHTS = ROOT / "pointmap" / "weights" / "small.safetensors"
BASELINE = ROOT / "benchmarks" / "baselines" / "small"
BASELINE_FILES = ("card.txt", "pairs.csv", "ga_auto+E.csv")  # with weights.sha256


def shipped_baseline(weights=SHIPPED_WEIGHTS, folder=BASELINE) -> tuple:
    """(card, pairs, ga) paths of the committed baseline, after checking that it was measured on ``weights``."""
    folder = Path(folder)
    missing = [n for n in (*BASELINE_FILES, "weights.sha256") if not (folder / n).is_file()]
    if missing:
        raise ValueError(f"the shipped model's baseline in {folder} lacks {', '.join(missing)} "
                         "(write it with --record when a model ships)")
    recorded = ((folder / "weights.sha256").read_text().split() or [""])[0]
    actual = sha256_file(weights)
    if recorded != actual:
        raise ValueError(f"the baseline in {folder} was measured on weights with SHA-256 {recorded or '(none)'}, "
                         f"but {weights} has {actual}: a ship that did not record its files (--record)")
    return tuple(folder / n for n in BASELINE_FILES)


def record_baseline(card, pairs, ga, weights=SHIPPED_WEIGHTS, folder=BASELINE) -> None:
    """Write a shipped model's card, per-pair and global-alignment files, and the weights' hash, into ``folder``,
    each file atomically, after checking that they parse."""
    parse_card(Path(card).read_text())
    read_per_pair(pairs)
    read_per_pair(ga)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for src, name in zip((card, pairs, ga), BASELINE_FILES):
        write_bytes(folder / name, Path(src).read_bytes())
    write_bytes(folder / "weights.sha256", f"{sha256_file(weights)}  {Path(weights).name}\n".encode())


def ga_count(per_pair: dict, tol: float = 15.0) -> int:
    """Global alignment's share of the count: rotations + directions within ``tol`` degrees over every camera pair
    of a ``bench_ga.py`` per-pair file (read by ``paired.read_per_pair``). A failed alignment is written there as
    180 degrees; a NaN error is a miss too."""
    return sum(int(v[c] < tol) for v in per_pair.values() for c in (0, 1))


def _mcnemar_row(criterion: str, res: dict, errors: tuple) -> tuple:
    """A criterion row from the pooled ("all") rows of a ``paired`` result: it fails when any of ``errors`` goes
    against B (the candidate) at McNemar p < ALPHA; the detail names those losses, or every pooled row."""
    pooled = [(e, res[("all", e)]) for e in errors if ("all", e) in res]
    text = {e: f"{e} {r['a_hits']} -> {r['b_hits']} (p {r['mcnemar_p']:.3g})" for e, r in pooled}
    losses = [text[e] for e, r in pooled if r["a_only"] > r["b_only"] and r["mcnemar_p"] < ALPHA]
    return (criterion, "", "", not losses,
            ("significant losses: " + "; ".join(losses)) if losses else "; ".join(text.values()))


def _same_pairs(inc: dict, cand: dict, what: str, card_only: bool = False) -> None:
    """ValueError unless both files hold the same pairs (of the card sets, with ``card_only``) and, where they hold
    the true rotation, the same one: counts over different pairs (more pairs carded, or sets rendered anew)
    compare nothing, and a candidate carded on more pairs passed the count without a better pose."""
    ki = {k for k in inc if not card_only or k[0] in CARD_SETS}
    kc = {k for k in cand if not card_only or k[0] in CARD_SETS}
    if ki != kc:
        diff = sorted(ki ^ kc)
        raise ValueError(f"the {what} hold different pairs: {len(ki - kc)} only in the incumbent's, {len(kc - ki)} "
                         f"only in the candidate's (e.g. {diff[:3]}); card both on the same sets")
    moved = [k for k in sorted(ki) if not abs(inc[k][2] - cand[k][2]) <= 1e-3  # the true rotation, degrees
             and not (math.isnan(inc[k][2]) and math.isnan(cand[k][2]))]  # (NaN in one file alone differs)
    if moved:
        raise ValueError(f"the {what} hold the same pair names but {len(moved)} true rotations differ (e.g. "
                         f"{moved[0]}: {inc[moved[0]][2]:.4f} against {cand[moved[0]][2]:.4f} degrees): the "
                         "sets were rendered anew; card both on the same renders")


def same_conditions(inc: dict, cand: dict, what: str) -> list:
    """``["<what> <sets>"]`` naming the sets that record conditions on one side only (files before session 89), or
    ``[]``, of two per-pair files' conditions (``paired.read_conditions``). ValueError when any set records
    different ones: a pair's pipeline pose and global alignment move with torch's thread count
    (``evaluate.measurement_conditions``), so such files would credit the candidate with the change of conditions."""
    differ = [s for s in sorted(inc.keys() & cand.keys()) if inc[s] != cand[s]]
    if differ:
        s = differ[0]
        a, b = (dict(f.partition("=")[::2] for f in c.split(";")) for c in (inc[s], cand[s]))  # key=value fields
        diff = ", ".join(f"{k} {a.get(k)} against {b.get(k)}" for k in sorted(a.keys() | b.keys()) if a.get(k) != b.get(k))
        raise ValueError(f"the {what} were measured under other conditions on {len(differ)} set(s) (e.g. {s}: "
                         f"{diff}, the incumbent's first): measure both alike (model_card.sh's THREADS, "
                         "bench_ga.py --threads) on one machine")
    unrecorded = sorted(inc.keys() ^ cand.keys())
    return [f"{what} {', '.join(unrecorded)}"] if unrecorded else []


def check(inc_card: dict, inc_pairs: dict, cand_card: dict, cand_pairs: dict, ga: tuple | None = None) -> list:
    """[(criterion, incumbent's figure, candidate's figure, verdict True / False / None (not checked), detail)]
    for the parsed cards (``compare_cards.parse_card``), per-pair files (``paired.read_per_pair``) and, optionally,
    the two ``bench_ga.py`` per-pair files read the same way."""
    rows = []
    _same_pairs(inc_pairs, cand_pairs, "per-pair files", card_only=True)
    for who, pp in (("incumbent's", inc_pairs), ("candidate's", cand_pairs)):  # a NaN error the count would take
        nan = [k for k in pp if k[0] in CARD_SETS and (math.isnan(pp[k][0]) or math.isnan(pp[k][1])  # for a miss and
                                                       or (math.isnan(pp[k][4]) and not math.isnan(pp[k][3])))]  # McNemar
        if nan:  # leave out: refused rather than judged two ways (a file without the pipeline's columns has no count)
            raise ValueError(f"the {who} per-pair file holds NaN errors on {len(nan)} card pairs (e.g. {nan[0]}): "
                             "the count and the pair-by-pair tests would judge them differently")
    if ga is not None:
        _same_pairs(*ga, "global-alignment files")
    ci, cc = exact_count(inc_pairs), exact_count(cand_pairs)
    if ci is None or cc is None:
        rows.append(("count", ci, cc, None, "a per-pair file lacks a card set or the pipeline's columns"))
    elif ga is None:
        rows.append(("count", ci, cc, cc > ci, f"{cc - ci:+d} pairs (two-view alone: no --ga files)"))
    else:  # session 88: two-view and global alignment, each pose judged within 15 degrees counting once
        gi, gc = ga_count(ga[0]), ga_count(ga[1])
        rows.append(("count", ci + gi, cc + gc, cc + gc > ci + gi,
                     f"{cc + gc - ci - gi:+d}: two-view {ci} -> {cc}, global alignment {gi} -> {gc}"))

    res, _ = paired(inc_pairs, cand_pairs)
    rows.append(_mcnemar_row("pair by pair", res, POOLED))

    sets = [s for s in EVAL_SETS if "AbsRel" in inc_card["eval"].get(s, {}) and "AbsRel" in cand_card["eval"].get(s, {})]
    if sets:
        ai = sum(inc_card["eval"][s]["AbsRel"] for s in sets) / len(sets)
        ac = sum(cand_card["eval"][s]["AbsRel"] for s in sets) / len(sets)
        rows.append(("depth AbsRel (mean)", round(ai, 4), round(ac, 4), ac - ai <= ABSREL_SLACK,
                     f"{ac - ai:+.4f} over {', '.join(sets)} (allowed +{ABSREL_SLACK})"))
    else:
        rows.append(("depth AbsRel (mean)", None, None, None, "the cards share no eval set with an AbsRel"))

    if ga is None:
        rows.append(("global alignment", None, None, None, "no --ga files"))
    else:
        rows.append(_mcnemar_row("global alignment", paired(*ga)[0], ("rotation", "direction")))

    real = sorted({s for s, e in res if s.startswith("real") and e == "direction"})
    if not real:
        rows.append(("real photographs", None, None, None, "no real_* set in both per-pair files"))
    else:
        diffs = {s: res[(s, "direction")]["median_diff"] for s in real}
        worse = [s for s, d in diffs.items() if math.isfinite(d) and d > REAL_DIR_SLACK]
        rows.append(("real photographs", "", "", len(worse) < len(real),
                     "median direction change " + ", ".join(f"{s} {d:+.1f}" for s, d in diffs.items())
                     + f" (fails only if every set is worse by > {REAL_DIR_SLACK:g} degrees)"))
    return rows


def ships(rows: list, partial: bool = False) -> bool:
    """The verdict: the count passes and every other criterion passes (``partial``: is not failed; a criterion
    whose files are missing then does not block, the session-42 rule being checked only in part)."""
    return rows[0][3] is True and all(r[3] is True or (partial and r[3] is None) for r in rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--incumbent", nargs="+", metavar="CARD PAIRS",
                   help="the shipped model's model_card.sh output and per-pair CSV, or the word 'shipped' for the "
                        "committed baseline (benchmarks/baselines/small)")
    p.add_argument("--candidate", nargs=2, metavar=("CARD", "PAIRS"),
                   help="the candidate's model_card.sh output and per-pair CSV")
    p.add_argument("--ga", nargs="+", metavar="INCUMBENT CANDIDATE", default=None,
                   help="the two models' bench_ga.py per-pair CSVs of one setting (e.g. X-GA_auto+E.csv); with "
                        "--incumbent shipped, the candidate's alone")
    p.add_argument("--names", nargs=2, metavar=("INCUMBENT", "CANDIDATE"), default=("incumbent", "candidate"))
    p.add_argument("--partial", action="store_true",
                   help="let a criterion that cannot be checked (no --ga files, no real_* set, cards without eval "
                        "sets) pass; by default every criterion of the rule must be checked and pass")
    p.add_argument("--record", nargs=3, metavar=("CARD", "PAIRS", "GA"), default=None,
                   help="record these files as the shipped model's baseline (benchmarks/baselines/small, with the "
                        "SHA-256 of pointmap/weights/small.safetensors) and exit")
    a = p.parse_args(argv)
    if a.record is not None:
        if a.incumbent or a.candidate or a.ga:
            p.error("--record takes no --incumbent, --candidate or --ga")
        try:
            record_baseline(*a.record, weights=SHIPPED_WEIGHTS, folder=BASELINE)
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"recorded {', '.join(a.record)} as the baseline of {SHIPPED_WEIGHTS.name} in {BASELINE}")
        return 0
    if a.incumbent is None or a.candidate is None:
        p.error("expected --incumbent and --candidate (or --record)")
    shipped = a.incumbent == ["shipped"]
    if not shipped and len(a.incumbent) != 2:
        p.error(f"--incumbent expected CARD PAIRS or 'shipped', got {len(a.incumbent)} value(s): {a.incumbent}")
    if a.ga is not None and len(a.ga) != (1 if shipped else 2):
        wanted = "the candidate's file alone (with --incumbent shipped)" if shipped else "INCUMBENT CANDIDATE"
        p.error(f"--ga expected {wanted}, got {len(a.ga)} file(s)")
    try:
        if shipped:
            card, pairs, ga_file = shipped_baseline(SHIPPED_WEIGHTS, BASELINE)
            a.incumbent = [card, pairs]
            if a.ga is not None:
                a.ga = [ga_file, a.ga[0]]
        inc_card, cand_card = (parse_card(Path(f).read_text()) for f in (a.incumbent[0], a.candidate[0]))
        inc_pairs, cand_pairs = read_per_pair(a.incumbent[1]), read_per_pair(a.candidate[1])
        ga = None if a.ga is None else (read_per_pair(a.ga[0]), read_per_pair(a.ga[1]))
        unrecorded = same_conditions(read_conditions(a.incumbent[1]), read_conditions(a.candidate[1]),
                                     "per-pair files")
        if a.ga is not None:
            unrecorded += same_conditions(read_conditions(a.ga[0]), read_conditions(a.ga[1]),
                                          "global-alignment files")
        rows = check(inc_card, inc_pairs, cand_card, cand_pairs, ga)
    except (OSError, ValueError) as e:  # CardError, PairedError, or a figure that is not a number
        print(f"error: {e}", file=sys.stderr)
        return 2
    verdicts = {True: "PASS", False: "FAIL", None: "not checked"}
    print(f"| criterion | {a.names[0]} | {a.names[1]} | verdict | detail |")
    print("|---|---|---|---|---|")
    for name, vi, vc, ok, detail in rows:
        print(f"| {name} | {'-' if vi is None else vi} | {'-' if vc is None else vc} | {verdicts[ok]} | {detail} |")
    if unrecorded:
        print(f"\nconditions (threads, package versions) not recorded on both sides for the {'; the '.join(unrecorded)} "
              "(files before session 89): make sure both were measured alike")
    ok = ships(rows, a.partial)
    unchecked = [r[0] for r in rows if r[3] is None]
    print(f"\n{a.names[1]} {'ships' if ok else 'does not ship'} under the rule"
          + (f" (not checked: {', '.join(unchecked)}{'' if a.partial else '; --partial lets them pass'})."
             if unchecked else "."))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
