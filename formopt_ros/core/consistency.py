"""Consistency watch: windowed NIS and NEES against chi-square bands, and the gated share.

An estimator whose errors are as large as its covariance says has a normalised innovation
squared (NIS, nu^2 / S, chi-square with 1 dof for a scalar range or bearing) and, where the
truth is known, a normalised estimation error squared (NEES, chi-square with 3 dof for
[x, y, phi]) of mean 1 and 3. The watch keeps the last ``window`` samples of each and judges,
once ``min_samples`` are in:

* **sustained inconsistency** (ERROR): the window mean of NIS or NEES lies above the upper
  ``confidence`` quantile (two-sided, default 99.9 %) of the window mean of a consistent
  filter; the filter is overconfident (its errors are larger than it believes);
* **sustained gating** (ERROR): more than ``max_gated_share`` of the measurements in the
  window were refused by the innovation gate;
* **a run steadily overconfident** (ERROR): the mean NEES of the whole run (from
  ``run_min_samples`` on) lies above the band of the mean of (samples / ``nees_correlation``)
  independent chi-square(3) values; the window's NEES band is that of one value (the samples
  of one run are correlated), which lets a filter a few times overconfident through;
* WARN: the window mean lies below the band (a conservative filter), or some measurements of
  the window were gated (fewer than the share above);
* OK otherwise (also while the window fills).

Each sample counts at most ``cap`` (default: its 99.9 % chi-square quantile, 10.83 for 1 dof,
16.27 for 3), so that one outlier moves the mean of a full window of 50 by at most 0.2 and a
single large innovation in a transient does not raise an alarm; the band is that of the mean
of ``n`` capped chi-square samples, a gamma distribution matched to its mean and variance
(exact chi-square(n dof) / n without a cap). A diverged filter produces NIS in the hundreds
and gated measurements: both rules fire within a window.

The verdict is latched: the worst one seen (``worst``) decides whether a run ends ok, while
``verdict()`` is the current one (for live diagnostics).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from scipy.special import gammainc, gammaincinv

OK, WARN, ERROR = 'ok', 'warn', 'error'
LEVELS = (OK, WARN, ERROR)
#: Degrees of freedom of the NIS of a scalar measurement and of the pose NEES.
NIS_DOF, NEES_DOF = 1, 3


def capped_moments(dof: int, cap: float) -> tuple[float, float]:
    """Mean and variance of min(X, cap) for X ~ chi-square(dof) (cap = inf: dof and 2 dof)."""
    if math.isinf(cap):
        return float(dof), 2.0 * dof
    k, c = float(dof), float(cap)
    above = 1.0 - gammainc(0.5 * k, 0.5 * c)                  # P(X > c)
    mean = k * gammainc(0.5 * k + 1.0, 0.5 * c) + c * above
    second = k * (k + 2.0) * gammainc(0.5 * k + 2.0, 0.5 * c) + c * c * above
    return float(mean), float(second - mean * mean)


def chi2_quantile(dof: int, probability: float) -> float:
    """The ``probability`` quantile of chi-square(dof)."""
    return float(2.0 * gammaincinv(0.5 * dof, probability))


def window_band(samples: int, dof: int, confidence: float = 0.999,
                cap: float = math.inf) -> tuple[float, float]:
    """Two-sided ``confidence`` band of the mean of ``samples`` independent chi-square(dof)
    values, each capped at ``cap``: the quantiles of a gamma distribution with the mean's mean
    and variance (exactly chi-square(samples dof) / samples when ``cap`` is inf).

    Args:
        samples: number of values averaged, >= 1.
        dof: degrees of freedom of each value (1 for a scalar NIS, 3 for the pose NEES).
        confidence: probability inside the band, in (0, 1).
        cap: largest value a sample counts with.

    Returns:
        (low, high), dimensionless.
    """
    if samples < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(f'samples must be >= 1 and confidence in (0, 1), got {samples}, '
                         f'{confidence}')
    mean, variance = capped_moments(dof, cap)
    shape = samples * mean * mean / variance                 # of the window's sum
    scale = variance / mean
    tail = 0.5 * (1.0 - confidence)
    low, high = gammaincinv(shape, [tail, 1.0 - tail]) * scale / samples
    return float(low), float(high)


@dataclass(frozen=True)
class WatchSettings:
    """How the watch judges (see the module docstring).

    Attributes:
        window: samples in the sliding window (per statistic).
        min_samples: samples needed before a statistic is judged.
        confidence: two-sided probability of the band of the window mean.
        patience: judgements in a row with a window mean above the band before the
            inconsistency counts as sustained (an ERROR).
        max_gated_share: share of gated measurements in the window above which gating is
            sustained (an ERROR), in [0, 1].
        judge_gated_nis: a gated measurement's NIS enters the NIS window too (the simulated
            filter, whose measurements have no outliers: a gated one is the filter's fault).
            False for real data, whose gate refuses non-line-of-sight ranges rightly: 10 % of
            them, each counted at the cap, lift a consistent filter's window mean above the
            band (2.2-2.9 against 2.12); the gated share judges them instead.
        cap_probability: each sample counts at most its chi-square quantile of this
            probability (1.0: no cap).
        nees_correlation: steps over which one run's NEES stays correlated; the run's mean
            NEES counts as the mean of (samples / nees_correlation) independent values.
        run_min_samples: NEES samples needed before the run's mean is judged.
    """

    window: int = 50
    min_samples: int = 20
    confidence: float = 0.99999
    patience: int = 25
    max_gated_share: float = 0.1
    judge_gated_nis: bool = True
    cap_probability: float = 0.999
    nees_correlation: int = 150
    run_min_samples: int = 300

    def __post_init__(self) -> None:
        if not 1 <= self.min_samples <= self.window:
            raise ValueError(f'min_samples must be in [1, window], got {self.min_samples} '
                             f'(window {self.window})')
        if self.patience < 1:
            raise ValueError(f'patience must be >= 1, got {self.patience}')
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f'confidence must be in (0, 1), got {self.confidence}')
        if not 0.0 <= self.max_gated_share <= 1.0:
            raise ValueError(f'max_gated_share must be in [0, 1], got {self.max_gated_share}')
        if self.nees_correlation < 1 or self.run_min_samples < self.nees_correlation:
            raise ValueError('nees_correlation must be >= 1 and run_min_samples >= it, got '
                             f'{self.nees_correlation}, {self.run_min_samples}')
        if not 0.0 < self.cap_probability <= 1.0:
            raise ValueError(f'cap_probability must be in (0, 1], got {self.cap_probability}')

    def cap(self, dof: int) -> float:
        """The largest value one sample of ``dof`` degrees of freedom counts with."""
        return math.inf if self.cap_probability >= 1.0 else \
            chi2_quantile(dof, self.cap_probability)


@dataclass(frozen=True)
class Verdict:
    """A judgement: level 'ok', 'warn' or 'error', why, and the step it was made at."""

    level: str = OK
    reason: str = ''
    step: int | None = None

    def worse_than(self, other: 'Verdict') -> bool:
        """True when this level is more severe than ``other``'s."""
        return LEVELS.index(self.level) > LEVELS.index(other.level)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly form."""
        return {'level': self.level, 'reason': self.reason, 'step': self.step}


@dataclass
class _Window:
    """The last ``size`` samples of one statistic, each capped at ``cap``."""

    dof: int
    cap: float
    size: int
    white: bool               # independent samples (NIS); else one run's correlated NEES
    values: deque[float] = field(default_factory=deque)
    above: int = 0            # judgements in a row with the mean above the band
    status: tuple[str, str] = (OK, '')      # (level, reason) of the last judgement

    def add(self, value: float) -> None:
        """Append one sample (nan counts as the cap); the oldest leaves a full window."""
        self.values.append(min(value, self.cap) if not math.isnan(value) else self.cap)
        if len(self.values) > self.size:
            self.values.popleft()

    @property
    def mean(self) -> float:
        """Mean of the window (nan when empty)."""
        return math.fsum(self.values) / len(self.values) if self.values else math.nan


class ConsistencyWatch:
    """Tracks NIS (and NEES where the truth is known) over a sliding window; see the module
    docstring for the rules.

    Args:
        settings: window, band and gating share.
    """

    def __init__(self, settings: WatchSettings = WatchSettings()) -> None:
        self.settings = settings
        self.nis = _Window(NIS_DOF, settings.cap(NIS_DOF), settings.window, True)
        self.nees = _Window(NEES_DOF, math.inf, settings.window, False)
        self.gated: deque[bool] = deque(maxlen=settings.window)
        self.counters = {'nis_samples': 0, 'nees_samples': 0, 'gated': 0,
                         'inconsistent_steps': 0, 'gating_steps': 0, 'warn_steps': 0}
        self.gating_status: tuple[str, str] = (OK, '')
        self.run_nees: list[float] = []         # the run's NEES samples (finite ones)
        self.run_status: tuple[str, str] = (OK, '')
        self.current = Verdict()
        self.worst = Verdict()
        self._bands: dict[tuple[int, int], tuple[float, float]] = {}

    def band(self, dof: int, samples: int) -> tuple[float, float]:
        """The band of the mean of ``samples`` capped chi-square(dof) values (cached)."""
        key = (dof, samples)
        if key not in self._bands:
            self._bands[key] = window_band(samples, dof, self.settings.confidence,
                                           self.settings.cap(dof))
        return self._bands[key]

    def add_nis(self, nis: float, gated: bool = False, step: int | None = None) -> Verdict:
        """One measurement's normalised innovation squared (dimensionless; nan counts as the
        cap) and whether the gate refused it; returns the verdict after it."""
        if self.settings.judge_gated_nis or not gated:
            self.nis.add(float(nis))
        self.gated.append(bool(gated))
        self.counters['nis_samples'] += 1
        self.counters['gated'] += int(gated)
        self._judge_window('NIS', self.nis)
        self._judge_gating()
        return self._combine(step)

    def add_nees(self, nees: float, step: int | None = None) -> Verdict:
        """One step's NEES of the pose (dimensionless); returns the verdict after it."""
        self.nees.add(float(nees))
        self.counters['nees_samples'] += 1
        self._judge_window('NEES', self.nees)
        if math.isfinite(nees):
            self.run_nees.append(float(nees))
        self._judge_run()
        return self._combine(step)

    def _judge_run(self) -> None:
        """The run's mean NEES against the band of the mean of samples / nees_correlation
        independent chi-square(3) values: a filter steadily a few times overconfident (e.g.
        unobservable, as MTF with range) stays under the single-value band of the window."""
        count = len(self.run_nees)
        if count < self.settings.run_min_samples:
            return
        independent = count // self.settings.nees_correlation
        key = (-NEES_DOF, independent)
        if key not in self._bands:
            self._bands[key] = window_band(independent, NEES_DOF, self.settings.confidence)
        low, high = self._bands[key]
        mean = math.fsum(self.run_nees) / count
        self.run_status = (OK, '')
        if mean > high:
            self.run_status = (ERROR, f'sustained inconsistency: mean NEES {mean:.3g} over the '
                                      f'run ({count} steps) above the '
                                      f'{100 * self.settings.confidence:g} % band '
                                      f'[{low:.3g}, {high:.3g}] of a consistent filter '
                                      f'(NEES is correlated over about '
                                      f'{self.settings.nees_correlation} steps: {independent} '
                                      'independent values)')
            self.counters['inconsistent_steps'] += 1

    def _judge_window(self, name: str, window: _Window) -> None:
        n = len(window.values)
        window.status = (OK, '')
        if n < self.settings.min_samples:
            return
        low, high = self.band(window.dof, n if window.white else 1)
        mean = window.mean
        window.above = window.above + 1 if mean > high else 0
        if window.above >= self.settings.patience:
            window.status = (ERROR, f'sustained inconsistency: window mean {name} {mean:.3g} '
                                    f'over the last {n} samples above the '
                                    f'{100 * self.settings.confidence:g} % band [{low:.3g}, '
                                    f'{high:.3g}] of a consistent filter ({window.dof} dof) '
                                    f'for {window.above} samples in a row')
            self.counters['inconsistent_steps'] += 1
        elif mean > high:
            window.status = (WARN, f'window mean {name} {mean:.3g} above the band [{low:.3g}, '
                                   f'{high:.3g}] for {window.above} samples in a row')
        elif mean < low:
            window.status = (WARN, f'conservative: window mean {name} {mean:.3g} below the '
                                   f'band [{low:.3g}, {high:.3g}]')

    def _judge_gating(self) -> None:
        gated, n = sum(self.gated), len(self.gated)
        self.gating_status = (OK, '')
        if n >= self.settings.min_samples and gated > self.settings.max_gated_share * n:
            self.gating_status = (ERROR, f'sustained gating: {gated} of the last {n} '
                                         'measurements refused by the innovation gate (more '
                                         f'than {100 * self.settings.max_gated_share:g} %)')
            self.counters['gating_steps'] += 1
        elif gated:
            self.gating_status = (WARN, f'{gated} of the last {n} measurements gated')

    def _combine(self, step: int | None) -> Verdict:
        statuses = [self.nis.status, self.nees.status, self.gating_status, self.run_status]
        level = max((level for level, _ in statuses), key=LEVELS.index)
        reason = '; '.join(text for lvl, text in statuses if lvl == level and text)
        self.current = Verdict(level, reason, step)
        if level == WARN:
            self.counters['warn_steps'] += 1
        if self.current.worse_than(self.worst):
            self.worst = self.current
        return self.current

    def verdict(self) -> Verdict:
        """The current verdict (after the last sample)."""
        return self.current

    @property
    def failed(self) -> bool:
        """True once an ERROR was seen: the run must not end ok."""
        return self.worst.level == ERROR

    def summary(self) -> dict[str, Any]:
        """JSON-friendly state: the worst verdict (latched: it decides the run), the last one
        (after the last sample), window means, counters."""
        return {'worst': self.worst.as_dict(), 'last': self.current.as_dict(),
                'window_mean_nis': _finite_or_none(self.nis.mean),
                'window_mean_nees': _finite_or_none(self.nees.mean),
                'counters': dict(self.counters),
                'settings': {'window': self.settings.window,
                             'min_samples': self.settings.min_samples,
                             'confidence': self.settings.confidence,
                             'patience': self.settings.patience,
                             'max_gated_share': self.settings.max_gated_share,
                             'cap_probability': self.settings.cap_probability,
                             'nees_correlation': self.settings.nees_correlation,
                             'run_min_samples': self.settings.run_min_samples}}


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


__all__ = ['ERROR', 'NEES_DOF', 'NIS_DOF', 'OK', 'WARN', 'ConsistencyWatch', 'Verdict',
           'WatchSettings', 'capped_moments', 'chi2_quantile', 'window_band']
