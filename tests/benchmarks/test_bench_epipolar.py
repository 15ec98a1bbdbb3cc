import re

from benchmarks.bench_epipolar import main


def _table(text):
    return [ln for ln in text.splitlines() if re.match(r"\| \d", ln)]


def test_the_epipolar_benchmark_times_both_jacobians_on_the_same_inputs_and_they_reach_the_same_poses(capsys):
    main(["--sizes", "4", "6", "--hw", "48", "64", "--window", "2"])
    rows = _table(capsys.readouterr().out)
    assert [r.split("|")[1].strip() for r in rows] == ["4", "6"]
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")]
        start_rot = float(cells[3].split("/")[0])
        fd_rot, _, fd_dir = (float(x) for x in cells[6].split("/"))
        an_rot, _, an_dir = (float(x) for x in cells[10].split("/"))
        assert start_rot > 2.0 and fd_rot < 0.5 * start_rot and an_rot < 0.5 * start_rot  # both fits moved
        assert abs(fd_rot - an_rot) < 0.05 and abs(fd_dir - an_dir) < 0.2  # to the same poses
        assert float(cells[4]) >= 0 and float(cells[8]) >= 0 and cells[12].endswith("x")
        assert cells[7] == "0" and cells[11] == "0"  # no pair reversed


def test_the_stage_mode_times_the_alignment_and_the_stage_after_it(capsys):
    main(["--stage", "--sizes", "4", "--hw", "48", "64", "--window", "2"])
    rows = _table(capsys.readouterr().out)
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[0] == "4" and int(cells[2]) > 0 and float(cells[3]) >= 0 and float(cells[4]) >= 0
    assert int(cells[5]) > 0  # the fit ran (a skipped stage reports no evaluations)


def test_the_epipolar_benchmark_refuses_image_counts_below_three(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["--sizes", "2"])
    assert "--sizes expected image counts >= 3" in capsys.readouterr().err
