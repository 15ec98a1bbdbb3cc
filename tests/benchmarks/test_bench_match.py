import pointmap as pm
import pointmap.matching as matching
from benchmarks.bench_match import main


def rows_of(out: str) -> list[list[str]]:
    return [[c.strip() for c in r.split("|")[1:-1]] for r in out.splitlines() if r.startswith("| ") and "size" not in r]


def test_the_budget_blocks_and_fixed_rows_find_the_same_matches_each_in_its_own_process(test_model, tmp_path, capsys):
    weights = pm.save_model(test_model, tmp_path / "m.safetensors")
    assert main(["--model", str(weights), "--sizes", "64", "--blocks", "budget", "7", "--threads", "1"]) == 0
    rows = rows_of(capsys.readouterr().out)
    assert [r[2] for r in rows] == ["budget", "7"]
    w, h = map(int, rows[0][1].split("x"))  # the demo pair is 4:3
    assert (w, h) == (64, 48)
    n_db = w * h
    assert rows[0][3] == f"{matching.BLOCK_ENTRIES // n_db:,}" and rows[1][3] == "7"
    assert rows[0][4] == rows[1][4] and int(rows[0][4].replace(",", "")) > 0
    assert [r[7] for r in rows] == ["yes", "yes"]
    peak, loaded = rows[1][6].replace(")", "").split(" (")
    assert float(peak) >= float(loaded) > 0


def test_a_block_count_of_zero_a_size_below_16_and_a_missing_model_are_refused(test_model, tmp_path, capsys):
    import pytest

    weights = pm.save_model(test_model, tmp_path / "m.safetensors")
    with pytest.raises(SystemExit):
        main(["--model", str(weights), "--blocks", "0"])
    assert "--blocks expected 'budget' or a positive row count, got '0'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--model", str(weights), "--sizes", "8"])
    capsys.readouterr()
    assert main(["--model", str(tmp_path / "none.safetensors"), "--sizes", "64"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: checkpoint not found")
