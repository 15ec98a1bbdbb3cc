import re

import pytest

from benchmarks.bench_epipolar import main


def _table(text):
    return [ln for ln in text.splitlines() if re.match(r"\| \d", ln)]


def test_the_epipolar_benchmark_times_both_jacobians_on_the_same_inputs_and_they_reach_the_same_poses(capsys):
    main(["--sizes", "4", "6", "--hw", "48", "64", "--window", "2"])
    rows = _table(capsys.readouterr().out)
    assert [r.split("|")[1].strip() for r in rows] == ["4", "6"]
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")][1:]  # after the image count: seed, pairs, ...
        start_rot = float(cells[3].split("/")[0])
        fd_rot, _, fd_dir = (float(x) for x in cells[6].split("/"))
        an_rot, _, an_dir = (float(x) for x in cells[10].split("/"))
        assert start_rot > 2.0 and fd_rot < 0.5 * start_rot and an_rot < 0.5 * start_rot  # both fits moved
        assert abs(fd_rot - an_rot) < 0.05 and abs(fd_dir - an_dir) < 0.2  # to the same poses
        assert float(cells[4]) >= 0 and float(cells[8]) >= 0 and cells[12].endswith("x")
        assert cells[7] == "0" and cells[11] == "0"  # no pair reversed


def test_several_starts_and_modes_run_on_the_same_rings_and_the_summary_counts_the_failed_starts(capsys):
    main(["--sizes", "5", "--hw", "48", "64", "--window", "2", "--seeds", "0", "1", "2", "--rot-deg", "6",
          "--jacobians", "analytic", "--cheirality", "off", "on", "--fail-deg", "1e-6"])
    out = capsys.readouterr().out
    rows = _table(out)
    per_start = [[c.strip() for c in r.strip("|").split("|")] for r in rows if r.count("|") > 10]
    assert [(c[0], c[1]) for c in per_start] == [("5", "0"), ("5", "1"), ("5", "2")]
    assert len({c[4] for c in per_start}) == 3  # three seeds, three starts
    for c in per_start:
        assert float(c[4].split("/")[0]) > 2.0  # the start is off
        for k in (7, 11):  # off, then on: both moved the cameras most of the way back
            assert float(c[k].split("/")[0]) < 0.5 * float(c[4].split("/")[0])
    summary = [[c.strip() for c in r.strip("|").split("|")] for r in rows if r.count("|") == 7]
    assert [(c[0], c[1], c[2]) for c in summary] == [("5", "off, analytic", "3"), ("5", "on, analytic", "3")]
    # a threshold below any fit's error fails every start, and lists each start's worst rotation
    assert all(c[3].startswith("3 (") and c[4] == "-" for c in summary)
    assert "| 5 | off, analytic | on, analytic |" not in out and "off, analytic: time (s)" in out
    # a threshold above every error fails none, and the worst of the others is the largest worst rotation
    main(["--sizes", "5", "--hw", "48", "64", "--window", "2", "--seeds", "0", "1", "2", "--rot-deg", "6",
          "--jacobians", "analytic", "--cheirality", "on", "--fail-deg", "90"])
    rows = _table(capsys.readouterr().out)
    per_start = [[c.strip() for c in r.strip("|").split("|")] for r in rows if r.count("|") == 10]  # one method
    assert len(per_start) == 3
    worst = max(float(c[7].split("/")[0]) for c in per_start)
    summary, = [[c.strip() for c in r.strip("|").split("|")] for r in rows if r.count("|") == 7]
    assert summary[3] == "0 (-)" and float(summary[4]) == pytest.approx(worst, abs=0.006)


def test_the_stage_mode_times_the_alignment_and_the_stage_after_it_with_and_without_cheirality(capsys):
    main(["--stage", "--sizes", "4", "--hw", "48", "64", "--window", "2", "--seeds", "0", "5",
          "--cheirality", "off", "one", "on"])
    rows = _table(capsys.readouterr().out)
    assert len(rows) == 6  # one per seed and cheirality setting
    cells = [[c.strip() for c in r.strip("|").split("|")] for r in rows]
    assert [(c[0], c[1], c[5]) for c in cells] == [("4", s, ch) for s in ("0", "5") for ch in ("off", "one", "on")]
    for c in cells:
        assert int(c[2]) > 0 and int(c[3]) > 0 and float(c[4]) >= 0 and float(c[6]) >= 0
        assert int(c[7]) > 0 and c[8] in ("yes", "kept")  # the fit ran (a skipped stage reports no evaluations)
        ga, stage = (float(x) for x in c[9].split("/"))
        assert ga >= 0 and stage >= 0
    assert cells[0][9].split("/")[0] == cells[1][9].split("/")[0]  # both settings start from the same alignment
    assert cells[0][9] != cells[3][9]  # another seed, another scene


def test_the_epipolar_benchmark_refuses_image_counts_below_three(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["--sizes", "2"])
    assert "--sizes expected image counts >= 3" in capsys.readouterr().err
