import pytest
import torch

import pointmap as pm
from benchmarks.bench_pose import errors, main, one_focal_K
from benchmarks.paired import read_per_pair


def test_the_pose_benchmark_scores_the_pointmaps_pose_and_the_pipelines_pose_on_the_same_pair(scenes_and_model,
                                                                                                capsys):
    from data.datasets import PairDataset

    data, model_path = scenes_and_model
    csv = data.parent / "bench_pose_pairs.csv"
    assert main(["--data", str(data), "--model", str(model_path), "--pairs", "1", "--size", "64", "--threads", "1",
                 "--per-pair", str(csv), "--known-k-priors", "1,10"]) == 0
    rows = {}
    for line in capsys.readouterr().out.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[0] == "all":
            rows[cells[2]] = cells
    assert {"model", "model + own matches (no K)", "sift+E (known K)", "no rotation"} <= set(rows)
    # one pair: the medians are that pair's errors, recomputed here with pm.relative_pose and pm.pair_pose
    v1, v2 = PairDataset(data, size=64, augment=False, split="all")[0]
    model = pm.load_model(model_path)
    with torch.inference_mode():
        pred, rev = model(v1["img"][None], v2["img"][None]), model(v2["img"][None], v1["img"][None])
    gt = (torch.linalg.inv(v1["cam2world"].double()) @ v2["cam2world"].double()).numpy()
    Ks = (v1["K"].double(), v2["K"].double())
    # the swept priors' rows: the pipeline's default with both K (1 degree) is the row of "known K"
    assert rows["model + own matches (known K, prior 1)"][3:] == rows["model + own matches (known K)"][3:]
    assert "model + own matches (known K, prior 10)" in rows
    K_one = one_focal_K(pred, rev)  # both views' one focal (None without one: each view's, as `pointmap pair`)
    one = pm.pair_pose(pred, rev, patch=model.cfg.patch_size)[0] if K_one is None else \
        pm.pair_pose(pred, rev, K_one, K_one, patch=model.cfg.patch_size, rotation_prior_deg=3.0)[0]
    for name, est in (("model", pm.relative_pose(pred, pred_reverse=rev)[0]),
                      ("model + own matches (no K)", pm.pair_pose(pred, rev, patch=model.cfg.patch_size)[0]),
                      ("model + own matches (one focal)", one),
                      ("model + own matches (known K)", pm.pair_pose(pred, rev, *Ks, patch=model.cfg.patch_size)[0])):
        rot, direction = errors(est.numpy(), gt)
        assert float(rows[name][5]) == pytest.approx(rot, abs=0.051)
        assert float(rows[name][6]) == pytest.approx(direction, abs=0.051)
        if name in ("model", "model + own matches (no K)"):
            # the per-pair file holds both poses' errors: the pointmaps' in columns 0-1, the pipeline's in 3-4
            col = 0 if name == "model" else 3
            assert read_per_pair(csv)[(data.name, 0)][col:col + 2] == pytest.approx((rot, direction), abs=1e-6)


def test_the_pose_benchmark_refuses_missing_data_an_impossible_size_and_no_pairs_in_one_line(scenes_and_model,
                                                                                             tmp_path, capsys):
    data, model_path = scenes_and_model
    for flags, message in [(["--data", str(tmp_path / "nowhere")], "error:"),
                           (["--data", str(data), "--size", "100"], "--size expected 224 or a multiple of 16"),
                           (["--data", str(data), "--pairs", "0"], "--pairs expected >= 1, got 0"),
                           (["--data", str(data), "--known-k-priors", "1,x"], "--known-k-priors expected degrees >= 0"),
                           (["--data", str(data), "--known-k-priors", "-1"], "--known-k-priors expected degrees >= 0")]:
        with pytest.raises(SystemExit) as e:
            main(["--model", str(model_path), *flags])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and "Traceback" not in err
