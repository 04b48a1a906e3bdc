"""Relative kinematics, range/bearing measurement models and the EKF of the paper (eqs. 8-19).

Frames and units
----------------
The state ``x = [x, y, phi]`` is the follower's pose in the leader's body frame {L}: position in
metres, heading in radians (follower x-axis relative to leader x-axis), wrapped to [-pi, pi).
Velocities are body-frame forward speed (m/s) and yaw rate (rad/s).

The paper assumes omega_L = 0. We keep the leader's yaw rate in the model so that a turning
leader can be simulated; with ``omega_l = 0`` every formula reduces to the printed eqs. (9)-(12).
Derivation of the general case: p = C_L^T (p_F - p_L) gives
``p_dot = -omega_L J p + C(phi) e1 v_F - e1 v_L`` with ``J = [[0, -1], [1, 0]]``, i.e.
``x_dot = omega_L y + cos(phi) v_F - v_L``, ``y_dot = -omega_L x + sin(phi) v_F``,
``phi_dot = omega_F - omega_L``.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

RANGE = 'range'
BEARING = 'bearing'
MEASUREMENT_KINDS = (RANGE, BEARING)


def wrap_angle(angle: Any) -> Any:
    """Wrap an angle (rad) to [-pi, pi); floats or arrays (the same arithmetic)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


#: The last few array arguments (as bytes) and results of each one-argument function given to
#: elementwise(): one step of the batched engine takes cos and sin of the same headings
#: several times. Bits in, the same bits out, so the memo changes no number.
_RECENT: dict[Callable[..., float], dict[bytes, np.ndarray]] = {}
_RECENT_SIZE = 4


def elementwise(function: Callable[..., float], *args: Any) -> Any:
    """``function`` (a scalar libm function such as math.atan2) on floats, or element by element
    on arrays: numpy's vectorised atan2, hypot, ... may differ from libm in the last bit, and the
    batched engine must reproduce the per-trial arithmetic exactly."""
    arrays = [a for a in args if isinstance(a, np.ndarray)]
    if not arrays:
        return function(*args)
    recent = _RECENT.setdefault(function, {}) if len(args) == 1 else None
    if recent is not None:
        key = args[0].tobytes() + repr(args[0].shape).encode()
        hit = recent.get(key)
        if hit is not None:
            return hit.copy()
    shape = arrays[0].shape
    if any(a.shape != shape for a in arrays[1:]):
        args = tuple(np.broadcast_arrays(*args))
        shape = args[0].shape
    columns = [a.ravel().tolist() if isinstance(a, np.ndarray) else [a] * math.prod(shape)
               for a in args]
    out = np.fromiter(map(function, *columns), dtype=float,
                      count=math.prod(shape)).reshape(shape)
    if recent is not None:
        if len(recent) >= _RECENT_SIZE:
            del recent[next(iter(recent))]
        recent[key] = out.copy()
    return out


def _components(x: np.ndarray) -> tuple[Any, Any, Any]:
    """x[..., 0], x[..., 1], x[..., 2]: Python floats for one pose (3,), arrays for (T, 3)."""
    if x.ndim == 1:
        px, py, phi = x.tolist()
        return px, py, phi
    return x[..., 0], x[..., 1], x[..., 2]


def stack_vector(*components: Any) -> np.ndarray:
    """Components (floats or arrays of one shape) as a vector (n,) or a batch (..., n)."""
    arrays = [c for c in components if isinstance(c, np.ndarray)]
    if not arrays:
        return np.array(components, dtype=float)
    out = np.empty(arrays[0].shape + (len(components),))
    for i, c in enumerate(components):
        out[..., i] = c
    return out


def propagate_state(x: np.ndarray, v_f: Any, omega_f: Any, dt: float,
                    v_l: float, omega_l: float = 0.0) -> np.ndarray:
    """Euler step of the relative kinematics, paper eqs. (9)/(10).

    Args:
        x: pose [x, y, phi] of the follower in {L} (m, m, rad), shape (3,) or (T, 3).
        v_f, omega_f: follower forward speed (m/s) and yaw rate (rad/s) during the step
            (floats, or arrays (T,) for a batch of poses).
        dt: step length (s).
        v_l, omega_l: leader forward speed (m/s) and yaw rate (rad/s).

    Returns:
        The pose after ``dt``, shape of x, heading wrapped.
    """
    px, py, phi = _components(x)
    return _moved(px, py, phi, elementwise(math.cos, phi), elementwise(math.sin, phi), v_f,
                  omega_f, dt, v_l, omega_l)


def _moved(px: Any, py: Any, phi: Any, c: Any, s: Any, v_f: Any, omega_f: Any, dt: float,
           v_l: float, omega_l: float) -> np.ndarray:
    """The pose after eq. (9) (heading wrapped), given cos and sin of the heading phi."""
    return stack_vector(px + (omega_l * py + c * v_f - v_l) * dt,
                        py + (-omega_l * px + s * v_f) * dt,
                        wrap_angle(phi + (omega_f - omega_l) * dt))


def integrate_unicycle(pose: tuple[float, float, float], v: float, omega: float,
                       dt: float) -> tuple[float, float, float]:
    """Dead reckoning of a planar robot in a fixed frame (odometry pose), one Euler step.

    Args:
        pose: (x m, y m, yaw rad) in the fixed frame.
        v, omega: forward speed (m/s) and yaw rate (rad/s) during the step.
        dt: step length, s.

    Returns:
        The pose after ``dt`` (yaw not wrapped: odometry yaw is continuous).
    """
    x, y, yaw = pose
    return x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt, yaw + omega * dt


def _transition_terms(phi: Any, v_f: Any, dt: float, omega_l: float, sigma_v: float,
                      sigma_omega: float) -> tuple[Any, ...]:
    """Entries of eqs. (11)-(12) at heading phi (a float, or an array for a batch):
    Phi = [[1, a, b], [-a, 1, e], [0, 0, 1]] and G Q G' = qv [c, s, 0][c, s, 0]' + qw e3 e3';
    returns (a, b, e, c, s, qv, qw)."""
    c, s = elementwise(math.cos, phi), elementwise(math.sin, phi)
    return omega_l * dt, -s * v_f * dt, c * v_f * dt, c, s, (sigma_v * dt) ** 2, \
        (sigma_omega * dt) ** 2


def propagate(x: np.ndarray, P: np.ndarray, v_f: Any, omega_f: Any, dt: float,
              v_l: float, omega_l: float, sigma_v: float,
              sigma_omega: float) -> tuple[np.ndarray, np.ndarray]:
    """EKF propagation with measured follower velocities, paper eqs. (10)-(12).

    Args:
        x: estimated pose [x, y, phi] in {L}, shape (3,) or (T, 3).
        P: its covariance, shape (3, 3) or (T, 3, 3), units m^2 / m rad / rad^2.
        v_f, omega_f: odometry (measured) follower velocities, m/s and rad/s (floats, or
            arrays (T,)).
        dt: step length, s.
        v_l, omega_l: leader velocities (known), m/s and rad/s.
        sigma_v, sigma_omega: odometry noise standard deviations, m/s and rad/s.

    Returns:
        (x, P) after the step; P_next = Phi P Phi' + G Q G' written out (symmetric by
        construction; a test checks it against :func:`transition_matrices`).
    """
    px, py, phi = _components(x)
    a, b, e, c, s, qv, qw = _transition_terms(phi, v_f, dt, omega_l, sigma_v, sigma_omega)
    if P.ndim == 2:
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = P.tolist()
    else:
        p00, p01, p02, p11, p12, p22 = (P[..., 0, 0], P[..., 0, 1], P[..., 0, 2],
                                        P[..., 1, 1], P[..., 1, 2], P[..., 2, 2])
    # rows of Phi P
    r00, r01, r02 = p00 + a * p01 + b * p02, p01 + a * p11 + b * p12, p02 + a * p12 + b * p22
    r10, r11, r12 = -a * p00 + p01 + e * p02, -a * p01 + p11 + e * p12, -a * p02 + p12 + e * p22
    n00 = r00 + a * r01 + b * r02 + qv * c * c
    n01 = -a * r00 + r01 + e * r02 + qv * c * s
    n11 = -a * r10 + r11 + e * r12 + qv * s * s
    n02, n12, n22 = r02, r12, p22 + qw
    return _moved(px, py, phi, c, s, v_f, omega_f, dt, v_l, omega_l), symmetric3(
        (n00, n01, n02, n11, n12, n22))


def transition_matrices(x: np.ndarray, v_f: float, dt: float, omega_l: float, sigma_v: float,
                        sigma_omega: float) -> tuple[np.ndarray, np.ndarray]:
    """The matrices of one propagation sub-step, eqs. (11)-(12): (Phi, G Q G'), each (3, 3).

    :func:`propagate` applies them written out (P_next = Phi P Phi' + G Q G'); multi-step
    planners compose them. Args as in :func:`propagate` (Phi does not depend on omega_f or v_l).
    """
    a, b, e, c, s, qv, qw = _transition_terms(float(x[2]), v_f, dt, omega_l, sigma_v,
                                              sigma_omega)
    Phi = np.array([[1.0, a, b], [-a, 1.0, e], [0.0, 0.0, 1.0]])
    u = np.array([c, s, 0.0])
    GQG = qv * np.outer(u, u)
    GQG[2, 2] += qw
    return Phi, GQG


def symmetric3(entries: tuple[Any, Any, Any, Any, Any, Any]) -> np.ndarray:
    """The symmetric matrix (3, 3), or batch (..., 3, 3), with six distinct entries
    (00, 01, 02, 11, 12, 22) given as floats or arrays of one shape."""
    a00, a01, a02, a11, a12, a22 = entries
    arrays = [v for v in entries if isinstance(v, np.ndarray)]
    if not arrays:
        return np.array([[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]], dtype=float)
    out = np.empty(np.broadcast_shapes(*(a.shape for a in arrays)) + (3, 3))
    for (i, j), value in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), entries):
        out[..., i, j] = value
        out[..., j, i] = value
    return out


def predict_measurement(kind: str, x: np.ndarray) -> Any:
    """Noise-free range (m, eq. 15) or bearing (rad, eq. 17, wrapped) at pose x (3,) or
    poses (T, 3) in {L}: a float, or an array (T,)."""
    px, py, phi = _components(x)
    if kind == RANGE:
        return elementwise(math.hypot, px, py)
    bearing = wrap_angle(elementwise(math.atan2, py, px) - phi + math.pi)
    return float(bearing) if x.ndim == 1 else bearing


def measurement_jacobian(kind: str, x: np.ndarray) -> np.ndarray:
    """Jacobian of the measurement w.r.t. [x, y, phi], eqs. (16) and (18), shape of x."""
    px, py, _ = _components(x)
    d2 = px * px + py * py
    if kind == RANGE:
        d = elementwise(math.sqrt, d2)
        return stack_vector(px / d, py / d, 0.0 * d)
    return stack_vector(-py / d2, px / d2, -1.0 + 0.0 * d2)


def ekf_update(x: np.ndarray, P: np.ndarray, z: Any, kind: str,
               variance: float) -> tuple[np.ndarray, np.ndarray, Any, Any]:
    """EKF measurement update, eq. (19), in Joseph form (stays symmetric positive definite).

    Args:
        x: prior pose [x, y, phi] in {L}, shape (3,), or a batch (T, 3).
        P: prior covariance, shape (3, 3), or (T, 3, 3).
        z: measured range (m) or bearing (rad): a float, or an array (T,).
        kind: 'range' or 'bearing'.
        variance: measurement noise variance, m^2 or rad^2.

    Returns:
        (x_post, P_post, innovation, innovation_variance); bearing innovations are wrapped.
        The products are stacked matrix products, so a batch gives each pose the bits it
        gets alone.
    """
    h = measurement_jacobian(kind, x)
    innovation = z - predict_measurement(kind, x)
    if kind == BEARING:
        innovation = wrap_angle(innovation)
    Ph = np.matmul(P, h[..., None])[..., 0]
    S = np.matmul(h[..., None, :], Ph[..., None])[..., 0, 0] + variance
    K = Ph / S[..., None]
    x_post = x + K * np.asarray(innovation)[..., None]
    x_post[..., 2] = wrap_angle(x_post[..., 2])
    A = np.eye(3) - K[..., :, None] * h[..., None, :]
    P_post = A @ P @ np.swapaxes(A, -1, -2) + variance * (K[..., :, None] * K[..., None, :])
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    if x.ndim == 1:
        return x_post, P_post, float(innovation), float(S)
    return x_post, P_post, innovation, S


def state_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b for poses [x, y, phi], shape (3,) or (T, 3), with the heading difference wrapped."""
    e = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    e[..., 2] = wrap_angle(e[..., 2])
    return e


def normalized_estimation_error(x_true: np.ndarray, x_est: np.ndarray, P: np.ndarray) -> Any:
    """NEES of [x, y, phi] (heading error wrapped): e' P^-1 e, dimensionless; a float for one
    pose, an array (T,) for a batch (stacked solves: each pose gets the bits it gets alone)."""
    e = state_difference(x_true, x_est)
    if e.ndim == 1:
        return float(e @ np.linalg.solve(P, e))
    y = np.linalg.solve(P, e[..., None])
    return np.matmul(e[..., None, :], y)[..., 0, 0]


def covariance_ellipse(covariance: np.ndarray, sigmas: float = 3.0) -> tuple[float, float, float]:
    """The ``sigmas``-sigma ellipse of a 2x2 position covariance (m^2).

    Returns:
        (major semi-axis m, minor semi-axis m, angle of the major axis rad): the eigen-
        decomposition of the covariance, semi-axes ``sigmas * sqrt(eigenvalue)``.
    """
    values, vectors = np.linalg.eigh(np.asarray(covariance, dtype=float)[:2, :2])
    major, minor = (sigmas * math.sqrt(max(float(v), 0.0)) for v in values[::-1])
    return major, minor, math.atan2(float(vectors[1, 1]), float(vectors[0, 1]))


def ellipse_points(centre: np.ndarray, covariance: np.ndarray, sigmas: float = 3.0,
                   count: int = 48) -> np.ndarray:
    """A closed polygon (count + 1, 2) on the ``sigmas``-sigma ellipse around centre (m)."""
    major, minor, angle = covariance_ellipse(covariance, sigmas)
    t = np.linspace(0.0, 2.0 * math.pi, count + 1)
    c, s = math.cos(angle), math.sin(angle)
    x, y = major * np.cos(t), minor * np.sin(t)
    return np.asarray(centre, dtype=float)[:2] + np.stack([c * x - s * y, s * x + c * y], axis=1)
