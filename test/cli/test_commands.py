"""The command-line convention shared by every command: outputs are never overwritten, an
output that cannot be made is refused before any work, Ctrl-C / a closed pipe / a failed write
end with one line and a documented exit code, never a traceback."""
from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from formopt_ros.cli.common import CLOSED_PIPE_EXIT, INTERRUPTED_EXIT, SYSTEM_EXIT, command


def test_commands_refuse_to_overwrite_outputs(tmp_path, capsys: pytest.CaptureFixture) -> None:
    """An output folder that holds files (--out) and an output file that exists (--csv,
    --json, --figure) stop the command with exit code 2 before any work; nothing is
    overwritten."""
    from formopt_ros.cli import bench, bench_ros, montecarlo, periodic, replay
    taken = tmp_path / 'taken.csv'
    taken.write_text('keep me')
    (tmp_path / 'busy').mkdir()
    (tmp_path / 'busy' / 'summary.json').write_text('keep me')
    for main, argv in ((montecarlo.main, ['--out', str(tmp_path / 'busy')]),
                       (montecarlo.main, ['--out', str(taken)]),
                       (bench.main, ['--csv', str(taken)]),
                       (bench_ros.main, ['--json', str(taken)]),
                       (bench_ros.main, ['--json', str(tmp_path / 'busy')]),
                       (periodic.main, ['--figure', str(taken)]),
                       (replay.main, [str(taken), '--json', str(taken)])):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2, argv
        err = capsys.readouterr().err
        assert 'refusing to overwrite' in err or 'is a folder' in err, argv
    assert taken.read_text() == 'keep me'
    assert (tmp_path / 'busy' / 'summary.json').read_text() == 'keep me'


def test_outputs_through_a_dangling_link_are_refused_at_start(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """An output named through a symbolic link to nothing (the output itself, or a folder on its
    way) stops every command at start with exit 2 naming the link; before, the work ran and
    the write failed at the end (exit 1)."""
    from formopt_ros.cli import bag, bench, bench_ros, montecarlo, periodic, replay, report
    link = tmp_path / 'link'
    link.symlink_to(tmp_path / 'missing' / 'deeper')
    for target in (link, link / 'out.csv', link / 'new' / 'out.csv'):
        for main, argv in ((montecarlo.main, ['--out', str(target)]),
                           (report.main, [__file__, '--out', str(target)]),
                           (bench.main, ['--csv', str(target)]),
                           (bench_ros.main, ['--json', str(target)]),
                           (periodic.main, ['--figure', str(target)]),
                           (replay.main, [__file__, '--offline', '--json', str(target)]),
                           (bag.main, ['repair', __file__, str(target)])):
            with pytest.raises(SystemExit) as stop:
                main(argv)
            assert stop.value.code == 2, argv
            err = capsys.readouterr().err
            assert f'{link} is a symbolic link to ' in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / 'missing').exists()


@pytest.mark.parametrize('text, message', [
    (',', "got ',' (an empty name)"), ('', "got '' (an empty name)"),
    ('rq,,ram', "got 'rq,,ram' (an empty name)"), ('rq,rq', "'rq' given twice in 'rq,rq'"),
    ('rq,foo', "unknown 'foo': the names are ")])
def test_name_lists_refuse_empty_repeated_and_unknown_names(
        text: str, message: str, capsys: pytest.CaptureFixture) -> None:
    """--strategies of formopt-montecarlo and --methods of formopt-bench: exit 2 and one line
    for an empty, repeated or unknown name (',' used to crash the study with a traceback)."""
    from formopt_ros.cli import bench, montecarlo
    for main, option in ((montecarlo.main, '--strategies'), (bench.main, '--methods')):
        with pytest.raises(SystemExit) as stop:
            main([option, text])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert f'argument {option}: ' in err and message in err, err
        assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize('argv', [
    ['formopt_ros.cli.montecarlo', '--out', '/proc/formopt-study'],
    ['formopt_ros.cli.bench', '--csv', '/proc/formopt.csv'],
    ['formopt_ros.cli.bench_ros', '--json', '/proc/formopt.json'],
    ['formopt_ros.cli.periodic', '--figure', '/proc/formopt.png'],
    ['formopt_ros.cli.report', __file__, '--out', '/proc/formopt-report'],
    ['formopt_ros.cli.replay', __file__, '--offline', '--json', '/proc/formopt.json']])
def test_an_output_that_cannot_be_made_is_refused_at_start(argv: list[str]) -> None:
    """A path where nothing can be created (/proc, even for root) stops the command at once:
    exit 2, one line naming the path, no traceback, no work done."""
    done = subprocess.run([sys.executable, '-m', *argv], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2, done.stderr
    assert 'cannot create /proc/formopt' in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and done.stdout == ''


def test_missing_output_folders_are_created(tmp_path: Path) -> None:
    """An output file in folders that do not exist yet: they are made, the file written."""
    from formopt_ros.cli import bench
    target = tmp_path / 'new' / 'deeper' / 'rows.csv'
    assert bench.main(['--problems', '2', '--repeats', '1', '--methods', 'rq',
                       '--measurement', 'range', '--csv', str(target)]) == 0
    assert len(target.read_text().splitlines()) == 1 + 2       # header, one row per problem


def test_command_wrapper_turns_failures_into_one_line(capsys: pytest.CaptureFixture) -> None:
    """Ctrl-C: 'interrupted', 130; an OSError: one 'error:' line with the path, 1; a return
    value and SystemExit pass through."""
    def raising(error: BaseException):
        def main() -> int:
            raise error
        return command('tool')(main)

    assert raising(KeyboardInterrupt())() == INTERRUPTED_EXIT == 130
    assert capsys.readouterr().err == 'tool: interrupted\n'
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), '/data/out.csv')
    assert raising(full)() == SYSTEM_EXIT == 1
    assert capsys.readouterr().err == 'tool: error: No space left on device: /data/out.csv\n'
    with pytest.raises(SystemExit):
        raising(SystemExit(2))()
    assert command('tool')(lambda: 7)() == 7


def test_closed_pipe_ends_quietly(tmp_path: Path) -> None:
    """`formopt-bench ... | head -1`: the reader leaves early; the command ends with exit 141
    (as if SIGPIPE had ended it) and prints nothing on stderr (no BrokenPipeError traceback)."""
    process = subprocess.Popen(
        [sys.executable, '-m', 'formopt_ros.cli.bench', '--problems', '2', '--repeats', '1',
         '--methods', 'rq'], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert process.stdout is not None and process.stderr is not None
    process.stdout.close()                                   # the reader is gone at once
    assert process.wait(timeout=120) == CLOSED_PIPE_EXIT == 141
    assert process.stderr.read() == b''


def children(pid: int) -> list[str]:
    """The child process ids of ``pid``, started by any of its threads (Linux /proc; Dask
    starts its workers from its event loop's thread)."""
    return [child for path in Path(f'/proc/{pid}/task').glob('*/children')
            for child in path.read_text().split()]


def ignores_sigint(pid: int | str) -> bool:
    """True when process ``pid`` ignores SIGINT (the SigIgn mask of /proc/PID/status)."""
    status = Path(f'/proc/{pid}/status').read_text()
    mask = next(line for line in status.splitlines() if line.startswith('SigIgn:'))
    return bool(int(mask.split()[1], 16) >> (signal.SIGINT - 1) & 1)


def running(pid: str) -> bool:
    """Process ``pid`` exists and is not a zombie waiting for its parent."""
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except FileNotFoundError:
        return False


def pool_running(pid: int) -> bool:
    """The worker pool is up: workers that ignore SIGINT, a main process that handles it."""
    try:
        workers = children(pid)
        return bool(workers) and all(ignores_sigint(w) for w in workers) and \
            not ignores_sigint(pid)
    except (FileNotFoundError, StopIteration):
        return False


def test_ctrl_c_stops_the_study_with_one_line(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) while the Dask workers run:
    exit 130 within 30 s, stderr is the one line 'formopt-montecarlo: interrupted' (the
    workers print nothing), no worker is left 10 s later."""
    process = subprocess.Popen(
        [sys.executable, '-m', 'formopt_ros.cli.montecarlo', '--out', str(tmp_path / 'study'),
         '--jobs', '2', '--steps', '5000', '--no-figures'],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 60.0
    while not pool_running(process.pid) and time.monotonic() < deadline:
        time.sleep(0.05)                                     # polling a condition, with deadline
    workers = children(process.pid)
    assert pool_running(process.pid), 'the worker pool never started'
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=30.0)
    assert process.returncode == INTERRUPTED_EXIT, err
    assert err == 'formopt-montecarlo: interrupted\n'
    deadline = time.monotonic() + 10.0
    while any(map(running, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)                                     # polling a condition, with deadline
    assert not any(map(running, workers))


def test_the_audit_forgives_one_step_in_flight_per_restart(tmp_path: Path) -> None:
    """A killed node's last step (SUBSTEPS odometry messages) may never reach the recorder:
    after one restart a shortfall of up to SUBSTEPS per topic is reported as lost in flight,
    not a failure; without a restart, or beyond it, it fails."""
    import json

    from formopt_ros.cli.audit import audit_recording, expected_counts
    from formopt_ros.core.protocol import SUBSTEPS
    leader = {'leader_id': 'leader', 'published': {'odometry': 20, 'clock': 20, 'tf': 20}}
    expected = expected_counts('/p', leader, {})
    for short, restarts, fails in [(SUBSTEPS, 1, False), (SUBSTEPS, 0, True),
                                   (SUBSTEPS + 1, 1, True), (2 * SUBSTEPS, 2, False)]:
        counts = {**expected, '/p/leader/odom': expected['/p/leader/odom'] - short}
        (tmp_path / 'recorder_counts.json').write_text(json.dumps({'counts': counts}))
        recording, failure = audit_recording(tmp_path, '/p', leader, {}, restarts)
        assert recording['missing'] == {'/p/leader/odom': short}
        assert bool(failure) == fails and recording['lost_in_flight'] != fails, (short, restarts)


DEFERRED = """
import os, signal, sys
from formopt_ros.cli.common import ctrl_c_deferred
with ctrl_c_deferred() as stop:
    os.kill(os.getpid(), signal.SIGINT)
    print('recorded', stop(), flush=True)
    if sys.argv[1] == 'poll' and stop():
        raise KeyboardInterrupt
    print('block ends', flush=True)
"""


@pytest.mark.parametrize('where', ['poll', 'end'])
def test_ctrl_c_in_a_deferred_block_is_raised_where_it_is_polled(where: str) -> None:
    """Inside ctrl_c_deferred a SIGINT only records itself; KeyboardInterrupt comes where the
    block polls it, or when the block ends."""
    result = subprocess.run([sys.executable, '-c', DEFERRED, where], capture_output=True,
                            text=True, timeout=60)
    expected = 'recorded True\n' + ('' if where == 'poll' else 'block ends\n')
    assert (result.stdout, result.returncode) == (expected, -signal.SIGINT)
    assert 'KeyboardInterrupt' in result.stderr


@pytest.mark.parametrize('flags, message', [
    (['--strategy', 'rq'], '--strategy needs --offline'),
    (['--topic-map', __file__], '--topic-map needs --offline'),
    (['--offline', '--rate', '2'], '--rate applies to playback on ROS topics, not to --offline'),
    (['--offline', '--topic-map', __file__, '--tolerance', '1e-6'],
     '--tolerance applies to a recorded formopt_ros run, not to --topic-map'),
    (['--offline', '--skip', '5'], '--skip applies to --topic-map')])
def test_replay_refuses_a_flag_its_mode_would_not_read(
        flags: list[str], message: str, capsys: pytest.CaptureFixture) -> None:
    """replay BAG with a flag of another mode (an offline flag without --offline, a playback
    flag with it, a recorded-run flag with --topic-map): exit 2, one line naming the flag,
    before the bag is read."""
    from formopt_ros.cli import replay
    with pytest.raises(SystemExit) as stop:
        replay.main([__file__, *flags])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize('argv, message', [
    (['--robot'], '--robot needs a value'),
    (['--robot', 'f1', '--leader'], '--leader needs a value'),
    (['--robot', '1x'], '--robot must be letters'), (['--robto', 'f1'], 'unknown argument')])
def test_robot_sh_names_a_bad_argument(argv: list[str], message: str) -> None:
    """scripts/robot.sh with a flag missing its value, a bad id or an unknown flag: exit 2 and
    one line naming it, before any node starts."""
    script = Path(__file__).resolve().parents[2] / 'scripts' / 'robot.sh'
    done = subprocess.run(['bash', str(script), *argv], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 2 and message in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and done.stdout == ''


def test_a_rosbag2_folder_is_read_through_its_mcap_files(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A bag as `ros2 bag record` writes it (a folder holding one .mcap file, or several for a
    split recording) is read as one bag; a folder with none, or of sqlite3 storage, is refused
    in one line (exit 2)."""
    from formopt_ros.cli import bag
    source = Path(__file__).resolve().parents[1] / 'data' / 'tiers_uwb_case4_test3.mcap'
    folder = tmp_path / 'rosbag2_run'
    folder.mkdir()
    with pytest.raises(SystemExit) as stop:
        bag.main(['info', str(folder)])
    assert stop.value.code == 2 and 'a folder without an .mcap file' in capsys.readouterr().err
    (folder / 'run_0.mcap').symlink_to(source)
    bag.main(['info', str(folder)])
    single = capsys.readouterr().out
    assert '/uwb/range' in single
    (folder / 'run_1.mcap').symlink_to(source)      # a split: both files, as one bag
    bag.main(['info', str(folder)])
    split = capsys.readouterr().out
    counts = [int(line.split()[-1]) for text in (single, split)
              for line in text.splitlines() if line.strip().startswith('/uwb/range')]
    assert counts[1] == 2 * counts[0], (single, split)
    (folder / 'metadata.yaml').write_text(
        'rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n'
        '  relative_file_paths: [run_0.db3]\n')
    with pytest.raises(SystemExit) as stop:
        bag.main(['info', str(folder)])
    assert stop.value.code == 2 and 'a sqlite3 bag' in capsys.readouterr().err


@pytest.mark.slow
def test_the_commands_numbers_do_not_depend_on_the_blas_threads() -> None:
    """PERIODIC's design behind an S-curve (SLSQP ends at digits that depend on the BLAS thread
    count): a process that loads the commands first, with no thread count set, designs the
    cycle a Dask worker (one thread) designs, to the last digit; so --jobs 1 and --jobs 2 give
    one study."""
    from formopt_ros import BLAS_THREAD_VARIABLES
    code = ('import formopt_ros.cli\n'
            'from formopt_ros.core.scenario import Scenario\n'
            'from formopt_ros.core.strategies.phase_locked import design_phase_locked\n'
            "print(repr(design_phase_locked(Scenario.paper('range', leader={'kind': 's-curve', "
            "'amplitude': 0.5})).steady_cost))\n")
    unset = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    costs = [subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            env=env, timeout=300, check=True).stdout
             for env in (unset, {**unset, **dict.fromkeys(BLAS_THREAD_VARIABLES, '1')})]
    assert costs[0] == costs[1] and float(costs[0]) > 0.0, costs
