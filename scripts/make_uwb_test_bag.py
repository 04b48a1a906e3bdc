"""Turn the TIERS UWB extract (CSV) into test/data/tiers_uwb_case4_test3.mcap, a bag of standard
message types: each robot's nav_msgs/Odometry, synthesised from its motion-capture poses (the
data set has none), the sensor_msgs/Range between them, and the motion-capture poses as
geometry_msgs/PoseStamped ground truth.

Source: github.com/TIERS/uwb-relative-localization-dataset (MIT licence, (c) 2023 TIERS), commit
5dceab32, case_4/ros2/test3/test3_0.db3: /uwb/tof/n_6/n_7/distance and the VRPN poses of
turtlebot6 ('follower') and turtlebot7 ('leader'), extracted to CSV (t_s, range_m) and
(t_s, x_m, y_m, yaw_rad) by the script in that extract. Synthesised odometry: each 30 Hz pose
interval becomes the twist of the arc through both poses (omega = dyaw / dt, v = chord /
(dt sinc(dyaw / 2))), stamped at the interval's end, as a base reports it. The poses carry
their publish times, and a few arrive in bursts 0.1 ms apart (1 cm in 0.1 ms would read as
100 m/s): the odometry skips poses less than MIN_INTERVAL after the last one it used.

Usage: python scripts/make_uwb_test_bag.py EXTRACT_FOLDER OUT.mcap
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_typestore

from formopt_ros.bag.writer import BagWriter
from formopt_ros.core.model import wrap_angle

#: Seconds since the epoch of the extract's t = 0 (the bag's first range).
EPOCH_NS = 1684138632_701700000
#: Shortest pose interval the synthesised odometry differentiates over, s.
MIN_INTERVAL = 0.01
TOPICS = {'leader_odom': '/leader/odom', 'follower_odom': '/follower/odom',
          'range': '/uwb/range', 'leader_truth': '/leader/mocap',
          'follower_truth': '/follower/mocap'}


def arc_twists(poses: np.ndarray) -> list[tuple[float, float, float]]:
    """(t s, v m/s, omega rad/s) of each interval between consecutive (t, x, y, yaw) poses."""
    kept = [poses[0]]
    for pose in poses[1:]:
        if pose[0] - kept[-1][0] >= MIN_INTERVAL:
            kept.append(pose)
    out = []
    for (t0, x0, y0, a0), (t1, x1, y1, a1) in zip(kept[:-1], kept[1:]):
        dt = t1 - t0
        turn = float(wrap_angle(a1 - a0))
        half = 0.5 * turn
        sinc = 1.0 if half == 0.0 else math.sin(half) / half
        chord = math.hypot(x1 - x0, y1 - y0)
        heading = math.atan2(y1 - y0, x1 - x0) - (a0 + half)
        sign = 1.0 if math.cos(heading) >= 0.0 else -1.0      # driving backwards
        out.append((t1, sign * chord / (dt * sinc), turn / dt))
    return out


def main(extract: Path, out: Path) -> None:
    """Write the bag."""
    store = get_typestore(Stores.ROS2_JAZZY)
    Odometry = store.types['nav_msgs/msg/Odometry']
    Range = store.types['sensor_msgs/msg/Range']
    PoseStamped = store.types['geometry_msgs/msg/PoseStamped']
    msg = {name: store.types[f'{name}'] for name in (
        'std_msgs/msg/Header', 'builtin_interfaces/msg/Time', 'geometry_msgs/msg/Pose',
        'geometry_msgs/msg/Point', 'geometry_msgs/msg/Quaternion',
        'geometry_msgs/msg/PoseWithCovariance', 'geometry_msgs/msg/TwistWithCovariance',
        'geometry_msgs/msg/Twist', 'geometry_msgs/msg/Vector3')}

    def header(t: float, frame: str) -> object:
        ns = EPOCH_NS + int(round(t * 1e9))
        return msg['std_msgs/msg/Header'](
            stamp=msg['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id=frame)

    def pose(x: float, y: float, yaw: float) -> object:
        return msg['geometry_msgs/msg/Pose'](
            position=msg['geometry_msgs/msg/Point'](x=x, y=y, z=0.0),
            orientation=msg['geometry_msgs/msg/Quaternion'](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))

    def vector(x: float) -> object:
        return msg['geometry_msgs/msg/Vector3'](x=x, y=0.0, z=0.0)

    writer = BagWriter(out)
    types = {'leader_odom': 'nav_msgs/msg/Odometry', 'follower_odom': 'nav_msgs/msg/Odometry',
             'range': 'sensor_msgs/msg/Range', 'leader_truth': 'geometry_msgs/msg/PoseStamped',
             'follower_truth': 'geometry_msgs/msg/PoseStamped'}
    for key, topic in TOPICS.items():
        writer.add_channel(topic, types[key])
    records: list[tuple[float, str, bytes]] = []
    for robot in ('leader', 'follower'):
        poses = np.loadtxt(extract / f'truth_{robot}.csv', delimiter=',', skiprows=1)[:, :4]
        for t, x, y, yaw in poses:
            message = PoseStamped(header=header(t, 'mocap'), pose=pose(x, y, yaw))
            records.append((t, TOPICS[f'{robot}_truth'],
                            bytes(store.serialize_cdr(message, PoseStamped.__msgtype__))))
        for t, v, omega in arc_twists(poses):
            twist = msg['geometry_msgs/msg/Twist'](linear=vector(v), angular=msg[
                'geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=omega))
            message = Odometry(
                header=header(t, 'odom'), child_frame_id=f'{robot}/base_link',
                pose=msg['geometry_msgs/msg/PoseWithCovariance'](
                    pose=pose(0.0, 0.0, 0.0), covariance=np.zeros(36)),
                twist=msg['geometry_msgs/msg/TwistWithCovariance'](
                    twist=twist, covariance=np.zeros(36)))
            records.append((t, TOPICS[f'{robot}_odom'],
                            bytes(store.serialize_cdr(message, Odometry.__msgtype__))))
    for t, value in np.loadtxt(extract / 'ranges.csv', delimiter=',', skiprows=1):
        message = Range(header=header(t, 'uwb'), radiation_type=1, field_of_view=6.28,
                        min_range=0.0, max_range=100.0, range=float(value),
                        variance=0.0)
        records.append((t, TOPICS['range'],
                        bytes(store.serialize_cdr(message, Range.__msgtype__))))
    for t, topic, data in sorted(records, key=lambda r: (r[0], r[1])):
        writer.write(topic, data, EPOCH_NS + int(round(t * 1e9)))
    writer.close()


if __name__ == '__main__':
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]))
