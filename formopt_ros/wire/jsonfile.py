"""Strict JSON files: non-finite numbers become null (JSON has no NaN), written atomically."""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (numpy scalars and arrays too)."""
    if hasattr(value, 'tolist') and not isinstance(value, (str, bytes)):
        value = value.tolist()                       # numpy arrays and scalars
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented strict JSON to ``path`` (folders created; a crash mid-write
    leaves the previous file, never half a file)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    temporary = target.with_name(target.name + '.tmp')
    try:
        temporary.write_text(json.dumps(json_safe(data), indent=2, allow_nan=False) + '\n')
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)       # only left after a failure: never keep it
