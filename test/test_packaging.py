"""package.xml declares every package the code imports (the ROS ones by name, the Python
libraries by their rosdep keys)."""
from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Python import name -> rosdep key in package.xml.
ROSDEP_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy',
               'matplotlib': 'python3-matplotlib', 'yaml': 'python3-yaml',
               'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
               'mcap': 'mcap-ros2-support'}
#: Imports that are part of rclpy or of this project's build, not separate dependencies.
PART_OF_OTHERS = {'formopt_ros', '__future__'}


def imported_top_levels() -> set[str]:
    """Top-level names of every module the package imports (anywhere, lazily too)."""
    found = set()
    for path in (REPO / 'formopt_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                found.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                found.add(node.module.split('.')[0])
    return found - set(sys.stdlib_module_names) - PART_OF_OTHERS


def test_package_xml_lists_every_import() -> None:
    declared = set(re.findall(r'<(?:exec_)?depend>([^<]+)</', (REPO / 'package.xml')
                              .read_text()))
    missing = sorted(name for name in imported_top_levels()
                     if ROSDEP_KEYS.get(name, name) not in declared
                     # optional extras ([peers], [sweep]) that rosdep has no key for
                     and name not in ('casadi', 'dask'))
    assert not missing, f'package.xml lacks: {missing}'
