"""Formation files (YAML): one leader, its path, and the followers with sensor, slot, allowed
deviation, noise and strategy; see config/formation_fig4.yaml for every key documented."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from formopt_ros.core.domain import check_domain
from formopt_ros.core.formation import Formation


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe loader that refuses a key given twice in one mapping (YAML would silently keep
    the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> Any:
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)   # type: ignore[no-untyped-call]
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f'key {key!r} is given twice', key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def read_yaml(path: str | Path, what: str) -> Any:
    """The content of a YAML file; ValueError in one line naming the file and ``what`` it
    should hold when it is missing, not YAML or gives a key twice."""
    try:
        return yaml.load(Path(path).read_text(), Loader=_UniqueKeyLoader)
    except FileNotFoundError:
        raise ValueError(f'{path}: no such {what} file') from None
    except (OSError, yaml.YAMLError) as error:
        where = ' '.join(str(error).split())           # YAML's message spans lines
        raise ValueError(f'{path}: cannot read the {what}: {where}') from None


def load_formation(path: str | Path) -> Formation:
    """The formation of a YAML file; ValueError with the file name and what is wrong."""
    path = Path(path)
    data = read_yaml(path, 'formation')
    if not isinstance(data, dict) or 'formation' not in data:
        raise ValueError(f"{path}: a formation file has one top-level key 'formation'")
    try:
        formation = Formation.from_dict(data['formation'] or {})
        for follower in formation.followers:
            try:
                check_domain(follower.scenario, 'slot', 'deviation')
            except ValueError as error:
                raise ValueError(f'formation follower {follower.id}: {error}') from None
        return formation
    except ValueError as error:
        raise ValueError(f'{path}: {error}') from None
