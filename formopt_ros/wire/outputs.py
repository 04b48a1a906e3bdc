"""Output paths: the checks that the commands and the nodes share."""
from __future__ import annotations

import os
from pathlib import Path


def broken_link_on(path: Path) -> str | None:
    """Why a write to ``path`` would fail, or None: a control character in it (a newline or a
    tab: a ROS parameter does not carry it, so a node would write elsewhere), or the path
    itself, or a folder on its way, is a link to nothing or part of a loop of links (writing
    would follow it, or fail on it only after the work)."""
    if not str(path).isprintable():
        return (f'{str(path)!r} holds a control character (a newline or a tab?), which a ROS '
                'parameter does not carry')
    for entry in (path, *path.parents):
        if entry.is_symlink() and not entry.exists():        # exists() is False in a loop
            return (f'{entry} is a symbolic link to {os.readlink(entry)}, which does not exist '
                    'or leads back to itself')
    return None
