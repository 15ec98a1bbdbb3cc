import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture
def tiny_model():
    import pointmap as pm

    torch.manual_seed(0)
    return pm.PointmapNet(pm.PRESETS["test"]).eval()
