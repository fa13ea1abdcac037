"""The figures read right: units on every parameter axis, mathtext labels, integer run ticks, legend
entries only for what is drawn, colour bars as tall as the map, the release outlined."""
from __future__ import annotations

from types import SimpleNamespace

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402


@pytest.fixture
def saved(monkeypatch):
    """The figures saved during the test (Figure.savefig still writes the file)."""
    figs = []
    real = Figure.savefig

    def keep(self, *a, **k):
        figs.append(self)
        return real(self, *a, **k)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figs


def _grid_result(n_initial=3, n=5, failed=()):
    a0, a1 = np.linspace(0.02, 0.3, 20), np.linspace(100.0, 2200.0, 20)
    dens = np.exp(-((a0[:, None] - 0.2) ** 2) / 0.002 - ((a1[None, :] - 1000) ** 2) / 2e5)
    x = np.column_stack([np.linspace(0.05, 0.25, n), np.linspace(200, 2000, n)])
    return SimpleNamespace(names=["mu", "xi"], bounds=np.array([[0.02, 100.0], [0.3, 2200.0]]), x=x,
                           failed=np.isin(np.arange(n), failed), n_initial=n_initial, grid_axes=[a0, a1],
                           posterior_grid=dens / dens.sum(), samples=None)


def test_posterior_axes_carry_units_and_the_legend_only_what_is_drawn(tmp_path, saved):
    from torchslide.figures import plot_posterior_any

    plot_posterior_any(_grid_result(), tmp_path / "a.png", truth=[0.23, 1000.0])
    ax = saved[-1].axes[0]
    assert ax.get_xlabel() == r"$\mu$ (-)" and ax.get_ylabel() == r"$\xi$ (m/s$^2$)"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["initial", "adaptive", "truth"]
    # a sweep's figure: only failed nodes are drawn, so the legend holds only them (or nothing)
    plot_posterior_any(_grid_result(n_initial=5, n=2, failed=(0, 1)), tmp_path / "b.png", title="$3^2$ runs")
    ax = saved[-1].axes[0]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["failed"] and ax.get_title() == "$3^2$ runs"
    plot_posterior_any(_grid_result(n_initial=0, n=0), tmp_path / "c.png")
    assert saved[-1].axes[0].get_legend() is None


def test_tv_figure_has_a_mathtext_label_and_integer_run_ticks(tmp_path, saved):
    from torchslide.figures import plot_tv

    plot_tv({"case": [(10, 0.3), (11, 0.1), (12, 0.05), (13, 0.01)]}, tmp_path / "tv.png")
    ax = saved[-1].axes[0]
    assert ax.get_ylabel() == r"TV$(p_i, p_{i-10})$"
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)


def test_map_colour_bar_is_as_tall_as_the_map_and_the_release_is_outlined(tmp_path, saved):
    from torchslide.mapplots import plot_hmax_map
    from torchslide.terrain.synthetic import bondo_like

    case = bondo_like(cellsize=200.0)
    h = np.where(case.release > 0, 5.0, 0.0)
    plot_hmax_map(case.dem, h, tmp_path / "h.png", points=case.points, release=case.release)
    fig = saved[-1]
    fig.canvas.draw()
    ax, cax = fig.axes
    assert abs(ax.get_position().height - cax.get_position().height) < 1e-6
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["release"]
    assert cax.get_ylabel() == "h_max (m)"
