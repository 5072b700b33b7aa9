"""The controller state on disk: written atomically every visit, read back at start.

A restarted ofc_node continues from the last visit it applied: the accumulated DoF, the filter
state (or the PI integral) and the last applied stamp, so that a visit applied before the
restart is refused after it (``stale_visit``). JSON, so that an operator can read it. Written
to a temporary file in the same directory, flushed to disk and renamed over the old one: a
crash leaves either the old state or the new, never half of one.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from cwfs_ros.errors import ConfigError

__all__ = ["STATE_VERSION", "load_state", "save_state"]

STATE_VERSION = 1


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.integer, np.floating)):
        return v.item()
    return v


def save_state(path: str | Path, state: dict[str, Any]) -> None:
    """Write ``state`` (arrays, numbers, strings, None) to ``path`` atomically."""
    p = Path(path).expanduser()
    p.parent.mkdir(parents=True, exist_ok=True)
    doc = {"version": STATE_VERSION, **{k: _jsonable(v) for k, v in state.items()}}
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_state(path: str | Path) -> dict[str, Any] | None:
    """The state saved at ``path``, or None when there is no file. Raises ConfigError for a
    file that is not a state of this version (an operator must look, not a silent restart
    from zero)."""
    p = Path(path).expanduser()
    # Temporary files of writes that a crash interrupted (save_state's own prefix).
    for tmp in p.parent.glob(f".{p.name}.*") if p.parent.is_dir() else ():
        tmp.unlink(missing_ok=True)
    if not p.exists():
        return None
    if not p.is_file():
        raise ConfigError(f"controller state {p}: not a file")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"controller state {p}: unreadable ({exc}); move it away or call "
                          "~/reset") from exc
    if not isinstance(doc, dict) or doc.get("version") != STATE_VERSION:
        raise ConfigError(f"controller state {p}: not a version-{STATE_VERSION} state file")
    return doc
