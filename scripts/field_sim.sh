#!/usr/bin/env bash
# field_sim.sh - start field_sim: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/field_sim.yaml
# (not passed when they give a --params-file of their own):
#   scripts/field_sim.sh -p leader_clock_offset:=2.0 -p duration:=30.0
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node field_sim "$@"
