"""CUDA graphs of solver steps: n steps recorded once, then replayed with one launch.

A step costs the host kernel launches and tensor allocations (the Triton step five launches, the torch step
some hundreds); where that is more than the card's time for the step, the card waits. A CUDA graph records
the n steps between two host checks (the same kernels in the same order on the same memory, so the same
bits) and replays them with one call. SolverConfig.cuda_graphs is off by default until a GPU run measures it
(`make bench-solver-gpu`). A recording is only valid for the tensors it was made with: the caller
starts a new ``StepGraphs`` whenever the working set changes (a new cropping box, members dropped).
The step must not synchronise with the host (stepping.make_step, fused_triton.triton_step do not).
"""
from __future__ import annotations

from typing import Callable

import torch

from .crop import SPATIAL

Tensor = torch.Tensor


class StepGraphs:
    """``run(S, n)``: n calls of ``advance(S, *args)`` (simulate's step with its output record) for one
    working set (``args`` fixed: parameters, output times, gauges); the first ``warm`` calls for each n
    run step by step (compiling the kernels for this working set's shapes), the later ones replay a graph.

    The returned rasters (crop.SPATIAL) are the graph's own output buffers, overwritten by the next
    replay (the caller replaces its state with each result and copies rasters out before moving on);
    everything else (per-member values and records) is returned as copies.
    """

    def __init__(self, advance: Callable, args: tuple, warm: int = 1):
        self.advance, self.args, self.warm = advance, args, warm
        self.calls: dict[int, int] = {}
        self.graphs: dict[int, tuple] = {}

    def _steps(self, S: dict, n: int) -> dict:
        for _ in range(n):
            S = self.advance(S, *self.args)
        return S

    def _record(self, S: dict, n: int) -> tuple:
        """(graph, its input buffers, its outputs) of n steps. Recorded on a side stream with the graph's
        own memory pool, without torch.cuda.graph's garbage collection and cache flush (a run records a
        graph for every cropping box)."""
        inputs = {k: v.clone() if torch.is_tensor(v) else v for k, v in S.items()}
        graph, side = torch.cuda.CUDAGraph(), torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            graph.capture_begin()
            try:
                out = self._steps(dict(inputs), n)
            finally:
                graph.capture_end()
        torch.cuda.current_stream().wait_stream(side)
        return graph, inputs, out

    def run(self, S: dict, n: int) -> dict:
        """The state after n steps from ``S`` (a dict of tensors on one CUDA device)."""
        self.calls[n] = self.calls.get(n, 0) + 1
        if self.calls[n] <= self.warm:
            return self._steps(S, n)
        if n not in self.graphs:
            self.graphs[n] = self._record(S, n)
        graph, inputs, out = self.graphs[n]
        for k, v in inputs.items():
            if torch.is_tensor(v):
                v.copy_(S[k])
        graph.replay()
        return {k: (v.clone() if torch.is_tensor(v) and k not in SPATIAL else v) for k, v in out.items()}
