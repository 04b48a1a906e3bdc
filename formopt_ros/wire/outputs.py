"""Output paths: the symbolic-link check that the commands and the nodes share."""
from __future__ import annotations

import os
from pathlib import Path


def broken_link_on(path: Path) -> str | None:
    """Why a write to ``path`` would fail on a symbolic link, or None: the path itself, or a
    folder on its way, is a link to nothing or part of a loop of links (writing would follow
    it, or fail on it only after the work)."""
    for entry in (path, *path.parents):
        if entry.is_symlink() and not entry.exists():        # exists() is False in a loop
            return (f'{entry} is a symbolic link to {os.readlink(entry)}, which does not exist '
                    'or leads back to itself')
    return None
