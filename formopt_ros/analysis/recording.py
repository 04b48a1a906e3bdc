"""A formation run read back from its bag: the followers, their topics and run descriptions.

The run description is recorded once per follower (its latched ``<follower>/description``
topic). Bags recorded before that topic existed still work: their description is reconstructed
from the recorded messages here, in one place, with the paper's defaults for what the messages
do not say (and ``legacy`` set).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from formopt_ros.bag import Bag, BagError, Record
from formopt_ros.core.model import MEASUREMENT_KINDS
from formopt_ros.core.protocol import Timebase
from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.core.strategies import STRATEGIES, make_strategy
from formopt_ros.wire.description import RunDescription
from formopt_ros.wire.messages import KIND_NAMES, header_ns
from formopt_ros.wire.topics import BY_KEY, DEFAULT_LEADER, resolve, split_follower_topic

#: What to do with a bag of standard messages (odometry, ranges: another robot, a data set, a
#: run on real interfaces), which formopt's own readers cannot take.
STANDARD_HINT = ('standard messages, e.g. from real robots, are re-estimated with: replay BAG '
                 '--offline --topic-map MAP, docs/real_robots.md')


@dataclass
class FollowerRecording:
    """One follower's part of a bag.

    Attributes:
        namespace: its namespace, e.g. '/follower'.
        topics: topic-table key -> recorded topic name.
        description: its run description (recorded, or reconstructed when ``legacy``).
        legacy: True when the bag has no description topic for it.
    """

    namespace: str
    topics: dict[str, str]
    description: RunDescription
    legacy: bool = False

    @property
    def follower_id(self) -> str:
        """The follower's id."""
        return self.description.follower_id


@dataclass
class Recording:
    """A bag of a formation run, its messages decoded on demand (with rosbags, no ROS)."""

    bag: Bag
    leader_topic: str | None
    followers: dict[str, FollowerRecording] = field(default_factory=dict)
    _decoded: dict[str, list[tuple[Record, Any]]] = field(default_factory=dict, repr=False)

    def messages(self, topic: str | None) -> list[tuple[Record, Any]]:
        """(record, message) pairs of a recorded topic in log-time order ([] for None)."""
        if topic is None:
            return []
        if topic not in self._decoded:
            self._decoded[topic] = self.bag.decode(topic)
        return self._decoded[topic]

    def follower_messages(self, follower: FollowerRecording, key: str) -> list[Any]:
        """The decoded messages of one of a follower's topics ([] when not recorded)."""
        return [m for _, m in self.messages(follower.topics.get(key))]

    def follower_estimates(self, follower: FollowerRecording) -> list[tuple[int, Any, Any]]:
        """(step, estimate message, its status message or None) of each recorded estimate, in
        recorded order: the step is the status's of the same stamp, else the estimate's
        position (1-based)."""
        status_of = {header_ns(m): m for m in self.follower_messages(follower, 'status')}
        out = []
        for index, msg in enumerate(self.follower_messages(follower, 'estimate')):
            status = status_of.get(header_ns(msg))
            out.append((int(status.step) if status else index + 1, msg, status))
        return out

    def follower(self, follower_id: str | None = None) -> FollowerRecording:
        """The follower ``follower_id``, or the only one; BagError naming the choices."""
        if follower_id is None:
            if len(self.followers) == 1:
                return next(iter(self.followers.values()))
            raise BagError(f'{self.bag.path}: the bag has {len(self.followers)} followers '
                           f"({', '.join(sorted(self.followers)) or 'none'}); name one")
        if follower_id not in self.followers:
            raise BagError(f'{self.bag.path}: no follower {follower_id!r} in the bag (it has: '
                           f"{', '.join(sorted(self.followers)) or 'none'})")
        return self.followers[follower_id]


def load_recording(bag: Bag) -> Recording:
    """Find the followers of a formation bag and read (or reconstruct) their descriptions."""
    grouped: dict[str, dict[str, str]] = {}
    for topic, channel in bag.channels.items():
        found = split_follower_topic(topic)
        if found is not None and BY_KEY[found[1]].type == channel.type:
            grouped.setdefault(found[0], {})[found[1]] = topic
    recording = Recording(bag, None)
    for namespace, topics in sorted(grouped.items()):
        if not {'estimate', 'status', 'measurement'} & set(topics):
            continue            # the leader (odometry, description): not a follower
        recording.leader_topic = _leader_topic(bag, namespace, DEFAULT_LEADER)
        follower = FollowerRecording(namespace, topics, _placeholder(namespace))
        described = recording.messages(topics.get('description'))
        if described:
            try:
                follower.description = RunDescription.from_json(described[-1][1].description)
            except ValueError as error:
                raise BagError(f'{bag.path}: {topics["description"]}: {error}') from None
        else:
            follower.description = reconstruct_description(recording, follower)
            follower.legacy = True
        recording.followers[follower.follower_id] = follower
    if not recording.followers:
        raise BagError(f'{bag.path}: no follower topics (estimate, status, measurement) in the '
                       f"bag; it has: {', '.join(sorted(bag.channels)) or 'no topics'} "
                       f'({STANDARD_HINT})')
    first = next(iter(recording.followers.values()))
    recording.leader_topic = _leader_topic(bag, first.namespace, first.description.leader_id)
    return recording


def _leader_topic(bag: Bag, follower_namespace: str, leader_id: str) -> str | None:
    """The recorded odometry topic of the leader beside a follower's namespace, if any."""
    name = resolve(f"{follower_namespace.rpartition('/')[0]}/{leader_id}",
                   BY_KEY['leader_odom'])
    channel = bag.channels.get(name)
    return name if channel is not None and channel.type == BY_KEY['leader_odom'].type else None


def _placeholder(namespace: str) -> RunDescription:
    return RunDescription(namespace.strip('/').rpartition('/')[2] or 'follower',
                          Scenario.paper('range'), 'ram')


def reconstruct_description(recording: Recording,
                            follower: FollowerRecording) -> RunDescription:
    """The run description of a bag without one, from its messages (paper defaults otherwise).

    measurement kind: the last status, else the first measurement; dt, slot and r: the first
    waypoint, else the paper's; sigma: the first measurement's variance; odometry noise: the
    follower odometry's twist covariance; the leader: its first odometry (constant velocity);
    strategy: the last status, else the first waypoint (default options); mode: lockstep when
    every measurement lies on the lockstep grid; seed and trial: 0.
    """
    status = recording.follower_messages(follower, 'status')
    waypoints = recording.follower_messages(follower, 'waypoint')
    meas = recording.follower_messages(follower, 'measurement')
    odom = recording.follower_messages(follower, 'follower_odom')
    leader = [m for _, m in recording.messages(recording.leader_topic)]
    kind = (status[-1].measurement_kind if status else
            KIND_NAMES.get(int(meas[0].kind)) if meas else None)
    if kind not in MEASUREMENT_KINDS:
        raise BagError(f'{recording.bag.path}: {follower.namespace} has no formopt '
                       'measurement or status messages to tell its measurement kind from '
                       f'({STANDARD_HINT})')
    base = Scenario.paper(kind)
    dt = waypoints[0].substep_duration if waypoints else base.dt
    p_o = ((waypoints[0].formation_slot.x, waypoints[0].formation_slot.y) if waypoints
           else base.p_o)
    r = waypoints[0].radius if waypoints else 0.1 * math.hypot(*p_o)
    sigma = math.sqrt(meas[0].variance) if meas and meas[0].variance > 0 else base.sigma
    sigma_v = math.sqrt(odom[0].twist.covariance[0]) if odom else base.sigma_v
    sigma_omega = math.sqrt(odom[0].twist.covariance[35]) if odom else base.sigma_omega
    path = (LeaderPath.constant(leader[0].twist.twist.linear.x, leader[0].twist.twist.angular.z)
            if leader else base.leader)
    scenario = Scenario.paper(kind, p_o=p_o, r=r, sigma=sigma, leader=path, dt=dt,
                              sigma_v=sigma_v, sigma_omega=sigma_omega)
    strategy = (status[-1].strategy if status else
                waypoints[0].strategy if waypoints else 'ram')
    if strategy not in STRATEGIES:
        raise BagError(f'{recording.bag.path}: unknown strategy {strategy!r} in '
                       f'{follower.namespace}')
    timebase = Timebase.from_dt(dt)
    lockstep = all(header_ns(m) == timebase.measurement_stamp(int(m.step)) for m in meas)
    follower_id = meas[0].follower_id if meas else follower.namespace.strip('/')
    leader_id = leader[0].child_frame_id if leader else DEFAULT_LEADER
    return RunDescription(follower_id, scenario, strategy,
                          dict(make_strategy(strategy).settings), 0, 0,
                          'lockstep' if lockstep else 'realtime', 0, '', leader_id)


def with_overrides(description: RunDescription, **overrides: Any) -> RunDescription:
    """The description with the given fields replaced (None values are ignored); a strategy
    or options given replace the recorded mid-run strategy changes too (one strategy)."""
    given = {k: v for k, v in overrides.items() if v is not None}
    if 'strategy' in given or 'options' in given:
        given.setdefault('strategy_changes', ())
    return replace(description, **given)
