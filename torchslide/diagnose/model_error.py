"""Approximation error of the inversion grid: discretisation error as a model-error term.

The recordings come from the real flow; the likelihood compares them with a solver on cells of h.
Following the "enhanced error model" of Kaipio & Somersalo (2007, J. Comput. Appl. Math. 198,
493-504), the difference

    eps(theta) = y_{h/f}(theta) - y_h(theta)        (a run on cells f times smaller minus the inversion run)

is sampled at n parameter sets theta_i (posterior draws of a first calibration) and approximated as
Gaussian, independent of theta and of the measurement noise e ~ N(0, Sigma):

    d = y_h(theta) + eps + e,   eps ~ N(eps_bar, Gamma_eps)
    =>  ln L(theta) = ln N(d - eps_bar | y_h(theta), Sigma + Gamma_eps)

with eps_bar and Gamma_eps the sample mean and covariance (rank <= n - 1). A structure that the
finer grid produces and the inversion grid cannot is then no longer read as missing physics, and a
parameter that the grid biases gets a wider interval.

The finer run uses the DEM interpolated bilinearly to the finer cell centres, the release thickness,
erodible depth and friction scale repeated on the f x f sub-cells (same volumes), and the same gauges;
or, when the user has the terrain at the finer resolution (a LiDAR DEM coarsened for the inversion),
that terrain (:class:`FineTerrain`): then eps also carries what the coarse DEM loses of the terrain (a
channel two cells wide is shallower and wider on 40 m cells than on 20 m ones), usually the larger
part of the error. Its rasters are block-averaged back onto the inversion grid (h_final, h_max, v_max,
bed change; arrival time: block minimum), so every observation predicts from it as from an inversion run.

The release volume is an input known only to a relative standard deviation s_V (a back-analysed scar's
depth); the same enhanced error model marginalises it. With y linearised in the relative volume error
delta ~ (0, s_V^2), y(V (1 + delta)) ~ y(V) + delta J, so

    Gamma = Gamma_eps + s_V^2 (1/m) sum_i J_i J_i^T,   J_i = (y(V (1 + a), theta_i) - y(V (1 - a), theta_i)) / (2 a)

(central differences on the inversion grid at the same m = n draws, a = sqrt(3) s_V: the end points of
a uniform error with that sd). Without it, a term that changes the volume (entrainment) absorbs the
release's error into its own parameter with an interval that does not allow for it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..terrain.grid import DEM


def refine_dem(dem: DEM, f: int) -> DEM:
    """The DEM on cells f times smaller (same extent): elevation interpolated bilinearly between the
    coarse cell centres (linear extrapolation in the outer half cells)."""
    from scipy.interpolate import RegularGridInterpolator

    if int(f) != f or f < 2:
        raise ValueError(f"refinement factor must be an integer >= 2, got {f!r}")
    f = int(f)
    fine_cs = dem.cellsize / f
    yc = dem.yll + (np.arange(dem.ny * f) + 0.5) * fine_cs
    xc = dem.xll + (np.arange(dem.nx * f) + 0.5) * fine_cs
    itp = RegularGridInterpolator((dem.y_centres(), dem.x_centres()), dem.z, bounds_error=False, fill_value=None)
    Y, X = np.meshgrid(yc, xc, indexing="ij")
    z = itp(np.column_stack([Y.ravel(), X.ravel()])).reshape(Y.shape)
    return DEM(z, fine_cs, xll=dem.xll, yll=dem.yll, crs=dem.crs)


def repeat_cells(a, f: int):
    """(ny, nx) -> (ny f, nx f): every cell's value on its f x f sub-cells (None stays None)."""
    if a is None:
        return None
    a = np.asarray(a, dtype=np.float64)
    return np.repeat(np.repeat(a, f, axis=0), f, axis=1)


@dataclass
class FineTerrain:
    """The terrain on cells ``factor`` times smaller than the inversion grid, same extent.

    dem: the finer DEM (ny f, nx f); release: (ny f, nx f) release thickness, m; erodible_depth and
    mu_scale: (ny f, nx f) or None (None: the coarse fields repeated on the sub-cells).
    """

    dem: DEM
    release: np.ndarray
    erodible_depth: np.ndarray | None = None
    mu_scale: np.ndarray | None = None

    def factor_for(self, coarse: DEM) -> int:
        """The refinement factor against ``coarse``; ValueError naming the field unless the grid is an
        exact f-fold refinement (f >= 2 integer, same lower-left corner, shape (ny f, nx f))."""
        f = coarse.cellsize / self.dem.cellsize
        if abs(f - round(f)) > 1e-9 * f or round(f) < 2:
            raise ValueError(f"fine_terrain.dem: cellsize {self.dem.cellsize:g} m must divide the inversion cellsize "
                             f"{coarse.cellsize:g} m by an integer >= 2")
        f = int(round(f))
        if self.dem.shape != (coarse.ny * f, coarse.nx * f):
            raise ValueError(f"fine_terrain.dem: shape {self.dem.shape} must be {(coarse.ny * f, coarse.nx * f)} "
                             f"(the inversion grid {coarse.shape} refined {f} times)")
        tol = 1e-6 * coarse.cellsize
        if abs(self.dem.xll - coarse.xll) > tol or abs(self.dem.yll - coarse.yll) > tol:
            raise ValueError(f"fine_terrain.dem: lower-left corner ({self.dem.xll:g}, {self.dem.yll:g}) must be the "
                             f"inversion grid's ({coarse.xll:g}, {coarse.yll:g})")
        for name in ("release", "erodible_depth", "mu_scale"):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.asarray(a)
            if a.shape != self.dem.shape:
                raise ValueError(f"fine_terrain.{name}: shape {a.shape} must be the fine DEM's {self.dem.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"fine_terrain.{name}: contains non-finite values")
        return f

    def fields(self, evaluator, f: int) -> tuple:
        """(release, erodible_depth, mu_scale) on the fine grid; the evaluator's coarse fields repeated on
        the f x f sub-cells where not given (``f``: factor_for(evaluator.dem))."""
        erod = self.erodible_depth if self.erodible_depth is not None else repeat_cells(evaluator.erodible_depth, f)
        mus = self.mu_scale if self.mu_scale is not None else repeat_cells(evaluator.mu_scale, f)
        return np.asarray(self.release, dtype=np.float64), erod, mus


def _blocks(t: torch.Tensor, f: int) -> torch.Tensor:
    B, ny, nx = t.shape
    return t.reshape(B, ny // f, f, nx // f, f)


def coarsen_result(res, dem: DEM, f: int):
    """A finer-grid SimulationResult as seen on the coarse ``dem``: block means of h_final, h_max,
    v_max and bed_change, block minimum of arrival_time, cell areas summed; volumes, gauges and
    histories unchanged."""
    mean = lambda t: None if t is None else _blocks(t, f).mean(dim=(2, 4))
    ca = res.cell_area
    ca = ca.reshape(ca.shape[0] // f, f, ca.shape[1] // f, f).sum(dim=(1, 3))
    return dataclasses.replace(res, dem=dem, h_final=mean(res.h_final), h_max=mean(res.h_max), v_max=mean(res.v_max),
                               bed_change=mean(res.bed_change), cell_area=ca, map_cell_area=res.map_cell_area * f * f,
                               arrival_time=_blocks(res.arrival_time, f).amin(dim=(2, 4)))


@dataclass
class ModelError:
    """Sampled approximation error of the inversion grid.

    samples: (n, k) eps_i = y_fine(theta_i) - y_coarse(theta_i) in the flat observable order of the
    evaluator; x: (n, p) the parameter sets theta_i; factor: the refinement factor f.
    release_jacobian: (m, k) J_i = dy / d(relative release volume) at m parameter sets, observable units
    per unit relative volume, or None; release_sd: s_V, the release volume's relative sd (0: none).
    """

    samples: np.ndarray
    x: np.ndarray
    factor: int
    release_jacobian: np.ndarray | None = None
    release_sd: float = 0.0

    @property
    def mean(self) -> np.ndarray:
        """(k,) eps_bar."""
        return self.samples.mean(axis=0)

    @property
    def grid_covariance(self) -> np.ndarray:
        """(k, k) Gamma_eps, the sample covariance of the grid's error (zero for n = 1)."""
        s = self.samples
        if len(s) < 2:
            return np.zeros((s.shape[1], s.shape[1]))
        c = s - s.mean(axis=0)
        return c.T @ c / (len(s) - 1)

    @property
    def release_covariance(self) -> np.ndarray:
        """(k, k) s_V^2 (1/m) sum_i J_i J_i^T, the release volume's error (zero without it)."""
        k = self.samples.shape[1]
        J = self.release_jacobian
        if J is None or self.release_sd <= 0:
            return np.zeros((k, k))
        return self.release_sd**2 * (J.T @ J) / len(J)

    @property
    def covariance(self) -> np.ndarray:
        """(k, k) Gamma = Gamma_eps + the release volume's part (module doc)."""
        return self.grid_covariance + self.release_covariance

    def summary(self, blocks) -> dict:
        """Per observation block: rms of eps_bar and of the per-value sd (the size of what is absorbed)."""
        sd = np.sqrt(np.diag(self.grid_covariance))
        sd_v = np.sqrt(np.diag(self.release_covariance))
        m = self.mean
        out = {"n": int(len(self.samples)), "factor": int(self.factor),
               "blocks": {b.name: {"rms_mean": float(np.sqrt(np.mean(m[b.slice] ** 2))),
                                   "rms_sd": float(np.sqrt(np.mean(sd[b.slice] ** 2)))} for b in blocks}}
        if self.release_jacobian is not None and self.release_sd > 0:
            out["release_sd"] = float(self.release_sd)
            for b in blocks:
                out["blocks"][b.name]["rms_sd_release"] = float(np.sqrt(np.mean(sd_v[b.slice] ** 2)))
        return out


def _predictions(evaluator, x, run) -> tuple[np.ndarray, np.ndarray]:
    """(predictions (n, k), failed (n,)) of ``run(x_chunk) -> SimulationResult on the evaluator's grid``
    at the (n, p) parameter sets ``x``, in chunks of evaluator.max_batch (no run records are kept)."""
    x = torch.as_tensor(np.asarray(x, dtype=np.float64)).reshape(-1, len(evaluator.names))
    out, fails = [], []
    for s in range(0, len(x), evaluator.max_batch):
        preds, failed, _ = evaluator.predict(run(x[s:s + evaluator.max_batch]))
        out.append(preds.numpy())
        fails.append(failed.numpy())
    return np.concatenate(out), np.concatenate(fails)


def fine_run(evaluator, x, factor: int = 2):
    """One solver call for the (n, p) parameter sets ``x`` (n <= evaluator.max_batch) on the finer grid
    (:func:`fine_simulate`)."""
    return fine_simulate(evaluator, evaluator.params(x), factor)


def fine_simulate(evaluator, p, factor: int = 2):
    """One solver call of the members ``p`` (Params) on the finer grid, returned as seen on the evaluator's
    grid (:func:`coarsen_result`), so every observation predicts from it as from an inversion run. With
    ``evaluator.fine_terrain`` (a FineTerrain) its terrain and fields and its own factor (``factor`` must
    agree); else the coarse ones refined ``factor`` times."""
    return coarsen_result(fine_result(evaluator, p, factor)[0], evaluator.dem, factor)


def fine_result(evaluator, p, factor: int = 2) -> tuple:
    """(SimulationResult on the finer grid itself, its release (ny f, nx f) m): :func:`fine_simulate`'s run
    before it is coarsened."""
    from ..solver import simulate

    ft = getattr(evaluator, "fine_terrain", None)
    if ft is not None:
        f = ft.factor_for(evaluator.dem)
        if f != factor:
            raise ValueError(f"model_error_factor {factor} differs from the fine terrain's refinement factor {f}")
        dem_f = ft.dem
        rel_f, erod_f, mus_f = ft.fields(evaluator, f)
    else:
        dem_f = refine_dem(evaluator.dem, factor)
        rel_f = repeat_cells(evaluator.release, factor)
        erod_f = repeat_cells(evaluator.erodible_depth, factor)
        mus_f = repeat_cells(evaluator.mu_scale, factor)
    res = simulate(dem_f, rel_f, p, t_end=evaluator.t_end, gauges=list(evaluator.gauges) or None,
                   config=evaluator.solver_config, erodible_depth=erod_f, mu_scale=mus_f, dtype=evaluator.dtype,
                   device=evaluator.device, thickness=getattr(evaluator, "thickness", "normal"))
    return res, rel_f


def fine_predictions(evaluator, x: np.ndarray, factor: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(predictions (n, k), failed (n,)) of the finer-grid model (:func:`fine_run`) at the (n, p)
    parameter sets ``x``, in the evaluator's observable order."""
    return _predictions(evaluator, x, lambda xb: fine_run(evaluator, xb, factor))


def release_jacobian(evaluator, x: np.ndarray, release_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """(J (n, k), ok (n,)): central differences of the predictions at the (n, p) parameter sets ``x``
    in the relative release volume, J_i = (y(V (1 + a)) - y(V (1 - a))) / (2 a), a = sqrt(3) release_sd
    (module doc), on the inversion grid; ok is False where a run failed."""
    if not 0 < release_sd < 0.5:
        raise ValueError(f"release_volume_sd must be in (0, 0.5) (a relative sd), got {release_sd!r}")
    a = float(np.sqrt(3.0) * release_sd)
    rel = np.asarray(evaluator.release, dtype=np.float64)
    up, up_failed = _predictions(evaluator, x, evaluator._copy(release=rel * (1 + a)).simulate)
    dn, dn_failed = _predictions(evaluator, x, evaluator._copy(release=rel * (1 - a)).simulate)
    return (up - dn) / (2 * a), ~(up_failed | dn_failed)


def approximation_error(evaluator, x: np.ndarray, factor: int = 2, release_sd: float = 0.0) -> ModelError:
    """Sample eps = y_fine - y_coarse at the (n, p) parameter sets ``x`` (n >= 2; members failing on
    either grid are dropped); ``release_sd`` > 0: also the release volume's relative sd, its Jacobian
    taken at the same sets (:func:`release_jacobian`)."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < 2:
        raise ValueError(f"the approximation error needs at least 2 parameter sets, got {len(x)}")
    coarse, c_failed = _predictions(evaluator, x, evaluator.simulate)
    fine, f_failed = fine_predictions(evaluator, x, factor)
    ok = ~(c_failed | f_failed)
    J = None
    if release_sd > 0:
        J, j_ok = release_jacobian(evaluator, x, release_sd)
        ok &= j_ok
        J = J[ok]
    if ok.sum() < 2:
        raise RuntimeError(f"the approximation error needs 2 runs that succeed on both grids, got {int(ok.sum())}")
    return ModelError(samples=fine[ok] - coarse[ok], x=x[ok], factor=int(factor), release_jacobian=J,
                      release_sd=float(release_sd))
