#!/usr/bin/env bash
# follower_estimator.sh - start follower_estimator: ros2 run if available, else the install prefix.
# Arguments go to the node (inside --ros-args), after --params-file config/follower_estimator.yaml
# (not passed when they give a --params-file of their own):
#   scripts/follower_estimator.sh -p bias_sigma:=0.3 -p huber:=2.5 -r leader_odom:=/leader/odom
source "$(dirname "${BASH_SOURCE[0]}")/_ros_env.sh"
formopt_run_node follower_estimator "$@"
