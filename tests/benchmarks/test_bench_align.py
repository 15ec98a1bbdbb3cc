import re

from benchmarks.bench_align import main


def test_the_alignment_benchmark_runs_both_starts_on_the_same_predictions(capsys, tmp_path):
    main(["--sizes", "12", "--hw", "32", "48", "--window", "2", "--pose-noise", "8", "--init", "mst", "averaging",
          "--png", str(tmp_path / "a.png")])
    out = capsys.readouterr().out
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in out.splitlines() if re.match(r"\| \d", ln)]
    assert [(r[0], r[2]) for r in rows] == [("12", "mst"), ("12", "averaging")]
    assert rows[0][1] == rows[1][1] == "24"  # the same graph
    start = {r[2]: float(r[7]) for r in rows}
    final = {r[2]: float(r[8]) for r in rows}
    assert start["averaging"] < start["mst"]  # the averaged start is closer on a noisy ring
    assert all(0 <= final[k] < 20 for k in final) and all(float(r[3]) > 0 for r in rows), rows
    assert (tmp_path / "a.png").stat().st_size > 0
