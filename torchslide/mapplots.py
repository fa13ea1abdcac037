"""Map figures: a field (h_max, deposit, residual) over the hillshaded terrain, with named points."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .files import save_figure
from .terrain.fields import hillshade
from .terrain.grid import DEM


def plot_field_map(dem: DEM, field: np.ndarray, path, *, points: dict | None = None, title: str = "",
                   label: str = "h_max (m)", threshold: float = 0.0, cmap: str = "viridis",
                   vmin: float | None = None, vmax: float | None = None, dpi: int = 110,
                   release: np.ndarray | None = None) -> Path:
    """Save a PNG of ``field`` (ny, nx) over the hillshade of ``dem`` (map coordinates in m).

    Cells with |field| <= threshold are transparent; ``points`` maps names to (x, y) in m;
    ``release`` (ny, nx) thickness, m: its outline (> 0) is drawn. The colour bar is as tall as the map.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1 import make_axes_locatable

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
    if release is not None and np.any(np.asarray(release) > 0):
        ax.contour(dem.x_centres(), dem.y_centres(), (np.asarray(release) > 0).astype(float), levels=[0.5],
                   colors="red", linewidths=1.2, linestyles="--")
        ax.plot([], [], "--", color="red", lw=1.2, label="release")
        ax.legend(loc="lower right", fontsize=8)
    cax = make_axes_locatable(ax).append_axes("right", size="2.5%", pad=0.1)
    fig.colorbar(im, cax=cax, label=label)
    for name, (x, y) in (points or {}).items():
        ax.plot(x, y, "o", ms=6, mfc="w", mec="k")
        ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=9,
                    bbox=dict(boxstyle="round,pad=0.15", fc="w", alpha=0.7))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi)
    plt.close(fig)
    return path


def plot_hmax_map(dem: DEM, h_max: np.ndarray, path, *, points: dict | None = None, title: str = "",
                  threshold: float = 0.05, release: np.ndarray | None = None) -> Path:
    """h_max (m) over the hillshaded terrain with the release outlined; cells with h_max <= threshold are
    not coloured."""
    return plot_field_map(dem, h_max, path, points=points, title=title, label="h_max (m)", threshold=threshold,
                          release=release)
