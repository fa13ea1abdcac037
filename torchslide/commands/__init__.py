"""Subcommand implementations of the ``torchslide`` CLI (one module per command; see torchslide.cli)."""
from __future__ import annotations

import argparse
import contextlib


def add_executor_arguments(p: argparse.ArgumentParser) -> None:
    """--executor / --scheduler / --workers: override [run] executor, scheduler, workers (torchslide.executor)."""
    p.add_argument("--executor", choices=("local", "dask"), default=None,
                   help="where the solver batches run: this process (local) or Dask workers (dask); default [run]")
    p.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="with --executor dask: a running Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="with --executor dask: a LocalCluster of N worker processes on this machine")


@contextlib.contextmanager
def executor_for(args: argparse.Namespace, cfg, evaluator):
    """The evaluator with the executor of [run] as overridden by the CLI options, closed at the end."""
    from ..config import ConfigError, parse_executor

    r = {"executor": args.executor or cfg.run.executor}
    sched = args.scheduler if args.scheduler is not None else (None if args.workers is not None else cfg.run.scheduler)
    work = args.workers if args.workers is not None else (None if args.scheduler is not None else cfg.run.workers)
    r.update({k: v for k, v in (("scheduler", sched), ("workers", work)) if v is not None})
    kind, scheduler, workers = parse_executor(r, cfg.path)
    try:
        from ..executor import make_executor

        ex = make_executor(kind, scheduler=scheduler, workers=workers)
    except (RuntimeError, OSError) as e:
        raise ConfigError(f"{cfg.path}: executor {kind!r}: {e}") from None
    evaluator.executor = None if kind == "local" else ex
    try:
        yield evaluator
    finally:
        evaluator.executor = None
        ex.close()
