"""offered_qos_profiles, the QoS metadata of a recorded topic, with rosbags' own QoS types."""
from __future__ import annotations

from collections.abc import Iterable

import yaml
from rosbags.interfaces import (
    Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime)
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

from formopt_ros.bag.errors import BagError

#: rmw's "infinite" duration (RMW_DURATION_INFINITE), ns.
INFINITE_NS = 2**63 - 1

__all__ = ['INFINITE_NS', 'Qos', 'QosDurability', 'QosHistory', 'QosLiveliness',
           'QosReliability', 'QosTime', 'duration', 'parse_qos_yaml', 'qos_yaml']


def duration(ns: int) -> QosTime:
    """A QoS duration of ``ns`` nanoseconds."""
    return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)


def qos_yaml(profiles: Iterable[Qos]) -> str:
    """offered_qos_profiles as rosbag2 (Jazzy, metadata version 9) stores it: a YAML list."""
    items = dump_qos_v9(list(profiles))
    return yaml.safe_dump(items, sort_keys=False).strip() if items else ''


def parse_qos_yaml(text: str) -> list[Qos]:
    """Inverse of :func:`qos_yaml`; also reads the integer policies of older bags."""
    try:
        return parse_qos(text)
    except (ReaderError, KeyError, TypeError) as error:
        raise BagError(f'offered_qos_profiles is not rosbag2 QoS YAML: {error}') from None
