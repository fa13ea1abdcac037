"""Posterior-predictive runs: M posterior samples -> batched solver calls -> moments of every observable."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..predict import posterior_samples  # noqa: F401  (re-exported: the diagnosis draws with it)


def posterior_mode(cal) -> np.ndarray:
    """(p,) MAP of a CalibrationResult (summary 'map')."""
    return np.array([cal.summary["map"][n] for n in cal.names], dtype=np.float64)


@dataclass
class Predictive:
    """Posterior-predictive moments of the flat observable vector (k,).

    draws: (M_ok, k) predictions of the successful members; x: (M_ok, p) their parameters.
    """

    x: np.ndarray
    draws: np.ndarray
    n_failed: int

    @property
    def mean(self) -> np.ndarray:
        return self.draws.mean(axis=0)

    @property
    def var(self) -> np.ndarray:
        return self.draws.var(axis=0, ddof=1) if len(self.draws) > 1 else np.zeros(self.draws.shape[1])


def posterior_predictive(evaluator, samples: np.ndarray) -> Predictive:
    """Run the solver on all samples (in chunks of evaluator.max_batch members, one call per chunk)."""
    x = torch.as_tensor(np.asarray(samples, dtype=np.float64))
    res, preds = evaluator.evaluate(x)
    ok = ~res.failed.numpy()
    return Predictive(x=np.asarray(samples)[ok], draws=preds.numpy()[ok], n_failed=int((~ok).sum()))


def map_mismatches(evaluator, samples: np.ndarray, n: int = 16) -> dict:
    """Where the baseline's runs (the first ``n`` of ``samples`` (M, p)) and the mapped footprint disagree,
    in a modeller's terms (torchslide.predict.footprint_mismatches: clusters of excess and deficit, the
    run-out's shortfall or overshoot), with the maps for the report's figure ("mapped", "p_reached" (ny, nx));
    {} when no observation maps a footprint (no runs then); {"failed": why} when every run failed (a
    description must not end a finished diagnosis)."""
    from ..predict import footprint_mismatches, run_predictive
    from ..survey import FOOTPRINT_KINDS

    if not any(getattr(o, "kind", None) in FOOTPRINT_KINDS for o in evaluator.observations):
        return {}
    try:
        pr = run_predictive(evaluator, np.asarray(samples)[:n], evaluator.reach_threshold)
    except RuntimeError as e:
        return {"failed": str(e)}
    got = footprint_mismatches(evaluator, pr)
    return dict(got, p_reached=pr.impact_probability, threshold=pr.threshold, n_runs=len(pr.x))
