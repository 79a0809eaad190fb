"""Atomic file writes: a reader, or a resumed job, never sees half a file; and one writer a folder."""

from __future__ import annotations

import fcntl
import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

import numpy as np


def npy_writer(array: np.ndarray) -> Callable[[BinaryIO], None]:
    """What write_atomic calls to write `array` as a .npy file."""
    return lambda fh: np.save(fh, array)


def write_atomic(path: str | Path, write: Callable[[BinaryIO], object]) -> None:
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


class FolderBusyError(RuntimeError):
    """Another run is writing into the folder."""


@contextmanager
def folder_lock(folder: str | Path) -> Iterator[None]:
    """Hold `folder` for this process while the block runs: a second run into the same folder is refused
    by name instead of writing over the first's files. The lock is the kernel's (flock on `.lock`), so a
    killed run leaves no stale lock behind."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "a+") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            raise FolderBusyError(
                f"{folder}: another run (pid {holder}) is writing into it; wait for it to end or choose another folder"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@contextmanager
def new_folder(folder: str | Path) -> Iterator[Path]:
    """`folder` created for the block (with its parents), and removed again, with what the block wrote
    there, where the block fails and the folder did not exist before it: a refused run leaves nothing
    behind. A folder that existed (a run resumed) is left as it is."""
    folder = Path(folder)
    fresh = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield folder
    except BaseException:
        if fresh:
            shutil.rmtree(folder, ignore_errors=True)
        raise
