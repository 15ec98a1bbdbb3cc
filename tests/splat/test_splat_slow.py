import pytest

pytest.importorskip("pyrender")


@pytest.mark.slow
def test_scene_psnr_bar():
    """4 training views at 256x192, 1 % depth noise, 1 deg / 2 cm pose noise: init + fit within two
    minutes of CPU time and >= 26 dB on held-out views after test-time pose alignment."""
    from benchmarks.bench_splat import bench_scene

    r = bench_scene(time_budget=None, align_steps=60)
    assert r["psnr"] >= 26.0
    assert r["rot"][1] < r["rot"][0]
    assert r["rot"][1] + 100 * r["trans"][1] < r["rot"][0] + 100 * r["trans"][0]
    # CPU seconds: the shared machine's wall time depends on the other jobs (reported by the benchmark)
    assert r["fit_cpu"] <= 120.0
