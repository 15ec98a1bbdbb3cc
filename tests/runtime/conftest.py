"""Exports of the tiny 'test' preset shared with tests/export (same names, same session directory)."""

import pytest
import torch

from pointmap.model import PRESETS, PointmapNet
from pointmap.runtime.onnx import SIDECAR


def cached_export(factory, name: str, *extra: str):
    """Export preset:test (seed 0) through the CLI into the session's base temp dir, once per name.
    tests/runtime/conftest.py uses the same names and directory, so either suite reuses the other's."""
    from export.__main__ import main

    out = factory.getbasetemp() / "onnx-exports" / name
    if not (out / SIDECAR).exists():
        rc = main(["--model", "preset:test", "--seed", "0", "--out", str(out), "--parity", "quick", "--quiet", *extra])
        assert rc == 0, f"export {name} failed with exit code {rc}"
    return out


@pytest.fixture(scope="session")
def test_model():
    torch.manual_seed(0)
    return PointmapNet(PRESETS["test"]).eval()


@pytest.fixture(scope="session")
def full_export(tmp_path_factory):
    return cached_export(tmp_path_factory, "full")


@pytest.fixture(scope="session")
def split_export(tmp_path_factory):
    return cached_export(tmp_path_factory, "split", "--split")
