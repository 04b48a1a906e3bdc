"""ROS test setup: per-module domain id, localhost discovery, skip without rclpy, helpers."""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = REPO / 'scripts'
HERE = Path(__file__).resolve().parent
#: ROS_DOMAIN_IDs this folder may use (other suites use 20-39).
DOMAIN_IDS = range(10, 20)
#: Cross-process discovery took up to 3.6 s here; every cross-process wait allows far more.
DISCOVERY_TIMEOUT = 30.0

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

try:
    import rclpy
    from formopt_interfaces.msg import PlannerStatus
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from formopt_ros import conversions
    from formopt_ros.nodes.common import RELIABLE, TOPICS
    ROS_MISSING = ''
except ImportError as error:       # no ROS 2 here: skip the whole folder, see below
    ROS_MISSING = f'ROS 2 (rclpy, formopt_interfaces) not importable: {error}'


if ROS_MISSING:
    class _SkippedModule(pytest.Module):
        """Stands in for a test module that would fail to import without ROS."""

        def collect(self):
            pytest.skip(ROS_MISSING)

    def pytest_pycollect_makemodule(module_path: Path, parent) -> pytest.Module:
        """Collect every module of this folder as skipped, without importing it."""
        return _SkippedModule.from_parent(parent, path=module_path)

    def pytest_sessionfinish(session, exitstatus) -> None:
        """A session that only skipped this folder is a success, not 'no tests ran'."""
        if exitstatus == pytest.ExitCode.NO_TESTS_COLLECTED:
            session.exitstatus = pytest.ExitCode.OK


def domain_id_for(module_name: str) -> int:
    """A ROS_DOMAIN_ID in 10-19: per xdist worker when parallel, else per test module."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw'):
        return DOMAIN_IDS[int(worker[2:]) % len(DOMAIN_IDS)]
    modules = sorted(path.stem for path in HERE.glob('test_*.py'))
    index = modules.index(module_name) if module_name in modules else 0
    return DOMAIN_IDS[index % len(DOMAIN_IDS)]


@pytest.fixture(autouse=True, scope='module')
def ros_domain(request) -> Iterator[int]:
    """Set ROS_DOMAIN_ID (read at rclpy.init and by child processes) for this module."""
    domain = domain_id_for(request.module.__name__.rsplit('.', 1)[-1])
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('ROS_DOMAIN_ID', str(domain))
        patch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        yield domain


@contextlib.contextmanager
def domain_environment(domain_id: str, repo: Path) -> Iterator[dict[str, str]]:
    """Set ROS_DOMAIN_ID and localhost discovery for in-process nodes and children, then
    restore; yields the environment for subprocesses (with the repo on PYTHONPATH)."""
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    os.environ.update(ROS_DOMAIN_ID=domain_id, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    try:
        yield dict(os.environ, PYTHONPATH=str(repo))
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def ros_args(params: dict[str, object]) -> list[str]:
    """--ros-args -p name:=value ... for every parameter (bool, number, str, list)."""
    args = ['--ros-args']
    for name, value in params.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        args += ['-p', f'{name}:={text}']
    return args


@pytest.fixture
def ros_init() -> Iterator[Callable[[dict[str, object]], None]]:
    """init(params): rclpy.init with the parameters for every node of this process.

    Nodes created in the test must be destroyed by it or are destroyed with the context.
    """
    def init(params: dict[str, object]) -> None:
        rclpy.init(args=ros_args(params))
    yield init
    rclpy.try_shutdown()


def spin_until(executor: 'SingleThreadedExecutor', condition: Callable[[], bool],
               timeout: float, step: Callable[[], None] | None = None) -> bool:
    """Spin until condition() holds or timeout s pass; step() runs after each callback."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
        if step is not None:
            step()
    return True


class Probe(Node if not ROS_MISSING else object):   # object: the folder is skipped then
    """Test subscriber: every estimate (x, P) and status message of the run, in order."""

    def __init__(self) -> None:
        super().__init__('test_probe')
        self.estimates: list[tuple] = []
        self.statuses: list = []
        self.create_subscription(PoseWithCovarianceStamped, TOPICS['estimate'],
                                 lambda msg: self.estimates.append(
                                     conversions.estimate_values(msg)), RELIABLE)
        self.create_subscription(PlannerStatus, TOPICS['status'], self.statuses.append,
                                 RELIABLE)


class Formation:
    """leader_sim, follower_sim, estimator_planner and a Probe in one process, one executor."""

    def __init__(self, follower: bool = True) -> None:
        from formopt_ros.nodes.estimator_planner import EstimatorPlannerNode
        from formopt_ros.nodes.follower_sim import FollowerSim
        from formopt_ros.nodes.leader_sim import LeaderSim
        self.executor = SingleThreadedExecutor()
        self.probe = Probe()
        self.leader = LeaderSim()
        self.follower = FollowerSim() if follower else None
        self.estimator = EstimatorPlannerNode()
        self.nodes = [n for n in (self.probe, self.leader, self.follower, self.estimator) if n]
        for node in self.nodes:
            self.executor.add_node(node)

    def spin_until(self, condition: Callable[[], bool], timeout: float,
                   step: Callable[[], None] | None = None) -> bool:
        """Spin the nodes until condition() holds (True) or timeout s pass (False)."""
        return spin_until(self.executor, condition, timeout, step)

    def run(self, timeout: float, step: Callable[[], None] | None = None) -> bool:
        """Spin until the estimator finished and the probe has its last status."""
        def done() -> bool:
            return self.estimator.finished and len(self.probe.statuses) >= self.estimator.step
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

    def __init__(self, node: str, params: dict[str, object] | None = None) -> None:
        self.node = node
        self.process = subprocess.Popen(
            [str(SCRIPTS / f'{node}.sh'), *ros_args(params or {})[1:]],
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
        for line in self.process.stderr:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def _read_stdout(self) -> None:
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


@pytest.fixture
def node_process() -> Iterator[Callable[..., NodeProcess]]:
    """start(node, params) -> NodeProcess; every process still running is killed at the end."""
    started: list[NodeProcess] = []

    def start(node: str, params: dict[str, object] | None = None) -> NodeProcess:
        process = NodeProcess(node, params)
        started.append(process)
        return process
    yield start
    for process in started:
        process.kill()


@pytest.fixture
def formation(ros_init) -> Iterator[Callable[..., Formation]]:
    """make(params, follower=True) -> Formation after rclpy.init(params); destroyed after."""
    made: list[Formation] = []

    def make(params: dict[str, object], follower: bool = True) -> Formation:
        ros_init(params)
        made.append(Formation(follower))
        return made[-1]
    yield make
    for item in made:
        item.destroy()


def pytest_configure(config) -> None:
    """rosidl's parser (lark) imports the deprecated sre modules; not our warning."""
    config.addinivalue_line('filterwarnings', "ignore:module 'sre_:DeprecationWarning")
