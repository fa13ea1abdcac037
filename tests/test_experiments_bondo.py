"""experiments.bondo: Table 1 noise, Table 2 log-posteriors, and the whole pipeline in its quick
configuration (coarse terrain, 8 initial + 4 adaptive runs, 2 cases, 6 x 6 sweep), including resume."""
import json
import shutil
import time

import numpy as np
import torch

from experiments.bondo.config import CASES, DATA, OBSERVABLES, BondoConfig
from experiments.bondo.data import CaseLogPosterior, synthetic_data


def test_config_matches_paper():
    cfg = BondoConfig()
    assert cfg.truth == {"mu": 0.23, "xi": 1000.0}
    assert cfg.bounds == {"mu": (0.02, 0.3), "xi": (100.0, 2200.0)}
    assert (cfg.n_initial, cfg.n_adaptive, cfg.grid_size) == (40, 80, 100)
    assert sorted(CASES) == list(range(1, 11))
    assert CASES[9][1] == ("vmax_L1", "deposit_volume") and CASES[10][1] == ("vmax_L3", "hdep_L3")
    assert [d[2] for d in DATA if d[1] == "vmax_L1"] == [0.1, 0.2, 0.3]


def test_synthetic_data_fixed_seed_and_sigma():
    sim = {k: 10.0 + i for i, k in enumerate(OBSERVABLES)}
    a, b = synthetic_data(sim, 5), synthetic_data(sim, 5)
    assert a == b
    assert a["vmax_L1_30"]["sigma"] == 0.3 * sim["vmax_L1"]
    assert a != synthetic_data(sim, 6)


def test_case_log_posterior_uses_its_columns():
    cfg = BondoConfig.quick()
    sim = {k: 10.0 + i for i, k in enumerate(OBSERVABLES)}
    data = synthetic_data(sim, 1)
    fn = CaseLogPosterior(9, None, data, cfg)
    y = np.tile([sim[k] for k in OBSERVABLES], (2, 1)).astype(float)
    y[1, list(OBSERVABLES).index("hdep_L2")] += 100.0  # not used by case 9: same z
    z = fn.from_observables(np.array([[0.1, 500.0], [0.1, 500.0]]), y)
    assert torch.allclose(z[0], z[1])
    y[1, list(OBSERVABLES).index("deposit_volume")] *= 2  # used by case 9: lower z
    assert fn.from_observables(np.array([[0.1, 500.0], [0.1, 500.0]]), y)[1] < z[0]


def test_quick_pipeline_end_to_end(tmp_path):
    from experiments.bondo.report import write_readme
    from experiments.bondo.simulator import CachedSimulator
    from experiments.bondo.study import run_active, run_study

    cfg = BondoConfig.quick(str(tmp_path), tensorboard=True)
    t0 = time.perf_counter()
    res = run_study(cfg)
    wall = time.perf_counter() - t0
    rd = cfg.run_dir
    saved = json.loads((rd / "results.json").read_text())
    assert set(saved["cases"]) == {"1", "10"}
    assert set(saved["table1"]["data"]) == {d[0] for d in DATA}
    for c, e in saved["cases"].items():
        assert e["n_runs"] == cfg.n_total
        assert set(e["tv_ref"]) == {str(k) for k in cfg.snapshots}
        assert all(0.0 <= v <= 1.0 for v in e["tv_ref"].values())
        assert 0.0 <= e["tv_ref_lhs_only"] <= 1.0
        assert isinstance(e["truth_in_hdr90"], bool)
        p = np.load(rd / f"case_{c}" / "posteriors.npz")
        assert p["reference"].shape == (cfg.grid_size, cfg.grid_size)
        np.testing.assert_array_equal(p["x"][:cfg.n_initial], np.load(rd / "case_1" / "posteriors.npz")["x"][:cfg.n_initial])
        assert any((rd / "tb" / f"case_{c}").iterdir())
    # all cases share the initial runs: distinct simulations = truth + 8 initial + 12 LHS + 2 x 4 adaptive
    assert res["timing"]["n_simulations_cached"] <= 1 + 8 + 12 + 2 * 4
    readme = write_readme(rd, rd / "README.md", rd / "figures")
    text = readme.read_text()
    assert "Table 1" in text and "| 10 |" in text and "TV ref" in text
    for f in ("map.png", "fig3_case1_7_8.png", "fig4_tv.png", "fig6_cases_9_10.png"):
        assert (rd / "figures" / f).stat().st_size < 300_000
    # resume: a second run does no new solver call
    sim = CachedSimulator(cfg, rd / "cache.npz")
    n_before = len(sim)
    res2 = run_study(cfg)
    assert res2["timing"]["solver_calls"] == 0 and res2["timing"]["n_simulations_cached"] == n_before
    assert res2["cases"]["1"]["tv_ref"] == res["cases"]["1"]["tv_ref"]
    # the cases' GPs in worker processes pick the same points (the simulations come from a copy of the cache)
    par = cfg.with_(workers=2, work_dir=str(tmp_path / "workers"), tensorboard=False)
    par.run_dir.mkdir(parents=True)
    shutil.copy(rd / "cache.npz", par.run_dir / "cache.npz")
    res3 = run_active(par, CachedSimulator(par, par.run_dir / "cache.npz"),
                      {c: CaseLogPosterior(c, sim, saved["table1"]["data"], par) for c in par.cases})
    for c in par.cases:
        np.testing.assert_array_equal(res3[c]["state"].x.numpy(), np.load(rd / f"case_{c}" / "posteriors.npz")["x"])
    print(f"quick pipeline wall time {wall:.1f} s")
