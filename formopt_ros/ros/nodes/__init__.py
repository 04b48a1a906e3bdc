"""The nodes: leader_sim, follower_sim, estimator_planner, follower_estimator (real robots),
field_sim (simulated real robots), recorder, replay.

``python -m formopt_ros.ros.nodes --write-configs DIR`` writes every node's documented
parameters file, ``--readme`` prints the node reference of docs/nodes.md (topics, frames,
parameters); the repository's config/ and docs/nodes.md are generated this way and checked by
the tests.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

#: Node executable name -> module.
NODES = {name: f'formopt_ros.ros.nodes.{name}' for name in
         ('leader_sim', 'follower_sim', 'estimator_planner', 'follower_estimator', 'field_sim',
          'recorder', 'replay')}


def config_text(node: str) -> str:
    """The generated config/<node>.yaml of a node."""
    from formopt_ros.ros.params import config_yaml
    module = importlib.import_module(NODES[node])
    return config_yaml(node, module.SUMMARY, module.PARAMS)


#: Frames: (frame, parent, published by, meaning).
FRAMES = (
    ('odom', '-', 'leader_sim', "the fixed frame: the leader's odometry starts at its origin"),
    ('<leader>', 'odom', 'leader_sim (/tf)', "the leader's body; the frame of every estimate, "
     'truth, waypoint and marker'),
    ('<follower>/estimate', '<leader>', 'estimator_planner (/tf)',
     'the estimated follower pose (the EKF state)'),
    ('<follower>/truth', '<leader>', 'follower_sim (/tf)', 'the true follower pose'),
    ('<follower>/odom', 'odom', 'follower_sim (/tf_static)',
     "where the follower's odometry started (its true start pose)"),
    ('<follower>', '<follower>/odom', 'follower_sim (/tf)',
     "the follower's body by dead reckoning of its (noisy) odometry"),
)


def readme_text() -> str:
    """docs/nodes.md's node reference: every topic of a formation (name, type, who publishes and
    reads it, QoS, meaning), the frames, and per node its parameters (default, admissible
    values, whether ``ros2 param set`` may change it)."""
    from formopt_ros.ros import qos
    from formopt_ros.wire.topics import BY_KEY
    lines = ['| topic | type | published by | read by | QoS | carries |',
             '|---|---|---|---|---|---|']
    for topic in BY_KEY.values():
        owner = '/<leader>' if topic.key.startswith('leader') else '/<follower>'
        name = topic.name if topic.name.startswith('/') else f'{owner}/{topic.name}'
        kind = topic.type.split('/')[-1]
        readers = ', '.join(topic.listeners) or 'recorder, tools'
        lines.append(f"| `{name}` | `{kind}` | {', '.join(topic.publishers)} | {readers} | "
                     f'{qos.describe(qos.profile(topic.qos))} | {topic.description} |')
    lines += ['', '| frame | parent | published by | meaning |', '|---|---|---|---|']
    lines += [f'| `{f}` | `{p}` | {who} | {what} |' for f, p, who, what in FRAMES]
    for node in NODES:
        module = importlib.import_module(NODES[node])
        lines += ['', f'<details><summary><code>{node}</code>: {len(module.PARAMS)} '
                      'parameters</summary>', '', module.SUMMARY, '',
                  '| parameter | default | accepts | at run time |', '|---|---|---|---|']
        for spec in module.PARAMS:
            settable = 'read-only' if spec.read_only else 'settable'
            lines.append(f'| `{spec.name}` | `{spec.default!r}` | '
                         f"{spec.expected().replace('|', '&#124;')} | {settable} |")
        lines += ['', '</details>']
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    """Write the nodes' parameter files, or print the node reference of docs/nodes.md."""
    parser = argparse.ArgumentParser(prog='python -m formopt_ros.ros.nodes',
                                     description='Write the documented parameters file of '
                                                 'every node, or print the node reference.')
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument('--write-configs', type=Path, metavar='DIR',
                       help='folder to write <node>.yaml into (existing files are replaced)')
    group.add_argument('--readme', action='store_true',
                       help='print the node reference of docs/nodes.md (Markdown)')
    args = parser.parse_args(argv)
    if args.readme:
        print(readme_text(), end='')
        return 0
    args.write_configs.mkdir(parents=True, exist_ok=True)
    for node in NODES:
        (args.write_configs / f'{node}.yaml').write_text(config_text(node))
        print(f'wrote {args.write_configs / node}.yaml')
    return 0


if __name__ == '__main__':
    sys.exit(main())
