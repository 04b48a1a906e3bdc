"""QoS profiles of the formation topics (by the kinds of the topic table) and the recorder's
translation between rclpy and rosbag2's QoS vocabulary."""
from __future__ import annotations

from typing import TypeVar

from rclpy.qos import (
    DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_system_default)

from formopt_ros.bag import qos as bag_qos

#: Depth of streaming topics. Volatile, so no late subscriber ever receives this history; it
#: is what a reliable writer keeps for a reader that has not acknowledged yet (a recorder
#: lagging behind a lockstep run at hundreds of steps a second): a reader more than this many
#: messages behind would lose the oldest (KEEP_LAST overwrites), so it is generous.
STREAM_DEPTH = 1000

#: Streaming topics: reliable (lockstep must not drop a message), volatile (a late subscriber
#: such as ``ros2 topic echo`` gets live messages only). Nothing is published before the
#: expected subscribers (and recorders) are matched (ros/gate.py).
STREAM = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: The nodes subscribe with the same profile.
SUBSCRIBED = STREAM
#: The run description: one message that every late subscriber (and every bag) must still get.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: /clock: reliable (rclpy's time source subscribes best effort, which is compatible).
CLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                   reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.VOLATILE)
#: /tf, /tf_static and /diagnostics: tf2's and diagnostic_updater's defaults.
TF = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
TF_STATIC = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: A reader of /tf_static: tf2's static listener keeps 100, so that the latched messages of
#: several publishers (robot_state_publisher, a camera driver) arriving together all stay.
TF_STATIC_READER = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)

#: Sensor streams of real robots (odometry, range, bearing): best effort and volatile like
#: rclpy's qos_profile_sensor_data (which drivers publish with), but a reader history of 100
#: messages instead of 5, so a stall of the subscriber up to 1-2 s at 50-100 Hz loses
#: nothing.
SENSOR = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.VOLATILE)

PROFILES = {'stream': STREAM, 'sensor': SENSOR, 'latched': LATCHED, 'clock': CLOCK, 'tf': TF,
            'tf_static': TF_STATIC, 'diagnostics': DIAGNOSTICS,
            'default': qos_profile_system_default}


def profile(kind: str) -> QoSProfile:
    """The QoS profile of a topic-table QoS kind."""
    return PROFILES[kind]


_E = TypeVar('_E', bag_qos.QosHistory, bag_qos.QosReliability,
             bag_qos.QosDurability, bag_qos.QosLiveliness)


def _member(enum: type[_E], policy: object) -> _E:
    """The rosbags enum member named like an rclpy policy (UNKNOWN when it has no such name)."""
    name = getattr(policy, 'name', str(policy)).upper()
    return enum.__members__.get(name, enum.__members__['UNKNOWN'])


def offered_qos(qos: QoSProfile) -> bag_qos.Qos:
    """A publisher's QoS (from get_publishers_info_by_topic) as rosbag2 stores it."""
    return bag_qos.Qos(
        _member(bag_qos.QosHistory, qos.history), int(qos.depth),
        _member(bag_qos.QosReliability, qos.reliability),
        _member(bag_qos.QosDurability, qos.durability),
        bag_qos.duration(qos.deadline.nanoseconds), bag_qos.duration(qos.lifespan.nanoseconds),
        _member(bag_qos.QosLiveliness, qos.liveliness),
        bag_qos.duration(qos.liveliness_lease_duration.nanoseconds),
        bool(qos.avoid_ros_namespace_conventions))


def adapted(reliable: bool, latched: bool, depth: int = STREAM_DEPTH) -> QoSProfile:
    """A KEEP_LAST profile, reliable or best effort, transient-local or volatile."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


def adapted_to_offers(offers: list[QoSProfile]) -> QoSProfile:
    """Subscription QoS compatible with every offer (rosbag2's adapt_request_to_offers)."""
    reliable = all(p.reliability == ReliabilityPolicy.RELIABLE for p in offers)
    latched = bool(offers) and all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                   for p in offers)
    return adapted(reliable, latched)


def replay_profile(offers: list[bag_qos.Qos]) -> QoSProfile:
    """QoS offered on replay: reliable/latched when every recorded publisher was."""
    reliable = all(q.reliability != bag_qos.QosReliability.BEST_EFFORT for q in offers)
    latched = bool(offers) and all(q.durability == bag_qos.QosDurability.TRANSIENT_LOCAL
                                   for q in offers)
    return adapted(reliable, latched, 1 if latched else STREAM_DEPTH)


def describe(profile: QoSProfile) -> str:
    """'reliable, volatile, keep last 100' (for the docs' tables and --help)."""
    return (f'{profile.reliability.name.lower().replace("_", " ")}, '
            f'{profile.durability.name.lower().replace("_", " ")}, '
            f'keep last {profile.depth}')
