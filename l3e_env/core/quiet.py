"""PyBullet without its build banner: the C library prints "pybullet build time: ..." to standard error
when it is imported, into every command's output. Hand-written: pybullet has no switch for it, so the
banner is sent to /dev/null at the file-descriptor level while the module loads."""

from __future__ import annotations

import os
import sys
from types import ModuleType


def import_pybullet() -> ModuleType:
    """`import pybullet`, with its banner dropped; where standard error is no file descriptor (a
    notebook's), imported as it is."""
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        import pybullet

        return pybullet
    sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), fd)
            import pybullet
    finally:
        os.dup2(saved, fd)
        os.close(saved)
    return pybullet
