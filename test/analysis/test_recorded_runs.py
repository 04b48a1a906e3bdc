"""The offline tools without ROS, on a bag recorded by formopt_ros 0.1.0 (before the run
description existed): the description is reconstructed, the offline re-estimation reproduces
every recorded estimate exactly, the report and the commands work, nothing is overwritten."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rosbags')
pytest.importorskip('mcap')

from formopt_ros.analysis.offline import offline  # noqa: E402
from formopt_ros.analysis.recording import load_recording  # noqa: E402
from formopt_ros.bag import read_bag  # noqa: E402
from formopt_ros.core.scenario import Scenario  # noqa: E402
from formopt_ros.core.simulation import run_trial  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / 'data'
#: scripts/run_formation.sh --measurement bearing --strategy crm --steps 20 --seed 2 of 0.1.0.
LEGACY = DATA / 'legacy_0.1.0_lockstep_bearing_crm_seed2.mcap'
#: Its summary.json: the final estimate (m, m, rad) and mean NEES.
FINAL_ESTIMATE = [-0.7809831396564715, 2.0463658646430702, 0.4991763456520051]
MEAN_NEES = 2.295959755852919


def test_legacy_description_is_reconstructed() -> None:
    recording = load_recording(read_bag(LEGACY))
    follower = recording.follower()
    assert follower.legacy and follower.namespace == '/follower'
    description = follower.description
    assert (description.strategy, description.mode, description.follower_id) == (
        'crm', 'lockstep', 'follower')
    assert description.scenario == Scenario.paper('bearing')
    assert recording.leader_topic == '/leader/odom'


def test_legacy_offline_reproduces_every_estimate_and_the_simulation() -> None:
    """With the seed of the run (not recorded in 0.1.0 bags) even CRM's waypoints match; with
    another seed the estimates still match but the waypoints do not, and the verdict fails."""
    recording = load_recording(read_bag(LEGACY))
    result = offline(recording, seed=2)
    assert (result.steps, result.recorded_steps, result.max_stamp_diff_ns) == (20, 20, 0)
    assert result.max_diff <= 1e-12 and result.max_waypoint_diff <= 1e-12
    np.testing.assert_allclose(result.estimates[-1], FINAL_ESTIMATE, rtol=0, atol=1e-12)
    ref = run_trial(Scenario.paper('bearing'), 'crm', 2, 0, 20)
    np.testing.assert_allclose(np.array(result.estimates), ref.estimate, rtol=0, atol=1e-9)
    wrong_seed = offline(recording, seed=3)
    # the estimates follow the recorded inputs; CRM's draws differ: the verdict fails
    assert wrong_seed.max_state_diff <= 1e-12 and wrong_seed.max_covariance_diff <= 1e-12
    assert wrong_seed.max_waypoint_diff > 1e-3
    assert wrong_seed.max_diff == wrong_seed.max_waypoint_diff


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_commands_on_the_legacy_bag(tmp_path: Path) -> None:
    """replay --offline and formopt-report run without ROS; outputs are never overwritten."""
    out = tmp_path / 'offline.json'
    result = run('formopt_ros.cli.replay', str(LEGACY), '--offline', '--seed', '2',
                 '--json', str(out))
    assert result.returncode == 0, result.stderr
    assert 'OK' in result.stdout and json.loads(out.read_text())['ok'] is True
    again = run('formopt_ros.cli.replay', str(LEGACY), '--offline', '--json', str(out))
    assert again.returncode == 2 and 'exists' in again.stderr
    report = tmp_path / 'report'
    result = run('formopt_ros.cli.report', str(LEGACY), '--out', str(report))
    assert result.returncode == 0, result.stderr
    summary = json.loads((report / 'summary.json').read_text())
    assert summary['steps'] == 20 and summary['description'] == 'reconstructed from the messages'
    assert summary['mean_nees'] == pytest.approx(MEAN_NEES, rel=1e-12)
    # 20 steps of 2 dt = 0.1 s of the scenario, recorded in 0.15 s of the recorder's clock
    assert summary['run_time_s'] == pytest.approx(2.0, rel=1e-12)
    assert summary['duration_s'] < 1.0
    for name in ('trajectory.png', 'weighted_trace.png', 'nees.png'):
        assert (report / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    before = (report / 'summary.json').read_bytes()
    again = run('formopt_ros.cli.report', str(LEGACY), '--out', str(report))
    assert again.returncode == 2 and 'not an empty folder' in again.stderr
    assert (report / 'summary.json').read_bytes() == before


def test_report_names_the_steps_a_bag_lacks(tmp_path: Path) -> None:
    """A bag without the estimates, statuses and measurements of steps 1-5 (as after a repair
    that lost the first chunk): the report does not claim a full run: 15 of 20 steps,
    'missing 1-5' in summary.md and stdout, a warning on stderr; exit 0."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from formopt_ros.wire.messages import header_ns
    source = read_bag(LEGACY)
    dropped = set()                                    # (topic, log time) of steps 1-5
    for suffix in ('estimate', 'status', 'measurement', 'truth'):
        topic = f'/follower/{suffix}'
        records = [(r.log_time, header_ns(m)) for r, m in zip(
            (r for r in source.messages if r.topic == topic), (m for _, m in source.decode(
                source.find(topic))))]
        stamps = sorted({stamp for _, stamp in records if stamp > 0})[:5]
        dropped |= {(topic, log_time) for log_time, stamp in records if stamp in stamps}
    gappy = tmp_path / 'gappy.mcap'
    with open(LEGACY, 'rb') as stream, open(gappy, 'xb') as out:
        writer = Writer(out)
        writer.start(profile='ros2', library='test')
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in make_reader(stream).iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                            schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id],
                    dict(channel.metadata))
            if (channel.topic, message.log_time) not in dropped:
                writer.add_message(channels[channel.id], message.log_time, message.data,
                                   message.publish_time)
        writer.finish()
    result = run('formopt_ros.cli.report', str(gappy), '--out', str(tmp_path / 'report'))
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / 'report' / 'summary.json').read_text())
    assert (summary['steps'], summary['estimates'], summary['missing_steps']) == (20, 15, 5)
    assert summary['missing_ranges'] == '1-5'
    assert '15 of 20 (missing 1-5)' in (tmp_path / 'report' / 'summary.md').read_text()
    assert '15 of 20 (missing 1-5) steps' in result.stdout
    assert 'warning: follower: the bag lacks steps 1-5 (5 of 20' in result.stderr
