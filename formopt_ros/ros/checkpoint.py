"""Node checkpoints: a node's state after each step (or tick), written atomically, so that a
restarted node resumes its run instead of starting over.

A checkpoint is a pickle of the node's state with the run's identity (its description JSON):
a node started with ``checkpoint_path`` resumes from the file when it exists, refuses one of
another run or of a finished run (exit 2), and otherwise starts a new run and writes the file.
Load only checkpoints you wrote: unpickling runs code of the file's choosing.
"""
from __future__ import annotations

import os
import pickle
import time
from pathlib import Path
from typing import Any

from formopt_ros.ros.params import ParameterError
from formopt_ros.ros.runtime import check_output_path

FORMAT = 'formopt_ros.checkpoint/1'


class Checkpoint:
    """The checkpoint file of one node.

    Args:
        path: the file ('' disables checkpoints).
        node: the node's fully qualified name (stored, reported).
        identity: the run's identity (description JSON); a checkpoint of another run is
            refused.
    """

    def __init__(self, path: str, node: str, identity: str) -> None:
        check_output_path('checkpoint_path', path)
        self.path = Path(path) if path else None
        self.node = node
        self.identity = identity
        self.saved_at: float | None = None

    def load(self) -> dict[str, Any] | None:
        """The saved state, or None when there is no checkpoint (a new run).

        Raises:
            ParameterError: unreadable, of another run or node, or of a finished run.
        """
        if self.path is None or not self.path.exists():
            return None
        try:
            with open(self.path, 'rb') as handle:
                data = pickle.load(handle)
        except Exception as error:            # truncated, not a pickle, missing classes
            raise ParameterError(f"parameter 'checkpoint_path': {self.path} is not a readable "
                                 f'checkpoint ({type(error).__name__}: {error})') from None
        if not isinstance(data, dict) or data.get('format') != FORMAT:
            raise ParameterError(f"parameter 'checkpoint_path': {self.path} is not a "
                                 f'{FORMAT} file')
        if data.get('node') != self.node or data.get('identity') != self.identity:
            raise ParameterError(f"parameter 'checkpoint_path': {self.path} holds a checkpoint "
                                 f"of another run or node ({data.get('node')}); remove it or "
                                 'choose another path')
        if data.get('finished'):
            raise ParameterError(f"parameter 'checkpoint_path': {self.path} holds a finished "
                                 'run; remove it or choose another path')
        self.saved_at = float(data['wall_time'])
        state: dict[str, Any] = data['state']
        return state

    def save(self, state: dict[str, Any], finished: bool = False) -> None:
        """Write ``state`` atomically (a crash mid-write leaves the previous checkpoint)."""
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        temporary = self.path.with_name(self.path.name + '.tmp')
        with open(temporary, 'wb') as handle:
            pickle.dump({'format': FORMAT, 'node': self.node, 'identity': self.identity,
                         'wall_time': time.time(), 'finished': finished, 'state': state},
                        handle, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(temporary, self.path)


def open_checkpoint(node: Any, values: dict[str, Any],
                    identity: str) -> tuple[Checkpoint, dict[str, Any] | None]:
    """The node's checkpoint and the state to resume (None: a new run); also checks the
    summary path at start (an existing summary is refused unless the node resumes)."""
    checkpoint = Checkpoint(values['checkpoint_path'], node.get_fully_qualified_name(),
                            identity)
    state = checkpoint.load()
    check_output_path('summary_path', values['summary_path'], may_exist=state is not None)
    if state is not None:
        node.get_logger().warning(f'resuming from checkpoint {checkpoint.path} (saved '
                                  f'{time.time() - (checkpoint.saved_at or 0.0):.1f} s ago)')
    return checkpoint, state
