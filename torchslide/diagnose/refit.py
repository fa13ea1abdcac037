"""Refit a candidate in the enlarged parameter space (baseline parameters + its switch) with calibrate()."""
from __future__ import annotations

from ..bayes import Prior, Uniform
from ..calibration import calibrate
from .candidates import CANDIDATES


def candidate_prior(base_prior: Prior, candidate: str) -> Prior:
    """Baseline prior components plus Uniform(prior box) on the candidate's switch parameter."""
    cd = CANDIDATES[candidate]
    comps = dict(base_prior.components)
    comps[cd.param] = Uniform(float(cd.prior[0]), float(cd.prior[1]))
    return Prior(comps)


def calibrate_evaluator(evaluator, n_initial: int, n_total: int, batch_size: int = 8, seed: int = 0,
                        grid_size: int = 60, mcmc_steps: int = 1500, mcmc_chains: int = 4, **kw):
    """calibrate() on an evaluator's prior box with small, diagnosis-sized settings: the emulator's posterior
    (the diagnosis chooses its inference path itself)."""
    kw.setdefault("inference", "emulator")
    return calibrate(evaluator, evaluator.prior.bounds, n_initial=n_initial, n_total=n_total, batch_size=batch_size,
                     seed=seed, grid_size=grid_size, names=evaluator.prior.names, progress=False,
                     num_restarts=4, raw_samples=128, mcmc_steps=mcmc_steps, mcmc_chains=mcmc_chains, **kw)


def candidate_evaluator(evaluator, candidate: str):
    """The evaluator of the baseline + ``candidate`` model (enlarged prior, the candidate's fixed values)."""
    cd = CANDIDATES[candidate]
    return evaluator.with_prior(candidate_prior(evaluator.prior, candidate), fixed=dict(cd.fixed))


def refit(evaluator, candidate: str, n_initial: int, n_total: int, batch_size: int = 8, seed: int = 0,
          mcmc_steps: int = 1500, checkpoint=None):
    """(candidate evaluator, CalibrationResult) of the baseline + ``candidate`` model. With a
    ``checkpoint`` file the refit can later be continued to a larger n_total (calibrate_evaluator on the
    returned evaluator with the same checkpoint)."""
    ev = candidate_evaluator(evaluator, candidate)
    cal = calibrate_evaluator(ev, n_initial, n_total, batch_size=batch_size, seed=seed, mcmc_steps=mcmc_steps,
                              checkpoint=checkpoint)
    return ev, cal
