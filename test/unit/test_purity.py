"""The pure core (formopt_ros/core) must import nothing but stdlib, numpy, scipy and itself."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CORE = REPO / 'formopt_ros' / 'core'
ALLOWED_THIRD_PARTY = {'numpy', 'scipy'}
CORE_PACKAGE = 'formopt_ros.core'

IMPORT_ALL = '''
import importlib, json, pkgutil, sys
import formopt_ros.core as core
names = [core.__name__]
for info in pkgutil.walk_packages(core.__path__, core.__name__ + '.'):
    importlib.import_module(info.name)
    names.append(info.name)
print(json.dumps({'modules': names,
                  'ros': sorted(m for m in sys.modules
                                if m.split('.')[0] in ('rclpy', 'rosidl_runtime_py'))}))
'''


def core_files() -> list[Path]:
    """Every Python file under formopt_ros/core."""
    files = sorted(CORE.rglob('*.py'))
    assert files, f'no Python files found under {CORE}'
    return files


def module_name(path: Path) -> str:
    """Dotted module name of a file under the repository root."""
    parts = list(path.relative_to(REPO).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement in a file, relative ones resolved."""
    tree = ast.parse(path.read_text(encoding='utf-8'), filename=str(path))
    package = module_name(path)
    if path.name != '__init__.py':
        package = package.rpartition('.')[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - (node.level - 1)]
                name = '.'.join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ''
            found.append((node.lineno, name))
    return found


def allowed(name: str) -> bool:
    """True for stdlib, numpy, scipy and formopt_ros.core modules."""
    top = name.split('.')[0]
    return (top in sys.stdlib_module_names or top in ALLOWED_THIRD_PARTY
            or name == CORE_PACKAGE or name.startswith(CORE_PACKAGE + '.'))


def test_importing_core_does_not_import_rclpy() -> None:
    """A fresh interpreter importing formopt_ros.core and every submodule has no rclpy loaded."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(REPO), env.get('PYTHONPATH', '')])
    result = subprocess.run([sys.executable, '-c', IMPORT_ALL], capture_output=True, text=True,
                            env=env, cwd=str(REPO), timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    expected = {module_name(path) for path in core_files()}
    assert expected <= set(report['modules']), expected - set(report['modules'])
    assert report['ros'] == [], f'ROS modules imported by the core: {report["ros"]}'


@pytest.mark.parametrize('path', core_files(), ids=lambda p: str(p.relative_to(CORE)))
def test_core_file_imports_only_allowed_modules(path: Path) -> None:
    """Each core file imports only stdlib, numpy, scipy or formopt_ros.core (checked with ast)."""
    text = path.read_text(encoding='utf-8')
    assert 'import rclpy' not in text
    bad = [(line, name) for line, name in imported_modules(path) if not allowed(name)]
    assert not bad, f'{path}: disallowed imports {bad}'


def test_import_checker_rejects_foreign_modules() -> None:
    """The checker itself flags ROS, other project modules and third-party packages."""
    assert not allowed('rclpy.node')
    assert not allowed('formopt_ros.nodes.leader_sim')
    assert not allowed('formopt_ros')
    assert not allowed('matplotlib.pyplot')
    assert allowed('numpy.linalg') and allowed('scipy.optimize') and allowed('math')
    assert allowed('formopt_ros.core.cost')
