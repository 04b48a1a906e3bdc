"""Plumbing shared by the nodes: parameter specs and validation, QoS, topics, the run loop."""
from __future__ import annotations

import math
import signal
import sys
import time
from dataclasses import dataclass
from typing import Callable

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from formopt_ros.core.model import MEASUREMENT_KINDS
from formopt_ros.core.simulation import Scenario

#: Reliable, deep queue: lockstep runs must not drop a message.
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                      reliability=ReliabilityPolicy.RELIABLE)

#: What the nodes offer: reliable, and TRANSIENT_LOCAL so that a subscriber that matches late
#: (the recorder, when discovery takes seconds) still receives the history (up to 1000 per
#: topic). Volatile subscriptions (the nodes' own) are compatible with it.
PUBLISHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)



def qos_for(reliable: bool, latched: bool) -> QoSProfile:
    """A deep KEEP_LAST profile, reliable or best effort, transient-local or volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=PUBLISHED.depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


#: Topic names relative to the node namespace.
TOPICS = {
    'leader_odom': 'leader/odom',
    'follower_odom': 'follower/odom',
    'measurement': 'follower/measurement',
    'truth': 'follower/truth',
    'estimate': 'follower/estimate',
    'waypoint': 'follower/waypoint',
    'status': 'follower/status',
}
MODES = ('lockstep', 'realtime')


class ParameterError(ValueError):
    """A parameter value outside its documented range."""


@dataclass(frozen=True)
class Param:
    """One node parameter: default, description with unit, and its admissible values."""

    name: str
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()

    def descriptor(self) -> ParameterDescriptor:
        """The ROS descriptor, with the range for introspection (ros2 param describe)."""
        text = self.description
        if self.choices:
            text += f" (one of: {', '.join(self.choices)})"
        descriptor = ParameterDescriptor(description=text)
        if self.low is not None and self.high is not None and not isinstance(self.default,
                                                                             bool):
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(self.low), to_value=int(self.high), step=1)]
            elif isinstance(self.default, float):
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low), to_value=float(self.high), step=0.0)]
        return descriptor

    def check(self, value: object) -> object:
        """Return value if admissible, else raise ParameterError naming the parameter."""
        expected = self._expected()
        if isinstance(self.default, float) and isinstance(value, int) \
                and not isinstance(value, bool):
            value = float(value)
        if type(value) is not type(self.default) and not (
                isinstance(self.default, list) and isinstance(value, (list, tuple))):
            raise ParameterError(f"parameter '{self.name}' must be {expected}, got {value!r}")
        if self.choices and value not in self.choices:
            raise ParameterError(f"parameter '{self.name}' must be {expected}, got {value!r}")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if isinstance(value, float) and not math.isfinite(value):
                raise ParameterError(f"parameter '{self.name}' must be {expected}, "
                                     f'got {value!r}')
            if (self.low is not None and value < self.low) or \
                    (self.high is not None and value > self.high):
                raise ParameterError(f"parameter '{self.name}' must be {expected}, "
                                     f'got {value!r}')
        return value

    def _expected(self) -> str:
        if self.choices:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        kind = type(self.default).__name__
        if self.low is not None or self.high is not None:
            return f'a {kind} in [{self.low}, {self.high}] ({self.description})'
        return f'a {kind} ({self.description})'


def declare(node: Node, specs: list[Param]) -> dict[str, object]:
    """Declare every parameter with its descriptor and return the validated values."""
    values = {}
    for spec in specs:
        override = getattr(node, '_parameter_overrides', {}).get(spec.name)
        try:
            node.declare_parameter(spec.name, spec.default, spec.descriptor())
            value = node.get_parameter(spec.name).value
        except Exception as error:   # rclpy rejects out-of-range or mistyped overrides
            received = override.value if override is not None else '?'
            raise ParameterError(f"parameter '{spec.name}' must be {spec._expected()}, got "
                                 f'{received!r} ({type(error).__name__})') from None
        if isinstance(spec.default, list) and value is not None:
            value = list(value)
        values[spec.name] = spec.check(value)
    return values


# Parameters shared by several nodes; each node lists the ones it uses.
FOLLOWER_ID = Param('follower_id', 'follower', 'id of the follower (frame and message filter)')
LEADER_ID = Param('leader_id', 'leader', 'id of the leader (its odometry child_frame_id)')
MODE = Param('mode', 'lockstep', 'lockstep: act on the awaited message, deterministic; '
             'realtime: timers at 1/dt', choices=MODES)
DT = Param('dt', 0.05, 'sub-step length, s', 1e-4, 10.0)
MEASUREMENT = Param('measurement', 'range', 'the follower sensor', choices=MEASUREMENT_KINDS)
SEED = Param('seed', 0, 'seed of the random streams (same as formopt-montecarlo)', 0, 2**31 - 1)
TRIAL = Param('trial', 0, 'trial index: the streams are seeded by (seed, trial)', 0, 2**31 - 1)
SIGMA_V = Param('sigma_v', 0.2, 'follower linear velocity noise std, m/s', 0.0, 100.0)
SIGMA_OMEGA = Param('sigma_omega', 0.1, 'follower angular velocity noise std, rad/s', 0.0,
                    100.0)
RANGE_SIGMA = Param('range_sigma', 0.1, 'range noise std, m', 1e-9, 1e3)
BEARING_SIGMA = Param('bearing_sigma', 0.02, 'bearing noise std, rad', 1e-9, 3.2)
SLOT = Param('formation_slot', [0.0], 'formation slot p_o [x, y] in the leader frame, m; '
             '[0.0] means the paper default for the measurement kind')
DEVIATION = Param('deviation_fraction', 0.1, 'allowed deviation r as a fraction of |p_o|',
                  1e-6, 0.999)
V_LEADER = Param('v_leader', 1.0, 'leader forward speed, m/s', -100.0, 100.0)
OMEGA_LEADER = Param('omega_leader', 0.0, 'leader yaw rate, rad/s', -100.0, 100.0)
SCENARIO_PARAMS = [MEASUREMENT, DT, SIGMA_V, SIGMA_OMEGA, RANGE_SIGMA, BEARING_SIGMA, SLOT,
                   DEVIATION, V_LEADER, OMEGA_LEADER]


def scenario_from(values: dict[str, object]) -> Scenario:
    """The Scenario described by the shared parameters (paper defaults otherwise)."""
    kind = values['measurement']
    slot = values['formation_slot']
    base = Scenario.paper(kind)
    if list(slot) != [0.0]:
        if len(slot) != 2 or math.hypot(*slot) == 0.0:
            raise ParameterError("parameter 'formation_slot' must be [x, y] with |p_o| > 0 m, "
                                 f'got {slot!r}')
        base = Scenario.paper(kind, p_o=(float(slot[0]), float(slot[1])))
    return Scenario.paper(
        kind, p_o=base.p_o, r=values['deviation_fraction'] * math.hypot(*base.p_o),
        sigma=values['range_sigma'] if kind == 'range' else values['bearing_sigma'],
        v_leader=values['v_leader'], omega_leader=values['omega_leader'], dt=values['dt'],
        sigma_v=values['sigma_v'], sigma_omega=values['sigma_omega'])


class Throttle:
    """Log a warning at most once per ``period`` seconds per key."""

    def __init__(self, node: Node, period: float = 2.0) -> None:
        self.node, self.period, self.last = node, period, {}

    def warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self.last.get(key, -math.inf) >= self.period:
            self.last[key] = now
            self.node.get_logger().warning(text)


def run(node_factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Create the node, spin until it finishes or SIGINT/SIGTERM; return the exit code.

    A ParameterError ends the process with code 2 and one line naming the parameter.
    SIGINT and SIGTERM end the spin loop (within 0.1 s) while the context is still valid, so
    ``close()`` can still log and publish; then the context shuts down.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop: list[int] = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda received, _frame: stop.append(received))
    node = None
    try:
        node = node_factory()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop and not getattr(node, 'finished', False):
            executor.spin_once(timeout_sec=0.1)
        return 0
    except ParameterError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if node is not None:
            try:
                node.close()
            except Exception as error:  # never turn a clean stop into a traceback
                print(f'warning: shutdown: {error}', file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
