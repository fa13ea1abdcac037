"""Figures of the study (small PNGs): map with L1-L3 (Fig. 2-like), posteriors (Fig. 3, 5, 6-like)
each beside its brute-force reference, and TV(p_i, p_{i-10}) (Fig. 4-like)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from mpl_toolkits.axes_grid1 import make_axes_locatable  # noqa: E402

from torchslide.physics import label  # noqa: E402

DPI = 64


def map_figure(case, h_max: np.ndarray, h_final: np.ndarray, path: Path, threshold: float = 0.5) -> Path:
    """Terrain contours, impact area (h_max > 0.5 m), deposit (h > 0.5 m) and L1-L3 (Fig. 2-like)."""
    dem = case.dem
    ny, nx = dem.z.shape
    ext = [0, nx * dem.cellsize, 0, ny * dem.cellsize]
    fig, ax = plt.subplots(figsize=(9, 3.8))
    ax.contour(np.asarray(dem.z), levels=25, colors="0.6", linewidths=0.5, extent=ext, origin="lower")
    imp = np.ma.masked_where(h_max <= threshold, np.ones_like(h_max))
    ax.imshow(imp, extent=ext, origin="lower", cmap="Oranges", vmin=0, vmax=2.5, alpha=0.6)
    dep = np.ma.masked_where(h_final <= threshold, h_final)
    im = ax.imshow(dep, extent=ext, origin="lower", cmap="viridis", alpha=0.9)
    ax.contour(np.asarray(case.release) > 0, levels=[0.5], colors="r", extent=ext, origin="lower", linewidths=1)
    if case.thalweg is not None:
        ax.plot(case.thalweg[:, 0], case.thalweg[:, 1], "k--", lw=0.6)
    for k, (x, y) in case.points.items():
        ax.plot(x, y, "k^", ms=7)
        ax.annotate(k, (x, y), xytext=(5, 6), textcoords="offset points", fontsize=10, weight="bold")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Truth run: release (red), impact area (orange, h_max > 0.5 m), deposit (h > 0.5 m)", fontsize=9)
    ax.set_aspect("equal")
    cax = make_axes_locatable(ax).append_axes("right", size="2.5%", pad=0.1)
    fig.colorbar(im, cax=cax, label="deposit height h (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _panel(ax, axes, dens, truth, title, x_init=None, x_adapt=None):
    h0, h1 = (axes[0][1] - axes[0][0]) / 2, (axes[1][1] - axes[1][0]) / 2
    ext = [axes[0][0] - h0, axes[0][-1] + h0, axes[1][0] - h1, axes[1][-1] + h1]
    ax.imshow(dens.T, origin="lower", extent=ext, aspect="auto", cmap="viridis")
    if x_init is not None:
        ax.plot(x_init[:, 0], x_init[:, 1], "o", mfc="none", mec="k", ms=4, mew=0.7)
    if x_adapt is not None and len(x_adapt):
        ax.plot(x_adapt[:, 0], x_adapt[:, 1], "D", mfc="none", mec="r", ms=3.5, mew=0.8)
    ax.plot(truth[0], truth[1], "kx", ms=9, mew=2)
    ax.set_title(title, fontsize=8)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel(label("mu"))
    ax.set_ylabel(label("xi"))


def posterior_grid_figure(panels: list[dict], truth, path: Path, ncols: int = 2, title: str = "") -> Path:
    """panels: dicts with axes, density, title, optional x_init, x_adapt."""
    n = len(panels)
    nrows = int(np.ceil(n / ncols))
    fig, axs = plt.subplots(nrows, ncols, figsize=(2.9 * ncols, 2.5 * nrows), squeeze=False)
    for ax, p in zip(axs.flat, panels):
        _panel(ax, p["axes"], p["density"], truth, p["title"], p.get("x_init"), p.get("x_adapt"))
    for ax in list(axs.flat)[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def tv_figure(histories: dict, n_initial: int, path: Path) -> Path:
    """TV(p_i, p_{i-lag}) against adaptive runs (Fig. 4-like). histories: label -> [(n_runs, tv)]."""
    fig, ax = plt.subplots(figsize=(5, 3.4))
    for name, h in histories.items():
        h = np.asarray(h, dtype=float).reshape(-1, 2)
        if len(h):
            ax.plot(h[:, 0] - n_initial, h[:, 1], "o-", label=name, ms=4)
    ax.set_yscale("log")
    ax.set_xlabel("adaptive runs $i$")
    ax.set_ylabel(r"TV$(p_i, p_{i-10})$")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
