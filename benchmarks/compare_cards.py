"""Side by side: the model-card figures of several models, from the outputs of ``benchmarks/model_card.sh``.

    bash benchmarks/model_card.sh OLD.safetensors DATA > old.txt
    bash benchmarks/model_card.sh NEW.safetensors DATA > new.txt
    python benchmarks/compare_cards.py old.txt new.txt [--names v15 v17]

Prints one markdown row per figure (docs/models.md, "How good it is") and one column per card, then the
totals a ship decision rests on: pairs with a rotation within 15 degrees over the synthetic card sets
(``eval_s424242`` + ``eval_p4_s434343`` + ``bench_s525252``: 478 pairs; and with ``eval_cam_s464646`` when every
card has it) and the same for translation, for the pointmaps' own pose and for the pipeline's; last, the sum of
those four counts over all four sets (the count proposed in session 41, docs/training-log.md). A figure a card
lacks (a skipped section, an older card without a metric) shows as "-". Nothing here runs a model: it reads what
the card script printed.

A card before session 42 printed ``bench_s525252``'s shares in whole percents, so its counts there can be a pair
off. ``--per-pair A.csv B.csv ...`` (the card's fourth argument, one file per card, in the same order) adds the
same sum counted pair by pair from those files, exact ("-" for a file without the pipeline's columns).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

EVAL_SETS = ("eval_s424242", "eval_p4_s434343", "eval_cam_s464646")
CARD_SETS = (*EVAL_SETS, "bench_s525252")  # the sets the ship count is over
# (label, key in an evaluate JSON line, format)
EVAL_ROWS = (("RRA@15 %", "RRA15", "{:.1f}"), ("RTA@15 %", "RTA15", "{:.1f}"), ("median rot err", "rot_err_med", "{:.1f}"),
             ("RRA@15 % under 30 deg", "RRA15_under30", "{:.1f}"), ("RRA@15 % over 45 deg", "RRA15_over45", "{:.1f}"),
             ("median dir err", "trans_err_med", "{:.1f}"), ("AbsRel", "AbsRel", "{:.3f}"),
             ("depth_ratio_err", "depth_ratio_err", "{:.3f}"),
             ("focal error (median, relative)", "focal_err", "{:.3f}"),
             ("focal slope (log on log true; 1 = follows the image)", "focal_slope", "{:.2f}"),
             ("fwd_corr", "fwd_corr", "{:.2f}"),
             ("RRA@15 % of the pipeline's pose (+ own matches)", "RRA15_pair", "{:.1f}"),
             ("RTA@15 % of the pipeline's pose (+ own matches)", "RTA15_pair", "{:.1f}"),
             ("match precision", "match_prec", "{:.3f}"), ("RRA@15 from matches %", "RRA15_matches", "{:.1f}"),
             ("coarse match score AUC (0.5: says nothing)", "match_score_auc", "{:.3f}"),
             ("the same within each pair (mean)", "match_score_auc_within", "{:.3f}"),
             ("confidence >= 1.1, share of pixels", "conf_spread", "{:.3f}"),
             ("AbsRel of the confident half / all", "conf_order", "{:.3f}"))
BENCH_CATEGORIES = ("all", "low-texture", "wide (>30 deg)", "short baseline (<0.1 depth)")
PIPELINE = "model + own matches (no K)"  # the pose the pipeline reports (pm.pair_pose), a row of bench_pose / bench_real


class CardError(ValueError):
    pass


def parse_card(text: str) -> dict:
    """The figures of one ``model_card.sh`` output: {"eval": {set: {key: value}}, "bench": {category: (pairs,
    RRA, RTA, med rot)}, "sift": (RRA, RTA) or None, "rig": (med rot, med dir) or None, "focal": %, "aloe_r": r,
    "moto": (rot err, dir err) or None, "moto_focal": %, "moto_absrel": AbsRel, "moto_r": r} (the Middlebury motorcycle
    rows, None on cards made without them); "bench_pair", "rig_pair", "aloe_pair", "moto_pair": the same for the
    pipeline's pose ("model + own matches (no K)", ``pm.pair_pose``; empty / None on cards made before it).
    CardError when the text has none of the card's sections."""
    sections: dict[str, list[str]] = {}
    name = None
    for line in text.splitlines():
        m = re.match(r"^== (\S+)", line)
        if m:
            name = m.group(1).rstrip(":")
            sections[name] = []
        elif name is not None:
            sections[name].append(line)
    if not sections:
        raise CardError("expected the output of benchmarks/model_card.sh (sections starting with '== '), found none")
    card: dict = {"eval": {}, "bench": {}, "sift": None, "rig": None, "focal": None, "aloe_r": None,
                  "moto": None, "moto_focal": None, "moto_absrel": None, "moto_r": None,
                  "bench_pair": {}, "rig_pair": None, "aloe_pair": None, "moto_pair": None}
    for s in EVAL_SETS:
        for line in sections.get(s, []):
            if line.startswith("{"):
                try:
                    card["eval"][s] = json.loads(line)
                except json.JSONDecodeError as e:
                    raise CardError(f"{s}: a JSON line that does not parse ({e})") from None
    for line in sections.get("bench_s525252", []):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[2] in ("model", PIPELINE, "sift+E (known K)") and cells[1].isdigit():
            rra, rta = (float(c.rstrip("%")) if c != "-" else float("nan") for c in cells[3:5])
            if cells[2] in ("model", PIPELINE):
                card["bench" if cells[2] == "model" else "bench_pair"][cells[0]] = (int(cells[1]), rra, rta,
                                                                                     float(cells[5]))
            elif cells[0] == "all":
                card["sift"] = (rra, rta)
    for line in sections.get("real", []):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[0] == "stereo rig" and cells[2].startswith("model (own pointmaps"):
            card["rig"] = (float(cells[5]), float(cells[6]))
        for where, key in (("stereo rig", "rig_pair"), ("aloe (rectified)", "aloe_pair"),
                           ("motorcycle (rectified)", "moto_pair")):
            if len(cells) == 7 and cells[0] == where and cells[2] == PIPELINE:
                card[key] = (float(cells[5]), float(cells[6]))
        if len(cells) == 4 and cells[0].startswith("model (1 / depth"):
            card["aloe_r"] = float(cells[2])
        if len(cells) == 7 and cells[0] == "motorcycle (rectified)" and cells[2].startswith("model (own pointmaps"):
            card["moto"] = (float(cells[5]), float(cells[6]))
        if len(cells) == 4 and cells[0] == "model (depth of view 1)":
            card["moto_absrel"], card["moto_r"] = float(cells[1]), float(cells[2])
        m = re.search(r"motorcycle, model focal .* relative error ([\d.]+)%", line)
        if m:
            card["moto_focal"] = float(m.group(1))
        m = re.search(r"model focal .* median relative error ([\d.]+)%", line)
        if m:
            card["focal"] = float(m.group(1))
    return card


def _at(figures: tuple | None, i: int):
    """Item ``i`` of a parsed tuple of figures, None when the card has no such tuple."""
    return None if figures is None else figures[i]


def _fmt(v, fmt: str) -> str:
    return "-" if v is None or math.isnan(v) else fmt.format(v)


def compare(cards: list[dict], names: list[str]) -> str:
    """A markdown table, one column per card."""
    rows = [f"| figure | {' | '.join(names)} |", "|---|" + "---|" * len(names)]

    def row(label, values, fmt):
        rows.append(f"| {label} | {' | '.join(_fmt(v, fmt) for v in values)} |")

    for s in EVAL_SETS:
        if not any(s in c["eval"] for c in cards):
            continue
        for label, key, fmt in EVAL_ROWS:
            row(f"`{s}` {label}", [c["eval"].get(s, {}).get(key) for c in cards], fmt)
    for cat in BENCH_CATEGORIES:
        row(f"`bench_s525252` {cat}: RRA@15 %", [_at(c["bench"].get(cat), 1) for c in cards], "{:.0f}")
    row("`bench_s525252` all: RTA@15 %", [_at(c["bench"].get("all"), 2) for c in cards], "{:.0f}")
    row("`bench_s525252` all: median rot err", [_at(c["bench"].get("all"), 3) for c in cards], "{:.1f}")
    if any(c["bench_pair"] for c in cards):
        row("`bench_s525252` all, the pipeline's pose: RRA@15 %", [_at(c["bench_pair"].get("all"), 1) for c in cards],
            "{:.0f}")
        row("`bench_s525252` all, the pipeline's pose: RTA@15 %", [_at(c["bench_pair"].get("all"), 2) for c in cards],
            "{:.0f}")
    row("SIFT + E (true K), all: RRA@15 %", [_at(c["sift"], 0) for c in cards], "{:.0f}")
    row("real rig: median rot err", [_at(c["rig"], 0) for c in cards], "{:.1f}")
    row("real rig: median dir err", [_at(c["rig"], 1) for c in cards], "{:.1f}")
    row("real rig: focal error %", [c["focal"] for c in cards], "{:.1f}")
    for label, key in (("real rig", "rig_pair"), ("Aloe", "aloe_pair"), ("motorcycle", "moto_pair")):
        if any(c[key] is not None for c in cards):
            row(f"{label}, the pipeline's pose: rot err", [_at(c[key], 0) for c in cards], "{:.1f}")
            row(f"{label}, the pipeline's pose: dir err", [_at(c[key], 1) for c in cards], "{:.1f}")
    row("Aloe: Pearson r", [c["aloe_r"] for c in cards], "{:.2f}")
    if any(c["moto"] is not None for c in cards):
        row("motorcycle: rot err", [_at(c["moto"], 0) for c in cards], "{:.1f}")
        row("motorcycle: dir err", [_at(c["moto"], 1) for c in cards], "{:.1f}")
        row("motorcycle: focal error %", [c["moto_focal"] for c in cards], "{:.1f}")
        row("motorcycle: depth AbsRel", [c["moto_absrel"] for c in cards], "{:.3f}")
        row("motorcycle: depth Pearson r", [c["moto_r"] for c in cards], "{:.2f}")
    every_set = {}  # (pose, metric) -> each card's total over all four sets
    for pose, bench, suffix in (("", "bench", ""), (", the pipeline's pose", "bench_pair", "_pair")):
        for metric, i, key in (("rotation", 1, "RRA15"), ("translation", 2, "RTA15")):
            for sets in (EVAL_SETS[:2], EVAL_SETS):
                totals = []
                for c in cards:
                    if not all(key + suffix in c["eval"].get(s, {}) for s in sets) or "all" not in c[bench]:
                        totals.append(None)
                        continue
                    pairs = c[bench]["all"][0] + sum(int(c["eval"][s]["pairs"]) for s in sets)
                    good = c[bench]["all"][0] * c[bench]["all"][i] / 100
                    good += sum(c["eval"][s]["pairs"] * c["eval"][s][key + suffix] / 100 for s in sets)
                    totals.append((round(good), pairs))
                if sets == EVAL_SETS:
                    every_set[(pose, metric)] = totals
                if all(t is None for t in totals):
                    continue
                label = f"{metric} within 15 deg{pose}, pairs over {' + '.join(sets)} + bench_s525252"
                rows.append(f"| {label} | {' | '.join('-' if t is None else f'{t[0]} / {t[1]}' for t in totals)} |")
    # the count proposed in session 41 (docs/training-log.md): the pose a user receives counts beside the pointmaps'
    ship = [None if any(t[k] is None for t in every_set.values()) else sum(t[k][0] for t in every_set.values())
            for k in range(len(cards))]
    if any(v is not None for v in ship):
        rows.append("| rotations + directions within 15 deg, own pointmaps' pose + the pipeline's, pairs over all "
                    f"four sets | {' | '.join('-' if v is None else str(v) for v in ship)} |")
    return "\n".join(rows)


def exact_count(per_pair: dict, tol: float = 15.0) -> int | None:
    """The session-42 ship count from a per-pair file (``paired.read_per_pair``): rotations + directions within
    ``tol`` of the pointmaps' pose and of the pipeline's over the four card sets; None when the file lacks a set or
    the pipeline's errors."""
    keys = [k for k in per_pair if k[0] in CARD_SETS]
    if {k[0] for k in keys} != set(CARD_SETS):
        return None
    if any(math.isnan(per_pair[k][3]) for k in keys):
        return None
    return sum(int(per_pair[k][c] < tol) for k in keys for c in (0, 1, 3, 4))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cards", nargs="+", help="outputs of benchmarks/model_card.sh")
    p.add_argument("--names", nargs="+", help="column names (default: the file names)")
    p.add_argument("--per-pair", nargs="+", default=None, metavar="CSV",
                   help="each card's per-pair file (model_card.sh's fourth argument), in the cards' order: the last "
                   "row's count again, exact")
    a = p.parse_args(argv)
    names = a.names or [Path(c).stem for c in a.cards]
    if len(names) != len(a.cards):
        p.error(f"--names expected {len(a.cards)} names (one per card), got {len(names)}")
    if a.per_pair is not None and len(a.per_pair) != len(a.cards):
        p.error(f"--per-pair expected {len(a.cards)} files (one per card), got {len(a.per_pair)}")
    try:
        cards = [parse_card(Path(c).read_text()) for c in a.cards]
        counts = None
        if a.per_pair is not None:
            sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
            from benchmarks.paired import read_per_pair

            counts = [exact_count(read_per_pair(f)) for f in a.per_pair]
    except (OSError, ValueError) as e:  # CardError, PairedError, or a figure that is not a number
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(compare(cards, names))
    if counts is not None:
        print("| the same, counted pair by pair from the per-pair files (exact) | "
              f"{' | '.join('-' if v is None else str(v) for v in counts)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
