"""Physical upper bounds of a run's peak speeds: the energy line from the release (docs/verification.md,
case 7) and free fall.

A mass that starts at rest in release cell r and slides with Coulomb friction mu (plus any turbulent
friction, which only takes energy away) reaches a point at horizontal distance d_r with
|V|^2 / (2 g) <= z_r + h_r - z - mu d_r: the work of friction along a path on the surface is
mu g times its horizontal length, at least mu g d_r. A depth-averaged flow also carries a pressure
head; the bound grants the peak thickness h_max on top. No cell's v_max may exceed it, on any terrain.
"""
from __future__ import annotations

import numpy as np
import torch

G = 9.81


def energy_line_head(z: np.ndarray, cellsize: float, release: np.ndarray, mu: float,
                     chunk: int = 512) -> np.ndarray:
    """max over release cells r of (z_r + h_r - mu d_r) - z, m: the energy line's height above each cell.

    Args:
        z: (ny, nx) bed, m. cellsize: m. release: (ny, nx) release thickness, m (> 0 in the release).
        mu: Coulomb friction coefficient, -. chunk: release cells per batch (memory).
    Returns:
        (ny, nx) head, m (negative where no release cell's energy line reaches).
    """
    ny, nx = z.shape
    zt = torch.as_tensor(np.asarray(z, dtype=np.float64))
    X, Y = torch.meshgrid(torch.arange(nx, dtype=torch.float64) * cellsize,
                          torch.arange(ny, dtype=torch.float64) * cellsize, indexing="xy")
    rr, cc = np.nonzero(np.asarray(release) > 0)
    if rr.size == 0:
        raise ValueError("energy_line_head: the release has no cell with a positive thickness")
    top = torch.as_tensor(np.asarray(z, dtype=np.float64)[rr, cc] + np.asarray(release, dtype=np.float64)[rr, cc])
    xr, yr = torch.as_tensor(cc * cellsize, dtype=torch.float64), torch.as_tensor(rr * cellsize, dtype=torch.float64)
    best = torch.full((ny, nx), -torch.inf, dtype=torch.float64)
    for a in range(0, rr.size, chunk):
        s = slice(a, a + chunk)
        d = torch.sqrt((X[None] - xr[s, None, None]) ** 2 + (Y[None] - yr[s, None, None]) ** 2)
        best = torch.maximum(best, (top[s, None, None] - mu * d).amax(dim=0))
    return (best - zt).numpy()


def energy_line_speed(z: np.ndarray, cellsize: float, release: np.ndarray, mu: float,
                      h_max: np.ndarray) -> np.ndarray:
    """sqrt(2 g (energy_line_head + h_max)), m/s (0 where negative): the largest speed a flow may reach
    at each cell (docs/verification.md, case 7)."""
    head = energy_line_head(z, cellsize, release, mu) + np.asarray(h_max, dtype=np.float64)
    return np.sqrt(2.0 * G * np.clip(head, 0.0, None))


def free_fall_speed(z: np.ndarray, release: np.ndarray) -> np.ndarray:
    """sqrt(2 g (top of the release - z)), m/s: free fall from the release's highest surface point."""
    rel = np.asarray(release, dtype=np.float64)
    top = float((np.asarray(z) + rel)[rel > 0].max())
    return np.sqrt(2.0 * G * np.clip(top - np.asarray(z, dtype=np.float64), 0.0, None))
