"""The one door for user values: convert, check range and finiteness, name the field."""
from __future__ import annotations

import math
import operator
import reprlib
from collections.abc import Sequence

import numpy as np

from formopt_ros.core.linalg import positive_definite_exactly

#: Relative difference of P[i, j] and P[j, i] (to the pair's scale, see :func:`as_covariance`)
#: taken for rounding: a filter that never symmetrises its covariance drifts up to about 1e-6
#: of the pair's scale, which changes a correlation by 5e-7 at most.
SYMMETRY_TOLERANCE = 1e-6


class InvalidInput(ValueError):
    """A value refused at the boundary: ``name`` is the field, ``reason`` what is wrong."""

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f'{name} {reason}')
        self.name = name
        self.reason = reason


def interval(low: float | None, high: float | None, low_open: bool = False,
             high_open: bool = False) -> str:
    """The range in words, e.g. '(0, 1000]'; None is an unbounded side."""
    def text(x: float) -> str:
        return str(x) if isinstance(x, int) else f'{x:g}'
    left = '(-inf' if low is None else f"{'(' if low_open else '['}{text(low)}"
    right = 'inf)' if high is None else f"{text(high)}{')' if high_open else ']'}"
    return f'{left}, {right}'


def as_real(name: str, value: object, low: float | None = None, high: float | None = None, *,
            unit: str = '', low_open: bool = False, high_open: bool = False) -> float:
    """``float(value)``, or InvalidInput naming ``name`` unless it is a finite number in the
    range (booleans are refused: True would become 1.0)."""
    where = interval(low, high, low_open, high_open) + (f' {unit}' if unit else '')
    reason = f'must be a number in {where}, got {reprlib.repr(value)}'
    if isinstance(value, (bool, np.bool_)):
        raise InvalidInput(name, reason)
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        raise InvalidInput(name, reason) from None
    if not (math.isfinite(number)
            and (low is None or (number > low if low_open else number >= low))
            and (high is None or (number < high if high_open else number <= high))):
        raise InvalidInput(name, reason)
    return number


def as_integer(name: str, value: object, low: int | None = None,
               high: int | None = None) -> int:
    """``value`` as an int (an integer, or its decimal text), or InvalidInput naming ``name``
    unless it lies in [low, high]; floats and booleans are refused."""
    reason = f'must be an integer in {interval(low, high)}, got {reprlib.repr(value)}'
    if isinstance(value, (bool, np.bool_)):
        raise InvalidInput(name, reason)
    try:
        number = int(value, 10) if isinstance(value, str) else operator.index(
            value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidInput(name, reason) from None
    if (low is not None and number < low) or (high is not None and number > high):
        raise InvalidInput(name, reason)
    return number


def as_bool(name: str, value: object) -> bool:
    """``value`` if it is a boolean, else InvalidInput naming ``name``."""
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidInput(name, f'must be true or false, got {reprlib.repr(value)}')
    return bool(value)


def as_choice(name: str, value: object, choices: Sequence[str]) -> str:
    """``value`` if it is one of ``choices``, else InvalidInput naming ``name``."""
    if not isinstance(value, str) or value not in choices:
        raise InvalidInput(name, f'must be one of {tuple(choices)}, got {reprlib.repr(value)}')
    return value


def as_array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """``np.asarray(value, dtype=float)`` of ``shape`` (-1: any length) with finite entries, or
    InvalidInput naming ``name``; an array with masked entries is refused."""
    wanted = '(' + ', '.join('n' if n == -1 else str(n) for n in shape) + \
        (',)' if len(shape) == 1 else ')')
    try:
        if np.ma.is_masked(value):
            raise ValueError('masked')
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InvalidInput(name, f'must be an array of real numbers of shape {wanted}, got '
                                 f'{reprlib.repr(value)}') from None
    if array.ndim != len(shape) or any(n not in (-1, m) for n, m in zip(shape, array.shape)):
        raise InvalidInput(name, f'must have shape {wanted}, got shape {array.shape}')
    if not np.isfinite(array).all():
        raise InvalidInput(name, f'must be finite, got {reprlib.repr(array.tolist())}')
    return array


def as_covariance(name: str, value: object, low: float = 0.0,
                  high: float = math.inf) -> np.ndarray:
    """A symmetric positive definite (3, 3) float array with variances in [low, high], or
    InvalidInput naming ``name``.

    P[i, j] and P[j, i] may differ by rounding, up to SYMMETRY_TOLERANCE of the pair's own
    scale max(sqrt(P[i, i] P[j, j]), |P[i, j]|, |P[j, i]|), and are then averaged (the scale is
    the pair's: with variances 1e4 and 1e-16, 9e-7 and -9e-7 are correlations of +-0.9)."""
    P = as_array(name, value, (3, 3))
    if not (P == P.T).all():
        roots = np.sqrt(np.abs(np.diag(P)))
        scale = np.maximum(np.maximum(np.outer(roots, roots), np.abs(P)), np.abs(P.T))
        if (np.abs(P - P.T) > SYMMETRY_TOLERANCE * np.maximum(scale, 1e-300)).any():
            raise InvalidInput(name, f'must be symmetric (to rounding), got {P.tolist()}')
        P = 0.5 * (P + P.T)
    variances = np.diag(P)
    if ((variances > 0.0) & ((variances < low) | (variances > high))).any():
        raise InvalidInput(name, f'must have variances in {interval(low, high)}, got '
                                 f'{variances.tolist()}')
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = P.tolist()
    if not positive_definite_exactly((p00, p01, p02, p11, p12, p22)):
        raise InvalidInput(name, f'must be positive definite, got eigenvalues '
                                 f'{np.linalg.eigvalsh(P).tolist()}')
    return P
