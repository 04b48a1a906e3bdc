#!/usr/bin/env bash
# leader_sim.sh - start the leader_sim node: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/leader_sim.yaml
# (not passed when they give a --params-file of their own):
#   scripts/leader_sim.sh -p mode:=realtime -p dt:=0.02
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node leader_sim "$@"
