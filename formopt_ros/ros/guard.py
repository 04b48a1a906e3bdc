"""The run guard: a node starts its run only once its peers' run descriptions agree with its
own (the scenario handshake), and stops the run when they disagree or when a second publisher
appears on a topic it reads (another run, or a stray node, in the same domain and namespace).

Mismatch: the node stops with exit code 2 and one line naming every differing parameter with
both values. It stops once every peer that reads its description has been matched (at most
``MISMATCH_LINGER`` s later): the description is latched by a publisher that dies with the node,
so a peer matched only after the node left would wait for the run forever instead of stopping
too. Run over (a watchdog for simulators started by hand): once the node's part of the run
is done and no estimator it serves has published its waypoints for ``END_LINGER`` s (they
finished and left), the node finishes with exit code 0 instead of waiting for good.
Intruder: a topic the node reads has more than one publisher for longer than
``INTRUDER_GRACE`` s; the node stops with exit code 1 and names the publishing nodes. The grace
covers a restarted peer whose killed predecessor stays in the ROS graph until its discovery
lease ends (3 s with config/fastdds_discovery.xml, which every formopt_ros node loads unless
FASTRTPS_DEFAULT_PROFILES_FILE is set); publishers that all have one name get
``RESTART_GRACE`` s (a robot's driver restarted under Fast DDS's default 20 s lease).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from formopt_interfaces.msg import RunDescription

from formopt_ros.ros import conversions, qos
from formopt_ros.ros.naming import peer_topic
from formopt_ros.ros.runtime import stop_run
from formopt_ros.wire.description import LeaderDescription
from formopt_ros.wire.description import RunDescription as Description
from formopt_ros.wire.description import follower_differences, leader_differences
from formopt_ros.wire.topics import BY_KEY

#: How long (s) a topic may have a second publisher before the run is stopped.
INTRUDER_GRACE = 5.0
#: How long (s) when every publisher has the same name: a restarted node whose predecessor
#: stays in the graph until its discovery lease ends (20 s with Fast DDS's default profile,
#: which a robot's own drivers keep).
RESTART_GRACE = 25.0
#: Look at the publishers of the watched topics at most this often, s.
CHECK_PERIOD = 0.5
#: A node stopped by a mismatch waits at most this long (s) for its description's readers.
MISMATCH_LINGER = 3.0
#: A simulator whose part of the run is done ends once its estimators' waypoint topics have
#: had no publisher this long, s.
END_LINGER = 2.0
#: Exit codes: a scenario mismatch is a configuration error; an intruder a run-time failure.
MISMATCH_EXIT, INTRUDER_EXIT = 2, 1

#: Differences as (parameter, value here, value there), from a peer's description JSON text.
Compare = Callable[[str], list[tuple[str, Any, Any]]]


@dataclass(frozen=True)
class Failure:
    """Why the guard stopped the run."""

    code: int
    message: str


class RunGuard:
    """Handshake with the peers of a run and watch the topics the node reads.

    Args:
        node: the node.
        wait: the run waits for every expected peer description (False: compare the ones that
            come, start without them; e.g. an estimator driven by a replayed bag).
        on_failure: called once with the Failure that stops the run.
    """

    def __init__(self, node: Any, wait: bool, on_failure: Callable[[Failure], None]) -> None:
        self.node = node
        self.wait = wait
        self.on_failure = on_failure
        self.failure: Failure | None = None
        self.seen: dict[str, str] = {}            # description topic -> publishing node
        self.expected: list[str] = []
        self.watched: list[str] = []
        self._crowded_since: dict[str, float] = {}
        self._checked = -math.inf
        self._failed_at = math.inf
        self._reported = False
        self.description_pub: Any = None
        self.description_message: Any = None
        self.readers = 0
        self.texts: dict[str, str] = {}           # description topic -> the agreeing text
        self._end: tuple[list[str], Callable[[], bool]] | None = None
        self._idle_since: float | None = None

    def announce(self, key: str, description: str, run_id: str, readers: int) -> None:
        """Publish the node's run description (JSON text) latched on topic ``key``; ``readers``
        peer nodes read it (a mismatch stop waits until they are matched, see the module)."""
        self.description_pub = self.node.create_publisher(RunDescription, BY_KEY[key].name,
                                                          qos.LATCHED)
        self.description_message = conversions.description(
            self.node.get_clock().now().to_msg(), run_id, self.node.get_fully_qualified_name(),
            description)
        self.description_pub.publish(self.description_message)
        self.readers = readers

    def reannounce(self, description: str) -> None:
        """Publish an updated description of the same run (e.g. with a strategy change) on the
        latched topic of :meth:`announce`: late subscribers and the bag get the latest."""
        self.description_message = conversions.description(
            self.node.get_clock().now().to_msg(), self.description_message.run_id,
            self.node.get_fully_qualified_name(), description)
        self.description_pub.publish(self.description_message)

    def expect(self, topic: str, compare: Compare) -> None:
        """Subscribe to the latched description on ``topic`` and compare it when it comes."""
        self.expected.append(topic)
        self.watch(topic)

        def on_description(msg: Any) -> None:
            try:
                differences = compare(msg.description)
            except ValueError as error:
                self.fail(Failure(MISMATCH_EXIT, f'the description on {topic} from {msg.node} '
                                                 f'is unreadable: {error}'))
                return
            if differences:
                self.fail(Failure(MISMATCH_EXIT, 'scenario mismatch: ' + '; '.join(
                    f'parameter {name!r} is {mine!r} in {self.node.get_fully_qualified_name()} '
                    f'and {theirs!r} in {msg.node}' for name, mine, theirs in differences)))
                return
            self.seen[topic] = msg.node
            self.texts[topic] = msg.description

        self.node.create_subscription(RunDescription, topic, on_description, qos.LATCHED)

    def watch(self, topic: str) -> None:
        """Expect exactly one publisher on ``topic`` (checked by :meth:`check`)."""
        self.watched.append(topic)

    def end_when(self, waypoint_topics: list[str], done: Callable[[], bool]) -> None:
        """Finish the node (exit code 0) once ``done()`` holds and none of
        ``waypoint_topics`` has had a publisher for END_LINGER s (checked by :meth:`check`)."""
        self._end = (waypoint_topics, done)

    def peer_steps(self, topic: str) -> int | None:
        """The run's steps in the agreeing description heard on ``topic`` (0: a run until
        stopped; None: not heard)."""
        text = self.texts.get(topic)
        return Description.from_json(text).steps if text else None

    def missing(self) -> list[str]:
        """The description topics not heard yet."""
        return [topic for topic in self.expected if topic not in self.seen]

    def ready(self) -> bool:
        """True when the run may start: no failure and (unless not waiting) every peer agreed."""
        return self.failure is None and (not self.wait or not self.missing())

    def check(self) -> None:
        """Look for topics with more than one publisher (call it from a timer; it looks at
        most every CHECK_PERIOD s); report a mismatch once the description's readers are
        matched or MISMATCH_LINGER s have passed."""
        now = time.monotonic()
        if self.failure is not None:
            if not self._reported and (self._read_by_all() or
                                       now - self._failed_at >= MISMATCH_LINGER):
                self._report()
            return
        if now - self._checked < CHECK_PERIOD:
            return
        self._checked = now
        for topic in self.watched:
            infos = self.node.get_publishers_info_by_topic(topic)
            if len(infos) <= 1:
                self._crowded_since.pop(topic, None)
                continue
            since = self._crowded_since.setdefault(topic, now)
            names = sorted(f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos)
            alike = len(set(names)) == 1
            if now - since >= (RESTART_GRACE if alike else INTRUDER_GRACE):
                why = (f'two nodes named {names[0]} (a restarted node\'s predecessor leaves the '
                       f'graph within its discovery lease, less than {RESTART_GRACE:g} s)'
                       if alike else 'another run or node publishes on the topics of this run')
                self.fail(Failure(INTRUDER_EXIT, (
                    f"{len(infos)} publishers on {topic} ({', '.join(names)}) for "
                    f'{now - since:.1f} s: {why}; its data may be mixed in (run formations '
                    'in separate ROS_DOMAIN_IDs or namespaces)')))
                return
        self._check_end(now)

    def _check_end(self, now: float) -> None:
        if self._end is None:
            return
        topics, done = self._end
        if not done() or any(self.node.count_publishers(t) for t in topics):
            self._idle_since = None
            return
        self._idle_since = self._idle_since or now
        if now - self._idle_since >= END_LINGER and not self.node.finished:
            self.node.get_logger().info('the run is over: its estimators finished their steps '
                                        f'and left {END_LINGER:g} s ago; ending')
            self.node.finished = True

    def fail(self, failure: Failure) -> None:
        """Record the first failure and report it (a mismatch: when :meth:`check` may)."""
        if self.failure is None:
            self.failure = failure
            self._failed_at = time.monotonic()
            if failure.code != MISMATCH_EXIT or self._read_by_all():
                self._report()

    def _read_by_all(self) -> bool:
        """True when every reader of the node's description is matched (or none announced)."""
        return (self.description_pub is None or
                self.description_pub.get_subscription_count() >= self.readers)

    def _report(self) -> None:
        self._reported = True
        assert self.failure is not None
        self.on_failure(self.failure)


def follower_guard(node: Any, description: Any, leader_id: str, own_key: str, peer_key: str,
                   watched: tuple[str, ...]) -> RunGuard:
    """The guard of a follower's node (follower_sim or estimator_planner): it announces
    ``description`` (a wire RunDescription) on its ``own_key`` topic, expects its partner's on
    its own ``peer_key`` topic and the leader's, compares both with it, and watches its own
    ``watched`` topics and the leader's odometry. A failure stops the node
    (:func:`~formopt_ros.ros.runtime.stop_run`)."""
    guard = RunGuard(node, node.params['wait_for_peers'],
                     lambda failure: stop_run(node, failure.code, failure.message))
    guard.announce(own_key, description.to_json(), node.params['run_id'],
                   len(BY_KEY[own_key].listeners))
    guard.expect(node.resolve_topic_name(BY_KEY[peer_key].name),
                 lambda text: follower_differences(description, Description.from_json(text)))
    guard.expect(peer_topic(node, leader_id, 'leader_description'),
                 lambda text: leader_differences(description,
                                                 LeaderDescription.from_json(text)))
    for key in watched:
        guard.watch(node.resolve_topic_name(BY_KEY[key].name))
    guard.watch(peer_topic(node, leader_id, 'leader_odom'))
    return guard
