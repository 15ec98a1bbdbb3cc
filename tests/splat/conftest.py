"""Slow splatting tests (the PSNR/time bar on the rendered scene) run only with ``-m slow``; the suite runs
single-threaded (see tests/conftest.py)."""

import importlib

import pytest
import torch


def pytest_collection_modifyitems(config, items):
    if "slow" in (config.getoption("-m") or ""):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow")
    for item in items:
        if "slow" in item.keywords and "tests/splat" in str(item.fspath).replace("\\", "/"):
            item.add_marker(skip)


@pytest.fixture
def fit_module():
    """The module ``pointmap.splat.fit`` (the package exports the function ``fit`` under the same name)."""
    return importlib.import_module("pointmap.splat.fit")


@pytest.fixture
def spy(monkeypatch, fit_module):
    """``spy(name, keep=...)`` -> a list that records every call of ``pointmap.splat.fit``'s ``name`` for the
    test: (its positional arguments, tensors copied as they were at the call; its keywords; ``keep(result)``).
    The calls pass through unchanged."""
    def install(name, keep=lambda out: out):
        calls, real = [], getattr(fit_module, name)

        def recorded(*args, **kwargs):
            copied = [a.detach().clone() if isinstance(a, torch.Tensor) else a for a in args]
            out = real(*args, **kwargs)
            calls.append((copied, kwargs, keep(out)))
            return out

        monkeypatch.setattr(fit_module, name, recorded)
        return calls

    return install
