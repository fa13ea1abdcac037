"""Compile the fused steps once into their on-disk caches: ``python -m torchslide.solver.warm`` (what
``make`` runs at install), so that a user's first run loads them in about a second instead of compiling
(about a minute of CPU for the numba step; a few seconds per Triton kernel).

One small run per step that can run here: the fused CPU step (numba) in float64, and on a CUDA device the
Triton step in float32 and float64. The numba step compiles once for every set of terms (they are run-time
flags); Triton compiles each set of switched-on terms on first use, plain Voellmy here.
"""
from __future__ import annotations

import numpy as np
import torch

from ..physics import Params
from ..terrain.grid import DEM
from . import fused_cpu, fused_triton
from .config import SolverConfig
from .simulate import simulate


def warm() -> list[str]:
    """Run the small case on every fused step available here; returns the kernels that ran."""
    x = np.arange(12) * 10.0
    dem = DEM(z=np.tile(-0.5 * x, (8, 1)), cellsize=10.0)
    rel = np.zeros(dem.shape)
    rel[3:5, 2:4] = 2.0
    params = Params.make(mu=[0.2, 0.3], xi=500.0)
    ran = []
    runs = [("cpu", torch.float64)] if fused_cpu.available() else []
    if fused_triton.triton is not None and torch.cuda.is_available():
        runs += [("cuda", torch.float32), ("cuda", torch.float64)]
    for device, dtype in runs:
        r = simulate(dem, rel, params, t_end=2.0, config=SolverConfig(kernel="fused"), dtype=dtype, device=device)
        ran.append(f"{r.kernel} {str(dtype).removeprefix('torch.')}")
    return ran


if __name__ == "__main__":
    print("compiled: " + (", ".join(warm()) or "nothing (neither numba nor a CUDA device with triton)"))
