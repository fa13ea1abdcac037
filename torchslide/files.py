"""The files torchslide writes and reads back: replaced whole or not at all, one writer per folder.

* :func:`atomic_path` / :func:`write_text_atomic`: write to a temporary file in the same folder, fsync,
  then rename over the target, so that a kill at any moment leaves the old file or the new one, never
  a truncated one (checkpoints, result JSON, tables); :func:`save_figure` does the same for figures.
* :func:`folder_lock`: one process at a time writes an output folder; a second is refused with the
  owner's pid, a lock left by a process that died is taken over.
* :class:`FileStateError`: a file or folder in a state the command cannot use (a corrupt or truncated
  checkpoint, a checkpoint of another configuration, a folder another process writes); the command
  line prints its message as one line and exits with 2.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


class FileStateError(ValueError):
    """A file or folder the command cannot use as it is; the message names it and says what to do."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path):
    """``with atomic_path(p) as tmp: write(tmp)``: ``tmp`` (a path in p's folder, same suffix) replaces
    ``p`` when the block ends without an error, after an fsync; on an error it is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_figure(fig, path, dpi: int) -> None:
    """``fig.savefig`` to ``path`` atomically (:func:`atomic_path`): a kill leaves the old figure or the new."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def lock_file(folder) -> Path:
    """The lock of ``folder``: a file beside it, so that it exists before the folder does."""
    folder = Path(folder).absolute()
    return folder.parent / f".{folder.name}.torchslide-lock"


@contextmanager
def folder_lock(folder):
    """Hold the write lock of ``folder`` for the block (FileStateError when a live process holds it)."""
    lock = lock_file(folder)
    lock.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _alive(pid):
                raise FileStateError(f"{folder} is being written by another torchslide process (pid {pid}, lock "
                                     f"{lock}); wait for it or choose another --out") from None
            lock.unlink(missing_ok=True)       # a lock left by a process that is gone: take it over
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        break
    else:
        raise FileStateError(f"could not take the lock {lock} of {folder}")
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
