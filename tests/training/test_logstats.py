"""training.logstats: a run's train.csv as window and range means, resumed runs' repeated steps counted once."""

import math
import re
import statistics

import pytest

from training.logstats import Summary, difference, main, read_log, summarise, windows


def _write(path, header, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(",".join(header) + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return path


def test_a_step_logged_again_by_a_resumed_run_counts_once_with_the_resumed_runs_value(tmp_path):
    # the killed process logged 10 and 20 past its checkpoint at 0; the resumed run logs them again
    log = _write(tmp_path / "train.csv", ["step", "time", "pose_dir_deg"],
                 [(0, 1, 40.0), (10, 2, 90.0), (20, 3, 90.0), (10, 4, 50.0), (20, 5, 60.0)])
    rows = read_log(log)
    assert sorted(rows) == [0, 10, 20]
    s = summarise(rows, "pose_dir_deg")
    assert s.n == 3 and s.mean == pytest.approx(50.0)


def test_the_range_mean_and_standard_error_agree_with_the_statistics_module(tmp_path):
    vals = [41.5, 38.25, 55.0, 47.0, 60.5, 33.0, 44.75]
    log = _write(tmp_path / "train.csv", ["step", "pose_dir_deg"], [(10 * i, v) for i, v in enumerate(vals)])
    s = summarise(read_log(log), "pose_dir_deg", start=20, stop=60)  # steps 20, 30, 40, 50
    ref = vals[2:6]
    assert s.n == 4 and s.skipped == 0
    assert s.mean == pytest.approx(statistics.mean(ref))
    assert s.se == pytest.approx(statistics.stdev(ref) / math.sqrt(len(ref)))


def test_blank_and_non_finite_values_are_left_out_and_counted(tmp_path):
    # a column a resumed run added is blank in the earlier rows; a diverged batch logs nan
    log = _write(tmp_path / "train.csv", ["step", "loss", "attn_acc"],
                 [(0, 1.0, ""), (10, 1.0, ""), (20, 1.0, 0.25), (30, 1.0, "nan"), (40, 1.0, 0.75), (50, 1.0, "inf")])
    s = summarise(read_log(log), "attn_acc")
    assert (s.n, s.skipped) == (2, 4) and s.mean == pytest.approx(0.5)


def test_a_column_with_no_value_in_the_range_has_no_mean_rather_than_zero(tmp_path):
    log = _write(tmp_path / "train.csv", ["step", "x"], [(0, ""), (10, 3.0)])
    s = summarise(read_log(log), "x", stop=10)
    assert s.n == 0 and math.isnan(s.mean) and s.skipped == 1
    one = summarise(read_log(log), "x")
    assert one.n == 1 and one.mean == 3.0 and math.isnan(one.se)


def test_the_windows_partition_the_range_so_their_counts_add_up_to_the_ranges(tmp_path):
    log = _write(tmp_path / "train.csv", ["step", "x"], [(s, s / 10) for s in range(0, 1000, 10)])
    rows = read_log(log)
    ws = windows(rows, ["x"], 100, start=250, stop=720)
    assert [lo for lo, _ in ws] == [200, 300, 400, 500, 600, 700]
    assert sum(summ["x"].n for _, summ in ws) == summarise(rows, "x", 250, 720).n == 47
    assert ws[0][1]["x"].mean == pytest.approx(statistics.mean(s / 10 for s in range(250, 300, 10)))
    with pytest.raises(ValueError, match="at least 1 step, got 0"):
        windows(rows, ["x"], 0)


def test_the_difference_of_two_runs_has_the_welch_standard_error():
    a, b = Summary(10, 44.0, 3.0, 0), Summary(20, 40.0, 4.0, 0)
    d, se = difference(a, b)
    assert d == pytest.approx(-4.0) and se == pytest.approx(5.0)


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    ("", "with a 'step' column"),
    ("loss,lr\n1,2\n", "with a 'step' column"),
    ("step,loss\n", "header only"),
    ("step,loss\n10,1\nten,2\n", r"train.csv:3: expected an integer step, got 'ten'"),
])
def test_a_missing_empty_or_foreign_log_is_refused_in_one_line(tmp_path, content, message):
    path = tmp_path / "train.csv"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ValueError, match=message):
        read_log(path)


def test_the_cli_compares_two_runs_given_as_directories(tmp_path, capsys):
    _write(tmp_path / "a" / "train" / "train.csv", ["step", "pose_dir_deg"], [(s, 44.0 + s % 20) for s in range(0, 400, 10)])
    _write(tmp_path / "b" / "train" / "train.csv", ["step", "pose_dir_deg"], [(s, 40.0 + s % 20) for s in range(0, 400, 10)])
    assert main([str(tmp_path / "a" / "train"), str(tmp_path / "b" / "train"), "--columns", "pose_dir_deg",
                 "--from", "200"]) == 0
    out = capsys.readouterr().out
    assert "## a: mean (standard error) per 100-step window, steps >= 200" in out
    assert "| 200-299 | 10 | 49.0 (1.7) |" in out  # 44, 54 alternating: sd 5.27, se 5.27 / sqrt(10)
    assert "| b | -4.0 (1.6) |" in out  # the same spread shifted down by 4: se 1.15 each, 1.62 in quadrature


@pytest.mark.parametrize("extra, message", [
    (["--columns", "pose_dir_deg", "no_such_metric"], r"expected columns \['no_such_metric'\], not in the log"),
    (["--names", "one", "two"], "expected one name per log"),
    (["--from", "500", "--to", "500"], "expected --to after --from"),
])
def test_the_cli_refuses_bad_arguments_with_exit_2_and_a_message(tmp_path, capsys, extra, message):
    log = _write(tmp_path / "train.csv", ["step", "pose_dir_deg"], [(0, 40.0), (10, 41.0)])
    assert main([str(log), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and re.search(message, err), err


def test_the_cli_names_the_missing_column_and_lists_the_logs_columns(tmp_path, capsys):
    log = _write(tmp_path / "train.csv", ["step", "time", "loss", "pose_dir_deg"], [(0, 1, 2.0, 40.0)])
    assert main([str(log), "--columns", "coarse_acc"]) == 2
    err = capsys.readouterr().err
    assert "expected columns ['coarse_acc'], not in the log; it has ['loss', 'pose_dir_deg']" in err


def test_a_learning_rate_column_is_printed_with_significant_digits_not_rounded_to_zero(tmp_path, capsys):
    log = _write(tmp_path / "train.csv", ["step", "lr"], [(0, 1e-4), (10, 1e-4)])
    assert main([str(log), "--columns", "lr"]) == 0
    assert "| 0-99 | 2 | 0.0001 (0) |" in capsys.readouterr().out


def test_a_standard_error_is_printed_in_its_means_format(tmp_path, capsys):
    log = _write(tmp_path / "train.csv", ["step", "coarse_acc"], [(0, 0.37), (10, 0.38), (20, 0.39)])
    assert main([str(log), "--columns", "coarse_acc"]) == 0
    assert "| 0-99 | 3 | 0.380 (0.006) |" in capsys.readouterr().out  # se 0.00577, to the mean's 3 decimals


def test_a_binary_file_is_refused_in_one_line_naming_it(tmp_path):
    path = tmp_path / "train.csv"
    path.write_bytes(b"step,x\n\x84\xff\xfe\x00\x91,1\n")
    with pytest.raises(ValueError, match=r"train.csv: cannot read a training log \(a text CSV\)"):
        read_log(path)


def test_without_columns_the_default_ones_every_log_has_are_reported(tmp_path, capsys):
    log = _write(tmp_path / "train.csv", ["step", "loss", "match_acc"], [(0, 2.0, 0.1), (10, 1.0, 0.2)])
    assert main([str(log)]) == 0  # no pose, coarse or attention columns in this run
    assert "match_acc" in capsys.readouterr().out
    bare = _write(tmp_path / "b" / "train.csv", ["step", "loss"], [(0, 2.0)])
    assert main([str(bare)]) == 2
    assert "none of the default columns" in capsys.readouterr().err


def test_a_row_longer_than_the_header_does_not_end_the_cli_in_a_traceback(tmp_path, capsys):
    # (a log appended to by a writer with more columns than its header: csv files the extras under the key None,
    # which sorting the log's columns for the message compared with strings: a TypeError traceback before)
    log = _write(tmp_path / "train.csv", ["step", "time", "loss"], [(10, 1, 0.5), (20, 2, 0.4, 0.9)])
    assert main([str(log), "--columns", "coarse_acc"]) == 2
    err = capsys.readouterr().err
    assert "expected columns ['coarse_acc']" in err and "['loss']" in err and "Traceback" not in err
    assert main([str(log), "--columns", "loss"]) == 0
    assert "| 0-99 | 2 | 0.450 (0.050) |" in capsys.readouterr().out
