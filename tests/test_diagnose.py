"""torchslide.diagnose: localisation pieces, decision rules, CLI bad input (exit 2), and a tiny blind harness."""
from __future__ import annotations


import numpy as np
import pytest

from torchslide.cli import main
from torchslide.diagnose.decide import Thresholds, decide
from torchslide.diagnose.localise import arrival_shift, benjamini_hochberg, map_clusters
from torchslide.terrain import DEM
from torchslide.terrain.io import write_asc


def test_benjamini_hochberg():
    p = np.array([0.001, 0.2, 0.01, 0.04, 0.9])
    assert benjamini_hochberg(p, 0.05).tolist() == [True, False, True, False, False]


def test_map_cluster_bbox_in_map_coordinates():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((20, 30))
    z[5:9, 10:15] += 5.0
    dem = DEM(z=np.zeros((20, 30)), cellsize=10.0, xll=1000.0, yll=500.0)
    cl, _ = map_clusters(z, np.ones_like(z, bool), dem, radius=1, n_perm=99)
    assert cl and cl[0].sign == 1
    x0, y0, x1, y1 = cl[0].bbox
    assert 1080 <= x0 <= 1100 and 1150 <= x1 <= 1170 and 530 <= y0 <= 550 and 590 <= y1 <= 610


def test_arrival_shift():
    t = np.arange(0, 60, 1.0)
    y = np.exp(-((t - 20) / 4) ** 2)
    d = np.exp(-((t - 26) / 4) ** 2)
    assert abs(arrival_shift(t, d, y) - 6.0) <= 0.5


def test_decide_rules():
    th = Thresholds()
    cands = [{"name": "entrainment", "log_bayes_factor": 20.0}, {"name": "curvature", "log_bayes_factor": 1.0}]
    big = [{"standardised_residual": 12.0}]
    d = decide(cands, big, {"entrainment": []}, 100.0, {"entrainment": 50.0}, th)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "entrainment" and not d["ambiguous"]
    d = decide(cands, big, {"entrainment": big}, 100.0, {"entrainment": 50.0}, th)  # still mismatched after refit
    assert d["verdict"] == "unexplained" and d["missing_physics"] is None
    weak = [{"name": "entrainment", "log_bayes_factor": 1.0}]
    assert decide(weak, big, {}, 100.0, {}, th)["verdict"] == "unexplained"
    assert decide(weak, [], {}, 100.0, {}, th)["verdict"] == "no_missing_physics"


# ------------------------------------------------------------------------------------------------ CLI
BASE = """
[terrain]
synthetic = "inclined_plane"
cellsize = 50.0
options = {{ theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }}
release = {{ centre = [250.0, 150.0], radii = [120.0, 100.0], volume = 1.0e5 }}

[model]
rheology = "voellmy"
mu = 0.2
xi = 1000.0

[run]
t_end = 60.0

[[gauges]]
name = "G1"
x = 475.0
y = 150.0

[prior]
mu = [0.05, 0.5]
xi = [200.0, 2000.0]

[[observations]]
kind = "gauge_series"
file = "g1.csv"
gauge = "G1"
sigma = {{ h = 0.5, speed = 2.0 }}

[[observations]]
kind = "deposit_map"
file = "dep.asc"
sigma = 0.5

[diagnose]
candidates = {candidates}
"""


def _setup(tmp_path, csv="t,h,speed\n1,0,0\n2,1,3\n3,2,4\n", grid=(6, 24), candidates='["entrainment", "mu_i"]'):
    from torchslide.terrain.synthetic import inclined_plane
    (tmp_path / "g1.csv").write_text(csv)
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    other = DEM(z=np.zeros(grid), cellsize=50.0)
    write_asc(tmp_path / "dep.asc", np.zeros(grid), other)
    p = tmp_path / "diag.toml"
    p.write_text(BASE.format(candidates=candidates))
    return p, dem


@pytest.mark.parametrize("case", ["times", "grid", "candidate"])
def test_cli_bad_input_exit_2(tmp_path, capsys, case):
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    kw = {"grid": dem.shape}
    if case == "times":
        kw["csv"] = "t,h,speed\n1,0,0\n3,1,3\n2,2,4\n"
    elif case == "grid":
        kw["grid"] = (dem.shape[0] + 1, dem.shape[1])
    else:
        kw["candidates"] = '["entrainment", "dark_matter"]'
    p, _ = _setup(tmp_path, **kw)
    rc = main(["diagnose", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert not (tmp_path / "out").exists()
    if case == "times":
        assert "g1.csv" in err and "row 4" in err and "increase strictly" in err
    elif case == "grid":
        assert "dep.asc" in err and f"{dem.shape[0] + 1}x{dem.shape[1]}" in err and f"{dem.shape[0]}x{dem.shape[1]}" in err
    else:
        assert "dark_matter" in err and "unknown candidate" in err


# ---------------------------------------------------------------------------------- small blind harness
def test_small_harness(tmp_path):
    """Null + entrainment on the coarse channel with tiny budgets: runs end to end, writes reports,
    and the screening ranks entrainment first where entrainment is hidden."""
    from experiments.hidden_physics.harness import run_case
    from experiments.hidden_physics.make_page import build_page

    bud = dict(n_posterior_samples=8, n_posterior_samples_after=4, n_initial=6, n_total=8, baseline_n_initial=6,
               baseline_n_total=8, batch_size=8, top_k=1, n_perm=19, mcmc_steps=200)
    cands = ["entrainment", "yield_stress", "mu_i"]
    out = tmp_path / "res"
    cases = {sc: run_case(sc, 0, out, budgets=bud, candidates=cands, log=lambda s: None) for sc in ("null", "entrainment")}
    for sc, c in cases.items():
        j = c["diagnosis"]
        assert j["verdict"] in ("missing_physics", "no_missing_physics", "unexplained")
        for key in ("missing_physics", "located", "candidates", "fit_before", "fit_after"):
            assert key in j
        for cand in j["candidates"]:
            assert {"name", "log_evidence", "log_bayes_factor", "screening_score", "parameters"} <= set(cand)
    assert cases["entrainment"]["diagnosis"]["screening"]["ranking"][0] == "entrainment"
    assert cases["null"]["diagnosis"]["missing_physics"] != "yield_stress"
    page = build_page(out, tmp_path / "page")
    assert "Confusion matrix" in page.read_text()
