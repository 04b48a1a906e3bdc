"""scripts/run_formation.sh: each node its own process, started the way a user starts it; the
lockstep run equals the pure simulation per follower and the recording loses nothing."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from harness.ros import REPO, node_scenario

from formopt_ros.bag import read_bag
from formopt_ros.core.simulation import run_formation, run_trial
from formopt_ros.wire.formation import load_formation

SCRIPT = REPO / 'scripts' / 'run_formation.sh'
FIG4 = REPO / 'config' / 'formation_fig4.yaml'
STEPS = 50
TOL = 1e-9


def run(*args: str, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=timeout)


def test_single_follower_flags(tmp_path: Path, ros_domain: int) -> None:
    out = tmp_path / 'run'
    result = run('--measurement', 'bearing', '--strategy', 'crm', '--steps', str(STEPS),
                 '--seed', '5', '--out', str(out), '--domain-id', str(ros_domain),
                 '--no-record', '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    ref = run_trial(node_scenario('bearing'), 'crm', 5, 0, STEPS)
    assert summary['ok'] and summary['steps'] == STEPS and summary['recording'] is None
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_covariance'], ref.covariance[-1], rtol=0,
                               atol=TOL)
    np.testing.assert_allclose(summary['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    assert summary['exit_codes'] == {'leader_sim': 0, 'follower.follower_sim': 0,
                                     'follower.estimator_planner': 0}
    assert summary['counters']['accepted_measurements'] == STEPS
    assert summary['wall_time_s'] > 0 and summary['steps_per_s'] > 0
    # config/fastdds_discovery.xml parses (an error there silently drops the whole profile)
    logs = ''.join(log.read_text(errors='replace') for log in out.glob('*.log'))
    assert 'XMLPARSER' not in logs and 'Error' not in logs, logs[:2000]


def test_p_values_shape_the_run_and_its_summary(tmp_path: Path, ros_domain: int) -> None:
    """-p dt, a segments path given with integer lists (accepted for floats) and a strategy
    option: the run equals run_trial of that scenario (1e-9) and summary.json's formation
    describes what ran."""
    from formopt_ros.core.scenario import LeaderPath, Segment
    out = tmp_path / 'p'
    result = run('-p', 'dt:=0.02', '-p', 'path:=segments', '-p', 'segment_durations:=[1, 2]',
                 '-p', 'segment_speeds:=[1, 2]', '-p', 'segment_yaw_rates:=[0, 0.1]',
                 '--strategy', 'gbs', '-p', 'gbs_cell:=0.02', '--steps', '30', '--seed', '3',
                 '--out', str(out), '--domain-id', str(ros_domain), '--no-record')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    leader = LeaderPath('segments', segments=(Segment(1.0, 1.0, 0.0), Segment(2.0, 2.0, 0.1)))
    scenario = node_scenario('range', dt=0.02, leader=leader)
    assert summary['formation']['dt'] == 0.02
    assert summary['formation']['leader']['path']['segments'][1] == {
        'duration': 2.0, 'speed': 2.0, 'yaw_rate': 0.1}
    assert summary['formation']['followers'][0]['options'] == {'cell': 0.02}
    ref = run_trial(scenario, 'gbs', 3, 0, 30, options={'cell': 0.02})
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)


def test_a_follower_that_cannot_reach_its_disc_is_named(tmp_path: Path,
                                                        ros_domain: int) -> None:
    """A bearing follower limited to the leader's own speed (max_speed 1 m/s, the least the
    scenario accepts) cannot get back into its disc once noise pushes it out: the run is ok,
    the summary counts the unreachable plans and the console warns, naming the follower."""
    out = tmp_path / 'run'
    result = run('--measurement', 'bearing', '--steps', '60', '-p', 'max_speed:=1.0', '--out',
                 str(out), '--domain-id', str(ros_domain))
    assert result.returncode == 0, result.stderr
    unreachable = json.loads((out / 'summary.json').read_text())['plan_fallbacks']['unreachable']
    assert unreachable > 6 and f'out of reach on {unreachable} of 60 steps' in result.stderr


def test_fig4_formation_recorded(tmp_path: Path, ros_domain: int) -> None:
    """The paper's Fig. 4 pair under a namespace prefix: every follower equals the pure
    formation simulation (1e-9), the bag holds every published message, rosbags reads it."""
    out = tmp_path / 'fig4'
    result = run('--formation', str(FIG4), '--steps', str(STEPS), '--out', str(out),
                 '--prefix', '/fig4test', '--domain-id', str(ros_domain), '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    reference = run_formation(load_formation(FIG4), STEPS)
    assert summary['ok'] and set(summary['followers']) == {'bearing', 'range'}
    for follower, ref in reference.items():
        got = summary['followers'][follower]
        assert got['steps'] == STEPS
        np.testing.assert_allclose(got['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
        np.testing.assert_allclose(got['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    recording = summary['recording']
    assert recording['complete'] and recording['missing'] == {}
    assert recording['counts'] == recording['expected']
    counts = read_bag(out / 'run.mcap').counts()
    assert counts == recording['counts']
    assert counts['/fig4test/leader/odom'] == 2 * STEPS and counts['/fig4test/clock'] == 2 * STEPS
    assert counts['/fig4test/range/estimate'] == counts['/fig4test/bearing/estimate'] == STEPS
    from rosbags.highlevel import AnyReader
    with AnyReader([out / 'run.mcap']) as reader:
        assert sum(1 for _ in reader.messages()) == sum(counts.values())
    # formopt-report draws the paper's Fig. 4 and a row per follower, top to bottom
    report = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.report',
                             str(out / 'run.mcap'), '--out', str(out / 'report')],
                            capture_output=True, text=True, timeout=120)
    assert report.returncode == 0, report.stderr
    rows = json.loads((out / 'report' / 'summary.json').read_text())['followers']
    assert list(rows) == ['bearing', 'range']
    for follower, ref in reference.items():
        assert rows[follower]['steps'] == STEPS and rows[follower]['description'] == 'recorded'
        assert rows[follower]['final_weighted_trace'] == pytest.approx(
            ref.weighted_trace[-1], abs=TOL)
        assert rows[follower]['mean_nees'] == pytest.approx(float(np.mean(ref.nees)), rel=1e-9)
    assert (out / 'report' / 'trajectory.png').stat().st_size > 20_000


def test_range_bearing_formation_equals_the_simulation(tmp_path: Path, ros_domain: int) -> None:
    """config/formation_range_bearing.yaml: the range-bearing follower sends two measurements
    per step, every follower equals the pure formation simulation (1e-9), and the recording
    holds every message."""
    path = REPO / 'config' / 'formation_range_bearing.yaml'
    out = tmp_path / 'rb'
    result = run('--formation', str(path), '--steps', str(STEPS), '--out', str(out),
                 '--domain-id', str(ros_domain), '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    reference = run_formation(load_formation(path), STEPS)
    assert summary['ok'] and set(summary['followers']) == {'bearing', 'range', 'both'}
    for follower, ref in reference.items():
        got = summary['followers'][follower]
        np.testing.assert_allclose(got['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
        np.testing.assert_allclose(got['final_covariance'], ref.covariance[-1], rtol=0,
                                   atol=TOL)
    counts = summary['recording']['counts']
    assert summary['recording']['complete']
    assert counts['/both/measurement'] == 2 * STEPS and counts['/range/measurement'] == STEPS


@pytest.mark.parametrize('args,text', [
    (['--mode', 'warp'], "argument --mode: invalid choice: 'warp'"),
    (['--strategy', 'fast'], "argument --strategy: invalid choice: 'fast'"),
    (['--measurement', 'range-bearing', '--strategy', 'ram'],
     "--strategy ram: strategy ram is the paper's method for one scalar measurement"),
    (['--steps', '0'], 'argument --steps: must be an integer in [1,'),
    (['--domain-id', 'x'], 'argument --domain-id: must be an integer'),
    (['--formation', 'nonexistent.yaml'], 'no such formation file'),
    (['--formation', str(FIG4), '--strategy', 'rq'], 'cannot be combined with --formation'),
    (['--prefix', 'bad name'], '--prefix must look like'),
    (['-p', 'dt:=-1'], "-p dt:=-1: parameter 'dt' must be a number in [0.001, 10]"),
    (['-p', 'dt:=nan'], "-p dt:=nan: parameter 'dt' must be a number"),
    (['-p', 'stratgy:=rq'], "-p stratgy: no such parameter of follower_sim or "
                            "estimator_planner; did you mean 'strategy'?"),
    (['-p', 'strategy:=rq'], '-p strategy: set by run_formation.sh itself; use --strategy'),
    (['-p', 'leader_id:=a_b'], '-p leader_id: set by run_formation.sh itself; use --formation'),
    (['-p', 'segment_durations:=[]'], "parameter 'segment_durations' must be a non-empty list"),
    (['-p', 'path:=segments', '-p', 'segment_durations:=[1, 2]'],
     'segment_durations, segment_speeds and segment_yaw_rates must have the same length'),
    (['-p', 'dt:=0.02', '-p', 'dt:=0.03'], "-p dt is given twice ('0.02' and '0.03')"),
    (['--prefix', 'a'], "--prefix must look like /name or /name/name, got 'a'"),
    (['--prefix', '//a'], "--prefix must look like /name or /name/name, got '//a'"),
    (['--prefix', ('/' + 'p' * 64) * 3], "--prefix and the id 'follower' make ROS names of 249 "
                                         'characters, more than ROS 2 accepts (247)'),
    (['--formation', str(REPO / 'test' / 'data' / 'formation_loud_noise.yaml')],
     'formation follower range: noise must be a number in [0.001, 1000] m'),
    (['--formation', str(REPO / 'test' / 'data' / 'formation_broken.yaml')],
     "cannot read the formation: while parsing a flow sequence"),
])
def test_bad_arguments_stop_before_any_node_starts(tmp_path: Path, args: list[str],
                                                   text: str) -> None:
    """Exit 2, one line naming the option and the value; no node was started (no logs)."""
    out = tmp_path / 'bad'
    result = run(*args, '--out', str(out), timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('run_formation.sh: error: ') and \
        text in lines[0], lines
    assert not out.exists() or not any(out.iterdir())


def test_an_earlier_run_is_never_overwritten(tmp_path: Path) -> None:
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'summary.json').write_text('{"earlier": true}')
    result = run('--steps', '3', '--out', str(out), timeout=30)
    assert result.returncode == 2 and 'is not empty (summary.json' in result.stderr
    assert json.loads((out / 'summary.json').read_text()) == {'earlier': True}
    help_text = run('--help', timeout=30)
    assert help_text.returncode == 0 and '--formation FILE' in help_text.stdout


# --- faults, as a user meets them -----------------------------------------------------------
def node_pid(command_part: str, namespace_part: str) -> int | None:
    """PID of the running node process whose command line holds both strings."""
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            command = (entry / 'cmdline').read_bytes().replace(b'\0', b' ').decode()
        except OSError:
            continue
        if command_part in command and namespace_part in command and 'python' in command:
            return int(entry.name)
    return None


def test_a_second_run_in_the_same_domain_stops_both(tmp_path: Path, ros_domain: int) -> None:
    """Two runs started in one ROS domain with the same topic names (no --prefix): their
    handshakes see each other's run_id and both stop, exit 1, summaries not ok, naming the
    other run; nothing is reported as success."""
    args = ('--steps', '100000', '--domain-id', str(ros_domain), '--no-record',
            '--timeout', '120')
    first = subprocess.Popen([str(SCRIPT), '--out', str(tmp_path / 'a'), '--run-id', 'run_a',
                              *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    second = subprocess.Popen([str(SCRIPT), '--out', str(tmp_path / 'b'), '--run-id', 'run_b',
                               *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    outputs = [p.communicate(timeout=150) for p in (first, second)]
    for process, name, (_, stderr) in zip((first, second), 'ab', outputs):
        assert process.returncode == 1, stderr
        summary = json.loads((tmp_path / name / 'summary.json').read_text())
        assert summary['ok'] is False and 'run_a' in summary['failure'] + stderr \
            or 'run_b' in summary['failure'] + stderr, summary['failure']
        assert "parameter 'run_id'" in (summary['failure'] or ''), summary['failure']


def test_prefixed_runs_share_a_domain_without_mixing(tmp_path: Path, ros_domain: int) -> None:
    """Two runs at once in one domain under --prefix /pa and /pb: /tf, /tf_static, /clock and
    /diagnostics are remapped under each prefix, so each bag holds exactly what its own
    nodes published (no extra message) and each run equals the pure simulation."""
    steps = 300
    processes = {prefix: subprocess.Popen(
        [str(SCRIPT), '--prefix', f'/{prefix}', '--steps', str(steps), '--seed', '6',
         '--out', str(tmp_path / prefix), '--domain-id', str(ros_domain), '--timeout', '150'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for prefix in ('pa', 'pb')}
    ref = run_trial(node_scenario('range'), 'ram', 6, 0, steps)
    for prefix, process in processes.items():
        stdout, stderr = process.communicate(timeout=180)
        assert process.returncode == 0, stdout + stderr
        summary = json.loads((tmp_path / prefix / 'summary.json').read_text())
        recording = summary['recording']
        assert recording['complete'] and recording['extra'] == {}
        assert recording['counts'] == recording['expected']
        assert recording['counts'][f'/{prefix}/clock'] == 2 * steps
        assert recording['counts'][f'/{prefix}/tf'] == 3 * 2 * steps
        assert all(topic.startswith(f'/{prefix}/') for topic in recording['counts'])
        np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0,
                                   atol=TOL)


def test_foreign_messages_in_the_recording_fail_the_run(tmp_path: Path, ros_domain: int,
                                                        ros_init) -> None:
    """A stray node publishing on the run's /x/tf during the run: the bag holds messages no
    node of the run published; the run is not reported as a success (exit 1, 'extra')."""
    from rclpy.node import Node
    from tf2_msgs.msg import TFMessage

    from formopt_ros.ros import qos
    ros_init()
    stray = Node('stray_tf')
    publisher = stray.create_publisher(TFMessage, '/x/tf', qos.TF)
    process = subprocess.Popen(
        [str(SCRIPT), '--prefix', '/x', '--steps', '600', '--out', str(tmp_path / 'x'),
         '--domain-id', str(ros_domain), '--timeout', '150'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sent = 0
    while process.poll() is None:
        if publisher.get_subscription_count() > 0:         # the recorder is up
            publisher.publish(TFMessage())
            sent += 1
        time.sleep(0.02)                                   # pacing the stray, not a sync
    stdout, stderr = process.communicate(timeout=30)
    stray.destroy_node()
    assert sent > 0
    assert process.returncode == 1, stdout + stderr
    summary = json.loads((tmp_path / 'x' / 'summary.json').read_text())
    assert summary['ok'] is False and summary['recording']['extra']['/x/tf'] > 0
    assert 'no node of this run published' in summary['failure']


@pytest.mark.parametrize('steps', [2, 3])
def test_short_runs_are_recorded_completely(tmp_path: Path, ros_domain: int, steps: int) -> None:
    """2 and 3 steps: every node delivers its last messages before it exits; the recording
    holds every message the nodes say they published."""
    out = tmp_path / 'short'
    result = run('--steps', str(steps), '--out', str(out), '--domain-id', str(ros_domain),
                 '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    recording = summary['recording']
    assert summary['ok'] and recording['complete'] and recording['missing'] == {}
    counts = read_bag(out / 'run.mcap').counts()
    assert counts['/follower/measurement'] == steps and counts['/follower/estimate'] == steps


def test_respawned_nodes_resume_exactly(tmp_path: Path, ros_domain: int) -> None:
    """--respawn: the estimator and then the follower are killed with SIGKILL mid-run; each is
    restarted and resumes from its checkpoint; the lockstep run still equals the pure
    simulation (1e-9) and the summary lists the restarts."""
    import os
    import signal
    import time
    steps, out = 1200, tmp_path / 'respawn'
    process = subprocess.Popen([str(SCRIPT), '--measurement', 'bearing', '--strategy', 'rq',
                                '--seed', '4', '--steps', str(steps), '--out', str(out),
                                '--domain-id', str(ros_domain), '--respawn', '2',
                                '--prefix', '/respawn', '--timeout', '150'],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = []
    deadline = time.monotonic() + 60
    for node in ('estimator_planner', 'follower_sim'):
        # mid-run: once the node has saved a checkpoint, and a little later
        checkpoint = out / 'checkpoints' / f'follower.{node}.pkl'
        while not checkpoint.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        pid = node_pid(f'lib/formopt_ros/{node}', '__ns:=/respawn/follower')
        assert pid is not None and process.poll() is None, (node, process.poll())
        os.kill(pid, signal.SIGKILL)
        killed.append(node)
    stdout, stderr = process.communicate(timeout=170)
    assert process.returncode == 0, stdout + stderr
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['ok'] and summary['steps'] == steps
    assert summary['restarts'] == {f'follower.{n}': [-9] for n in killed}
    # a killed node's last step may be lost in flight (its checkpoint counts it): at most that
    recording = summary['recording']
    assert recording['complete'] or recording['lost_in_flight'], recording
    ref = run_trial(node_scenario('bearing'), 'rq', 4, 0, steps)
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    assert summary['resumed']['from_step'] > 0


@pytest.mark.parametrize('node, respawn', [('leader_sim', 0), ('follower_sim', 1)])
def test_a_node_stopped_from_outside_fails_the_run_or_is_restarted(
        tmp_path: Path, ros_domain: int, node: str, respawn: int) -> None:
    """A `kill` (SIGTERM) of one simulator mid-run, which the node answers with exit code 0
    and a summary saying so: without --respawn the run fails at once naming the node and the
    signal; with it the node is restarted from its checkpoint and the run ends ok."""
    import os
    out, prefix = tmp_path / 'killed', f'/killed_{node}'
    process = subprocess.Popen([str(SCRIPT), '--measurement', 'range', '--steps', '600',
                                '--out', str(out), '--domain-id', str(ros_domain), '--respawn',
                                str(respawn), '--prefix', prefix, '--timeout', '120'],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    name = node if node == 'leader_sim' else f'follower.{node}'
    log = out / 'follower.estimator_planner.log'
    deadline = time.monotonic() + 60
    while not (log.exists() and ' ready ' in log.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)                             # mid-run: 600 lockstep steps take 5-20 s
    pid = node_pid(f'lib/formopt_ros/{node}', f'__ns:={prefix}')
    assert pid is not None and process.poll() is None, process.poll()
    os.kill(pid, signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=150)
    summary = json.loads((out / 'summary.json').read_text())
    if respawn:
        assert process.returncode == 0 and summary['ok'], stdout + stderr
        assert summary['restarts'] == {name: [0]}
        assert f'{name} was stopped by SIGTERM; restarting it' in stderr
    else:
        assert process.returncode == 1 and not summary['ok'], stdout + stderr
        assert summary['failure'].startswith(f'{name} was stopped by SIGTERM before the run '
                                             'finished'), summary['failure']


def _alive_with(marker: str) -> list[str]:
    """Command lines of live processes that mention ``marker`` (the run's output folder)."""
    alive = []
    for proc in Path('/proc').iterdir():
        if proc.name.isdigit():
            try:
                line = (proc / 'cmdline').read_bytes().replace(b'\0', b' ').decode()
            except OSError:
                continue
            if marker in line:
                alive.append(line)
    return alive


@pytest.mark.parametrize('signum, background', [
    (signal.SIGHUP, False), (signal.SIGTERM, False), (signal.SIGINT, False),
    (signal.SIGINT, True)], ids=['SIGHUP', 'SIGTERM', 'SIGINT', 'SIGINT-background'])
def test_a_signal_ends_every_process_and_writes_the_summary(
        tmp_path: Path, ros_domain: int, signum: int, background: bool) -> None:
    """A realtime run of 100 s, signalled three times once its nodes started (the terminal
    closed, a kill, Ctrl-C, or `kill -INT` of a run a script started with `&`, which inherits
    SIGINT ignored): exit 1, summary.json names the signal, and 5 s later no process of the
    run lives."""
    out = tmp_path / 'signalled'
    process = subprocess.Popen([str(SCRIPT), '--measurement', 'range', '--mode', 'realtime',
                                '--steps', '1000', '--out', str(out), '--domain-id',
                                str(ros_domain)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, preexec_fn=(
                                   lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
                               if background else None)
    assert process.stdout is not None
    for line in process.stdout:                  # blocks per line until the nodes started
        if 'started' in line:
            break
    for _ in range(3):                           # an impatient user: the later ones are ignored
        process.send_signal(signum)
        time.sleep(0.3)
    try:
        _, stderr = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:           # the stop hung: its stacks are on stderr
        process.kill()
        pytest.fail(f'no exit 60 s after the signal: {process.communicate()[1]}')
    assert process.returncode == 1, stderr
    summary = json.loads((out / 'summary.json').read_text())
    assert not summary['ok'] and summary['failure'].startswith(
        f'interrupted by {signal.Signals(signum).name}'), summary['failure']
    deadline = time.monotonic() + 5.0
    while _alive_with(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive_with(str(out))


SIGNAL_WHILE_POLLING = """
import os, signal, subprocess, sys
from formopt_ros.cli import supervisor
supervisor.stop_on_signals()
child = subprocess.Popen(['sleep', '30'])
with supervisor.supervising():
    os.kill(os.getpid(), signal.SIGHUP)
    while child.poll() is None and not supervisor.interrupted_by():
        pass
    os.kill(os.getpid(), signal.SIGTERM)
    child.kill()
    print(supervisor.interrupted_by(), child.wait())
os.kill(os.getpid(), signal.SIGINT)
if sys.argv[1] == 'outside':
    supervisor.RECEIVED_SIGNALS.clear()
    supervisor.stop_on_signals()
    os.kill(os.getpid(), signal.SIGINT)
"""


@pytest.mark.parametrize('where', ['inside', 'outside'])
def test_a_signal_while_processes_are_polled_is_only_recorded(where: str) -> None:
    """While run_formation polls its processes a signal only records itself (raised there, a
    KeyboardInterrupt can leave Popen.poll()'s lock held and the stop's wait() blocks for
    ever); later signals are ignored; outside the polling the first signal raises."""
    result = subprocess.run([sys.executable, '-c', SIGNAL_WHILE_POLLING, where],
                            capture_output=True, text=True, timeout=60)
    assert result.stdout.split('\n')[0] == 'interrupted by SIGHUP -9'
    assert (result.returncode, 'KeyboardInterrupt' in result.stderr) == \
        ((-signal.SIGINT, True) if where == 'outside' else (0, False))


def test_nodes_end_when_run_formation_is_killed(tmp_path: Path, ros_domain: int) -> None:
    """run_formation killed by SIGKILL once its nodes are up (no handler of it runs): the kernel
    sends each node SIGTERM, each writes its summary saying so (not ok: stopped before the last
    of its 1000 steps), 5 s later no process of the run lives, and the run's own summary.json
    is the placeholder it wrote at start (not ok)."""
    out = tmp_path / 'killed'
    process = subprocess.Popen([str(SCRIPT), '--measurement', 'range', '--mode', 'realtime',
                                '--steps', '1000', '--out', str(out), '--domain-id',
                                str(ros_domain)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    names = ('leader_sim', 'follower.follower_sim', 'follower.estimator_planner')
    logs = [out / f'{name}.log' for name in names]
    deadline = time.monotonic() + 60.0
    while not all(log.exists() and ' ready ' in log.read_text() for log in logs):
        assert time.monotonic() < deadline and process.poll() is None, 'the nodes never started'
        time.sleep(0.1)
    process.kill()
    process.communicate(timeout=30)
    deadline = time.monotonic() + 5.0
    while _alive_with(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive_with(str(out))
    for name in names:
        summary = json.loads((out / f'{name}.json').read_text())
        assert summary['stopped_by'] == 'SIGTERM' and not summary['ok'], summary
    for name in names[:2]:
        assert json.loads((out / f'{name}.json').read_text())['complete'] is False
    summary = json.loads((out / 'summary.json').read_text())      # what the run left before
    assert not summary['ok'] and 'ended before it wrote its summary' in summary['failure']


def test_a_start_failure_leaves_no_process_behind(tmp_path: Path, ros_domain: int,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The third node cannot be started (an OSError, e.g. a path the system refuses): exit 1,
    summary.json names the error, and no process of the run lives 5 s later."""
    from formopt_ros.cli import run_formation as command
    from formopt_ros.cli.supervisor import Launcher
    start = Launcher.start

    def failing_start(self: Launcher, *args: object, **kwargs: object) -> object:
        if len(self.processes) == 2:
            raise OSError(36, 'File name too long')
        return start(self, *args, **kwargs)

    monkeypatch.setattr(Launcher, 'start', failing_start)
    out = tmp_path / 'failed'
    code = command.main(['--formation', str(FIG4), '--steps', '10', '--out', str(out),
                         '--domain-id', str(ros_domain)])
    assert code == 1
    summary = json.loads((out / 'summary.json').read_text())
    assert not summary['ok'] and 'File name too long' in summary['failure']
    assert len(summary['exit_codes']) == 2 and None not in summary['exit_codes'].values()
    assert 'File name too long' in capsys.readouterr().err
    deadline = time.monotonic() + 5.0
    while _alive_with(str(out)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive_with(str(out))


def test_a_node_hanging_after_its_part_is_named_not_failed(
        tmp_path: Path, ros_domain: int, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """leader_sim's process outlives its node, deaf to SIGINT and SIGTERM (a hang on exit after
    its summary was written): the stop kills it, the run stays ok (exit 0), names it in
    killed_after_its_part and warns on stderr."""
    from formopt_ros.cli import run_formation as command
    from formopt_ros.cli import supervisor
    wrappers = tmp_path / 'scripts'
    wrappers.mkdir()
    for node in ('leader_sim', 'follower_sim', 'estimator_planner', 'recorder'):
        real = supervisor.SCRIPTS / f'{node}.sh'
        body = (f"trap '' INT TERM\n\"{real}\" \"$@\"\nsleep 60\n" if node == 'leader_sim'
                else f'exec "{real}" "$@"\n')
        (wrappers / f'{node}.sh').write_text('#!/usr/bin/env bash\n' + body)
        (wrappers / f'{node}.sh').chmod(0o755)
    monkeypatch.setattr(supervisor, 'SCRIPTS', wrappers)
    monkeypatch.setattr(supervisor, 'STOP_WAITS', ((signal.SIGINT, 3.0), (signal.SIGTERM, 1.0),
                                                   (signal.SIGKILL, 5.0)))
    out = tmp_path / 'run'
    code = command.main(['--measurement', 'range', '--steps', '5', '--out', str(out),
                         '--domain-id', str(ros_domain)])
    summary = json.loads((out / 'summary.json').read_text())
    assert code == 0 and summary['ok'], summary['failure']
    assert summary['killed_after_its_part'] == ['leader_sim']
    assert summary['exit_codes']['leader_sim'] == -signal.SIGKILL
    assert 'leader_sim did its part but outlived' in capsys.readouterr().err


def test_paths_with_yaml_characters_stay_inside_the_output_folder(
        tmp_path: Path, ros_domain: int) -> None:
    """--out "hash #1: it's" (a comment sign, a mapping sign and a quote, which rcl would read
    as YAML): the run is ok and every file lands in that folder."""
    out = tmp_path / "hash #1: it's"
    result = run('--measurement', 'range', '--steps', '5', '--out', str(out), '--domain-id',
                 str(ros_domain), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert json.loads((out / 'summary.json').read_text())['ok']
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    assert (out / 'run.mcap').is_file() and (out / 'follower.estimator_planner.json').is_file()


def test_an_output_path_with_a_newline_is_refused_at_start(tmp_path: Path,
                                                           ros_domain: int) -> None:
    """--out with a newline (a ROS parameter would carry a space instead, and the nodes would
    write to another folder): one line, exit 2, nothing created."""
    result = run('--steps', '5', '--out', str(tmp_path / 'a\nb'), '--domain-id',
                 str(ros_domain), timeout=60)
    assert result.returncode == 2 and 'control character' in result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('followers, text', [
    ('[{id: a, sensor: range, slot: [-1, -2]}, {id: b, sensor: range, slot: [-1, -2]}]',
     "followers 'a' and 'b' share the slot [-1.0, -2.0]"),
    ('[{id: a, sensor: range, slot: [-1, -2], id: b}]', "key 'id' is given twice"),
    ('[{id: a__b, sensor: range, slot: [-1, -2]}]', "must not contain '__'"),
    ('[{id: odom, sensor: range, slot: [-1, -2]}]', 'must not be a reserved frame name'),
    (f"[{{id: {'f' * 65}, sensor: range, slot: [-1, -2]}}]", 'at most 64 characters'),
    ('[{id: a, sensor: range, slot: [-1, -2], max_speed: 0.5}]',
     'max_speed 0.5 m/s is below 1 m/s'),
    ('[{id: a, sensor: range, slot: [-1, -2], max_speed: 1.5, interfaces: real, '
     'real: {max_speed: 2.0}}]', 'max_speed is given twice'),
    ('[{id: a, sensor: range, slot: [-1, -2], interfaces: real, real: {safety_distance: 3.0}}]',
     "follower 'a': real: safety_distance 3 m leaves no point of the slot's disc"),
])
def test_misused_formation_files_stop_before_any_node_starts(tmp_path: Path, followers: str,
                                                             text: str) -> None:
    formation = tmp_path / 'formation.yaml'
    formation.write_text(f'formation:\n  followers: {followers}\n')
    out = tmp_path / 'out'
    result = run('--formation', str(formation), '--out', str(out), timeout=30)
    assert result.returncode == 2 and text in result.stderr, result.stderr
    assert not out.exists() or not any(out.iterdir())


def test_a_real_followers_limits_reach_both_of_its_nodes() -> None:
    """max_speed and safety_distance of a real follower: both its nodes get the speed (the
    base's limit, and the planner's: plan_within_reach), the estimator the distance; without
    them the nodes keep their own default speed and plan over the whole disc."""
    from formopt_ros.cli.preflight import real_names
    from formopt_ros.cli.real_run import node_parameters
    from formopt_ros.core.formation import Formation
    follower = {'id': 'a', 'sensor': 'range', 'slot': [-1.0, -2.0], 'interfaces': 'real'}
    limited = Formation.from_dict({'followers': [{**follower, 'max_speed': 1.5,
                                                  'safety_distance': 2.0}]})
    params = node_parameters(limited, 0, '/odom', 1.0, 1.0, real_names())
    assert params['field_sim']['max_speed'] == params['follower_estimator']['max_speed'] == 1.5
    assert params['follower_estimator']['safety_distance'] == 2.0
    assert params['follower_estimator']['plan_within_reach'] is True
    free = node_parameters(Formation.from_dict({'followers': [follower]}), 0, '/odom', 1.0, 1.0,
                           real_names())
    assert 'max_speed' not in free['field_sim'] and 'max_speed' not in free['follower_estimator']
    assert 'plan_within_reach' not in free['follower_estimator']


def test_overlapping_discs_are_a_warning() -> None:
    from formopt_ros.cli.preflight import check_discs
    from formopt_ros.core.formation import Formation, FollowerSpec
    from formopt_ros.core.scenario import Scenario
    near = [FollowerSpec(name, Scenario.paper('range', p_o=slot, r=0.3))
            for name, slot in (('a', (-1.0, -2.0)), ('b', (-1.0, -2.5)))]
    import contextlib
    import io
    stream = io.StringIO()
    with contextlib.redirect_stderr(stream):
        check_discs(Formation('leader', tuple(near)), Path('f.yaml'))
    assert "warning: --formation f.yaml: the discs of 'a' and 'b' overlap" in stream.getvalue()


def test_an_estimator_that_outlives_its_peers_fails_the_run(tmp_path: Path) -> None:
    """An estimator still running ORPHAN_GRACE s after its follower_sim ended (a restart after
    its peers had left, which waits for them forever) is a failure naming both; within the
    grace, or with its peers alive, it is not."""
    from formopt_ros.cli.supervisor import ORPHAN_GRACE, Process, orphaned

    def process(name: str, command: list[str]) -> Process:
        return Process(name, subprocess.Popen(command), tmp_path / f'{name}.log', command)

    estimator = process('f.estimator_planner', ['sleep', '60'])
    leader, sim = process('leader_sim', ['sleep', '60']), process('f.follower_sim', ['true'])
    try:
        sim.process.wait(timeout=10)
        assert orphaned([(estimator, [leader, sim])]) == ''          # sim not seen ended
        sim.ended_at = time.monotonic() - ORPHAN_GRACE / 2
        assert orphaned([(estimator, [leader, sim])]) == ''          # within the grace
        sim.ended_at = time.monotonic() - ORPHAN_GRACE - 0.1
        assert orphaned([(estimator, [leader, sim])]) == (
            f'f.estimator_planner still ran {ORPHAN_GRACE:g} s after f.follower_sim ended: '
            'its peers are gone, nothing is left to estimate')
        estimator.process.kill()
        estimator.process.wait(timeout=10)
        assert orphaned([(estimator, [leader, sim])]) == ''          # it ended too
    finally:
        for item in (estimator, leader):
            item.process.kill()
            item.process.wait(timeout=10)
