"""What a run's own log says: ``train.csv`` columns as means per step window and over a step range.

    python -m training.logstats runs/legX/train/train.csv --from 500
    python -m training.logstats A/train.csv B/train.csv --names legW legX --columns pose_dir_deg coarse_acc --from 500

Each logged batch is one sample (``train.csv`` has a row every ``--log_every`` steps). A resumed run logs again the
steps between its checkpoint and the point where the killed process stopped; those rows describe weights the
lineage discarded, so for a step logged more than once only its last row counts. A column that a resumed run added
is blank in the earlier rows, and blank or non-finite values are left out (their count is reported), so no mean is
taken over a value that was never measured. With several runs, the last table compares each with the first: the
difference of the range means and its standard error (Welch), the usual way to tell a shift of the in-training
error from the batches' noise.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import dataclass
from pathlib import Path

DEFAULT_COLUMNS = ("pose_rot_deg", "pose_dir_deg", "coarse_acc", "attn_acc", "match_acc")


@dataclass(frozen=True)
class Summary:
    """The mean of one column over the rows of a step range: ``n`` values, standard error ``se`` (nan for n < 2)."""

    n: int
    mean: float
    se: float
    skipped: int  # blank or non-finite values in the range


def read_log(path: str | Path) -> dict[int, dict[str, str]]:
    """``step -> row`` of a ``train.csv``, the last row of a step logged more than once; ValueError (one line) for a
    file that is missing, unreadable, empty, has no ``step`` column or a step that is not an integer."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"expected a training log (train.csv), got {str(path)!r}: no such file")
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or "step" not in reader.fieldnames:
                raise ValueError(f"expected a training log with a 'step' column, got {str(path)!r} with columns "
                                 f"{reader.fieldnames or []}")
            rows: dict[int, dict[str, str]] = {}
            for line, row in enumerate(reader, start=2):
                try:
                    step = int(row["step"])
                except (TypeError, ValueError):
                    raise ValueError(f"{path}:{line}: expected an integer step, got {row['step']!r}") from None
                row.pop(None, None)  # values beyond the header (a row longer than it) have no column to count in
                rows[step] = row  # a resumed run's row replaces the discarded one
    except (OSError, UnicodeDecodeError, csv.Error) as e:  # unreadable, binary, not a CSV
        raise ValueError(f"{path}: cannot read a training log (a text CSV): {e}") from None
    if not rows:
        raise ValueError(f"expected a training log with rows, got {str(path)!r} with a header only")
    return rows


def summarise(rows: dict[int, dict[str, str]], column: str, start: int = 0, stop: int | None = None) -> Summary:
    """The mean and its standard error of ``column`` over the logged steps in [start, stop)."""
    vals, skipped = [], 0
    for step, row in rows.items():
        if step < start or (stop is not None and step >= stop):
            continue
        try:
            v = float(row.get(column) or "nan")
        except ValueError:
            v = math.nan
        if math.isfinite(v):
            vals.append(v)
        else:
            skipped += 1
    n = len(vals)
    if n == 0:
        return Summary(0, math.nan, math.nan, skipped)
    mean = sum(vals) / n
    se = math.sqrt(sum((v - mean) ** 2 for v in vals) / (n - 1) / n) if n > 1 else math.nan
    return Summary(n, mean, se, skipped)


def windows(rows: dict[int, dict[str, str]], columns, width: int, start: int = 0, stop: int | None = None):
    """``[(first step, {column: Summary})]`` per ``width``-step window of the logged steps in [start, stop)."""
    if width < 1:
        raise ValueError(f"expected a window of at least 1 step, got {width}")
    groups: dict[int, dict[int, dict[str, str]]] = {}  # the rows of each window, in one pass over the log
    for step, row in rows.items():
        if step >= start and (stop is None or step < stop):
            groups.setdefault(step // width * width, {})[step] = row
    if not groups:
        return []
    return [(lo, {c: summarise(groups.get(lo, {}), c) for c in columns})
            for lo in range(min(groups), max(groups) + 1, width)]


def difference(a: Summary, b: Summary) -> tuple[float, float]:
    """``b.mean - a.mean`` and its standard error (Welch: the two standard errors in quadrature)."""
    return b.mean - a.mean, math.hypot(a.se, b.se)


def _spec(v: float, column: str) -> str:
    """Degrees to 0.1, other columns to 3 decimals, small ones (a learning rate) to 3 significant digits."""
    if column.endswith("_deg"):
        return ".1f"
    return ".3g" if 0 < abs(v) < 0.01 else ".3f"


def _fmt(s: Summary, column: str) -> str:
    """A mean and its standard error in the mean's format (the error of 0.376 reads 0.006, not 0.00623)."""
    if s.n == 0:
        return "-"
    spec = _spec(s.mean, column)
    return f"{s.mean:{spec}}" + ("" if math.isnan(s.se) else f" ({s.se:{spec}})")


def report(paths, names, columns, start: int, stop: int | None, width: int) -> str:
    """``columns`` None: the default columns every log has (ValueError when none)."""
    logs = [read_log(p) for p in paths]
    if columns is None:
        have = [set().union(*(r.keys() for r in rows.values())) for rows in logs]
        columns = [c for c in DEFAULT_COLUMNS if all(c in h for h in have)]
        if not columns:
            raise ValueError(f"none of the default columns {list(DEFAULT_COLUMNS)} is in every log: name --columns")
    for path, rows in zip(paths, logs):
        have = set().union(*(r.keys() for r in rows.values()))
        missing = [c for c in columns if c not in have]
        if missing:
            raise ValueError(f"{path}: expected columns {missing}, not in the log; it has "
                             f"{sorted(have - {'step', 'time'})}")
    lines = []
    span = f"steps >= {start}" + ("" if stop is None else f" and < {stop}")
    for name, rows in zip(names, logs):
        lines.append(f"## {name}: mean (standard error) per {width}-step window, {span}")
        lines.append("| steps | n | " + " | ".join(columns) + " |")
        lines.append("|---|---|" + "---|" * len(columns))
        for lo, summ in windows(rows, columns, width, start, stop):
            n = max(s.n for s in summ.values())
            lines.append(f"| {lo}-{lo + width - 1} | {n} | "
                         + " | ".join(_fmt(summ[c], c) for c in columns) + " |")
        lines.append("")
    lines.append(f"## over {span}")
    lines.append("| run | n | " + " | ".join(columns) + " |")
    lines.append("|---|---|" + "---|" * len(columns))
    totals = [{c: summarise(rows, c, start, stop) for c in columns} for rows in logs]
    for name, tot in zip(names, totals):
        skipped = sum(s.skipped for s in tot.values())
        lines.append(f"| {name} | {max(s.n for s in tot.values())} | "
                     + " | ".join(_fmt(tot[c], c) for c in columns) + " |"
                     + (f" ({skipped} blank or non-finite values left out)" if skipped else ""))
    if len(logs) > 1:
        lines.append("")
        lines.append(f"## each run minus {names[0]}: difference (standard error)")
        lines.append("| run | " + " | ".join(columns) + " |")
        lines.append("|---|" + "---|" * len(columns))
        for name, tot in zip(names[1:], totals[1:]):
            cells = []
            for c in columns:
                d, se = difference(totals[0][c], tot[c])
                spec = _spec(totals[0][c].mean, c)
                cells.append("-" if math.isnan(d) else f"{d:+{spec}} ({se:{spec}})")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.logstats", description=__doc__.split("\n\n")[0])
    p.add_argument("logs", nargs="+", help="train.csv files (or run directories holding train.csv)")
    p.add_argument("--names", nargs="+", help="one name per log (default: the run directories' names)")
    p.add_argument("--columns", nargs="+", default=None,
                   help=f"train.csv columns (default: those of {', '.join(DEFAULT_COLUMNS)} every log has)")
    p.add_argument("--from", dest="start", type=int, default=0, help="first step counted (default 0)")
    p.add_argument("--to", dest="stop", type=int, default=None, help="first step not counted (default: the end)")
    p.add_argument("--window", type=int, default=100, help="steps per window (default 100)")
    a = p.parse_args(argv)
    paths = [Path(x) / "train.csv" if Path(x).is_dir() else Path(x) for x in a.logs]
    names = a.names or [x.parent.parent.name if x.parent.name == "train" else x.parent.name for x in paths]
    try:
        if len(names) != len(paths):
            raise ValueError(f"expected one name per log ({len(paths)}), got {len(names)}: {names}")
        if a.stop is not None and a.stop <= a.start:
            raise ValueError(f"expected --to after --from, got --from {a.start} --to {a.stop}")
        print(report(paths, names, a.columns, a.start, a.stop, a.window))
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
