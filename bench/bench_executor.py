"""A 256-run sweep in this process and on a Dask LocalCluster of 1 and 2 worker processes.

    python -m bench.bench_executor --out bench/results/executor.json

The sweep is ``torchslide sweep --n 16`` (16 x 16 nodes of mu, xi) on the Bondo-like example case
(``torchslide example bondo``, 60 m cells) with ``max_batch`` members per solver call; every setting
runs the same chunks, so the three sweeps' results are identical (checked here) and only the wall
time differs. Reports each wall time (median of ``--repeats``; the LocalCluster's start-up included,
as a user pays it) and the speed-up of 2 workers over 1 and over the local run.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import write_result
from torchslide.cli import main as cli


def _sweep(case: Path, out: Path, extra: list[str]) -> float:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rc = cli(["sweep", str(case / "calibrate.toml"), "--out", str(out), "--n", "16", "--quiet"] + extra)
    if rc not in (0, 1):
        raise RuntimeError(f"sweep failed with exit code {rc}")
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/results/executor.json")
    ap.add_argument("--max-batch", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=1)
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench_executor_"))
    case = work / "case"
    if cli(["example", "bondo", "--out", str(case)]) != 0:
        raise RuntimeError("torchslide example bondo failed")
    toml = (case / "calibrate.toml").read_text()
    if "max_batch" in toml:
        raise RuntimeError("the example's calibrate.toml already sets max_batch")
    (case / "calibrate.toml").write_text(toml.replace("[calibration]", f"[calibration]\nmax_batch = {a.max_batch}"))
    settings = {"local": [], "dask, 1 worker": ["--executor", "dask", "--workers", "1"],
                "dask, 2 workers": ["--executor", "dask", "--workers", "2"]}
    wall, z = {}, {}
    for name, extra in settings.items():
        out = work / name.replace(", ", "_").replace(" ", "")
        wall[name] = statistics.median(_sweep(case, out, extra) for _ in range(a.repeats))
        z[name] = np.load(out / "sweep.npz")["z"]
    identical = all(np.array_equal(z["local"], v) for v in z.values())
    res = {"case": "torchslide example bondo (60 m cells), sweep --n 16 (256 runs)", "max_batch": a.max_batch,
           "cpu_count": os.cpu_count(), "torch_threads_per_process": int(os.environ.get("OMP_NUM_THREADS", "0")) or None,
           "wall_s": wall, "speedup_2_workers_over_1": wall["dask, 1 worker"] / wall["dask, 2 workers"],
           "speedup_2_workers_over_local": wall["local"] / wall["dask, 2 workers"],
           "results_identical": identical, "repeats": a.repeats}
    write_result(a.out, res)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
