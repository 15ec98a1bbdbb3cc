import re

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

import pointmap as pm
from benchmarks.bench_inference import main


@pytest.fixture(scope="module")
def model_file(tmp_path_factory, test_model):
    return pm.save_model(test_model, tmp_path_factory.mktemp("bench_inference") / "tiny.safetensors")


@pytest.fixture(scope="module")
def pose_head_file(tmp_path_factory):
    """A tiny model with the shipped model's extras: the pose head (its learnt queries are parameters) and a stem."""
    torch.manual_seed(0)
    model = pm.PointmapNet(pm.PRESETS["test"].replace(pose_head=True, desc_stem=4))
    return pm.save_model(model, tmp_path_factory.mktemp("bench_inference") / "posehead.safetensors")


def test_a_model_file_is_timed_with_its_own_architecture_and_counted_in_flops(model_file, test_model, capsys):
    assert main(["--presets", "--models", str(model_file), "--sizes", "160", "--runs", "1", "--threads", "1",
                 "--cache-preset", str(model_file), "--cache-counts", "2"]) == 0
    out = capsys.readouterr().out
    cfg = test_model.cfg
    row = re.search(rf"\| tiny\.safetensors \(file: {cfg.enc_depth} / {cfg.dec_depth} blocks\) \| 160x160 \| "
                    r"([0-9.]+) \| ([0-9.]+) \| ([0-9.]+) \|", out)
    assert row, out
    seconds, gflop, rate = map(float, row.groups())
    with torch.inference_mode(), FlopCounterMode(display=False) as fc:
        test_model(torch.rand(1, 3, 160, 160), torch.rand(1, 3, 160, 160))
    assert seconds > 0 and rate > 0 and gflop == round(fc.get_total_flops() / 1e9, 1) > 0
    assert "small |" not in out  # no preset rows were asked for
    assert re.search(r"\| 2 \| 2 \| [0-9.]+ \| [0-9.]+ \| [0-9.]+x \|", out), out  # the N-image table ran on the file


def test_the_benchmark_refuses_a_missing_model_and_an_empty_request_before_timing_anything(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--presets", "--models", str(tmp_path / "absent.safetensors"), "--cache-counts"])
    assert e.value.code == 2 and "absent.safetensors" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--presets", "--cache-counts"])
    assert "at least one of --presets and --models" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--presets", "test", "--cache-preset", "nonesuch"])
    assert "--cache-preset expected" in capsys.readouterr().err


def test_a_model_with_a_pose_head_and_a_stem_is_timed_and_counted(pose_head_file, capsys):
    assert main(["--presets", "--models", str(pose_head_file), "--sizes", "160", "--runs", "1", "--threads", "1",
                 "--cache-counts"]) == 0
    assert re.search(r"\| posehead\.safetensors \(file: \d+ / \d+ blocks\) \| 160x160 \| [0-9.]+ \| [0-9.]*[1-9][0-9.]* \|",
                     capsys.readouterr().out)


def test_the_flop_count_includes_attention_as_its_two_matmuls():
    from benchmarks.bench_inference import flops_of

    q, k, v = (torch.rand(1, 2, 50, 16) for _ in range(3))
    attention = flops_of(lambda: torch.nn.functional.scaled_dot_product_attention(q, k, v))
    assert attention == 2 * (2 * 2 * 50 * 50 * 16)  # q k^T and (softmax) v, 2 heads, multiply-adds as 2
