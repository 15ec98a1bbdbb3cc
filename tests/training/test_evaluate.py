import math
import sys
from pathlib import Path

import pytest
import torch

from pointmap.model import PRESETS, PointmapNet
from training.evaluate import evaluate_pairs

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import PlanePairs


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
    assert math.isnan(ev["match_score_auc"]) or 0 <= ev["match_score_auc"] <= 1
    assert math.isnan(ev["baseline_ratio"]) or ev["baseline_ratio"] >= 0
    assert math.isnan(ev["depth_ratio_err"]) or ev["depth_ratio_err"] >= 0
    assert math.isnan(ev["fwd_corr"]) or -1 <= ev["fwd_corr"] <= 1
    assert math.isnan(ev["fwd_sign"]) or 0 <= ev["fwd_sign"] <= 1
    assert math.isfinite(ev["focal_err"]) and ev["focal_err"] >= 0
    assert "focal_slope" in ev  # its value: test_the_focal_slope_is_one_...
    # PlanePairs only translate: every pair is in the under-30-degree group, none in the over-45 one
    assert ev["RRA15_under30"] == ev["RRA15"] and math.isnan(ev["RRA15_over45"])
    assert 0 <= ev["RRA15_matches"] <= 100 and 0 <= ev["RTA15_matches"] <= 100 and 0 <= ev["RTA15_refined"] <= 100 and 0 <= ev["RRA15_refined"] <= 100
    assert 0 <= ev["RRA15_pair"] <= 100 and 0 <= ev["RTA15_pair"] <= 100  # pm.pair_pose: what the pipeline reports


class _MixedShapes(torch.utils.data.Dataset):
    """Pairs 0 and 2 at 32 x 32, pair 1 at 32 x 48: evaluate_pairs batches 0 and 2 together, then 1."""

    def __init__(self):
        self.parts = [PlanePairs(3, seed=1), PlanePairs(3, W=48, seed=2), PlanePairs(3, seed=3)]

    def __len__(self):
        return 3

    def __getitem__(self, i):
        return self.parts[i][i]


def test_per_pair_results_come_back_in_dataset_order_and_match_each_pair_evaluated_alone():
    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"]).eval()
    data = _MixedShapes()
    rows = []
    evaluate_pairs(model, data, n_pairs=3, batch_size=4, per_pair=rows)
    assert [r.pair for r in rows] == [0, 1, 2]
    for k in range(3):  # the slow reference: the pair on its own
        alone = []
        evaluate_pairs(model, torch.utils.data.Subset(data, [k]), n_pairs=1, per_pair=alone)
        assert rows[k].rot_err == pytest.approx(alone[0].rot_err, abs=1e-3)
        assert rows[k].dir_err == pytest.approx(alone[0].dir_err, abs=1e-3)
        assert rows[k].pair_rot_err == pytest.approx(alone[0].pair_rot_err, abs=1e-3)  # the pipeline's pose
        assert rows[k].pair_dir_err == pytest.approx(alone[0].pair_dir_err, abs=1e-3, nan_ok=True)
        assert math.isfinite(rows[k].pair_rot_err)  # the test preset has descriptors: the pipeline's pose exists
        assert rows[k].true_rot == pytest.approx(0.0, abs=1e-3)  # PlanePairs only translate


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
    assert main(["--model", str(weights), "--data", str(tmp_path / "eval"), "--size", "64", "--pairs", "2",
                 "--per-pair", str(tmp_path / "pairs.csv")]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["size"] == 64 and 1 <= out["pairs"] <= 2 and 0 <= out["RRA15"] <= 100
    from benchmarks.paired import read_per_pair

    rows = read_per_pair(tmp_path / "pairs.csv")  # one row per evaluated pair, under the data folder's name
    assert sorted(rows) == [("eval", k) for k in range(int(out["pairs"]))]
    assert 100 * sum(r[0] < 15 for r in rows.values()) / len(rows) == pytest.approx(out["RRA15"], abs=0.01)
    # the pipeline's pose (pm.pair_pose) per pair: the card's RRA15_pair / RTA15_pair counted from the rows
    assert 100 * sum(r[3] < 15 for r in rows.values()) / len(rows) == pytest.approx(out["RRA15_pair"], abs=0.01)
    assert 100 * sum(r[4] < 15 for r in rows.values()) / len(rows) == pytest.approx(out["RTA15_pair"], abs=0.01)
    # a per-pair file that cannot be written is refused before the evaluation, not after it
    (tmp_path / "notes.csv").write_text("name,value\n")
    assert main(["--model", str(weights), "--data", str(tmp_path / "eval"), "--per-pair",
                 str(tmp_path / "notes.csv")]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # several folders need a --set name for their rows
        main(["--model", str(weights), "--data", f"{tmp_path / 'eval'},{tmp_path / 'eval'}", "--per-pair",
              str(tmp_path / "pairs.csv")])


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


def test_baseline_ratio_is_the_predicted_over_the_true_baseline_whatever_the_prediction_units():
    from training.evaluate import baseline_ratio

    g = torch.Generator().manual_seed(0)
    gt_z = torch.rand(8, 8, generator=g) + 1.0
    valid = torch.ones(8, 8, dtype=torch.bool)
    valid[:, :3] = False
    pred_z = gt_z * (1 + 0.1 * torch.randn(8, 8, generator=g))  # a noisy prediction ...
    pred_z[~valid] = 1e6  # ... with junk where there is no ground truth (must not count)
    scale = torch.median(gt_z[valid] / pred_z[valid])  # the alignment AbsRel uses, on valid pixels only
    t_gt = torch.tensor([0.3, 0.0, 0.1])
    for units in (1.0, 0.01, 7.0):  # a prediction in other units: depth and translation both scaled
        t_pred = 0.4 * t_gt / scale * units
        assert math.isclose(baseline_ratio(t_pred, pred_z * units, t_gt, gt_z, valid), 0.4, rel_tol=1e-5)
    # no baseline to speak of, a failed pose, no depth in front: NaN, never a number that looks like a result
    assert math.isnan(baseline_ratio(t_gt, gt_z, torch.tensor([1e-4, 0.0, 0.0]), gt_z, valid))
    assert math.isnan(baseline_ratio(torch.full((3,), float("nan")), gt_z, t_gt, gt_z, valid))
    assert math.isnan(baseline_ratio(t_gt, -gt_z, t_gt, gt_z, valid))


def test_pose_error_sources_split_the_pose_error_between_matches_and_depth_and_the_oracle_is_exact():
    from training.evaluate import PIPELINE_ROWS, SOURCE_ROWS, pose_error_sources

    torch.manual_seed(0)
    model = PointmapNet(PRESETS["test"]).eval()
    res = pose_error_sources(model, PlanePairs(3, H=32, W=32), n_pairs=3)
    assert tuple(res) == SOURCE_ROWS + PIPELINE_ROWS
    assert tuple(pose_error_sources(model, PlanePairs(3, H=32, W=32), n_pairs=3, pipeline=False)) == SOURCE_ROWS
    oracle = res["true matches + true depth"]  # true correspondences on true geometry: the method itself
    assert oracle["pairs"] == 3 and oracle["RRA15"] == 100 and oracle["RTA15"] == 100
    assert oracle["rot_err_med"] < 0.5 and oracle["trans_err_med"] < 2
    for r in res.values():
        assert 0 <= r["RRA15"] <= 100 and 0 <= r["RTA15"] <= 100 and 0 <= r["rot_err_med"] <= 180


class TrueDepthModel(torch.nn.Module):
    """A stand-in whose view-1 pointmap is the truth (and whose descriptors are noise): "true matches + model
    depth" must then be as exact as the oracle row, "model matches + ..." must not."""

    def __init__(self, dataset):
        super().__init__()
        self.inner = PointmapNet(PRESETS["test"]).eval()
        self.cfg = self.inner.cfg
        self.truth = [v for i in range(len(dataset)) for v in dataset[i]]  # both views of every pair

    def forward(self, img1, img2):
        from dataclasses import replace

        from pointmap.geometry import depth_to_points_cam

        v1 = next(v for v in self.truth if torch.equal(v["img"], img1[0]))  # either pass: the truth of its view 1
        return replace(self.inner(img1, img2), pts1_cam1=depth_to_points_cam(v1["depth_z"], v1["K"])[None])


class OracleModel(TrueDepthModel):
    """Both views' pointmaps true, but for view 2's in the forward pass, shifted by ``shift`` (view 1's frame; the
    same shift in both passes would cancel in ``relative_pose``'s average of the two), descriptors noise: the
    pointmaps' rotation and focals are exact, their translation direction off by ~60 degrees, and only true
    matches can set it right."""

    def __init__(self, dataset, shift=(0.0, 0.0, 0.8)):
        super().__init__(dataset)
        self.pairs = [dataset[i] for i in range(len(dataset))]
        self.shift = torch.tensor(shift)

    def forward(self, img1, img2):
        from dataclasses import replace

        from pointmap.geometry import depth_to_points_cam, invert_rigid, transform_points

        for a, b in self.pairs:
            for v1, v2, shift in ((a, b, self.shift), (b, a, 0.0)):
                if torch.equal(v1["img"], img1[0]) and torch.equal(v2["img"], img2[0]):
                    pts = [depth_to_points_cam(v["depth_z"], v["K"]) for v in (v1, v2)]
                    to1 = invert_rigid(v1["cam2world"]) @ v2["cam2world"]
                    return replace(self.inner(img1, img2), pts1_cam1=pts[0][None],
                                   pts2_cam1=(transform_points(to1, pts[1]) + shift)[None])
        raise AssertionError("an image pair the dataset does not hold")


def test_pose_error_sources_put_the_model_depth_and_the_true_matches_in_the_right_rows():
    from training.evaluate import pose_error_sources

    torch.manual_seed(0)
    data = PlanePairs(3, H=32, W=32)
    res = pose_error_sources(TrueDepthModel(data), data, n_pairs=3)
    exact = res["true matches + model depth"]
    assert exact["RRA15"] == 100 and exact["RTA15"] == 100 and exact["rot_err_med"] < 0.5
    assert res["model matches + model depth"] == res["model matches + true depth"]  # the same geometry here


def test_the_pipeline_fed_true_matches_sets_the_direction_right_with_or_without_intrinsics_and_its_own_do_not():
    from training.evaluate import pose_error_sources

    torch.manual_seed(0)
    data = PlanePairs(3, H=32, W=32)
    res = pose_error_sources(OracleModel(data), data, n_pairs=3)
    for row in ("pipeline: true matches + model focals", "pipeline: true matches + true intrinsics"):
        assert res[row]["pairs"] == 3 and res[row]["RRA15"] == 100 and res[row]["RTA15"] == 100, (row, res[row])
        assert res[row]["rot_err_med"] < 1 and res[row]["trans_err_med"] < 3, (row, res[row])
    for row in ("pipeline: model matches + model focals", "pipeline: model matches + true intrinsics"):
        assert res[row]["RRA15"] == 100 and res[row]["trans_err_med"] > 30, (row, res[row])  # noise matches


def test_the_pipeline_row_fed_the_model_matches_and_focals_is_the_pose_the_card_reports():
    from training.evaluate import PairResult, pose_error_sources

    torch.manual_seed(1)
    data = PlanePairs(4, H=32, W=32)
    model = OracleModel(data)
    per_pair: list = []
    ev = evaluate_pairs(model, data, n_pairs=4, batch_size=1, per_pair=per_pair)
    row = pose_error_sources(model, data, n_pairs=4)["pipeline: model matches + model focals"]
    assert row["pairs"] == 4 and row["RRA15"] == ev["RRA15_pair"] and row["RTA15"] == ev["RTA15_pair"]
    pair_rot = torch.tensor([r.pair_rot_err for r in per_pair], dtype=torch.float64)
    pair_dir = torch.tensor([r.pair_dir_err for r in per_pair], dtype=torch.float64)
    assert math.isclose(row["rot_err_med"], float(pair_rot.quantile(0.5)), abs_tol=1e-4)
    assert math.isclose(row["trans_err_med"], float(pair_dir.quantile(0.5)), abs_tol=1e-4)
    assert all(isinstance(r, PairResult) for r in per_pair) and len(per_pair) == 4


def test_pose_error_sources_refuse_a_model_without_matches():
    import pytest

    from pointmap.model import ModelConfig
    from training.evaluate import pose_error_sources

    cfg = ModelConfig.from_dict({**PRESETS["test"].to_dict(), "head": "linear", "desc_dim": 0})
    with pytest.raises(ValueError, match="descriptor head"):
        pose_error_sources(PointmapNet(cfg).eval(), PlanePairs(1), n_pairs=1)


def test_depth_ratio_says_how_much_too_deep_view_2_is_placed_relative_to_view_1_whatever_the_units():
    from training.evaluate import depth_ratio

    g = torch.Generator().manual_seed(1)
    gt1, gt2 = torch.rand(8, 8, generator=g) + 1.0, torch.rand(8, 8, generator=g) + 2.0
    valid1 = torch.ones(8, 8, dtype=torch.bool)
    valid2 = valid1.clone()
    valid2[:2] = False
    noisy2 = gt2 * (1 + 0.05 * torch.randn(8, 8, generator=g))
    noisy2[~valid2] = -1e6  # junk where there is no ground truth: must not count
    for units in (1.0, 0.02, 9.0):
        # view 2's scene predicted 1.2x as deep as it is, relative to view 1's; the prediction in any units
        r = depth_ratio(gt1 * units, gt1, valid1, noisy2 * 1.2 * units, gt2, valid2)
        exact = float(torch.median(gt2[valid2] / noisy2[valid2]) ** -1)  # the noise's own median, then x 1.2
        assert math.isclose(r, 1.2 * exact, rel_tol=1e-6) and abs(r - 1.2) < 0.05
        right = depth_ratio(gt1 * units, gt1, valid1, gt2 * units, gt2, valid2)
        assert math.isclose(right, 1.0, rel_tol=1e-6)
    # nothing predicted in front, or no valid pixel: NaN, never a number that looks like a result
    assert math.isnan(depth_ratio(gt1, gt1, valid1, -gt2, gt2, valid2))
    assert math.isnan(depth_ratio(gt1, gt1, torch.zeros_like(valid1), gt2, gt2, valid2))


def test_forward_agreement_tells_a_model_that_reads_depth_change_from_one_that_only_reads_sideways_motion():
    from training.evaluate import forward_agreement

    g = torch.Generator().manual_seed(0)
    t_gt = torch.randn(200, 3, generator=g)
    good = t_gt * 3.0 + 0.05 * torch.randn(200, 3, generator=g)  # other units
    corr, sign = forward_agreement(good, t_gt)
    assert corr > 0.95 and sign > 0.95
    sideways = t_gt.clone()
    sideways[:, 2] = torch.randn(200, generator=g)  # x, y right, the forward component noise
    corr, sign = forward_agreement(sideways, t_gt)
    assert abs(corr) < 0.3 and 0.3 < sign < 0.7
    flipped = t_gt * torch.tensor([1.0, 1.0, -1.0])
    corr, sign = forward_agreement(flipped, t_gt)
    assert corr < -0.9 and sign == 0.0
    # failed poses (NaN) and pairs without a baseline are left out; nothing to count gives NaN, not a number
    holes = good.clone()
    holes[:50] = float("nan")
    assert forward_agreement(holes, t_gt)[0] > 0.95
    assert all(math.isnan(v) for v in forward_agreement(torch.full((4, 3), float("nan")), t_gt[:4]))
    only_sideways = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    assert math.isnan(forward_agreement(only_sideways, only_sideways)[1])


def test_rotation_accuracy_by_angle_splits_pairs_at_30_and_45_degrees_of_true_rotation():
    from training.evaluate import rra_by_angle

    angle = torch.tensor([5.0, 29.9, 30.0, 44.9, 45.0, 80.0, 120.0], dtype=torch.float64)
    err = torch.tensor([1.0, 20.0, 1.0, 1.0, 14.9, 15.0, 180.0], dtype=torch.float64)
    under30, over45 = rra_by_angle(err, angle)
    assert under30 == pytest.approx(50.0)  # 5 and 29.9 deg; 30 and 44.9 belong to neither group
    assert over45 == pytest.approx(100 / 3)  # 45 deg counts; an error of exactly 15 does not
    assert math.isnan(rra_by_angle(err[:2], angle[:2])[1])
    with pytest.raises(ValueError, match="same shape"):
        rra_by_angle(err, angle[:3])


def test_confidence_order_tells_a_flat_confidence_from_one_that_ranks_the_errors():
    from training.evaluate import confidence_order

    g = torch.Generator().manual_seed(0)
    gt = 2 + torch.rand(16, 16, generator=g)
    rel = 0.3 * torch.rand(16, 16, generator=g)  # each pixel's relative depth error
    sign = torch.ones(16, 16)
    sign[:, ::2] = -1  # errors both ways, so the median scale alignment leaves each pixel's error near rel
    pred = gt * (1 + sign * rel) / 1.5  # any scale: the prediction is scale-free
    valid = torch.ones(16, 16, dtype=torch.bool)
    valid[0] = False
    # slow reference: the scale and the two means written out over the valid pixels
    p, t, e_true = pred[valid].double(), gt[valid].double(), None
    scale = torch.median(t / p)
    e_true = (p * scale - t).abs() / t
    flat = torch.ones(16, 16)
    assert confidence_order(flat, pred, gt, valid) == (0.0, pytest.approx(1.0))
    good = 1 + 1 / (rel + 0.01)  # high where the error is low
    spread, order = confidence_order(good, pred, gt, valid)
    c = good[valid].double()
    assert spread == pytest.approx(float((c >= 1.1).double().mean()))
    assert order == pytest.approx(float(e_true[c >= c.median()].mean() / e_true.mean()))
    assert order < 0.8
    assert confidence_order(1 + rel, pred, gt, valid)[1] > 1.2  # confident where wrong
    assert all(math.isnan(v) for v in confidence_order(good, pred, gt, torch.zeros_like(valid)))


def test_confidence_order_ranks_a_confidence_left_at_its_floor_on_just_over_half_the_pixels():
    from training.evaluate import confidence_order

    # 510 of 1000 pixels at the floor (1.0) and 30% off, the other 490 confident (5.0) and exact: the confident
    # half is the 490 and 11 of the tied floor pixels. Taking every pixel tied at the median made the "half" all
    # of them and the ratio 1.0 (a flat confidence), while 490 at the floor gave 0.0
    gt = torch.full((1000,), 2.0)
    valid = torch.ones(1000, dtype=torch.bool)
    for at_floor in (490, 510):
        conf = torch.ones(1000)
        conf[at_floor:] = 5.0
        pred = gt.clone()
        pred[:at_floor] *= torch.where(torch.arange(at_floor) % 2 == 0, 1.3, 0.7)
        top = max(0, 501 - (1000 - at_floor)) * 0.3 / 501  # the half: n - (n - 1) // 2 = 501 pixels
        assert confidence_order(conf, pred, gt, valid)[1] == pytest.approx(top / (at_floor * 0.3 / 1000))
    assert confidence_order(conf, pred, gt, valid)[1] == pytest.approx(0.0431, abs=1e-3)


def test_focal_error_is_zero_for_a_true_pointmap_and_the_relative_error_for_a_wrong_focal():
    from pointmap.geometry import depth_to_points_cam
    from training.evaluate import focal_error

    K = torch.tensor([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
    depth = 2 + torch.rand(24, 32, generator=torch.Generator().manual_seed(0))
    pts = depth_to_points_cam(depth, K)[None].expand(2, -1, -1, -1)
    K_other = K.clone()
    K_other[0, 0] = K_other[1, 1] = 24.0  # the pointmap was made with 30: 25% too long against 24
    err = focal_error(pts, torch.stack([K, K_other]))
    assert err[0] < 1e-3 and abs(float(err[1]) - 0.25) < 1e-3
    with pytest.raises(ValueError, match="expected"):
        focal_error(pts[0], K)


def test_match_precision_scores_a_pair_without_matches_as_zero_and_only_unjudgeable_pairs_as_nan(monkeypatch):
    from types import SimpleNamespace

    import training.evaluate as ev

    corr = torch.full((4, 5, 2), float("nan"))
    corr[1, 2] = torch.tensor([3.0, 1.0])  # view-1 pixel (u=2, v=1) sees view-2 pixel (3, 1)
    pred = SimpleNamespace(has_desc=True)

    class Matches:
        def __init__(self, xy1, xy2):
            self.xy1, self.xy2 = torch.tensor(xy1).reshape(-1, 2), torch.tensor(xy2).reshape(-1, 2)

        def __len__(self):
            return len(self.xy1)

    monkeypatch.setattr(ev, "match", lambda _: Matches([], []))
    assert ev.match_precision(pred, corr) == 0.0
    monkeypatch.setattr(ev, "match", lambda _: Matches([[2.0, 1.0], [0.0, 0.0]], [[3.5, 1.0], [1.0, 1.0]]))
    assert ev.match_precision(pred, corr) == 1.0  # the match at (0, 0) has no ground truth: not judged
    monkeypatch.setattr(ev, "match", lambda _: Matches([[0.0, 0.0]], [[1.0, 1.0]]))
    assert math.isnan(ev.match_precision(pred, corr))
    assert math.isnan(ev.match_precision(SimpleNamespace(has_desc=False), corr))


def test_the_evaluate_command_refuses_a_checkpoint_missing_its_training_config_and_an_impossible_size(tmp_path,
                                                                                                       capsys):
    import pointmap as pm
    from training.evaluate import main

    model = PointmapNet(PRESETS["test"])
    torch.save({"kind": "train", "model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 3},
               tmp_path / "nocfg.pt")
    assert main(["--model", str(tmp_path / "nocfg.pt"), "--data", str(tmp_path)]) == 2
    assert "not a complete training checkpoint (missing ['train_config'])" in capsys.readouterr().err
    weights = pm.save_model(model, tmp_path / "m.safetensors")
    with pytest.raises(SystemExit):
        main(["--model", str(weights), "--data", str(tmp_path), "--size", "0"])
    assert "--size expected 224 or a multiple of 16 from 32 to 2048 (e.g. 512), got 0" in capsys.readouterr().err


def test_a_view_whose_focal_cannot_be_estimated_counts_as_a_full_error_not_as_missing():
    from training.evaluate import focal_error

    pts = torch.rand(2, 8, 8, 3) + 0.5
    pts[1, ..., 2] = -1.0  # no point in front of the camera: no estimate
    K = torch.eye(3).repeat(2, 1, 1) * 10
    K[:, 2, 2] = 1
    err = focal_error(pts, K)
    assert math.isfinite(float(err[0])) and float(err[1]) == 1.0


def test_the_focal_slope_is_one_for_focals_that_follow_the_truth_and_zero_for_one_focal_everywhere():
    import numpy as np

    from training.evaluate import focal_slope

    true = [120.0, 150.0, 200.0, 260.0, 400.0]
    assert focal_slope([1.1 * f for f in true], true) == pytest.approx(1.0)  # a constant factor: still 1
    assert focal_slope([210.0] * 5, true) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(0)
    est = np.exp(4.6 + 0.15 * np.log(true) + 0.1 * rng.standard_normal(5))
    assert focal_slope(est.tolist(), true) == pytest.approx(np.polyfit(np.log(true), np.log(est), 1)[0])
    # views without an estimate are left out; fewer than two, or one true focal, say nothing
    assert focal_slope([float("nan"), 0.0, 200.0, 260.0, 400.0], true) == pytest.approx(1.0)
    assert math.isnan(focal_slope([float("nan")] * 4 + [5.0], true))
    assert math.isnan(focal_slope([1.0, 2.0], [100.0, 100.0]))
    with pytest.raises(ValueError, match="two \\[N\\] sequences"):
        focal_slope([1.0, 2.0], [1.0])


def test_score_auc_agrees_with_counting_every_right_and_wrong_pair_of_matches_ties_as_half():
    from training.evaluate import score_auc

    gen = torch.Generator().manual_seed(3)
    scores = torch.randint(0, 6, (200,), generator=gen).double()  # many ties
    labels = (torch.rand(200, generator=gen) < 0.4).double()
    labels[::17] = float("nan")  # unjudged matches are left out
    keep = torch.isfinite(labels)
    s, y = scores[keep], labels[keep]
    right, wrong = s[y == 1], s[y == 0]
    slow = sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in right.tolist() for b in wrong.tolist())
    assert score_auc(scores, labels) == pytest.approx(slow / (len(right) * len(wrong)), abs=1e-12)
    assert score_auc([1.0, 2.0, 3.0, 4.0], [0, 0, 1, 1]) == 1.0
    assert score_auc([4.0, 3.0, 2.0, 1.0], [0, 0, 1, 1]) == 0.0
    assert score_auc([2.0, 2.0, 2.0], [0, 1, 1]) == 0.5  # a constant score says nothing
    assert math.isnan(score_auc([1.0, 2.0], [1, 1]))
    with pytest.raises(ValueError, match="labels 0, 1 or NaN"):
        score_auc([1.0, 2.0], [0, 2])
    with pytest.raises(ValueError, match="one length"):
        score_auc([1.0, 2.0], [0])


def test_coarse_match_labels_call_a_match_right_near_its_true_correspondence_wrong_far_or_unseen_and_unjudged_off_depth():
    from types import SimpleNamespace

    from training.evaluate import coarse_match_labels

    corr = torch.full((4, 5, 2), float("nan"))
    corr[1, 2] = torch.tensor([3.0, 1.0])
    corr[2, 2] = torch.tensor([4.0, 2.0])
    valid = torch.ones(4, 5, dtype=torch.bool)
    valid[0, 0] = False  # no depth at (u=0, v=0): cannot be judged
    m = SimpleNamespace(xy1=torch.tensor([[2.0, 1.0], [2.0, 2.0], [1.0, 3.0], [0.0, 0.0]]),
                        xy2=torch.tensor([[3.5, 1.0], [0.0, 0.0], [1.0, 3.0], [0.0, 0.0]]))
    lab = coarse_match_labels(m, corr, valid, tol=1.0)
    assert lab[:3].tolist() == [1.0, 0.0, 0.0] and math.isnan(lab[3])  # right, far, a cell view 2 does not see


def test_the_cards_medians_are_the_middle_values_mean_for_an_even_count_nan_left_out():
    from training.evaluate import _median

    assert _median([0.1, 0.2, 0.3, 0.9]) == pytest.approx(0.25)  # torch's median gives 0.2
    assert _median(torch.tensor([3.0, float("nan"), 1.0, 2.0])) == 2.0
    assert math.isnan(_median([])) and math.isnan(_median([float("nan")]))


def test_a_score_that_only_tells_easy_pairs_from_hard_ones_ranks_nothing_within_a_pair():
    from training.evaluate import score_auc, within_pair_auc

    easy = (torch.tensor([0.9, 0.8, 0.7, 0.6]), torch.tensor([1.0, 0.0, 1.0, 0.0]))  # right and wrong interleaved
    hard = (torch.tensor([0.3, 0.2, 0.1, 0.05]), torch.tensor([0.0, 1.0, 0.0, 0.0]))
    pooled = score_auc(torch.cat([easy[0], hard[0]]), torch.cat([easy[1], hard[1]]))
    assert pooled > 0.7  # the easy pair's matches score higher and are right more often
    within = within_pair_auc([easy[0], hard[0]], [easy[1], hard[1]])
    assert within == pytest.approx((0.75 + 2 / 3) / 2)  # each pair's own ranking, counted by hand
    one_kind = (torch.tensor([0.5, 0.4]), torch.tensor([1.0, 1.0]))  # no wrong match: no AUC of its own
    assert within_pair_auc([easy[0], one_kind[0]], [easy[1], one_kind[1]]) == pytest.approx(0.75)


class _OnDevice(torch.nn.Module):
    """A model whose weights say they are on another device (meta: shapes without data, as a GPU is to a CPU-only
    machine): it records the device of the inputs it is given and runs the real model on the CPU, on stand-ins of
    the same shapes (meta tensors hold no values: the metrics are of no use, that they are computed is)."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        self.marker = torch.nn.Parameter(torch.empty(1, device="meta"))
        self.seen = []

    def parameters(self, recurse=True):
        yield self.marker

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.inner, name)

    def forward(self, *args):
        self.seen += [a.device.type for a in args]
        def stand_in(a):
            if not a.is_meta:
                return a
            if a.dtype == torch.bool:  # the completion mask
                return self.inner.random_mask(*a.shape)
            return torch.rand(a.shape, generator=torch.Generator().manual_seed(0))  # an image in [0, 1]

        return self.inner(*(stand_in(a) for a in args))


def test_held_out_evaluation_feeds_the_model_on_the_device_of_its_weights():
    """A GPU run evaluates its model where it trains (cuda): the images must go there, the metrics stay on the CPU."""
    torch.manual_seed(0)
    model = _OnDevice(PointmapNet(PRESETS["test"]).eval())
    ev = evaluate_pairs(model, PlanePairs(2), n_pairs=2, batch_size=2)
    assert ev["pairs"] == 2 and model.seen and set(model.seen) == {"meta"}


def test_held_out_completion_feeds_the_model_on_the_device_of_its_weights():
    from pointmap.model.pretrain import CrossViewCompletion
    from training.pretrain import completion_eval

    torch.manual_seed(0)
    model = _OnDevice(CrossViewCompletion(PRESETS["test"], mask_ratio=0.5).eval())
    ev = completion_eval(model, PlanePairs(2), n=2)
    assert math.isfinite(ev["completion_loss"]) and set(model.seen) == {"meta"}


def test_abs_rel_scales_by_the_lower_median_ratio_in_front_and_averages_over_every_valid_pixel():
    from training.evaluate import abs_rel

    g = torch.Generator().manual_seed(4)
    true_z = 1 + 4 * torch.rand(10, 14, generator=g, dtype=torch.float64)
    pred_z = true_z * (0.5 + torch.rand(10, 14, generator=g, dtype=torch.float64))
    pred_z[2, 5:9] = -2.0  # behind the camera: full relative error, left out of the scale
    valid = torch.rand(10, 14, generator=g) > 0.3
    got = abs_rel(pred_z, true_z, valid)
    # the obviously-correct reference, pixel by pixel
    p, t = pred_z[valid].tolist(), true_z[valid].tolist()
    ratios = sorted(ti / pi for pi, ti in zip(p, t) if pi > 0)
    s = ratios[(len(ratios) - 1) // 2]
    want = sum(abs(max(pi, 0.0) * s - ti) / ti for pi, ti in zip(p, t)) / len(p)
    assert got == pytest.approx(want, rel=1e-12)
    assert math.isnan(abs_rel(pred_z, true_z, torch.zeros(10, 14, dtype=torch.bool)))
    assert abs_rel(-torch.ones(10, 14, dtype=torch.float64), true_z, valid) == 1.0
