"""Alignment tests import their scene helper (align_scene.py) from this directory; they run single-threaded
(see tests/conftest.py)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
