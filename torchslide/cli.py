"""The ``torchslide`` console script: a thin dispatcher over subcommand modules.

Each subcommand lives in its own module that defines

* ``HELP``: a one-line description (str),
* ``add_arguments(parser)``: adds its arguments to an ``argparse.ArgumentParser``,
* ``run(args) -> int``: does the work and returns the exit code.

Register a new one by adding ``name: "module.path"`` to :data:`SUBCOMMANDS` (or calling
:func:`register`). Modules that are not present yet are skipped.

Errors: bad input (:class:`torchslide.config.ConfigError`, :class:`torchslide.terrain.TerrainError`), a
file in a state the command cannot use (:class:`torchslide.files.FileStateError`) and a file-system error
(OSError) print one line ``torchslide: error: ...`` on stderr and exit with code 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS: dict[str, str] = {
    "simulate": "torchslide.commands.simulate",
    "calibrate": "torchslide.commands.calibrate",
    "predict": "torchslide.commands.predict",
    "diagnose": "torchslide.commands.diagnose",
    "sweep": "torchslide.commands.sweep",
    "example": "torchslide.commands.example",
}


def register(name: str, module: str) -> None:
    """Add a subcommand implemented by ``module`` (which defines HELP, add_arguments, run)."""
    SUBCOMMANDS[name] = module


class _Unavailable:
    """Stands in for a command module that failed to import (e.g. a missing optional dependency)."""

    def __init__(self, name: str, error: Exception) -> None:
        self.HELP = f"(unavailable: {error})"
        self._msg = f"command {name!r} is unavailable: {type(error).__name__}: {error}"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("rest", nargs=argparse.REMAINDER)

    def run(self, args) -> int:
        print(f"torchslide: error: {self._msg}", file=sys.stderr)
        return 2


def _load(name: str, module: str):
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):  # the command module itself is absent: skip it
            return None
        return _Unavailable(name, e)
    except ImportError as e:
        return _Unavailable(name, e)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="torchslide",
        description="Batched landslide run-out simulation, Bayesian calibration and diagnosis.",
    )
    parser.add_argument("--version", action="version", version=f"torchslide {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in SUBCOMMANDS.items():
        mod = _load(name, module)
        if mod is None:
            continue
        p = sub.add_parser(name, help=getattr(mod, "HELP", None), description=getattr(mod, "HELP", None))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    from .config import ConfigError
    from .files import FileStateError
    from .terrain.grid import TerrainError

    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args._run(args) or 0)
    except (ConfigError, TerrainError, FileStateError, OSError) as e:
        msg = " ".join(str(e).split())  # one line
        print(f"torchslide: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torchslide: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
