#!/usr/bin/env bash
# recorder.sh - start the MCAP recorder: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/recorder.yaml
# (not passed when they give a --params-file of their own):
#   scripts/recorder.sh -p output_path:=runs/run.mcap
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node recorder "$@"
