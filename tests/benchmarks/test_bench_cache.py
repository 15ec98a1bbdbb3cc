import pointmap as pm
from benchmarks.bench_cache import main, rotation_gap_deg


def test_the_rotation_gap_is_zero_for_the_same_cameras_and_the_angle_of_a_known_turn():
    import torch

    cams = torch.eye(4).repeat(3, 1, 1)
    turned = cams.clone()
    turned[1, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    assert rotation_gap_deg(cams, cams) == 0.0
    assert abs(rotation_gap_deg(cams, turned) - 90.0) < 1e-6


def test_the_benchmark_reads_every_pair_on_the_second_runs_and_float32_matches_the_baseline(test_model, tmp_path,
                                                                                           capsys):
    weights = pm.save_model(test_model, tmp_path / "m.safetensors")
    assert main(["--model", str(weights), "--views", "3", "--render-size", "64", "--size", "64", "--niter", "20",
                 "--threads", "1", "--repeats", "2"]) == 0
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]]
            for r in capsys.readouterr().out.splitlines() if r.startswith("| ") and "cache" in r}
    assert rows["float32 cache, first run"][2] == "0 / 6" and rows["float32 cache, second run"][2] == "6 / 0"
    assert rows["float16 cache, second run"][2] == "6 / 0"
    assert float(rows["float32 cache, second run"][4]) < 0.01  # read back bit for bit
    assert float(rows["float32 cache, first run"][3]) > 0 and rows["no cache (baseline)"][3] == "-"
