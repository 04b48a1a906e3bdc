"""The ROS test harness: spin until a condition, an in-process formation with a probe, node
processes started the way a user starts them, and parameter arguments.

Every test module runs in its own ROS_DOMAIN_ID (test/ros/conftest.py) and every node of this
test session under the formation prefix ``PREFIX`` (``/t<pid>``), so concurrent test sessions
on one machine cannot see each other's topics.
"""
from __future__ import annotations

import copy
import json
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from formopt_interfaces.msg import PlannerStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from formopt_ros.ros import qos
from formopt_ros.wire.messages import estimate_values

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = REPO / 'scripts'
#: Cross-process discovery took up to 3.6 s here; every cross-process wait allows far more.
DISCOVERY_TIMEOUT = 30.0
#: The formation prefix of this test session.
PREFIX = f'/t{os.getpid()}'
#: Robot namespace of each node class (the default ids).
ROBOT = {'leader_sim': 'leader', 'follower_sim': 'follower', 'estimator_planner': 'follower'}


def namespace(robot: str) -> str:
    """A robot's namespace in this session, e.g. '/t123/follower'."""
    return f'{PREFIX}/{robot}'


def topic(robot: str, name: str) -> str:
    """A robot's topic in this session, e.g. '/t123/follower/estimate'."""
    return f'{namespace(robot)}/{name}'


def parameter_args(params: dict[str, Any]) -> list[str]:
    """-p name:=value ... for every parameter (bool, number, str, list)."""
    args: list[str] = []
    for name, value in params.items():
        text = str(value).lower() if isinstance(value, bool) else \
            json.dumps(value) if isinstance(value, list) else str(value)
        args += ['-p', f'{name}:={text}']
    return args


def remap_args(nodes: dict[str, str] | None = None) -> list[str]:
    """Node-specific namespace remaps: node name -> robot (default: ROBOT) under PREFIX."""
    args: list[str] = []
    for node, robot in (nodes or ROBOT).items():
        args += ['-r', f'{node}:__ns:={namespace(robot)}']
    return args


def params_file(path: Path, sections: dict[str, dict[str, Any]]) -> Path:
    """A parameters file: node name ('*' for every node) -> values."""
    path.write_text(json.dumps({f'/**/{node}' if node != '*' else '/**':
                                {'ros__parameters': values}
                                for node, values in sections.items()}))
    return path


def spin_until(executor: SingleThreadedExecutor, condition: Callable[[], bool],
               timeout: float, step: Callable[[], None] | None = None) -> bool:
    """Spin until condition() holds (True) or timeout s pass (False); step() after each round."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
        if step is not None:
            step()
    return True


def tap(publisher: Any, sink: list[Any]) -> None:
    """Keep a copy of every message the publisher sends."""
    original = publisher.publish

    def publish(msg: Any) -> None:
        sink.append(copy.deepcopy(msg))
        original(msg)

    publisher.publish = publish


class Probe(Node):
    """Test subscriber: every estimate (x, P) and status message of one follower, in order."""

    def __init__(self, robot: str = 'follower') -> None:
        super().__init__('test_probe')
        self.estimates: list[tuple[Any, Any]] = []
        self.statuses: list[PlannerStatus] = []
        self.create_subscription(PoseWithCovarianceStamped, topic(robot, 'estimate'),
                                 lambda msg: self.estimates.append(estimate_values(msg)),
                                 qos.SUBSCRIBED)
        self.create_subscription(PlannerStatus, topic(robot, 'status'), self.statuses.append,
                                 qos.SUBSCRIBED)


class Formation:
    """leader_sim, follower_sim (optional), estimator_planner and a Probe in this process.

    ``published`` holds a copy of every message the nodes published, per topic.
    """

    def __init__(self, follower: bool = True) -> None:
        from formopt_ros.ros.nodes.estimator_planner import EstimatorPlannerNode
        from formopt_ros.ros.nodes.follower_sim import FollowerSim
        from formopt_ros.ros.nodes.leader_sim import LeaderSim
        self.executor = SingleThreadedExecutor()
        self.probe = Probe()
        self.leader = LeaderSim()
        self.follower = FollowerSim() if follower else None
        self.estimator = EstimatorPlannerNode()
        self.nodes = [n for n in (self.probe, self.leader, self.follower, self.estimator) if n]
        for node in self.nodes:
            self.executor.add_node(node)
        self.publishers = [self.leader.odom_pub, self.estimator.estimate_pub,
                           self.estimator.waypoint_pub, self.estimator.status_pub]
        if self.follower is not None:
            self.publishers += [self.follower.odom_pub, self.follower.meas_pub,
                                self.follower.truth_pub]
        self.published: dict[str, list[Any]] = {}
        for publisher in self.publishers:
            tap(publisher, self.published.setdefault(publisher.topic_name, []))
        self.published[self.estimator.description_pub.topic_name] = [
            self.estimator.description_message]

    def total(self) -> int:
        """Messages published so far, all topics."""
        return sum(len(v) for v in self.published.values())

    def matched(self, subscriber_node: str) -> bool:
        """True when the node ``subscriber_node`` subscribes to every topic of the formation
        and every publisher has matched every subscriber the graph shows."""
        for pub in self.publishers:
            infos = self.leader.get_subscriptions_info_by_topic(pub.topic_name)
            if not any(info.node_name == subscriber_node for info in infos) or \
                    pub.get_subscription_count() < len(infos):
                return False
        return True

    def spin_until(self, condition: Callable[[], bool], timeout: float,
                   step: Callable[[], None] | None = None) -> bool:
        """Spin the nodes until condition() holds (True) or timeout s pass (False)."""
        return spin_until(self.executor, condition, timeout, step)

    def run(self, timeout: float, step: Callable[[], None] | None = None) -> bool:
        """Spin until the estimator finished and the probe has its last status."""
        def done() -> bool:
            return self.estimator.finished and \
                len(self.probe.statuses) >= self.estimator.session.step
        return self.spin_until(done, timeout, step)

    def destroy(self) -> None:
        """Close and destroy every node."""
        for node in self.nodes:
            if hasattr(node, 'close'):
                node.close()
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()


class NodeProcess:
    """A node started as a subprocess through scripts/<node>.sh, stderr read line by line."""

    def __init__(self, node: str, params: dict[str, Any] | None = None,
                 robot: str | None = None, extra: list[str] | None = None) -> None:
        self.node = node
        robot = ROBOT.get(node) if robot is None else robot
        remap = ['-r', f'__ns:={namespace(robot)}'] if robot else ['-r', f'__ns:={PREFIX}']
        self.process = subprocess.Popen(
            [str(SCRIPTS / f'{node}.sh'), *remap, *parameter_args(params or {}),
             *(extra or [])],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ),
            start_new_session=True)
        self.lines: list[str] = []
        self.stdout = ''
        self._changed = threading.Condition()
        self._readers = [threading.Thread(target=self._read_stderr, daemon=True),
                         threading.Thread(target=self._read_stdout, daemon=True)]
        for reader in self._readers:
            reader.start()

    def _read_stderr(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def _read_stdout(self) -> None:
        assert self.process.stdout is not None
        self.stdout = self.process.stdout.read()

    @property
    def stderr(self) -> str:
        """stderr so far (all of it after wait())."""
        with self._changed:
            return ''.join(self.lines)

    def wait_for_line(self, pattern: str, timeout: float = DISCOVERY_TIMEOUT) -> bool:
        """Block until a stderr line matches pattern (True), the process ends or timeout."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._changed:
            while not any(regex.search(line) for line in self.lines):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.process.poll() is not None
                                      and not self._readers[0].is_alive()):
                    return False
                self._changed.wait(timeout=min(remaining, 0.5))
        return True

    def wait(self, timeout: float = 30.0) -> int:
        """Exit code; kills the process group if it does not end within timeout s."""
        try:
            code = self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        for reader in self._readers:
            reader.join(timeout=5.0)
        return code

    def signal(self, signum: int) -> None:
        """Send signum to the node process."""
        self.process.send_signal(signum)

    def kill(self) -> None:
        """SIGKILL the whole process group (the node and anything it started)."""
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=10.0)


def init(params: dict[str, Any], extra: list[str] | None = None) -> None:
    """rclpy.init with the parameters (every node) and this session's namespaces."""
    rclpy.init(args=['--ros-args', *parameter_args(params), *remap_args(), *(extra or [])])
