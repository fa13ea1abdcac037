"""Wall time of one ``torchslide diagnose`` case, as a user runs it: a harness case written as files, then the CLI.

    OMP_NUM_THREADS=2 python -m bench.bench_diagnose --out bench/results/diagnose_case.json

Each case (``SCENARIO:SEED:TERRAIN``, default a null and an entrainment case) is written by
experiments.hidden_physics.export_case (40 m DEM, deposit map, two gauges with h and speed, the harness'
budgets and thresholds, no finer terrain) and diagnosed by ``torchslide diagnose`` in this process, with
the process' torch threads (OMP_NUM_THREADS). Reports per case the wall time (median of ``--repeats``),
the report's time per stage (report.json "timings", of the last repeat) and the verdict, so the figure
the diagnosis promises (a 40 m case in under 5 minutes on 2 idle cores) is measured by one command.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch

from experiments.hidden_physics import export_case
from bench import write_result
from torchslide.cli import main as cli

DEFAULT_CASES = "null:0:fan,entrainment:0:narrow"


def _diagnose(toml: Path, out: Path) -> tuple[float, dict]:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rc = cli(["diagnose", str(toml), "--out", str(out)])
    wall = time.perf_counter() - t0
    if rc != 0:
        raise RuntimeError(f"torchslide diagnose {toml} failed with exit code {rc}")
    return wall, json.loads((out / "report.json").read_text())


def run_case(spec: str, work: Path, repeats: int) -> dict:
    """One case ``SCENARIO:SEED:TERRAIN``: its wall time (s, median of ``repeats``), stage times and verdict."""
    scenario, seed, terrain = spec.split(":")
    case = work / spec.replace(":", "_")
    if export_case.main([scenario, seed, "--terrain", terrain, "--out", str(case)]) != 0:
        raise RuntimeError(f"export_case {spec} failed")
    walls, report = [], None
    for _ in range(repeats):
        wall, report = _diagnose(case / "diagnose.toml", case / "diagnosis")
        walls.append(wall)
    return {"case": spec, "wall_s": statistics.median(walls), "wall_s_each": walls,
            "stage_s": report["timings"], "verdict": report["verdict"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/results/diagnose_case.json")
    ap.add_argument("--cases", default=DEFAULT_CASES, help="comma-separated SCENARIO:SEED:TERRAIN")
    ap.add_argument("--repeats", type=int, default=1)
    a = ap.parse_args(argv)
    bad = [spec for spec in a.cases.split(",") if len(spec.split(":")) != 3]
    if bad:
        raise SystemExit(f"--cases {bad[0]!r}: each case must be SCENARIO:SEED:TERRAIN, e.g. null:0:fan")
    work = Path(tempfile.mkdtemp(prefix="bench_diagnose_"))
    rows = [run_case(spec, work, a.repeats) for spec in a.cases.split(",")]
    res = {"what": "torchslide diagnose on one exported harness case (40 m, deposit map, 2 gauges)",
           "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "repeats": a.repeats,
           "cases": rows, "slowest_wall_s": max(r["wall_s"] for r in rows)}
    write_result(a.out, res)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
