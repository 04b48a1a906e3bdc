"""The run description: what one follower's run is, as JSON, latched on ``<follower>/description``
and so recorded once in every bag; replay and report read the scenario back from it."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from formopt_ros.core.scenario import Scenario

#: Version tag of the JSON layout.
FORMAT = 'formopt_ros.run/1'
MODES = ('lockstep', 'realtime')


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
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f'run description is not JSON: {error}') from None
        if not isinstance(data, dict) or data.get('format') != FORMAT:
            raise ValueError(f'run description format must be {FORMAT!r}, got '
                             f'{data.get("format") if isinstance(data, dict) else data!r}')
        try:
            return cls(follower_id=str(data['follower_id']),
                       scenario=Scenario.from_dict(data['scenario']),
                       strategy=str(data['strategy']), options=dict(data.get('options', {})),
                       seed=int(data['seed']), trial=int(data['trial']), mode=str(data['mode']),
                       steps=int(data['steps']), run_id=str(data.get('run_id', '')),
                       leader_id=str(data.get('leader_id', 'leader')))
        except (KeyError, TypeError) as error:
            raise ValueError(f'run description lacks or mangles {error}') from None
