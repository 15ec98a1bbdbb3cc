import numpy as np
import pytest

import pointmap as pm
from benchmarks.bench_retrieval import agreement, main, view_angles


def test_agreement_is_perfect_for_a_similarity_that_is_the_closeness_itself_and_reversed_for_its_opposite():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    cams = np.tile(np.eye(4), (6, 1, 1))
    for k, z in enumerate(axes):  # any rotation whose third column is z
        x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        cams[k, :3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    angles = view_angles(cams)
    assert np.allclose(np.diag(angles), 0, atol=1e-5) and np.allclose(angles, angles.T)
    assert agreement(-angles, angles) == (pytest.approx(1.0), 6)
    rho, _ = agreement(angles, angles)
    assert rho == pytest.approx(-1.0)


def test_the_benchmark_prints_both_similarities_for_each_scene(test_model, tmp_path, capsys):
    weights = pm.save_model(test_model, tmp_path / "m.safetensors")
    assert main(["--model", str(weights), "--views", "4", "--scenes", "room", "--render-size", "64", "--size",
                 "64"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| room |")]
    assert [r.split("|")[2].strip() for r in rows] == ["mutual-nearest tokens (retrieval-K)", "mean-token cosine"]
    for r in rows:
        rho, hits = r.split("|")[3].strip(), r.split("|")[4].strip()
        assert -1 <= float(rho) <= 1 and hits.endswith("/ 4") and 0 <= int(hits.split("/")[0]) <= 4
