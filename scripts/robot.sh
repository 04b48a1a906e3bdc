#!/usr/bin/env bash
# robot.sh - start one follower's nodes on this computer (one robot per computer).
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/robot.sh --robot ID [--leader ID] [--sim [--sim-params FILE]] [-- NODE ARGS...]

Start the nodes of follower ID on this computer, in the namespace /ID:
  follower_estimator  reads /ID/odom (nav_msgs/Odometry of this base), /ID/range
                      (sensor_msgs/Range of its UWB radio) and the leader's odometry
                      /LEADER/odom over the network; publishes /ID/cmd_vel, /ID/estimate,
                      /ID/target and /diagnostics.
  field_sim (--sim)   a simulated base and radio for ID (and the leader, publishing
                      /LEADER/odom), to try the set-up without robots.
NODE ARGS go to follower_estimator (e.g. -p max_speed:=0.8 -r odom:=/ID/base/odom; a
-r leader_odom:=TOPIC of yours replaces /LEADER/odom); with --sim field_sim simulates the
sensor, slot, base frame and camera mount follower_estimator runs with (its parameters);
--sim-params FILE is a params file for field_sim (e.g. its leader's path, keyed /**/field_sim).

Across computers: every computer uses the same ROS_DOMAIN_ID; discovery reaches the subnet
(ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET is set unless given; for networks without multicast set
ROS_STATIC_PEERS to the other computers' addresses). The clocks must agree to a few milliseconds
(chrony or NTP against one server on every robot): messages stamped ahead of this clock by
more than future_tolerance (0.05 s), or a stream whose median delay over a status period
exceeds reorder_lag (0.1 s), is an ERROR on /diagnostics and ends the run not ok (a single
late message is a WARN: the link stalled).
EOF
}

robot='' leader='leader' sim=0 sim_params=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --robot|--leader|--sim-params)
      if [[ $# -lt 2 ]]; then
        echo "robot.sh: error: $1 needs a value (see --help)" >&2
        exit 2
      fi ;;&
    --robot) robot="$2"; shift 2 ;;
    --leader) leader="$2"; shift 2 ;;
    --sim) sim=1; shift ;;
    --sim-params) sim_params=(--params-file "$2"); shift 2 ;;
    -h|--help) usage; exit 0 ;;
    --) shift; break ;;
    *) echo "robot.sh: error: unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
for name in robot leader; do
  if [[ ! "${!name}" =~ ^[A-Za-z][A-Za-z0-9_]*$ ]]; then
    echo "robot.sh: error: --$name must be letters, digits and underscores starting with a" \
         "letter (it becomes a ROS namespace), got '${!name}'" >&2
    exit 2
  fi
done
if [[ ${#sim_params[@]} -gt 0 && $sim -eq 0 ]]; then
  echo "robot.sh: error: --sim-params is for the simulated robot: give --sim too" >&2
  exit 2
fi
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-SUBNET}"
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
pids=()
stop() { kill -INT "${pids[@]}" 2>/dev/null; wait; }
trap stop INT TERM HUP
if [[ $sim -eq 1 ]]; then
  estimator=follower_estimator          # the simulated robot carries the estimator's sensor
  for arg in "$@"; do                   # rcl takes the first __node:= rule
    if [[ "$arg" == __node:=* || "$arg" == *:__node:=* ]]; then    # also NODE:__node:=
      estimator="${arg#*__node:=}"; break
    fi
  done
  "$here/field_sim.sh" -r "__ns:=/$robot" -p "leader_odom_topic:=/$leader/odom" \
    -p "sensor_of:=/$robot/$estimator" "${sim_params[@]}" &
  pids+=($!)
fi
leader_remap=(-r "leader_odom:=/$leader/odom")   # rcl takes the first remap: the user's wins
for arg in "$@"; do [[ "$arg" == leader_odom:=* ]] && leader_remap=(); done
"$here/follower_estimator.sh" -r "__ns:=/$robot" "${leader_remap[@]}" \
  -p "leader_frame:=$leader" "$@" &
pids+=($!)
set +e                                   # the first node to end decides the exit code
wait -n "${pids[@]}"
code=$?
stop
exit $code
