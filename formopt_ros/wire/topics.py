"""The topic table of a formation run: every topic's name, message type, publisher and QoS kind.

Naming: every robot runs in the namespace of its id. The leader's nodes publish in ``/<leader>``
(default ``/leader``), each follower's follower_sim and estimator_planner in ``/<follower>``
(default ``/follower``); names below are relative to that namespace. ``/tf``, ``/clock`` and
``/diagnostics`` are the global ROS conventions.

QoS kinds: 'stream' (reliable, volatile, modest depth: a late subscriber gets live messages
only), 'latched' (reliable, transient local, depth 1: the run descriptions, which a late
subscriber must still get), 'tf', 'tf_static', 'clock' and 'diagnostics' (the ROS conventions
of those topics).

``listeners`` name the formation nodes that subscribe to a topic (per follower for leader
topics): a publisher waits until it has matched them (and the recorders) before a run starts,
so that nothing is published before it can be received.

This module imports nothing from ROS: nodes, the recorder, the offline analysis and the scripts
(``python -m formopt_ros.wire.topics``) all read the same table.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass

DEFAULT_LEADER = 'leader'
DEFAULT_FOLLOWER = 'follower'


@dataclass(frozen=True)
class Topic:
    """One topic of the run.

    Attributes:
        key: short name used in code and counts.
        name: name relative to the publisher's namespace, or absolute ('/tf').
        type: ROS message type 'pkg/msg/Name'.
        publishers: the nodes that publish it.
        qos: QoS kind ('stream', 'latched', 'tf', 'clock', 'diagnostics').
        description: what it carries.
    """

    key: str
    name: str
    type: str
    publishers: tuple[str, ...]
    qos: str
    description: str
    listeners: tuple[str, ...] = ()


LEADER_TOPICS = (
    Topic('leader_odom', 'odom', 'nav_msgs/msg/Odometry', ('leader_sim',), 'stream',
          "the leader's odometry per sub-step (pose in 'odom', twist in the leader frame)",
          ('follower_sim', 'estimator_planner')),
    Topic('leader_description', 'description', 'formopt_interfaces/msg/RunDescription',
          ('leader_sim',), 'latched', "the leader's description (path, dt, followers, run id)",
          ('follower_sim', 'estimator_planner')),
)
FOLLOWER_TOPICS = (
    Topic('follower_odom', 'odom', 'nav_msgs/msg/Odometry', ('follower_sim',), 'stream',
          "the follower's odometry per sub-step: commanded velocities, noise variances",
          ('estimator_planner',)),
    Topic('measurement', 'measurement', 'formopt_interfaces/msg/Measurement', ('follower_sim',),
          'stream', 'one range or bearing measurement per step', ('estimator_planner',)),
    Topic('truth', 'truth', 'geometry_msgs/msg/PoseStamped', ('follower_sim',), 'stream',
          'the true follower pose in the leader frame (evaluation only)',
          ('estimator_planner',)),
    Topic('estimate', 'estimate', 'geometry_msgs/msg/PoseWithCovarianceStamped',
          ('estimator_planner',), 'stream', 'the EKF estimate of the pose in the leader frame'),
    Topic('waypoint', 'waypoint', 'formopt_interfaces/msg/Waypoint', ('estimator_planner',),
          'stream', 'the next position (leader frame) and the commands that reach it',
          ('leader_sim', 'follower_sim')),
    Topic('status', 'status', 'formopt_interfaces/msg/PlannerStatus', ('estimator_planner',),
          'stream', 'progress, cost and input counters after each step and every second'),
    Topic('markers', 'markers', 'visualization_msgs/msg/MarkerArray', ('estimator_planner',),
          'stream', 'slot, feasible disc, chosen waypoint and 3-sigma ellipse (leader frame)'),
    Topic('description', 'description', 'formopt_interfaces/msg/RunDescription',
          ('estimator_planner',), 'latched', 'the run description (scenario, strategy, seed)',
          ('follower_sim', 'leader_sim')),
    Topic('sim_description', 'sim_description', 'formopt_interfaces/msg/RunDescription',
          ('follower_sim',), 'latched', "follower_sim's description of the same run (the "
          'scenario handshake compares it with the estimator\'s)', ('estimator_planner',)),
)
GLOBAL_TOPICS = (
    Topic('tf', '/tf', 'tf2_msgs/msg/TFMessage',
          ('leader_sim', 'follower_sim', 'estimator_planner'), 'tf',
          'odom -> leader, leader -> <follower>/estimate and <follower>/truth, '
          '<follower>/odom -> <follower>'),
    Topic('tf_static', '/tf_static', 'tf2_msgs/msg/TFMessage', ('follower_sim',), 'tf_static',
          "odom -> <follower>/odom: where each follower's odometry frame starts"),
    Topic('clock', '/clock', 'rosgraph_msgs/msg/Clock', ('leader_sim',), 'clock',
          'lockstep simulated time (use_sim_time:=true makes node clocks follow it)'),
    Topic('diagnostics', '/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray',
          ('estimator_planner',), 'diagnostics', 'OK / WARN / ERROR of every estimator, 1 Hz'),
)
BY_KEY = {t.key: t for t in LEADER_TOPICS + FOLLOWER_TOPICS + GLOBAL_TOPICS}


#: The frames. Every robot's odometry starts in 'odom'; the leader's body frame is its id.
ODOM_FRAME = 'odom'


def follower_frames(follower_id: str) -> dict[str, str]:
    """A simulated follower's frames: its odometry frame, its body, its true and estimated
    poses."""
    return {'odom': f'{follower_id}/odom', 'body': follower_id,
            'truth': f'{follower_id}/truth', 'estimate': f'{follower_id}/estimate'}


def real_frames(robot_id: str, sensor: str) -> dict[str, str]:
    """The frames of a follower on the real-robot interfaces: its base and its sensor (a UWB
    radio for 'range', a camera for 'bearing')."""
    return {'base': f'{robot_id}/base_link',
            'sensor': f"{robot_id}/{'uwb' if sensor == 'range' else 'camera'}"}


def resolve(namespace: str, topic: Topic) -> str:
    """Absolute name of ``topic`` published in ``namespace`` (a robot id or '/id')."""
    if topic.name.startswith('/'):
        return topic.name
    return '/' + '/'.join(part for part in (namespace.strip('/'), topic.name) if part)


def leader_topic(key: str, leader: str = DEFAULT_LEADER) -> str:
    """Absolute name of a leader topic, e.g. ``leader_topic('leader_odom') == '/leader/odom'``."""
    return resolve(leader, BY_KEY[key])


def follower_topic(key: str, follower: str = DEFAULT_FOLLOWER) -> str:
    """Absolute name of a follower topic, e.g. '/follower/estimate'."""
    return resolve(follower, BY_KEY[key])


def formation_topics(leader: str = DEFAULT_LEADER,
                     followers: tuple[str, ...] = (DEFAULT_FOLLOWER,),
                     prefix: str = '') -> dict[str, str]:
    """Absolute name -> message type of every topic of a formation (what a bag records); robot
    namespaces under ``prefix`` (e.g. '/run7'), the global topics as they are."""
    out = {resolve(f'{prefix}/{leader}', t): t.type for t in LEADER_TOPICS}
    for follower in followers:
        out.update({resolve(f'{prefix}/{follower}', t): t.type for t in FOLLOWER_TOPICS})
    out.update({t.name: t.type for t in GLOBAL_TOPICS})
    return out


def split_follower_topic(name: str) -> tuple[str, str] | None:
    """('/f1' namespace, key) of a recorded follower topic name, or None if it is not one."""
    namespace, _, last = name.rpartition('/')
    for topic in FOLLOWER_TOPICS:
        if topic.name == last and namespace:
            return namespace, topic.key
    return None


def main(argv: list[str] | None = None) -> int:
    """``python -m formopt_ros.wire.topics [--leader L] [--followers F ...] [--json]``."""
    parser = argparse.ArgumentParser(prog='python -m formopt_ros.wire.topics',
                                     description='Print the topics of a formation run.')
    parser.add_argument('--leader', default=DEFAULT_LEADER, help='leader id (default leader)')
    parser.add_argument('--followers', nargs='+', default=[DEFAULT_FOLLOWER],
                        help='follower ids (default follower)')
    parser.add_argument('--prefix', default='', help="formation namespace prefix, e.g. /run7")
    parser.add_argument('--json', action='store_true', help='print {name: type} as JSON')
    args = parser.parse_args(argv)
    topics = formation_topics(args.leader, tuple(args.followers), args.prefix)
    if args.json:
        print(json.dumps(topics, indent=2))
    else:
        for name, type_name in topics.items():
            print(f'{name} {type_name}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
