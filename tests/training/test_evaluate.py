import math
import sys
from pathlib import Path

import torch

from pointmap.model import PRESETS, PointmapNet
from training.evaluate import evaluate_pairs

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import PlanePairs  # noqa: E402


def test_held_out_evaluation_reports_every_metric_in_its_range_over_the_requested_pairs():
    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"]).eval()
    ev = evaluate_pairs(model, PlanePairs(5), n_pairs=3, batch_size=2)
    assert ev["pairs"] == 3
    assert set(ev) >= {"RRA15", "RTA15", "rot_err_med", "trans_err_med", "AbsRel", "match_prec", "coarse_acc"}
    assert 0 <= ev["RRA15"] <= 100 and 0 <= ev["RTA15"] <= 100
    assert 0 <= ev["rot_err_med"] <= 180 and 0 <= ev["trans_err_med"] <= 180
    assert math.isfinite(ev["AbsRel"]) and ev["AbsRel"] >= 0
    assert 0 <= ev["coarse_acc"] <= 1
    assert 0 <= ev["RRA15_matches"] <= 100 and 0 <= ev["RTA15_matches"] <= 100


def test_the_evaluate_command_reports_held_out_metrics_of_saved_weights(tmp_path, capsys):
    import json
    import os
    import subprocess

    import pointmap as pm
    from training.evaluate import main

    root = Path(__file__).resolve().parents[2]  # rendered in a process of its own: this one may hold a GL context
    env = dict(os.environ, PYOPENGL_PLATFORM="egl", PYTHONPATH=str(root))
    subprocess.run([sys.executable, "-m", "data.render", "--out", str(tmp_path / "eval"), "--kind", "pairs",
                    "--scenes", "2", "--views", "2", "--size", "64", "--shard-size", "1", "--seed", "5", "--quiet"],
                   cwd=root, env=env, check=True, capture_output=True, timeout=300)
    torch.manual_seed(0)
    weights = pm.save_model(PointmapNet(PRESETS["test"]), tmp_path / "m.safetensors")
    assert main(["--model", str(weights), "--data", str(tmp_path / "eval"), "--size", "64", "--pairs", "2"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["size"] == 64 and 1 <= out["pairs"] <= 2 and 0 <= out["RRA15"] <= 100


def test_the_evaluate_command_refuses_missing_data_and_foreign_checkpoints_in_one_line(tmp_path, capsys):
    import pointmap as pm
    from training.evaluate import main

    weights = pm.save_model(PointmapNet(PRESETS["test"]), tmp_path / "m.safetensors")
    assert main(["--model", str(weights), "--data", str(tmp_path / "nowhere")]) == 2
    assert "error:" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    assert main(["--model", str(tmp_path / "junk.pt"), "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and len(err.strip().splitlines()) == 1
