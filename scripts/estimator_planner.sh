#!/usr/bin/env bash
# estimator_planner.sh - start estimator_planner: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/estimator_planner.yaml
# (not passed when they give a --params-file of their own):
#   scripts/estimator_planner.sh -p mode:=realtime -p dt:=0.02
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node estimator_planner "$@"
