"""Alignment tests run single-threaded: on the shared 2-core machine, two torch threads competing with
other processes make small tensor ops ~10x slower."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
