"""The active-learning loop of Algorithm 1 (Zhao & Kowalski style Bayesian active learning).

1. b0 initial points from a seeded maximin Latin hypercube, evaluated in one call;
2. per iteration: fit the GP emulator on the successful runs, estimate the posterior (grid, Eq. 15),
   record TV(p_i, p_{i-lag}) (Eq. 17), pick q points by maximising the acquisition (Eq. 16; kriging
   believer for q > 1), evaluate them in one call, checkpoint;
3. stop at n_total runs or when TV stays below ``tv_threshold`` for ``tv_patience`` iterations.

Reproducibility and resume: every random choice of iteration i is seeded from (seed, i), the GP fit is
warm-started from hyperparameters that are stored in the checkpoint, and the checkpoint is written
atomically (temporary file + os.replace) after every evaluated batch. A run that is interrupted (an
exception in the evaluator, a killed process) and resumed from its checkpoint therefore produces the
same points and result as an uninterrupted run with the same seed; finished runs are never repeated
or lost.

Failed runs (failed mask or non-finite z) are recorded with their reason and excluded from the GP.
So that the acquisition does not propose the same failing point again, the *acquisition* model is
conditioned on the failed points with the lowest training value (a pessimistic kriging believer);
the posterior estimate never sees them.

For p > 2 the loop tracks TV on a fixed Sobol point set (self-normalised weights exp(g_hat)) instead
of a full grid; the final posterior of p > 2 comes from MCMC (see calibrate.py).
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from scipy.stats import qmc

from acquisition import select_batch

from .bayes import EvaluationResult, FunctionEvaluator, check_bounds
from .emulator import LogPosteriorEmulator, cap_low_values, single_threaded
from .files import FileStateError, atomic_path
from .posterior import GridPosterior, grid_posterior, tv_distance

CHECKPOINT_VERSION = 1


def iteration_seed(seed: int, iteration: int) -> int:
    """Deterministic per-iteration seed from (seed, iteration)."""
    return int(np.random.SeedSequence([int(seed), int(iteration)]).generate_state(1)[0])


def maximin_lhs(n: int, dim: int, seed: int = 0, n_candidates: int = 100) -> np.ndarray:
    """Maximin Latin hypercube in [0, 1]^dim: the best of n_candidates seeded scipy
    ``qmc.LatinHypercube`` draws by the minimum pairwise distance. Returns (n, dim)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7919]))
    best, best_d = None, -1.0
    for _ in range(n_candidates):
        s = qmc.LatinHypercube(d=dim, seed=rng).random(n)
        if n < 2:
            return s
        diff = s[:, None, :] - s[None, :, :]
        dist = np.sqrt((diff**2).sum(-1))
        dmin = dist[np.triu_indices(n, 1)].min()
        if dmin > best_d:
            best, best_d = s, dmin
    return best


def initial_design(bounds, n: int, seed: int) -> torch.Tensor:
    """(n, p) the loop's initial design in parameter units: the seeded maximin LHS scaled to the box
    (2, p), point for point the runs ``ActiveLearner.initialise`` makes (a pilot may run them first)."""
    b = check_bounds(bounds)
    return b[0] + torch.from_numpy(maximin_lhs(n, b.shape[1], seed)).to(b) * (b[1] - b[0])


@dataclass
class ActiveConfig:
    """Settings of the loop (all stored in the checkpoint)."""

    n_initial: int = 40
    n_total: int = 120
    batch_size: int = 1
    seed: int = 0
    grid_size: int = 100
    acquisition: str = "entropy"
    tv_threshold: float | None = None
    tv_lag: int = 10  # TV(p_i, p_{i - tv_lag}) with i counted in runs
    tv_patience: int = 3
    clip_range: float | None = 1000.0
    num_restarts: int = 8
    raw_samples: int = 256
    image_every: int = 10  # runs between posterior images in TensorBoard
    n_tv_points: int = 8192  # Sobol points for TV when p > 2
    track_tv: bool = True  # estimate the posterior / TV every iteration (benchmarks switch it off)


@dataclass
class ActiveState:
    x: torch.Tensor  # (n, p) parameter units, all runs in order
    z: torch.Tensor  # (n,) nan where failed
    failed: torch.Tensor  # (n,) bool
    reasons: list
    is_initial: torch.Tensor  # (n,) bool
    iteration: int = 0
    tv_history: list = field(default_factory=list)  # (n_runs, TV)
    acq_history: list = field(default_factory=list)  # (n_runs, acquisition max)
    hyper_state: dict | None = None
    fit_start_state: dict | None = None  # the warm start of the latest fit (a finished run refits from it)
    density_history: dict = field(default_factory=dict)  # n_runs -> density (grid or Sobol weights)
    below_count: int = 0
    stopped_reason: str = ""
    fit_seconds: list = field(default_factory=list)
    acq_seconds: list = field(default_factory=list)

    @property
    def n_runs(self) -> int:
        return int(self.x.shape[0])


def _atomic_save(obj, path: Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


class ActiveLearner:
    """Algorithm 1. ``evaluator`` maps (n, p) parameter points to an EvaluationResult (or to z, or to
    (z, failed)); see torchslide.bayes."""

    def __init__(self, evaluator: Callable, bounds, config: ActiveConfig | None = None,
                 checkpoint: str | os.PathLike | None = None, log_dir: str | os.PathLike | None = None,
                 progress: bool = True, names=None):
        self.bounds = check_bounds(bounds, names)
        self.dim = self.bounds.shape[1]
        self.config = config or ActiveConfig()
        c = self.config
        if c.n_initial < 2 or c.n_total < c.n_initial or c.batch_size < 1:
            raise ValueError(f"need 2 <= n_initial <= n_total and batch_size >= 1, got {c}")
        self.evaluator = evaluator if isinstance(evaluator, FunctionEvaluator) else FunctionEvaluator(evaluator)
        self.checkpoint = Path(checkpoint) if checkpoint is not None else None
        self.log_dir = log_dir
        self.progress = progress
        self.emulator = LogPosteriorEmulator(self.bounds, clip_range=c.clip_range)
        self.state: ActiveState | None = None
        self.posterior: GridPosterior | None = None
        self._writer = None
        if self.dim > 2:
            sob = qmc.Sobol(d=self.dim, scramble=True, seed=int(c.seed)).random(c.n_tv_points)
            self._tv_points = self.emulator.from_unit(torch.from_numpy(sob))

    # --------------------------------------------------------------------------------------------
    def _save(self) -> None:
        if self.checkpoint is None:
            return
        s = self.state
        _atomic_save({"version": CHECKPOINT_VERSION, "config": asdict(self.config),
                      "bounds": self.bounds, "state": asdict(s)}, self.checkpoint)

    def _load(self) -> bool:
        if self.checkpoint is None or not self.checkpoint.exists():
            return False
        try:
            ck = torch.load(self.checkpoint, weights_only=False)
        except Exception as e:  # noqa: BLE001 - torch raises several kinds for a truncated or foreign file
            raise FileStateError(f"checkpoint {self.checkpoint} is corrupt or truncated ({type(e).__name__}); "
                                 "delete it to start the calibration again") from None
        if not isinstance(ck, dict) or ck.get("version") != CHECKPOINT_VERSION:
            raise FileStateError(f"checkpoint {self.checkpoint} is not a calibration checkpoint of this version; "
                                 "delete it to start again")
        saved = ck["config"]
        for key in ("n_initial", "batch_size", "seed", "acquisition", "clip_range", "grid_size"):
            if saved[key] != getattr(self.config, key):
                raise FileStateError(f"checkpoint {self.checkpoint} was made with {key} = {saved[key]!r}, not "
                                     f"{getattr(self.config, key)!r}: resume with the settings it was made with, "
                                     "or choose another output folder")
        if not torch.allclose(ck["bounds"], self.bounds):
            raise FileStateError(f"checkpoint {self.checkpoint} was made with another prior box "
                                 f"{ck['bounds'].tolist()}; resume with the prior it was made with")
        self.state = ActiveState(**ck["state"])
        return True

    def _evaluate(self, x: torch.Tensor) -> EvaluationResult:
        res = self.evaluator(x.clone())
        if res.z.numel() != x.shape[0]:
            raise ValueError(f"evaluator returned {res.z.numel()} values for {x.shape[0]} points")
        return res

    def _append(self, x: torch.Tensor, res: EvaluationResult, initial: bool) -> None:
        s = self.state
        s.x = torch.cat([s.x, x])
        s.z = torch.cat([s.z, res.z])
        s.failed = torch.cat([s.failed, res.failed])
        s.reasons = s.reasons + list(res.reasons)
        s.is_initial = torch.cat([s.is_initial, torch.full((x.shape[0],), initial)])

    # --------------------------------------------------------------------------------------------
    def _fit(self) -> None:
        s = self.state
        ok = ~s.failed
        if int(ok.sum()) < 2:
            raise RuntimeError(f"only {int(ok.sum())} successful runs; cannot fit the emulator "
                               f"(failures: {[r for r in s.reasons if r][:5]})")
        start = s.hyper_state
        self.emulator._hyper_state = start
        t0 = time.perf_counter()
        self.emulator.fit(s.x[ok], s.z[ok])
        s.fit_seconds.append(time.perf_counter() - t0)
        s.fit_start_state, s.hyper_state = start, self.emulator._hyper_state

    def _refit_final(self) -> None:
        """The emulator and posterior estimate of a finished run, as they ended: the final fit repeated from
        its own warm start on the same runs (single-threaded, so bitwise the same), nothing recorded."""
        s = self.state
        ok = ~s.failed
        self.emulator._hyper_state = s.fit_start_state
        self.emulator.fit(s.x[ok], s.z[ok])
        self._estimate()

    def _estimate(self):
        """Posterior estimate of the current emulator: grid density (p <= 2) or Sobol weights (p > 2)."""
        if self.dim <= 2:
            self.posterior = grid_posterior(self.emulator.mean, self.bounds, self.config.grid_size)
            return self.posterior.density, self.posterior.cell_volume
        m = self.emulator.mean(self._tv_points).numpy()
        w = np.exp(m - m.max())
        return w / w.sum(), 1.0

    def _record_tv(self, density: np.ndarray, cvol: float) -> float | None:
        s, c = self.state, self.config
        n = s.n_runs
        s.density_history[n] = density
        past = [k for k in s.density_history if k <= n - c.tv_lag]
        tv = None
        if past:
            ref = max(past)
            tv = tv_distance(density, s.density_history[ref], cvol)
            s.tv_history.append((n, tv))
            # keep only what a future lagged comparison can need
            for k in [k for k in s.density_history if k < ref]:
                del s.density_history[k]
        return tv

    def _acquire(self, q: int, it: int) -> tuple[torch.Tensor, torch.Tensor]:
        s, c = self.state, self.config
        model = self.emulator.model
        if bool(s.failed.any()):
            ok = ~s.failed
            y_low = float(cap_low_values(s.z[ok], c.clip_range).min())
            xf = self.emulator.to_unit(s.x[s.failed])
            with torch.no_grad():
                model.posterior(xf[:1])  # build prediction caches before conditioning
            model = model.condition_on_observations(X=xf, Y=torch.full((xf.shape[0], 1), y_low, dtype=xf.dtype))
        t0 = time.perf_counter()
        seed = iteration_seed(c.seed, it)
        torch.manual_seed(seed)
        with single_threaded():  # reproducible picks for a given seed, whatever the thread count
            u, vals = select_batch(model, q=q, acquisition=c.acquisition, num_restarts=c.num_restarts,
                                   raw_samples=c.raw_samples, seed=seed % (2**31), dim=self.dim)
        s.acq_seconds.append(time.perf_counter() - t0)
        return self.emulator.from_unit(u), vals

    # --------------------------------------------------------------------------------------------
    def _log(self, tv, new_z=None, acq_max=None, density=None) -> None:
        w = self._writer
        if w is None:
            return
        s = self.state
        n = s.n_runs
        if tv is not None:
            w.add_scalar("tv", tv, n)
        if new_z is not None:
            fin = new_z[torch.isfinite(new_z)]
            if fin.numel():
                w.add_scalar("z_new/max", float(fin.max()), n)
                w.add_histogram("z_new", fin.numpy(), n)
            w.add_scalar("failed_total", int(s.failed.sum()), n)
        if acq_max is not None:
            w.add_scalar("acquisition_max", float(acq_max), n)
        if self.emulator.model is not None:
            hp = self.emulator.hyperparameters()
            for i, l in enumerate(hp["lengthscale"]):
                w.add_scalar(f"gp/lengthscale_{i}", l, n)
            w.add_scalar("gp/outputscale", hp["outputscale"], n)
            w.add_scalar("gp/noise", hp["noise"], n)
        if density is not None and self.dim == 2 and n % max(self.config.image_every, 1) < self.config.batch_size:
            img = density.T[::-1].copy()  # rows = x2 descending, cols = x1
            w.add_image("posterior", (img / max(img.max(), 1e-300))[None], n)

    # ------------------------------------------------------------------ public ask / tell interface
    def initialise(self, x0: torch.Tensor | None = None) -> bool:
        """Resume from the checkpoint, or evaluate the initial design (``x0`` (n, p) in parameter units,
        default the maximin LHS of n_initial points) and checkpoint it. Returns True when resumed."""
        if self._load():
            return True
        self.state = ActiveState(x=torch.empty(0, self.dim, dtype=torch.float64),
                                 z=torch.empty(0, dtype=torch.float64),
                                 failed=torch.empty(0, dtype=torch.bool), reasons=[],
                                 is_initial=torch.empty(0, dtype=torch.bool))
        if x0 is None:
            x0 = initial_design(self.bounds, self.config.n_initial, self.config.seed)
        x0 = torch.as_tensor(x0, dtype=torch.float64).reshape(-1, self.dim)
        self._append(x0, self.evaluate(x0), initial=True)
        self._save()
        return False

    def evaluate(self, x: torch.Tensor) -> EvaluationResult:
        """The evaluator at (n, p) points (no state change)."""
        return self._evaluate(x)

    def update(self, estimate: bool = True):
        """Fit the emulator to all runs so far; with ``estimate`` also compute the posterior estimate and
        record the lagged TV. Returns (density, cell volume, TV) (None where not computed)."""
        self._fit()
        if not estimate:
            return None, None, None
        density, cvol = self._estimate()
        return density, cvol, self._record_tv(density, cvol)

    def propose(self, q: int) -> tuple[torch.Tensor, torch.Tensor]:
        """q new points (q, p) maximising the acquisition on the current fit, and the acquisition values."""
        return self._acquire(q, self.state.iteration)

    def tell(self, x: torch.Tensor, res: EvaluationResult, acq_max=None, tv=None, density=None) -> None:
        """Add evaluated adaptive points, advance the iteration, checkpoint and log."""
        s = self.state
        self._append(x, res, initial=False)
        if acq_max is not None:
            s.acq_history.append((s.n_runs, float(acq_max)))
        s.iteration += 1
        self._save()
        self._log(tv, new_z=res.z, acq_max=acq_max, density=density)

    def finish(self, reason: str, tv=None, density=None) -> None:
        """Mark the run as ended (``reason``), log the final estimate and checkpoint."""
        self.state.stopped_reason = reason
        self._log(tv, density=density)
        self._save()

    def open_log(self, log_dir) -> None:
        """Start TensorBoard logging to ``log_dir``."""
        from torch.utils.tensorboard import SummaryWriter

        self._writer = SummaryWriter(str(log_dir))

    def close_log(self) -> None:
        if self._writer is not None:
            self._writer.flush()
            self._writer.close()
            self._writer = None

    def run(self) -> ActiveState:
        """Run (or resume) the loop until n_total runs or TV convergence. Returns the final state."""
        c = self.config
        resumed = self._load()
        if self.log_dir is not None:
            self.open_log(self.log_dir)
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=c.n_total, desc="calibrate", unit="run")
        try:
            if not resumed:
                self.initialise()
            s = self.state
            if bar is not None:
                bar.update(s.n_runs)
            if resumed and s.stopped_reason and s.n_runs >= c.n_total:
                self._refit_final()
                return s
            while True:
                density, cvol, tv = self.update(estimate=c.track_tv or s.n_runs >= c.n_total)
                if bar is not None:
                    bar.set_postfix(tv=f"{tv:.3g}" if tv is not None else "-", failed=int(s.failed.sum()))
                if c.tv_threshold is not None and tv is not None:
                    s.below_count = s.below_count + 1 if tv < c.tv_threshold else 0
                    if s.below_count >= c.tv_patience:
                        self.finish(f"TV < {c.tv_threshold} for {c.tv_patience} iterations", tv, density)
                        break
                if s.n_runs >= c.n_total:
                    self.finish("n_total reached", tv, density)
                    break
                q = min(c.batch_size, c.n_total - s.n_runs)
                x_new, vals = self.propose(q)
                self.tell(x_new, self.evaluate(x_new), acq_max=vals[0], tv=tv, density=density)
                if bar is not None:
                    bar.update(q)
            self._save()
        finally:
            if bar is not None:
                bar.close()
            self.close_log()
        return self.state
