"""``make demo``: a real calibration on the embedded Bondo-like case, through the command line.

1. ``torchslide simulate`` runs the truth (mu = 0.23, xi = 1000 m/s^2) on the Bondo-like terrain and
   writes its maps; a PNG shows h_max over the hillshaded terrain with L1-L3.
2. The synthetic recording: maximum velocity at L1 with 10 % Gaussian noise (fixed seed), sigma = 10 %.
3. ``torchslide calibrate`` calibrates (mu, xi) on the prior box of the paper by Bayesian active
   learning and writes the posterior (JSON, NPZ, figures, TensorBoard logs).
4. The demo reports whether the truth lies inside the 90 % highest-density region.
5. ``torchslide predict`` runs 32 posterior draws: the impact-probability map (against the truth's own
   footprint) and the recorded velocity against its 90 % posterior-predictive interval.

Run: ``python -m experiments.demo --out demo_out [--cellsize 60] [--n-initial 30 --n-total 70 --batch-size 10]
[--figures docs/figures]`` (``--figures``: also copy the three figures there, as the README shows them).
Interrupted? Run the same command with ``--resume``: finished solver runs are not repeated.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

TRUTH = {"mu": 0.23, "xi": 1000.0}
BOUNDS = {"mu": [0.02, 0.3], "xi": [100.0, 2200.0]}


def write_toml(path: Path, text: str) -> Path:
    path.write_text(text.strip() + "\n")
    return path


def base_config(cellsize: float, t_end: float, points: dict) -> str:
    gauges = "\n".join(f'[[gauges]]\nname = "{k}"\nx = {x:.3f}\ny = {y:.3f}\n' for k, (x, y) in points.items())
    return f"""
[terrain]
synthetic = "bondo_like"
cellsize = {cellsize}

[model]
rheology = "voellmy"
mu = {TRUTH['mu']}
xi = {TRUTH['xi']}

[run]
t_end = {t_end}
dtype = "float64"
device = "cpu"

{gauges}
"""


FIGURES = {"demo_h_max.png": "h_max.png", "demo_posterior.png": "calibration/posterior.png",
           "demo_impact_probability.png": "predictive/impact_probability.png"}
"""The README's figures: name in --figures <- path under --out."""


def copy_figures(out: Path, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    for name, src in FIGURES.items():
        if (out / src).exists():
            shutil.copyfile(out / src, dest / name)


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="demo_out")
    # Defaults sized for a laptop CPU (about 4 s per run at 60 m cells on 2 shared cores): the paper's
    # 20 m grid and 40 + 80 runs are ``--cellsize 20 --n-initial 40 --n-total 120`` (a GPU job).
    ap.add_argument("--cellsize", type=float, default=60.0)
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--n-initial", type=int, default=30)
    ap.add_argument("--n-total", type=int, default=70)
    ap.add_argument("--batch-size", type=int, default=10)
    ap.add_argument("--noise-seed", type=int, default=1)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--figures", default=None, metavar="DIR", help="also copy the demo's figures into DIR")
    ap.add_argument("--n-predictive", type=int, default=32,
                    help="posterior draws of `torchslide predict` after the calibration (0: skip it)")
    return ap.parse_args(argv)


def simulate_truth(out: Path, base: str, case) -> tuple[dict, np.ndarray]:
    """Step 1: ``torchslide simulate`` at the truth (skipped when done); (summary.json, h_max (ny, nx) m)."""
    from torchslide.cli import main as cli
    from torchslide.mapplots import plot_hmax_map
    from torchslide.terrain.io import read_raster

    sim_cfg = write_toml(out / "simulate.toml", base)
    truth_dir = out / "truth"
    if not (truth_dir / "summary.json").exists():
        rc = cli(["simulate", str(sim_cfg), "--out", str(truth_dir), "--overwrite"])
        if rc:
            raise SystemExit(rc)
    summary = json.loads((truth_dir / "summary.json").read_text())
    h_max = read_raster(truth_dir / "h_max.asc", fill_nodata=True).z
    plot_hmax_map(case.dem, h_max, out / "h_max.png", points=case.points, release=case.release,
                  title=f"Bondo-like case, mu = {TRUTH['mu']}, xi = {TRUTH['xi']:g} m/s$^2$: h_max (m)")
    return summary, h_max


def calibration_config(base: str, point: tuple, v_obs: float, sigma: float, args) -> str:
    """Step 3's config: the prior box of the paper, the recorded velocity at ``point``, the budget."""
    x1, y1 = point
    return base + f"""
[prior]
mu = {BOUNDS['mu']}
xi = {BOUNDS['xi']}

[[observations]]
kind = "max_velocity"
name = "v_max_L1"
x = {x1:.3f}
y = {y1:.3f}
value = {v_obs:.6f}
sigma = {sigma:.6f}

[calibration]
n_initial = {args.n_initial}
n_total = {args.n_total}
batch_size = {args.batch_size}
seed = 0
grid_size = 100
truth = {{ mu = {TRUTH['mu']}, xi = {TRUTH['xi']} }}
"""


def truth_in_hdr(cal_dir: Path) -> tuple[bool, float]:
    """Step 4: (the truth inside the 90 % highest-density region, the region's share of the prior box)."""
    from torchslide.posterior import hdr_mask

    npz = np.load(cal_dir / "posterior.npz")
    dens, ax_mu, ax_xi = npz["posterior_grid"], npz["axis_0"], npz["axis_1"]
    mask = hdr_mask(dens, 0.9)
    i = int(np.argmin(np.abs(ax_mu - TRUTH["mu"])))
    j = int(np.argmin(np.abs(ax_xi - TRUTH["xi"])))
    return bool(mask[i, j]), float(mask.mean())


def predictive_check(cal_cfg: Path, cal_dir: Path, out: Path, n: int, h_max: np.ndarray) -> dict:
    """Step 5: ``torchslide predict`` with ``n`` draws; its impact probability against the truth's footprint."""
    from torchslide.cli import main as cli
    from torchslide.terrain.io import read_raster

    pred_dir = out / "predictive"
    rc = cli(["predict", str(cal_cfg), "--calibration", str(cal_dir), "--out", str(pred_dir), "--n", str(n),
              "--overwrite"])
    if rc:
        raise SystemExit(rc)
    p_hit = read_raster(pred_dir / "impact_probability.asc").z
    reached = h_max > 0.5
    pred = json.loads((pred_dir / "predictive.json").read_text())
    report = {"n_draws": pred["n_ok"], "v_max_L1_interval90": pred["observations"][0]["interval90"],
              "truth_footprint_cells": int(reached.sum()),
              "share_of_truth_footprint_with_p_ge_0.5": float((p_hit[reached] >= 0.5).mean()),
              "share_of_p_ge_0.5_cells_outside_truth_footprint": float((~reached[p_hit >= 0.5]).mean())}
    print(f"impact probability over {pred['n_ok']} posterior draws: {pred_dir / 'impact_probability.png'}; "
          f"{100 * report['share_of_truth_footprint_with_p_ge_0.5']:.0f} % of the truth's footprint has P >= 0.5")
    return report


def main(argv=None) -> int:
    t_start = time.perf_counter()
    args = parse_args(argv)
    from torchslide.cli import main as cli
    from torchslide.terrain.synthetic import bondo_like

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    case = bondo_like(cellsize=args.cellsize)
    base = base_config(args.cellsize, args.t_end, case.points)
    summary, h_max = simulate_truth(out, base, case)
    # 2. the synthetic recording: max velocity at L1 with 10 % noise
    v_true = float(summary["gauges"]["L1"]["v_max"])
    rng = np.random.default_rng(args.noise_seed)
    v_obs = v_true * (1.0 + 0.1 * rng.standard_normal())
    sigma = 0.1 * v_obs
    # 3. calibrate through the CLI
    cal_cfg = write_toml(out / "calibrate.toml", calibration_config(base, case.points["L1"], v_obs, sigma, args))
    cal_dir = out / "calibration"
    cal_args = ["calibrate", str(cal_cfg), "--out", str(cal_dir)]
    if args.resume or (cal_dir / "checkpoint.pt").exists():
        cal_args.append("--resume")
    rc = cli(cal_args)
    if rc:
        return rc
    inside, share = truth_in_hdr(cal_dir)
    post = json.loads((cal_dir / "posterior.json").read_text())
    report = {"truth": TRUTH, "v_max_L1_true": v_true, "v_max_L1_observed": v_obs, "sigma": sigma,
              "truth_in_hdr90": inside, "hdr90_fraction_of_prior_box": share,
              "posterior_mean": post["mean"], "posterior_map": post["map"], "log_evidence": post["log_evidence"],
              "n_runs": post["n_runs"], "n_failed": post["n_failed"]}
    if args.n_predictive > 0:
        report["predictive"] = predictive_check(cal_cfg, cal_dir, out, args.n_predictive, h_max)
    report["wall_s"] = time.perf_counter() - t_start
    (out / "demo_summary.json").write_text(json.dumps(report, indent=2))
    if args.figures:
        copy_figures(out, Path(args.figures))
    print(f"v_max at L1: true {v_true:.2f} m/s, observed {v_obs:.2f} +- {sigma:.2f} m/s")
    print(f"truth (mu={TRUTH['mu']}, xi={TRUTH['xi']:g}) inside the 90 % HDR: {inside} "
          f"(HDR covers {100 * share:.1f} % of the prior box)")
    print(f"figures: {out / 'h_max.png'}, {cal_dir / 'posterior.png'}; TensorBoard: tensorboard --logdir {cal_dir / 'tensorboard'}")
    return 0 if inside else 1


if __name__ == "__main__":
    sys.exit(main())
