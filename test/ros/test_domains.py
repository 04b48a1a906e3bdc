"""The ROS tests' ROS_DOMAIN_IDs: one per module, 30 from $FORMOPT_TEST_DOMAIN_BASE."""
from __future__ import annotations

import os
import subprocess
import sys

from harness.ros import REPO


def test_module_domain_follows_the_base(ros_domain: int) -> None:
    """This module runs in its own domain, within the 30 ids from the base (default 10)."""
    base = int(os.environ.get('FORMOPT_TEST_DOMAIN_BASE', '10'))
    assert os.environ['ROS_DOMAIN_ID'] == str(ros_domain)
    assert base <= ros_domain < base + 30


def test_bad_base_is_a_usage_error() -> None:
    """A base that is not an integer in [0, 202] stops pytest with one line naming it."""
    result = subprocess.run(
        [sys.executable, '-m', 'pytest', '--collect-only', '-q', 'test/ros/test_domains.py'],
        cwd=REPO, capture_output=True, text=True, timeout=120,
        env={**os.environ, 'FORMOPT_TEST_DOMAIN_BASE': '220'})
    assert result.returncode == 4, result.stdout + result.stderr
    assert 'FORMOPT_TEST_DOMAIN_BASE must be an integer in [0, 202]' in result.stderr
