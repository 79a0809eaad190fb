"""Atomic file writes: a reader, or a resumed job, never sees half a file; and one writer a folder."""

from __future__ import annotations

import contextlib
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
    killed run leaves no stale lock behind; a run that ends removes the file."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / ".lock"
    while True:
        fh = open(path, "a+")  # noqa: SIM115 - held open across the block
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            fh.close()
            raise FolderBusyError(
                f"{folder}: another run (pid {holder}) is writing into it; wait for it to end or choose another folder"
            ) from None
        with contextlib.suppress(FileNotFoundError):
            if os.stat(path).st_ino == os.fstat(fh.fileno()).st_ino:
                break  # the file at the path is the one locked (not one a finishing run removed)
        fh.close()
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # while still held: a run that opened the old file finds it gone and tries again
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()


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
