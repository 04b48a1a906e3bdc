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
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from formopt_ros.core.scenario import Scenario
from formopt_ros.ros import qos
from formopt_ros.ros.conversions import message_class
from formopt_ros.wire.messages import estimate_values
from formopt_ros.wire.topics import formation_topics

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = REPO / 'scripts'
#: Cross-process discovery took up to 3.6 s here; every cross-process wait allows far more.
DISCOVERY_TIMEOUT = 30.0
#: The formation prefix of this test session.
PREFIX = f'/t{os.getpid()}'
#: Formation nodes wait for the test's probe as they would for a recorder.
WITH_PROBE = {'recorders': 1}
#: Robot namespace of each node class (the default ids).
ROBOT = {'leader_sim': 'leader', 'follower_sim': 'follower', 'estimator_planner': 'follower'}


def node_scenario(kind: str, **overrides: Any) -> Scenario:
    """The scenario of nodes started with default parameters: the paper's Sec. V settings
    with the nodes' default 'exact' kinematics (Scenario.paper keeps the paper's 'euler')."""
    return Scenario.paper(kind, **{'kinematics': 'exact', **overrides})


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
    """Test subscriber of every topic of the formation, like a recorder (the nodes are started
    with recorders:=1 and wait for it): every estimate (x, P) and status of each follower in
    order, and a count of every other topic's messages.
    """

    def __init__(self, followers: tuple[str, ...] = ('follower',)) -> None:
        super().__init__('test_probe')
        self.estimates: list[tuple[Any, Any]] = []
        self.statuses: list[PlannerStatus] = []
        self.by_follower: dict[str, dict[str, list[Any]]] = {
            f: {'estimates': [], 'statuses': []} for f in followers}
        self.counts: dict[str, int] = {}
        for name, type_name in formation_topics('leader', followers, PREFIX).items():
            if name.endswith('description') or name == '/tf_static':
                continue                             # latched: not part of the start gate
            cls = message_class(type_name)
            self.counts[name] = 0
            self.create_subscription(cls, name, lambda msg, n=name: self._on(n, msg),
                                     qos.SUBSCRIBED)

    def _on(self, name: str, msg: Any) -> None:
        self.counts[name] += 1
        robot, _, kind = name[len(PREFIX) + 1:].rpartition('/')
        if kind == 'estimate':
            self.by_follower[robot]['estimates'].append(estimate_values(msg))
            if robot == next(iter(self.by_follower)):
                self.estimates.append(estimate_values(msg))
        elif kind == 'status':
            self.by_follower[robot]['statuses'].append(msg)
            if robot == next(iter(self.by_follower)):
                self.statuses.append(msg)

    def step_statuses(self, follower: str | None = None) -> list[PlannerStatus]:
        """The statuses published after steps (the periodic ones while stalled left out)."""
        statuses = self.by_follower[follower or next(iter(self.by_follower))]['statuses']
        out: list[PlannerStatus] = []
        for status in statuses:
            if status.step > 0 and (not out or status.step > out[-1].step):
                out.append(status)
        return out


def declared(node: str, params: dict[str, Any]) -> dict[str, Any]:
    """The parameters among ``params`` that formation node ``node`` declares (a node refuses
    others)."""
    import importlib
    names = {spec.name for spec in importlib.import_module(
        f'formopt_ros.ros.nodes.{node}').PARAMS} | {'use_sim_time'}
    return {k: v for k, v in params.items() if k in names}


def node_args(node: str, robot: str, params: dict[str, Any]) -> list[str]:
    """Node-local ROS arguments: the robot's namespace under PREFIX and the parameters the node
    declares (a formation node also waits for the probe: recorders:=1 unless given)."""
    values = declared(node, {**WITH_PROBE, **params})
    return ['--ros-args', '-r', f'__ns:={namespace(robot)}', *parameter_args(values)]


class Formation:
    """leader_sim, per follower a follower_sim (optional) and an estimator_planner, and a Probe,
    all in this process on one executor, each node with its own arguments.

    Args:
        params: parameters for every node (each gets those it declares).
        followers: follower ids (their namespaces under PREFIX).
        follower: create the follower_sim nodes (False: the test starts them elsewhere).
        per_follower: id -> extra parameters of that follower's nodes.
        per_node: node name ('leader_sim', 'follower_sim', 'estimator_planner') -> extra
            parameters of every node of that kind.

    ``published`` holds a copy of every message the nodes published, per topic.
    """

    def __init__(self, params: dict[str, Any], followers: tuple[str, ...] = ('follower',),
                 follower: bool = True,
                 per_follower: dict[str, dict[str, Any]] | None = None,
                 per_node: dict[str, dict[str, Any]] | None = None) -> None:
        per_follower, per_node = per_follower or {}, per_node or {}
        self.executor = SingleThreadedExecutor()
        self.probe = Probe(followers)
        self.formation_topics = set(formation_topics('leader', followers, PREFIX))
        self.published: dict[str, list[Any]] = {}
        self.publishers: list[Any] = []          # the formation nodes' formation publishers
        self.args: dict[tuple[str, str], list[str]] = {}
        leader_params = params if 'formation_file' in params else {
            'followers': list(followers), **params}
        self.leader = self._make('leader_sim', 'leader', {**leader_params,
                                                          **per_node.get('leader_sim', {})})
        self.followers = {f: self._make('follower_sim', f, {
            **params, **per_follower.get(f, {}), **per_node.get('follower_sim', {})})
            for f in followers} if follower else {}
        self.estimators = {f: self._make('estimator_planner', f, {
            **params, **per_follower.get(f, {}), **per_node.get('estimator_planner', {})})
            for f in followers}
        self.follower = next(iter(self.followers.values()), None)
        self.estimator = next(iter(self.estimators.values()))
        self.nodes = [self.probe, self.leader, *self.followers.values(),
                      *self.estimators.values()]
        self.executor.add_node(self.probe)

    def _make(self, kind: str, robot: str, params: dict[str, Any],
              extra: list[str] | None = None) -> Any:
        """Create a formation node, add it to the executor and tap its publications."""
        import importlib
        module = importlib.import_module(f'formopt_ros.ros.nodes.{kind}')
        cls = {'leader_sim': 'LeaderSim', 'follower_sim': 'FollowerSim',
               'estimator_planner': 'EstimatorPlannerNode'}[kind]
        args = self.args.setdefault((kind, robot), node_args(kind, robot, params))
        node = getattr(module, cls)(args + (extra or []))
        self.executor.add_node(node)
        latched = {node.guard.description_pub: node.guard.description_message}
        if kind == 'follower_sim':
            latched[node.tf_static_pub] = node.tf_static_message
        for publisher in node.publishers:
            if publisher.topic_name in self.formation_topics:
                self.publishers.append(publisher)
                sink = self.published.setdefault(publisher.topic_name, [])
                if publisher in latched:
                    sink.append(latched[publisher])
                tap(publisher, sink)
        return node

    def restart(self, kind: str, robot: str = 'follower', down: float = 0.0,
                extra: list[str] | None = None) -> Any:
        """Kill a node the hard way (no close(): no summary, no final checkpoint), spin ``down``
        s without it, start it again with the same arguments (plus ``extra``); the new node."""
        old = {'leader_sim': lambda: self.leader, 'follower_sim': lambda: self.followers[robot],
               'estimator_planner': lambda: self.estimators[robot]}[kind]()
        self.executor.remove_node(old)
        self.publishers = [p for p in self.publishers if p not in old.publishers]
        old.destroy_node()
        self.nodes.remove(old)
        if down:
            self.spin_until(lambda: False, down)
        node = self._make(kind, robot, {}, extra)
        self.nodes.append(node)
        if kind == 'leader_sim':
            self.leader = node
        elif kind == 'follower_sim':
            self.followers[robot] = node
            self.follower = next(iter(self.followers.values()))
        else:
            self.estimators[robot] = node
            self.estimator = next(iter(self.estimators.values()))
        return node

    def total(self) -> int:
        """Messages published so far, all topics."""
        return sum(len(v) for v in self.published.values())

    def spin_until(self, condition: Callable[[], bool], timeout: float,
                   step: Callable[[], None] | None = None) -> bool:
        """Spin the nodes until condition() holds (True) or timeout s pass (False)."""
        return spin_until(self.executor, condition, timeout, step)

    def run(self, timeout: float, step: Callable[[], None] | None = None) -> bool:
        """Spin until every estimator finished and the probe has its last step status."""
        def done() -> bool:
            for follower, estimator in self.estimators.items():
                statuses = self.probe.step_statuses(follower)
                if not (estimator.finished and statuses
                        and statuses[-1].step >= estimator.session.step):
                    return False
            return True
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
        if node in ROBOT:
            params = declared(node, {**WITH_PROBE, **(params or {})})
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


def init(extra: list[str] | None = None) -> None:
    """rclpy.init for this process (the formation nodes get their arguments one by one)."""
    rclpy.init(args=['--ros-args', *(extra or [])] if extra else None)


def set_parameters(run: Any, node: Any, values: dict[str, Any],
                   atomically: bool = False) -> list[Any]:
    """Set parameters through the node's own service, as ros2 param set does (one result per
    parameter; ``atomically``: all or none, one result)."""
    client = AsyncParameterClient(run.probe, node.get_fully_qualified_name())
    assert run.spin_until(client.services_are_ready, 10.0)
    parameters = [Parameter(k, value=v) for k, v in values.items()]
    future = client.set_parameters_atomically(parameters) if atomically else \
        client.set_parameters(parameters)
    assert run.spin_until(future.done, 10.0)
    result = future.result()
    return [result.result] if atomically else list(result.results)
