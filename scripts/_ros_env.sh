# _ros_env.sh - sourced by the node scripts: ROS environment defaults and how to start a node.
#
# formopt_run_node NODE [ARGS...] starts formopt_ros's executable NODE the way a ROS user does:
#   `ros2 run formopt_ros NODE --ros-args --params-file CONFIG ARGS...` when ros2 is on PATH;
#   otherwise the same executable from the install prefix: the first PREFIX/lib/formopt_ros/NODE
#   of $AMENT_PREFIX_PATH, else this checkout's .venv/lib/formopt_ros/NODE (scripts/setup.sh).
# CONFIG is $FORMOPT_CONFIG_DIR/NODE.yaml, default <this folder>/../config (the repo's config/,
# or share/formopt_ros/config when installed); without that file the node's defaults apply.
# The process replaces the shell (exec), so signals reach the node directly.

export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
_formopt_scripts="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

# Print the path of executable NODE outside ros2 (non-zero status if there is none).
formopt_find_exe() {
  local node="$1" prefix
  local IFS=:
  for prefix in ${AMENT_PREFIX_PATH:-}; do
    if [[ -n "$prefix" && -x "$prefix/lib/formopt_ros/$node" ]]; then
      echo "$prefix/lib/formopt_ros/$node"; return 0
    fi
  done
  # <repo>/scripts -> <repo>/.venv; installed <prefix>/share/formopt_ros/scripts -> <prefix>
  for prefix in "$_formopt_scripts/../.venv" "$_formopt_scripts/../../.."; do
    if [[ -x "$prefix/lib/formopt_ros/$node" ]]; then
      echo "$(cd "$prefix" && pwd)/lib/formopt_ros/$node"; return 0
    fi
  done
  return 1
}

formopt_run_node() {
  local node="$1"; shift
  local config="${FORMOPT_CONFIG_DIR:-$_formopt_scripts/../config}/$node.yaml"
  local params=()
  [[ -f "$config" ]] && params=(--params-file "$config")     # else the node's defaults
  if command -v ros2 >/dev/null 2>&1; then
    exec ros2 run formopt_ros "$node" --ros-args "${params[@]}" "$@"
  fi
  local exe
  if ! exe="$(formopt_find_exe "$node")"; then
    echo "$node.sh: error: executable $node not found: no ros2 on PATH, no" \
         "lib/formopt_ros/$node under \$AMENT_PREFIX_PATH or $_formopt_scripts/../.venv" \
         "(run scripts/setup.sh)" >&2
    exit 127
  fi
  exec "$exe" --ros-args "${params[@]}" "$@"
}
