"""The consistency watch on seeded streams, in the estimator session, the study's flag and the
domain rules."""
from __future__ import annotations

import math

import numpy as np
import pytest

from formopt_ros.core.consistency import (
    ERROR, OK, WARN, ConsistencyWatch, WatchSettings, capped_moments, window_band)
from formopt_ros.core.domain import check_deviation_domain, check_domain, check_input_domain
from formopt_ros.core.session import EstimatorSession
from formopt_ros.core.protocol import Timebase
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import TrialResult, run_trial, trial_streams
from formopt_ros.core.strategies import make_strategy
from formopt_ros.core.study import StudyConfig, nees_band, run_study, summarize

SQRT5 = math.sqrt(5.0)


def stream(watch: ConsistencyWatch, nis: np.ndarray, nees: np.ndarray | None = None,
           gated: np.ndarray | None = None) -> list[str]:
    """Feed one NIS (and NEES) per step; the level after each step."""
    levels = []
    for k, value in enumerate(nis):
        watch.add_nis(value, bool(gated[k]) if gated is not None else False, k + 1)
        if nees is not None:
            watch.add_nees(nees[k], k + 1)
        levels.append(watch.verdict().level)
    return levels


def test_band_without_cap_is_the_chi_square_band_of_the_mean() -> None:
    """Uncapped, the band is chi2(n dof) / n: the study's NEES band for 50 trials, and the
    99.999 % band of 50 NIS values; the cap of 1 dof at 99.9 % lowers the mean to 0.998 and
    the band's upper edge from 2.140 to 2.124."""
    assert window_band(50, 3, 0.95) == pytest.approx(nees_band(50), rel=1e-12)
    low, high = window_band(50, 1, 0.99999)
    assert low == pytest.approx(0.3483, abs=1e-4) and high == pytest.approx(2.1403, abs=1e-4)
    watch = ConsistencyWatch()
    assert watch.band(1, 50) == pytest.approx((0.3517, 2.1235), abs=1e-4)
    mean, variance = capped_moments(1, 10.827566)
    assert mean == pytest.approx(0.9981, abs=1e-4) and variance < 2.0


def test_consistent_streams_stay_ok() -> None:
    """100 seeded runs of 600 chi-square NIS (1 dof) and NEES (3 dof) values: none ends in
    error (the band is 99.999 %, held for 25 samples in a row)."""
    rng = np.random.default_rng(0)
    failed = 0
    for _ in range(100):
        watch = ConsistencyWatch()
        stream(watch, rng.chisquare(1, 600), rng.chisquare(3, 600))
        failed += watch.failed
    assert failed == 0
    assert watch.counters['nis_samples'] == watch.counters['nees_samples'] == 600
    assert watch.summary()['window_mean_nis'] == pytest.approx(1.0, abs=0.5)


def correlated_nees(rng: np.random.Generator, steps: int, rho: float) -> np.ndarray:
    """chi-square(3) values correlated from step to step: |e_k|^2 of a 3-vector AR(1) with
    unit-variance components (integrated correlation time of the squares about
    (1 + rho^2) / (1 - rho^2) steps, as one run's NEES)."""
    e = np.empty((steps, 3))
    e[0] = rng.standard_normal(3)
    for k in range(1, steps):
        e[k] = rho * e[k - 1] + np.sqrt(1.0 - rho * rho) * rng.standard_normal(3)
    return np.sum(e * e, axis=1)


def test_a_run_steadily_a_few_times_overconfident_is_an_error() -> None:
    """NEES correlated over about 40 steps (the paper's strategies: 15-45, CRM with range up
    to about 150): 50 consistent runs of 600 steps raise no error; four times too large (MTF
    with range: NEES 9-13), which the window's single-value band lets through, is an error in
    at least 22 of 50 runs (measured: 27), naming the run's mean."""
    rng = np.random.default_rng(3)
    failed, caught, by_run = 0, 0, 0
    for _ in range(50):
        nees = correlated_nees(rng, 600, 0.975)
        watch = ConsistencyWatch()
        stream(watch, rng.chisquare(1, 600), nees)
        failed += watch.failed
        watch = ConsistencyWatch()
        stream(watch, rng.chisquare(1, 600), 4.0 * nees)
        caught += watch.failed
        by_run += 'over the run' in watch.worst.reason
    assert failed == 0 and caught >= 22, (failed, caught)          # measured: 0 and 27
    assert by_run >= 10, (by_run, caught)      # measured: 15 first by the run's mean


def test_an_overconfident_filter_is_an_error_with_its_reason() -> None:
    """NIS three times too large: the window mean (about 2.4 once capped) leaves the band
    (upper edge 2.12-2.27 for 50-20 samples); after 25 samples in a row above it, an error,
    latched with the step it came at (the current verdict may drop back to a warning)."""
    rng = np.random.default_rng(1)
    watch = ConsistencyWatch()
    levels = stream(watch, 3.0 * rng.chisquare(1, 200))
    first = levels.index(ERROR) + 1
    assert first == 49
    assert watch.failed and watch.worst.step == first
    assert watch.worst.reason == (
        'sustained inconsistency: window mean NIS 2.4 over the last 49 samples above the '
        '99.999 % band [0.347, 2.14] of a consistent filter (1 dof) for 25 samples in a row')
    assert watch.counters['inconsistent_steps'] == levels.count(ERROR) == 24


def test_sustained_gating_is_an_error_and_a_few_gated_a_warning() -> None:
    """Every fifth measurement gated (20 % > 10 %): an error at the 20th sample, when the
    window is first judged; one gated measurement among 60 only warns."""
    nis = np.ones(60)
    gated = np.arange(60) % 5 == 4
    nis[gated] = 400.0
    watch = ConsistencyWatch()
    levels = stream(watch, nis, gated=gated)
    assert levels[18] != ERROR and levels[19] == ERROR
    assert watch.worst.reason.startswith('sustained gating: 4 of the last 20 measurements')
    assert watch.counters['gated'] == 12 and watch.counters['gating_steps'] == 41
    once = ConsistencyWatch()
    stream(once, np.where(np.arange(60) == 30, 400.0, 1.0), gated=np.arange(60) == 30)
    assert once.worst.level == WARN and not once.failed


def test_one_outlier_is_capped_and_a_conservative_filter_warns() -> None:
    """A single NIS of 1e6 (or nan) in a consistent stream moves the window mean by at most
    10.8 / 50: no error. NIS ten times too small: a warning, never an error."""
    rng = np.random.default_rng(2)
    nis = rng.chisquare(1, 300)
    nis[100], nis[200] = 1e6, math.nan
    watch = ConsistencyWatch()
    stream(watch, nis)
    assert not watch.failed
    small = ConsistencyWatch()
    levels = stream(small, 0.1 * rng.chisquare(1, 300))
    assert small.worst.level == WARN and levels[-1] == WARN
    assert small.worst.reason.startswith('conservative: window mean NIS')


def test_settings_are_checked() -> None:
    for bad in (dict(window=10, min_samples=20), dict(confidence=1.0), dict(patience=0),
                dict(max_gated_share=1.5), dict(cap_probability=0.0)):
        with pytest.raises(ValueError):
            WatchSettings(**bad)
    assert ConsistencyWatch(WatchSettings(cap_probability=1.0)).nis.cap == math.inf


def session_run(scenario: Scenario, trial: int,
                steps: int) -> tuple[EstimatorSession, TrialResult]:
    """A lockstep session fed run_trial's inputs and truth (as the node is)."""
    ref = run_trial(scenario, 'ram', 0, trial, steps)
    timebase = Timebase.from_dt(scenario.dt)
    _, rng = trial_streams(0, trial)
    session = EstimatorSession.create(scenario, make_strategy('ram'), rng, True, steps)
    session.plan_next()
    for k in range(1, steps + 1):
        for j, n in enumerate(((k - 1) * 2, (k - 1) * 2 + 1)):
            stamp = timebase.substep_end(n)
            session.add_odometry('leader', stamp, *ref.leader[k - 1, j])
            session.add_odometry('follower', stamp, *ref.commands[k - 1, j])
        stamp = timebase.measurement_stamp(k)
        session.add_truth(stamp, ref.truth[k - 1])
        session.add_measurement(k, stamp, ref.measurements[k - 1], scenario.sigma ** 2)
        session.advance()
    return session, ref


def test_the_session_watches_a_diverging_bearing_follower() -> None:
    """Bearing, deviation 0.9 |p_o|, trial 1: the first update, 0.11 m from the leader with a
    prior of 0.32 m, leaves NEES 785; the window mean NEES stays above the band and the
    session's watch is in error at step 44; the true follower later passes 7 cm from the
    leader (step 81) and the estimate runs off. The paper's disc, same trial: ok."""
    session, ref = session_run(Scenario.paper('bearing', r=0.9 * SQRT5), 1, 140)
    np.testing.assert_allclose(session.estimator.x, ref.estimate[-1], rtol=0, atol=1e-9)
    watch = session.watch
    assert watch.failed and watch.worst.step == 44, watch.worst
    assert watch.worst.reason.startswith('sustained inconsistency: window mean NEES 27.5 ')
    assert watch.counters['nees_samples'] == watch.counters['nis_samples'] == 140
    assert ref.nees[0] > 700 and np.hypot(*ref.truth[80, :2]) < 0.08
    paper, _ = session_run(Scenario.paper('bearing'), 1, 140)
    assert paper.watch.worst.level in (OK, WARN) and not paper.watch.failed


@pytest.mark.slow
def test_study_flags_an_inconsistent_strategy_and_the_report_withholds_it() -> None:
    """Bearing with a disc of 0.9 |p_o| (4 trials x 150 steps): RAM's NEES leaves the band, the
    summary flags it (ok false) and the report withholds every "vs RAM"; with
    allow_inconsistent it prints them marked. The paper's disc: nothing flagged."""
    from formopt_ros.cli.montecarlo import report_markdown
    config = StudyConfig('bearing', trials=4, steps=150, seed=0, strategies=('ram', 'periodic'),
                         scenario={'r': 0.9 * SQRT5})
    summary = summarize(run_study(config, jobs=1))
    flagged = summary['consistency']['flagged']
    assert not summary['ok'] and 'ram' in flagged
    assert summary['strategies']['ram']['nees_mean'] > 100
    assert 'outside the 95 % band' in flagged['ram']
    report = report_markdown(summary)
    row = next(line for line in report.splitlines() if line.startswith('| PERIODIC |'))
    assert row.count('| withheld |') == 2 and '%  |' not in row
    assert '- RAM: trial-mean NEES outside the 95 % band' in report
    allowed = report_markdown(summary, allow_inconsistent=True)
    row = next(line for line in allowed.splitlines() if line.startswith('| PERIODIC |'))
    assert row.count(' % (inconsistent) |') == 2
    paper = summarize(run_study(StudyConfig('bearing', trials=4, steps=150, seed=0,
                                            strategies=('ram', 'periodic')), jobs=1))
    assert paper['ok'] and paper['consistency']['flagged'] == {}
    assert '| withheld |' not in report_markdown(paper)


def test_a_flag_under_a_tight_speed_limit_names_the_margin() -> None:
    """Bearing behind an arc at -0.2 rad/s (the disc keeps pace from 1.3695 m/s), RQ, 3 trials
    x 200 steps: at 1.45 m/s the filter is flagged (mean NEES 17.4) and the reason gives the
    margin (0.0805 m/s) and the share of steps that fell back (32.0 %); at 1.9 m/s it is
    consistent and nothing is flagged."""
    from formopt_ros.core.scenario import LeaderPath

    def flagged(speed: float) -> dict[str, str]:
        config = StudyConfig('bearing', trials=3, steps=200, seed=0, strategies=('rq',),
                             scenario={'max_speed': speed,
                                       'leader': LeaderPath('arc', 1.0, -0.2)})
        return summarize(run_study(config, jobs=1))['consistency']['flagged']

    reason = flagged(1.45)['rq']
    assert 'mean NEES 17.39 above' in reason
    assert 'limit 1.45 m/s, 0.0805 m/s above the 1.369 m/s' in reason
    assert 'fell back on 32.0 % of its steps' in reason
    assert flagged(1.9) == {}


def test_domain_rules_refuse_with_the_field_and_the_reason() -> None:
    """The paper's settings pass; a bearing (or range-bearing) disc of 0.6 |p_o| and a 2 mm
    slot are refused, naming the field, the rule and the limit; a safety distance of 1.2 m
    lets a bearing disc of 0.9 |p_o| pass."""
    for kind in ('range', 'bearing', 'range-bearing'):
        check_domain(Scenario.paper(kind))
    check_deviation_domain(Scenario.paper('range', r=0.999 * SQRT5))
    check_deviation_domain(Scenario.paper('bearing', r=0.5 * SQRT5))
    for kind in ('bearing', 'range-bearing'):
        with pytest.raises(ValueError, match=r'^deviation_fraction 0\.6: .*measures bearings.*'
                                             r'at most 0\.505'):
            check_deviation_domain(Scenario.paper(kind, r=0.6 * SQRT5), 'deviation_fraction')
    with pytest.raises(ValueError, match=r'0\.22 \|p_o\|'):
        check_deviation_domain(Scenario.paper('bearing', r=0.9 * SQRT5,
                                              initial_covariance=(1e-4, 1e-4, 4e-4)))
    # a safety distance keeps every planned point as far out as a smaller disc would
    check_deviation_domain(Scenario.paper('bearing', r=0.9 * SQRT5, safety_distance=1.2))
    tiny = Scenario.paper('range', p_o=(-0.002, 0.0), r=0.0002)
    with pytest.raises(ValueError, match=r'^slot \[-0\.002, 0\] .*refuses as implausible.*'
                                         r'at least 0\.052'):
        check_input_domain(tiny, 'slot')
    sure = dict(initial_covariance=(1e-8, 1e-8, 4e-4))     # even a well-known start:
    with pytest.raises(ValueError, match=r"twice the leader's 1 m/s"):
        check_input_domain(Scenario.paper('range', p_o=(-0.002, 0.0), r=0.0002, **sure))
    check_input_domain(Scenario.paper('range', p_o=(-0.006, 0.0), r=0.0006, **sure))
    with pytest.raises(ValueError, match='yaw rate'):
        from formopt_ros.core.scenario import LeaderPath
        check_input_domain(Scenario.paper('range', leader=LeaderPath('arc', 1.0, 9.0),
                                          dt=5.0, kinematics='exact'))


def test_offline_replay_reports_the_watch(capsys: pytest.CaptureFixture) -> None:
    """replay --offline of the 20-step legacy bag: the re-estimate's watch saw 20 NIS and 20
    NEES samples, too few to judge (ok), and the command prints that verdict."""
    from pathlib import Path

    from formopt_ros.analysis.offline import offline
    from formopt_ros.analysis.recording import load_recording
    from formopt_ros.bag import read_bag
    from formopt_ros.cli.replay import main
    bag = Path(__file__).resolve().parents[1] / 'data' / \
        'legacy_0.1.0_lockstep_bearing_crm_seed2.mcap'
    result = offline(load_recording(read_bag(bag)), seed=2)
    assert result.consistent and result.consistency['worst']['level'] == OK
    assert result.consistency['counters']['nis_samples'] == 20
    assert result.as_dict()['consistency'] == result.consistency
    with pytest.raises(SystemExit) as stop:
        main([str(bag), '--offline', '--seed', '2'])
    assert stop.value.code == 0
    assert 'consistency of the re-estimate: ok\n' in capsys.readouterr().out


def test_montecarlo_command_refuses_the_domain_unless_told(
        tmp_path, capsys: pytest.CaptureFixture) -> None:
    """formopt-montecarlo on a diverging bearing disc: refused at the door (exit 2, naming
    --r-fraction and the largest fraction allowed); with --allow-inconsistent it runs, exit 0,
    a warning names RAM and RQ, report.md and summary.json flag them and print the
    percentages marked."""
    import json

    from formopt_ros.cli.montecarlo import main
    argv = ['--measurement', 'bearing', '--r-fraction', '0.9', '--trials', '2', '--steps',
            '100', '--strategies', 'ram,rq', '--jobs', '1', '--no-figures', '--out',
            str(tmp_path)]
    with pytest.raises(SystemExit) as refused:
        main(argv)
    assert refused.value.code == 2
    assert '--r-fraction 0.9' in capsys.readouterr().err
    assert main(argv + ['--allow-inconsistent']) == 0
    err = capsys.readouterr().err
    assert 'warning: bearing: RAM, RQ flagged inconsistent' in err
    summary = json.loads((tmp_path / 'bearing' / 'summary.json').read_text())
    assert summary['ok'] is False and set(summary['consistency']['flagged']) == {'ram', 'rq'}
    row = next(line for line in (tmp_path / 'bearing' / 'report.md').read_text().splitlines()
               if line.startswith('| RQ |'))
    assert row.count('% (inconsistent) |') == 2, row


def test_a_covariance_that_grows_is_no_steady_state() -> None:
    """Range behind an arc at 0.3 rad/s, r = 0.5 |p_o|, 3 m/s: greedy (RQ) holds the front of
    its disc, where the tangential direction stays unobserved, and its tr(W P W) grows (71 %
    over the last 100 of 300 steps against the 100 before): marked as no steady state, its
    filter consistent all the same. PERIODIC's design starts a cycle at the slot too and plays
    one 8x below RQ, steady; holding the slot (MTF) is steady."""
    from formopt_ros.core.scenario import LeaderPath
    config = StudyConfig('range', trials=4, steps=300, seed=0,
                         strategies=('mtf', 'rq', 'periodic'),
                         scenario={'max_speed': 3.0, 'r': 0.5 * math.hypot(1.0, 2.0),
                                   'leader': LeaderPath('arc', 1.0, 0.3)})
    summary = summarize(run_study(config, jobs=1))
    rows = summary['strategies']
    assert list(summary['growing']) == ['rq'] and '71 % higher' in summary['growing']['rq']
    assert summary['consistency']['flagged'] == {}
    assert rows['periodic']['steady_trace'] < rows['rq']['steady_trace'] / 8.0
    assert rows['periodic']['steady_growth'] == pytest.approx(0.0, abs=0.01)


def test_a_flag_from_the_start_says_so() -> None:
    """The paper's range study cut at 45 steps (50 trials): RAM is flagged (40 % of the steps
    out of the band), and the reason says that 16 of its 18 steps out of the band are among
    the first 30, the filter's start from the broad initial prior; MTF's (unobservable), out
    of the band after the start as well, does not."""
    config = StudyConfig('range', trials=50, steps=45, seed=0, strategies=('ram', 'mtf'))
    flagged = summarize(run_study(config, jobs=1))['consistency']['flagged']
    assert 'on 40.0 % of the steps' in flagged['ram']
    assert '16 of its 18 steps out of the band are among the first 30' in flagged['ram']
    assert 'first 30' not in flagged['mtf']        # out of the band after its start too


def test_a_trace_that_follows_the_path_is_steady() -> None:
    """Behind an S-curve of 100 steps the trace follows the path's phase: windows of 133 steps
    hold other phases (bearing RQ: +19 % between the last two), whole periods do not; a
    study's growth compares whole periods (within 3 % here, 3 trials x 400 steps)."""
    from formopt_ros.core.scenario import LeaderPath
    from formopt_ros.core.study import growth_window, steady_growth
    config = StudyConfig('bearing', trials=3, steps=400, seed=0, strategies=('rq',),
                         scenario={'leader': LeaderPath('s-curve', 1.0, amplitude=0.5)})
    result = run_study(config, jobs=1)
    assert growth_window(result.scenario, 133) == 100
    trace = result.records['rq'].weighted_trace
    assert steady_growth(trace, 133) > 0.15
    summary = summarize(result)
    assert abs(summary['strategies']['rq']['steady_growth']) < 0.03 and not summary['growing']
