"""Unit tests of formopt_ros.core.cost: validation, the cost tr(W P_post W) and the q-disc map."""
from __future__ import annotations

import math
from collections import Counter
from fractions import Fraction

import numpy as np
import pytest

from formopt_ros.core import METHODS, Problem, cost, solve, solver
from formopt_ros.core.checks import InvalidInput, as_covariance
from formopt_ros.core.formulas import point_from_q
from formopt_ros.core.strategies import STRATEGIES, PlanContext, Solution, make_solution
from formopt_ros.core.linalg import positive_definite_entries, positive_definite_exactly
from formopt_ros.core.model import BEARING, RANGE, ekf_update, predict_measurement

SEED = 4711
GOOD_P = np.array([[0.04, 0.01, 0.002], [0.01, 0.03, -0.001], [0.002, -0.001, 0.01]])
GOOD_P_O = np.array([-1.0, 2.0])


def random_problem(rng: np.random.Generator, kind: str) -> Problem:
    """A moderately conditioned random problem (condition number of P below ~1e3)."""
    A = rng.standard_normal((3, 3))
    P = (A @ A.T + 0.05 * np.eye(3)) * 10 ** rng.uniform(-4, 0)
    d_o = rng.uniform(0.5, 10.0)
    angle = rng.uniform(-math.pi, math.pi)
    p_o = d_o * np.array([math.cos(angle), math.sin(angle)])
    sigma = rng.uniform(0.01, 0.5) if kind == RANGE else rng.uniform(0.002, 0.1)
    return Problem(P, p_o, d_o * rng.uniform(0.01, 0.5), sigma, kind)


def points_in_disc(rng: np.random.Generator, problem: Problem, n: int) -> np.ndarray:
    """n points uniformly distributed in the feasible disc, plus its boundary, shape (n, 2)."""
    radius = problem.r * np.sqrt(rng.uniform(0, 1, n))
    radius[: n // 4] = problem.r
    angle = rng.uniform(-math.pi, math.pi, n)
    return problem.p_o + radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def bad_problem_cases() -> list[tuple[str, dict, str]]:
    """(label, keyword overrides, the field the refusal names) for bad inputs."""
    not_symmetric = GOOD_P.copy()
    not_symmetric[0, 1] += 1e-3
    # +0.9 above the diagonal and -0.9 below, between variances 1e4 and 1e-16: tiny next to
    # P's largest entry, but not rounding
    sign_flipped = np.array([[1e4, 0.0, 0.0], [0.0, 1e4, 9e-7], [0.0, -9e-7, 1e-16]])
    d_o = math.hypot(*GOOD_P_O)
    cases = [('P not symmetric', {'P': not_symmetric}, 'P'),
             ('P sign-flipped correlation', {'P': sign_flipped}, 'P'),
             ('P indefinite', {'P': np.diag([1.0, 1.0, -1e-3])}, 'P'),
             ('P singular', {'P': np.diag([1.0, 1.0, 0.0])}, 'P'),
             ('P indefinite below rounding',
              {'P': [[3.0, 1.7157497662356598, 0.0], [1.7157497662356598, 0.981265753445907, 0.0],
                     [0.0, 0.0, 1.0]]}, 'P'),
             ('P shape', {'P': np.eye(2)}, 'P'),
             ('P ragged', {'P': [[1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}, 'P'),
             ('P with None', {'P': [[1, 0, 0], [0, None, 0], [0, 0, 1]]}, 'P'),
             ('P masked', {'P': np.ma.masked_array(GOOD_P, mask=np.eye(3, dtype=bool))}, 'P'),
             ('P tiny', {'P': GOOD_P * 1e-300}, 'P'),
             ('P huge', {'P': GOOD_P * 1e300}, 'P'),
             ('p_o shape', {'p_o': np.array([1.0, 2.0, 3.0])}, 'p_o'),
             ('tiny p_o', {'p_o': GOOD_P_O * 1e-200, 'r': 0.1e-200}, 'p_o'),
             ('huge p_o', {'p_o': GOOD_P_O * 1e200, 'r': 0.1e200}, 'p_o'),
             ('r zero', {'r': 0.0}, 'r'),
             ('r negative', {'r': -0.1}, 'r'),
             ('r reaches leader', {'r': d_o}, 'r'),
             ('r just below |p_o|', {'r': 0.999999 * d_o}, 'r'),
             ('r below 1e-6 |p_o|', {'r': 0.9e-6 * d_o}, 'r'),
             ('r None', {'r': None}, 'r'),
             ('r bool', {'r': True}, 'r'),
             ('sigma list', {'sigma': [1.0]}, 'sigma'),
             ('sigma huge', {'sigma': 1e200}, 'sigma'),
             ('sigma tiny', {'sigma': 1e-200}, 'sigma'),
             ('sigma zero', {'sigma': 0.0}, 'sigma'),
             ('sigma negative', {'sigma': -0.01}, 'sigma'),
             ('measurement', {'measurement': 'lidar'}, 'measurement')]
    for bad in (math.nan, math.inf, -math.inf):
        for i, j in ((0, 0), (1, 2), (2, 2)):
            P = GOOD_P.copy()
            P[i, j] = P[j, i] = bad
            cases.append((f'P[{i},{j}]={bad}', {'P': P}, 'P'))
        for i in range(2):
            p_o = GOOD_P_O.copy()
            p_o[i] = bad
            cases.append((f'p_o[{i}]={bad}', {'p_o': p_o}, 'p_o'))
        cases.append((f'r={bad}', {'r': bad}, 'r'))
        cases.append((f'sigma={bad}', {'sigma': bad}, 'sigma'))
    return cases


@pytest.mark.parametrize('label, overrides, field', bad_problem_cases(),
                         ids=[case[0] for case in bad_problem_cases()])
@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_problem_rejects_bad_input(label: str, overrides: dict, field: str, kind: str) -> None:
    """Each bad input raises InvalidInput naming the field, from Problem and from solve()."""
    arguments = {'P': GOOD_P, 'p_o': GOOD_P_O, 'r': 0.3, 'sigma': 0.05, 'measurement': kind}
    arguments.update(overrides)
    with pytest.raises(InvalidInput) as refused:
        Problem(**arguments)
    assert refused.value.name == field
    measurement = arguments.pop('measurement')
    with pytest.raises(InvalidInput) as refused:
        solve(**arguments, measurement=measurement, method='rq')
    assert refused.value.name == field


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_problem_accepts_numbers_of_any_numeric_type(kind: str) -> None:
    """r and sigma as numpy scalars or 0-d arrays, P and p_o as lists, give the answer of
    plain floats bit for bit."""
    reference = solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=kind, method='rq')
    variants = [{'r': np.array(0.3), 'sigma': np.array(0.05)},
                {'r': np.float64(0.3), 'sigma': np.float64(0.05)},
                {'P': GOOD_P.tolist(), 'p_o': tuple(GOOD_P_O)}]
    for variant in variants:
        arguments = {'P': GOOD_P, 'p_o': GOOD_P_O, 'r': 0.3, 'sigma': 0.05, **variant}
        solution = solve(**arguments, measurement=kind, method='rq')
        np.testing.assert_array_equal(solution.p, reference.p)
        assert solution.cost == reference.cost


def test_rounding_level_asymmetry_is_averaged_per_pair() -> None:
    """P[i, j] and P[j, i] differing by up to 1e-6 of the pair's scale are averaged (the
    problem is that of the averaged P), whatever the other entries; 1e-5 is refused. The
    covariances of an EKF that never symmetrises (a reviewer's: F P F' + Q, then P - K S K',
    20 steps, 200 seeded runs) are all accepted, as their averages."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        P = (q * 10.0 ** rng.uniform([-3, -3, -8], [3, 3, -2])) @ q.T
        P = 0.5 * (P + P.T)
        for _ in range(20):
            F = np.eye(3)
            F[:2, 2] = 10.0 * rng.normal(size=2)
            P = F @ P @ F.T + np.diag([1e-3, 1e-3, 1e-8])
            H = rng.normal(size=(1, 3)) * np.array([1.0, 1.0, 10.0 ** rng.uniform(-2, 3)])
            S = H @ P @ H.T + 1e-4
            K = P @ H.T / S
            P = P - K @ S @ K.T
        P = P / np.abs(P).max()         # inside the admissible variances
        np.testing.assert_array_equal(as_covariance('P', P), as_covariance('P', 0.5 * (P + P.T)))
    P = np.array([[1e4, 0.0, 0.0], [0.0, 1e4, 9e-7], [0.0, 9e-7, 1e-16]])
    for tolerated, factor in ((True, 1.0 + 5e-7), (False, 1.0 + 1e-5)):
        skewed = P.copy()
        skewed[2, 1] *= factor
        if not tolerated:
            with pytest.raises(InvalidInput, match='^P '):
                Problem(skewed, GOOD_P_O, 0.3, 0.05, BEARING)
            continue
        averaged = 0.5 * (skewed + skewed.T)
        assert Problem(skewed, GOOD_P_O, 0.3, 0.05, BEARING).entries == Problem(
            averaged, GOOD_P_O, 0.3, 0.05, BEARING).entries


def test_positive_definite_exactly_agrees_with_exact_minors() -> None:
    """On 3000 symmetric matrices at the edge of definiteness (rank-2 Gram matrices plus a
    third eigenvalue of +-1e-20..1e-8 of the scale, scales 1e-80..1e20, so that half are
    indefinite in exact arithmetic and floats cannot tell), positive_definite_exactly equals
    Sylvester's criterion in Fractions; the float LDL' alone disagreed on some (it is why)."""
    rng = np.random.default_rng(5)
    disagreements_of_floats = 0
    for _ in range(3000):
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        scale = 10.0 ** rng.uniform(-80.0, 20.0)
        smallest = rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-20.0, -8.0)
        A = (q * np.array([1.0, 10.0 ** rng.uniform(-6.0, 0.0), smallest])) @ q.T * scale
        entries = (A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2])
        e00, e01, e02, e11, e12, e22 = map(Fraction, entries)
        exact = bool(e00 > 0 and e00 * e11 - e01 * e01 > 0 and e00 * (e11 * e22 - e12 * e12)
                     - e01 * (e01 * e22 - e12 * e02) + e02 * (e01 * e12 - e11 * e02) > 0)
        assert positive_definite_exactly(entries) == exact, entries
        disagreements_of_floats += positive_definite_entries(entries) != exact
    assert disagreements_of_floats > 0


def edge_inputs(rng: np.random.Generator) -> list[dict]:
    """Inputs at the checks' edges: valid problems, and each one broken in one
    place (NaN, infinity, an asymmetry within and beyond the averaging tolerance, variances
    and sigma at and beyond their bounds, r at its bounds, indefinite P, overflowing sums) or
    given in another type (integers, float32, big-endian, lists, numpy scalars)."""
    cases = []
    low, high = cost.VARIANCE_RANGE
    for _ in range(60):
        problem = random_problem(rng, RANGE)
        base = {'P': problem.P, 'p_o': problem.p_o, 'r': float(problem.r),
                'sigma': float(problem.sigma), 'measurement': str(rng.choice([RANGE, BEARING]))}
        cases.append(base)
        P = problem.P
        d_o = math.hypot(*problem.p_o)
        i, j = sorted(rng.choice(3, 2, replace=False))
        for value in (math.nan, math.inf, -math.inf, 1e308, -1e308):
            broken = P.copy()
            broken[i, j] = value
            cases.append({**base, 'P': broken})
            broken = broken.copy()
            broken[j, i] = value
            cases.append({**base, 'P': broken})
            cases.append({**base, 'p_o': np.array([value, base['p_o'][1]])})
            cases.append({**base, 'r': value})
            cases.append({**base, 'sigma': value})
        for factor in (1e-12, 1e-8):                 # within and beyond 1e-9 relative
            broken = P.copy()
            broken[i, j] += factor * np.abs(P).max()
            cases.append({**base, 'P': broken})
        for k in range(3):
            for value in (low, high, low * 0.5, high * 2.0, 0.0, -P[k, k]):
                broken = P.copy()
                broken[k, k] = value
                cases.append({**base, 'P': broken})
        for value in (*cost.SIGMA_RANGE, cost.SIGMA_RANGE[0] * 0.99, cost.SIGMA_RANGE[1] * 1.01):
            cases.append({**base, 'sigma': value})
        for value in (cost.MIN_DEVIATION * d_o, cost.MAX_DEVIATION * d_o,
                      cost.MIN_DEVIATION * d_o * 0.99, cost.MAX_DEVIATION * d_o * 1.001, 0.0):
            cases.append({**base, 'r': value})
        for distance in (*cost.SLOT_DISTANCE_RANGE, cost.SLOT_DISTANCE_RANGE[0] * 0.99,
                         cost.SLOT_DISTANCE_RANGE[1] * 1.01, 1e-160, 1e160):
            scale = distance / d_o                  # the disc scaled with its slot
            cases.append({**base, 'p_o': base['p_o'] * scale, 'r': base['r'] * scale})
        eigenvalues, vectors = np.linalg.eigh(P)
        cases.append({**base, 'P': (vectors * eigenvalues * [-1, 1, 1]) @ vectors.T})
        cases.append({**base, 'P': P.astype(np.float32), 'p_o': base['p_o'].astype('>f8')})
        cases.append({**base, 'P': P.tolist(), 'p_o': tuple(base['p_o']),
                      'r': np.float64(base['r']), 'sigma': np.float32(base['sigma'])})
        cases.append({**base, 'P': np.round(P * 1e6).astype(int), 'r': int(base['r'] + 1)})
        cases.append({**base, 'measurement': 'lidar'})
    return cases


def test_batch_checks_each_problem_as_problem_does() -> None:
    """check_batch (ProblemBatch's validation) on batches of three valid problems and one case
    of edge_inputs at index 2: it accepts what check_problem accepts, with the same
    numbers (an averaged P included), and refuses the rest naming the field of problem 2."""
    outcomes = Counter()
    for case in edge_inputs(np.random.default_rng(SEED + 8)):
        kind = case['measurement']
        columns = [np.array([GOOD_P, GOOD_P, np.asarray(case['P'], dtype=float), GOOD_P]),
                   np.array([GOOD_P_O, GOOD_P_O, np.asarray(case['p_o'], dtype=float),
                             GOOD_P_O]),
                   np.array([0.3, 0.3, float(case['r']), 0.3]),
                   np.array([0.05, 0.05, float(case['sigma']), 0.05])]
        try:
            expected = cost.check_problem(*(column[2] for column in columns), kind)
        except InvalidInput as error:
            with pytest.raises(InvalidInput) as refused:
                cost.check_batch(*columns, kind)
            assert refused.value.name in (error.name, f'{error.name} of problem 2')
            outcomes['refused'] += 1
            continue
        P, p_o, r, sigma = cost.check_batch(*columns, kind)
        np.testing.assert_array_equal(P[2], expected[0])
        np.testing.assert_array_equal(p_o[2], expected[1])
        assert (r[2], sigma[2]) == expected[2:4]
        np.testing.assert_array_equal(P[[0, 1, 3]], columns[0][[0, 1, 3]])
        outcomes['accepted'] += 1
    assert outcomes['accepted'] > 300 and outcomes['refused'] > 2000, outcomes


@pytest.mark.parametrize('label, arguments, field', [
    ('single P', (GOOD_P, [GOOD_P_O], [0.3], [0.05]), 'P'),
    ('lengths', ([GOOD_P] * 3, [GOOD_P_O] * 2, [0.3] * 2, [0.05] * 2), 'P, p_o, r and sigma'),
    ('complex', ([GOOD_P], [GOOD_P_O], [0.3 + 1j], [0.05]), 'r'),
    ('None', ([GOOD_P], [GOOD_P_O], [None], [0.05]), 'r'),
    ('masked', ([GOOD_P], np.ma.masked_array([GOOD_P_O], mask=[[False, True]]), [0.3],
                [0.05]), 'p_o'),
    ('generator', ((P for P in [GOOD_P]), [GOOD_P_O], [0.3], [0.05]), 'P'),
    ('sigma zero', ([GOOD_P], [GOOD_P_O], [0.3], [0.0]), 'sigma of problem 0'),
    ('measurement', ([GOOD_P], [GOOD_P_O], [0.3], [0.05], 'lidar'), 'measurement')])
def test_problem_batch_refuses_bad_arrays(label: str, arguments: tuple, field: str) -> None:
    """A ProblemBatch of malformed arrays is refused naming the array; an empty batch and one
    built with validate=False (the engine's) are accepted."""
    with pytest.raises(InvalidInput) as refused:
        cost.ProblemBatch(*arguments[:4], *(arguments[4:] or (BEARING,)))
    assert refused.value.name == field
    assert len(cost.ProblemBatch(np.zeros((0, 3, 3)), np.zeros((0, 2)), [], [], RANGE)) == 0
    for r, sigma, name in ((True, 0.05, 'r'), ([0.3, 0.3], 0.05, 'r'),
                           (0.3, 0.0, 'sigma of problem 0')):
        with pytest.raises(InvalidInput) as refused:
            cost.ProblemBatch.shared(np.array([GOOD_P, GOOD_P]), GOOD_P_O, r, sigma, RANGE)
        assert refused.value.name == name
    unchecked = cost.ProblemBatch(-np.array([GOOD_P]), [GOOD_P_O], [5.0], [0.0], RANGE, False)
    assert unchecked.P[0, 0, 0] == -GOOD_P[0, 0]


def test_solve_shares_only_stateless_strategies() -> None:
    """solve() reuses one object per stateless method (PERIODIC keeps a cycle's state, so it
    gets a new one) and answers the same problem alike on every call."""
    assert solver._SHARED and set(solver._SHARED) == {
        name for name, cls in STRATEGIES.items() if cls.stateless}
    assert 'periodic' not in solver._SHARED
    for method in METHODS:
        answers = [solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=BEARING, method=method,
                         rng=np.random.default_rng(1)).p for _ in range(2)]
        np.testing.assert_array_equal(*answers)


def test_timed_plan_never_changes_a_record_it_returned_before() -> None:
    """timed_plan stamps the wall time on a new record in place, but a strategy that returns
    one record twice gets a timed copy the second time: the first answer keeps its time."""
    problem = Problem(GOOD_P, GOOD_P_O, 0.3, 0.05, RANGE)
    record = make_solution(problem, problem.p_o, 'mtf')

    class Repeating(STRATEGIES['mtf']):
        """Returns the same record on every call."""

        def plan(self, problem: Problem, context: PlanContext) -> Solution:
            return record
    first = solver.timed_plan(Repeating(), problem, solver.DEFAULT_CONTEXT)
    assert first is record and first.solve_time_s > 0.0
    first_time = first.solve_time_s
    second = solver.timed_plan(Repeating(), problem, solver.DEFAULT_CONTEXT)
    assert second is not record and record.solve_time_s == first_time
    assert second.solve_time_s > 0.0 and second.p is record.p


def test_good_problem_is_accepted() -> None:
    """The reference inputs of the validation tests are themselves valid (tests can fail)."""
    for kind in (RANGE, BEARING):
        problem = Problem(GOOD_P, GOOD_P_O, 0.3, 0.05, kind)
        assert problem.d_o == pytest.approx(math.sqrt(5.0), rel=1e-15)  # rounding only


def test_solve_takes_r_at_the_bound_from_either_norm_and_refuses_a_foreign_region() -> None:
    """r = 0.999 |p_o| is accepted whether |p_o| came from numpy's norm or math.hypot (they
    differ by an ulp on some slots); a context.region built for another slot or r is refused
    naming 'region' (its answer would lie outside the problem's disc)."""
    from formopt_ros.core.reach import Region
    rng = np.random.default_rng(4)
    for _ in range(200):
        p_o = rng.uniform(-10.0, 10.0, 2)
        for d_o in (float(np.linalg.norm(p_o)), math.hypot(*p_o)):
            solve(GOOD_P, p_o, 0.999 * d_o, 0.05, measurement=RANGE, method='mtf')
    foreign = (Region((-1.5, 2.5), 0.22, (-1.4, 2.5), 0.15), Region((-1.0, 2.0), 0.5))
    for region in foreign:
        with pytest.raises(InvalidInput) as error:
            solve(GOOD_P, np.array([-1.0, 2.0]), 0.22, 0.05, measurement=RANGE, method='rq',
                  context=PlanContext(region=region))
        assert error.value.name == 'region'


def test_solve_rejects_unknown_method_and_option() -> None:
    """solve() names the unknown method or option in its ValueError."""
    with pytest.raises(ValueError, match=r"^method must be one of .*'simplex'"):
        solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=RANGE, method='simplex')
    with pytest.raises(ValueError, match=r"^method must be one of .*got \['rq'\]"):
        solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=RANGE, method=['rq'])  # type: ignore
    with pytest.raises(ValueError, match=r"^method 'gbs' accepts options .*unknown \['spacing'\]"):
        solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=RANGE, method='gbs', spacing=0.1)
    with pytest.raises(ValueError, match=r"^method 'rq' accepts options .*unknown \['cell'\]"):
        solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=BEARING, method='rq', cell=0.1)
    with pytest.raises(ValueError, match=r'^rng must be a numpy.random.Generator .*got 3'):
        solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=BEARING, method='crm',
              rng=3)  # type: ignore[arg-type]
    for method, option, value in (('mme', 'period', math.inf), ('mme', 'period', 2.5),
                                  ('periodic', 'horizon', math.inf), ('gbs', 'cell', math.nan),
                                  ('ram', 'fallback', 1), ('gbs', 'cell', True)):
        with pytest.raises(InvalidInput) as refused:
            solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=RANGE, method=method,
                  **{option: value})
        assert refused.value.name == f'{method} option {option}'
    for method in ('mme', 'periodic', 'rq'):
        with pytest.raises(ValueError, match=r"^context must be a PlanContext, got 'x'"):
            solve(GOOD_P, GOOD_P_O, 0.3, 0.05, measurement=RANGE, method=method,
                  context='x')  # type: ignore[arg-type]


def brute_force_cost(problem: Problem, point: np.ndarray, phi: float) -> float:
    """tr(W P_post W) with P_post from model.ekf_update at x = [point, phi]."""
    x = np.array([point[0], point[1], phi])
    z = predict_measurement(problem.measurement, x)
    _, P_post, _, _ = ekf_update(x, problem.P, z, problem.measurement, problem.sigma ** 2)
    d_o = math.hypot(*problem.p_o)
    W = np.diag([1.0, 1.0, d_o])
    return float(np.trace(W @ P_post @ W))


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_cost_equals_brute_force_ekf(kind: str) -> None:
    """Problem.cost equals tr(W P_post W) of the EKF update, 60 problems x 50 points per kind."""
    rng = np.random.default_rng(SEED)
    for _ in range(60):
        problem = random_problem(rng, kind)
        points = points_in_disc(rng, problem, 50)
        costs = problem.cost(points)
        assert costs.shape == (50,)
        for point, value in zip(points, costs):
            expected = brute_force_cost(problem, point, rng.uniform(-math.pi, math.pi))
            # 1e-12 relative (the heading phi does not enter h, so any phi is fine).
            assert value == pytest.approx(expected, rel=1e-12, abs=0)
        # The single-point form returns a float equal to the vectorised one (1e-14 relative:
        # BLAS may sum a (1, k) and an (n, k) product in a different order).
        single = problem.cost(points[0])
        assert isinstance(single, float)
        assert single == pytest.approx(float(costs[0]), rel=1e-14)
        # 1e-12 relative: the cost at the slot is tr(W P W) minus the slot's gain.
        assert problem.base_cost == pytest.approx(
            float(np.dot([1.0, 1.0, problem.d_o ** 2], np.diag(problem.P))), rel=1e-12)


def test_cost_depends_on_position() -> None:
    """The brute-force comparison is not vacuous: costs differ across the disc."""
    rng = np.random.default_rng(SEED + 1)
    for kind in (RANGE, BEARING):
        problem = random_problem(rng, kind)
        costs = problem.cost(points_in_disc(rng, problem, 200))
        assert np.ptp(costs) > 1e-9 * np.max(costs)
        assert np.all(costs < problem.base_cost)     # a measurement always helps


@pytest.mark.filterwarnings('error')
@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_gain_at_is_minus_infinity_where_the_formula_breaks_down_for_every_type(kind: str) -> None:
    """At the origin the gain formula divides by zero: gain_at gives -inf for Python floats,
    numpy scalars of any precision, ints, 0-d and n-d arrays, without a warning; elsewhere a
    numpy scalar gives the Python float's number exactly."""
    problem = random_problem(np.random.default_rng(SEED + 2), kind)
    for zero in (0.0, np.float64(0.0), np.float32(0.0), 0, np.array(0.0)):
        assert problem.gain_at(zero, zero) == -math.inf
    # a non-finite coordinate, or one whose squares overflow (a reviewer's: nan for Python
    # floats): -inf, or the finite limit the formula still reaches (bearing far away: q = 0)
    for point in ((1e200, 1e200), (1e155, 1e155), (math.nan, 1.0), (math.inf, 1.0)):
        gain = problem.gain_at(*point)
        assert gain == -math.inf or math.isfinite(gain) and point[0] > 1e100, point
        assert problem.gain_at(*map(np.float64, point)) == gain
    gains = problem.gain_at(np.array([0.0, *problem.p_o[:1]]), np.array([0.0, problem.p_o[1]]))
    assert gains[0] == -math.inf and gains[1] == problem.gain_at(*problem.slot)
    assert problem.gain(np.zeros(2)).tolist() == [-math.inf]
    x, y = problem.slot
    assert problem.gain_at(np.float64(x), np.float64(y)) == problem.gain_at(x, y)
    assert type(problem.gain_at(x, y)) is float


def test_q_disc_maps_boundary_circle_and_inverts() -> None:
    """p -> q = (-y, x)/|p|^2 maps the disc boundary onto q_disc's circle; point_from_q inverts."""
    rng = np.random.default_rng(SEED + 2)
    for _ in range(100):
        problem = random_problem(rng, BEARING)
        centre, rho = problem.q_disc()
        angle = rng.uniform(-math.pi, math.pi, 500)
        boundary = problem.p_o + problem.r * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        q = np.stack([-boundary[:, 1], boundary[:, 0]], axis=1) / np.sum(
            boundary ** 2, axis=1)[:, None]
        # 1e-12 relative to rho: the image of the boundary circle is the circle (centre, rho).
        np.testing.assert_allclose(np.hypot(*(q - centre).T), rho, rtol=1e-12)
        # Interior points map strictly inside the image disc, exterior points outside.
        inner = problem.p_o + 0.9 * (boundary - problem.p_o)
        outer = problem.p_o + 1.1 * (boundary - problem.p_o)
        for pts, inside in ((inner, True), (outer, False)):
            qq = np.stack([-pts[:, 1], pts[:, 0]], axis=1) / np.sum(pts ** 2, axis=1)[:, None]
            assert np.all((np.hypot(*(qq - centre).T) < rho) == inside)
        # 1e-12 relative: point_from_q is the inverse map (also on the whole array at once).
        np.testing.assert_allclose(point_from_q(q), boundary, rtol=1e-12)
        np.testing.assert_allclose(point_from_q(q[0]), boundary[0], rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_every_method_solves_the_whole_admissible_scale(kind: str) -> None:
    """Across VARIANCE_RANGE (variances log-uniform over 125 decades, correlations up to 0.9),
    sigma in [1e-6, 1] and, for a third of the problems, over all of SIGMA_RANGE, and r at
    0.3 m, at MIN_DEVIATION and at MAX_DEVIATION of |p_o|: every method returns a feasible
    finite point, without an exception (a large sigma with P = 1e-100 I once divided by zero
    in the certificate); RQ's answers carry a proof, the enumeration of all critical points, or
    'none' with the reason; RAM's are proved or visibly RQ's (seeded: 150 problems)."""
    import warnings

    from formopt_ros.core.cost import MAX_DEVIATION, MIN_DEVIATION, SIGMA_RANGE, VARIANCE_RANGE
    from formopt_ros.core.solver import solve
    from formopt_ros.core.strategies.certificate import CRITICAL_POINTS, PROVED
    rng = np.random.default_rng(11)
    low, high = np.log10(VARIANCE_RANGE)
    d_o = math.hypot(*GOOD_P_O)
    solved = 0
    while solved < 150:
        d = 10.0 ** rng.uniform(low, high, 3)
        c = rng.uniform(-0.9, 0.9, 3)
        correlation = np.array([[1, c[0], c[1]], [c[0], 1, c[2]], [c[1], c[2], 1]])
        if np.linalg.eigvalsh(correlation).min() <= 1e-3:
            continue
        P = np.sqrt(d)[:, None] * correlation * np.sqrt(d)[None, :]
        sigma = 10.0 ** rng.uniform(-6, 0) if solved % 3 else 10.0 ** rng.uniform(
            *np.log10(SIGMA_RANGE))
        r = (0.3, MIN_DEVIATION * d_o, MAX_DEVIATION * d_o)[solved % 5 % 3]
        for method in ('ram', 'rq', 'gbs', 'mtf', 'periodic'):
            with warnings.catch_warnings():
                warnings.simplefilter('ignore', RuntimeWarning)
                solution = solve(P, GOOD_P_O, r, sigma, measurement=kind, method=method)
            label = (method, d, sigma, r)
            assert np.all(np.isfinite(solution.p)) and math.isfinite(solution.cost), label
            assert np.hypot(*(solution.p - GOOD_P_O)) <= r * (1 + 1e-9), label
            if method in ('ram', 'rq'):
                assert solution.certificate in (*PROVED, CRITICAL_POINTS) or (
                    solution.details.get('reason') and (method == 'rq' or solution.fallback)
                ), (label, solution.certificate, solution.details)
        solved += 1


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_extremes_of_the_admissible_range_solve_without_exception(kind: str) -> None:
    """The corners of the admissible range: P = 1e-100 I with the largest sigma (the
    certificate's scale underflowed to 0 with sigma = 1e100: it divided by zero) and P = 1e25 I
    with the smallest, at the nearest and farthest slot: every method returns a feasible finite
    point."""
    from formopt_ros.core.cost import SIGMA_RANGE, SLOT_DISTANCE_RANGE
    from formopt_ros.core.solver import METHODS, solve
    extremes = ((np.eye(3) * 1e-100, SIGMA_RANGE[1]), (np.eye(3) * 1e25, SIGMA_RANGE[0]))
    corners = [(P, sigma, d) for P, sigma in extremes for d in SLOT_DISTANCE_RANGE]
    for P, sigma, d in corners:
        p_o, r = GOOD_P_O / math.hypot(*GOOD_P_O) * d, 0.3 * d
        for method in METHODS:
            solution = solve(P, p_o, r, sigma, measurement=kind, method=method,
                             rng=np.random.default_rng(0))
            label = (method, P[0, 0], sigma, d)
            assert math.isfinite(solution.cost) and np.all(np.isfinite(solution.p)), label
            assert np.hypot(*(solution.p - p_o)) <= r * (1 + 1e-9), label
