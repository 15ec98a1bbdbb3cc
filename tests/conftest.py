import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(min(2, torch.get_num_threads()))

# Suites of many small tensor ops run single-threaded: on a shared 2-core machine two torch threads
# competing with other processes make small ops ~10x slower.
ONE_THREAD_DIRS = ("align", "io", "splat")
TESTS = Path(__file__).parent


@pytest.fixture(autouse=True)
def _one_thread_for_small_op_suites(request):
    rel = Path(str(request.node.fspath)).resolve().relative_to(TESTS.resolve())
    if not (rel.parts and rel.parts[0] in ONE_THREAD_DIRS):
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _seeded_test_preset_model():
    import pointmap as pm

    torch.manual_seed(0)
    return pm.PointmapNet(pm.PRESETS["test"]).eval()


@pytest.fixture
def tiny_model():
    """A fresh PRESETS["test"] model (seed 0) per test: tests may change it."""
    return _seeded_test_preset_model()


@pytest.fixture(scope="session")
def test_model():
    """The same model shared by the whole session: for tests that only read it."""
    return _seeded_test_preset_model()


def cached_export(factory, name: str, *extra: str):
    """Export preset:test (seed 0) through the CLI into the session's base temp dir, once per name (each
    export takes ~1-2 min on 2 cores; tests/export and tests/runtime share them)."""
    from export.__main__ import main
    from pointmap.runtime.onnx import SIDECAR

    out = factory.getbasetemp() / "onnx-exports" / name
    if not (out / SIDECAR).exists():
        rc = main(["--model", "preset:test", "--seed", "0", "--out", str(out), "--parity", "quick", "--quiet", *extra])
        assert rc == 0, f"export {name} failed with exit code {rc}"
    return out


@pytest.fixture(scope="session")
def full_export(tmp_path_factory):
    return cached_export(tmp_path_factory, "full")


@pytest.fixture(scope="session")
def split_export(tmp_path_factory):
    return cached_export(tmp_path_factory, "split", "--split")


@pytest.fixture(scope="session")
def tiny_pairs(tmp_path_factory):
    """A tiny rendered pair dataset (4 scenes of 3 views at 64 px, 2 shards), made once per session."""
    from data.generate import GenConfig, generate

    out = tmp_path_factory.mktemp("pairs")
    cfg = GenConfig(kind="pairs", scenes=4, views=3, size=64, shard_size=2, seed=7)
    generate(out, cfg, workers=1, progress=False, log=None)
    return out
