"""Helpers shared by the test folders (imported as ``harness``: test/ is on sys.path)."""
from __future__ import annotations

from typing import Any

import pytest


def split_by_tier(fast: int, total: int) -> Any:
    """Parametrize a test over ('first', 'last'): items 0..fast-1 in the fast tier, fast..total-1
    in the slow one, so that the full suite runs each item once."""
    return pytest.mark.parametrize('first, last', [
        (0, fast), pytest.param(fast, total, marks=pytest.mark.slow)])


__all__ = ['split_by_tier']
