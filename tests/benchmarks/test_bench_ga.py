import csv
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

import pointmap as pm  # noqa: E402
from benchmarks.bench_ga import main  # noqa: E402


@pytest.fixture(scope="module")
def scenes_and_model(tmp_path_factory, test_model):
    from data.generate import GenConfig, generate

    root = tmp_path_factory.mktemp("bench_ga")
    generate(root / "heldout", GenConfig(kind="pairs", scenes=2, views=3, size=64, shard_size=2, seed=11),
             workers=1, progress=False, log=None)
    return root / "heldout", pm.save_model(test_model, root / "m.safetensors")


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_the_ga_benchmark_scores_every_camera_pair_of_every_scene_pairwise_and_aligned(scenes_and_model, tmp_path):
    from data.datasets import MultiViewDataset
    from pointmap.align import AlignConfig, global_align
    from pointmap.geometry.rotations import relative_rotation_error_deg

    data, model_path = scenes_and_model
    prefix = tmp_path / "pp"
    assert main(["--model", str(model_path), "--data", str(data), "--size", "64", "--threads", "1",
                 "--settings", "log", "id", "id+K", "--per-pair", str(prefix)]) == 0
    rows = {m: _rows(f"{prefix}-{m}.csv") for m in ("pairwise", "GA_log", "GA_id", "GA_id+K")}
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


def test_a_setting_names_the_weighting_the_optimizer_and_the_known_intrinsics_or_shared_focal():
    import argparse

    from benchmarks.bench_ga import parse_setting

    cfg, known_K = parse_setting("id:lbfgs+F+K")
    assert (cfg.conf_transform, cfg.optimizer, cfg.shared_focal, known_K) == ("id", "lbfgs", True, True)
    cfg, known_K = parse_setting("auto")
    assert (cfg.conf_transform, cfg.optimizer, cfg.shared_focal, known_K) == ("auto", "adam", False, False)
    for bad in ("auto+X", "auto+K+K", "rank", "log:sgd"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_setting(bad)
