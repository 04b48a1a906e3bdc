"""replay: republishes a recorded bag with its recorded timing (the node; see cli.replay)."""
from __future__ import annotations

import time
from pathlib import Path

from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from formopt_ros import bag as bags
from formopt_ros.ros import qos
from formopt_ros.ros.conversions import clock, message_class
from formopt_ros.ros.params import Param, ParameterError, declare

PARAMS = [
    Param('bag_path', '', 'the .mcap file to replay (required)'),
    Param('rate', 1.0, 'playback speed: factor on the recorded log-time deltas', 1e-3, 1e6),
    Param('fast', False, 'ignore the recorded timing: publish burst messages per executor '
          'round (in log-time order)'),
    Param('burst', 1, 'fast mode: messages per executor round', 1, 100000),
    Param('topics', ['*'], "topics to replay, as recorded ('/leader/odom') or by suffix "
          "('leader/odom'); ['*']: all"),
    Param('wait_subscribers', 0, 'before starting, wait until every publisher has this many '
          'subscribers', 0, 1000),
    Param('wait_timeout', 10.0, 'longest wait for subscribers before starting anyway, and for '
          'the last messages to be acknowledged, s', 0.0, 3600.0),
    Param('clock', False, "publish /clock at the recorded log time of the messages sent, ahead "
          "of them (as ros2 bag play --clock): nodes with use_sim_time run on the recording's "
          'time, so its stamps are current to them'),
]


def select_topics(bag: bags.Bag, names: list[str]) -> list[str]:
    """The recorded topics named by ``names`` (['*']: all); BagError when one is missing."""
    if not names or list(names) == ['*']:
        topics = sorted(bag.channels)
    else:
        topics = [bag.find(name) or '' for name in names]
    if not topics:
        raise bags.BagError(f'{bag.path}: the bag has no topics to replay')
    for topic in topics:
        message_class(bag.channels[topic].type, topic)
    return list(dict.fromkeys(topics))


class Replay(Node):
    """Publishes the raw CDR bytes of a bag's topics with the recorded timing.

    Message i goes out at start + (log_time_i - log_time_0) / rate (or as fast as the executor
    turns, ``burst`` per round, with ``fast``). Publishers take the recorded type and offered
    QoS. When all are sent and acknowledged (or ``wait_timeout`` passed) the node finishes.
    """

    def __init__(self, preloaded: bags.Bag | None = None,
                 cli_args: list[str] | None = None) -> None:
        super().__init__('replay', cli_args=cli_args)
        self.params = declare(self, PARAMS)
        p = self.params
        if not p['bag_path']:
            raise ParameterError("parameter 'bag_path' is required (the .mcap file to replay)")
        try:
            self.bag = preloaded if preloaded is not None and \
                Path(preloaded.path) == Path(p['bag_path']) else bags.read_bag(p['bag_path'])
            topics = select_topics(self.bag, p['topics'])
        except bags.BagError as error:
            raise ParameterError(f"parameter 'bag_path' or 'topics': {error}") from None
        self.publishers_ = {
            topic: self.create_publisher(
                message_class(self.bag.channels[topic].type, topic), topic,
                qos.replay_profile(self.bag.channels[topic].qos))
            for topic in topics}
        self.clock_pub = None
        if p['clock']:
            if '/clock' in self.publishers_:
                raise ParameterError("parameter 'clock': the bag records /clock itself: replay "
                                     "that (clock false), or leave /clock out with 'topics'")
            self.clock_pub = self.create_publisher(Clock, '/clock', qos.profile('clock'))
        self.queue = [r for r in self.bag.messages if r.topic in self.publishers_]
        self.sent = 0
        self.counts = {topic: 0 for topic in topics}
        self.finished = False
        self.created = time.monotonic()
        self.start: float | None = None
        self.timer = self.create_timer(0.0 if p['fast'] else 0.001, self.on_timer)
        self.get_logger().info(
            f"replaying {len(self.queue)} messages on {len(topics)} topics from "
            f"{p['bag_path']} ({'fast' if p['fast'] else 'rate %g' % p['rate']})")

    def _ready(self) -> bool:
        want = self.params['wait_subscribers']
        if want == 0 or all(pub.get_subscription_count() >= want
                            for pub in self.publishers_.values()):
            return True
        return time.monotonic() - self.created > self.params['wait_timeout']

    def on_timer(self) -> None:
        """Publish what is due; finish once everything went out."""
        if self.finished:
            return
        if self.start is None:
            if not self._ready():
                return
            self.start = time.monotonic()
        p = self.params
        if p['fast']:
            end = min(len(self.queue), self.sent + p['burst'])
        else:
            due = self.queue[0].log_time + (time.monotonic() - self.start) * p['rate'] * 1e9 \
                if self.queue else 0
            end = self.sent
            while end < len(self.queue) and self.queue[end].log_time <= due:
                end += 1
        if self.clock_pub is not None and end > self.sent:
            self.clock_pub.publish(clock(self.queue[end - 1].log_time))
        for record in self.queue[self.sent:end]:
            self.publishers_[record.topic].publish(record.data)
            self.counts[record.topic] += 1
        self.sent = end
        if self.sent >= len(self.queue):
            self._finish()

    def _finish(self) -> None:
        timeout = Duration(seconds=self.params['wait_timeout'])
        acked = all(pub.wait_for_all_acked(timeout) for pub in self.publishers_.values())
        elapsed = time.monotonic() - (self.start or self.created)
        self.get_logger().info(f'replayed {self.sent} messages in {elapsed:.3f} s'
                               + ('' if acked else ' (not all acknowledged)'))
        self.finished = True
        self.timer.cancel()

    def close(self) -> None:
        """Log what was sent."""
        self.get_logger().info('replay counts: ' + ', '.join(
            f'{t} {n}' for t, n in self.counts.items()))


SUMMARY = ('Republishes the topics of a recorded bag with their recorded timing (or as fast as '
           'possible), with the recorded types and QoS.')
