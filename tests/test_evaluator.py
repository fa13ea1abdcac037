"""LandslideEvaluator.best_fit: the best successful run's standardised residual per observation."""
from __future__ import annotations

import numpy as np
import pytest

from torchslide.bayes import Prior, Uniform
from torchslide.evaluator import LandslideEvaluator, RunRecord
from torchslide.observe import Observation
from torchslide.terrain import DEM


def _evaluator(**kw):
    dem = DEM(np.zeros((6, 6)), 10.0)
    obs = [Observation("max_velocity", 10.0, 2.0, x=25.0, y=25.0), Observation("max_velocity", 4.0, 1.0, x=35.0, y=25.0)]
    return LandslideEvaluator(dem=dem, release=np.ones((6, 6)), observations=obs,
                              prior=Prior({"mu": Uniform(0.05, 0.5)}), fixed={"xi": 1000.0}, **kw)


def test_best_fit_takes_the_best_successful_run():
    ev = _evaluator()
    assert ev.best_fit() is None
    ev.records += [RunRecord(np.array([0.1]), np.array([16.0, 4.0]), -3.0, False),
                   RunRecord(np.array([0.2]), np.array([11.0, 1.0]), -1.0, False),
                   RunRecord(np.array([0.3]), np.array([np.nan, np.nan]), 0.0, True, "failed")]
    fit = ev.best_fit()
    assert fit["x"] == {"mu": 0.2} and fit["z"] == -1.0 and fit["n_runs"] == 2
    assert [o["standardised_residual"] for o in fit["observations"]] == pytest.approx([0.5, -3.0])
    assert [o["sigma"] for o in fit["observations"]] == [2.0, 1.0]


def test_best_fit_uses_the_marginal_sd_of_a_full_covariance():
    cov = np.array([[4.0, 1.0], [1.0, 9.0]])
    ev = _evaluator(covariance=cov)
    ev.records.append(RunRecord(np.array([0.2]), np.array([14.0, 7.0]), -2.0, False))
    fit = ev.best_fit()
    assert [o["sigma"] for o in fit["observations"]] == pytest.approx([2.0, 3.0])
    assert [o["standardised_residual"] for o in fit["observations"]] == pytest.approx([2.0, 1.0])
