import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_pairs(tmp_path_factory):
    """A tiny rendered pair dataset (4 scenes of 3 views at 64 px, 2 shards), made once per session."""
    from data.generate import GenConfig, generate

    out = tmp_path_factory.mktemp("pairs")
    cfg = GenConfig(kind="pairs", scenes=4, views=3, size=64, shard_size=2, seed=7)
    generate(out, cfg, workers=1, progress=False, log=None)
    return out


@pytest.fixture(scope="session")
def renderer():
    from data.render import get_renderer

    return get_renderer()
