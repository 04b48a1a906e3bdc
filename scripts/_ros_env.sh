# _ros_env.sh - sourced by the node scripts: ROS environment defaults and how to start a node.
#
# formopt_run_node NODE [ARGS...] starts formopt_ros's executable NODE the way a ROS user does:
#   `ros2 run formopt_ros NODE --ros-args --params-file CONFIG ARGS...` when ros2 is on PATH
#   AND `ros2 pkg prefix formopt_ros` finds the package (a stock ROS sourced without this
#   package would only answer "Package 'formopt_ros' not found");
#   otherwise the same executable from an install prefix: the first PREFIX/lib/formopt_ros/NODE
#   of $AMENT_PREFIX_PATH, else this checkout's .venv/lib/formopt_ros/NODE (scripts/setup.sh).
# CONFIG is $FORMOPT_CONFIG_DIR/NODE.yaml, default <this folder>/../config (the repo's config/,
# or share/formopt_ros/config when installed); without that file the node's defaults apply. It
# is not passed when ARGS set formation_file (the formation file then decides the scenario, and
# the config's values would conflict with it) or give a --params-file of their own (CONFIG only
# restates the node's defaults, and where two files give one parameter values of different
# types, e.g. "0.5" and 0.5, rcl keeps the first file's and the user's is lost without a word),
# or rename the node (-r __node:=NAME: CONFIG's section is keyed by NODE, which rcl would not
# apply to NAME).
# The process replaces the shell (exec), so signals reach the node directly.

export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
_formopt_scripts="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# Fast DDS participants announce themselves every 0.25 s (config/fastdds_discovery.xml says why)
if [[ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ]]; then
  if [[ -f "$_formopt_scripts/../config/fastdds_discovery.xml" ]]; then
    FASTRTPS_DEFAULT_PROFILES_FILE="$(cd "$_formopt_scripts/../config" && pwd)/fastdds_discovery.xml"
    export FASTRTPS_DEFAULT_PROFILES_FILE
  fi
fi

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

# True when `ros2 run formopt_ros ...` would find the package.
formopt_ros2_knows_package() {
  command -v ros2 >/dev/null 2>&1 && ros2 pkg prefix formopt_ros >/dev/null 2>&1
}

formopt_run_node() {
  local node="$1"; shift
  local config="${FORMOPT_CONFIG_DIR:-$_formopt_scripts/../config}/$node.yaml"
  local params=()
  [[ -f "$config" && " $* " != *" formation_file:="* && " $* " != *" --params-file "* &&
     " $* " != *"__node:="* ]] && params=(--params-file "$config")
  if formopt_ros2_knows_package; then
    exec ros2 run formopt_ros "$node" --ros-args "${params[@]}" "$@"
  fi
  local exe
  if ! exe="$(formopt_find_exe "$node")"; then
    echo "$node.sh: error: executable $node not found: ros2 does not know formopt_ros and" \
         "there is no lib/formopt_ros/$node under \$AMENT_PREFIX_PATH or" \
         "$_formopt_scripts/../.venv (run scripts/setup.sh)" >&2
    exit 127
  fi
  exec "$exe" --ros-args "${params[@]}" "$@"
}
