"""Map figures: a field (h_max, deposit, residual) over the hillshaded terrain, with named points."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .terrain.fields import hillshade
from .terrain.grid import DEM


def plot_field_map(dem: DEM, field: np.ndarray, path, *, points: dict | None = None, title: str = "",
                   label: str = "h_max (m)", threshold: float = 0.0, cmap: str = "viridis",
                   vmin: float | None = None, vmax: float | None = None, dpi: int = 110) -> Path:
    """Save a PNG of ``field`` (ny, nx) over the hillshade of ``dem`` (map coordinates in m).

    Cells with |field| <= threshold are transparent; ``points`` maps names to (x, y) in m.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    field = np.asarray(field, dtype=float)
    if field.shape != dem.shape:
        raise ValueError(f"field shape {field.shape} does not match the DEM {dem.shape}")
    xmin, ymin, xmax, ymax = dem.extent
    extent = (xmin, xmax, ymin, ymax)
    aspect = (ymax - ymin) / (xmax - xmin)
    fig, ax = plt.subplots(figsize=(9, max(2.5, 9 * aspect + 1.0)))
    ax.imshow(hillshade(dem.z, dem.cellsize), cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1)
    ax.contour(dem.x_centres(), dem.y_centres(), dem.z, levels=15, colors="k", linewidths=0.3, alpha=0.4)
    shown = np.ma.masked_where(np.abs(field) <= threshold, field)
    im = ax.imshow(shown, cmap=cmap, origin="lower", extent=extent, alpha=0.85, vmin=vmin, vmax=vmax)
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)
    for name, (x, y) in (points or {}).items():
        ax.plot(x, y, "o", ms=6, mfc="w", mec="k")
        ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=9,
                    bbox=dict(boxstyle="round,pad=0.15", fc="w", alpha=0.7))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_hmax_map(dem: DEM, h_max: np.ndarray, path, *, points: dict | None = None, title: str = "",
                  threshold: float = 0.05) -> Path:
    """h_max (m) over the hillshaded terrain; cells with h_max <= threshold are not coloured."""
    return plot_field_map(dem, h_max, path, points=points, title=title, label="h_max (m)", threshold=threshold)
