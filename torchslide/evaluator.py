"""The landslide evaluator: parameter points -> one batched solver call -> observables -> z.

This is where the data flow closes: terrain + release + physics -> solver -> SimulationResult ->
observe -> bayes. ``LandslideEvaluator(x)`` takes an (n, p) batch of parameter points (in the units
of the prior, names = prior names = :class:`torchslide.physics.Params` fields), runs the solver
once per chunk of at most ``max_batch`` members, applies the observation operators and returns

    z = ln L(x | d) + ln pi(x)                     (paper Eq. 10, with Eq. 6-7 for L)

as a :class:`torchslide.bayes.EvaluationResult`. A member whose run failed or whose observables are
not finite is flagged with its reason, never turned into a number. Every evaluated point and its
predicted observables are kept in ``records`` (used by sweeps and the diagnosis).
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
from .physics import Params, check_range
from .result import SimulationResult
from .terrain.grid import DEM


@dataclass
class RunRecord:
    """One evaluated parameter point: x (p,), predicted observables (k,), z, failure reason ('' if fine)."""

    x: np.ndarray
    predictions: np.ndarray
    z: float
    failed: bool
    reason: str = ""


def save_records(records: list, path) -> None:
    """Write run records to ``path`` (.npz) atomically, so that a resumed calibration knows every run's
    predictions, not only those of its own invocation."""
    from .files import atomic_path

    with atomic_path(path) as tmp:
        np.savez(tmp, x=np.array([r.x for r in records]), predictions=np.array([r.predictions for r in records]),
                 z=np.array([r.z for r in records]), failed=np.array([r.failed for r in records]),
                 reasons=np.array([r.reason for r in records]))


def load_records(path) -> list:
    """The run records :func:`save_records` wrote (FileStateError when the file is unreadable)."""
    from .files import FileStateError

    try:
        with np.load(path) as f:
            return [RunRecord(x.copy(), p.copy(), float(z), bool(b), str(r))
                    for x, p, z, b, r in zip(f["x"], f["predictions"], f["z"], f["failed"], f["reasons"])]
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

    def __post_init__(self) -> None:
        if not self.observations:
            raise ValueError("at least one observation is needed to calibrate")
        for o in self.observations:
            o.validate(self.dem)
        self.check_parameters()
        if self.max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {self.max_batch}")
        values = torch.tensor([float(o.value) for o in self.observations], dtype=torch.float64)
        if self.covariance is not None:
            self.likelihood = GaussianLikelihood(values, covariance=self.covariance)
        else:
            sigma = torch.tensor([float(o.sigma) for o in self.observations], dtype=torch.float64)
            self.likelihood = GaussianLikelihood(values, sigma=sigma)

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
        return [str(o.name) for o in self.observations]

    def params(self, x: torch.Tensor) -> Params:
        """Params for the (n, p) points x (calibrated names from x, the rest from ``fixed``)."""
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1, len(self.names))
        values = {n: x[:, i] for i, n in enumerate(self.names)}
        values.update(self.fixed)
        return Params.make(B=x.shape[0], dtype=self.dtype, device=self.device, **values)

    def simulate(self, x: torch.Tensor) -> SimulationResult:
        """Run the solver once for all n points (n <= max_batch is the caller's business)."""
        from .solver import simulate  # imported here: bayes-level modules stay importable without it

        t0 = time.perf_counter()
        res = simulate(self.dem, self.release, self.params(x), t_end=self.t_end, gauges=list(self.gauges) or None,
                       config=self.solver_config, erodible_depth=self.erodible_depth, mu_scale=self.mu_scale,
                       dtype=self.dtype, device=self.device, progress=self.solver_progress, thickness=self.thickness)
        self.solver_seconds += time.perf_counter() - t0
        return res

    def simulate_values(self, values: dict):
        """SimulationResults of explicit Params values {name: (n,) array} (+ fixed), one per chunk of
        max_batch members (a generator)."""
        from .solver import simulate
        n = max(np.size(v) for v in values.values())
        allv = {k: v for k, v in self.fixed.items()}
        allv.update(values)
        for s in range(0, n, self.max_batch):
            sub = {k: (np.asarray(v, dtype=np.float64).reshape(-1)[s:s + self.max_batch] if np.size(v) > 1 else v)
                   for k, v in allv.items()}
            nb = min(self.max_batch, n - s)
            p = Params.make(B=nb, dtype=self.dtype, device=self.device, **sub)
            t0 = time.perf_counter()
            res = simulate(self.dem, self.release, p, t_end=self.t_end, gauges=list(self.gauges) or None,
                           config=self.solver_config, erodible_depth=self.erodible_depth, mu_scale=self.mu_scale,
                           dtype=self.dtype, device=self.device, thickness=self.thickness)
            self.solver_seconds += time.perf_counter() - t0
            yield res

    def run_values(self, values: dict) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (n, k) and failed (n,) for explicit Params values {name: (n,) array} (+ fixed),
        in chunks of max_batch members (screening uses this for one batch of perturbed parameter sets)."""
        out, fails = [], []
        for res in self.simulate_values(values):
            preds, failed, _ = self.predict(res)
            out.append(preds.numpy())
            fails.append(failed.numpy())
        return np.concatenate(out), np.concatenate(fails)

    def predict(self, result: SimulationResult) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
        """Observables (B, k) float64 of a result, a failed mask (B,) and reasons."""
        B = result.batch_size
        preds = torch.stack([o.predict(result).to(torch.float64).cpu() for o in self.observations], dim=1)
        failed = torch.zeros(B, dtype=torch.bool) if result.failed is None else result.failed.cpu().clone()
        reasons = [(result.failure_reason[b] or "") if result.failure_reason else "" for b in range(B)]
        for b in range(B):
            if failed[b] and not reasons[b]:
                reasons[b] = "solver reported failure"
            bad = [self.observation_names[k] for k in range(preds.shape[1]) if not math.isfinite(float(preds[b, k]))]
            if bad and not failed[b]:
                failed[b] = True
                reasons[b] = f"non-finite observable(s) {bad}"
        return preds, failed, reasons

    def evaluate(self, x: torch.Tensor) -> tuple[EvaluationResult, torch.Tensor]:
        """(EvaluationResult, predictions (n, k)) for (n, p) points, in chunks of max_batch."""
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1, len(self.names))
        zs, fails, reasons, preds_all = [], [], [], []
        for s in range(0, x.shape[0], self.max_batch):
            xb = x[s:s + self.max_batch]
            preds, failed, why = self.predict(self.simulate(xb))
            z = self.likelihood.log_likelihood(preds) + self.prior.log_prob(xb)
            zs.append(z)
            fails.append(failed)
            reasons += why
            preds_all.append(preds)
        preds = torch.cat(preds_all)
        out = EvaluationResult(torch.cat(zs), torch.cat(fails), reasons)
        for i in range(x.shape[0]):
            self.records.append(RunRecord(x[i].numpy().copy(), preds[i].numpy().copy(), float(out.z[i]),
                                          bool(out.failed[i]), out.reasons[i]))
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
        obs = [{"name": str(o.name), "kind": o.kind, "value": float(o.value), "sigma": float(sd[k]),
                "predicted": float(best.predictions[k]),
                "standardised_residual": float((best.predictions[k] - float(o.value)) / sd[k])}
               for k, o in enumerate(self.observations)]
        return {"x": {n: float(v) for n, v in zip(self.names, best.x)}, "z": float(best.z), "n_runs": len(ok),
                "observations": obs}
