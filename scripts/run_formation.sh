#!/usr/bin/env bash
# run_formation.sh - one formation run: leader_sim, follower_sim, estimator_planner (+ recorder)
# as separate processes, started like scripts/<node>.sh; writes logs and DIR/summary.json.
set -uo pipefail

usage() {
  cat <<'EOF'
Usage: scripts/run_formation.sh --out DIR [options]

Run the three formopt_ros nodes as separate processes (plus the MCAP recorder), wait until the
estimator has processed --steps measurement steps, stop the others with SIGINT and write
DIR/summary.json (final estimate and truth, tr(W P W), message counts, wall time, steps/s).

  --measurement range|bearing   the follower's sensor (default range)
  --strategy NAME               mtf, crm, mme, gbs, ram, rq or periodic (default ram)
  --steps N                     measurement steps, N >= 1 (default 100)
  --seed S                      seed of the random streams, S >= 0 (default 0)
  --mode lockstep|realtime      lockstep: deterministic, equals the pure simulation;
                                realtime: timers at 1/dt (default lockstep)
  --out DIR                     output folder: <node>.log, estimator_summary.json,
                                summary.json, run.mcap (required)
  --domain-id ID                ROS_DOMAIN_ID of the run (default: $ROS_DOMAIN_ID, else 0)
  --no-record                   do not start the recorder (no DIR/run.mcap)
  --timeout SEC                 give up after SEC s (default 600)
  -p NAME:=VALUE                extra parameter for every node, e.g. -p dt:=0.02 (repeatable)
  -h, --help                    show this help

summary.json: ok, failure, steps, final_estimate, final_covariance, final_truth,
final_weighted_trace (m^2), mean_nees, counters and message_counts (from the estimator),
exit_codes, wall_time_s and steps_per_s (estimator start to exit, start-up included),
run_time_s and run_steps_per_s (estimator 'ready' to 'run finished' log lines), recording.

Exit status: 0 when the estimator finished all steps and every node exited cleanly; 1 on a
failed or timed-out run (the reason is printed); 2 on bad arguments.
Environment: ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST.
EOF
}

die_usage() { echo "run_formation.sh: error: $*" >&2; echo "(see --help)" >&2; exit 2; }
say() { echo "run_formation.sh: $*"; }
warn() { echo "run_formation.sh: warning: $*" >&2; }

measurement=range strategy=ram steps=100 seed=0 mode=lockstep out='' record=1 timeout=600
extra=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    -h|--help) usage; exit 0 ;;
    --measurement|--strategy|--steps|--seed|--mode|--out|--domain-id|--timeout|-p)
      [[ $# -ge 2 ]] || die_usage "$1 needs a value"
      case "$1" in
        --measurement) measurement="$2" ;;
        --strategy) strategy="$2" ;;
        --steps) steps="$2" ;;
        --seed) seed="$2" ;;
        --mode) mode="$2" ;;
        --out) out="$2" ;;
        --domain-id) export ROS_DOMAIN_ID="$2" ;;
        --timeout) timeout="$2" ;;
        -p) extra+=(-p "$2") ;;
      esac
      shift 2 ;;
    --no-record) record=0; shift ;;
    *) die_usage "unknown argument: $1" ;;
  esac
done
[[ -n "$out" ]] || die_usage '--out DIR is required'
[[ "$measurement" == range || "$measurement" == bearing ]] \
  || die_usage "--measurement must be range or bearing, got '$measurement'"
[[ "$mode" == lockstep || "$mode" == realtime ]] \
  || die_usage "--mode must be lockstep or realtime, got '$mode'"
[[ "$steps" =~ ^[0-9]+$ && "$steps" -ge 1 ]] || die_usage "--steps must be >= 1, got '$steps'"
[[ "$seed" =~ ^[0-9]+$ ]] || die_usage "--seed must be an integer >= 0, got '$seed'"
[[ "${ROS_DOMAIN_ID:-0}" =~ ^[0-9]+$ ]] \
  || die_usage "--domain-id must be an integer, got '${ROS_DOMAIN_ID}'"
[[ "$timeout" =~ ^[0-9]+([.][0-9]+)?$ ]] || die_usage "--timeout must be seconds, got '$timeout'"

scripts="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
# shellcheck source=_ros_env.sh
source "$scripts/_ros_env.sh"
mkdir -p "$out" || die_usage "cannot create $out"
out="$(cd "$out" && pwd)"
rm -f "$out/estimator_summary.json" "$out/summary.json" "$out/recorder_counts.json"
py="$scripts/../.venv/bin/python"
[[ -x "$py" ]] || py=python3

common=(-p "mode:=$mode" -p "measurement:=$measurement" -p "seed:=$seed")
declare -A pids=()
order=()
set -m                       # each node gets its own process group (reaches `ros2 run` children)

now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { print b - a }'; }
alive() { kill -0 "$1" 2>/dev/null; }

# start NAME ARGS...: NAME.sh (or the executable via _ros_env.sh) in the background.
start() {
  local name="$1"; shift
  if [[ -x "$scripts/$name.sh" ]]; then
    "$scripts/$name.sh" "$@" >"$out/$name.log" 2>&1 &
  else
    ( formopt_run_node "$name" "$@" ) >"$out/$name.log" 2>&1 &
  fi
  pids[$name]=$!
  order+=("$name")
}

# stop_group NAME...: SIGINT those running, SIGTERM after 10 s, SIGKILL after 5 s more.
stop_group() {
  local sig name deadline grace
  for sig in INT TERM KILL; do
    for name in "$@"; do
      alive "${pids[$name]}" && kill -s "$sig" -- "-${pids[$name]}" 2>/dev/null
    done
    grace=5
    [[ $sig == INT ]] && grace=10
    deadline=$(( SECONDS + grace ))
    while (( SECONDS < deadline )); do
      local running=0
      for name in "$@"; do alive "${pids[$name]}" && running=1; done
      (( running )) || return 0
      sleep 0.1
    done
    [[ $sig == KILL ]] || warn "nodes still running after SIG$sig, escalating"
  done
}

# stop_all: the nodes first, the recorder (if any) last, so that it keeps their last messages.
stop_all() {
  local name nodes=()
  for name in "${order[@]}"; do [[ $name == recorder ]] || nodes+=("$name"); done
  (( ${#nodes[@]} )) && stop_group "${nodes[@]}"
  [[ -n "${pids[recorder]:-}" ]] && stop_group recorder
  return 0
}
trap 'warn "interrupted, stopping the nodes"; stop_all; exit 130' INT TERM

t0="$(now)"
peers=2
if (( record )); then
  if command -v ros2 >/dev/null 2>&1 || formopt_find_exe recorder >/dev/null; then
    rm -f "$out/run.mcap"         # the recorder refuses to overwrite a bag
    start recorder -p "output_path:=$out/run.mcap" -p "counts_path:=$out/recorder_counts.json" \
      "${extra[@]}"
    # Wait for its first log line, written once it subscribed (or for its end), so that it listens before anything is published.
    deadline=$(( SECONDS + 20 ))
    while alive "${pids[recorder]}" && ! grep -q "\] \[recorder\]: " "$out/recorder.log" \
        && (( SECONDS < deadline )); do
      sleep 0.1
    done
    if ! alive "${pids[recorder]}"; then
      wait "${pids[recorder]}"; code=$?
      warn "recorder exited at start (code $code, see $out/recorder.log): not recording"
      unset 'pids[recorder]'; order=()
    else
      peers=3                 # the estimator also waits for the recorder's waypoint subscription
    fi
  else
    warn 'no recorder executable (formopt_ros recorder) yet: not recording'
  fi
fi
start leader_sim "${common[@]}" "${extra[@]}"
start follower_sim "${common[@]}" "${extra[@]}"
# The estimator last, once the others are up: it sends the first waypoint as soon as it sees
# the peers' waypoint subscriptions, and the recorder should by then know every publisher.
deadline=$(( SECONDS + 30 ))
for name in leader_sim follower_sim; do
  while ! grep -q "\[[A-Za-z0-9_.]*$name\]: .*ready" "$out/$name.log"; do
    if ! alive "${pids[$name]}" || (( SECONDS > deadline )); then
      echo "run_formation.sh: error: $name did not start; last lines of $out/$name.log:" >&2
      tail -n 5 "$out/$name.log" >&2
      stop_all
      exit 1
    fi
    sleep 0.1
  done
done
t_est="$(now)"
start estimator_planner "${common[@]}" -p "strategy:=$strategy" -p "steps:=$steps" \
  -p "peers:=$peers" -p "summary_path:=$out/estimator_summary.json" "${extra[@]}"
say "started ${order[*]} (ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-0}, $mode, $measurement," \
    "$strategy, $steps steps, seed $seed); logs in $out"

# Wait for the estimator; a peer that dies first, or the timeout, fails the run.
failure=''
while alive "${pids[estimator_planner]}"; do
  for name in "${order[@]}"; do
    [[ $name == estimator_planner ]] && continue
    if ! alive "${pids[$name]}"; then failure="$name exited before the run finished"; break 2; fi
  done
  if awk -v e="$(elapsed "$t0")" -v t="$timeout" 'BEGIN { exit !(e > t) }'; then
    failure="timeout after $timeout s (see $out/estimator_planner.log)"; break
  fi
  sleep 0.1
done
wall="$(elapsed "$t_est")"
stop_all
trap - INT TERM

declare -A codes=()
for name in "${order[@]}"; do
  wait "${pids[$name]}"; codes[$name]=$?
  if [[ ${codes[$name]} -ne 0 ]]; then
    warn "$name exited with code ${codes[$name]}; last lines of $out/$name.log:"
    tail -n 5 "$out/$name.log" >&2
    [[ -n "$failure" ]] || failure="$name exited with code ${codes[$name]}"
  fi
done
if [[ ! -f "$out/estimator_summary.json" ]]; then
  [[ -n "$failure" ]] || failure='the estimator wrote no summary'
  echo "run_formation.sh: error: $failure" >&2
  exit 1
fi

codes_json="$(for name in "${order[@]}"; do printf '%s=%s\n' "$name" "${codes[$name]}"; done)"
if ! "$py" - "$out" "$wall" "$steps" "${failure:-}" "$codes_json" <<'EOF'
import json, re, sys
from pathlib import Path

out, wall, wanted, failure, codes = Path(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), \
    sys.argv[4], sys.argv[5]
est = json.loads((out / 'estimator_summary.json').read_text())
stamps = {}
log = (out / 'estimator_planner.log').read_text(errors='replace')
for key, pattern in (('ready', 'estimator_planner ready'), ('finished', 'run finished')):
    match = re.search(r'\[(\d+\.\d+)\] \[[\w.]*estimator_planner\]: ' + pattern, log)
    if match:
        stamps[key] = float(match.group(1))
run_time = stamps['finished'] - stamps['ready'] if len(stamps) == 2 else None
if not failure and est['steps'] != wanted:
    failure = f"the estimator processed {est['steps']} of {wanted} steps"
summary = {
    'ok': not failure,
    'failure': failure or None,
    'steps': est['steps'],
    'steps_requested': wanted,
    'mode': est['mode'], 'measurement': est['measurement'], 'strategy': est['strategy'],
    'seed': est['seed'],
    'final_estimate': est['final_estimate'],
    'final_covariance': est['final_covariance'],
    'final_truth': est['final_truth'],
    'final_weighted_trace': est['final_weighted_trace'],
    'mean_nees': est['mean_nees'],
    'counters': est['counters'],
    'message_counts': est['message_counts'],
    'exit_codes': {k: int(v) for k, v in (line.split('=') for line in codes.split())},
    'wall_time_s': wall,
    'steps_per_s': est['steps'] / wall if wall > 0 else None,
    'run_time_s': run_time,
    'run_steps_per_s': est['steps'] / run_time if run_time else None,
    'recording': None,
}
counts_file = out / 'recorder_counts.json'
if (out / 'run.mcap').exists():
    # Complete when the bag holds at least what the estimator received and published.
    recorded = json.loads(counts_file.read_text())['counts'] if counts_file.exists() else {}
    expected = {'/leader/odom': ('received', 'leader_odom'),
                '/follower/odom': ('received', 'follower_odom'),
                '/follower/measurement': ('received', 'measurement'),
                '/follower/truth': ('received', 'truth'),
                '/follower/estimate': ('published', 'estimate'),
                '/follower/waypoint': ('published', 'waypoint'),
                '/follower/status': ('published', 'status')}
    missing = {topic: est['message_counts'][a][b] - recorded.get(topic, 0)
               for topic, (a, b) in expected.items()
               if recorded.get(topic, 0) < est['message_counts'][a][b]}
    summary['recording'] = {'path': str(out / 'run.mcap'), 'counts': recorded,
                            'complete': bool(recorded) and not missing, 'missing': missing}
    if missing or not recorded:
        print('run_formation.sh: warning: the recording misses messages (a publisher and the '
              f'recorder discovered each other late): {missing or "no counts"}', file=sys.stderr)
(out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
print(f"run_formation.sh: {summary['steps']} steps, tr(W P W) = "
      f"{summary['final_weighted_trace']:.6g} m^2, {wall:.2f} s wall "
      f"({summary['steps_per_s']:.1f} steps/s); {out / 'summary.json'}")
sys.exit(1 if failure else 0)
EOF
then
  echo "run_formation.sh: error: ${failure:-the run failed (see $out/summary.json)}" >&2
  exit 1
fi
