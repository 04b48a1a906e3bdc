#!/usr/bin/env bash
# follower_sim.sh - start the follower_sim node: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/follower_sim.yaml
# (not passed when they give a --params-file of their own):
#   scripts/follower_sim.sh -p mode:=realtime -p dt:=0.02
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node follower_sim "$@"
