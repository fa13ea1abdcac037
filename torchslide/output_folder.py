"""Output folders of the commands: checked before any run, one writer at a time, written whole or not at all."""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .config import ConfigError
from .files import folder_lock


def _nearest_existing(p: Path) -> Path:
    p = p.absolute()
    while not p.exists():
        p = p.parent
    return p


def check_writable(out: Path) -> Path:
    """The nearest existing ancestor of ``out``, checked to take a new folder (ConfigError otherwise)."""
    if str(out) in ("", "."):
        raise ConfigError("--out must name an output folder, not the current folder")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output path {out} exists and is not a folder")
    anc = _nearest_existing(out.parent)
    if not anc.is_dir():
        raise ConfigError(f"cannot write the output folder {out}: {anc} is a file, not a folder")
    try:                                 # os.access says yes on read-only or virtual file systems
        Path(tempfile.mkdtemp(prefix=".torchslide-probe-", dir=anc)).rmdir()
    except OSError as e:
        raise ConfigError(f"cannot write the output folder {out}: {e.strerror} in {anc}") from None
    return anc


def check_output(out: Path, overwrite: bool) -> Path:
    """Validate a folder written whole at the end (simulate, predict, example) before running; return the
    existing ancestor for the temporary folder."""
    anc = check_writable(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ConfigError(f"output folder {out} exists and is not empty (use --overwrite to replace it)")
    return anc


def prepare_work_folder(out: Path) -> Path:
    """Validate and create a folder written as the command goes (calibrate, sweep, diagnose: checkpoints,
    reports) before any run."""
    check_writable(out)
    out.mkdir(parents=True, exist_ok=True)
    return out


@contextmanager
def staged_output(out: Path, anc: Path, command: str):
    """Write into a temporary folder next to ``out`` (in ``anc``, from :func:`check_output`) and move it into
    place when the block ends; on any error (or Ctrl-C) remove it, so nothing is half-written."""
    tmp = Path(tempfile.mkdtemp(prefix=f".torchslide-{command}-", dir=anc))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)   # the permissions of an ordinary folder, not mkdtemp's private 0700
    try:
        yield tmp
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def run_locked(out, fn, args) -> int:
    """``fn(args)`` while this process holds the write lock of ``out`` (after checking it can be written):
    a second command writing the same folder is refused, not mixed in."""
    out = Path(out)
    check_writable(out)
    with folder_lock(out):
        return fn(args)

