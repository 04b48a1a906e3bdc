"""The nodes: leader_sim, follower_sim, estimator_planner, recorder, replay.

``python -m formopt_ros.ros.nodes --write-configs DIR`` writes every node's documented
parameters file (the repository's config/ is generated this way and checked by the tests).
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

#: Node executable name -> module.
NODES = {name: f'formopt_ros.ros.nodes.{name}' for name in
         ('leader_sim', 'follower_sim', 'estimator_planner', 'recorder', 'replay')}


def config_text(node: str) -> str:
    """The generated config/<node>.yaml of a node."""
    from formopt_ros.ros.params import config_yaml
    module = importlib.import_module(NODES[node])
    return config_yaml(node, module.SUMMARY, module.PARAMS)


def main(argv: list[str] | None = None) -> int:
    """Write (or print) the nodes' parameter files."""
    parser = argparse.ArgumentParser(prog='python -m formopt_ros.ros.nodes',
                                     description='Write the documented parameters file of '
                                                 'every node.')
    parser.add_argument('--write-configs', type=Path, metavar='DIR', required=True,
                        help='folder to write <node>.yaml into (existing files are replaced)')
    args = parser.parse_args(argv)
    args.write_configs.mkdir(parents=True, exist_ok=True)
    for node in NODES:
        (args.write_configs / f'{node}.yaml').write_text(config_text(node))
        print(f'wrote {args.write_configs / node}.yaml')
    return 0


if __name__ == '__main__':
    sys.exit(main())
