import math

import numpy as np
import pytest

from benchmarks.bench_pose import errors
from benchmarks.breakdown import BASELINE_EDGES, BreakdownError, join, label, main, pair_geometry, summarise
from benchmarks.paired import read_per_pair
from training.evaluate import PairResult, write_per_pair


def _reference_geometry(root):
    """Each pair's baseline / depth and true rotation the slow way: the shards opened with tarfile, each pair's
    metadata and view 1's rendered depth read as plain JSON and NumPy, in the dataset's item order."""
    import io
    import json
    import tarfile

    from data.datasets import PairDataset

    ds = PairDataset(root, size=64, augment=False, split="all")
    out = []
    for k, scene, i, j in ds.items:
        with tarfile.open(ds._store.root / ds._store.names[k]) as tar:
            meta = json.load(tar.extractfile(f"{scene}/meta.json"))
            depth = np.load(io.BytesIO(tar.extractfile(f"{scene}/view-{i}.npz").read()))["depth_z"]
        A, B = (np.asarray(meta["views"][v]["cam2world"], np.float64) for v in (i, j))
        gt = np.linalg.inv(A) @ B
        out.append((float(np.linalg.norm(gt[:3, 3]) / np.median(depth[depth > 0])), errors(np.eye(4), gt)[0]))
    return out


def _write(path, set_name, rows):
    write_per_pair(path, set_name, [PairResult(*r) for r in rows])


def test_the_pairs_geometry_agrees_with_the_dataset_items_read_one_by_one(scenes_and_model):
    data, _ = scenes_and_model
    geom = pair_geometry(data)
    ref = _reference_geometry(data)
    assert len(geom) == len(ref) > 0
    for g, (base, rot) in zip(geom, ref):
        assert g["baseline"] == pytest.approx(base, rel=1e-3)
        assert g["rotation"] == pytest.approx(rot, abs=1e-3)
        assert g["move"] in {"small", "medium", "wide", "zoom", "slide", "pan", "composed"}
        assert g["kind"] in {"room", "cluster", "courtyard"}


def test_the_bands_count_hits_as_a_loop_over_the_pairs_does(scenes_and_model, tmp_path, capsys):
    data, _ = scenes_and_model
    geom = pair_geometry(data)
    rng = np.random.default_rng(0)
    rows = []
    for i, g in enumerate(geom):
        d = math.nan if i % 4 == 3 else float(rng.uniform(0, 40))  # an undefined direction now and then
        rows.append((i, float(rng.uniform(0, 40)), d, g["rotation"], float(rng.uniform(0, 40)),
                     float(rng.uniform(0, 40))))
    csv = tmp_path / "a.csv"
    _write(csv, data.name, rows)
    joined = join(read_per_pair(csv), {data.name: geom})
    for by in ("baseline", "rotation", "move", "scene"):
        table = summarise(joined, by, tol=15)
        assert sum(r["pairs"] for r in table.values()) == len(rows)
        for band, r in table.items():
            mine = [row for row, g in zip(rows, geom) if label(g, by) == band]
            dirs = [row[2] for row in mine if not math.isnan(row[2])]
            assert r["pairs"] == len(mine)
            assert r["rra"] == pytest.approx(100 * sum(row[1] < 15 for row in mine) / len(mine))
            assert r["pipe_rta"] == pytest.approx(100 * sum(row[5] < 15 for row in mine) / len(mine))
            if dirs:
                assert r["rta"] == pytest.approx(100 * sum(d < 15 for d in dirs) / len(dirs))
                assert r["dir_med"] == pytest.approx(float(np.median(dirs)))
            else:
                assert math.isnan(r["rta"]) and math.isnan(r["dir_med"])
    assert main([str(csv), str(csv), "--data", str(data), "--names", "A", "B", "--by", "baseline"]) == 0
    out = capsys.readouterr().out
    bands = [line.split("|")[1].strip() for line in out.splitlines() if line.startswith("| ") and "|---" not in line]
    assert bands[0] == "baseline" and len(bands) == 1 + len(summarise(joined, "baseline"))


def test_the_baseline_bands_cover_every_ratio_once():
    for x in (0.0, 0.049, 0.05, 0.3, 0.8, 7.5):
        hits = [i for i, (lo, hi) in enumerate(zip(BASELINE_EDGES[:-1], BASELINE_EDGES[1:])) if lo <= x < hi]
        assert len(hits) == 1
        assert label({"baseline": x}, "baseline") == (">= 0.8" if x >= 0.8 else
                                                      f"{BASELINE_EDGES[hits[0]]:g}-{BASELINE_EDGES[hits[0] + 1]:g}")


def test_a_file_measured_on_another_set_is_refused_not_misread(scenes_and_model, tmp_path, capsys):
    data, _ = scenes_and_model
    geom = pair_geometry(data)
    wrong = tmp_path / "wrong.csv"
    _write(wrong, data.name, [(0, 1.0, 2.0, geom[0]["rotation"] + 5.0)])
    with pytest.raises(BreakdownError, match="another set"):
        join(read_per_pair(wrong), {data.name: geom})
    assert main([str(wrong), "--data", str(data)]) == 2
    assert "another set" in capsys.readouterr().err
    beyond = tmp_path / "beyond.csv"
    _write(beyond, data.name, [(len(geom), 1.0, 2.0, math.nan)])
    with pytest.raises(BreakdownError, match="not in that set"):
        join(read_per_pair(beyond), {data.name: geom})
    other = tmp_path / "other.csv"
    _write(other, "some_other_set", [(0, 1.0, 2.0, math.nan)])
    with pytest.raises(BreakdownError, match="no row belongs"):
        join(read_per_pair(other), {data.name: geom})


def test_the_command_names_what_it_expected_when_given_a_missing_set_or_too_few_names(tmp_path, capsys,
                                                                                     scenes_and_model):
    data, _ = scenes_and_model
    csv = tmp_path / "a.csv"
    _write(csv, data.name, [(0, 1.0, 2.0, math.nan)])
    assert main([str(csv), "--data", str(tmp_path / "nowhere")]) == 2
    assert "nowhere is missing: expected the folder `python -m data.render` wrote" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(csv), str(csv), "--data", str(data), "--names", "only_one"])
    assert "expected 2 names" in capsys.readouterr().err
    (tmp_path / "copy").mkdir()
    twin = tmp_path / "copy" / data.name
    twin.symlink_to(data, target_is_directory=True)
    with pytest.raises(SystemExit):
        main([str(csv), "--data", str(data), str(twin)])
    assert "distinct directory names" in capsys.readouterr().err
