"""``make demo`` end to end at a tiny size: simulate the truth, record, calibrate, check, predict, figures."""
from __future__ import annotations

import json


def test_demo_runs_end_to_end_and_copies_its_figures(tmp_path):
    from experiments import demo

    out, figs = tmp_path / "demo", tmp_path / "figures"
    rc = demo.main(["--out", str(out), "--cellsize", "150", "--t-end", "120", "--n-initial", "4", "--n-total", "6",
                    "--batch-size", "2", "--n-predictive", "2", "--figures", str(figs)])
    s = json.loads((out / "demo_summary.json").read_text())
    assert rc == (0 if s["truth_in_hdr90"] else 1)
    assert s["n_runs"] == 6 and s["n_failed"] == 0 and s["predictive"]["n_draws"] == 2
    assert 0 < s["hdr90_fraction_of_prior_box"] <= 1 and s["wall_s"] > 0
    lo, hi = s["predictive"]["v_max_L1_interval90"]
    assert lo < hi
    assert sorted(p.name for p in figs.iterdir()) == sorted(demo.FIGURES)
