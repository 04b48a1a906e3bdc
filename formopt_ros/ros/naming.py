"""Robot ids and peer topics from node namespaces.

Every robot's nodes run in the namespace of its id, optionally under a formation prefix:
``/leader`` and ``/follower`` by default, ``/run7/leader`` and ``/run7/f1`` when a run is
started under ``/run7``. A node finds its peers' topics beside its own namespace, so several
formations can share one ROS domain under different prefixes.
"""
from __future__ import annotations

from rclpy.node import Node

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.formation import check_id
from formopt_ros.ros.params import ParameterError
from formopt_ros.wire.topics import BY_KEY, resolve


def robot_id(node: Node, default: str) -> str:
    """The last part of the node's namespace ('/run7/f1' -> 'f1'), or ``default`` at the root;
    ParameterError when that part is not a valid id (e.g. a reserved frame name)."""
    value = node.get_namespace().rstrip('/').rpartition('/')[2] or default
    try:
        return check_id('the robot id taken from the namespace', value)
    except InvalidInput as error:
        raise ParameterError(str(error)) from None


def formation_prefix(node: Node) -> str:
    """The namespace above the node's robot namespace ('/run7/f1' -> '/run7', '/f1' -> '')."""
    return node.get_namespace().rstrip('/').rpartition('/')[0]


def peer_topic(node: Node, robot: str, key: str) -> str:
    """Absolute name of another robot's topic in the node's formation, e.g. '/leader/odom'."""
    return resolve(f'{formation_prefix(node)}/{robot}', BY_KEY[key])
