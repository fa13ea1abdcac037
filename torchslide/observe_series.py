"""Vector-valued observation kinds: gauge series and maps on the DEM grid.

A :class:`SeriesObservation` contributes m residuals (not one). Its operator returns a (B, m) tensor;
an evaluator flattens all observations (scalar ones count as m = 1) into one data vector d (k,) with
per-element effective standard deviations, so the usual diagonal Gaussian likelihood applies
(see :class:`torchslide.diagnose.evaluator.DiagnosisEvaluator`).

Kinds (registered in :data:`torchslide.observe.KINDS` with :func:`register_kind`; their ``fn``
returns (B, m), which is why they are listed in :data:`VECTOR_KINDS` and must be used through
``SeriesObservation``, not the scalar ``Observation``):

* ``gauge_series``: flow thickness ("h", m) or speed ("speed", m/s) of a named gauge at the observed
  times t (s), linearly interpolated between the solver's output samples (clamped at both ends).
  CSV input: a header row with ``t`` and ``h`` and/or ``speed`` columns; times must increase strictly;
  an empty (or NA) h or speed cell is a gap in that recording, left out of its series.
* ``deposit_map``: final thickness h_final (m) on every cell of the DEM grid with a finite value in the
  raster (nodata cells are left out).
* ``elevation_change``: a DEM of difference (post- minus pre-event surface, vertical m: + deposition,
  - erosion; nodata where not surveyed) per mapped cell, against the simulated change of the surface
  (SimulationResult.elevation_change: the bed's change plus the flow's thickness per map area minus the
  release's).
* ``footprint``: a mapped outline (a polygon file, or a 0/1 raster with nodata where not mapped) against the
  smooth reach h_max^2 / (h_max^2 + threshold^2) per cell: 0 where the flow never came, 1/2 at the
  threshold, towards 1 where it was thick. A cell's h_max grows from 0 as the front arrives, so the
  prediction, and the likelihood, change continuously with the parameters (a 0/1 indicator steps), for
  the emulator and for the local fits alike.
* ``impact_map``: 1 where h_max > threshold, else 0, per cell (the indicator of ``impact_area``).
  With a Gaussian error model on a 0/1 quantity, sigma ~ 0.3-0.5 is sensible. The recording is a 0/1
  raster (nodata where not mapped) or an observed outline as a polygon file (1 inside, 0 outside).
  Thicknesses are normal to the slope and speeds along the surface (torchslide.observe).

Error model: independent Gaussian errors with standard deviation ``sigma`` (scalar or per element),
optionally *correlated*: ``corr_length`` (m for maps, s for gauge series) is the length of an
exponential covariance exp(-r / L). We do not invert the dense covariance; we use the effective
number of independent samples instead. For an exponential covariance the integral of the
correlation over the plane is 2 pi L^2 (over a line, 2 L), so each cell (sample) carries the
information of 1/f independent values with

    f = max(1, 2 pi L^2 / cellsize^2)   (maps),     f = max(1, 2 L / dt)   (series, dt the sample step)

and the likelihood uses sigma_eff = sigma sqrt(f) (equivalently, n_eff = m / f independent samples).
This is exact for the total information in the large-domain limit and keeps correlated map errors
from being counted as thousands of independent ones (a cause of false discoveries).
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from .observe import DEFAULT_THRESHOLD, KINDS, register_kind
from .result import SimulationResult
from .terrain.grid import DEM, TerrainError

__all__ = ["SeriesObservation", "VECTOR_KINDS", "read_gauge_csv", "read_map", "interp_series",
           "GaugeSeriesError", "effective_factor", "exponential_field"]

VECTOR_KINDS = ("gauge_series", "deposit_map", "impact_map", "elevation_change", "footprint")
MAP_KINDS = ("deposit_map", "impact_map", "elevation_change", "footprint")


class GaugeSeriesError(ValueError):
    """Bad gauge-series input (names the file and row)."""


# ----------------------------------------------------------------------------------------- operators
def interp_series(t_model: torch.Tensor, y: torch.Tensor, t_obs: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of (B, T) series sampled at t_model (T,) onto t_obs (m,) -> (B, m); clamped."""
    t_model = t_model.to(y)
    t_obs = t_obs.to(y)
    T = t_model.numel()
    if T == 1:
        return y[:, :1].expand(-1, t_obs.numel())
    tq = t_obs.clamp(t_model[0], t_model[-1])
    j = torch.searchsorted(t_model, tq, right=True).clamp(1, T - 1)
    t0, t1 = t_model[j - 1], t_model[j]
    w = ((tq - t0) / (t1 - t0).clamp_min(1e-12)).clamp(0, 1)
    return y[:, j - 1] * (1 - w) + y[:, j] * w


def _gauge_fn(result: SimulationResult, obs: "SeriesObservation") -> torch.Tensor:
    name = obs.gauge
    if name not in result.gauges:
        raise KeyError(f"observation {obs.name!r}: the run has no gauge named {name!r}; gauges: {sorted(result.gauges)}")
    g = result.gauges[name]
    y = g.speed if obs.quantity == "speed" else g.h
    return interp_series(g.t, y, torch.as_tensor(obs.times, dtype=y.dtype, device=y.device))


def _cells(result: SimulationResult, obs: "SeriesObservation", field_: torch.Tensor) -> torch.Tensor:
    idx = torch.as_tensor(obs.cell_index, device=field_.device)
    return field_.flatten(1)[:, idx]


def _deposit_map_fn(result, obs):
    return _cells(result, obs, result.h_final)


def _elevation_change_fn(result, obs):
    if result.elevation_change is None:
        raise ValueError(f"observation {obs.name!r}: the result holds no elevation change (not a solver result)")
    return _cells(result, obs, result.elevation_change)


def footprint_reach(h_max: torch.Tensor, threshold: float) -> torch.Tensor:
    """h_max^2 / (h_max^2 + threshold^2): the smooth reach of a cell, 0 unreached, 1/2 at the threshold."""
    h2 = h_max * h_max
    return h2 / (h2 + threshold * threshold)


def _footprint_fn(result, obs):
    return _cells(result, obs, footprint_reach(result.h_max, obs.threshold))


def _impact_map_fn(result, obs):
    return _cells(result, obs, (result.h_max > obs.threshold).to(result.h_max))


register_kind("gauge_series", _gauge_fn, unit="m or m/s",
              description="vector (B, m): gauge h or speed at the observed times (use SeriesObservation)",
              overwrite=True)
register_kind("deposit_map", _deposit_map_fn, unit="m",
              description="vector (B, m): h_final per mapped cell (use SeriesObservation)", overwrite=True)
register_kind("elevation_change", _elevation_change_fn, unit="m",
              description="vector (B, m): the surface's vertical change per surveyed cell (use SeriesObservation)",
              overwrite=True)
register_kind("footprint", _footprint_fn, unit="-", uses_threshold=True,
              description="vector (B, m): the smooth reach h_max^2 / (h_max^2 + threshold^2) per mapped cell",
              overwrite=True)
register_kind("impact_map", _impact_map_fn, unit="-", uses_threshold=True,
              description="vector (B, m): 1 where h_max > threshold per mapped cell (use SeriesObservation)",
              overwrite=True)


def effective_factor(kind: str, corr_length: float | None, cellsize: float | None = None,
                     dt: float | None = None) -> float:
    """Variance inflation f >= 1 for an exponential correlation of length L (see the module doc)."""
    if not corr_length:
        return 1.0
    if kind == "gauge_series":
        return max(1.0, 2.0 * corr_length / dt) if dt else 1.0
    return max(1.0, 2.0 * math.pi * corr_length**2 / cellsize**2)


def exponential_field(shape: tuple, cellsize: float, corr_length: float, rng: np.random.Generator,
                      n: int = 1) -> np.ndarray:
    """(n, ny, nx) zero-mean, unit-variance Gaussian fields on a grid of ``cellsize`` m with the exponential
    correlation exp(-r / corr_length) (r the distance between cell centres, m), by circulant embedding:
    the covariance is laid on a periodic grid at least twice the size (plus 2 correlation lengths) so that
    the wrapped distance of every pair of the grid is its true one; the FFT of that row gives the
    eigenvalues lambda of the circulant covariance, and ifft2(sqrt(lambda) fft2(w)) of white noise w has
    it. The few slightly negative eigenvalues the embedding may give are set to 0 (an error of that size in
    the covariance)."""
    ny, nx = (int(v) for v in shape)
    pad = int(math.ceil(2.0 * corr_length / cellsize))
    Ny, Nx = 2 * (ny + pad), 2 * (nx + pad)
    iy = np.minimum(np.arange(Ny), Ny - np.arange(Ny))[:, None]
    ix = np.minimum(np.arange(Nx), Nx - np.arange(Nx))[None, :]
    c = np.exp(-cellsize * np.hypot(iy, ix) / corr_length)
    lam = np.clip(np.fft.fft2(c).real, 0.0, None)
    w = rng.standard_normal((n, Ny, Nx))
    f = np.fft.ifft2(np.sqrt(lam) * np.fft.fft2(w), axes=(-2, -1)).real
    return f[:, :ny, :nx]


# -------------------------------------------------------------------------------------------- readers
MISSING = ("", "na", "nan", "-")  # a gauge CSV's marks of a missing h or speed sample (case-insensitive)


def read_gauge_csv(path) -> dict[str, np.ndarray]:
    """Read a gauge CSV (header ``t`` plus ``h`` and/or ``speed``) -> {column: (m,) array}.

    A gap in a recording (a sensor drop-out) is an empty h or speed cell, or ``NA`` / ``NaN`` / ``-``
    there: it comes back as NaN, and :meth:`SeriesObservation.from_gauge_csv` leaves that sample out of
    that quantity's series. Times must all be given. Raises GaugeSeriesError naming the file and the
    (1-based, header = row 1) row for missing columns, non-numeric values, infinite values, a missing or
    negative time (t is seconds since the release) or times that do not increase strictly.
    """
    path = Path(path)
    if not path.is_file():
        raise GaugeSeriesError(f"{path}: gauge series file not found")
    with open(path, newline="") as f:
        rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    if not rows:
        raise GaugeSeriesError(f"{path}: empty gauge series file (need a header t,h and/or t,speed)")
    header = [c.strip().lower() for c in rows[0]]
    if "t" not in header or not ({"h", "speed"} & set(header)):
        raise GaugeSeriesError(f"{path}: row 1: header must name t and h and/or speed, got {rows[0]}")
    cols = {c: [] for c in header if c in ("t", "h", "speed")}
    for r_i, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise GaugeSeriesError(f"{path}: row {r_i}: expected {len(header)} values, got {len(row)}")
        for c in cols:
            s = row[header.index(c)].strip()
            if c != "t" and s.lower() in MISSING:
                cols[c].append(math.nan)
                continue
            try:
                v = float(s)
            except ValueError:
                what = "has no time" if c == "t" and s.lower() in MISSING else f"column {c!r} is not a number: {s!r}"
                raise GaugeSeriesError(f"{path}: row {r_i}: {what}") from None
            if not math.isfinite(v):
                raise GaugeSeriesError(f"{path}: row {r_i}: column {c!r} is not finite: {s!r}"
                                       + ("; mark a missing sample with an empty cell or NA" if c != "t" else ""))
            cols[c].append(v)
    t = np.asarray(cols["t"])
    if t.size < 2:
        raise GaugeSeriesError(f"{path}: need at least 2 samples, got {t.size}")
    if t[0] < 0:
        raise GaugeSeriesError(f"{path}: row 2: times are seconds since the release and must be >= 0, got t = {t[0]:g}")
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        raise GaugeSeriesError(f"{path}: row {k + 2}: times must increase strictly, got t = {t[k]:g} after {t[k - 1]:g}")
    return {c: np.asarray(v) for c, v in cols.items()}


def read_map(path, dem: DEM, what: str = "map") -> np.ndarray:
    """A raster on ``dem``'s grid (ny, nx), nodata as NaN; TerrainError naming the file and both grids otherwise."""
    from .terrain.io import read_raster_on_grid

    return read_raster_on_grid(path, dem, what)


# ------------------------------------------------------------------------------------ the observation
@dataclass
class SeriesObservation:
    """A vector-valued observation (m values) with its error model.

    Attributes:
        kind: "gauge_series", "deposit_map", "impact_map", "elevation_change" or "footprint".
        values: (m,) observed values (for maps: the mapped cells in row-major order of ``cell_index``).
        sigma: standard deviation (scalar or (m,)), > 0.
        name: label.
        gauge, quantity, times: gauge series only (gauge name, "h" or "speed", (m,) s).
        cell_index: (m,) flat indices (row-major, row 0 south) of the mapped cells (maps only).
        grid_shape: (ny, nx) of the map grid.
        threshold: impact_map and footprint thickness threshold, m.
        corr_length: exponential correlation length (m for maps, s for series) or None (independent).
        source: the file it came from (messages).
    """

    kind: str
    values: np.ndarray
    sigma: Any
    name: str
    gauge: str | None = None
    quantity: str = "h"
    times: np.ndarray | None = None
    cell_index: np.ndarray | None = None
    grid_shape: tuple | None = None
    cellsize: float | None = None
    threshold: float = DEFAULT_THRESHOLD
    corr_length: float | None = None
    source: str = ""
    options: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_gauge_csv(cls, path, gauge: str, sigma: dict | float, quantities: Sequence[str] | None = None,
                       corr_time: float | None = None, name: str | None = None) -> list["SeriesObservation"]:
        """One observation per quantity column (h, speed) of a gauge CSV. ``sigma``: a number or {quantity: sigma}."""
        cols = read_gauge_csv(path)
        qs = [q for q in ("h", "speed") if q in cols] if quantities is None else list(quantities)
        out = []
        for q in qs:
            if q not in cols:
                raise GaugeSeriesError(f"{path}: no column {q!r} (columns: {sorted(cols)})")
            s = sigma.get(q) if isinstance(sigma, dict) else sigma
            if s is None:
                raise GaugeSeriesError(f"{path}: sigma for {q!r} is missing")
            have = np.isfinite(cols[q])  # gaps in the recording are left out of this quantity's series
            if have.sum() < 2:
                raise GaugeSeriesError(f"{path}: column {q!r} has {int(have.sum())} recorded samples "
                                       f"({int((~have).sum())} missing); need at least 2")
            out.append(cls("gauge_series", cols[q][have], s, name=f"{name or gauge}:{q}", gauge=gauge, quantity=q,
                           times=cols["t"][have], corr_length=corr_time, source=str(path)))
        return out

    @classmethod
    def from_array(cls, kind: str, array: np.ndarray, dem: DEM, sigma, name: str | None = None,
                   threshold: float = DEFAULT_THRESHOLD, corr_length: float | None = None,
                   source: str = "", mask: np.ndarray | None = None) -> "SeriesObservation":
        """A map observation from an (ny, nx) array on ``dem``'s grid (NaN = not mapped)."""
        a = np.asarray(array, dtype=np.float64)
        if a.shape != dem.shape:
            raise TerrainError(f"{source or name or kind}: map has shape {a.shape}, the DEM grid is {dem.shape}")
        label = source or name or kind

        def first_cell(bad: np.ndarray) -> str:
            r, c = (int(v) for v in np.argwhere(bad)[0])
            return (f"first at row {r} from the south, col {c} (x={dem.xll + (c + 0.5) * dem.cellsize:g} m, "
                    f"y={dem.yll + (r + 0.5) * dem.cellsize:g} m): {float(a[r, c])!r}")

        inf = np.isinf(a)
        if inf.any():
            raise ValueError(f"{label}: {int(inf.sum())} infinite cells, {first_cell(inf)}; "
                             f"mark cells without a recording as nodata (NaN)")
        if kind in ("impact_map", "footprint"):
            not01 = np.isfinite(a) & (a != 0) & (a != 1)
            if not01.any():
                raise ValueError(f"{label}: an impact map holds 0 (not reached) or 1 (reached) per cell, and "
                                 f"nodata where not mapped; {int(not01.sum())} cells hold other values, "
                                 f"{first_cell(not01)}")
        ok = np.isfinite(a) if mask is None else (np.isfinite(a) & mask)
        idx = np.flatnonzero(ok.ravel())
        if idx.size == 0:
            raise ValueError(f"{label}: map has no finite cells")
        return cls(kind, a.ravel()[idx], sigma, name=name or kind, cell_index=idx, grid_shape=dem.shape,
                   cellsize=float(dem.cellsize), threshold=threshold, corr_length=corr_length, source=source)

    @classmethod
    def from_raster(cls, path, kind: str, dem: DEM, sigma, **kw) -> "SeriesObservation":
        """A map observation from a raster on ``dem``'s grid, or for impact_map an observed outline
        (a polygon file: 1 inside, 0 outside, every cell mapped)."""
        from .terrain.vector import is_vector, rasterize_outline

        if kind in ("impact_map", "footprint") and is_vector(path):
            return cls.from_array(kind, rasterize_outline(path, dem), dem, sigma, source=str(path), **kw)
        arr = read_map(path, dem, what=kind.replace("_", " "))
        return cls.from_array(kind, arr, dem, sigma, source=str(path), **kw)

    def on_grid(self, src: DEM, dst: DEM) -> "SeriesObservation":
        """This map (on ``src``'s grid) on ``dst``'s grid, each new cell the area-weighted mean of the
        recorded cells it overlaps (terrain.resample.resample_map; impact maps and footprints rounded to 0 or
        1), with the same stated sigma per value (an error correlated over the source cells does not average
        out); a gauge series or a map already on ``dst``'s grid is returned as it is."""
        from .terrain.resample import resample_map

        if not self.is_map or (tuple(self.grid_shape) == dst.shape and abs(self.cellsize - dst.cellsize) <= 1e-9 * dst.cellsize):
            return self
        full = np.full(src.shape, np.nan)
        full.ravel()[self.cell_index] = self.values
        binary = self.kind in ("impact_map", "footprint")
        sigma = self.sigma
        if np.ndim(sigma) and np.size(sigma) > 1:
            s_full = np.full(src.shape, np.nan)
            s_full.ravel()[self.cell_index] = np.asarray(sigma, dtype=np.float64)
            s_dst = resample_map(s_full, src, dst)
        arr = resample_map(full, src, dst, binary=binary)
        o = type(self).from_array(self.kind, arr, dst, sigma, name=self.name, threshold=self.threshold,
                                  corr_length=self.corr_length, source=self.source)
        if np.ndim(sigma) and np.size(sigma) > 1:
            o.sigma = s_dst.ravel()[o.cell_index]
        o.options = dict(self.options)
        return o

    # ---------------------------------------------------------------- properties
    @property
    def m(self) -> int:
        return int(np.asarray(self.values).size)

    @property
    def is_map(self) -> bool:
        return self.kind in MAP_KINDS

    def sigma_vector(self) -> np.ndarray:
        s = np.asarray(self.sigma, dtype=np.float64)
        return np.broadcast_to(s, (self.m,)).copy()

    def factor(self) -> float:
        dt = float(np.median(np.diff(self.times))) if self.times is not None and len(self.times) > 1 else None
        return effective_factor(self.kind, self.corr_length, self.cellsize, dt)

    def sigma_eff(self) -> np.ndarray:
        """(m,) sigma * sqrt(f): the standard deviations the likelihood uses."""
        return self.sigma_vector() * math.sqrt(self.factor())

    def sample_errors(self, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """(n, m) draws of the stated error model: zero-mean Gaussian, covariance sigma_i sigma_j exp(-r_ij / L)
        (r_ij: distance between the cells' centres, m, for maps; |t_i - t_j|, s, for series; L =
        ``corr_length``; independent when it is None or 0). The likelihood stands in for this covariance
        with independent values of sigma_eff (module doc); synthetic recordings of this design (the null
        runs of torchslide.diagnose.null) take their noise from here."""
        s = self.sigma_vector()
        L = self.corr_length
        if not L:
            return s * rng.standard_normal((n, self.m))
        if self.is_map:
            f = exponential_field(self.grid_shape, self.cellsize, L, rng, n)
            return s * f.reshape(n, -1)[:, self.cell_index]
        t = np.asarray(self.times, dtype=np.float64)
        c = np.exp(-np.abs(t[:, None] - t[None, :]) / L) + 1e-10 * np.eye(t.size)
        return s * (rng.standard_normal((n, self.m)) @ np.linalg.cholesky(c).T)

    @property
    def n_eff(self) -> float:
        return self.m / self.factor()

    def labels(self) -> list[str]:
        if self.kind == "gauge_series":
            return [f"{self.name}@t={t:g}" for t in self.times]
        return [f"{self.name}[{i}]" for i in self.cell_index]

    def to_grid(self, vec) -> np.ndarray:
        """(m,) values of this map -> (ny, nx) array with NaN off the map."""
        out = np.full(int(np.prod(self.grid_shape)), np.nan)
        out[self.cell_index] = np.asarray(vec, dtype=np.float64)
        return out.reshape(self.grid_shape)

    # ---------------------------------------------------------------- checks and prediction
    def validate(self, dem: DEM | None = None, gauges: Sequence[str] | None = None) -> "SeriesObservation":
        label = f"observation {self.name!r}" + (f" ({self.source})" if self.source else "")
        if self.kind not in VECTOR_KINDS:
            raise ValueError(f"{label}: kind {self.kind!r} is not a vector kind ({', '.join(VECTOR_KINDS)})")
        v = np.asarray(self.values, dtype=np.float64)
        if v.ndim != 1 or v.size == 0 or not np.isfinite(v).all():
            raise ValueError(f"{label}: values must be a non-empty finite vector")
        s = np.asarray(self.sigma, dtype=np.float64)
        if s.size not in (1, v.size) or not (np.isfinite(s).all() and (s > 0).all()):
            raise ValueError(f"{label}: sigma must be > 0 (scalar or one per value), got {self.sigma!r}")
        if self.corr_length is not None and not (math.isfinite(self.corr_length) and self.corr_length >= 0):
            raise ValueError(f"{label}: corr_length must be >= 0, got {self.corr_length!r}")
        if self.kind == "gauge_series":
            if self.quantity not in ("h", "speed"):
                raise ValueError(f"{label}: quantity must be 'h' or 'speed', got {self.quantity!r}")
            t = np.asarray(self.times, dtype=np.float64)
            if t.shape != v.shape:
                raise ValueError(f"{label}: {t.size} times for {v.size} values")
            if not np.isfinite(t).all() or t[0] < 0:
                raise GaugeSeriesError(f"{label}: times are finite seconds since the release (>= 0), first t = {t[0]:g}")
            bad = np.nonzero(np.diff(t) <= 0)[0]
            if bad.size:
                raise GaugeSeriesError(f"{label}: times must increase strictly (sample {int(bad[0]) + 2}: "
                                       f"t = {t[bad[0] + 1]:g} after {t[bad[0]]:g})")
            if gauges is not None and self.gauge not in gauges:
                raise ValueError(f"{label}: gauge {self.gauge!r} is not defined; gauges: {sorted(gauges)}")
        elif dem is not None and tuple(self.grid_shape) != dem.shape:
            raise TerrainError(f"{label}: map grid {self.grid_shape} does not match the DEM grid {dem.shape}")
        return self

    def predict(self, result: SimulationResult) -> torch.Tensor:
        """(B, m) predictions."""
        out = KINDS[self.kind].fn(result, self)
        if out.shape != (result.batch_size, self.m):
            raise RuntimeError(f"kind {self.kind!r} returned {tuple(out.shape)}, expected ({result.batch_size}, {self.m})")
        return out
