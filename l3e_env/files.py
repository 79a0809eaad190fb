"""Atomic file writes: a reader, or a resumed job, never sees half a file; and what differs
between the settings a folder was made with and a run that would resume it."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, BinaryIO, Callable


def write_atomic(path: str | Path, write: Callable[[BinaryIO], None]) -> None:
    """Write through a temporary file beside `path`, fsync, rename. On any failure the temporary
    file is removed and whatever was at `path` before is left untouched."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def settings_changed(before: dict[str, Any], now: dict[str, Any]) -> str:
    """The top-level settings that differ, named for an error message: the old and new values of
    the short ones, the names only of long ones (a mesh's route is a long list)."""
    def shown(key: str) -> str:
        old, new = repr(before.get(key)), repr(now.get(key))
        return key if len(old) + len(new) > 80 else f"{key} {old}, now {new}"

    return ", ".join(shown(k) for k in sorted(before.keys() | now.keys()) if before.get(k) != now.get(k))
