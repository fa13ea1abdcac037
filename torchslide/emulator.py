"""GP emulator of the log-unnormalised posterior z = g(x) (Eq. 11-14).

A BoTorch ``SingleTaskGP`` (a GPyTorch ExactGP) in float64 with

* inputs scaled to the unit cube [0, 1]^p (done here, so the model and the acquisition functions
  live on the unit cube; ``to_unit`` / ``from_unit`` convert),
* outputs standardised (``Standardize`` outcome transform; predictions come back in z units),
* a Matern 5/2 ARD kernel with Gamma(3, 6) lengthscale and Gamma(2, 0.15) outputscale priors and a
  small-noise LogNormal prior (z is deterministic up to solver noise),
* hyperparameters fitted with ``botorch.fit.fit_gpytorch_mll`` and warm-started from the previous
  fit, with Cholesky failures handled by increasing jitter and retries.

Robustness (documented choice): far from the mode the log-posterior can be -1e4 while the interesting
part spans a few nats. A stationary GP fitted to both resolves neither. Training values are therefore
capped from below, ``z_train = max(z, max(z) - clip_range)`` (as in GPry / approxposterior
variants). With ``clip_range = C`` the capped region carries at most ``exp(-C)`` of the peak density,
so the posterior is unchanged to that order, while the GP spends its variance on the region that
matters. ``clip_range=None`` disables it. Measured on Rosenbrock (40 + 60 runs, seed 0): C = 50 gave
TV 0.011 and no cap TV 0.002 -- a tight cap adds a kink that the stationary GP pays for -- so the
default is a loose safety cap, C = 1000 nats, which leaves the analytic benchmark targets untouched
and only flattens pathological values such as -1e4 from a run far from the data.
"""
from __future__ import annotations

import contextlib
import warnings

import gpytorch
import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.outcome import Standardize
from botorch.models.utils.gpytorch_modules import get_matern_kernel_with_gamma_prior
from gpytorch.constraints import GreaterThan
from gpytorch.likelihoods import GaussianLikelihood as GPLikelihood
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.priors import LogNormalPrior

DTYPE = torch.float64
_HYPER_PREFIXES = ("likelihood.", "mean_module.", "covar_module.")


def cap_low_values(z: torch.Tensor, clip_range: float | None) -> torch.Tensor:
    """z_train = max(z, max(z) - clip_range) (no-op when clip_range is None)."""
    if clip_range is None or z.numel() == 0:
        return z
    return torch.clamp_min(z, float(z.max()) - float(clip_range))


@contextlib.contextmanager
def single_threaded():
    """Run the enclosed torch work on one intra-op thread, then restore the caller's setting.

    GP fitting and acquisition optimisation on a few hundred points gain nothing from threads, and
    multi-threaded reductions change the last bits of results from call to call, which sends L-BFGS to
    other local optima: with one thread the same seed gives the same points, so a resumed calibration
    repeats an uninterrupted one exactly whatever the machine's thread count.
    """
    n = torch.get_num_threads()
    if n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


class LogPosteriorEmulator:
    """GP emulator of z over a box.

    Args:
        bounds: (2, p) box [lows; highs] in parameter units.
        clip_range: cap for low training values (see module docstring); None disables.
        noise_floor: lower bound of the GP noise variance (standardised units).
        warm_start: start each fit from the previous hyperparameters.
        max_jitter: the largest Cholesky jitter tried before giving up on a fit.
    """

    def __init__(self, bounds, clip_range: float | None = 1000.0, noise_floor: float = 1e-6,
                 warm_start: bool = True, max_jitter: float = 1e-2):
        self.bounds = torch.as_tensor(bounds, dtype=DTYPE)
        self.dim = self.bounds.shape[1]
        self.clip_range = clip_range
        self.noise_floor = noise_floor
        self.warm_start = warm_start
        self.max_jitter = max_jitter
        self.model: SingleTaskGP | None = None
        self._hyper_state: dict | None = None
        self.fit_info: dict = {}

    # ---------------------------------------------------------------------------------------------
    def to_unit(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=DTYPE)
        return (x - self.bounds[0]) / (self.bounds[1] - self.bounds[0])

    def from_unit(self, u: torch.Tensor) -> torch.Tensor:
        u = torch.as_tensor(u, dtype=DTYPE)
        return self.bounds[0] + u * (self.bounds[1] - self.bounds[0])

    def _build(self, X: torch.Tensor, Y: torch.Tensor) -> SingleTaskGP:
        noise_prior = LogNormalPrior(loc=-8.0, scale=2.0)
        lik = GPLikelihood(noise_prior=noise_prior,
                           noise_constraint=GreaterThan(self.noise_floor, transform=None,
                                                        initial_value=max(1e-4, 2 * self.noise_floor)))
        model = SingleTaskGP(X, Y, likelihood=lik, covar_module=get_matern_kernel_with_gamma_prior(self.dim),
                             outcome_transform=Standardize(m=1))
        return model.to(DTYPE)

    def fit(self, x: torch.Tensor, z: torch.Tensor) -> "LogPosteriorEmulator":
        """Fit the GP to training points x (n, p) (parameter units) and finite values z (n,)."""
        with single_threaded():
            return self._fit(x, z)

    def _fit(self, x: torch.Tensor, z: torch.Tensor) -> "LogPosteriorEmulator":
        x = torch.as_tensor(x, dtype=DTYPE).reshape(-1, self.dim)
        z = torch.as_tensor(z, dtype=DTYPE).reshape(-1)
        ok = torch.isfinite(z)
        if not bool(ok.all()):
            raise ValueError("emulator.fit got non-finite z; exclude failed runs before fitting")
        if x.shape[0] < 2:
            raise ValueError(f"need at least 2 successful runs to fit the GP, got {x.shape[0]}")
        X = self.to_unit(x)
        Y = cap_low_values(z, self.clip_range).unsqueeze(-1)
        self.z_max = float(z.max())
        last_err = None
        jitter = 1e-8
        attempt = 0
        while jitter <= self.max_jitter:
            model = self._build(X, Y)
            if self.warm_start and self._hyper_state is not None and attempt == 0:
                try:
                    model.load_state_dict(self._hyper_state, strict=False)
                except RuntimeError:
                    pass
            mll = ExactMarginalLogLikelihood(model.likelihood, model)
            try:
                with gpytorch.settings.cholesky_jitter(double_value=jitter), warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    fit_gpytorch_mll(mll, optimizer_kwargs={"options": {"maxiter": 200}})
                model.eval()
                # Check that prediction works at this jitter (Cholesky of the training covariance).
                with torch.no_grad(), gpytorch.settings.cholesky_jitter(double_value=jitter):
                    model.posterior(X[:1])
                self.model = model
                self.jitter = jitter
                self._hyper_state = {k: v.detach().clone() for k, v in model.state_dict().items()
                                     if k.startswith(_HYPER_PREFIXES)}
                self.fit_info = {"attempts": attempt + 1, "jitter": jitter}
                return self
            except Exception as err:  # NotPSDError, ModelFittingError, numerical failures
                last_err = err
                attempt += 1
                jitter *= 10.0
        raise RuntimeError(f"GP fit failed after {attempt} attempts (max jitter {self.max_jitter}): {last_err}")

    # ---------------------------------------------------------------------------------------------
    def hyperparameters(self) -> dict:
        """Lengthscales (unit cube), outputscale and noise (standardised units)."""
        m = self.model
        return {
            "lengthscale": m.covar_module.base_kernel.lengthscale.detach().reshape(-1).tolist(),
            "outputscale": float(m.covar_module.outputscale.detach()),
            "noise": float(m.likelihood.noise.detach().reshape(-1)[0]),
            "mean_constant": float(m.mean_module.constant.detach()),
        }

    def predict(self, x: torch.Tensor, batch: int = 10000, unit: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior mean m'(x) and variance k'(x, x) of g (Eq. 13-14) in z units. x: (n, p) -> (n,), (n,)."""
        if self.model is None:
            raise RuntimeError("emulator is not fitted")
        x = torch.as_tensor(x, dtype=DTYPE).reshape(-1, self.dim)
        X = x if unit else self.to_unit(x)
        means, vars_ = [], []
        with torch.no_grad(), gpytorch.settings.cholesky_jitter(double_value=self.jitter):
            for i in range(0, X.shape[0], batch):
                # (b, 1, p): one t-batch per point, so only marginal variances are computed
                post = self.model.posterior(X[i:i + batch].unsqueeze(-2))
                means.append(post.mean.reshape(-1))
                vars_.append(post.variance.reshape(-1).clamp_min(0.0))
        return torch.cat(means), torch.cat(vars_)

    def mean(self, x: torch.Tensor, batch: int = 20000) -> torch.Tensor:
        """g_hat(x) = posterior mean m'(x) (Eq. 13) in z units; x (n, p) in parameter units -> (n,).

        The mean alone, m'(x) = m0 + k(x, X) alpha with alpha = (K + s^2 I)^-1 (y - m0) from GPyTorch's
        prediction cache (``prediction_strategy.mean_cache``, built once per fit), un-standardised by
        the model's ``Standardize``. It skips the predictive variances, whose cost per point grows with
        the square of the training set (``predict`` pays it): 4-6 times faster on grid posteriors, and
        equal to ``predict(x)[0]`` to round-off (tests/test_emulator.py).
        """
        if self.model is None:
            raise RuntimeError("emulator is not fitted")
        x = torch.as_tensor(x, dtype=DTYPE).reshape(-1, self.dim)
        m = self.model
        X = self.to_unit(x)
        Xt = m.train_inputs[0]
        with torch.no_grad(), gpytorch.settings.cholesky_jitter(double_value=self.jitter):
            if m.training or m.prediction_strategy is None:
                m.posterior(X[:1])          # eval mode, and GPyTorch builds its caches (alpha)
            alpha = m.prediction_strategy.mean_cache
            if alpha.shape != (Xt.shape[0],) or Xt.ndim != 2:   # a batched model: the general path
                return self.predict(x, batch=batch)[0]
            out = [m.mean_module(X[i:i + batch]) + m.covar_module(X[i:i + batch], Xt).to_dense() @ alpha
                   for i in range(0, X.shape[0], batch)]
        tf = m.outcome_transform
        return torch.cat(out) * tf.stdvs.reshape(()) + tf.means.reshape(())
