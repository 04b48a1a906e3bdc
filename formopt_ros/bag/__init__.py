"""rosbag2-compatible MCAP files: schema, QoS metadata, writer, reader, repair (no rclpy)."""
from formopt_ros.bag.errors import BagError
from formopt_ros.bag.reader import Bag, ChannelInfo, Record, read_bag, scan
from formopt_ros.bag.repair import RepairResult, repair
from formopt_ros.bag.writer import BagWriter

__all__ = ['Bag', 'BagError', 'BagWriter', 'ChannelInfo', 'Record', 'RepairResult', 'read_bag',
           'repair', 'scan']
