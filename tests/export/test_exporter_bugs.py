"""Tests of the bugs a mutation review of export/exporter.py found (session 93): ``export_model`` took any value for
its flags (``split="no"`` wrote a split export whose sidecar said ``"split": "no"``) and a parity name that is not a
string failed with a bare TypeError instead of the parity message."""

import pytest
import torch

import export.exporter as ex
import pointmap as pm
from export.exporter import export_model
from pointmap.model import PRESETS


@pytest.fixture
def no_export(monkeypatch):
    """export_graphs replaced by a failure: the checks must refuse before anything is exported."""
    monkeypatch.setattr(ex, "export_graphs", lambda *a, **k: pytest.fail("exported before the arguments were checked"))


@pytest.mark.parametrize("name, value", [("split", "no"), ("split", 1), ("fp16", "false"), ("quiet", None),
                                         ("external_data", "no"), ("external_data", 0)])
def test_export_model_refuses_a_flag_that_is_not_true_or_false_naming_it_before_anything_is_exported(
        tmp_path, no_export, name, value):
    torch.manual_seed(0)
    model = pm.PointmapNet(PRESETS["test"])
    with pytest.raises(ValueError, match=f"{name} expected True or False.*got {value!r}"):
        export_model(model, tmp_path / "out", parity="none", **{name: value})
    assert list(tmp_path.iterdir()) == []


def test_export_model_refuses_a_parity_that_is_not_a_name_with_the_parity_message(tmp_path, no_export):
    model = pm.PointmapNet(PRESETS["test"])
    with pytest.raises(ValueError, match=r"parity expected one of \['full', 'quick', 'standard', 'none'\], "
                                         r"got \['quick'\]"):
        export_model(model, tmp_path / "out", parity=["quick"])
