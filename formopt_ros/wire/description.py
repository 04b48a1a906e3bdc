"""The run description: what one follower's run is, as JSON, latched on ``<follower>/description``
and so recorded once in every bag; replay and report read the scenario back from it."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from formopt_ros.core.scenario import LeaderPath, Scenario

#: Version tags of the JSON layouts.
FORMAT = 'formopt_ros.run/1'
LEADER_FORMAT = 'formopt_ros.leader/1'
MODES = ('lockstep', 'realtime')


def _load(text: str, expected: str) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f'run description is not JSON: {error}') from None
    if not isinstance(data, dict) or data.get('format') != expected:
        raise ValueError(f'run description format must be {expected!r}, got '
                         f'{data.get("format") if isinstance(data, dict) else data!r}')
    return data


@dataclass(frozen=True)
class RunDescription:
    """One follower's run.

    Attributes:
        follower_id: the follower (its namespace).
        scenario: everything the estimator assumes about the world.
        strategy: motion strategy name; options: its settings (defaults filled in).
        seed, trial: the random streams are seeded by (seed, trial).
        mode: 'lockstep' or 'realtime'.
        steps: measurement steps of the run (0: until stopped).
        run_id: identity of the run ('' when not set).
        leader_id: the leader (its namespace and frame).
    """

    follower_id: str
    scenario: Scenario
    strategy: str
    options: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    trial: int = 0
    mode: str = 'lockstep'
    steps: int = 0
    run_id: str = ''
    leader_id: str = 'leader'

    def to_json(self) -> str:
        """The JSON text published in RunDescription.description."""
        return json.dumps({
            'format': FORMAT, 'run_id': self.run_id, 'leader_id': self.leader_id,
            'follower_id': self.follower_id, 'mode': self.mode, 'strategy': self.strategy,
            'options': self.options, 'seed': self.seed, 'trial': self.trial,
            'steps': self.steps, 'scenario': self.scenario.to_dict()}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> 'RunDescription':
        """Inverse of :meth:`to_json`; ValueError saying what is wrong."""
        data = _load(text, FORMAT)
        try:
            return cls(follower_id=str(data['follower_id']),
                       scenario=Scenario.from_dict(data['scenario']),
                       strategy=str(data['strategy']), options=dict(data.get('options', {})),
                       seed=int(data['seed']), trial=int(data['trial']), mode=str(data['mode']),
                       steps=int(data['steps']), run_id=str(data.get('run_id', '')),
                       leader_id=str(data.get('leader_id', 'leader')))
        except (KeyError, TypeError) as error:
            raise ValueError(f'run description lacks or mangles {error}') from None


@dataclass(frozen=True)
class LeaderDescription:
    """The leader's side of a run, latched on ``<leader>/description``.

    Attributes:
        leader_id: the leader (its namespace and frame).
        path: its path; dt: the sub-step length, s.
        followers: the ids of the followers it serves.
        mode: 'lockstep' or 'realtime'; run_id: identity of the run ('' when not set).
    """

    leader_id: str
    path: LeaderPath
    dt: float
    followers: tuple[str, ...]
    mode: str = 'lockstep'
    run_id: str = ''

    def to_json(self) -> str:
        """The JSON text published in RunDescription.description."""
        return json.dumps({'format': LEADER_FORMAT, 'leader_id': self.leader_id,
                           'path': self.path.to_dict(), 'dt': self.dt,
                           'followers': list(self.followers), 'mode': self.mode,
                           'run_id': self.run_id}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> 'LeaderDescription':
        """Inverse of :meth:`to_json`; ValueError saying what is wrong."""
        data = _load(text, LEADER_FORMAT)
        try:
            return cls(str(data['leader_id']), LeaderPath.from_dict(data['path']),
                       float(data['dt']), tuple(data['followers']), str(data['mode']),
                       str(data.get('run_id', '')))
        except (KeyError, TypeError) as error:
            raise ValueError(f'leader description lacks or mangles {error}') from None
