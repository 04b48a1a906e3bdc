"""Topic maps: which topic of a bag of standard message types is which estimator input, and the
filter's settings for it (the keys are documented in formopt_ros/analysis/foreign.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from formopt_ros.core.checks import InvalidInput, as_array
from formopt_ros.core.estimator import RealNoise
from formopt_ros.core.scenario import Scenario, ranged
from formopt_ros.wire.formation import read_yaml

TOPIC_KEYS = ('leader_odometry', 'follower_odometry', 'range', 'bearing', 'leader_truth',
              'follower_truth', 'relative_truth')
#: The measurement keys: a map names exactly one.
MEASUREMENT_KEYS = ('range', 'bearing')
ESTIMATOR_DEFAULTS: dict[str, Any] = {
    'sigma_v': 0.05, 'sigma_omega': 0.05, 'range_sigma': 0.1, 'range_variance': 0.0,
    'bias_sigma': 0.0,
    'bias_walk': 0.0, 'huber': 0.0, 'gate': 0.0, 'initial_covariance': [0.1, 0.1, 0.01],
    'initial_pose': [], 'bearing_sigma': 0.02, 'sensor_mount': [], 'reopen_after': 0,
    'sigma_v_leader': None, 'sigma_omega_leader': None}


@dataclass(frozen=True)
class TopicMap:
    """Which topic of a bag is which input (module docstring), and the filter's settings."""

    leader_odometry: str
    follower_odometry: str
    range: str = ''
    bearing: str = ''
    leader_truth: str = ''
    follower_truth: str = ''
    relative_truth: str = ''
    estimator: dict[str, Any] = field(default_factory=lambda: dict(ESTIMATOR_DEFAULTS))

    @classmethod
    def load(cls, path: str | Path) -> 'TopicMap':
        """Read a topic map; ValueError naming the file and the key for anything wrong."""
        data = read_yaml(path, 'topic map')
        if not isinstance(data, dict):
            raise ValueError(f'{path}: a topic map is a mapping of {TOPIC_KEYS}')
        unknown = sorted(set(data) - set(TOPIC_KEYS) - {'estimator'})
        missing = [k for k in TOPIC_KEYS[:2] if not data.get(k)]
        measured = [k for k in MEASUREMENT_KEYS if data.get(k)]
        if len(measured) != 1 and not unknown:
            raise ValueError(f'{path}: name exactly one of range and bearing (the follower\'s '
                             f"sensor), got {measured or 'neither'}")
        if unknown and set(unknown) <= set(ESTIMATOR_DEFAULTS):
            raise ValueError(f'{path}: {unknown} are filter settings: put them under '
                             "'estimator:'")
        if unknown or missing:
            raise ValueError(f'{path}: unknown keys {unknown}, missing keys {missing}'
                             if unknown and missing else
                             f'{path}: unknown keys {unknown}' if unknown else
                             f'{path}: missing keys {missing}')
        settings = dict(ESTIMATOR_DEFAULTS)
        given = data.get('estimator') or {}
        bad = sorted(set(given) - set(ESTIMATOR_DEFAULTS)) if isinstance(given, dict) else given
        if bad:
            raise ValueError(f'{path}: estimator: unknown keys {bad} (known: '
                             f'{sorted(ESTIMATOR_DEFAULTS)})')
        settings.update(given)
        for key in TOPIC_KEYS:
            if not isinstance(data.get(key, ''), str):
                raise ValueError(f'{path}: {key} must be a topic name, got {data[key]!r}')
        if data.get('relative_truth') and (data.get('leader_truth') or
                                           data.get('follower_truth')):
            raise ValueError(f'{path}: relative_truth (the follower in the leader\'s frame) or '
                             'leader_truth and follower_truth (both in one fixed frame), not '
                             'both')
        if bool(data.get('leader_truth')) != bool(data.get('follower_truth')):
            given, absent = ('leader_truth', 'follower_truth') if data.get('leader_truth') \
                else ('follower_truth', 'leader_truth')
            raise ValueError(f'{path}: {given} without {absent}: the evaluation needs both '
                             "robots' truth in one fixed frame, or relative_truth (the "
                             "follower's pose in the leader's frame, e.g. field_sim's truth)")
        check_settings(path, settings, measured[0])
        return cls(**{key: data.get(key, '') for key in TOPIC_KEYS}, estimator=settings)

    @property
    def kind(self) -> str:
        """The follower's sensor: 'range' or 'bearing'."""
        return 'range' if self.range else 'bearing'

    @property
    def measurement(self) -> str:
        """The measurement topic."""
        return self.range or self.bearing


def filter_model(settings: dict[str, Any], slot: tuple[float, float], kind: str = 'range'
                 ) -> tuple[Scenario, RealNoise]:
    """The scenario of the follower's sensor ``kind`` (its disc 0.1 |slot| about ``slot``, m,
    where the estimate starts; odometry noise ``sigma_v``, ``sigma_omega``, the leader's
    ``sigma_v_leader``, ``sigma_omega_leader`` where given) and the noise handling a topic
    map's filter settings (ESTIMATOR_DEFAULTS' keys) make; InvalidInput naming the field."""
    s = settings
    sigma = s['range_sigma'] if kind == 'range' else s['bearing_sigma']
    scenario = Scenario(kind, slot, 0.1 * math.hypot(*slot), sigma,
                        sigma_v=s['sigma_v'], sigma_omega=s['sigma_omega'],
                        sigma_v_leader=s['sigma_v'] if s['sigma_v_leader'] is None
                        else s['sigma_v_leader'],
                        sigma_omega_leader=s['sigma_omega'] if s['sigma_omega_leader'] is None
                        else s['sigma_omega_leader'],
                        initial_covariance=s['initial_covariance'])
    return scenario, RealNoise(s['bias_sigma'], s['bias_walk'], s['huber'], s['gate'],
                               s['reopen_after'])


def check_settings(path: str | Path, settings: dict[str, Any], kind: str = 'range') -> None:
    """The filter's settings checked by the rules of the estimator they build
    (:func:`filter_model`); ValueError naming the file and the map's key."""
    try:
        for sensor in MEASUREMENT_KEYS:
            try:
                filter_model(settings, (-1.0, 0.0), sensor)
            except InvalidInput as error:
                if error.name == 'sigma':
                    raise InvalidInput(f'{sensor}_sigma', error.reason) from None
                raise
        ranged('range_variance', settings['range_variance'])
        if settings['sensor_mount'] != []:
            mount = as_array('sensor_mount', settings['sensor_mount'], (6,))
            for angle in mount[3:]:
                ranged('sensor_mount', angle, 'angle')
        if settings['initial_pose'] != []:
            x, y, phi = as_array('initial_pose', settings['initial_pose'], (3,))
            filter_model(settings, (float(x), float(y)), kind)    # the slot's rules
            ranged('initial_pose', phi, 'angle')
    except InvalidInput as error:
        raise ValueError(f'{path}: estimator: {error.name} '
                         f'{error.reason}') from None


__all__ = ['ESTIMATOR_DEFAULTS', 'MEASUREMENT_KEYS', 'TOPIC_KEYS', 'TopicMap', 'filter_model']
