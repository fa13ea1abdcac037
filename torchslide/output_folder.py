"""Output folders of the commands: checked before any run, written whole or not at all."""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .config import ConfigError


def _nearest_existing(p: Path) -> Path:
    p = p.absolute()
    while not p.exists():
        p = p.parent
    return p


def check_output(out: Path, overwrite: bool) -> Path:
    """Validate the output folder before running; return the existing ancestor for the temp folder."""
    if out.exists():
        if not out.is_dir():
            raise ConfigError(f"output path {out} exists and is not a folder")
        if any(out.iterdir()) and not overwrite:
            raise ConfigError(f"output folder {out} exists and is not empty (use --overwrite to replace it)")
    anc = _nearest_existing(out.parent)
    if not anc.is_dir() or not os.access(anc, os.W_OK):
        raise ConfigError(f"cannot write the output folder {out}: {anc} is not a writable folder")
    return anc


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
