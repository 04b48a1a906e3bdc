"""The layers of the package: each imports only the layers below it and its allowed libraries;
nothing below ros/ (nor the commands that need no ROS) loads rclpy or a ROS message package."""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'formopt_ros'
#: layer -> (project layers it may import, third-party libraries it may import)
RULES: dict[str, tuple[set[str], set[str]]] = {
    'core': ({'core'}, {'numpy', 'scipy'}),
    'wire': ({'core', 'wire'}, {'numpy', 'yaml'}),
    'bag': ({'bag'}, {'mcap', 'rosbags', 'yaml'}),
    'analysis': ({'core', 'wire', 'bag', 'analysis'},
                 {'numpy', 'scipy', 'matplotlib', 'casadi', 'dask'}),
    'ros': ({'core', 'wire', 'bag', 'ros'}, {'numpy', 'yaml', 'rclpy', 'rcl_interfaces',
                                             'builtin_interfaces', 'std_msgs', 'geometry_msgs',
                                             'nav_msgs', 'formopt_interfaces', 'tf2_msgs',
                                             'rosgraph_msgs', 'visualization_msgs',
                                             'diagnostic_msgs', 'sensor_msgs'}),
    'cli': ({'core', 'wire', 'bag', 'analysis', 'ros', 'cli'},
            {'numpy', 'tqdm', 'rclpy', 'formopt_interfaces', 'dask'}),
}
#: Modules that must import without any ROS package loaded.
ROS_FREE = ['core', 'wire', 'bag', 'analysis', 'cli.montecarlo', 'cli.bench', 'cli.report',
            'cli.bag', 'cli.replay', 'cli.bench_ros', 'cli.periodic', 'cli.sweep']
ROS_PACKAGES = ('rclpy', 'rosidl_runtime_py', 'rpyutils', 'std_msgs', 'geometry_msgs',
                'nav_msgs', 'formopt_interfaces', 'builtin_interfaces', 'rcl_interfaces',
                'tf2_msgs', 'rosgraph_msgs', 'visualization_msgs', 'diagnostic_msgs')

IMPORT_ALL = '''
import importlib, json, pkgutil, sys
names = []
for name in sys.argv[1:]:
    module = importlib.import_module('formopt_ros.' + name)
    names.append(module.__name__)
    for info in pkgutil.walk_packages(getattr(module, '__path__', []), module.__name__ + '.'):
        importlib.import_module(info.name)
        names.append(info.name)
print(json.dumps({'modules': names, 'ros': sorted(m for m in sys.modules
                                                  if m.split('.')[0] in %r)}))
''' % (ROS_PACKAGES,)


def layer_files(layer: str) -> list[Path]:
    """Every Python file of a layer."""
    files = sorted((PACKAGE / layer).rglob('*.py'))
    assert files, f'no Python files under {PACKAGE / layer}'
    return files


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement of a file (relative resolved)."""
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    parts = list(path.relative_to(REPO).with_suffix('').parts)
    package = '.'.join(parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')[:len(package.split('.')) - (node.level - 1)]
                found.append((node.lineno, '.'.join(base + ([node.module] if node.module
                                                            else []))))
            elif node.module == 'formopt_ros':       # from formopt_ros import bag
                found.extend((node.lineno, f'formopt_ros.{alias.name}') for alias in node.names)
            else:
                found.append((node.lineno, node.module or ''))
    return found


def allowed(layer: str, name: str) -> bool:
    """True when ``layer`` may import module ``name``."""
    layers, libraries = RULES[layer]
    top = name.split('.')[0]
    if name == 'formopt_ros.one_blas_thread':       # the package root, below every layer
        return True
    if top == 'formopt_ros':
        below = name.split('.')[1] if '.' in name else ''
        return below in layers
    return top in sys.stdlib_module_names or top in libraries or top == '__future__'


@pytest.mark.parametrize('layer', sorted(RULES))
def test_layer_imports_only_what_is_below(layer: str) -> None:
    """Each file imports stdlib, its allowed libraries and the layers below (ast check)."""
    bad = [(str(path.relative_to(REPO)), line, name) for path in layer_files(layer)
           for line, name in imported_modules(path) if not allowed(layer, name)]
    assert not bad, f'disallowed imports: {bad}'


def test_importing_the_ros_free_layers_loads_no_ros() -> None:
    """A fresh interpreter imports core, wire, bag, analysis and the ROS-free commands (every
    submodule) without loading rclpy or any ROS message package."""
    result = subprocess.run([sys.executable, '-c', IMPORT_ALL, *ROS_FREE], capture_output=True,
                            text=True, cwd=str(REPO), timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    expected = {'.'.join(p.relative_to(REPO).with_suffix('').parts).removesuffix('.__init__')
                for layer in ('core', 'wire', 'bag', 'analysis') for p in layer_files(layer)}
    assert expected <= set(report['modules']), expected - set(report['modules'])
    assert report['ros'] == [], f'ROS modules imported: {report["ros"]}'


def test_the_checker_rejects_foreign_modules() -> None:
    """The checker itself flags ROS in core, upward imports and unlisted libraries."""
    assert not allowed('core', 'rclpy.node')
    assert not allowed('core', 'formopt_ros.ros.params')
    assert not allowed('analysis', 'formopt_ros.cli.report')
    assert not allowed('bag', 'formopt_ros.core.model')
    assert not allowed('core', 'matplotlib.pyplot')
    assert allowed('core', 'numpy.linalg') and allowed('core', 'math')
    assert allowed('analysis', 'formopt_ros.bag.reader')


def test_nodes_start_without_the_heavy_libraries() -> None:
    """Importing a node loads neither scipy.optimize (0.45 s, only PERIODIC's cycle design
    needs it) nor matplotlib: every process of a run pays its imports at start-up."""
    code = ('import sys\n'
            'import formopt_ros.ros.nodes.estimator_planner, formopt_ros.ros.nodes.follower_sim\n'
            'import formopt_ros.ros.nodes.leader_sim, formopt_ros.ros.nodes.recorder\n'
            "print([m for m in ('scipy.optimize', 'matplotlib') if m in sys.modules])")
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            cwd=str(REPO), timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == '[]'


def module_graph() -> dict[str, set[str]]:
    """Every package module -> the package modules it imports anywhere (TYPE_CHECKING and
    function-level imports included; ``from a import b`` is module a.b when that exists)."""
    modules = {'.'.join(p.relative_to(REPO).with_suffix('').parts).removesuffix('.__init__')
               for p in PACKAGE.rglob('*.py')}
    graph: dict[str, set[str]] = {}
    for path in PACKAGE.rglob('*.py'):
        name = '.'.join(path.relative_to(REPO).with_suffix('').parts).removesuffix('.__init__')
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                deps |= {f'{node.module}.{a.name}' if f'{node.module}.{a.name}' in modules
                         else node.module for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = stack[stack.index(v):]
            del stack[stack.index(v):]
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycle() -> None:
    """No two modules of the package import each other, directly or through others."""
    assert import_cycles(module_graph()) == []
    assert import_cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]


def test_every_long_module_says_why() -> None:
    """A module over 500 lines is named, with its reason, in docs/architecture.md."""
    notes = (REPO / 'docs' / 'architecture.md').read_text(encoding='utf-8')
    section = notes.split('## Modules over 500 lines, and why')[1].split('\n## ')[0]
    long = [str(p.relative_to(PACKAGE)) for p in sorted(PACKAGE.rglob('*.py'))
            if len(p.read_text(encoding='utf-8').splitlines()) > 500]
    assert all(f'`{name}`' in section for name in long), (long, section)
