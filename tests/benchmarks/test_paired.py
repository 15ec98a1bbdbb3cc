import itertools
import math
import random

import pytest
import torch

from benchmarks.paired import (
    PairedError,
    binomial_two_sided,
    by_scene,
    by_true_rotation,
    compare_errors,
    main,
    paired,
    read_conditions,
    read_per_pair,
)
from training.evaluate import PairResult, measurement_conditions, write_per_pair


def _brute_two_sided(k, n):
    """Every sequence of n fair coin flips, counted when its split is at least as uneven as k of n."""
    if n == 0:
        return 1.0
    hits = sum(min(sum(s), n - sum(s)) <= min(k, n - k) for s in itertools.product((0, 1), repeat=n))
    return hits / 2 ** n


@pytest.mark.parametrize("n", range(0, 11))
def test_the_exact_binomial_p_value_agrees_with_counting_every_coin_sequence(n):
    for k in range(n + 1):
        assert binomial_two_sided(k, n) == pytest.approx(_brute_two_sided(k, n), abs=1e-12)
    with pytest.raises(ValueError):
        binomial_two_sided(n + 1, n)


def test_the_paired_comparison_counts_discordant_pairs_and_drops_undefined_directions():
    a = [5.0, 20.0, 10.0, 30.0, float("nan")]
    b = [20.0, 5.0, 12.0, 10.0, 3.0]
    r = compare_errors(a, b, tol=15)
    assert r["pairs"] == 4 and r["a_hits"] == 2 and r["b_hits"] == 3
    assert r["a_only"] == 1 and r["b_only"] == 2
    assert r["mcnemar_p"] == pytest.approx(1.0)  # 1 against 2 discordant pairs: a draw
    assert r["median_diff"] == pytest.approx(-6.5) and (r["b_lower"], r["b_higher"]) == (2, 2)
    assert r["sign_p"] == pytest.approx(1.0)
    # ten pairs all won by B: McNemar p = 2 / 2^10, the sign test the same
    r = compare_errors([40.0] * 10, [1.0] * 10, tol=15)
    assert r["b_only"] == 10 and r["mcnemar_p"] == pytest.approx(2 / 1024) and r["sign_p"] == pytest.approx(2 / 1024)
    with pytest.raises(ValueError, match="same pairs"):
        compare_errors([1.0], [1.0, 2.0], tol=15)


def test_per_pair_files_round_trip_keep_other_sets_and_replace_a_rewritten_set(tmp_path):
    f = tmp_path / "pairs.csv"
    write_per_pair(f, "eval_a", [PairResult(0, 3.0, 40.0, 10.0), PairResult(1, 20.0, float("nan"), 50.0)])
    write_per_pair(f, "real_rig", [PairResult(0, 7.0, 25.0, 0.3)])
    write_per_pair(f, "eval_a", [PairResult(0, 4.0, 41.0, 10.0)])  # replaces eval_a's two rows
    rows = read_per_pair(f)
    assert set(rows) == {("eval_a", 0), ("real_rig", 0)}
    assert rows[("eval_a", 0)][:3] == (4.0, 41.0, 10.0) and rows[("real_rig", 0)][:3] == (7.0, 25.0, 0.3)
    assert all(math.isnan(v) for v in rows[("eval_a", 0)][3:])  # no pipeline pose given: NaN
    write_per_pair(f, "eval_a", [PairResult(0, 4.0, 41.0, 10.0, 2.0, 12.5)])
    assert read_per_pair(f)[("eval_a", 0)] == (4.0, 41.0, 10.0, 2.0, 12.5)
    for bad in ("a,b", "all", ""):
        with pytest.raises(ValueError, match="without commas"):
            write_per_pair(f, bad, [])
    write_per_pair(f, "edge", [PairResult(0, 14.99996, 15.0, 0.0)])  # full precision: still under 15
    assert read_per_pair(f)[("edge", 0)][0] < 15


def test_only_pair_results_are_written(tmp_path):
    with pytest.raises(ValueError, match="expected PairResult rows, got tuple"):
        write_per_pair(tmp_path / "p.csv", "eval_a", [(0, 1.0, 2.0, 3.0)])
    assert not (tmp_path / "p.csv").exists()


def test_a_per_pair_file_refuses_to_overwrite_a_foreign_file_and_reading_rejects_malformed_rows(tmp_path):
    foreign = tmp_path / "notes.csv"
    foreign.write_text("name,value\nx,1\n")
    with pytest.raises(ValueError, match="refusing to overwrite"):
        write_per_pair(foreign, "eval_a", [PairResult(0, 1.0, 2.0, 3.0)])
    assert foreign.read_text() == "name,value\nx,1\n"
    with pytest.raises(PairedError, match="expected the header"):
        read_per_pair(foreign)
    bad = tmp_path / "bad.csv"
    bad.write_text("set,pair,rot_err,dir_err,true_rot\neval_a,0,1.0,x,3\n")
    with pytest.raises(PairedError, match="line 2"):
        read_per_pair(bad)
    bad.write_text("set,pair,rot_err,dir_err,true_rot\neval_a,0,1,2,3\neval_a,0,1,2,3\n")
    with pytest.raises(PairedError, match="twice"):
        read_per_pair(bad)
    with pytest.raises(PairedError, match="cannot read"):
        read_per_pair(tmp_path / "missing.csv")
    bad.write_text("set,pair,rot_err,dir_err,true_rot\nall,0,1,2,3\n")  # a set that would hide the pooled row
    with pytest.raises(PairedError, match="clashes"):
        paired(read_per_pair(bad), read_per_pair(bad))


def test_the_paired_table_joins_two_models_on_shared_pairs_per_set_and_overall(tmp_path, capsys):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    write_per_pair(a, "eval_a", [PairResult(k, 30.0, 60.0, 20.0) for k in range(8)])
    write_per_pair(a, "real_rig", [PairResult(k, 5.0, 20.0, 0.3) for k in range(3)])
    write_per_pair(b, "eval_a", [PairResult(k, 5.0, 60.0, 20.0) for k in range(10)])  # 2 pairs A lacks
    write_per_pair(b, "real_rig", [PairResult(k, 5.0, 40.0, 0.3) for k in range(3)])
    res, notes = paired(read_per_pair(a), read_per_pair(b))
    assert res[("eval_a", "rotation")]["pairs"] == 8 and res[("eval_a", "rotation")]["b_only"] == 8
    assert res[("eval_a", "rotation")]["mcnemar_p"] == pytest.approx(2 / 256)
    assert res[("real_rig", "direction")]["b_higher"] == 3 and res[("real_rig", "direction")]["median_diff"] == 20
    assert res[("all", "rotation")]["pairs"] == 11
    assert notes == ["B alone holds 2 pairs of eval_a (left out)"]
    assert main([str(a), str(b), "--names", "old", "new"]) == 0
    out = capsys.readouterr().out
    assert "| set | error | pairs | old within 15 | new within 15 |" in out
    assert "| eval_a | rotation | 8 | 0 | 8 | 0 | 8 | 0.00781 | -25.0 | 8 / 0 | 0.00781 |" in out
    assert "note: B alone holds 2 pairs of eval_a (left out)" in out


def test_the_paired_command_fails_in_one_line_on_files_without_shared_pairs(tmp_path, capsys):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    write_per_pair(a, "eval_a", [PairResult(0, 1.0, 2.0, 3.0)])
    write_per_pair(b, "eval_b", [PairResult(0, 1.0, 2.0, 3.0)])
    assert main([str(a), str(b)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the two files share no") and len(err.strip().splitlines()) == 1
    assert main([str(a), str(tmp_path / "missing.csv")]) == 2
    assert "cannot read" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(a), str(a), "--tol", "0"])


def test_files_written_before_the_pipeline_columns_read_as_nan_and_gain_them_when_a_set_is_rewritten(tmp_path):
    old = tmp_path / "old.csv"
    old.write_text("set,pair,rot_err,dir_err,true_rot\neval_a,0,1.0,2.0,3.0\nreal_rig,0,4.0,5.0,6.0\n")
    rows = read_per_pair(old)
    assert rows[("eval_a", 0)][:3] == (1.0, 2.0, 3.0) and math.isnan(rows[("eval_a", 0)][3])
    write_per_pair(old, "eval_a", [PairResult(0, 1.5, 2.5, 3.0, 0.5, 9.0)])  # the file moves to the new header
    assert old.read_text().splitlines()[0] == "set,pair,rot_err,dir_err,true_rot,pair_rot_err,pair_dir_err"
    rows = read_per_pair(old)
    assert rows[("eval_a", 0)] == (1.5, 2.5, 3.0, 0.5, 9.0)
    assert rows[("real_rig", 0)][:3] == (4.0, 5.0, 6.0) and math.isnan(rows[("real_rig", 0)][4])
    bad = tmp_path / "bad.csv"  # a row with the old width under the new header is malformed
    bad.write_text("set,pair,rot_err,dir_err,true_rot,pair_rot_err,pair_dir_err\neval_a,0,1,2,3\n")
    with pytest.raises(PairedError, match="line 2"):
        read_per_pair(bad)


def test_each_set_records_the_threads_and_packages_it_was_measured_under_and_old_files_record_none(tmp_path):
    f, threads = tmp_path / "pairs.csv", torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        write_per_pair(f, "eval_a", [PairResult(0, 1.0, 2.0, 3.0)])
        torch.set_num_threads(2)
        write_per_pair(f, "eval_b", [PairResult(0, 1.0, 2.0, 3.0)])
    finally:
        torch.set_num_threads(threads)
    got = read_conditions(f)
    assert got["eval_a"].startswith("threads=1;python=") and got["eval_b"].startswith("threads=2;python=")
    assert f"torch={torch.__version__}" in got["eval_a"]
    assert set(read_per_pair(f)) == {("eval_a", 0), ("eval_b", 0)}  # the conditions rows are not pairs
    write_per_pair(f, "eval_a", [PairResult(1, 1.0, 2.0, 3.0)])  # a rewritten set takes this process's
    assert read_conditions(f) == {"eval_a": measurement_conditions(), "eval_b": got["eval_b"]}
    assert f.read_text().splitlines()[0].startswith("set,pair,")  # the header stays the first line
    old = tmp_path / "old.csv"
    old.write_text("set,pair,rot_err,dir_err,true_rot\neval_a,0,1.0,2.0,3.0\n")
    assert read_conditions(old) == {}
    with pytest.raises(ValueError, match="set_name expected"):
        write_per_pair(f, "# conditions", [PairResult(0, 1.0, 2.0, 3.0)])


def test_the_pipeline_pose_is_compared_only_on_the_sets_where_both_files_hold_it(tmp_path, capsys):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    write_per_pair(a, "eval_a", [PairResult(k, 5.0, 60.0, 20.0, 30.0, 50.0) for k in range(6)])
    write_per_pair(a, "real_rig", [PairResult(k, 5.0, 20.0, 0.3) for k in range(2)])  # no pipeline pose
    write_per_pair(b, "eval_a", [PairResult(k, 5.0, 60.0, 20.0, 3.0, 50.0) for k in range(6)])
    write_per_pair(b, "real_rig", [PairResult(k, 5.0, 20.0, 0.3, 1.0, 1.0) for k in range(2)])
    res, _ = paired(read_per_pair(a), read_per_pair(b))
    r = res[("eval_a", "pipeline rotation")]
    assert (r["pairs"], r["a_hits"], r["b_hits"], r["b_only"]) == (6, 0, 6, 6)
    assert r["mcnemar_p"] == pytest.approx(2 / 64)
    assert res[("eval_a", "rotation")]["b_only"] == 0  # the pointmaps' pose is the same in both
    assert ("real_rig", "pipeline rotation") not in res  # A lacks it there
    assert res[("all", "pipeline rotation")]["pairs"] == 6
    assert main([str(a), str(b), "--names", "old", "new"]) == 0
    assert "| eval_a | pipeline rotation | 6 | 0 | 6 | 0 | 6 | 0.0312 | -27.0 | 6 / 0 | 0.0312 |" in capsys.readouterr().out


def test_the_true_rotation_bins_hold_the_same_comparisons_as_filtering_the_pairs_by_hand(tmp_path):
    rng = random.Random(3)
    true = [0.0, 14.9, 15.0, 29.0, 30.0, 44.0, 45.0, 59.9, 60.0, 120.0, 180.0, float("nan")] * 3
    rows_a = [PairResult(k, rng.uniform(0, 40), rng.uniform(0, 90), t) for k, t in enumerate(true)]
    rows_b = [PairResult(k, rng.uniform(0, 40), rng.uniform(0, 90), t) for k, t in enumerate(true)]
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    write_per_pair(a, "eval_a", rows_a)
    write_per_pair(b, "eval_a", rows_b)
    res = by_true_rotation(read_per_pair(a), read_per_pair(b))
    for label, lo, hi in (("0-15", 0, 15), ("15-30", 15, 30), ("30-45", 30, 45), ("45-60", 45, 60), ("60-180", 60, 181)):
        ks = [k for k, t in enumerate(true) if lo <= t < hi]  # NaN fails both comparisons: in no bin
        for col, what in ((1, "rotation"), (2, "direction")):
            want = compare_errors([rows_a[k][col] for k in ks], [rows_b[k][col] for k in ks], 15.0)
            assert res[(label, what)] == want
    assert sum(res[(lab, "rotation")]["pairs"] for lab in ("0-15", "15-30", "30-45", "45-60", "60-180")) == 33
    assert ("0-15", "pipeline rotation") not in res  # neither file holds the pipeline's pose
    write_per_pair(b, "eval_a", [r._replace(true_rot=r.true_rot + 1) for r in rows_b])
    with pytest.raises(PairedError, match="true rotations"):
        by_true_rotation(read_per_pair(a), read_per_pair(b))
    with pytest.raises(ValueError, match="increasing"):
        by_true_rotation(read_per_pair(a), read_per_pair(a), edges=(0, 30, 30))


def test_scenes_are_compared_by_their_mean_errors_and_partial_scenes_are_refused(tmp_path, capsys):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    # scene 0: B far better on one pair; scenes 1 and 2: B a little worse on every pair
    write_per_pair(a, "ga_x", [PairResult(k, 90.0 if k == 0 else 10.0, 40.0, 30.0) for k in range(9)])
    write_per_pair(b, "ga_x", [PairResult(k, 1.0 if k == 0 else 11.0, 40.0, 30.0) for k in range(9)])
    write_per_pair(a, "ga_y", [PairResult(k, 10.0, 40.0, 30.0) for k in range(3)])
    write_per_pair(b, "ga_y", [PairResult(k, 9.0, 40.0, 30.0) for k in range(3)])
    res = by_scene(read_per_pair(a), read_per_pair(b), 3)
    r = res[("ga_x", "rotation")]
    assert r["pairs"] == 3 and (r["b_lower"], r["b_higher"]) == (1, 2)
    assert r["a_median"] == pytest.approx(10.0) and r["b_median"] == pytest.approx(11.0)
    assert r["median_diff"] == pytest.approx(1.0)
    assert res[("ga_x", "direction")]["b_lower"] == 0 and res[("ga_x", "direction")]["b_higher"] == 0
    assert res[("all", "rotation")]["pairs"] == 4 and res[("all", "rotation")]["b_lower"] == 2
    # pair for pair, the same files: B gets 1 more pair under 15 degrees and loses none
    assert paired(read_per_pair(a), read_per_pair(b))[0][("ga_x", "rotation")]["b_only"] == 1
    with pytest.raises(PairedError, match="is --scene-size right"):
        by_scene(read_per_pair(a), read_per_pair(b), 4)  # 9 pairs are not whole scenes of 4
    with pytest.raises(ValueError, match="int >= 1"):
        by_scene(read_per_pair(a), read_per_pair(b), 0)
    assert main([str(a), str(b), "--names", "old", "new", "--scene-size", "3", "--by-rotation"]) == 0
    out = capsys.readouterr().out
    assert "| ga_x | rotation | 3 | 1 / 2 | +1.00 | 1 |" in out
    assert "| 30-45 | rotation | 12 | 11 | 12 | 1 | 10.0 / 11.0 |" in out
    assert main([str(a), str(b), "--scene-size", "4"]) == 2
    assert "is --scene-size right" in capsys.readouterr().err
