import pytest

from benchmarks.bench_corr import main, measure


def test_the_geometric_field_lies_on_the_geometry_and_the_resampled_one_off_it_on_the_same_pairs(scenes_and_model):
    root, _ = scenes_and_model
    res = measure(root, pairs=6, size=48, seed=0)
    old, new = res["resampled stored field (up to v72x)"], res["geometric (session 72)"]
    assert new["matches"] > 0 and new["max"] < 0.01 and new["moved"] == 0.0
    assert old["median"] > 0.05 and old["moved"] > 0.05  # 64 px renders served at 48: every pair resampled
    assert new["colour"] < old["colour"]


def test_the_table_prints_and_bad_input_exits_2_in_one_line(scenes_and_model, tmp_path, capsys):
    root, _ = scenes_and_model
    assert main(["--data", str(root), "--pairs", "2", "--size", "48"]) == 0
    assert "| geometric (session 72) |" in capsys.readouterr().out
    assert main(["--data", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit):
        main(["--data", str(root), "--pairs", "0"])
    assert "--pairs expected >= 1, got 0" in capsys.readouterr().err
