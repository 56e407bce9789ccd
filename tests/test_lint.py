"""The tree passes ruff's lint (the configuration in pyproject.toml: pycodestyle and pyflakes at 120 columns)."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ruff_finds_nothing():
    run = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "ocpkit", "solvers", "studies",
                          "problems", "tests"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
