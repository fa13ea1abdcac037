"""Solver benchmark on the Bondo-like terrain (torchslide.terrain.synthetic.bondo_like) or a real event's.

    python -m bench.bench_solver --out bench/results/solver.json [--device cuda] [--batches 1,8,32]
    python -m bench.bench_solver --terrain msh2021 --mu 0.4 --xi 2500 --skip-throughput ...

``--terrain msh2021``: the embedded 2021 Mount St. Helens event (``torchslide example msh2021``: its 10 m DEM
lowered by the failure depths, the release they give), the grid and flow of the runs its calibration and
diagnosis make (a long, narrow path on a small grid: the cropping box, not the grid, sets the cost).

Two parts, each measured in this one process (medians of ``--repeats``; ratios between rows of the
same run only, since the machines are shared):

1. Throughput (cell-updates per second, whole grid, active-region cropping off so that every step
   costs the same) of each kernel (SolverConfig.kernel: eager, compiled = torch.compile, fused = the
   fused CPU step or, on CUDA, the Triton step) at batch 1/8/32, float64 and float32. On CUDA each row
   also gives its fraction of the bandwidth limit: the card's copy bandwidth, measured in the same run,
   over BYTES_PER_CELL_UPDATE values per cell-update. A cell-update is one cell of one member
   advanced by one (two-stage) time step. first_call_s: the first call in this process (compilation,
   or for "fused" loading numba's on-disk cache; the very first call after an install compiles it).
   On CUDA, ``--graphs on,off`` measures each kernel with and without CUDA graphs
   (SolverConfig.cuda_graphs; "compiled" runs without).
2. Full runs: the wall time per member of one run (mu 0.23, xi 1000 unless --mu, --xi; t_end 300 s; 20 m
   cells by default) for the configurations a calibration can use: eager float64 on the whole grid
   (the reference), with cropping, per kernel and precision. Compiled and fused rows are warmed up
   first (first_call_s). The "runs_120_min" column is 120 x the per-member wall time (one calibration
   of 40 + 80 runs).
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
from torchslide.terrain.synthetic import bondo_like

DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _timed(case, p, t_end, cfg, dtype, device):
    _sync(device)
    t0 = time.perf_counter()
    r = simulate(case.dem, case.release, p, t_end=t_end, config=cfg, dtype=dtype, device=device)
    _sync(device)
    return r, time.perf_counter() - t0


BYTES_PER_CELL_UPDATE = 20
"""Values of the state's dtype one cell-update must at least read and write through memory in a fused
second-order step (about 80 bytes in float32): the bandwidth model of the "bandwidth_fraction" column."""


def copy_bandwidth(device: str, n_bytes: int = 2 ** 30, repeats: int = 10) -> float | None:
    """The device's measured copy bandwidth, bytes/s (read + write of a device-to-device copy of
    ``n_bytes``; the median of ``repeats``); None on the CPU."""
    if not device.startswith("cuda"):
        return None
    a = torch.empty(n_bytes, dtype=torch.uint8, device=device)
    b = torch.empty_like(a)
    rates = []
    for _ in range(repeats + 1):
        _sync(device)
        t0 = time.perf_counter()
        b.copy_(a)
        _sync(device)
        rates.append(2 * n_bytes / (time.perf_counter() - t0))
    return statistics.median(rates[1:])


def bandwidth_fraction(row: dict, copy_bw: float | None) -> float | None:
    """Cell-updates/s of ``row`` as a fraction of the bandwidth limit copy_bw / (BYTES_PER_CELL_UPDATE
    values of its dtype)."""
    if copy_bw is None:
        return None
    size = torch.tensor([], dtype=DTYPES[row["dtype"]]).element_size()
    return row["cell_updates_per_s_median"] * BYTES_PER_CELL_UPDATE * size / copy_bw


LAUNCH = ("BLOCK", "NUM_WARPS", "FACES")
"""The Triton step's settings a --launch row sets (fused_triton's module constants)."""


def parse_launch(spec: str) -> tuple[int, int, str]:
    """'BLOCKxNUM_WARPS[:march|lines]' (e.g. '128x4:lines') -> (BLOCK, NUM_WARPS, FACES) of the Triton step: the
    line design's kernels' cells per program and warps, and the design of the faces (default fused_triton's)."""
    from torchslide.solver import fused_triton

    sizes, *rest = spec.split(":")
    block, _, warps = sizes.partition("x")
    if not (block.isdigit() and warps.isdigit()) or len(rest) > 1 or any(r not in ("march", "lines") for r in rest):
        raise SystemExit(f"--launch: {spec!r} is not BLOCKxNUM_WARPS[:march|lines]")
    return int(block), int(warps), rest[0] if rest else fused_triton.FACES


FULL_CONFIG = "{eager|compiled|fused}-{f64|f32}-{whole|crop}[:B][:graphs]"
"""The form of a --full-configs entry: kernel, dtype, the whole grid or cropped to the flow, the members (default
--full-batch) and CUDA graphs on."""


def parse_full_config(spec: str, full_batch: int) -> tuple[str, str, bool, int, bool]:
    """A --full-configs entry (FULL_CONFIG, e.g. 'fused-f32-crop:10:graphs') -> (kernel, dtype, crop, B, graphs)
    of a full run; a malformed one stops with a line naming it."""
    name, *opts = spec.split(":")
    parts = name.split("-")
    ok = (len(parts) == 3 and parts[0] in ("eager", "compiled", "fused") and parts[1] in ("f64", "f32")
          and parts[2] in ("whole", "crop") and all(o == "graphs" or (o.isdigit() and int(o) > 0) for o in opts)
          and sum(o.isdigit() for o in opts) <= 1 and opts.count("graphs") <= 1)
    if not ok:
        raise SystemExit(f"--full-configs: {spec!r} is not {FULL_CONFIG}")
    b = [int(o) for o in opts if o.isdigit()]
    return parts[0], {"f64": "float64", "f32": "float32"}[parts[1]], parts[2] == "crop", b[0] if b else full_batch, \
        "graphs" in opts


def throughput(case, B: int, kernel: str, dtype: str, device: str, t_end: float, repeats: int,
               graphs: bool = False, launch: tuple[int, int, str] | None = None) -> dict:
    """One row; ``launch``: (BLOCK, NUM_WARPS, FACES) of the Triton step (fused on CUDA; None: its defaults)."""
    from torchslide.solver import fused_triton

    default = tuple(getattr(fused_triton, k) for k in LAUNCH)
    for k, v in zip(LAUNCH, launch or default):
        setattr(fused_triton, k, v)
    try:
        row = _throughput(case, B, kernel, dtype, device, t_end, repeats, graphs)
    finally:
        for k, v in zip(LAUNCH, default):
            setattr(fused_triton, k, v)
    if launch is not None:
        row["block"], row["num_warps"], row["faces"] = launch
    return row


def _throughput(case, B: int, kernel: str, dtype: str, device: str, t_end: float, repeats: int,
                graphs: bool) -> dict:
    cfg = SolverConfig(kernel=kernel, crop=False, stop_ke_fraction=0.0, output_interval=t_end, check_every=20,
                       cuda_graphs=graphs)
    p = Params.make(mu=np.linspace(0.15, 0.3, B), xi=1000.0)
    ny, nx = case.dem.shape
    _, warm = _timed(case, p, t_end, cfg, DTYPES[dtype], device)  # warm-up / compilation
    rates, walls = [], []
    for _ in range(repeats):
        r, w = _timed(case, p, t_end, cfg, DTYPES[dtype], device)
        walls.append(w)
        rates.append(float(r.steps.sum()) * ny * nx / w)
    failed = int(r.failed.sum()) if r.failed is not None else 0
    if failed:
        print(f"bench_solver: {failed} of {B} members of {kernel} {dtype} failed ({next((x for x in r.failure_reason if x), '')}): "
              "this row's rate is not a throughput", flush=True)
    return {"B": B, "kernel": kernel, "dtype": dtype, "cuda_graphs": graphs and device.startswith("cuda"),
            "cell_updates_per_s_median": statistics.median(rates),
            "wall_s_median": statistics.median(walls), "first_call_s": warm,
            "steps_per_member": float(r.steps.float().mean()), "failed_members": failed}


def full_run(case, B: int, kernel: str, crop: bool, dtype: str, device: str, t_end: float, repeats: int,
             mu: float = 0.23, xi: float = 1000.0, graphs: bool = False) -> dict:
    cfg = SolverConfig(kernel=kernel, crop=crop, cuda_graphs=graphs)
    p = Params.make(B=B, mu=mu, xi=xi)
    warm = None
    if kernel != "eager":  # compile (or load) both code paths (small and large boxes) before timing
        _, warm = _timed(case, p, min(60.0, t_end), cfg, DTYPES[dtype], device)
    walls = []
    for _ in range(repeats):
        r, w = _timed(case, p, t_end, cfg, DTYPES[dtype], device)
        walls.append(w)
    w = statistics.median(walls)
    return {"kernel": kernel, "crop": crop, "dtype": dtype, "B": B, "cuda_graphs": graphs, "mu": mu, "xi": xi,
            "wall_s_median": w,
            "wall_s_repeats": walls,
            "wall_s_per_member": w / B, "runs_120_min": 120 * w / B / 60.0, "first_call_s": warm,
            "t_final_s": float(r.t_final[0]), "steps": int(r.steps[0]), "stopped": bool(r.stopped[0]),
            "release_volume_m3": float(r.release_volume[0]), "final_volume_m3": float(r.final_volume[0]),
            "h_max_max_m": float(r.h_max[0].max()), "v_max_max_ms": float(r.v_max[0].max())}


def full_run_speedups(rows: list) -> dict:
    """{"full_run_speedup_vs_eager_whole_f64": {config-B: per-member speed-up}} against the eager
    float64 whole-grid row of the same run (empty when that row is missing)."""
    base = [r for r in rows if r["kernel"] == "eager" and not r["crop"] and r["dtype"] == "float64"]
    if not base:
        return {}
    return {"full_run_speedup_vs_eager_whole_f64": {
        f"{r['kernel']}-{r['dtype']}-{'crop' if r['crop'] else 'whole'}-B{r['B']}":
            base[0]["wall_s_per_member"] / r["wall_s_per_member"] for r in rows}}


def event_case(name: str, work: str):
    """(dem, release) of the embedded event ``name`` as ``torchslide example`` writes it and a run of its
    simulate.toml reads it, under the folder ``work``."""
    from types import SimpleNamespace

    from torchslide.cli import main as cli
    from torchslide.config import load_config

    folder = os.path.join(work, name)
    if cli(["example", name, "--out", folder]) != 0:
        raise SystemExit(f"torchslide example {name} failed")
    cfg = load_config(os.path.join(folder, "simulate.toml"))
    return SimpleNamespace(dem=cfg.terrain.dem, release=cfg.terrain.release)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/results/solver.json")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--t-short", type=float, default=5.0, help="simulated seconds of the throughput runs")
    ap.add_argument("--batches", default="1,8,32")
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--kernels", default="eager,compiled,fused", help="comma list of SolverConfig.kernel values")
    ap.add_argument("--full-batch", type=int, default=8, help="members in the full Bondo-like run")
    ap.add_argument("--full-repeats", type=int, default=1)
    ap.add_argument("--full-t-end", type=float, default=300.0, help="simulated seconds of the full run")
    ap.add_argument("--full-configs", default="eager-f64-whole,eager-f64-crop,compiled-f64-crop,compiled-f32-crop",
                    help="comma list of {eager|compiled|fused}-{f64|f32}-{whole|crop}[:B][:graphs] (B defaults to "
                         "--full-batch; graphs: CUDA graphs on); '' skips the full runs")
    ap.add_argument("--cellsize", type=float, default=20.0, help="Bondo-like cell size, m")
    ap.add_argument("--terrain", default="bondo_like", choices=("bondo_like", "msh2021"),
                    help="the synthetic Bondo-like case or the embedded msh2021 event (torchslide example)")
    ap.add_argument("--mu", type=float, default=0.23, help="mu of every member of the full runs")
    ap.add_argument("--xi", type=float, default=1000.0, help="xi of every member of the full runs, m/s^2")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument("--graphs", default="off", help="on CUDA: 'on', 'off' or 'on,off' (SolverConfig.cuda_graphs)")
    ap.add_argument("--launch", default="", help="on CUDA: extra fused rows at these Triton launch settings, "
                                                   "BLOCKxNUM_WARPS[:march|lines] comma list (e.g. "
                                                   "512x4:march,128x4:lines; fused_triton.BLOCK, NUM_WARPS, FACES)")
    args = ap.parse_args(argv)
    full_configs = [parse_full_config(x, args.full_batch) for x in filter(None, args.full_configs.split(","))]
    launches = [parse_launch(x) for x in filter(None, args.launch.split(","))]     # both checked before any run
    if args.terrain == "msh2021":
        import tempfile

        with tempfile.TemporaryDirectory(prefix="bench-") as work:     # the case is read into memory
            case = event_case(args.terrain, work)
        terrain = "torchslide example msh2021"
    else:
        case = bondo_like(args.cellsize)
        terrain = "torchslide.terrain.synthetic.bondo_like"
    ny, nx = case.dem.shape
    res = {"load_average_at_start": os.getloadavg()[0], "terrain": terrain,
           "grid": [ny, nx], "cellsize_m": case.dem.cellsize, "device": args.device, "torch": torch.__version__,
           "threads": torch.get_num_threads(), "numba_threads": os.environ.get("NUMBA_NUM_THREADS"), "cpu": platform.processor() or platform.machine(),
           "cpu_count": os.cpu_count(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
           "gpu": torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None,
           "copy_bandwidth_bytes_per_s": copy_bandwidth(args.device), "throughput": [], "full_run": []}

    def save():
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(res, f, indent=2)

    if not args.skip_throughput:
        for dtype in args.dtypes.split(","):
            for B in [int(b) for b in args.batches.split(",")]:
                for kernel in args.kernels.split(","):
                    for graphs in ([g == "on" for g in args.graphs.split(",")] if args.device.startswith("cuda")
                                   else [False]):
                        if kernel == "compiled" and graphs:
                            continue
                        row_launches = [None]
                        if kernel == "fused" and args.device.startswith("cuda") and not graphs:
                            row_launches += launches
                        for launch in row_launches:
                            row = throughput(case, B, kernel, dtype, args.device, args.t_short, args.repeats, graphs,
                                             launch)
                            row["bandwidth_fraction"] = bandwidth_fraction(row, res["copy_bandwidth_bytes_per_s"])
                            print(json.dumps(row), flush=True)
                            res["throughput"].append(row)
                            save()
        ratios = {}
        for row in res["throughput"]:
            if row["kernel"] != "eager" and "block" not in row:
                e = [r for r in res["throughput"] if r["B"] == row["B"] and r["dtype"] == row["dtype"]
                     and r["kernel"] == "eager" and r["cuda_graphs"] == row["cuda_graphs"]]
                if e:
                    tag = "" if row["cuda_graphs"] or not args.device.startswith("cuda") else "_nographs"
                    ratios[f"{row['kernel']}{tag}_{row['dtype']}_B{row['B']}"] = (row["cell_updates_per_s_median"]
                                                                               / e[0]["cell_updates_per_s_median"])
        res["speedup_vs_eager"] = ratios
    for kernel, dtype, crop, B, graphs in full_configs:     # --full-configs "" skips the full runs
        if kernel not in args.kernels.split(","):
            continue
        row = full_run(case, B, kernel, crop, dtype, args.device, args.full_t_end, args.full_repeats, args.mu, args.xi,
                       graphs=graphs)
        print(json.dumps(row), flush=True)
        res["full_run"].append(row)
        save()
    res.update(full_run_speedups(res["full_run"]))
    res["load_average_at_end"] = os.getloadavg()[0]
    save()
    print("wrote", args.out)


if __name__ == "__main__":
    main()
