"""The code base passes the lint rules pinned in pyproject.toml ([tool.ruff.lint])."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_code_base_passes_its_pinned_lint_rules():
    pytest.importorskip("ruff", reason="ruff is a dev dependency (pip install -e '.[dev]')")
    run = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", "."],
                         cwd=ROOT, capture_output=True, text=True, check=False)
    assert run.returncode == 0, f"ruff check found problems:\n{run.stdout}{run.stderr}"
