"""Static checks run by the test command: flake8 (ament's style: line length 99, single
quotes are a convention, not checked) on the package and the tests; mypy on the package,
strict on the pure core (numpy's operators return Any, so --no-warn-return-any there)."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                          cwd=REPO, timeout=600)


@pytest.mark.skipif(importlib.util.find_spec('flake8') is None, reason='flake8 not installed')
def test_flake8() -> None:
    result = run('flake8', 'formopt_ros', 'test')
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.skipif(importlib.util.find_spec('mypy') is None, reason='mypy not installed')
def test_mypy_strict_on_core_and_checked_elsewhere() -> None:
    strict = run('mypy', '--strict', '--no-warn-return-any', 'formopt_ros/core')
    assert strict.returncode == 0, strict.stdout + strict.stderr
    everything = run('mypy', 'formopt_ros')
    assert everything.returncode == 0, everything.stdout + everything.stderr
