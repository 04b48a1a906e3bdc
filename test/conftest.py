"""Test-suite conventions: the ``slow`` marker (run by default; ``-m "not slow"`` skips it)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

#: test/ itself, so that the shared helpers import as ``harness``.
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))


def pytest_configure(config: pytest.Config) -> None:
    """Register the markers and silence the warnings of other people's code."""
    config.addinivalue_line('markers', 'slow: long-running test (dense references, studies); '
                            'deselect with -m "not slow"')
    config.addinivalue_line('filterwarnings', "ignore:module 'sre_:DeprecationWarning")
