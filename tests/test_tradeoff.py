"""The run-out measured on a survey, and what a model cannot meet together (torchslide.tradeoff): the pairs
of data no run fits at once with their numbers, in posterior.json and on stderr, and the front figure."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchslide.cli import main
from torchslide.config import ConfigError
from torchslide.evaluator import RunRecord
from torchslide.observe import runout_length, runout_reach
from torchslide.terrain.grid import DEM
from torchslide.terrain.io import write_asc

from .conftest import CALIBRATE_BASE as BASE, CALIBRATE_CAL as CAL, CALIBRATE_PRIOR as PRIOR, write_config as write


def _result(h: np.ndarray, cellsize: float = 10.0):
    dem = DEM(np.zeros(h.shape[-2:]), cellsize)
    return SimpleNamespace(h_max=torch.as_tensor(h, dtype=torch.float64), dem=dem)


def test_the_run_out_is_continuous_in_the_front_and_the_sharp_one_at_the_threshold():
    """Cells along x (10 m): the farthest cell at the threshold gives its distance, as the sharp run-out does; a
    thinner film beyond adds less than its distance, and the value grows continuously as it thickens."""
    d = (np.arange(12) + 0.5) * 10.0
    h = np.zeros((1, 3, 12))                          # the flow in the middle row of three
    h[0, 1, :6] = 1.0
    h[0, 1, 5] = 0.1                                  # the front cell exactly at the threshold 0.1
    r = _result(h)
    dist = np.tile(d, (3, 1))
    assert float(runout_reach(r, dist, 0.1)[0]) == pytest.approx(d[5])
    assert float(runout_length(r, [[0.0, 15.0], [120.0, 15.0]], 0.09)[0]) == pytest.approx(d[5])
    values = []
    for film in np.linspace(0.0, 0.2, 401):           # the next cell's h_max grows through the threshold
        h[0, 1, 6] = film
        values.append(float(runout_reach(_result(h), dist, 0.1)[0]))
    steps = np.diff(values)
    assert values[0] == pytest.approx(d[5]) and values[-1] > d[6] and np.all(steps >= -1e-12)
    assert steps.max() < 0.1 * 10.0                   # no jump of a cell: it moves with the front


def _plane_case(tmp_path):
    """The conftest plane, its DEM as a file, and a DoD-like map: 1 on the cells x < 700 m of the middle rows."""
    assert main(["simulate", str(write(tmp_path, BASE)), "--out", str(tmp_path / "t"), "--quiet"]) == 0
    from torchslide.config import load_config

    cfg = load_config(write(tmp_path, BASE))
    dem = cfg.terrain.dem
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    m = np.where((X < 700.0) & (np.abs(Y - 150.0) < 60.0), 1.0, np.nan)
    write_asc(tmp_path / "map.asc", m, dem)
    return cfg, m


def test_a_run_out_observation_measured_on_a_map_from_the_crown_or_along_a_path(tmp_path):
    from torchslide.calibration_config import load_calibration_config
    from torchslide.survey import crown_point

    cfg, m = _plane_case(tmp_path)
    dem = cfg.terrain.dem
    obs = '[[observations]]\nkind = "runout_length"\nmap = "map.asc"\nsigma = 20.0\nthreshold = 0.1\n'
    c = load_calibration_config(write(tmp_path, BASE + PRIOR + obs + CAL))
    o = c.extra["observations"][0]
    x0, y0 = crown_point(dem, cfg.terrain.release)
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    assert (o.x, o.y) == (x0, y0) and o.name == "runout"
    assert o.value == pytest.approx(np.hypot(X - x0, Y - y0)[np.isfinite(m)].max())
    path = '[[paths]]\nname = "down"\npoints = [[0.0, 150.0], [1200.0, 150.0]]\n'
    c = load_calibration_config(write(tmp_path, BASE + path + PRIOR + obs.replace("sigma", 'path = "down"\nsigma') + CAL))
    assert c.extra["observations"][0].value == pytest.approx(X[np.isfinite(m)].max())
    with pytest.raises(ConfigError, match="not both"):
        load_calibration_config(write(tmp_path, BASE + PRIOR + obs.replace("sigma", "value = 500.0\nsigma") + CAL))
    write_asc(tmp_path / "empty.asc", np.full(dem.shape, np.nan), dem)
    with pytest.raises(ConfigError, match="observation 1"):
        load_calibration_config(write(tmp_path, BASE + PRIOR + obs.replace("map.asc", "empty.asc") + CAL))


class _Ev:
    """The parts of an evaluator conflicts() reads: two scalar observations a (value 10 +- 1) and b (100 +- 5)."""

    names = ["mu"]
    data_recorded = np.array([10.0, 100.0])
    blocks = [SimpleNamespace(name=n, start=i, is_vector=False, obs=SimpleNamespace(spec=SimpleNamespace(unit=u)))
              for i, (n, u) in enumerate((("a", "m"), ("b", "m^2")))]

    def observation_sd(self):
        return np.array([1.0, 5.0])


def test_the_pairs_no_run_meets_together_are_named_with_their_numbers():
    from torchslide.tradeoff import conflicts, lines

    recs = [RunRecord(np.array([0.1]), np.array([10.2, 160.0]), -3.0, False),    # meets a, misses b by +12 sigma
            RunRecord(np.array([0.2]), np.array([4.0, 101.0]), -5.0, False),     # meets b, misses a by -6 sigma
            RunRecord(np.array([0.3]), np.array([9.5, 180.0]), -9.0, False),
            RunRecord(np.array([0.4]), np.array([np.nan, np.nan]), 0.0, True, "failed")]
    c = conflicts(recs, _Ev())
    (p,) = c["pairs"]
    assert c["n_runs"] == 3 and not c["unmet"]
    assert p["best_meeting_a"] == {"x": {"mu": 0.1}, "value_b": 160.0, "miss_b_sigma": pytest.approx(12.0)}
    assert p["best_meeting_b"]["x"] == {"mu": 0.2} and p["best_meeting_b"]["miss_a_sigma"] == pytest.approx(-6.0)
    assert lines(c) == [p["sentence"]] and "gives b = 160 m^2 (recorded 100 m^2 +- 5 m^2, +12.0 sigma)" in p["sentence"]
    recs.append(RunRecord(np.array([0.5]), np.array([10.5, 98.0]), -1.0, False))  # one run meets both: no conflict
    assert conflicts(recs, _Ev())["pairs"] == []
    far = [RunRecord(np.array([0.1]), np.array([30.0, 100.0]), -3.0, False)]
    (u,) = conflicts(far, _Ev())["unmet"]
    assert u["name"] == "a" and u["miss_sigma"] == pytest.approx(20.0) and "no run of 1 meets a" in lines(conflicts(far, _Ev()))[0]


def test_calibrate_reports_what_it_cannot_meet_together(tmp_path, capsys):
    """On the plane: an impact area that needs a long run and a run-out that needs a short one (both recorded
    within 10 % of runs at opposite ends of the prior): posterior.json's tradeoffs name the pair, stderr says
    it, and the learnt discrepancy is reported per observation."""
    obs = ('[[observations]]\nkind = "impact_area"\nname = "area"\nvalue = 3.0e5\nsigma = 1.0e4\nthreshold = 0.5\n\n'
           '[[observations]]\nkind = "runout_length"\nname = "runout"\nx = 250.0\ny = 150.0\nvalue = 150.0\n'
           'sigma = 15.0\nthreshold = 0.5\n')
    out = tmp_path / "cal"
    capsys.readouterr()
    assert main(["calibrate", str(write(tmp_path, BASE + PRIOR + obs + CAL)), "--out", str(out), "--quiet"]) == 0
    post = json.loads((out / "posterior.json").read_text())
    err = capsys.readouterr().err
    pairs = post["tradeoffs"]["pairs"] + post["tradeoffs"]["unmet"]
    assert pairs and any("no run" in line for line in err.splitlines())
    assert [d["observation"] for d in post["discrepancy"]["at_best_run"]] == ["area", "runout"]
    assert post["discrepancy"]["model"] == "learnt"


def test_the_front_and_outline_figures(tmp_path):
    from torchslide.figures import plot_front
    from torchslide.mapplots import plot_outlines

    f = {"footprint": "dod", "runout_m": [100.0, 400.0, 800.0], "share_of_reached_unmapped": [0.3, 0.5, 0.6],
         "mapped_runout_m": 786.0, "x": [[0.3], [0.2], [0.1]], "jaccard": [0.3, 0.4, 0.4]}
    assert plot_front(f, tmp_path / "front.png", draws=f, peers={"peer": (757.0, 0.37)}).stat().st_size > 5000
    dem = DEM(np.add.outer(np.arange(20.0), np.arange(30.0)), 10.0)
    mapped = np.zeros(dem.shape, bool)
    mapped[5:10, 5:20] = True
    reached = np.zeros(dem.shape, bool)
    reached[4:12, 3:12] = True
    assert plot_outlines(dem, mapped, {"run": reached}, tmp_path / "o.png").stat().st_size > 5000


def test_the_diagnosis_report_says_what_the_baseline_cannot_meet_together():
    from torchslide.diagnose.report import _tradeoff_section
    from torchslide.tradeoff import conflicts

    recs = [RunRecord(np.array([0.1]), np.array([10.2, 160.0]), -3.0, False),
            RunRecord(np.array([0.2]), np.array([4.0, 101.0]), -5.0, False)]
    sec = _tradeoff_section(conflicts(recs, _Ev()))
    assert sec[0] == "## What the baseline cannot meet together" and any("no run meets a and b together" in x for x in sec)
    assert _tradeoff_section(None) == [] and _tradeoff_section(conflicts([], _Ev())) == []


def test_the_mismatches_a_modeller_sees_a_lobe_outside_the_map_and_a_short_run_out():
    """A mapped path 3 cells wide down x, runs that stop half way and spill a lobe beside the upper path: the
    excess lobe and the unreached lower path are found with their cells, boxes, distances from the crown and
    where they meet the mapped path, and the run-out's shortfall is the runs' median minus the mapped run-out."""
    from torchslide.survey import mismatch_clusters, mismatch_line, runout_mismatch

    dem = DEM(np.add.outer(np.zeros(20), -np.arange(40.0)), 10.0)
    release = np.zeros(dem.shape)
    release[9:12, 0:2] = 1.0
    mapped = np.zeros(dem.shape, bool)
    mapped[9:12, :36] = True
    p = np.zeros(dem.shape)
    p[9:12, :18] = 0.9                      # reached down to x = 180 m
    p[13:17, 5:10] = 0.8                    # a lobe of 20 cells off the map, beside the upper path
    dz = np.where(mapped, 1.0, np.nan)
    got = mismatch_clusters(p, mapped, dem, release, h_p50=np.where(p > 0, 0.5, 0.0), survey_dz=dz)
    kinds = {m["what"].split(":")[0]: m for m in got}
    assert set(kinds) == {"excess", "deficit"} and len(got) == 2
    lobe, short = kinds["excess"], kinds["deficit"]
    assert lobe["n_cells"] == 20 and lobe["area_m2"] == 2000.0 and lobe["box"] == [50.0, 130.0, 100.0, 170.0]
    assert lobe["volume_m3"] == pytest.approx(20 * 0.5 * 100.0) and lobe["score"] == pytest.approx(20 * 0.6)
    assert short["n_cells"] == 3 * 18 and short["box"][0] == 180.0 and short["volume_m3"] == pytest.approx(54 * 100.0)
    assert short["from_crown_m"][0] >= 170.0 and short["from_crown_m"][1] == pytest.approx(np.hypot(35 - 1, 1) * 10, rel=0.05)
    # the lobe leaves the path beside its upper cells (x 50 m: the path's centre there is y 105 m), the unreached
    # path starts where the runs stop (x 180 m), each with its distance along the path from the crown (x 5 m)
    assert lobe["path_point"]["x"] == pytest.approx(55.0, abs=10.0) and lobe["path_point"]["y"] == pytest.approx(105.0, abs=6.0)
    assert short["path_point"]["x"] == pytest.approx(185.0, abs=10.0)
    assert short["path_point"]["along_m"] == pytest.approx(short["path_point"]["x"] - 5.0, abs=10.0)
    assert "meets the mapped path" in mismatch_line(short)
    r = runout_mismatch(np.array([170.0, 175.0, 180.0]), 355.0)
    assert r["what"] == "run-out shortfall" and r["difference_m"] == pytest.approx(-180.0)
    assert r["interval_m"][0] < -180.0 < r["interval_m"][1] < 0


def test_the_diagnosis_finds_a_known_lobe_and_a_known_shortfall_on_the_map(tmp_path, monkeypatch):
    """The plane's run (mu 0.2) against a map made from it with a known lobe taken off (the upper path's cells
    on one side: excess) and a strip added beyond its front (deficit, 3 cells longer): the baseline's runs
    through diagnose.predictive.map_mismatches find both clusters with their cells and the run-out's shortfall
    of three cells; report.md lists them and draws outlines.png."""
    from torchslide.calibration_config import load_calibration_config, make_evaluator
    from torchslide.diagnose.predictive import map_mismatches
    from torchslide.diagnose.report import _mismatch_section, write_figures
    from torchslide.terrain.io import read_asc_array

    assert main(["simulate", str(write(tmp_path, BASE)), "--out", str(tmp_path / "t"), "--quiet"]) == 0
    h = read_asc_array(tmp_path / "t" / "h_max.asc")[0]
    from torchslide.config import load_config

    dem = load_config(write(tmp_path, BASE)).terrain.dem
    reached = h > 0.5
    rows, cols = np.nonzero(reached)
    lobe = reached & (np.arange(dem.nx)[None, :] <= cols.min() + 3) & (np.arange(dem.ny)[:, None] >= rows.max() - 1)
    front = cols.max()
    strip = np.zeros(dem.shape, bool)
    strip[rows.min() + 1:rows.max(), front + 1:front + 4] = True     # 3 cells beyond the front, within the width
    mapped = (reached & ~lobe) | strip
    write_asc(tmp_path / "map.asc", mapped.astype(float), dem)
    obs = '[[observations]]\nkind = "footprint"\nfile = "map.asc"\nsigma = 0.3\nthreshold = 0.5\n'
    ev = make_evaluator(load_calibration_config(write(tmp_path, BASE + PRIOR + obs + CAL)))
    m = map_mismatches(ev, np.tile([0.2, 1000.0], (3, 1)))
    excess = [c for c in m["clusters"] if c["what"].startswith("excess")]
    deficit = [c for c in m["clusters"] if c["what"].startswith("deficit")]
    assert len(excess) == 1 and excess[0]["n_cells"] == lobe.sum() >= 3
    assert len(deficit) == 1 and deficit[0]["n_cells"] == strip.sum()
    assert deficit[0]["box"][0] == dem.xll + (front + 1) * dem.cellsize
    assert m["runout"]["what"] == "run-out shortfall" and m["n_runs"] == 3
    assert m["path_width"]["n_rings"] > 5 and m["path_width"]["median_cells"] >= 3
    assert -3.5 * dem.cellsize < m["runout"]["difference_m"] < -2.5 * dem.cellsize
    sec = _mismatch_section(m)
    assert sec[0] == "## Where the baseline and the map differ" and any("run-out shortfall" in x for x in sec)
    assert sorted(x.split(". ", 1)[1].split(":")[0] for x in sec if x[:1].isdigit()) == ["deficit", "excess"]
    d = SimpleNamespace(mismatches=m, evaluator=ev, localisation=SimpleNamespace(maps={}, located=[]),
                        after_localisation=None, refits={})
    assert "outlines.png" in write_figures(d, tmp_path) and (tmp_path / "outlines.png").stat().st_size > 5000

    def every_run_failed(*args, **kwargs):
        raise RuntimeError("all 3 posterior-predictive runs failed; first: unstable")

    monkeypatch.setattr("torchslide.predict.run_predictive", every_run_failed)   # a line, not an exception
    failed = map_mismatches(ev, np.tile([0.2, 1000.0], (3, 1)))
    assert failed == {"failed": "all 3 posterior-predictive runs failed; first: unstable"}
    assert _mismatch_section(failed)[2] == "Not measured: all 3 posterior-predictive runs failed; first: unstable."
    assert map_mismatches(make_evaluator(load_calibration_config(write(tmp_path, BASE + PRIOR + CAL.replace(
        "[calibration]", '[[observations]]\nkind = "impact_area"\nvalue = 1e5\nsigma = 1e4\n\n[calibration]')))),
        np.tile([0.2, 1000.0], (2, 1))) == {}


@pytest.mark.parametrize("width, narrow", [(2, True), (6, False)])
def test_whether_the_grid_holds_the_mapped_path(width, narrow):
    """A straight mapped channel ``width`` cells across below a release: its width in cells, and the sentence
    says the DEM does not resolve it only where it is narrower than three cells."""
    from torchslide.survey import path_width, width_line

    dem = DEM(np.add.outer(np.zeros(30), -np.arange(60.0)), 10.0)
    release = np.zeros(dem.shape)
    release[12:18, 0:4] = 1.0
    mapped = release > 0
    mapped[15 - width // 2:15 - width // 2 + width, 4:50] = True
    w = path_width(mapped, dem, release)
    assert w["median_cells"] == pytest.approx(width, abs=0.5) and w["cellsize_m"] == 10.0
    assert (w["share_narrower"] > 0.9) == narrow and (w["share_narrower"] < 0.1) == (not narrow)
    assert ("does not resolve the channel" in width_line(w)) == narrow
