"""Node parameters: one spec per parameter (default, unit, range, read-only), declared and
validated the same way in every node, and the documented config files generated from them."""
from __future__ import annotations

import difflib
import math
import re
import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
from rclpy.node import Node
from rclpy.parameter import Parameter

from formopt_ros.core.checks import InvalidInput, as_bool, as_choice, as_integer, as_real
from formopt_ros.core.scenario import RANGES


#: Parameters rclpy declares itself; never reported as unknown.
ROS_PARAMETERS = {'use_sim_time', 'start_type_description_service'}
#: Parameters rclpy declares mutable that a running node cannot honour when changed, and why
#: (refused in a set-parameters callback: rclpy owns their descriptors).
FIXED_WHILE_RUNNING = {
    'use_sim_time': 'the clock of a running node cannot change source (its inputs and timers '
                    'would jump between wall and simulated time); restart the node with it'}


class ParameterError(ValueError):
    """A parameter value outside its documented range (the node exits with code 2)."""


def check_angles(name: str, angles: list[float]) -> None:
    """Refuse (ParameterError naming ``name``) an angle of a list parameter outside the
    'angle' range of RANGES, rad: one turn either way; beyond it a value meant in degrees."""
    low, high, _ = RANGES['angle']
    for angle in angles:
        if not low <= angle <= high:
            raise ParameterError(f"parameter '{name}': angles are in radians, within one turn; "
                                 f'got {angle:g} (meant in degrees? {angle:g} deg is '
                                 f'{math.radians(angle):.4g} rad)')


@dataclass(frozen=True)
class Param:
    """One node parameter.

    Attributes:
        name: parameter name.
        default: default value; its type is the parameter's type (int values are accepted for
            float parameters).
        description: meaning and unit.
        low, high: admissible closed range of a number (None: unbounded).
        choices: admissible strings.
        read_only: fixed at start-up (``ros2 param set`` is refused); otherwise validated on set.
        identifier: a robot id ('' allowed): letters, digits, underscores, a letter first (it
            becomes a ROS namespace).
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True
    identifier: bool = False

    def descriptor(self) -> ParameterDescriptor:
        """The ROS descriptor, with range and read-only flag (ros2 param describe shows them)."""
        text = self.description
        if self.choices:
            text += f" (one of: {', '.join(self.choices)})"
        descriptor = ParameterDescriptor(description=text, read_only=self.read_only)
        if self.low is not None and self.high is not None and not isinstance(self.default,
                                                                             bool):
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(self.low), to_value=int(self.high), step=1)]
            elif isinstance(self.default, float):
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low), to_value=float(self.high), step=0.0)]
        return descriptor

    def check(self, value: Any) -> Any:
        """The value as the parameter's type (integers pass for floats), else ParameterError
        naming the parameter."""
        name = f"parameter '{self.name}'"
        try:
            if not isinstance(self.default, list):
                return self._check_one(name, value, self.default)
            if not isinstance(value, (list, tuple)) or not value:
                raise InvalidInput(name, f'must be a non-empty list ({self.expected()}), got '
                                         f'{value!r}')
            kind = self.default[0] if self.default else ''
            return [self._check_one(name, item, kind) for item in value]
        except InvalidInput as error:
            raise ParameterError(str(error)) from None

    def _check_one(self, name: str, value: Any, kind: Any) -> Any:
        if isinstance(kind, bool):
            return as_bool(name, value)
        if isinstance(kind, int):
            return as_integer(name, value, None if self.low is None else int(self.low),
                              None if self.high is None else int(self.high))
        if isinstance(kind, float):
            return as_real(name, value, self.low, self.high)
        if self.choices:
            return as_choice(name, value, self.choices)
        if not isinstance(value, str):
            raise InvalidInput(name, f'must be a string, got {value!r}')
        if self.identifier and value:
            from formopt_ros.core.formation import check_id
            check_id(name, value)
        return value

    def expected(self) -> str:
        """What the parameter accepts, in words."""
        if self.choices:
            return 'one of ' + ', '.join(repr(c) for c in self.choices)
        kind = {bool: 'a bool', int: 'an integer', float: 'a number', str: 'a string',
                list: 'a list of numbers' if self.low is not None else 'a list of strings'
                }.get(type(self.default), type(self.default).__name__)
        if self.low is not None or self.high is not None:
            return f'{kind} in [{_number(self.low)}, {_number(self.high)}] ({self.description})'
        return f'{kind} ({self.description})'

    def documentation(self) -> str:
        """One paragraph for the config file: meaning, type, range, default, mutability."""
        if self.choices:
            accepts = 'one of ' + ', '.join(self.choices)
        else:
            accepts = {bool: 'bool', int: 'integer', float: 'number', str: 'string',
                       list: 'list'}.get(type(self.default), type(self.default).__name__)
            if self.low is not None or self.high is not None:
                accepts += f' in [{_number(self.low)}, {_number(self.high)}]'
        mutable = 'read-only' if self.read_only else 'settable at run time'
        return (f'{self.description[0].upper()}{self.description[1:]}. Accepts {accepts}; '
                f'default {_yaml_value(self.default)}; {mutable}.')


def _number(value: float | None) -> str:
    if value is None:
        return '-inf'
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f'{value:g}'


#: rcl's plain scalars that are booleans (rcl_yaml_param_parser, get_value).
_TRUE = {'Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on', 'On', 'ON'}
_FALSE = {'N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off', 'Off', 'OFF'}
#: What C strtoll(text, base 0) reads whole: decimal, 0x hexadecimal, 0 octal.
_INTEGER = re.compile(r'^\s*([+-]?)(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)$')
#: What C strtod reads whole: decimal with exponent, hexadecimal with p exponent, inf, nan.
_DECIMAL = re.compile(r'^\s*[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$')
_HEXADECIMAL = re.compile(r'^\s*[+-]?0[xX]([0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)'
                          r'([pP][+-]?\d+)?$')
_SPECIAL = re.compile(r'^\s*[+-]?(inf|infinity|nan)$', re.IGNORECASE)
_YAML_SPECIAL = {f'{sign}.{word}' for sign in ('', '+', '-')
                 for word in ('inf', 'Inf', 'INF')} | {'.nan', '.NaN', '.NAN'}


def rcl_scalar(text: str) -> bool | int | float | str:
    """A plain (unquoted, untagged) YAML scalar typed the way rcl's parameter parser types it:
    its booleans (y, yes, on, true, ... in three cases), then what C strtoll with base 0 reads
    whole (42, +7, 0x1F, 010 is 8), then what strtod reads whole (1e-2, 1E3, .5, +1.0, 5.,
    0x1p3, inf, nan, .inf, -.Inf, .nan), else the text; a number out of the int64 range is
    read as a float, one out of the double range (1e400, 1e-400) stays text (strtod's ERANGE).
    """
    if text in _TRUE or text in _FALSE:
        return text in _TRUE
    match = _INTEGER.match(text)
    if match:
        digits = match.group(2)
        base = 16 if digits[:2] in ('0x', '0X') else 8 if digits[0] == '0' else 10
        number = int(digits, base) * (-1 if match.group(1) == '-' else 1)
        if -2**63 <= number < 2**63:
            return number
    if text in _YAML_SPECIAL:
        return float(text.replace('.', '', 1))
    if _SPECIAL.match(text):
        return float(text)
    if _DECIMAL.match(text) or _HEXADECIMAL.match(text):
        stripped = text.strip()
        value = float.fromhex(stripped) if _HEXADECIMAL.match(text) else float(stripped)
        mantissa = re.split('[eEpP]', stripped.lower().replace('0x', '', 1))[0]
        if math.isinf(value) or (abs(value) < sys.float_info.min
                                 and mantissa.strip('+-.0') != ''):
            return text                      # strtod's ERANGE: rcl keeps the text
        return value
    return text


def parse_value(name: str, text: str) -> Any:
    """The value of ``-p name:=text`` as ``--ros-args`` parses it: YAML whose plain scalars are
    typed by rcl's rules (:func:`rcl_scalar`: 1e-2 is a number, y a boolean), quoted or !!str
    scalars strings, a flow sequence of one type a list, [] None (no type); ParameterError
    otherwise. Integers beside floats ([0, 0.1]) pass, though rcl refuses them: the specs make
    them floats and run_formation passes them on as such ([0.0, 0.1])."""
    import yaml
    try:
        events = list(yaml.parse(text))
    except yaml.YAMLError:
        raise ParameterError(f"parameter '{name}': {text!r} is not a YAML value") from None
    body = [e for e in events if not isinstance(
        e, (yaml.StreamStartEvent, yaml.StreamEndEvent, yaml.DocumentStartEvent,
            yaml.DocumentEndEvent))]

    def scalar(event: Any) -> Any:
        if event.style in ("'", '"') or event.tag in ('!!str', 'tag:yaml.org,2002:str'):
            return event.value
        if event.value == '':
            raise ParameterError(f"parameter '{name}': {text!r} has no value")
        return rcl_scalar(event.value)

    if len(body) == 1 and isinstance(body[0], yaml.ScalarEvent):
        return scalar(body[0])
    if (len(body) >= 2 and isinstance(body[0], yaml.SequenceStartEvent)
            and isinstance(body[-1], yaml.SequenceEndEvent)
            and all(isinstance(e, yaml.ScalarEvent) for e in body[1:-1])):
        items = [scalar(e) for e in body[1:-1]]
        kinds = {float if type(item) is int else type(item) for item in items}
        if len(kinds) > 1:
            raise ParameterError(f"parameter '{name}': {text!r} mixes types (rcl takes one "
                                 'type per list)')
        return items or None
    raise ParameterError(f"parameter '{name}': {text!r} is not a value or a list of values "
                         '(rcl takes no mappings or nested lists)')


def declare(node: Node, specs: list[Param],
            defaults: dict[str, Any] | None = None) -> dict[str, Any]:
    """Declare every parameter with its descriptor and return the validated values.

    A parameter the node does not have is refused (ParameterError) when it is close to one it
    has (a typo such as 'stratgy'), and logged as a warning otherwise (a shared ``/**``
    parameters file may carry other nodes' parameters). Values of the wrong type or outside
    their range are refused; integers are accepted for float parameters. Mutable parameters
    are validated again when set at run time (:func:`validate_on_set`). ``defaults`` replace
    the specs' defaults (a formation file's values), so ``ros2 param get`` shows what runs.
    """
    defaults = defaults or {}
    known = {spec.name for spec in specs} | ROS_PARAMETERS
    for name in sorted(set(node._parameter_overrides) - known):
        close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.8)
        if close:
            raise ParameterError(f"unknown parameter '{name}' for {node.get_name()}; did you "
                                 f"mean '{close[0]}'?")
        node.get_logger().warning(f"ignoring parameter '{name}': {node.get_name()} has no "
                                  'such parameter (see --help)')
    values = {}
    for spec in specs:
        given = node._parameter_overrides.get(spec.name)
        override = None if given is None else given.value
        if given is not None:
            if override is None:                                   # e.g. -p x:=[]
                raise ParameterError(f"parameter '{spec.name}' must be {spec.expected()}, got "
                                     'a value without a type (an empty list?)')
            if isinstance(spec.default, list) and not isinstance(override, str):
                override = list(override)
            # our message before rclpy's type exception; the checked value replaces the given
            # one, so integers pass for floats (1 -> 1.0, [1, 2] -> [1.0, 2.0])
            node._parameter_overrides[spec.name] = Parameter(spec.name,
                                                             value=spec.check(override))
        default = defaults.get(spec.name, spec.default)
        try:
            node.declare_parameter(spec.name, default, spec.descriptor())
        except Exception as error:           # rclpy rejects out-of-range or mistyped overrides
            shown = override if override is not None else default
            raise ParameterError(f"parameter '{spec.name}' must be {spec.expected()}, got "
                                 f'{shown!r} ({type(error).__name__})') from None
        value = node.get_parameter(spec.name).value
        values[spec.name] = spec.check(list(value) if isinstance(spec.default, list)
                                       and value is not None else value)
    node.add_on_set_parameters_callback(lambda parameters: _fixed_result(node, parameters))
    return values


def refuse_fixed(node: Node, parameters: list[Parameter]) -> str | None:
    """The reason to refuse a change of a parameter fixed while the node runs
    (:data:`FIXED_WHILE_RUNNING`), None when there is none (setting its current value is
    accepted)."""
    for parameter in parameters:
        reason = FIXED_WHILE_RUNNING.get(parameter.name)
        if reason and node.has_parameter(parameter.name) and \
                parameter.value != node.get_parameter(parameter.name).value:
            return f"parameter '{parameter.name}' cannot be changed while the node runs: {reason}"
    return None


def _fixed_result(node: Node, parameters: list[Parameter]) -> SetParametersResult:
    reason = refuse_fixed(node, parameters)
    return SetParametersResult(successful=reason is None, reason=reason or '')


def validate_on_set(node: Node, specs: list[Param],
                    apply: Callable[[dict[str, Any]], str | None]) -> None:
    """Validate run-time ``ros2 param set`` of mutable parameters, then hand them to ``apply``.

    ``apply`` gets {name: value} of the accepted change and returns a reason to refuse it (or
    None); read-only parameters are refused by rclpy itself, use_sim_time and the other
    :data:`FIXED_WHILE_RUNNING` here (before ``apply`` sees any part of the change).
    """
    by_name = {spec.name: spec for spec in specs}

    def on_set(parameters: list[Parameter]) -> SetParametersResult:
        fixed = refuse_fixed(node, parameters)
        if fixed:
            return SetParametersResult(successful=False, reason=fixed)
        change = {}
        for parameter in parameters:
            spec = by_name.get(parameter.name)
            if spec is None:
                continue
            try:
                change[parameter.name] = spec.check(parameter.value)
            except ParameterError as error:
                return SetParametersResult(successful=False, reason=str(error))
        reason = apply(change) if change else None
        return SetParametersResult(successful=reason is None, reason=reason or '')

    node.add_on_set_parameters_callback(on_set)


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f"'{value}'" if value == '' or not value.replace('_', '').isalnum() else value
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    return repr(value)


def config_yaml(node: str, summary: str, specs: list[Param]) -> str:
    """The documented parameters file of a node (config/<node>.yaml): every parameter at its
    default, with meaning, unit, range and whether it can be set at run time."""
    lines = textwrap.wrap(f'Parameters of {node}. {summary}', 97, initial_indent='# ',
                          subsequent_indent='# ')
    lines += textwrap.wrap(f'Use: ros2 run formopt_ros {node} --ros-args --params-file '
                           f'config/{node}.yaml (scripts/{node}.sh passes this file). The '
                           'values are the defaults. Generated from the parameter specs of the '
                           'node by: python -m formopt_ros.ros.nodes --write-configs config',
                           97, initial_indent='# ', subsequent_indent='# ')
    lines += [f'/**/{node}:', '  ros__parameters:']
    for spec in specs:
        lines += textwrap.wrap(spec.documentation(), 95, initial_indent='    # ',
                               subsequent_indent='    # ', break_on_hyphens=False)
        lines.append(f'    {spec.name}: {_yaml_value(spec.default)}')
    return '\n'.join(lines) + '\n'
