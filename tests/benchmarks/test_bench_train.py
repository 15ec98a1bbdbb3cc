import re
from pathlib import Path

import pytest

from benchmarks.bench_train import main

ROOT = Path(__file__).resolve().parents[2]


def _rows(out: str) -> list:
    return re.findall(r"^\| (this|baseline) \| (\S+) \| [0-9.]+M \| ([a-z0-9 ,.]+) \| 64x64 \| 2 \| [0-9.]+ \| ([0-9.]+) \| "
                      r"([0-9.]+) \| [0-9.]+ \| ([0-9.]+) \|.* \| ([0-9.]+) \|$", out, flags=re.M)


def test_a_baseline_checkout_is_timed_in_the_same_run_and_the_same_code_gives_the_same_first_loss(capsys):
    # the baseline is this checkout itself: both rows run the same code from the same seed
    assert main(["--preset", "test", "--size", "64", "--batch", "2", "--threads", "1", "--steps", "1",
                 "--baseline-code", str(ROOT)]) == 0
    out = capsys.readouterr().out
    rows = _rows(out)
    assert [r[0] for r in rows] == ["baseline", "this"], out
    assert rows[0][1:3] == rows[1][1:3] == ("test", "eager, float32")
    assert all(float(r[3]) > 0 and float(r[4]) > 0 for r in rows)  # wall and CPU seconds per step
    assert rows[0][5] == rows[1][5] and float(rows[0][6]) == float(rows[1][6])  # GFLOP/step and first loss
    assert re.search(r"test, eager, float32: this / baseline speed [0-9.]+x \(wall\), [0-9.]+x \(CPU time\)", out)


def test_the_baseline_rows_come_from_the_baseline_checkouts_code(tmp_path, capsys):
    import shutil

    base = tmp_path / "base"  # a copy of the code whose test preset has one more encoder block
    skip = shutil.ignore_patterns("*.safetensors", "demo_scenes", "__pycache__")
    for pkg in ("pointmap", "training", "benchmarks", "data"):
        shutil.copytree(ROOT / pkg, base / pkg, ignore=skip)
    config = base / "pointmap" / "model" / "config.py"
    text = config.read_text()
    assert '"test": ModelConfig(enc_dim=32, enc_depth=2,' in text
    config.write_text(text.replace('"test": ModelConfig(enc_dim=32, enc_depth=2,', '"test": ModelConfig(enc_dim=32, enc_depth=3,'))
    assert main(["--preset", "test", "--size", "64", "--batch", "2", "--threads", "1", "--steps", "1",
                 "--baseline-code", str(base)]) == 0
    out = capsys.readouterr().out
    params = dict(re.findall(r"^\| (this|baseline) \| test \| ([0-9.]+)M \|", out, flags=re.M))
    assert set(params) == {"this", "baseline"} and float(params["baseline"]) > float(params["this"]), out


def test_the_benchmark_refuses_a_directory_that_is_not_a_checkout_and_zero_steps(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--preset", "test", "--baseline-code", str(tmp_path)])
    assert "--baseline-code expected a checkout of this project" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--preset", "test", "--steps", "0"])
    assert "--steps expected >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # refused before a baseline's subprocess is started
        main(["--preset", "bogus", "--baseline-code", str(ROOT)])
    assert "invalid choice: 'bogus'" in capsys.readouterr().err
