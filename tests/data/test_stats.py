import itertools
import json

import numpy as np
import pytest
import torch

from data.datasets import PairDataset
from data.stats import ROTATION_BINS, format_table, main, pair_records, summarize
from pointmap.geometry import invert_rigid, relative_rotation_error_deg


def test_pair_records_match_the_ground_truth_the_loader_serves(tiny_pairs):
    rec = pair_records(tiny_pairs)
    ds = PairDataset(tiny_pairs, size=64, augment=False, split="all")
    assert len(rec["rotation_deg"]) == len(ds) and rec["scenes"] == 4
    for n in range(len(ds)):
        v1, v2 = ds[n]
        rel = invert_rigid(v1["cam2world"].double()) @ v2["cam2world"].double()
        angle = relative_rotation_error_deg(rel[None, :3, :3], torch.eye(3, dtype=torch.float64)[None])[0]
        assert rec["rotation_deg"][n] == pytest.approx(float(angle), abs=1e-4)
        f1, f2 = float(v1["K"][0, 0]), float(v2["K"][0, 0])
        assert rec["focal_ratio"][n] == pytest.approx(max(f1, f2) / min(f1, f2), rel=1e-4)
    assert np.all((rec["overlap"] >= 0) & (rec["overlap"] <= 1))
    assert set(rec["kind"].tolist()) <= {"room", "cluster", "courtyard"}


def test_summary_bins_hand_made_pairs_as_the_evaluation_scores_them():
    rec = {"rotation_deg": np.array([0.0, 14.9, 15.0, 44.0, 90.0, 180.0]), "scenes": 2,
           "kind": np.array(["room"] * 4 + ["cluster"] * 2), "low_texture": np.array([True] + [False] * 5),
           "move": np.array(["small", "small", "wide", "wide", "wide", "pan"]),
           "overlap": np.array([0.1, 0.3, 0.3, 0.6, 0.9, 1.0]), "focal_ratio": np.array([1.0] * 5 + [1.2])}
    s = summarize(rec)
    assert s["scenes"] == 2 and s["pairs"] == 6
    assert [s[f"rotation {lo:g}-{hi:g} deg %"] for lo, hi in itertools.pairwise(ROTATION_BINS)] == \
        pytest.approx([200 / 6, 100 / 6, 100 / 6, 0.0, 200 / 6])  # 15 opens the second bin; 180 is in the last
    assert s["median rotation deg"] == pytest.approx(29.5)
    assert s["kind room %"] == pytest.approx(400 / 6) and s["kind courtyard %"] == 0.0
    assert s["view 2 by move wide %"] == pytest.approx(50.0) and s["low-texture %"] == pytest.approx(100 / 6)
    assert s["overlap 0.75-1 %"] == pytest.approx(200 / 6) and s["median overlap"] == pytest.approx(0.45)
    assert s["focal ratio > 1.01 %"] == pytest.approx(100 / 6)


def test_table_puts_sets_side_by_side_and_marks_statistics_a_set_lacks():
    t = format_table(["a", "b"], [{"pairs": 3, "view 2 by move pan %": 50.0}, {"pairs": 4}]).splitlines()
    assert t[0] == "| | a | b |"
    assert "| pairs | 3 | 4 |" in t and "| view 2 by move pan % | 50.0 | - |" in t


def test_cli_prints_one_column_per_set_and_refuses_what_is_not_a_pair_set(tiny_pairs, tmp_path, capsys):
    assert main([str(tiny_pairs), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert list(stats) == [str(tiny_pairs)] and stats[str(tiny_pairs)]["scenes"] == 4
    assert main([str(tiny_pairs)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"| | {tiny_pairs.name} |"
    assert main([str(tmp_path / "missing")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([str(empty)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {empty}") and len(err.strip().splitlines()) == 1


def test_the_move_statistic_counts_view_js_own_move_and_the_docs_say_it_need_not_be_from_view_i(tiny_pairs):
    import data.stats

    rec = pair_records(tiny_pairs)
    ds = PairDataset(tiny_pairs, size=64, augment=False, split="all")
    from data.datasets import pair_views

    refs = []
    for n, (meta, i, j) in enumerate(pair_views(ds)):
        assert rec["move"][n] == meta["views"][j]["move"]  # view j's own move, whatever view it was made from
        refs.append(meta["views"][j]["ref"] == i)
    assert not all(refs)  # some pair joins view j to a view it was not made from: the move is not the pair's motion
    doc = " ".join(data.stats.__doc__.split())
    assert "changes no statistic" not in doc and "only when ``ref == i``" in doc
    assert "not necessarily from view i" in " ".join(pair_records.__doc__.split())
