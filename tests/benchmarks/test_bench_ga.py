import numpy as np
import pytest
import torch

import pointmap as pm
from benchmarks.bench_ga import main


def test_the_ga_benchmark_scores_every_camera_pair_of_every_scene_pairwise_and_aligned(scenes_and_model, tmp_path, pair_rows):
    from data.datasets import MultiViewDataset
    from pointmap.align import AlignConfig, global_align
    from pointmap.geometry.rotations import relative_rotation_error_deg

    data, model_path = scenes_and_model
    prefix = tmp_path / "pp"
    assert main(["--model", str(model_path), "--data", str(data), "--size", "64", "--threads", "1",
                 "--settings", "log", "id", "id+K", "id+S", "id+E", "--per-pair", str(prefix)]) == 0
    rows = {m: pair_rows(f"{prefix}-{m}.csv") for m in ("pairwise", "pairwise_+_matches", "GA_log", "GA_id", "GA_id+K",
                                                     "GA_id+S", "GA_id+E")}
    assert all(len(r) == 2 * 3 for r in rows.values())  # 2 scenes x 3 camera pairs
    # the first scene's pair (0, 1) aligned with conf itself, recomputed here
    scene = MultiViewDataset(data)[0]
    imgs = [(x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for x in scene["img"]]
    views = pm.load_images(imgs, size=64)
    model = pm.load_model(model_path)
    preds = pm.predict_pairs(model, views, pm.make_pairs(3), quiet=True)
    c2w = global_align(views, preds, config=AlignConfig(conf_transform="id", quiet=True)).cam2world.double()
    gt = scene["cam2world"].double()
    est, true = torch.linalg.inv(c2w[0]) @ c2w[1], torch.linalg.inv(gt[0]) @ gt[1]
    assert float(rows["GA_id"][0]["rot_err"]) == pytest.approx(float(relative_rotation_error_deg(est[:3, :3], true[:3, :3])), abs=1e-3)
    angle = np.degrees(np.arccos(np.clip((np.trace(true[:3, :3].numpy()) - 1) / 2, -1, 1)))
    assert float(rows["pairwise"][0]["true_rot"]) == pytest.approx(angle, abs=1e-4)
    # the pair's own pose refined on its matches, recomputed here
    own = pm.pair_pose(preds[(0, 1)], preds[(1, 0)], patch=model.cfg.patch_size)[0].double()
    assert float(rows["pairwise_+_matches"][0]["rot_err"]) == pytest.approx(
        float(relative_rotation_error_deg(own[:3, :3], true[:3, :3])), abs=1e-3)
    # '+S': the same alignment, then the sparse refinement on every pair's matches
    from pointmap.align.sparse import SparseConfig, refine_matches

    recon = global_align(views, preds, config=AlignConfig(conf_transform="id", quiet=True))
    refined = refine_matches(recon, {k: pm.match(p) for k, p in preds.items()}, config=SparseConfig(quiet=True))
    c2w_S = refined.cam2world.double()
    est_S = torch.linalg.inv(c2w_S[0]) @ c2w_S[1]
    assert float(rows["GA_id+S"][0]["rot_err"]) == pytest.approx(
        float(relative_rotation_error_deg(est_S[:3, :3], true[:3, :3])), abs=1e-3)
    # '+E': the same alignment, then the poses refined on the model's matches (what reconstruct runs)
    from pointmap.align import EpipolarConfig, refine_epipolar

    refined = refine_epipolar(views, preds, recon, config=EpipolarConfig(patch=model.cfg.patch_size))
    # 64 px images hold 16 cells of 16 px: too few matches, so the stage says so and keeps the aligned poses (its
    # fit is tested in tests/align/test_epipolar.py); the benchmark must report exactly what it returned
    assert "too few matches" in refined.info["epipolar"]["reason"]
    c2w_E = refined.cam2world.double()
    est_E = torch.linalg.inv(c2w_E[0]) @ c2w_E[1]
    assert float(rows["GA_id+E"][0]["rot_err"]) == pytest.approx(
        float(relative_rotation_error_deg(est_E[:3, :3], true[:3, :3])), abs=1e-3)
    # '+K' hands the alignment the scene's true intrinsics (and that changes the result)
    assert rows["GA_id+K"][0]["rot_err"] != rows["GA_id"][0]["rot_err"]
    c2w_K = global_align(views, preds, K=scene["K"].double(),
                         config=AlignConfig(conf_transform="id", quiet=True)).cam2world.double()
    est_K = torch.linalg.inv(c2w_K[0]) @ c2w_K[1]
    assert float(rows["GA_id+K"][0]["rot_err"]) == pytest.approx(
        float(relative_rotation_error_deg(est_K[:3, :3], true[:3, :3])), abs=1e-3)


def test_the_ga_benchmark_refuses_a_foreign_per_pair_file_before_running(scenes_and_model, tmp_path, capsys):
    data, model_path = scenes_and_model
    (tmp_path / "pp-pairwise.csv").write_text("name,score\nx,1\n")
    with pytest.raises(SystemExit) as e:
        main(["--model", str(model_path), "--data", str(data), "--size", "64", "--per-pair", str(tmp_path / "pp")])
    assert e.value.code == 2 and "--per-pair" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["--model", str(model_path), "--data", str(data), "--settings", "rank"])
    assert e.value.code == 2 and "conf_transform expected 'auto' or one of" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["--model", str(model_path), "--data", str(data), str(data)])
    assert e.value.code == 2 and "twice" in capsys.readouterr().err


def test_a_setting_names_the_weighting_the_optimizer_the_known_intrinsics_shared_focal_and_refinements():
    import argparse

    from benchmarks.bench_ga import parse_setting
    from pointmap.align.epipolar import EpipolarConfig

    cfg, known_K, sparse, epipolar = parse_setting("id:lbfgs+F+K")
    assert (cfg.conf_transform, cfg.optimizer, cfg.shared_focal, known_K, sparse, epipolar) == \
        ("id", "lbfgs", True, True, False, None)
    cfg, known_K, sparse, epipolar = parse_setting("auto")
    assert (cfg.conf_transform, cfg.optimizer, cfg.shared_focal, known_K, sparse, epipolar) == \
        ("auto", "adam", False, False, False, None)
    assert parse_setting("log+S")[2] and not parse_setting("log+S")[1] and parse_setting("log+S")[3] is None
    assert parse_setting("auto+E")[3].cheirality and not parse_setting("auto+E")[2]
    assert parse_setting("auto+E-")[3].cheirality is False  # the stage without its cheirality residuals
    assert parse_setting("auto+E")[3].second_descent and not parse_setting("auto+E1")[3].second_descent
    assert parse_setting("auto+E1")[3].cheirality  # with them, in one descent (session 33's stage)
    assert parse_setting("auto+E")[3].rotation_prior_deg == EpipolarConfig().rotation_prior_deg  # the library's
    assert parse_setting("auto+K+E@1")[3].rotation_prior_deg == 1.0 and parse_setting("auto+K+E@1")[1]
    assert parse_setting("auto+E-@0.5")[3].rotation_prior_deg == 0.5 and not parse_setting("auto+E-@0.5")[3].cheirality
    assert cfg.init == "averaging" and parse_setting("auto+T+E")[0].init == "mst"  # the library's start, or the tree's
    assert cfg.pose_head and not parse_setting("auto+P+E")[0].pose_head  # the heads' motions, or the maps'
    # the stage's focals from the matches (off by default, as in the library)
    assert parse_setting("auto+F+E+C")[3].self_calibrate and not parse_setting("auto+E")[3].self_calibrate
    for bad in ("auto+X", "auto+K+K", "auto+S+S", "auto+E+E", "auto+E+E-", "auto+E1+E", "auto+T+T", "auto+P+P", "rank", "log:sgd",
                "auto+E@0", "auto+E@x", "auto+E@", "auto+K@1", "auto+E@1+E@3", "auto+C", "auto+E+C+C"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_setting(bad)


def test_a_setting_sets_the_pose_heads_prior_and_refuses_a_bad_one():
    import argparse

    from benchmarks.bench_ga import parse_setting
    from pointmap.align import AlignConfig

    assert parse_setting("auto+E")[0].head_prior == AlignConfig().head_prior  # the library's default
    cfg, _, _, epipolar = parse_setting("auto+H0.3@5,30+E")
    assert (cfg.head_prior, cfg.head_prior_deg, epipolar is not None) == (0.3, (5.0, 30.0), True)
    assert parse_setting("auto+E+H0")[0].head_prior == 0.0
    for bad in ("auto+H-1", "auto+Hx", "auto+H0.1+H0.2", "auto+H1@0,20", "auto+H1@10", "auto+P+H0.1"):
        with pytest.raises(argparse.ArgumentTypeError, match="H<weight>"):
            parse_setting(bad)


def test_the_ga_benchmark_refuses_a_missing_set_and_an_impossible_size_before_running(scenes_and_model, tmp_path,
                                                                                      capsys):
    data, model_path = scenes_and_model
    for flags, message in [(["--data", str(data), str(tmp_path / "nowhere")], "error:"),
                           (["--data", str(data), "--size", "100"], "--size expected 224 or a multiple of 16")]:
        with pytest.raises(SystemExit) as e:
            main(["--model", str(model_path), *flags])
        assert e.value.code == 2 and message in capsys.readouterr().err
