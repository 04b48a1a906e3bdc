"""config/<node>.yaml documents exactly the node's declared parameters, at their defaults."""
from __future__ import annotations

import importlib

import pytest
import yaml
from harness.ros import REPO

from formopt_ros.ros.nodes import NODES, config_text


@pytest.mark.parametrize('node', sorted(NODES))
def test_config_file_is_generated_from_the_specs(node: str) -> None:
    """The file equals what the specs generate (so its comments cannot drift), and it parses
    to every declared parameter at its default, under the '/**/<node>' key."""
    path = REPO / 'config' / f'{node}.yaml'
    assert path.read_text() == config_text(node), \
        f'regenerate: python -m formopt_ros.ros.nodes --write-configs config ({path})'
    module = importlib.import_module(NODES[node])
    values = yaml.safe_load(path.read_text())[f'/**/{node}']['ros__parameters']
    assert values == {spec.name: spec.default for spec in module.PARAMS}
    for spec in module.PARAMS:
        assert spec.check(values[spec.name]) == spec.default
