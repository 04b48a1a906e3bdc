"""README's commands are the ones CI and users run."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _fenced_commands(text: str) -> list[str]:
    return [block.strip() for block in re.findall(r'```bash\n(.*?)```', text, re.S)]


def test_ci_runs_the_readme_test_command() -> None:
    """The second fenced command of README is the one .ci/run executes, verbatim."""
    readme = (ROOT / 'README.md').read_text()
    test_command = _fenced_commands(readme)[1]
    assert 'pytest' in test_command
    assert test_command in (ROOT / '.ci' / 'run').read_text()


def test_readme_main_job_uses_the_setup_script() -> None:
    """The first command sets up from scratch and then runs the Fig. 4 formation, recorded."""
    first = _fenced_commands((ROOT / 'README.md').read_text())[0]
    assert first.startswith('bash scripts/setup.sh && scripts/run_formation.sh')
    assert '--formation config/formation_fig4.yaml' in first and '--no-record' not in first
    assert (ROOT / 'config' / 'formation_fig4.yaml').is_file()


def test_node_reference_is_generated() -> None:
    """The tables of docs/nodes.md between the node-reference markers are what
    ``python -m formopt_ros.ros.nodes --readme`` prints."""
    pytest.importorskip('rclpy')              # the generator reads the QoS profiles
    from formopt_ros.ros.nodes import readme_text
    reference = (ROOT / 'docs' / 'nodes.md').read_text()
    block = re.search(r'<!-- node-reference:[^\n]*-->\n(.*?)<!-- end node-reference -->',
                      reference, re.S)
    assert block is not None, 'docs/nodes.md lost its node-reference markers'
    assert block.group(1) == readme_text(), \
        'regenerate with: python -m formopt_ros.ros.nodes --readme'


def test_readme_commands_exist() -> None:
    """Every formopt-* command README mentions is a console script of setup.py, and every
    scripts/*.sh it mentions exists."""
    readme = (ROOT / 'README.md').read_text()
    setup = (ROOT / 'setup.py').read_text()
    for command in set(re.findall(r'\b(formopt-[a-z-]+)\b', readme)):
        assert f"'{command} = " in setup, command
    for script in set(re.findall(r'scripts/([a-z_]+\.sh)', readme)):
        assert (ROOT / 'scripts' / script).is_file(), script


def test_readme_is_one_page_and_its_links_resolve() -> None:
    """README stays at most 150 lines, and every relative link of README and docs/ points at
    a file of the repository."""
    readme = ROOT / 'README.md'
    assert len(readme.read_text().splitlines()) <= 150
    for page in [readme, *sorted((ROOT / 'docs').glob('*.md'))]:
        for target in re.findall(r'\]\(([^)#\s]+)(?:#[^)]*)?\)', page.read_text()):
            if '://' not in target:
                assert (page.parent / target).exists(), f'{page.name}: broken link {target}'
