"""Batched, resumable parameter sweep of the solver over the prior box (brute-force reference posteriors)."""
from .core import SweepResult, reference_posterior, run_sweep, sweep_axes

__all__ = ["SweepResult", "reference_posterior", "run_sweep", "sweep_axes"]
