import numpy as np
import pytest
import torch

import pointmap as pm
from benchmarks.bench_localize import main


def test_the_localize_benchmark_poses_each_view_in_the_reconstruction_of_the_others_three_ways(scenes_and_model,
                                                                                                tmp_path, capsys,
                                                                                                monkeypatch, pair_rows):
    from data.datasets import MultiViewDataset
    from pointmap.localization import Localization

    data, model_path = scenes_and_model
    scenes = [MultiViewDataset(data)[k] for k in range(2)]
    imgs = [[(x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for x in s["img"]] for s in scenes]
    calls = []

    def localize(model, recon, images, K=None, **kw):  # the query's true pose relative to the recon's first view
        (s, q), = [(s, q) for s in range(2) for q in range(3) if np.array_equal(imgs[s][q], images[0])]
        first = [k for k in range(3) if k != q][0]
        gt = scenes[s]["cam2world"].double()
        calls.append((s, q, None if K is None else torch.as_tensor(K).double(), recon.K.double()))
        if (s, q) == (1, 2):  # a query that cannot be posed counts 180 degrees
            raise pm.PointmapError("none of the 1 queries could be posed")
        T = recon.cam2world[0].double() @ torch.linalg.inv(gt[first]) @ gt[q]
        return Localization(T[None], torch.eye(3, dtype=torch.float64)[None], [0], [1.0], [1.0], ["q"])

    monkeypatch.setattr(pm, "localize", localize)
    prefix = tmp_path / "pp"
    assert main(["--model", str(model_path), "--data", str(data), "--size", "64", "--threads", "1",
                 "--shared-focal", "--per-pair", str(prefix)]) == 0
    assert "| overall | 12 | recon focal |" in capsys.readouterr().out
    rows = {m: pair_rows(f"{prefix}-{m}.csv") for m in ("estimated", "recon_focal", "true_K")}
    assert all(len(r) == 2 * 3 * 2 for r in rows.values())  # 2 scenes x 3 queries x 2 reconstruction views
    for m, r in rows.items():  # against the first reconstruction view the pose is the true one; the last is not posed
        assert all(float(r[k]["rot_err"]) < 1e-3 and float(r[k]["dir_err"]) < 1e-2 for k in range(0, 10, 2)), m
        assert float(r[10]["rot_err"]) == float(r[11]["rot_err"]) == 180.0
    # each query three times: its focal estimated, the reconstruction's one K, the scene's true K
    assert [(s, q) for s, q, _, _ in calls] == [(s, q) for s in range(2) for q in range(3) for _ in range(3)]
    for k, (s, q, K, K_rec) in enumerate(calls):
        assert float((K_rec[:, 0, 0] - K_rec[0, 0, 0]).abs().max()) == 0  # --shared-focal: one camera
        want = [None, K_rec[0], scenes[s]["K"][q].double()][k % 3]
        assert (K is None) if want is None else torch.equal(K, want)
    calls.clear()  # --recon-K: the reconstruction is given its views' true K (map px = original px here)
    assert main(["--model", str(model_path), "--data", str(data), "--size", "64", "--threads", "1", "--scenes", "1",
                 "--recon-K"]) == 0
    for s, q, _, K_rec in calls:
        assert torch.allclose(K_rec, scenes[s]["K"][[k for k in range(3) if k != q]].double(), rtol=1e-5)
    gt = scenes[0]["cam2world"].double()
    true = (torch.linalg.inv(gt[1]) @ gt[0]).numpy()  # query 0 against view 1
    angle = np.degrees(np.arccos(np.clip((np.trace(true[:3, :3]) - 1) / 2, -1, 1)))
    assert float(rows["true_K"][0]["true_rot"]) == pytest.approx(angle, abs=1e-4)


def test_the_localize_benchmark_refuses_a_set_given_twice_a_bad_scene_count_and_two_sources_of_focal(
        scenes_and_model, capsys):
    data, model_path = scenes_and_model
    for extra, message in ((["--data", str(data), str(data)], "given twice"),
                           (["--data", str(data), "--scenes", "0"], "--scenes expected a positive count"),
                           (["--data", str(data), "--shared-focal", "--recon-K"], "give one")):
        with pytest.raises(SystemExit):
            main(["--model", str(model_path), *extra])
        assert message in capsys.readouterr().err
