"""Solver benchmark: cell-updates per second (eager vs torch.compile, batch 1/8/32) on the Bondo-like
terrain, and the wall time per member of a full Bondo-like run (20 m cells, mu 0.23, xi 1000).

    python -m bench.bench_solver --out bench/results/solver.json [--device cuda] [--quick]

A cell-update is one cell of one member advanced by one (two-stage) time step.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numpy as np
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import DEM


def _fallback_bondo(cellsize: float = 20.0):
    """A simple stand-in valley (steep cirque, then a channel to a fan) if terrain.synthetic is absent."""
    class T:  # noqa: D401
        pass
    nx, ny = int(6000 / cellsize), int(2400 / cellsize)
    x = (np.arange(nx) + 0.5) * cellsize
    y = (np.arange(ny) + 0.5) * cellsize
    X, Y = np.meshgrid(x, y)
    yc = 1200 + 150 * np.sin(X / 900.0)
    z = 2500 * np.exp(-X / 2000.0) + 0.0008 * (Y - yc) ** 2 * (1 + X / 6000)
    t = T()
    t.dem = DEM(z, cellsize)
    t.release = np.clip(25.0 * (1 - ((X - 500) / 250) ** 2 - ((Y - yc) / 200) ** 2), 0, None)
    t.points = {"L1": (2500.0, 1200.0), "L2": (4000.0, 1200.0), "L3": (5200.0, 1200.0)}
    return t


def load_terrain(cellsize: float = 20.0):
    try:
        from torchslide.terrain.synthetic import bondo_like  # type: ignore
        return bondo_like(cellsize=cellsize), "torchslide.terrain.synthetic.bondo_like"
    except Exception as e:  # noqa: BLE001 - the other helper's module may not exist yet
        return _fallback_bondo(cellsize), f"bench fallback valley ({type(e).__name__})"


def throughput(terrain, B: int, compile_: bool, device: str, t_end: float, repeats: int) -> dict:
    cfg = SolverConfig(compile=compile_, stop_ke_fraction=0.0, output_interval=t_end, check_every=20)
    mu = np.linspace(0.15, 0.3, B)
    p = Params.make(mu=mu, xi=1000.0)
    ny, nx = terrain.dem.shape
    t0 = time.perf_counter()
    simulate(terrain.dem, terrain.release, p, t_end=t_end, config=cfg, device=device)  # warm-up / compile
    warm = time.perf_counter() - t0
    rates, walls = [], []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        r = simulate(terrain.dem, terrain.release, p, t_end=t_end, config=cfg, device=device)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        w = time.perf_counter() - t0
        walls.append(w)
        rates.append(float(r.steps.sum()) * ny * nx / w)
    return {"B": B, "compile": compile_, "cell_updates_per_s_median": statistics.median(rates),
            "wall_s_median": statistics.median(walls), "first_call_s": warm, "steps_per_member": float(r.steps.float().mean())}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="bench/results/solver.json")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--t-short", type=float, default=10.0, help="simulated seconds of the throughput runs")
    ap.add_argument("--batches", default="1,8,32")
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--full-batch", type=int, default=8, help="members in the full Bondo-like run")
    ap.add_argument("--full-t-end", type=float, default=300.0, help="simulated seconds of the full run")
    ap.add_argument("--cellsize", type=float, default=20.0, help="Bondo-like cell size, m")
    args = ap.parse_args(argv)
    terrain, source = load_terrain(args.cellsize)
    ny, nx = terrain.dem.shape
    res = {"load_average_at_start": os.getloadavg()[0], "terrain": source, "grid": [ny, nx], "cellsize_m": terrain.dem.cellsize, "device": args.device,
           "torch": torch.__version__, "threads": torch.get_num_threads(), "cpu": platform.processor() or platform.machine(),
           "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "throughput": []}
    for B in [int(b) for b in args.batches.split(",")]:
        for comp in ([False] if args.no_compile else [False, True]):
            row = throughput(terrain, B, comp, args.device, args.t_short, args.repeats)
            print(json.dumps(row))
            res["throughput"].append(row)
    ratios = {}
    for B in {r["B"] for r in res["throughput"]}:
        e = [r for r in res["throughput"] if r["B"] == B and not r["compile"]]
        c = [r for r in res["throughput"] if r["B"] == B and r["compile"]]
        if e and c:
            ratios[str(B)] = c[0]["cell_updates_per_s_median"] / e[0]["cell_updates_per_s_median"]
    res["compile_speedup"] = ratios
    # full run: mu 0.23, xi 1000 (batch of identical members to measure the per-member cost)
    Bf = args.full_batch
    for comp in ([False] if args.no_compile else [False, True]):
        cfg = SolverConfig(compile=comp)
        p = Params.make(B=Bf, mu=0.23, xi=1000.0)
        t0 = time.perf_counter()
        r = simulate(terrain.dem, terrain.release, p, t_end=args.full_t_end, config=cfg, device=args.device)
        w = time.perf_counter() - t0
        row = {"compile": comp, "B": Bf, "wall_s": w, "wall_s_per_member": w / Bf,
               "t_final_s": float(r.t_final[0]), "steps": int(r.steps[0]), "stopped": bool(r.stopped[0]),
               "release_volume_m3": float(r.release_volume[0]), "final_volume_m3": float(r.final_volume[0]),
               "outflow_m3": float(r.outflow_volume[0])}
        print(json.dumps(row))
        res.setdefault("full_run", []).append(row)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
