#!/usr/bin/env bash
# run_formation.sh - one formation run as separate node processes, recorded to MCAP.
#   scripts/run_formation.sh --formation config/formation_fig4.yaml --steps 600 --out runs/fig4
#   scripts/run_formation.sh --measurement range --strategy ram --steps 600 --out runs/one
# Every node is started through scripts/<node>.sh (ros2 run when ros2 knows formopt_ros, else
# the install prefix). See --help; the logic lives in formopt_ros/cli/run_formation.py.
set -u
scripts="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
source "$scripts/_ros_env.sh"
py="$scripts/../.venv/bin/python"
[[ -x "$py" ]] || py=python3
exec "$py" -m formopt_ros.cli.run_formation "$@"
