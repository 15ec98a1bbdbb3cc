import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def renderer():
    from data.render import get_renderer

    return get_renderer()
