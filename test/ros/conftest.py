"""ROS tests: skipped without ROS; one ROS_DOMAIN_ID per module; fixtures of harness.ros."""
from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

#: ROS_DOMAIN_IDs this folder uses, one per module (or per xdist worker): 30 from
#: $FORMOPT_TEST_DOMAIN_BASE (default 10), so that a shared machine's other ROS users can be
#: kept apart (valid bases: 0-202; ROS domain ids end at 232).
_BASE = os.environ.get('FORMOPT_TEST_DOMAIN_BASE', '10')
if not (_BASE.isdigit() and int(_BASE) <= 202):
    raise pytest.UsageError(f'FORMOPT_TEST_DOMAIN_BASE must be an integer in [0, 202], '
                            f'got {_BASE!r}')
DOMAIN_IDS = range(int(_BASE), int(_BASE) + 30)
HERE = Path(__file__).resolve().parent

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
#: Participants announce every 0.25 s, as with scripts/*.sh (config/fastdds_discovery.xml).
os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(
    Path(__file__).resolve().parents[2] / 'config' / 'fastdds_discovery.xml'))

try:
    import rclpy
    from formopt_interfaces.msg import RunDescription  # noqa: F401  (interfaces built?)

    from harness import ros
    ROS_MISSING = ''
except ImportError as error:       # no ROS 2 here: skip the whole folder, see below
    ROS_MISSING = f'ROS 2 (rclpy, formopt_interfaces) not importable: {error}'


if ROS_MISSING:
    class _SkippedModule(pytest.Module):
        """Stands in for a test module that would fail to import without ROS."""

        def collect(self) -> Any:
            pytest.skip(ROS_MISSING)

    def pytest_pycollect_makemodule(module_path: Path, parent: Any) -> pytest.Module:
        """Collect every module of this folder as skipped, without importing it."""
        return _SkippedModule.from_parent(parent, path=module_path)


def domain_id_for(module_name: str) -> int:
    """A ROS_DOMAIN_ID per xdist worker when parallel, else per test module."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw'):
        return DOMAIN_IDS[int(worker[2:]) % len(DOMAIN_IDS)]
    modules = sorted(path.stem for path in HERE.glob('test_*.py'))
    index = modules.index(module_name) if module_name in modules else 0
    return DOMAIN_IDS[index % len(DOMAIN_IDS)]


@pytest.fixture(autouse=True, scope='module')
def ros_domain(request: pytest.FixtureRequest) -> Iterator[int]:
    """Set ROS_DOMAIN_ID (read at rclpy.init and by child processes) for this module."""
    domain = domain_id_for(request.module.__name__.rsplit('.', 1)[-1])
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('ROS_DOMAIN_ID', str(domain))
        patch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        yield domain


@pytest.fixture
def ros_init() -> Iterator[Callable[..., None]]:
    """init(extra=None): rclpy.init for this process (global ROS arguments); shut down after."""
    yield ros.init
    rclpy.try_shutdown()


@pytest.fixture
def node_process() -> Iterator[Callable[..., 'ros.NodeProcess']]:
    """start(node, params, robot=None) -> NodeProcess; any still running is killed after."""
    started: list[ros.NodeProcess] = []

    def start(node: str, params: dict[str, Any] | None = None, robot: str | None = None,
              extra: list[str] | None = None) -> ros.NodeProcess:
        process = ros.NodeProcess(node, params, robot, extra)
        started.append(process)
        return process
    yield start
    for process in started:
        process.kill()


@pytest.fixture
def formation(ros_init: Callable[..., None]) -> Iterator[Callable[..., 'ros.Formation']]:
    """make(params, **options) -> a Formation (see harness.ros.Formation); destroyed after."""
    made: list[ros.Formation] = []

    def make(params: dict[str, Any], **options: Any) -> ros.Formation:
        if not made:
            ros_init()
        made.append(ros.Formation(params, **options))
        return made[-1]
    yield make
    for item in made:
        item.destroy()
