"""README's commands are the ones CI and users run."""
from __future__ import annotations

import re
from pathlib import Path

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
    """The first command sets up from scratch and then runs the formation."""
    first = _fenced_commands((ROOT / 'README.md').read_text())[0]
    assert first.startswith('bash scripts/setup.sh && scripts/run_formation.sh')
