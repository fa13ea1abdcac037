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


def plot_outlines(dem: DEM, mapped: np.ndarray, outlines: dict, path, *, title: str = "", dpi: int = 110,
                  background=None, labels: list | None = None) -> Path:
    """Save a PNG of a mapped footprint against simulated ones over the hillshade: the mapped cells (bool
    (ny, nx)) filled grey with a black outline, each of ``outlines`` {label: bool (ny, nx)} outlined in its
    own colour, and the cells reached but not mapped hatched per outline, so that what a run wets outside the
    map is as visible as what it misses. ``background``: (array, extent) of a finer hillshade to draw
    instead of the DEM's; ``labels``: [(x, y, text)] written there (e.g. the numbers of mismatch clusters). The
    view is cut to the cells shown, with a margin of 5 cells."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xmin, ymin, xmax, ymax = dem.extent
    extent = (xmin, xmax, ymin, ymax)
    shown = np.asarray(mapped, bool).copy()
    for m in outlines.values():
        shown |= np.asarray(m, bool)
    rows, cols = np.nonzero(shown) if shown.any() else (np.array([0, dem.ny - 1]), np.array([0, dem.nx - 1]))
    x0, x1 = dem.xll + (cols.min() - 5) * dem.cellsize, dem.xll + (cols.max() + 6) * dem.cellsize
    y0, y1 = dem.yll + (rows.min() - 5) * dem.cellsize, dem.yll + (rows.max() + 6) * dem.cellsize
    fig, ax = plt.subplots(figsize=(6.5, max(3.0, 6.5 * (y1 - y0) / max(x1 - x0, 1.0))))
    if background is not None:
        ax.imshow(background[0], cmap="gray", origin="lower", extent=background[1])
    else:
        ax.imshow(hillshade(dem.z, dem.cellsize), cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1)
    xc, yc = dem.x_centres(), dem.y_centres()
    ax.imshow(np.ma.masked_where(~np.asarray(mapped, bool), np.ones(dem.shape)), cmap="Greys", vmin=0, vmax=2.5,
              origin="lower", extent=extent, alpha=0.55)
    ax.contour(xc, yc, np.asarray(mapped, float), levels=[0.5], colors="black", linewidths=1.6)
    handles = [plt.Line2D([], [], color="black", lw=1.6, label=f"mapped ({int(np.sum(mapped))} cells)")]
    colours = ["tab:red", "tab:blue", "tab:orange", "tab:green"]
    for (name, m), c in zip(outlines.items(), colours):
        m = np.asarray(m, bool)
        ax.contour(xc, yc, m.astype(float), levels=[0.5], colors=c, linewidths=1.3)
        outside = m & ~np.asarray(mapped, bool)
        ax.contourf(xc, yc, outside.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"])
        handles.append(plt.Line2D([], [], color=c, lw=1.3, label=f"{name} ({int(m.sum())} cells, "
                                  f"{int(outside.sum())} outside the map)"))
    for x, y, text in labels or ():
        ax.annotate(text, (x, y), ha="center", va="center", fontsize=8, fontweight="bold",
                    bbox=dict(boxstyle="circle,pad=0.2", fc="yellow", alpha=0.8))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(handles=handles, loc="best", fontsize=7)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi)
    plt.close(fig)
    return path
