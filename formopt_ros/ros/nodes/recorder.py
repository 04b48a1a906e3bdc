"""recorder: records the formation's topics, raw CDR, into one rosbag2-compatible MCAP file."""
from __future__ import annotations

import errno
import sys
import time
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import QoSProfile

from formopt_ros import bag
from formopt_ros.bag.qos import qos_yaml
from formopt_ros.ros import qos
from formopt_ros.ros.conversions import message_class
from formopt_ros.ros.params import Param, ParameterError, declare
from formopt_ros.ros.run_config import FOLLOWERS, FORMATION_FILE
from formopt_ros.ros.runtime import Throttle, node_main
from formopt_ros.wire.formation import load_formation
from formopt_ros.wire.topics import BY_KEY, DEFAULT_LEADER, GLOBAL_TOPICS, formation_topics
from formopt_ros.wire.jsonfile import write_json

PARAMS = [
    Param('output_path', '', 'the .mcap file to write (required; an existing file is refused)'),
    FORMATION_FILE,
    Param('leader_id', DEFAULT_LEADER, 'the leader whose formation is recorded (without a '
          'formation file)'),
    FOLLOWERS,
    Param('topics', [''], "topics to record; [''] means every topic of the formation (robot "
          'topics under this node\'s namespace, the formation prefix, plus /tf, /tf_static, '
          '/clock, /diagnostics); relative names resolve in the node namespace; types of '
          'topics outside the formation table are looked up in the ROS graph'),
    Param('counts_path', '', 'on close, write the per-topic message counts here as JSON '
          '(empty: none)'),
    Param('flush_period', 1.0, 'close the current chunk and flush it to disk this often, s '
          '(bounds the loss when the recorder is killed)', 0.01, 60.0),
    Param('chunk_size', 1 << 20, 'uncompressed MCAP chunk size that also closes a chunk, bytes '
          '(a chunk is held in memory until written: at most 64 MiB)', 1024, 1 << 26),
    Param('compression', 'zstd', 'chunk compression', choices=('zstd', 'lz4', 'none')),
    Param('discovery_period', 0.5, 'period of the graph look-up for topics whose type is not in '
          'the fixed table, s', 0.01, 60.0),
]


class Recorder(Node):
    """Subscribes raw to each topic and appends the CDR bytes to one .mcap file.

    A topic's channel is registered at its first message, with the offered QoS profiles and
    the type hash of its publishers as channel metadata (like rosbag2). log_time is the
    receive time (node clock), publish_time the header stamp when the type has a header.
    A timer closes the current chunk every ``flush_period`` s, so a killed recorder loses at
    most that much (``formopt-bag repair`` recovers the rest); SIGINT or SIGTERM
    finalizes the file. A write error (a full disk: ENOSPC) stops the recording: the error
    names the file, goes to the log and the counts file, and the node exits with code 1.
    """

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments."""
        super().__init__('recorder', cli_args=cli_args)
        self.params = declare(self, PARAMS)
        p = self.params
        if not p['output_path']:
            raise ParameterError("parameter 'output_path' is required (the .mcap file to write)")
        if Path(p['output_path']).exists():
            raise ParameterError(f"parameter 'output_path': {p['output_path']} exists; "
                                 'refusing to overwrite it')
        self.throttle = Throttle(self)
        self.counts: dict[str, int] = {}
        self.pending: list[str] = []          # resolved names whose type is still unknown
        self.sources: list[tuple] = []        # (subscription, topic, type)
        self.closed = False
        self.finished = False
        self.exit_code = 0
        self.error = ''
        leader, followers = p['leader_id'], tuple(p['followers'])
        if p['formation_file']:
            try:
                formation = load_formation(p['formation_file'])
            except ValueError as error:
                raise ParameterError(f"parameter 'formation_file': {error}") from None
            leader, followers = formation.leader_id, tuple(f.id for f in formation.followers)
        global_names = {t.name for t in GLOBAL_TOPICS}
        known = {self.resolve_topic_name(name if name in global_names else name.lstrip('/')):
                 type_name for name, type_name in formation_topics(leader, followers).items()}
        wanted = []
        for name in (list(known) if list(p['topics']) == [''] else p['topics']):
            try:
                wanted.append(self.resolve_topic_name(name))
            except Exception as error:      # rclpy's invalid-name exceptions
                raise ParameterError(f"parameter 'topics': invalid topic name {name!r} "
                                     f'({type(error).__name__})') from None
        for topic in wanted:
            if topic in known:
                try:
                    message_class(known[topic], topic)     # fail early when not installed
                except bag.BagError as error:
                    raise ParameterError(f"parameter 'topics': {error}") from None
        try:
            self.writer = bag.BagWriter(p['output_path'], p['chunk_size'], p['compression'])
        except bag.BagError as error:
            raise ParameterError(f"parameter 'output_path': {error}") from None
        for topic in dict.fromkeys(wanted):
            if topic in known:
                self._subscribe(topic, known[topic], self._profile(topic))
            else:
                self.pending.append(topic)
        if self.pending:
            self.create_timer(p['discovery_period'], self.on_discovery)
        self.create_timer(p['flush_period'], self.on_flush)
        self.get_logger().info(f"recording {len(wanted)} topics to {p['output_path']}")

    @staticmethod
    def _profile(topic: str) -> QoSProfile:
        """The subscription QoS of a formation topic: transient local for the latched
        descriptions and /tf_static (so they are recorded whenever they were published)."""
        name = topic.rpartition('/')[2]
        latched = {t.name.lstrip('/') for t in BY_KEY.values()
                   if t.qos in ('latched', 'tf_static')}
        return qos.adapted(True, name in latched)

    def _subscribe(self, topic: str, type_name: str, profile: QoSProfile) -> None:
        cls = message_class(type_name, topic)
        self.counts[topic] = 0

        def receive(data: bytes) -> None:
            self.on_message(topic, type_name, data)

        subscription = self.create_subscription(cls, topic, receive, profile, raw=True)
        self.sources.append((subscription, topic, type_name))

    def on_discovery(self) -> None:
        """Subscribe to the pending topics once the graph knows their type."""
        types = dict(self.get_topic_names_and_types())
        for topic in list(self.pending):
            names = types.get(topic, [])
            if len(names) != 1:
                if len(names) > 1:
                    self.throttle.warn(topic, f'{topic} has several types {names}; not recorded')
                continue
            try:
                message_class(names[0], topic)
            except bag.BagError as error:
                self.throttle.warn(topic, f'{error}; not recorded')
                continue
            offers = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            self._subscribe(topic, names[0], qos.adapted_to_offers(offers))
            self.pending.remove(topic)
            self.get_logger().info(f'recording {topic} ({names[0]})')

    def on_message(self, topic: str, type_name: str, data: bytes) -> None:
        """Append one raw message; the first one registers the topic's channel."""
        if self.closed or self.error:
            return
        now = self.get_clock().now().nanoseconds
        try:
            if topic not in self.writer.channels:
                infos = [i for i in self.get_publishers_info_by_topic(topic)
                         if i.topic_type == type_name]
                hashes = [str(i.topic_type_hash) for i in infos]
                self.writer.add_channel(topic, type_name,
                                        qos_yaml(qos.offered_qos(i.qos_profile) for i in infos),
                                        next((h for h in hashes if h != 'INVALID'), ''))
            self.writer.write(topic, data, now)            # publish_time: the header stamp
        except OSError as error:
            self._failed(error, f'writing a message of {topic}')
            return
        self.counts[topic] += 1

    def _failed(self, error: OSError, doing: str) -> None:
        """Stop recording after a write error; the error names the file and the errno."""
        if self.error:
            return
        code = errno.errorcode.get(error.errno or 0, 'unknown errno')
        self.error = (f'cannot write {self.writer.path}: {error.strerror or error} ({code}) '
                      f'while {doing}; recording stopped after '
                      f'{sum(self.counts.values())} messages')
        self.exit_code = 1
        self.finished = True
        self.get_logger().error(self.error)

    def on_flush(self) -> None:
        """Close the current chunk so that a kill loses at most one flush period."""
        if not self.closed and not self.error:
            try:
                self.writer.flush()
            except OSError as error:
                self._failed(error, 'flushing a chunk')

    def drain(self, budget: float = 1.0) -> int:
        """Write the messages that arrived but were not taken yet (for at most budget s)."""
        taken, end = 0, time.monotonic() + budget
        for subscription, topic, type_name in self.sources:
            try:
                with subscription.handle:
                    while time.monotonic() < end:
                        item = subscription.handle.take_message(subscription.msg_type, True)
                        if item is None:
                            break
                        self.on_message(topic, type_name, item[0])
                        taken += 1
            except Exception:    # context already shut down: nothing more can be taken
                continue
        return taken

    def close(self) -> None:
        """Take what already arrived, finalize the file (summary, index), log the counts."""
        if self.closed:
            return
        drained = self.drain()
        self.closed = True
        try:
            self.writer.close()
        except OSError as error:
            self._failed(error, 'finalizing the file (formopt-bag repair recovers the chunks '
                                'written)')
        total = sum(self.counts.values())
        self.get_logger().info(f'recorded {total} messages to {self.writer.path} '
                               f'({drained} taken at shutdown): '
                               + ', '.join(f'{t} {n}' for t, n in self.counts.items()))
        path = self.params['counts_path']
        if path:
            try:
                write_json(path, {'output_path': str(self.writer.path), 'total': total,
                                  'counts': self.counts, 'error': self.error or None})
            except OSError as error:
                self.get_logger().error(f'cannot write the counts to {path}: '
                                        f'{error.strerror or error}')


SUMMARY = ('Records the formation topics, raw CDR, into one rosbag2-compatible MCAP file that '
           'ros2 bag, Foxglove, rosbags and mcap read.')


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros recorder --ros-args -p output_path:=run.mcap)."""
    sys.exit(node_main(Recorder, 'recorder', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()
