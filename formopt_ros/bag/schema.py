"""Message definitions as rosbag2 stores them (ros2msg schemas) and header stamps in CDR data."""
from __future__ import annotations

import os
import re
import struct
import sys
from pathlib import Path

from formopt_ros.bag.errors import BagError

SCHEMA_ENCODING = 'ros2msg'
DELIMITER = '=' * 80

# rosbag2's LocalMessageDefinitionSource: field types at the start of a .msg line.
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
               'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'}
_TYPE_NAME = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)(?:/(msg|srv|action))?/([A-Za-z][A-Za-z0-9_]*)$')


def share_prefixes() -> list[Path]:
    """Install prefixes searched for share/<pkg>/msg/*.msg: AMENT_PREFIX_PATH, then sys.prefix."""
    found: list[Path] = []
    for entry in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]:
        if entry and Path(entry) not in found:
            found.append(Path(entry))
    return found


def split_type(type_name: str) -> tuple[str, str, str]:
    """('pkg', 'msg', 'Type') of 'pkg/msg/Type' or 'pkg/Type'; BagError when malformed."""
    match = _TYPE_NAME.match(type_name)
    if match is None:
        raise BagError(f'malformed message type name {type_name!r} (expected pkg/msg/Type)')
    return match.group(1), match.group(2) or 'msg', match.group(3)


def definition_file(type_name: str) -> Path:
    """The installed .msg file of a type; BagError when no prefix has it."""
    package, namespace, name = split_type(type_name)
    for prefix in share_prefixes():
        candidate = prefix / 'share' / package / namespace / f'{name}.msg'
        if candidate.is_file():
            return candidate
    raise BagError(f'unknown message type {type_name!r}: no share/{package}/{namespace}/'
                   f'{name}.msg under AMENT_PREFIX_PATH or {sys.prefix}')


def msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a .msg text as 'pkg/Type', sorted (rosbag2's std::set)."""
    found = set()
    for match in _FIELD_TYPE.finditer(text):
        name = match.group(1)
        if name in _PRIMITIVES:
            continue
        found.add(name if '/' in name else f'{package}/{name}')
    return sorted(found)


def message_definition(type_name: str) -> str:
    """The ros2msg schema rosbag2 writes: root .msg text, then each nested type once.

    Each nested type follows a line of 80 '=' and a line 'MSG: pkg/Type', depth first in
    sorted order, exactly as rosbag2_cpp's LocalMessageDefinitionSource concatenates them.
    """
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise BagError(f'message definition of {type_name!r} nests too deeply')
        text = definition_file(name).read_text()
        result = text
        for dependency in msg_dependencies(text, split_type(name)[0]):
            if dependency not in seen:
                seen.add(dependency)
                result += f'\n{DELIMITER}\nMSG: {dependency}\n' + append(dependency, depth - 1)
        return result

    return append(type_name, 50)


def has_header(type_name: str) -> bool:
    """Whether the type's first field is a std_msgs/Header (its stamp starts the CDR data)."""
    for line in definition_file(type_name).read_text().splitlines():
        parts = line.split('#', 1)[0].split()
        if parts and '=' not in ''.join(parts[1:]):          # skip constants (NAME=value)
            return len(parts) == 2 and parts[0] in ('std_msgs/Header', 'Header')
    return False


def header_stamp_ns(data: bytes) -> int | None:
    """Header stamp (ns) of a CDR message whose first field is a std_msgs/Header."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nanosec if sec >= 0 else None
