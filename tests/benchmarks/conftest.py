import csv

import pytest

import pointmap as pm


@pytest.fixture(scope="session")
def scenes_and_model(tmp_path_factory, test_model):
    """A tiny held-out set (2 scenes x 3 views at 64 px, every pair both ways) and the test model's file."""
    from data.generate import GenConfig, generate

    root = tmp_path_factory.mktemp("heldout")
    generate(root / "heldout", GenConfig(kind="pairs", scenes=2, views=3, size=64, shard_size=2, seed=11),
             workers=1, progress=False, log=None)
    return root / "heldout", pm.save_model(test_model, root / "m.safetensors")


@pytest.fixture
def pair_rows():
    """Reads a per-pair file's pair rows as dicts (without its rows of measurement conditions)."""
    from training.evaluate import CONDITIONS_TAG

    def read(path) -> list:
        with open(path, newline="") as f:
            return [r for r in csv.DictReader(f) if r["set"] != CONDITIONS_TAG]
    return read
