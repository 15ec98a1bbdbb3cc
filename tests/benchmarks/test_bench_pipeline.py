import re

import numpy as np
import pytest
import torch

import pointmap as pm
from benchmarks.bench_pipeline import main, render_views, rra15


@pytest.fixture(scope="module")
def model_file(tmp_path_factory, test_model):
    return pm.save_model(test_model, tmp_path_factory.mktemp("bench_pipeline") / "tiny.safetensors")


def test_each_image_count_gets_a_row_of_estimated_and_measured_times_and_its_accuracy(model_file, capsys):
    assert main(["--model", str(model_file), "--counts", "3", "2", "--render-size", "64", "--size", "64",
                 "--threads", "1"]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\| (\d+) \| complete \| (\d+) \| ([0-9.]+) / ([0-9.]+) \| ([0-9.]+) / ([0-9.]+) \(([0-9.]+)\) \| "
                      r"([0-9.]+) \| (\d+)% \|$", out, re.M)
    assert [(r[0], r[1]) for r in rows] == [("2", "1"), ("3", "3")], out  # counts sorted; n (n - 1) / 2 pairs
    for r in rows:
        inf_est, inf, al_est, al, epi, total = map(float, r[2:8])
        assert inf_est >= 0 and al_est >= 0 and 0 < inf + al <= total + 0.1  # a tiny model's estimates round to 0
        assert epi <= al  # the refinement's share (it rounds to 0.00 on these 64-px images)


def test_several_graphs_run_on_each_count_of_the_views_in_a_shuffled_order(model_file, capsys):
    assert main(["--model", str(model_file), "--counts", "4", "--render-size", "64", "--size", "64", "--threads", "1",
                 "--graphs", "swin-1", "retrieval-1", "--shuffle", "3"]) == 0
    out = capsys.readouterr().out
    assert "views shuffled (seed 3)" in out
    rows = re.findall(r"^\| 4 \| ([a-z0-9-]+) \| (\d+) \|", out, re.M)
    assert [g for g, _ in rows] == ["swin-1", "retrieval-1"]
    assert int(rows[0][1]) == 4 and 3 <= int(rows[1][1]) <= 4  # a 4-cycle; each image's nearest + the tree
    with pytest.raises(SystemExit):
        main(["--model", str(model_file), "--graphs", "bogus"])
    assert "--graphs: unknown graph 'bogus'" in capsys.readouterr().err


def test_the_views_are_rendered_alike_each_time_and_the_accuracy_counts_camera_pairs():
    images, gt = render_views(3, "room", 64)
    again, gt2 = render_views(3, "room", 64)
    assert len(images) == 3 and images[0].dtype == np.uint8 and np.array_equal(images[2], again[2])
    assert np.array_equal(gt, gt2)
    assert rra15(torch.as_tensor(gt), gt) == 100.0
    turned = torch.as_tensor(gt).clone()
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    turned[2, :3, :3] = turned[2, :3, :3] @ torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=turned.dtype)
    assert rra15(turned, gt) == pytest.approx(100 / 3)  # camera 2 turned 30 degrees: two of three pairs fail


def test_the_benchmark_refuses_bad_counts_and_a_missing_model_before_rendering(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--counts", "1", "4"])
    assert "--counts expected image counts >= 2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--model", str(tmp_path / "absent.safetensors")])
    assert "absent.safetensors" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--size", "100"])
    assert "--size expected a multiple of 16" in capsys.readouterr().err
