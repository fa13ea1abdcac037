"""Figures like the paper's Fig. 3 (posterior map with design points) and Fig. 4 (TV against runs).
PNG via the matplotlib Agg backend."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from matplotlib.ticker import MaxNLocator  # noqa: E402

from .files import save_figure  # noqa: E402
from .physics import label  # noqa: E402
from .posterior import hdr_mask  # noqa: E402


def plot_posterior(result, path, truth=None, names=None, level: float = 0.9, title: str | None = None):
    """Fig. 3: pcolormesh of the grid posterior, initial points (black circles), adaptive points
    (red diamonds), the truth (black cross) when known, and the `level` HDR contour (p = 2 only)."""
    if result.posterior_grid is None or len(result.grid_axes) != 2:
        raise ValueError("plot_posterior needs a 2-D grid posterior")
    a0, a1 = result.grid_axes
    dens = result.posterior_grid
    names = names or result.names
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    pc = ax.pcolormesh(a0, a1, dens.T, shading="nearest", cmap="viridis")
    fig.colorbar(pc, ax=ax, label="posterior density")
    mask = hdr_mask(dens, level)
    ax.contour(a0, a1, mask.T.astype(float), levels=[0.5], colors="white", linewidths=1.0)
    x = np.asarray(result.x).reshape(-1, 2)
    ok = ~np.asarray(result.failed, dtype=bool)
    init = np.arange(len(x)) < result.n_initial
    for sel, style, lab in ((init & ok, dict(marker="o", mfc="none", mec="black", ms=5), "initial"),
                            (~init & ok, dict(marker="D", color="red", ms=4), "adaptive"),
                            (~ok, dict(marker="x", color="orange", ms=6), "failed")):
        if sel.any():      # a legend entry only for what is drawn
            ax.plot(x[sel, 0], x[sel, 1], ls="none", label=lab, **style)
    if truth is not None:
        ax.plot([truth[0]], [truth[1]], "+", color="black", ms=14, mew=2.5, label="truth")
    ax.set_xlabel(label(names[0]))
    ax.set_ylabel(label(names[1]))
    ax.set_xlim(result.bounds[0, 0], result.bounds[1, 0])
    ax.set_ylim(result.bounds[0, 1], result.bounds[1, 1])
    ax.set_title(title or f"posterior after {len(x)} runs ({int(level * 100)} % HDR in white)", fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 120)
    plt.close(fig)
    return Path(path)


def plot_posterior_any(result, path, truth=None, names=None, level: float = 0.9, title: str | None = None):
    """The posterior figure for any number p of calibrated parameters: Fig. 3 for p = 2
    (:func:`plot_posterior`), the grid density with its ``level`` HDR shaded for p = 1, and for p > 2 a
    corner plot of the MCMC samples (1-D histograms on the diagonal with the equal-tailed ``level``
    interval, 2-D histograms below it with the runs as dots). ``truth``: (p,) values or None."""
    names = list(names or result.names)
    p = len(names)
    if p == 2 and result.posterior_grid is not None:
        return plot_posterior(result, path, truth=truth, names=names, level=level, title=title)
    x = np.asarray(result.x)
    ok = ~np.asarray(result.failed, dtype=bool)
    b = np.asarray(result.bounds, dtype=float)
    if p == 1:
        if result.posterior_grid is None:
            raise ValueError("a 1-parameter calibration needs its grid posterior")
        ax0, dens = np.asarray(result.grid_axes[0]), np.asarray(result.posterior_grid)
        fig, ax = plt.subplots(figsize=(5.5, 3.6))
        ax.plot(ax0, dens, "-", color="tab:blue")
        ax.fill_between(ax0, 0, dens, where=hdr_mask(dens, level), color="tab:blue", alpha=0.3,
                        label=f"{int(level * 100)} % HDR")
        ax.plot(x[ok, 0], np.zeros(int(ok.sum())), "|", color="k", ms=10, label="runs")
        if truth is not None:
            ax.axvline(truth[0], color="k", ls="--", label="truth")
        ax.set_xlim(b[0, 0], b[1, 0])
        ax.set_xlabel(label(names[0]))
        ax.set_ylabel("posterior density")
        ax.legend(fontsize=7)
        ax.set_title(title or f"posterior after {len(x)} runs", fontsize=10)
    else:
        if result.samples is None or not len(result.samples):
            raise ValueError(f"a {p}-parameter calibration needs its MCMC samples")
        smp = np.asarray(result.samples)
        lo_q, hi_q = (1 - level) / 2, 1 - (1 - level) / 2
        fig, axes = plt.subplots(p, p, figsize=(2.3 * p, 2.3 * p), squeeze=False)
        for i in range(p):
            for j in range(p):
                ax = axes[i, j]
                if j > i:
                    ax.set_visible(False)
                    continue
                if i == j:
                    ax.hist(smp[:, i], bins=40, range=(b[0, i], b[1, i]), color="tab:blue", alpha=0.6)
                    for q in np.quantile(smp[:, i], [lo_q, hi_q]):
                        ax.axvline(q, color="tab:blue", ls=":")
                    if truth is not None:
                        ax.axvline(truth[i], color="k", ls="--")
                    ax.set_yticks([])
                else:
                    ax.hist2d(smp[:, j], smp[:, i], bins=40, range=[[b[0, j], b[1, j]], [b[0, i], b[1, i]]],
                              cmap="viridis")
                    ax.plot(x[ok, j], x[ok, i], ".", color="w", ms=2, alpha=0.7)
                    if truth is not None:
                        ax.plot([truth[j]], [truth[i]], "+", color="red", ms=10, mew=2)
                ax.set_xlim(b[0, j], b[1, j])
                if i == p - 1:
                    ax.set_xlabel(label(names[j]))
                else:
                    ax.set_xticklabels([])
                if j == 0 and i > 0:
                    ax.set_ylabel(label(names[i]))
                elif j > 0:
                    ax.set_yticklabels([])
        fig.suptitle(title or f"posterior after {len(x)} runs: MCMC samples, {int(level * 100)} % intervals "
                     "dotted, runs as white dots", fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 120)
    plt.close(fig)
    return Path(path)


def plot_tv(tv_histories: dict, path, n_initial: int | None = None, threshold: float | None = None,
            lag: int = 10):
    """Fig. 4: TV(p_i, p_{i-lag}) (Eq. 17) against the number of runs; tv_histories maps label -> [(n, tv), ...]."""
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name, hist in tv_histories.items():
        h = np.asarray(hist, dtype=float).reshape(-1, 2)
        n = h[:, 0] - (n_initial or 0)
        ax.semilogy(n, h[:, 1], "-o", ms=3, label=name)
    if threshold is not None:
        ax.axhline(threshold, color="gray", ls="--", lw=1)
    ax.set_xlabel("number of adaptive runs" if n_initial else "number of runs")
    ax.set_ylabel(rf"TV$(p_i, p_{{i-{lag}}})$")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 120)
    plt.close(fig)
    return Path(path)


def plot_predictive_check(checks: list, path):
    """Posterior-predictive check (torchslide.predict.observation_check): one row per observation, its
    recorded value (dot, +- sigma) against the 90 % interval of a new recording (bar) and the model's
    median (tick), in units of the recorded value so that rows of different kinds share an axis."""
    n = len(checks)
    fig, ax = plt.subplots(figsize=(6.5, 0.5 * n + 1.4))
    for i, c in enumerate(checks):
        scale = abs(c["value"]) if c["value"] != 0 else max(c["sigma"], 1e-12)
        lo, hi = (np.asarray(c["interval90"]) - c["value"]) / scale
        med = (c["model_quantiles"]["0.5"] - c["value"]) / scale
        colour = "tab:blue" if c["inside"] else "tab:red"
        ax.plot([lo, hi], [i, i], "-", lw=6, color=colour, alpha=0.35, solid_capstyle="butt")
        ax.plot([med], [i], "|", ms=14, mew=2, color=colour)
        ax.errorbar([0.0], [i], xerr=[[c["sigma"] / scale]], fmt="o", color="k", ms=5, capsize=3)
    ax.axvline(0.0, color="k", lw=0.5)
    ax.set_yticks(range(n))
    ax.set_yticklabels([c["name"] for c in checks], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("(prediction - recorded) / |recorded|")
    ax.set_title("recorded (dot, +- sigma); 90 % of a new recording (bar); model median (tick)", fontsize=8)
    ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 120)
    plt.close(fig)
    return Path(path)


def plot_front(front: dict, path, draws: dict | None = None, peers: dict | None = None,
               title: str | None = None):
    """The trade-off a mapped event shows: each run's run-out from the release's crown (m) against the share
    of its reached cells outside the mapped footprint (torchslide.tradeoff.front), grey; the posterior's
    draws (``draws``: the same keys) in red; the survey at (its mapped run-out, 0) as a star; ``peers``
    {name: (run-out m, share)} as labelled squares (another model's run on the same event)."""
    fig, ax = plt.subplots(figsize=(6.0, 4.3))
    ax.scatter(front["runout_m"], front["share_of_reached_unmapped"], s=14, color="0.55",
               label=f"calibration runs ({len(front['runout_m'])})")
    if draws is not None and draws.get("runout_m"):
        ax.scatter(draws["runout_m"], draws["share_of_reached_unmapped"], s=16, color="tab:red",
                   label=f"posterior draws ({len(draws['runout_m'])})")
    ax.plot([front["mapped_runout_m"]], [0.0], "*", color="black", ms=14, label="survey")
    for name, (r, share) in (peers or {}).items():
        ax.plot([r], [share], "s", color="tab:blue", ms=7)
        ax.annotate(name, (r, share), textcoords="offset points", xytext=(6, 4), fontsize=8, color="tab:blue")
    ax.set_xlabel("run-out from the release's crown (m)")
    ax.set_ylabel("share of reached cells outside the map")
    ax.set_ylim(-0.03, 1.0)
    ax.set_title(title or f"what the model can meet together (footprint: {front['footprint']})", fontsize=10)
    ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 120)
    plt.close(fig)
    return Path(path)
