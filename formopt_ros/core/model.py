"""Relative kinematics, range/bearing measurement models and the EKF of the paper (eqs. 8-19).

Frames and units
----------------
The state ``x = [x, y, phi]`` is the follower's pose in the leader's body frame {L}: position in
metres, heading in radians (follower x-axis relative to leader x-axis), wrapped to [-pi, pi).
Velocities are body-frame forward speed (m/s) and yaw rate (rad/s).

The paper assumes omega_L = 0 and discretises with Euler's method (eq. 9). We keep the leader's
yaw rate and propagate exactly for velocities held constant over a step: each robot drives an
arc, whose displacement in its frame at the start is the chord
``f(v, omega) = v dt sinc(h) [cos h, sin h]``, ``h = omega dt / 2``. With the relative pose
``T = T_L^-1 T_F`` (SE(2)), one step is ``T' = Exp_L^-1 T Exp_F``:
``p' = C(-omega_L dt) (p + C(phi) f(v_F, omega_F) - f(v_L, omega_L))``,
``phi' = phi + (omega_F - omega_L) dt``. Its first-order terms are the continuous kinematics
``x_dot = omega_L y + cos(phi) v_F - v_L``, ``y_dot = -omega_L x + sin(phi) v_F``,
``phi_dot = omega_F - omega_L``; with omega_L = 0 and a step that only turns (v_F = 0) or
only drives (omega_F = 0), as in the paper's protocol, it equals eq. (9) to rounding. Euler
is not exact once the leader turns: each step scales |p| by sqrt(1 + (omega_L dt)^2).
The leader's odometry noise enters the covariance through the Jacobian of ``p'`` with
respect to (v_L, omega_L) (zero by default: the paper takes the leader's motion as known).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

RANGE = 'range'
BEARING = 'bearing'
MEASUREMENT_KINDS = (RANGE, BEARING)
#: Range and bearing at one step: z = [d m, beta rad], R = diag(sigma_d^2, sigma_beta^2).
RANGE_BEARING = 'range-bearing'
SENSOR_KINDS = (RANGE, BEARING, RANGE_BEARING)
#: Motion models: 'exact' (arcs of constant velocities, SE(2)) or 'euler' (the paper's eq. 9,
#: with which its Sec. V simulates; kept to reproduce those numbers).
EXACT = 'exact'
EULER = 'euler'
KINEMATICS = (EXACT, EULER)


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


def _sinc_terms(h: Any) -> tuple[Any, Any, Any, Any]:
    """cos h, sin h, sinc h = sin(h) / h and its derivative (cos h - sinc h) / h, for a float
    or an array; a series where the quotients would cancel (|h| < 1e-3: truncation < 1e-19)."""
    c, s = elementwise(math.cos, h), elementwise(math.sin, h)
    if isinstance(h, np.ndarray):
        small = np.abs(h) < 1e-3
        with np.errstate(divide='ignore', invalid='ignore'):
            sinc = np.where(h == 0.0, 1.0, s / h)
            dsinc = np.where(small, h * (h * h / 30.0 - 1.0 / 3.0), (c - sinc) / h)
        return c, s, sinc, dsinc
    if abs(h) < 1e-3:
        return c, s, (1.0 if h == 0.0 else s / h), h * (h * h / 30.0 - 1.0 / 3.0)
    sinc = s / h
    return c, s, sinc, (c - sinc) / h


def chord(v: Any, omega: Any, dt: float) -> tuple[Any, ...]:
    """Displacement of a body driving at constant (v m/s, omega rad/s) for dt s, in its frame
    at the start: the chord v dt sinc(h) [cos h, sin h] with h = omega dt / 2, and its
    derivatives. Returns (dx, dy, ddx/dv, ddy/dv, ddx/domega, ddy/domega)."""
    c, s, sinc, dsinc = _sinc_terms(0.5 * omega * dt)
    length = dt * sinc                      # chord length per unit speed, s
    dlength = 0.5 * dt * dt * dsinc         # its derivative w.r.t. omega, s^2
    dx_dv, dy_dv = length * c, length * s
    half = 0.5 * dt * length                # d(h)/domega * length, s^2
    return (v * dx_dv, v * dy_dv, dx_dv, dy_dv,
            v * (dlength * c - half * s), v * (dlength * s + half * c))


def propagate_state(x: np.ndarray, v_f: Any, omega_f: Any, dt: float,
                    v_l: Any, omega_l: Any = 0.0, kinematics: str = EXACT) -> np.ndarray:
    """Exact step of the relative kinematics for velocities held constant over ``dt``.

    Both robots drive on circular arcs (SE(2) composition, module docstring); with omega_F = 0
    or v_F = 0, and omega_L = 0, this is the paper's Euler step, eqs. (9)/(10), to rounding.

    Args:
        x: pose [x, y, phi] of the follower in {L} (m, m, rad), shape (3,) or (T, 3).
        v_f, omega_f: follower forward speed (m/s) and yaw rate (rad/s) during the step
            (floats, or arrays (T,) for a batch of poses).
        dt: step length (s).
        v_l, omega_l: leader forward speed (m/s) and yaw rate (rad/s) (floats, or arrays (T,)).
        kinematics: 'exact', or 'euler' for the paper's eq. (9) itself.

    Returns:
        The pose after ``dt``, shape of x, heading wrapped.
    """
    return _transition(x, v_f, omega_f, dt, v_l, omega_l, kinematics, False)[0]


def integrate_unicycle(pose: tuple[float, float, float], v: float, omega: float,
                       dt: float) -> tuple[float, float, float]:
    """Dead reckoning of a planar robot in a fixed frame (odometry pose): the exact arc of
    constant (v, omega) over dt.

    Args:
        pose: (x m, y m, yaw rad) in the fixed frame.
        v, omega: forward speed (m/s) and yaw rate (rad/s) during the step.
        dt: step length, s.

    Returns:
        The pose after ``dt`` (yaw not wrapped: odometry yaw is continuous).
    """
    x, y, yaw = pose
    dx, dy = chord(v, omega, dt)[:2]
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * dx - s * dy, y + s * dx + c * dy, yaw + omega * dt


def _transition(x: np.ndarray, v_f: Any, omega_f: Any, dt: float, v_l: Any, omega_l: Any,
                kinematics: str, jacobians: bool) -> tuple[Any, ...]:
    """The pose after one step (module docstring) and, with ``jacobians``, the entries of its
    Jacobians: (pose, b0, b1, ca, sa, (a, b, e, f), scale), where Phi = [[ca, sa, b0], [-sa, ca,
    b1], [0, 0, 1]] and scale times a, b (follower v, omega) and e, f (leader v, omega) are the
    columns of the noise Jacobian, each a tuple of three components (floats or arrays (T,))."""
    px, py, phi = _components(x)
    cf, sf = elementwise(math.cos, phi), elementwise(math.sin, phi)
    if kinematics == EULER:
        pose = stack_vector(px + (omega_l * py + cf * v_f - v_l) * dt,
                            py + (-omega_l * px + sf * v_f) * dt,
                            wrap_angle(phi + (omega_f - omega_l) * dt))
        if not jacobians:
            return (pose,)
        columns = ((cf, sf, 0.0), (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0), (py, -px, -1.0))
        return pose, -sf * v_f * dt, cf * v_f * dt, 1.0, omega_l * dt, columns, dt
    fx, fy, fxv, fyv, fxw, fyw = chord(v_f, omega_f, dt)
    lx, ly, lxv, lyv, lxw, lyw = chord(v_l, omega_l, dt)
    qx, qy = px + (cf * fx - sf * fy) - lx, py + (sf * fx + cf * fy) - ly
    ca, sa = elementwise(math.cos, omega_l * dt), elementwise(math.sin, omega_l * dt)
    nx, ny = (qx, qy) if not isinstance(omega_l, np.ndarray) and omega_l == 0.0 else \
        (ca * qx + sa * qy, -sa * qx + ca * qy)
    pose = stack_vector(nx, ny, wrap_angle(phi + (omega_f - omega_l) * dt))
    if not jacobians:
        return (pose,)

    def turned(u: Any, w: Any) -> tuple[Any, Any]:     # A R(phi) [u, w]
        gx, gy = cf * u - sf * w, sf * u + cf * w
        return ca * gx + sa * gy, -sa * gx + ca * gy

    b0, b1 = turned(-fy, fx)                            # A J R(phi) f
    columns = ((*turned(fxv, fyv), 0.0), (*turned(fxw, fyw), dt),
               (-(ca * lxv + sa * lyv), sa * lxv - ca * lyv, 0.0),
               (dt * ny - (ca * lxw + sa * lyw), -dt * nx + (sa * lxw - ca * lyw), -dt))
    return pose, b0, b1, ca, sa, columns, 1.0


def _noise_covariance(columns: tuple[tuple[Any, Any, Any], ...],
                      variances: tuple[float, ...]) -> tuple[Any, ...]:
    """The six distinct entries (00, 01, 02, 11, 12, 22) of sum_k variance_k g_k g_k'."""
    out = [0.0] * 6
    for (g0, g1, g2), q in zip(columns, variances):
        if q == 0.0:
            continue
        for i, (u, w) in enumerate(((g0, g0), (g0, g1), (g0, g2), (g1, g1), (g1, g2),
                                    (g2, g2))):
            out[i] = out[i] + q * u * w
    return tuple(out)


def _variances(scale: float, *sigmas: float) -> tuple[float, ...]:
    """(scale sigma)^2 for each noise standard deviation (scale: the noise columns' unit)."""
    return tuple((scale * sigma) ** 2 for sigma in sigmas)


def propagate(x: np.ndarray, P: np.ndarray, v_f: Any, omega_f: Any, dt: float,
              v_l: float, omega_l: float, sigma_v: float, sigma_omega: float,
              sigma_v_l: float = 0.0, sigma_omega_l: float = 0.0,
              kinematics: str = EXACT) -> tuple[np.ndarray, np.ndarray]:
    """EKF propagation over one step with measured follower velocities (paper eqs. (10)-(12),
    exact for velocities held over the step: :func:`propagate_state`).

    Args:
        x: estimated pose [x, y, phi] in {L}, shape (3,) or (T, 3).
        P: its covariance, shape (3, 3) or (T, 3, 3), units m^2 / m rad / rad^2.
        v_f, omega_f: odometry (measured) follower velocities, m/s and rad/s (floats, or
            arrays (T,)).
        dt: step length, s.
        v_l, omega_l: leader velocities as reported by its odometry, m/s and rad/s.
        sigma_v, sigma_omega: follower odometry noise standard deviations, m/s and rad/s.
        sigma_v_l, sigma_omega_l: leader odometry noise standard deviations (0: the leader's
            velocities are known exactly, as in the paper).
        kinematics: 'exact', or 'euler' for the paper's eqs. (10)-(12) themselves.

    Returns:
        (x, P) after the step; P_next = Phi P Phi' + G Q G' written out (symmetric by
        construction; a test checks it against finite differences).
    """
    pose, b0, b1, ca, sa, columns, scale = _transition(x, v_f, omega_f, dt, v_l, omega_l,
                                                       kinematics, True)
    if P.ndim == 2:
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = P.tolist()
    else:
        p00, p01, p02, p11, p12, p22 = (P[..., 0, 0], P[..., 0, 1], P[..., 0, 2],
                                        P[..., 1, 1], P[..., 1, 2], P[..., 2, 2])
    # rows of Phi P
    r00, r01, r02 = ca * p00 + sa * p01 + b0 * p02, ca * p01 + sa * p11 + b0 * p12, \
        ca * p02 + sa * p12 + b0 * p22
    r10, r11, r12 = -sa * p00 + ca * p01 + b1 * p02, -sa * p01 + ca * p11 + b1 * p12, \
        -sa * p02 + ca * p12 + b1 * p22
    q00, q01, q02, q11, q12, q22 = _noise_covariance(
        columns, _variances(scale, sigma_v, sigma_omega, sigma_v_l, sigma_omega_l))
    n00 = ca * r00 + sa * r01 + b0 * r02 + q00
    n01 = -sa * r00 + ca * r01 + b1 * r02 + q01
    n11 = -sa * r10 + ca * r11 + b1 * r12 + q11
    return pose, symmetric3((n00, n01, r02 + q02, n11, r12 + q12, p22 + q22))


def transition_matrices(x: np.ndarray, v_f: Any, omega_f: Any, dt: float, v_l: Any,
                        omega_l: Any, sigma_v: float, sigma_omega: float,
                        sigma_v_l: float = 0.0, sigma_omega_l: float = 0.0,
                        kinematics: str = EXACT) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, G Q G') of one propagation step: (3, 3) for a pose (3,), (T, 3, 3) for poses (T, 3).

    :func:`propagate` applies them written out (P_next = Phi P Phi' + G Q G'); multi-step
    planners compose them. Args as in :func:`propagate` (v_l, omega_l also arrays (T,)).
    """
    _, b0, b1, ca, sa, columns, scale = _transition(x, v_f, omega_f, dt, v_l, omega_l,
                                                    kinematics, True)
    GQG = symmetric3(_noise_covariance(
        columns, _variances(scale, sigma_v, sigma_omega, sigma_v_l, sigma_omega_l)))
    entries = np.broadcast_arrays(ca, sa, b0, -sa, ca, b1, 0.0, 0.0, 1.0)
    return np.stack(entries, axis=-1).reshape(entries[0].shape + (3, 3)), GQG


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
    poses (T, 3) in {L}: a float, or an array (T,); for 'range-bearing' both stacked, (2,) or
    (T, 2)."""
    if kind == RANGE_BEARING:
        return stack_vector(predict_measurement(RANGE, x), predict_measurement(BEARING, x))
    px, py, phi = _components(x)
    if kind == RANGE:
        return elementwise(math.hypot, px, py)
    bearing = wrap_angle(elementwise(math.atan2, py, px) - phi + math.pi)
    return float(bearing) if x.ndim == 1 else bearing


def measurement_jacobian(kind: str, x: np.ndarray) -> np.ndarray:
    """Jacobian of the measurement w.r.t. [x, y, phi], eqs. (16) and (18), shape of x; for
    'range-bearing' the two rows stacked, (2, 3) or (T, 2, 3)."""
    if kind == RANGE_BEARING:
        return np.stack([measurement_jacobian(RANGE, x), measurement_jacobian(BEARING, x)],
                        axis=-2)
    px, py, _ = _components(x)
    d2 = px * px + py * py
    if kind == RANGE:
        d = elementwise(math.sqrt, d2)
        return stack_vector(px / d, py / d, 0.0 * d)
    return stack_vector(-py / d2, px / d2, -1.0 + 0.0 * d2)


def sensor_pose(x: np.ndarray, offset: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A sensor mounted at ``offset`` [m_x, m_y] (m, in the follower's body frame): its pose
    [p + C(phi) m, phi] in {L}, (3,), and the Jacobian (3, 3) of that pose w.r.t. the
    follower's [x, y, phi]; a measurement taken there has the Jacobian h(pose) times it."""
    c, s = math.cos(float(x[2])), math.sin(float(x[2]))
    mx, my = offset
    pose = np.array([x[0] + c * mx - s * my, x[1] + s * mx + c * my, x[2]])
    jacobian = np.array([[1.0, 0.0, -s * mx - c * my], [0.0, 1.0, c * mx - s * my],
                         [0.0, 0.0, 1.0]])
    return pose, jacobian


def rotation_matrix(quaternion: tuple[float, float, float, float]) -> np.ndarray:
    """The rotation (3, 3) of a unit quaternion (x, y, z, w), as geometry_msgs orders it."""
    x, y, z, w = np.asarray(quaternion, dtype=float) / np.linalg.norm(quaternion)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rpy_quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """The quaternion (x, y, z, w) of fixed-axis roll, pitch, yaw (rad), as in ROS (tf2)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def direction_bearing(direction: tuple[float, float, float],
                      rotation: np.ndarray) -> float | None:
    """The bearing (rad, wrapped) of a direction (any length) seen in a sensor frame, in a
    frame parallel to the follower's body frame: atan2 of the direction turned by the sensor's
    mounting ``rotation`` (3, 3; body from sensor). None when it points (nearly) straight up or
    down, where no bearing exists."""
    u = rotation @ np.asarray(direction, dtype=float)
    if not math.hypot(u[0], u[1]) > 1e-6 * float(np.linalg.norm(u)):
        return None
    return float(wrap_angle(math.atan2(u[1], u[0])))


def ekf_update(x: np.ndarray, P: np.ndarray, z: Any, kind: str, variance: float,
               offset: tuple[float, float] | None = None
               ) -> tuple[np.ndarray, np.ndarray, Any, Any]:
    """EKF measurement update, eq. (19), in Joseph form (stays symmetric positive definite).

    Args:
        x: prior pose [x, y, phi] in {L}, shape (3,), or a batch (T, 3); or, for a range with
            a bias state, [x, y, phi, b] (4,) with z = |p| + b + noise (b in m).
        P: prior covariance, shape (n, n), or (T, n, n), n the state size.
        z: measured range (m) or bearing (rad): a float, or an array (T,).
        kind: 'range' or 'bearing'.
        variance: measurement noise variance, m^2 or rad^2.
        offset: one pose only: the sensor's position [m_x, m_y] on the follower (m, body
            frame; :func:`sensor_pose`); the measurement is taken there (a bearing in a frame
            parallel to the body's). None: at the follower's origin, as in the paper.

    Returns:
        (x_post, P_post, innovation, innovation_variance); bearing innovations are wrapped.
        The products are stacked matrix products, so a batch gives each pose the bits it
        gets alone.
    """
    n = x.shape[-1]
    if offset is None:
        h = measurement_jacobian(kind, x[..., :3])
        innovation = z - predict_measurement(kind, x[..., :3])
    else:
        pose, jacobian = sensor_pose(x, offset)
        h = measurement_jacobian(kind, pose) @ jacobian
        innovation = z - predict_measurement(kind, pose)
    if kind == BEARING:
        innovation = wrap_angle(innovation)
    if n == 4:                                      # the range bias b enters with slope 1
        innovation = innovation - x[..., 3]
        h = np.concatenate([h, np.ones(h.shape[:-1] + (1,))], axis=-1)
    Ph = np.matmul(P, h[..., None])[..., 0]
    S = np.matmul(h[..., None, :], Ph[..., None])[..., 0, 0] + variance
    K = Ph / S[..., None]
    x_post = x + K * np.asarray(innovation)[..., None]
    x_post[..., 2] = wrap_angle(x_post[..., 2])
    A = np.eye(n) - K[..., :, None] * h[..., None, :]
    P_post = A @ P @ np.swapaxes(A, -1, -2) + variance * (K[..., :, None] * K[..., None, :])
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    if x.ndim == 1:
        return x_post, P_post, float(innovation), float(S)
    return x_post, P_post, innovation, S


def ekf_update_stacked(x: np.ndarray, P: np.ndarray, z: Any, variances: tuple[float, float]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """EKF update with range and bearing of the same instant (z = [d, beta]), Joseph form.

    P_post = (I - K H) P (I - K H)' + K R K' with H = [h_d'; h_beta'] (2, 3),
    S = H P H' + R (2, 2), K = P H' S^-1, R = diag(variances); the bearing residual is wrapped.
    S^-1 is the explicit 2 x 2 inverse (entry-wise, so a batch gives each pose the bits it gets
    alone).

    Args:
        x: prior pose [x, y, phi] in {L}, shape (3,) or (T, 3).
        P: prior covariance, shape (3, 3) or (T, 3, 3).
        z: measured [range m, bearing rad], shape (2,) or (T, 2).
        variances: (sigma_d^2 m^2, sigma_beta^2 rad^2).

    Returns:
        (x_post, P_post, innovation (2,) or (T, 2), S (2, 2) or (T, 2, 2)).
    """
    H = measurement_jacobian(RANGE_BEARING, x)
    innovation = np.asarray(z, dtype=float) - predict_measurement(RANGE_BEARING, x)
    innovation[..., 1] = wrap_angle(innovation[..., 1])
    PH = np.matmul(P, np.swapaxes(H, -1, -2))                     # (.., 3, 2)
    R = np.diag(np.asarray(variances, dtype=float))
    S = np.matmul(H, PH) + R
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    s00, s01, s11 = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    det = s00 * s11 - s01 * s01
    S_inv = np.empty_like(S)
    S_inv[..., 0, 0], S_inv[..., 1, 1] = s11 / det, s00 / det
    S_inv[..., 0, 1] = S_inv[..., 1, 0] = -s01 / det
    K = np.matmul(PH, S_inv)                                      # (.., 3, 2)
    x_post = x + np.matmul(K, innovation[..., None])[..., 0]
    x_post[..., 2] = wrap_angle(x_post[..., 2])
    A = np.eye(3) - np.matmul(K, H)
    P_post = A @ P @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    return x_post, P_post, innovation, S


def stacked_nis(innovation: np.ndarray, S: np.ndarray) -> Any:
    """Normalised innovation squared nu' S^-1 nu of a stacked update (chi-square, 2 dof):
    innovation (2,) or (T, 2), S (2, 2) or (T, 2, 2); a float or an array (T,)."""
    n0, n1 = innovation[..., 0], innovation[..., 1]
    s00, s01, s11 = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    nis = (s11 * n0 * n0 - 2.0 * s01 * n0 * n1 + s00 * n1 * n1) / (s00 * s11 - s01 * s01)
    return float(nis) if np.ndim(nis) == 0 else nis


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
