"""DiagnosisEvaluator: a LandslideEvaluator (scalar and vector observations, flattened into blocks of
the data vector) with the grid's approximation error in its likelihood, a finer terrain for it, and
copies over other priors (the candidates' enlarged spaces)."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..bayes import GaussianLikelihood
from ..evaluator import Block, LandslideEvaluator  # noqa: F401  (Block: the diagnosis' name for a data slice)
from ..physics import default_value


def stack_values(parts: list[tuple[int, dict]]) -> dict:
    """One batch of Params values from several groups of members: ``parts`` [(n_i, {name: scalar or
    (n_i,) array})] -> {name: (sum n_i,) array}; a name that a group does not give takes its default
    there (physics.default_value: the term off), so groups with different terms share one solver call."""
    keys = sorted({k for _, v in parts for k in v})
    out = {}
    for k in keys:
        cols = [np.broadcast_to(np.asarray(v[k] if k in v else default_value(k), dtype=np.float64).reshape(-1), (n,))
                for n, v in parts]
        out[k] = np.concatenate(cols)
    return out


@dataclass
class DiagnosisEvaluator(LandslideEvaluator):
    """LandslideEvaluator over scalar and vector observations (see the module doc).

    ``model_error``: an optional torchslide.diagnose.model_error.ModelError (approximation error of
    the grid). With it the likelihood is N(d - eps_bar | y, diag(sigma_eff^2) + Gamma_eps) (full
    covariance); ``data`` is then d - eps_bar and ``sigma`` / ``sigma_raw`` include Gamma_eps's
    diagonal (what the per-value checks, localisation and WAIC use); ``data_recorded`` is d.

    ``fine_terrain``: an optional torchslide.diagnose.model_error.FineTerrain, the terrain on finer cells
    for the model error's finer runs (validated here: an exact refinement of ``dem``).

    ``finer_grid``: True runs every simulation on the fine terrain (model_error.fine_simulate), seen on
    ``dem``'s cells, so the same data are compared with the finer grid's model (pipeline's finer-grid
    stage); it needs ``fine_terrain``.
    """

    model_error: object = None
    fine_terrain: object = None
    finer_grid: bool = False

    def __post_init__(self) -> None:
        if not self.observations:
            raise ValueError("at least one observation is needed")
        if self.fine_terrain is not None:
            self.fine_terrain.factor_for(self.dem)
        elif self.finer_grid:
            raise ValueError("finer_grid needs a fine_terrain (the terrain on finer cells)")
        names = [str(o.name) for o in self.observations]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"observations have duplicate names {dup}")
        super().__post_init__()
        me = self.model_error
        if me is None:
            return
        if me.samples.shape[1] != self.k:
            raise ValueError(f"model_error has {me.samples.shape[1]} values per sample, the observations {self.k}")
        gamma = me.covariance
        self.data = self.data_recorded - me.mean
        cov = np.diag(self.sigma**2) + gamma
        self.sigma = np.sqrt(np.diag(cov))
        self.sigma_raw = np.sqrt(self.sigma_raw**2 + np.diag(gamma))
        self.likelihood = self.with_discrepancy(GaussianLikelihood(torch.as_tensor(self.data),
                                                                   covariance=torch.as_tensor(cov)))

    def simulate_params(self, p):
        """LandslideEvaluator.simulate_params, on the fine terrain when ``finer_grid`` (class doc)."""
        if not self.finer_grid:
            return super().simulate_params(p)
        from .model_error import fine_simulate

        t0 = time.perf_counter()
        res = fine_simulate(self, p, self.fine_terrain.factor_for(self.dem))
        self.solver_seconds += time.perf_counter() - t0
        return res

    def _copy(self, **changes) -> "DiagnosisEvaluator":
        """A new evaluator with the same inputs except ``changes`` (own, empty run records)."""
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
              if f.init and f.name not in ("records", "solver_seconds")}
        kw.update(changes)
        return DiagnosisEvaluator(**kw)

    def with_prior(self, prior, fixed: dict | None = None) -> "DiagnosisEvaluator":
        """A copy with another prior (e.g. the enlarged space of a candidate) and extra fixed values."""
        f = {k: v for k, v in dict(self.fixed).items() if k not in prior.names}
        f.update(fixed or {})
        return self._copy(prior=prior, fixed=f)

    def with_model_error(self, model_error) -> "DiagnosisEvaluator":
        """A copy whose likelihood includes ``model_error`` (see the class doc; None: without)."""
        return self._copy(model_error=model_error, fixed=dict(self.fixed))

    def misfit(self, preds: np.ndarray) -> float:
        """Sum of squared effective-standardised residuals of one prediction vector (k,)."""
        r = (self.data - np.asarray(preds)) / self.sigma
        return float(np.sum(r * r))
