"""The landslide evaluator: parameter points -> one batched solver call -> observables -> z.

This is where the data flow closes: terrain + release + physics -> solver -> SimulationResult ->
observe -> bayes. ``LandslideEvaluator(x)`` takes an (n, p) batch of parameter points (in the units
of the prior, names = prior names = :class:`torchslide.physics.Params` fields), runs the solver
once per chunk of at most ``max_batch`` members, applies the observation operators and returns

    z = ln L(x | d) + ln pi(x)                     (paper Eq. 10, with Eq. 6-7 for L)

as a :class:`torchslide.bayes.EvaluationResult`. A member whose run failed or whose observables are
not finite is flagged with its reason, never turned into a number. Every evaluated point and its
predicted observables are kept in ``records`` (used by sweeps and the diagnosis).

Observations are scalar (:class:`torchslide.observe.Observation`, a block of one value) or vector-valued
(:class:`torchslide.observe_series.SeriesObservation`: a gauge series or a map, a block of m values):
predictions are the flattened (B, k) values (k = sum of the block sizes), against the data vector d (k,)
with the effective standard deviations (k,) (sigma sqrt(f) for correlated maps and series).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from .bayes import EvaluationResult, GaussianLikelihood, Prior
from .observe import Observation
from .observe_series import SeriesObservation
from .physics import Params, check_range
from .result import SimulationResult
from .terrain.grid import DEM


@dataclass
class RunRecord:
    """One evaluated parameter point: x (p,), predicted observables (k,), z, failure reason ('' if fine),
    and where the observations map a footprint the run's figures against it (torchslide.survey.run_figures:
    {observation name: {footprint_jaccard, share_of_reached_unmapped, runout_m, ...}}, else None)."""

    x: np.ndarray
    predictions: np.ndarray
    z: float
    failed: bool
    reason: str = ""
    figures: dict | None = None


def save_records(records: list, path) -> None:
    """Write run records to ``path`` (.npz) atomically, so that a resumed calibration knows every run's
    predictions, not only those of its own invocation."""
    import json

    from .files import atomic_path

    with atomic_path(path) as tmp:
        np.savez(tmp, x=np.array([r.x for r in records]), predictions=np.array([r.predictions for r in records]),
                 z=np.array([r.z for r in records]), failed=np.array([r.failed for r in records]),
                 reasons=np.array([r.reason for r in records]),
                 figures=np.array([json.dumps(r.figures) for r in records]))


def load_records(path) -> list:
    """The run records :func:`save_records` wrote (FileStateError when the file is unreadable)."""
    import json

    from .files import FileStateError

    try:
        with np.load(path) as f:
            figs = [json.loads(str(v)) for v in f["figures"]] if "figures" in f.files else [None] * len(f["z"])
            return [RunRecord(x.copy(), p.copy(), float(z), bool(b), str(r), g)
                    for x, p, z, b, r, g in zip(f["x"], f["predictions"], f["z"], f["failed"], f["reasons"], figs)]
    except Exception as e:  # noqa: BLE001 - numpy raises several kinds for a truncated file
        raise FileStateError(f"run records {path} are corrupt or truncated ({type(e).__name__}); delete the "
                             "output folder to start again") from None


def unique_records(records: list) -> list:
    """The records with each parameter point once (the first), in run order: a batch evaluated again after
    an interruption repeats records that were already saved."""
    seen, out = set(), []
    for r in records:
        key = tuple(np.round(np.asarray(r.x, dtype=float), 12))
        if key not in seen:
            seen.add(key)
            out.append(r)
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
class LandslideEvaluator:
    """Evaluate z = ln[L(x|d) pi(x)] for batches of parameter points with the batched solver.

    Attributes:
        dem, release: terrain and release thickness (ny, nx) m, measured as ``thickness`` says.
        observations: the recorded data; each validated against the DEM at construction.
        prior: prior over the calibrated parameters (names must be Params fields).
        fixed: values of the other Params fields (e.g. {"xi": 1000.0} when only mu is calibrated).
        t_end: simulated time limit, s.
        gauges: (name, x, y) gauges the observation kinds need.
        erodible_depth, mu_scale: optional (ny, nx) rasters passed to the solver.
        solver_config: torchslide.solver.SolverConfig or None.
        dtype, device: solver precision and device.
        max_batch: most members per solver call.
        covariance: optional (k, k) full residual covariance (else diagonal sigma, Eq. 7).
        solver_progress: show each solver call's simulated time as a progress bar.
        records_file: where every call's run records are saved (save_records), or None.
        thickness: convention of the release and erodible depths, "normal" (to the slope) or "vertical".
        executor: where the chunks of max_batch members run (torchslide.executor; None: here, one after
            another). The evaluator is sent to workers without its records, executor and progress bar.
        discrepancy: "learnt" (the model's own error, one per observation, learnt with the parameters:
            torchslide.discrepancy) or "none" (the stated errors only).
        discrepancy_factors: {map or series name: F / f}, how much farther its residual is correlated
            than its stated errors (``learn_discrepancy``); None: as stated.
    """

    dem: DEM
    release: np.ndarray
    observations: Sequence[Observation]
    prior: Prior
    fixed: dict = field(default_factory=dict)
    t_end: float = 600.0
    gauges: Sequence[tuple] = ()
    erodible_depth: np.ndarray | None = None
    mu_scale: np.ndarray | None = None
    solver_config: object = None
    dtype: torch.dtype = torch.float64
    device: str = "cpu"
    max_batch: int = 32
    covariance: object = None
    records: list = field(default_factory=list, repr=False)
    solver_seconds: float = 0.0
    solver_progress: bool = False
    records_file: object = None
    thickness: str = "normal"
    executor: object = field(default=None, repr=False)
    discrepancy: str = "learnt"
    discrepancy_factors: dict | None = None

    def __getstate__(self) -> dict:
        """What a worker needs to run chunks: everything but the run records, the executor and the progress bar."""
        state = dict(self.__dict__)
        state.update(records=[], records_file=None, executor=None, solver_progress=False, solver_seconds=0.0)
        return state

    def __post_init__(self) -> None:
        if not self.observations:
            raise ValueError("at least one observation is needed to calibrate")
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
        self.check_parameters()
        if self.max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {self.max_batch}")
        self.blocks: list[Block] = []
        d, s, s_raw = [], [], []
        for o in self.observations:
            start = sum(b.stop - b.start for b in self.blocks)
            if isinstance(o, SeriesObservation):
                d.append(np.asarray(o.values, dtype=np.float64))
                s.append(o.sigma_eff())
                s_raw.append(o.sigma_vector())
            else:
                d.append(np.array([float(o.value)]))
                s.append(np.array([float(o.sigma)]))
                s_raw.append(np.array([float(o.sigma)]))
            self.blocks.append(Block(str(o.name), o.kind, start, start + d[-1].size, o))
        self.data = np.concatenate(d)
        self.data_recorded = self.data
        self.sigma = np.concatenate(s)          # effective (what the likelihood uses)
        self.sigma_raw = np.concatenate(s_raw)  # per-value measurement sigma
        values = torch.as_tensor(self.data)
        if self.covariance is not None:
            self.likelihood = self.with_discrepancy(GaussianLikelihood(values, covariance=self.covariance))
        else:
            self.likelihood = self.with_discrepancy(GaussianLikelihood(values, sigma=torch.as_tensor(self.sigma)))

    def with_discrepancy(self, gaussian: GaussianLikelihood):
        """The likelihood of the stated errors ``gaussian`` with this evaluator's model of the model's own error
        (``discrepancy``: torchslide.discrepancy over the observation blocks, or the Gaussian itself)."""
        from .discrepancy import MODELS, DiscrepancyLikelihood, groups_of_blocks

        if self.discrepancy not in MODELS:
            raise ValueError(f"discrepancy must be one of {MODELS}, got {self.discrepancy!r}")
        if self.discrepancy == "none":
            return gaussian
        return DiscrepancyLikelihood(gaussian, groups_of_blocks(self.blocks, lambda b: b.obs.n_eff,
                                                                self.discrepancy_factors))

    def learn_discrepancy(self, x_pilot) -> dict:
        """Learn how far each map's and series' discrepancy is correlated, from pilot runs (the first step of
        a calibration: its initial design): the pilot points (n, p) are evaluated (or taken from the
        records), and for the best of them (largest z) each vector observation's standardised residual
        gives its correlation factor F (torchslide.discrepancy.correlation_factor, over the values where the
        discrepancy's weights put it: flow recorded or simulated); the likelihood then
        divides that observation's misfit and effective count by max(1, F / f) (f: its stated errors'),
        and every record's z is scored again. Returns {name: factor} (also ``discrepancy_factors``)."""
        if self.discrepancy != "learnt":
            return {}
        x_pilot = np.atleast_2d(np.asarray(x_pilot, dtype=np.float64))
        self.evaluate(x_pilot)
        keys = {tuple(np.round(x, 12)) for x in x_pilot}
        pilot = [r for r in self.records if tuple(np.round(r.x, 12)) in keys and not r.failed and np.isfinite(r.z)]
        if not pilot:
            return {}
        return self.learn_discrepancy_from(max(pilot, key=lambda r: r.z).predictions)

    def learn_discrepancy_from(self, predictions) -> dict:
        """``learn_discrepancy``'s factors from one run's predictions (k,) (the best pilot run's, or a fitted
        mode's), set in the likelihood; {name: factor}."""
        from .discrepancy import correlation_factor

        factors = {}
        for b in self.blocks:
            if not b.is_vector:
                continue
            y, d = np.asarray(predictions)[b.slice], self.data[b.slice]
            res = (y - d) / self.sigma_raw[b.slice]
            # where the discrepancy lives (its weights, torchslide.discrepancy): the values with flow recorded or
            # simulated, at least a tenth of the observation's mean square
            m2 = (0.5 * (np.abs(y) + np.abs(d))) ** 2
            res = np.where(m2 >= 0.1 * m2.mean(), res, np.nan) if m2.mean() > 0 else res
            F = correlation_factor(b.obs.to_grid(res) if b.obs.is_map else res)
            factors[b.name] = float(max(1.0, F / b.obs.factor()))
        self.set_discrepancy_factors(factors)
        return factors

    def set_discrepancy_factors(self, factors: dict | None) -> None:
        """Use ``factors`` ({name: F / f}, learn_discrepancy's) in the likelihood and score every record again."""
        self.discrepancy_factors = dict(factors) if factors else None
        self.likelihood = self.with_discrepancy(getattr(self.likelihood, "gaussian", self.likelihood))
        ok = [r for r in self.records if not r.failed]
        if ok:
            z = (self.likelihood.log_likelihood(torch.as_tensor(np.stack([r.predictions for r in ok])))
                 + self.prior.log_prob(torch.as_tensor(np.stack([r.x for r in ok]))))
            for r, zi in zip(ok, z.tolist()):
                r.z = float(zi)

    @property
    def k(self) -> int:
        """Number of recorded values (the length of the data vector)."""
        return int(self.data.size)

    def block(self, name: str) -> Block:
        for b in self.blocks:
            if b.name == name:
                return b
        raise KeyError(name)

    def check_parameters(self) -> None:
        """Calibrated and fixed names must be Params fields, disjoint, and give mu."""
        known = set(Params.names())
        for n in list(self.prior.names) + list(self.fixed):
            if n not in known:
                raise ValueError(f"parameter {n!r} is not a model parameter; known: {sorted(known)}")
        both = set(self.prior.names) & set(self.fixed)
        if both:
            raise ValueError(f"parameter(s) {sorted(both)} are both calibrated and fixed")
        for n, c in self.prior.components.items():     # a prior reaching e.g. mu <= 0: refused before any run
            check_range(n, c.low, c.high)
        if "mu" not in self.prior.names and "mu" not in self.fixed:
            raise ValueError("mu must be calibrated (in the prior) or fixed")

    @property
    def names(self) -> list[str]:
        return list(self.prior.names)

    @property
    def observation_names(self) -> list[str]:
        """(k,) labels of the data vector: an observation's name, or its name and element for a vector one."""
        return [lab for o in self.observations
                for lab in (o.labels() if isinstance(o, SeriesObservation) else [str(o.name)])]

    def params(self, x: torch.Tensor) -> Params:
        """Params for the (n, p) points x (calibrated names from x, the rest from ``fixed``)."""
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1, len(self.names))
        values = {n: x[:, i] for i, n in enumerate(self.names)}
        values.update(self.fixed)
        return Params.make(B=x.shape[0], dtype=self.dtype, device=self.device, **values)

    def simulate(self, x: torch.Tensor) -> SimulationResult:
        """Run the solver once for all n points (n <= max_batch is the caller's business)."""
        return self.simulate_params(self.params(x))

    def simulate_params(self, p: Params) -> SimulationResult:
        """One solver call of the members ``p`` on this evaluator's terrain and settings."""
        from .solver import simulate  # imported here: bayes-level modules stay importable without it

        t0 = time.perf_counter()
        res = simulate(self.dem, self.release, p, t_end=self.t_end, gauges=list(self.gauges) or None,
                       config=self.solver_config, erodible_depth=self.erodible_depth, mu_scale=self.mu_scale,
                       dtype=self.dtype, device=self.device, progress=self.solver_progress, thickness=self.thickness)
        self.solver_seconds += time.perf_counter() - t0
        return res

    def value_chunks(self, values: dict) -> list[dict]:
        """Explicit Params values {name: scalar or (n,) array} (+ fixed) as chunks of max_batch members."""
        n = max(np.size(v) for v in values.values())
        allv = {**self.fixed, **values}
        return [{k: (np.asarray(v, dtype=np.float64).reshape(-1)[s:s + self.max_batch] if np.size(v) > 1 else v)
                 for k, v in allv.items()} for s in range(0, n, self.max_batch)]

    def map_chunks(self, fn, chunks: list, done=None) -> list:
        """[fn(chunk)] on the executor (here, one after another, when there is none); each result's last
        item is the chunk's solver seconds, which a worker's runs add to ``solver_seconds`` here.
        ``done``: an optional callable(i, result) for each chunk in order, as soon as its result is here."""
        done = done or (lambda i, r: None)
        if self.executor is None:
            out = []
            for i, c in enumerate(chunks):
                out.append(fn(c))
                done(i, out[-1])
            return out
        out = self.executor.map(fn, chunks, progress=self.solver_progress)
        self.solver_seconds += sum(o[-1] for o in out)
        for i, o in enumerate(out):
            done(i, o)
        return out

    def values_chunk(self, values: dict) -> tuple:
        """One chunk of ``value_chunks``: (predictions (n, k), failed (n,), reasons, SimulationResult, seconds)."""
        t0 = time.perf_counter()
        nb = max(np.size(v) for v in values.values())
        res = self.simulate_params(Params.make(B=nb, dtype=self.dtype, device=self.device, **values))
        preds, failed, why = self.predict(res)
        return preds, failed, why, res, time.perf_counter() - t0

    def simulate_values(self, values: dict):
        """SimulationResults of explicit Params values {name: (n,) array} (+ fixed), one per chunk of
        max_batch members (in this process)."""
        for v in self.value_chunks(values):
            yield self.values_chunk(v)[3]

    def _predictions_chunk(self, values: dict) -> tuple:
        """One chunk's (predictions (n, k), failed (n,), reasons, figures (n dicts or Nones), seconds)."""
        preds, failed, why, res, sec = self.values_chunk(values)
        return preds, failed, why, self.survey_figures(res), sec

    @property
    def reach_threshold(self) -> float:
        """h_max above which a cell counts as reached in the survey's figures: the first threshold of a
        footprint, impact map, impact area or run-out observation (0.5 m without one)."""
        from .observe import DEFAULT_THRESHOLD

        kinds = ("footprint", "impact_map", "impact_area", "runout_length")
        return next((float(o.threshold) for o in self.observations if o.kind in kinds), DEFAULT_THRESHOLD)

    def survey_figures(self, result: SimulationResult) -> list:
        """Per member of ``result``, its figures against the mapped footprints among the observations
        (torchslide.survey.run_figures), or None for each member when no observation maps one."""
        from .survey import FOOTPRINT_KINDS, run_figures

        if not any(getattr(o, "kind", None) in FOOTPRINT_KINDS for o in self.observations):
            return [None] * result.batch_size
        h = result.h_max.detach().cpu().double().numpy()
        dz = None if result.elevation_change is None else result.elevation_change.detach().cpu().double().numpy()
        return [run_figures(h[b], None if dz is None else dz[b], self.observations, self.dem.z, self.release,
                            self.dem.cellsize, self.reach_threshold) for b in range(result.batch_size)]

    def maps_chunk(self, values: dict) -> tuple:
        """One chunk of ``value_chunks`` for maps: (predictions (n, k), failed (n,), reasons, {"h_max", "v_max",
        "h_final" and, from a solver run, "elevation_change": (n, ny, nx) float32 arrays}, map cell area (ny, nx)
        or scalar, seconds)."""
        preds, failed, why, res, sec = self.values_chunk(values)
        maps = {k: getattr(res, k).detach().cpu().float().numpy() for k in ("h_max", "v_max", "h_final", "elevation_change")
                if getattr(res, k, None) is not None}
        return preds, failed, why, maps, res.map_cell_area, sec

    def run_values(self, values: dict) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (n, k) and failed (n,) for explicit Params values {name: (n,) array} (+ fixed),
        in chunks of max_batch members on the executor (screening uses this for one batch of perturbed
        parameter sets)."""
        out = self.map_chunks(self._predictions_chunk, self.value_chunks(values))
        return np.concatenate([o[0].numpy() for o in out]), np.concatenate([o[1].numpy() for o in out])

    def predict(self, result: SimulationResult) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
        """Observables (B, k) float64 of a result, a failed mask (B,) and reasons."""
        B = result.batch_size
        preds = torch.cat([o.predict(result).to(torch.float64).cpu().reshape(B, -1) for o in self.observations], dim=1)
        failed = torch.zeros(B, dtype=torch.bool) if result.failed is None else result.failed.cpu().clone()
        reasons = [(result.failure_reason[b] or "") if result.failure_reason else "" for b in range(B)]
        finite = torch.isfinite(preds)
        for b in range(B):
            if failed[b] and not reasons[b]:
                reasons[b] = "solver reported failure"
            if not bool(finite[b].all()) and not failed[b]:
                names = self.observation_names
                bad = [names[k] for k in torch.nonzero(~finite[b]).flatten().tolist()]
                failed[b] = True
                reasons[b] = f"non-finite observable(s) {bad[:5]}" + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        return preds, failed, reasons

    def evaluate(self, x: torch.Tensor) -> tuple[EvaluationResult, torch.Tensor]:
        """(EvaluationResult, predictions (n, k)) for (n, p) points, in chunks of max_batch on the executor;
        points that the records already hold (a pilot's, a resumed run's) are not run again."""
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1, len(self.names))
        held = {tuple(np.round(r.x, 12)): r for r in self.records}
        known = [held.get(tuple(np.round(xi, 12))) for xi in x.numpy()]
        new = [i for i, r in enumerate(known) if r is None]
        if new:
            xn = x[new]
            out = self.map_chunks(self._predictions_chunk,
                                  self.value_chunks({n: xn[:, i].numpy() for i, n in enumerate(self.names)}))
            fresh = zip(torch.cat([o[0] for o in out]), torch.cat([o[1] for o in out]),
                        [r for o in out for r in o[2]], [f for o in out for f in o[3]])
            for i, (p, f, why, fig) in zip(new, fresh):
                known[i] = RunRecord(x[i].numpy().copy(), p.numpy().copy(), math.nan, bool(f), why, fig)
        preds = torch.as_tensor(np.stack([r.predictions for r in known]))
        out = EvaluationResult(self.likelihood.log_likelihood(preds) + self.prior.log_prob(x),
                               torch.as_tensor([r.failed for r in known]), [r.reason for r in known])
        for i in new:
            known[i].z = float(out.z[i])
            self.records.append(known[i])
        if self.records_file is not None:
            save_records(self.records, self.records_file)
        return out, preds

    def __call__(self, x: torch.Tensor) -> EvaluationResult:
        return self.evaluate(x)[0]

    def observation_sd(self) -> np.ndarray:
        """(k,) the likelihood's marginal sd of each observation (sigma, or the square root of the full
        covariance's diagonal)."""
        lik = self.likelihood
        return (lik.sigma if lik.chol is None else torch.sqrt(torch.diagonal(lik.chol @ lik.chol.T))).numpy()

    def best_fit(self) -> dict | None:
        """How well the best run seen (largest z among the ``records`` that did not fail) reproduces each
        observation: {"x": {name: value}, "z", "n_runs": records considered, "observations": [{name, kind,
        value, sigma, predicted, standardised_residual = (predicted - value) / sigma}]} (sigma the
        likelihood's marginal sd, also with a full covariance). None when no run succeeded.

        A residual of several sigma on the best run means that no parameter set tried reproduces that
        datum (a wrong value, unit or location, a point the flow never reaches, or physics the model
        lacks): the posterior then follows the other data or the prior, not this observation."""
        ok = [r for r in self.records if not r.failed and np.all(np.isfinite(r.predictions))]
        if not ok:
            return None
        best = max(ok, key=lambda r: r.z)
        sd = self.observation_sd()
        obs = []
        for b in self.blocks:
            k = b.slice
            r = (best.predictions[k] - self.data[k]) / sd[k]
            if b.is_vector:     # a map or series: how its values are missed as a whole
                obs.append({"name": b.name, "kind": b.kind, "n": int(r.size), "sigma_median": float(np.median(sd[k])),
                            "mean_residual": float(np.mean(best.predictions[k] - self.data[k])),
                            "rms_standardised_residual": float(np.sqrt(np.mean(r * r)))})
            else:
                obs.append({"name": b.name, "kind": b.kind, "value": float(self.data[k][0]), "sigma": float(sd[k][0]),
                            "predicted": float(best.predictions[k][0]), "standardised_residual": float(r[0])})
        return {"x": {n: float(v) for n, v in zip(self.names, best.x)}, "z": float(best.z), "n_runs": len(ok),
                "observations": obs}
