"""Slow splatting tests (the PSNR/time bar on the rendered scene) run only with ``-m slow``; the suite runs
single-threaded (see tests/conftest.py)."""

import pytest


def pytest_collection_modifyitems(config, items):
    if "slow" in (config.getoption("-m") or ""):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow")
    for item in items:
        if "slow" in item.keywords and "tests/splat" in str(item.fspath).replace("\\", "/"):
            item.add_marker(skip)
