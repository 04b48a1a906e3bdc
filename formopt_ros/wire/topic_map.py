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

TOPIC_KEYS = ('leader_odometry', 'follower_odometry', 'range', 'leader_truth',
              'follower_truth')
ESTIMATOR_DEFAULTS: dict[str, Any] = {
    'sigma_v': 0.05, 'sigma_omega': 0.05, 'range_sigma': 0.1, 'range_variance': 0.0,
    'bias_sigma': 0.0,
    'bias_walk': 0.0, 'huber': 0.0, 'gate': 0.0, 'initial_covariance': [0.1, 0.1, 0.01],
    'initial_pose': []}


@dataclass(frozen=True)
class TopicMap:
    """Which topic of a bag is which input (module docstring), and the filter's settings."""

    leader_odometry: str
    follower_odometry: str
    range: str
    leader_truth: str = ''
    follower_truth: str = ''
    estimator: dict[str, Any] = field(default_factory=lambda: dict(ESTIMATOR_DEFAULTS))

    @classmethod
    def load(cls, path: str | Path) -> 'TopicMap':
        """Read a topic map; ValueError naming the file and the key for anything wrong."""
        data = read_yaml(path, 'topic map')
        if not isinstance(data, dict):
            raise ValueError(f'{path}: a topic map is a mapping of {TOPIC_KEYS}')
        unknown = sorted(set(data) - set(TOPIC_KEYS) - {'estimator'})
        missing = [k for k in TOPIC_KEYS[:3] if not data.get(k)]
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
        if bool(data.get('leader_truth')) != bool(data.get('follower_truth')):
            given, absent = ('leader_truth', 'follower_truth') if data.get('leader_truth') \
                else ('follower_truth', 'leader_truth')
            raise ValueError(f'{path}: {given} without {absent}: the evaluation needs both '
                             "robots' truth in one fixed frame (or neither)")
        check_settings(path, settings)
        return cls(**{key: data.get(key, '') for key in TOPIC_KEYS}, estimator=settings)


#: The topic map's names of the fields the filter's settings check.
SETTING_OF = {'sigma': 'range_sigma', 'sigma_v_leader': 'sigma_v',
              'sigma_omega_leader': 'sigma_omega'}


def filter_model(settings: dict[str, Any], slot: tuple[float, float]
                 ) -> tuple[Scenario, RealNoise]:
    """The range scenario (its disc 0.1 |slot| about ``slot``, m, where the estimate starts;
    both robots' odometry noise ``sigma_v``, ``sigma_omega``) and the noise handling a topic
    map's filter settings (ESTIMATOR_DEFAULTS' keys) make; InvalidInput naming the field."""
    s = settings
    scenario = Scenario('range', slot, 0.1 * math.hypot(*slot), s['range_sigma'],
                        sigma_v=s['sigma_v'], sigma_omega=s['sigma_omega'],
                        sigma_v_leader=s['sigma_v'], sigma_omega_leader=s['sigma_omega'],
                        initial_covariance=s['initial_covariance'])
    return scenario, RealNoise(s['bias_sigma'], s['bias_walk'], s['huber'], s['gate'])


def check_settings(path: str | Path, settings: dict[str, Any]) -> None:
    """The filter's settings checked by the rules of the estimator they build
    (:func:`filter_model`); ValueError naming the file and the map's key."""
    try:
        filter_model(settings, (-1.0, 0.0))
        ranged('range_variance', settings['range_variance'])
        if settings['initial_pose'] != []:
            x, y, phi = as_array('initial_pose', settings['initial_pose'], (3,))
            filter_model(settings, (float(x), float(y)))    # the slot's rules
            ranged('initial_pose', phi, 'angle')
    except InvalidInput as error:
        raise ValueError(f'{path}: estimator: {SETTING_OF.get(error.name, error.name)} '
                         f'{error.reason}') from None


__all__ = ['ESTIMATOR_DEFAULTS', 'TOPIC_KEYS', 'TopicMap', 'filter_model']
