"""A node started with a bad parameter value exits with code 2 and names it, no traceback."""
from __future__ import annotations

import pytest

from formopt_ros.ros.params import ParameterError
from formopt_ros.ros.runtime import check_output_path

CASES = [
    ('leader_sim', 'dt', '-1.0', '-1.0'),
    ('follower_sim', 'dt', '0.0', '0.0'),
    ('estimator_planner', 'strategy', 'foo', "'foo'"),
    ('follower_sim', 'measurement', 'sonar', "'sonar'"),
    ('estimator_planner', 'seed', '-3', '-3'),
    ('leader_sim', 'mode', 'warp', "'warp'"),
    ('estimator_planner', 'sigma_v', 'fast', "'fast'"),
    ('follower_sim', 'formation_slot', '[1.0, 2.0, 3.0]', '[1.0, 2.0, 3.0]'),
]


@pytest.mark.parametrize(('node', 'name', 'value', 'shown'), CASES,
                         ids=[f'{c[0]}-{c[1]}' for c in CASES])
def test_bad_parameter_exits_2(node_process, node: str, name: str, value: str,
                               shown: str) -> None:
    process = node_process(node, {name: value})
    code = process.wait(timeout=60.0)
    stderr = process.stderr
    assert code == 2, stderr
    assert 'Traceback' not in stderr
    assert f"parameter '{name}'" in stderr
    assert f'got {shown}' in stderr
    assert ' ready ' not in stderr


MISUSE = [
    ('estimator_planner', ['-p', 'whatever:=1'], "unknown parameter 'whatever'"),
    ('estimator_planner', ['-p', 'stratgy:=rq'], "did you mean 'strategy'"),
    ('estimator_planner', ['--bogus'], 'bad ROS arguments'),
    ('estimator_planner', ['--params-file', '/nonexistent/p.yaml'], 'params file'),
    ('estimator_planner', ['-p', 'gbs_cell:=0.0001'], "parameter 'gbs_cell' must be"),
    ('follower_sim', ['-p', 'formation_slot:=[.nan, 1.0]'], "parameter 'formation_slot'"),
    ('follower_sim', ['-p', 'summary_path:=/dev/null/s.json'], "parameter 'summary_path'"),
    ('leader_sim', ['-p', 'checkpoint_path:=/dev/null/c.pkl'], "parameter 'checkpoint_path'"),
    ('recorder', ['-p', 'chunk_size:=100000000', '-p', 'output_path:=/tmp/never.mcap'],
     "parameter 'chunk_size' must be an integer in [1024, 67108864]"),
    ('estimator_planner', ['-p', 'leader_id:=a b'], "parameter 'leader_id' must be a name of"),
    ('follower_sim', ['-p', 'follower_id:=x/y'], "parameter 'follower_id' must be a name of"),
    ('follower_sim', ['-p', 'follower_id:=odom'], "'follower_id' must not be a reserved"),
    ('estimator_planner', ['-p', 'leader_id:=a__b'], "parameter 'leader_id' must not contain"),
    ('leader_sim', ['-p', 'segment_durations:=[]'], 'got a value without a type'),
    ('leader_sim', ['-p', 'path:=s-curve'], "parameter 'amplitude' of a path of kind"),
    ('estimator_planner', ['-p', 'path:=s-curve', '-p', 'amplitude:=0.5', '-p',
                           'omega_leader:=0.3'], "parameter 'omega_leader' is not read by"),
    ('estimator_planner', ['-p', 'bearing_every:=5'], "parameter 'bearing_every' is for"),
    ('follower_estimator', ['-p', 'sensor_mount:=[0.1, 0.0, 0.0, 0.0, 0.0, 90.0]'],
     "parameter 'sensor_mount': angles are in radians"),
    ('follower_estimator', ['-p', 'initial_pose:=[-1.0, -2.0, 45.0]'],
     "parameter 'initial_pose': angles are in radians"),
    ('field_sim', ['-p', 'camera_mount:=[0.1, 0.0, -90.0]'],
     "parameter 'camera_mount': angles are in radians"),
    ('field_sim', ['-p', 'formation_slot:=[-60.0, 5.0]'],
     "beyond the simulated radio's 50 m"),
]


@pytest.mark.parametrize(('node', 'extra', 'text'), MISUSE,
                         ids=[f'{m[0]}-{m[1][-1][:20]}' for m in MISUSE])
def test_misuse_is_one_line_exit_2(node_process, node: str, extra: list[str],
                                   text: str) -> None:
    """Typos, unknown parameters, values that would hang or exhaust memory, unwritable
    outputs: refused at start with exit code 2 and one 'node: error:' line, no traceback."""
    process = node_process(node, {}, extra=extra)
    assert process.wait(timeout=60.0) == 2, process.stderr
    errors = [line for line in process.stderr.splitlines() if f'{node}: error:' in line]
    assert len(errors) == 1 and text in errors[0], process.stderr
    assert 'Traceback' not in process.stderr and ' ready ' not in process.stderr


def test_existing_summary_is_not_overwritten(node_process, tmp_path) -> None:
    """An existing summary file is refused at start (unless the node resumes a checkpoint)."""
    summary = tmp_path / 'summary.json'
    summary.write_text('{"earlier": true}')
    process = node_process('leader_sim', {'summary_path': str(summary)})
    assert process.wait(timeout=60.0) == 2 and 'exists; refusing' in process.stderr
    assert summary.read_text() == '{"earlier": true}'


def test_a_params_file_of_the_users_own_is_read_whole(node_process, tmp_path) -> None:
    """A node script given a --params-file reads it alone (config/<node>.yaml only restates
    the defaults): a quoted number in it is converted and checked, where next to the config
    file rcl kept the config's value and the user's was lost without a word."""
    mine = tmp_path / 'mine.yaml'
    mine.write_text('/**/follower_estimator:\n  ros__parameters:\n    sensor: bearing\n'
                    '    deviation_fraction: "0.9"\n')
    process = node_process('follower_estimator', {'summary_path': str(tmp_path / 's.json')},
                           extra=['--params-file', str(mine)])
    assert process.wait(timeout=60.0) == 2, process.stderr
    assert 'deviation_fraction 0.9: a follower that measures bearings' in process.stderr


def test_a_params_file_for_another_node_is_named(node_process, tmp_path) -> None:
    """A params file whose only section is a near miss of the node's name (a typo), or its
    name in another namespace (rcl takes a key without '/' as the root namespace's) or its
    old name after a rename, is refused with exit code 2 naming the section; one for other
    nodes only is a warning (a file shared by several nodes), and the node runs on."""
    typo, other = tmp_path / 'typo.yaml', tmp_path / 'other.yaml'
    root = tmp_path / 'root.yaml'
    typo.write_text('follower_estimater:\n  ros__parameters:\n    max_speed: 0.5\n')
    root.write_text('follower_estimator:\n  ros__parameters:\n    max_speed: 0.5\n')
    process = node_process('follower_estimator', {'summary_path': str(tmp_path / 'r.json')},
                           extra=['--params-file', str(root)])      # in a test namespace
    assert process.wait(timeout=60.0) == 2, process.stderr
    assert "section 'follower_estimator' does not apply to node /" in process.stderr
    anywhere = tmp_path / 'anywhere.yaml'          # rcl does not apply it to a renamed node
    anywhere.write_text('/**/follower_estimator:\n  ros__parameters:\n    max_speed: 0.5\n')
    process = node_process('follower_estimator', {'summary_path': str(tmp_path / 'n.json')},
                           extra=['-r', '__node:=est', '--params-file', str(anywhere)])
    assert process.wait(timeout=60.0) == 2, process.stderr
    assert "section '/**/follower_estimator' does not apply to node /" in process.stderr
    other.write_text('/f1/leader_sim:\n  ros__parameters:\n    speed: 0.5\n')
    process = node_process('follower_estimator', {'summary_path': str(tmp_path / 't.json')},
                           extra=['--params-file', str(typo)])
    assert process.wait(timeout=60.0) == 2, process.stderr
    assert "section 'follower_estimater' is not this node" in process.stderr
    process = node_process('follower_estimator', {'summary_path': str(tmp_path / 'o.json'),
                                                  'duration': 0.2},
                           extra=['--params-file', str(other)])
    assert process.wait(timeout=60.0) == 0, process.stderr
    assert f'params file {other} has no section for follower_estimator (it has ' \
        '/f1/leader_sim)' in process.stderr


def test_help_does_not_start_the_node(node_process) -> None:
    """--help prints every parameter and exits 0 without starting a node."""
    process = node_process('estimator_planner', {}, extra=['--help'])
    assert process.wait(timeout=60.0) == 0
    assert 'resend_timeout' in process.stdout and 'checkpoint_path' in process.stdout
    assert ' ready ' not in process.stderr


def test_an_integer_is_accepted_for_a_float_parameter(ros_init) -> None:
    """-p dt:=1 (an integer) sets the float parameter dt to 1.0 instead of a type error; so
    does a list of integers for a list of floats (segment_durations:=[1, 2])."""
    from harness.ros import node_args

    from formopt_ros.ros.nodes.leader_sim import LeaderSim
    ros_init()
    node = LeaderSim(node_args('leader_sim', 'leader', {
        'dt': 1, 'path': 'segments', 'segment_durations': [1, 2],
        'segment_speeds': [1, 2], 'segment_yaw_rates': [0, 0]}))
    try:
        assert node.params['dt'] == 1.0 and isinstance(node.params['dt'], float)
        durations = node.params['segment_durations']
        assert durations == [1.0, 2.0] and all(isinstance(d, float) for d in durations)
    finally:
        node.destroy_node()


def test_a_list_of_floats_may_be_typed_with_integers(node_process, tmp_path) -> None:
    """-p sensor_mount:=[0.2, 0, 0, 0, 0, 0.5] on the command line (rcl refuses a list that
    mixes integers and floats): the node starts with it as floats and runs."""
    summary = tmp_path / 'mount.json'
    process = node_process('follower_estimator', {'summary_path': str(summary),
                                                  'duration': 0.3},
                           extra=['-p', 'sensor_mount:=[0.2, 0, 0, 0, 0, 0.5]'])
    assert process.wait(timeout=60.0) == 0, process.stderr
    assert summary.exists() and 'Traceback' not in process.stderr


def test_outputs_through_a_broken_link_are_refused_at_start(node_process, tmp_path) -> None:
    """A summary or checkpoint path through a symbolic link to nothing, or through a loop of
    links, is refused at start naming the parameter (a reviewer's checkpoint_path below a
    dangling link ended in a traceback mid-run, and a summary_path was lost at shutdown)."""
    (tmp_path / 'dangling').symlink_to(tmp_path / 'missing' / 'deeper')
    (tmp_path / 'loop').symlink_to(tmp_path / 'loop')
    for path in ('dangling', 'dangling/s.json', 'loop/s.json'):
        with pytest.raises(ParameterError, match="^parameter 'summary_path': cannot write "
                                                 '.* is a symbolic link to '):
            check_output_path('summary_path', str(tmp_path / path))
    process = node_process('leader_sim', {'checkpoint_path': str(tmp_path / 'dangling/c.pkl')})
    assert process.wait(timeout=60.0) == 2, process.stderr
    assert "parameter 'checkpoint_path': cannot write" in process.stderr
    assert 'Traceback' not in process.stderr and not (tmp_path / 'missing').exists()


NOTATIONS = ['1e-2', '1E3', '.5', '+1.0', '5.', '-.Inf', '.nan', '0x10', '010', '08', 'y', 'Off',
             'tRue', '1e400', '1_000', "'0.5'", '!!str 1', '[1e-2, 2E-2]', 'null']


def rcl_value(text: str) -> object:
    """The value rcl gives a node for ``-p x:=text`` (or the exception's type name)."""
    import rclpy
    from rclpy.node import Node
    context = rclpy.Context()
    try:
        rclpy.init(args=['--ros-args', '-p', f'x:={text}'], context=context)
        node = Node('notation_probe', context=context)
        value = node._parameter_overrides['x'].value
        node.destroy_node()
        return list(value) if isinstance(value, (list, tuple)) or hasattr(value, 'tolist') \
            else value
    except Exception as error:                 # rcl refuses some lists
        return type(error).__name__
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize('text', NOTATIONS + ['[a, 1]'])
def test_p_values_are_typed_the_way_rcl_types_them(text: str) -> None:
    """parse_value (run_formation's -p) gives the value and type rcl gives the node."""
    import math

    from formopt_ros.ros.params import parse_value
    expected = rcl_value(text)
    try:
        mine = parse_value('x', text)
    except ParameterError:
        assert expected == 'RCLError'
        return
    assert type(mine) is type(expected)
    assert mine == expected or (math.isnan(mine) and math.isnan(expected))


def test_scientific_notation_reaches_preflight_and_node_alike(ros_init) -> None:
    """-p dt:=2E-2 and repeat_segments:=y: run_formation's preflight and leader_sim both take
    0.02 s and True."""
    from harness.ros import node_args

    from formopt_ros.cli.preflight import check_extras
    from formopt_ros.ros.nodes.leader_sim import LeaderSim
    assert check_extras({'dt': '2E-2', 'repeat_segments': 'y', 'sigma_v': '.5e-1'}) == {
        'dt': 0.02, 'repeat_segments': True, 'sigma_v': 0.05}
    # rcl refuses [0, 0.1] (two types); the spec makes it floats, passed on as rcl takes them
    from formopt_ros.cli.supervisor import format_value
    yaw_rates = check_extras({'segment_yaw_rates': '[0, 1e-1]'})['segment_yaw_rates']
    assert rcl_value('[0, 1e-1]') == 'RCLError' and yaw_rates == [0.0, 0.1]
    assert rcl_value(format_value(yaw_rates)) == [0.0, 0.1]
    ros_init()
    node = LeaderSim(node_args('leader_sim', 'leader', {}) + [
        '-p', 'dt:=2E-2', '-p', 'path:=segments', '-p', 'repeat_segments:=y'])
    try:
        assert node.params['dt'] == 0.02 and node.params['repeat_segments'] is True
    finally:
        node.destroy_node()
