"""DiagnosisEvaluator: a LandslideEvaluator whose observations may be vector-valued.

Scalar :class:`torchslide.observe.Observation` s count as blocks of one value, each
:class:`torchslide.observe_series.SeriesObservation` as a block of m values. ``predict`` returns the
flattened (B, k) predictions (k = sum of block sizes), the data vector d (k,) and the effective
standard deviations (k,) (sigma sqrt(f) for correlated maps/series, see observe_series) feed the
ordinary diagonal :class:`torchslide.bayes.GaussianLikelihood`. Everything else (batching, records,
failure flags) is inherited unchanged, so ``calibrate(evaluator, ...)`` works as for scalar data.

Change proposed upstream (not made here): LandslideEvaluator could accept observations whose
``predict`` returns (B, m) and flatten them itself; this subclass is that change, kept local.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..bayes import GaussianLikelihood
from ..evaluator import LandslideEvaluator
from ..observe_series import SeriesObservation
from ..physics import default_value
from ..result import SimulationResult


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
class Block:
    """One observation's slice of the flat data vector."""

    name: str
    kind: str
    start: int
    stop: int
    obs: object

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)

    @property
    def is_vector(self) -> bool:
        return isinstance(self.obs, SeriesObservation)


@dataclass
class DiagnosisEvaluator(LandslideEvaluator):
    """LandslideEvaluator over scalar and vector observations (see the module doc).

    ``model_error``: an optional torchslide.diagnose.model_error.ModelError (approximation error of
    the grid). With it the likelihood is N(d - eps_bar | y, diag(sigma_eff^2) + Gamma_eps) (full
    covariance); ``data`` is then d - eps_bar and ``sigma`` / ``sigma_raw`` include Gamma_eps's
    diagonal (what the per-value checks, localisation and WAIC use); ``data_recorded`` is d.

    ``fine_terrain``: an optional torchslide.diagnose.model_error.FineTerrain, the terrain on finer cells
    for the model error's finer runs (validated here: an exact refinement of ``dem``).
    """

    model_error: object = None
    fine_terrain: object = None

    def __post_init__(self) -> None:
        if not self.observations:
            raise ValueError("at least one observation is needed")
        if self.fine_terrain is not None:
            self.fine_terrain.factor_for(self.dem)
        gauge_names = [g[0] for g in self.gauges]
        for o in self.observations:
            if isinstance(o, SeriesObservation):
                o.validate(self.dem, gauge_names)
                if o.kind == "gauge_series" and float(o.times[-1]) > self.t_end:
                    raise ValueError(f"observation {o.name!r}" + (f" ({o.source})" if o.source else "")
                                     + f": recorded until t = {float(o.times[-1]):g} s, after the simulated time "
                                     f"t_end = {self.t_end:g} s; raise t_end ([run] t_end) to cover the recording "
                                     f"(a run still stops early once the flow has stopped)")
            else:
                o.validate(self.dem)
        names = [str(o.name) for o in self.observations]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"observations have duplicate names {dup}")
        self.check_parameters()
        self.blocks: list[Block] = []
        d, s, s_raw = [], [], []
        k = 0
        for o in self.observations:
            if isinstance(o, SeriesObservation):
                m = o.m
                d.append(np.asarray(o.values, dtype=np.float64))
                s.append(o.sigma_eff())
                s_raw.append(o.sigma_vector())
            else:
                m = 1
                d.append(np.array([float(o.value)]))
                s.append(np.array([float(o.sigma)]))
                s_raw.append(np.array([float(o.sigma)]))
            self.blocks.append(Block(str(o.name), o.kind, k, k + m, o))
            k += m
        self.data = np.concatenate(d)
        self.data_recorded = self.data
        self.sigma = np.concatenate(s)          # effective (used by the likelihood)
        self.sigma_raw = np.concatenate(s_raw)  # per-value measurement sigma
        me = self.model_error
        if me is None:
            self.likelihood = GaussianLikelihood(torch.as_tensor(self.data), sigma=torch.as_tensor(self.sigma))
            return
        if me.samples.shape[1] != k:
            raise ValueError(f"model_error has {me.samples.shape[1]} values per sample, the observations {k}")
        gamma = me.covariance
        self.data = self.data_recorded - me.mean
        cov = np.diag(self.sigma**2) + gamma
        self.sigma = np.sqrt(np.diag(cov))
        self.sigma_raw = np.sqrt(self.sigma_raw**2 + np.diag(gamma))
        self.likelihood = GaussianLikelihood(torch.as_tensor(self.data), covariance=torch.as_tensor(cov))

    @property
    def k(self) -> int:
        return int(self.data.size)

    def block(self, name: str) -> Block:
        for b in self.blocks:
            if b.name == name:
                return b
        raise KeyError(name)

    def predict(self, result: SimulationResult):
        B = result.batch_size
        cols = []
        for o in self.observations:
            p = o.predict(result).to(torch.float64).cpu()
            cols.append(p.reshape(B, -1))
        preds = torch.cat(cols, dim=1)
        failed = torch.zeros(B, dtype=torch.bool) if result.failed is None else result.failed.cpu().clone()
        reasons = [(result.failure_reason[b] or "") if result.failure_reason else "" for b in range(B)]
        finite = torch.isfinite(preds).all(dim=1)
        for b in range(B):
            if failed[b] and not reasons[b]:
                reasons[b] = "solver reported failure"
            if not bool(finite[b]) and not failed[b]:
                failed[b] = True
                reasons[b] = "non-finite observable(s)"
        return preds, failed, reasons

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
