"""``python -m experiments.msh2021 [--work DIR] [--no-diagnose]``: a real event end to end.

1. ``torchslide example msh2021``: the pre-event DEM, the failure depths (the release), the surveyed DEM of
   difference (DoD) of the runout, calibrate.toml and diagnose.toml (landlab's data, MIT licence).
2. ``torchslide calibrate``: Voellmy mu, xi on the mapped impact area, the deposition area, the mapped
   outline (a footprint map), the run-out measured on the DoD (the release's crown to its farthest changed
   cell) and the DoD as an elevation_change map (sigma 0.5 m, correlation length 20 m), with the model's own
   error learnt with the parameters (the default ``[calibration] discrepancy = "learnt"``).
3. ``torchslide predict``: 32 posterior draws, 4 of them on 5 m cells too (the grid's error of the impact
   area and the run-out): the impact probability, the footprint figures with their intervals, the front of
   run-out against the share of reached cells outside the map.
4. The posterior median run against the survey: footprint Jaccard (h_max > 0.1 m against the 224 mapped
   cells), the shares of mapped cells reached and of reached cells outside the map, deposition and erosion
   volumes, the run-out from the release's crown, the DoD observed, simulated and their difference, and the
   mapped and simulated outlines over the hillshade (torchslide.survey, torchslide.mapplots.plot_outlines);
   what the model cannot meet together (posterior.json's ``tradeoffs``).
5. ``torchslide diagnose`` on the same files: where the calibrated model and the survey disagree, which
   candidate term explains it, if any.

Writes under --work (default experiments/msh2021/_work; rerunning resumes the calibration and the diagnosis)
and regenerates experiments/msh2021/README.md and its figures.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
THRESHOLD = 0.1


def _cli(args: list) -> int:
    from torchslide.cli import main

    print("$ torchslide " + " ".join(map(str, args)), file=sys.stderr)
    return main([str(a) for a in args])


def _median_run(case: Path, pred: Path):
    """The run at the posterior draws' median (mu, xi)."""
    from torchslide.config import load_config
    from torchslide.physics import Params
    from torchslide.solver import simulate

    draws = np.genfromtxt(pred / "draws.csv", delimiter=",", names=True)
    x = {n: float(np.median(draws[n])) for n in ("mu", "xi")}
    cfg = load_config(case / "simulate.toml")
    r = simulate(cfg.terrain.dem, cfg.terrain.release, Params.make(**x), t_end=cfg.run.t_end)
    return x, cfg, r


def solver_pace(cfg, repeats: int = 3) -> float:
    """Median wall time, s, of this machine's event batch: 8 members at the diagnosis' baseline (mu 0.4, xi
    2500) for 300 s, as bench.bench_solver --terrain msh2021 times it, after a short warm-up run: the unit
    that makes the diagnosis' stage times comparable between machines."""
    from torchslide.physics import Params
    from torchslide.solver import simulate

    p = Params.make(B=8, mu=0.4, xi=2500.0)
    simulate(cfg.terrain.dem, cfg.terrain.release, p, t_end=10.0)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate(cfg.terrain.dem, cfg.terrain.release, p, t_end=300.0)
        walls.append(time.perf_counter() - t0)
    return float(np.median(walls))


def survey_figures(dod: np.ndarray, dz: np.ndarray, h_max: np.ndarray, p_impact: np.ndarray, cell: float) -> dict:
    """Figures a modeller quotes (torchslide.survey), of a run (simulated change dz, h_max) and the impact
    probability against the survey (dod, NaN off the mapped cells)."""
    from torchslide.survey import change_figures, footprint_figures

    mapped = np.isfinite(dod) & (dod != 0)
    return {**footprint_figures(h_max > THRESHOLD, mapped),
            "share_of_mapped_cells_with_p_impact_ge_0.5": float((p_impact[mapped] >= 0.5).mean()),
            **change_figures(dz, dod, np.sqrt(cell))}


def runout(cfg, dod: np.ndarray, h_max: np.ndarray) -> dict:
    """Run-out from the release's crown (torchslide.survey) of the run (h_max > THRESHOLD) and of the survey."""
    from torchslide.survey import runout_from_crown

    dem, rel = cfg.terrain.dem, cfg.terrain.release
    return {"run": runout_from_crown(dem.z, rel, h_max > THRESHOLD, dem.cellsize),
            "survey": runout_from_crown(dem.z, rel, np.isfinite(dod) & (dod != 0), dem.cellsize)}


def plot_dod(dem, hillshade_file: Path, dod: np.ndarray, dz: np.ndarray, path: Path) -> None:
    """Observed DoD, simulated change and their difference over the hillshade (vertical m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchslide.files import save_figure
    from torchslide.terrain.io import read_asc_array

    hs, hc, hx, hy = read_asc_array(hillshade_file)
    ext_h = (hx, hx + hs.shape[1] * hc, hy, hy + hs.shape[0] * hc)
    ext = (dem.xll, dem.xll + dem.nx * dem.cellsize, dem.yll, dem.yll + dem.ny * dem.cellsize)
    sim = np.where(np.abs(dz) > 0.01, dz, np.nan)
    panels = [("surveyed DoD", dod), ("simulated change", sim), ("simulated - surveyed", dz - dod)]
    fig, axs = plt.subplots(1, 3, figsize=(12, 5.2), sharey=True)
    for ax, (title, a) in zip(axs, panels):
        ax.imshow(hs, origin="lower", extent=ext_h, cmap="gray")
        im = ax.imshow(np.ma.masked_invalid(a), origin="lower", extent=ext, cmap="RdBu", vmin=-6, vmax=6, alpha=0.85)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (m)")
        ys, xs = np.nonzero(np.isfinite(dod) | (np.abs(dz) > 0.01))
        ax.set_xlim(dem.xll + (xs.min() - 5) * dem.cellsize, dem.xll + (xs.max() + 6) * dem.cellsize)
        ax.set_ylim(dem.yll + (ys.min() - 5) * dem.cellsize, dem.yll + (ys.max() + 6) * dem.cellsize)
    axs[0].set_ylabel("y (m)")
    fig.colorbar(im, ax=axs, label="elevation change (m, vertical)", shrink=0.8)
    save_figure(fig, path, 110)
    plt.close(fig)


def diagnosis_summary(rep: dict) -> dict:
    """What the page reports of a diagnosis report.json: the verdict and why, its time (the sum of its
    stages'), where the baseline disagrees with the survey (the residuals' clusters and the footprint's), each refitted candidate's 2 ln BF, each
    candidate's detectable switch."""
    from torchslide.survey import mismatch_line, width_line

    det = {c: v["detectable_switch"] for c, v in rep["screening"]["candidates"].items() if v.get("detectable_switch")}
    mm = rep.get("mismatches")
    return {"verdict": rep["verdict"], "missing_physics": rep.get("missing_physics"),
            "reason": rep["decision"].get("reason", ""), "seconds": sum(rep["timings"].values()),
            "stages_s": rep["timings"],
            "detectable": {c: {"switch": d["switch"], "within_prior": d["within_prior"],
                               "measured": bool(d.get("measured"))} for c, d in det.items()},
            "located": [{"what": m["what"], "where": m["where"], "z": m["standardised_residual"]} for m in rep["located"]],
            "footprint_mismatches": [mismatch_line(m) for m in ([mm["runout"]] + mm["clusters"][:9] if mm else [])]
            + ([f"the grid: {width_line(mm['path_width'])}"] if mm and mm.get("path_width", {}).get("n_rings") else []),
            "candidates": {c["name"]: c.get("two_ln_bf") for c in rep["candidates"] if c.get("two_ln_bf") is not None},
            "at_range_end": {c["name"]: {"param": c["param"], "hdr90": c["parameters"][c["param"]]["hdr90"],
                                         "baseline": {k: v["hdr90"] for k, v in c["parameters"].items() if k != c["param"]}}
                             for c in rep["candidates"] if c.get("at_range_end")}}


MWR = "MassWastingRunout"


def peer_point(root: Path) -> dict:
    """{label: (run-out m, share of its changed cells outside the map)} of landlab's MassWastingRunout on this
    event (bench/results/msh2021_peers.json, bench.msh2021_peers), {} where the file is missing."""
    f = root / "bench" / "results" / "msh2021_peers.json"
    if not f.is_file():
        return {}
    m = json.loads(f.read_text())[MWR]
    return {f"{MWR} (changed cells)": (m["runout_m"], m["share_of_changed_cells_unmapped"])}


def plot_front_page(pred: Path, path: Path, peers: dict) -> None:
    """The front that ``torchslide predict`` wrote (front.json: the calibration's runs and the draws), with the
    peer's point."""
    from torchslide.figures import plot_front

    f = json.loads((pred / "front.json").read_text())
    plot_front(f["runs"], path, draws=f["draws"], peers=peers,
               title="run-out against the reached cells outside the map")


def write_page(out: dict, path: Path) -> None:
    """experiments/msh2021/README.md from the run's summary."""
    p, f, pr = out["posterior"], out, out["predictive"]
    fig = pr["figures"]
    ro, ia = fig["runout_m"], fig["impact_area_m2"]
    rog, iag = ro.get("with_grid_error", {}), ia.get("with_grid_error", {})
    ob = {o["name"]: o for o in pr["observations"]}
    lines = [
        "# The 2021 Mount St. Helens landslide: calibrated and diagnosed from its surveyed elevation change",
        "",
        "`python -m experiments.msh2021` (module docstring: the steps and the commands). Data: landlab's",
        "MassWastingRunout tutorial (MIT licence; torchslide/data/msh2021/SOURCE.md): the pre-event DEM (10 m),",
        "the failure depths of the 30 source cells (22,481 m^3, the release) and the surveyed DEM of difference",
        "of the 224 mapped cells of the runout. Voellmy mu, xi calibrated on the mapped impact area, the",
        "deposition area, the mapped outline (footprint.asc, a `footprint` observation), the run-out measured on",
        f"the DoD ({ob['runout']['value']:.0f} m from the release's crown, sigma 20 m) and the DoD itself (sigma",
        "0.5 m, correlation length 20 m), with the model's own error learnt with the parameters (torchslide's",
        "default); no entrainment in the model.",
        "",
        f"Posterior ({out['inference']} inference): mu {p['mean']['mu']:.3f} +- {p['sd']['mu']:.3f} "
        f"(90 % [{p['hdr90']['mu'][0]:.3f}, {p['hdr90']['mu'][1]:.3f}]), xi {p['mean']['xi']:.0f} +- {p['sd']['xi']:.0f} "
        f"m/s^2 (90 % [{p['hdr90']['xi'][0]:.0f}, {p['hdr90']['xi'][1]:.0f}]). The event's own H/L is "
        f"{out['h_over_l']:.2f}.",
        "",
        "## What the model cannot meet together",
        "",
    ]
    lines += [f"- {t}." for t in out["tradeoffs"]] or ["- every pair of scalar data is met by some run."]
    lines += ["", "The model's own error as learnt (at the best run; posterior.json `discrepancy`): " +
              ", ".join(f"{d['observation']} {d['discrepancy_sd_over_sigma']:.2g} x its sigma" for d in out["discrepancy"])
              + ". A datum whose discrepancy is many times its sigma is one the model cannot reproduce together with the"
              " others: it weighs in by its logarithm, not its square.", "",
              "![run-out against the share of reached cells outside the map](figures/front.png)", "",
              "## Predictions (32 posterior draws; `torchslide predict`)", "",
              "| figure | 90 % of the draws | with the grid's error (4 draws on 5 m cells: its rms, either sign) | survey |", "|---|---|---|---|",
              f"| run-out from the release's crown, m | {ro['q05']:.0f} - {ro['q95']:.0f} | "
              f"{rog.get('q05', float('nan')):.0f} - {rog.get('q95', float('nan')):.0f} (+- {rog.get('sd', float('nan')):.0f}) "
              f"| {ob['runout']['value']:.0f} |",
              f"| impact area (h_max > 0.1 m), m^2 | {ia['q05']:,.0f} - {ia['q95']:,.0f} | "
              f"{iag.get('q05', float('nan')):,.0f} - {iag.get('q95', float('nan')):,.0f} (+- {iag.get('sd', float('nan')):,.0f}) "
              f"| {ob['impact']['value']:,.0f} |", "",
              "A new recording of each scalar datum (the stated error; with the model's own error learnt):", "",
              "| datum | recorded | 90 % interval | with the model's own error |", "|---|---|---|---|"]
    for name, o in ob.items():
        w = o.get("interval90_model_error")
        lines.append(f"| {name} | {o['value']:,.0f} | {o['interval90'][0]:,.0f} - {o['interval90'][1]:,.0f} | "
                     + ("-" if w is None else f"{w[0]:,.0f} - {w[1]:,.0f}") + " |")
    mm = pr.get("mismatches")
    if mm:
        ro = mm["runout"]
        lines += ["", f"Where the draws and the mapped footprint disagree (`predictive.json` `mismatches`; numbered on the "
                  f"outlines figure): the {ro['what']}, {ro['difference_m']:+.0f} m (90 % {ro['interval_m'][0]:+.0f} to "
                  f"{ro['interval_m'][1]:+.0f} m) of the mapped {ro['mapped_m']:.0f} m, and", "",
                  "| # | mismatch | cells | area, m^2 | from the crown, m | meets the mapped path (along it, m; x, y) "
                  "| volume, m^3 |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {i + 1} | {m['what']} | {m['n_cells']} | {m['area_m2']:,.0f} | {m['from_crown_m'][0]:.0f} - "
                  f"{m['from_crown_m'][1]:.0f} | " + (f"{m['path_point']['along_m']:.0f} ({m['path_point']['x']:,.0f}, "
                                                     f"{m['path_point']['y']:,.0f})" if "path_point" in m else "")
                  + f" | {m.get('volume_m3', float('nan')):,.0f} |" for i, m in enumerate(mm["clusters"][:9])]
    lines += ["", f"The posterior median run (mu {f['median_run']['mu']:.3f}, xi {f['median_run']['xi']:.0f}) against the "
              "survey, and the draws' 90 % intervals:", "",
              "| figure | median run | 90 % of the draws |", "|---|---|---|"]
    a = pr["against"]
    rng = lambda k, s=1.0, fmt="{:.2f}": f"{fmt.format(s * a[k]['q05'])} - {fmt.format(s * a[k]['q95'])}"
    lines += [
        f"| footprint Jaccard (h_max > {THRESHOLD:g} m against the mapped cells) | {f['footprint_jaccard']:.2f} | "
        f"{rng('footprint_jaccard')} |",
        f"| mapped cells reached | {100 * f['share_of_mapped_reached']:.0f} % | {rng('share_of_mapped_reached', 100, '{:.0f} %')} |",
        f"| reached cells outside the map | {100 * f['share_of_reached_unmapped']:.0f} % | "
        f"{rng('share_of_reached_unmapped', 100, '{:.0f} %')} |",
        f"| mapped cells with impact probability >= 0.5 | {100 * f['share_of_mapped_cells_with_p_impact_ge_0.5']:.0f} % | |",
        f"| deposition, m^3 (vertical) | {f['deposition_m3']['run']:,.0f} (survey {f['deposition_m3']['survey']:,.0f}) | |",
        f"| erosion, m^3 (vertical, source included) | {f['erosion_m3']['run']:,.0f} (survey {f['erosion_m3']['survey']:,.0f}) | |",
        f"| DoD rmse over the mapped cells | {f['rmse_m']:.2f} m | {rng('rmse_m', 1, '{:.2f} m')} |",
        f"| run-out from the release's crown | {f['runout_m']['run']:.0f} m (survey {f['runout_m']['survey']:.0f} m) | |",
        "",
        "![mapped and simulated outlines](figures/outlines.png)",
        "![surveyed and simulated elevation change](figures/dod.png)",
        "![impact probability](figures/impact_probability.png)",
        "![posterior](figures/posterior.png)",
        "",
    ]
    if "diagnosis" in out:
        d = out["diagnosis"]
        lines += [f"## Diagnosis", "",
                  f"`torchslide diagnose diagnose.toml`, with a 1.2 m erodible regolith for the entrainment "
                  f"candidate; {d['seconds']:.0f} s in its stages"
                  + (f" ({d['seconds'] / out['solver_pace_s']:.0f} times the {out['solver_pace_s']:.1f} s this machine "
                     "takes for the event's 8-member batch of 300 s)" if out.get("solver_pace_s") else "")
                  + f": verdict **{d['verdict']}**"
                  + (f" ({d['missing_physics']})" if d.get("missing_physics") else "") + f": {d['reason']}.", "",
                  "Where the calibrated model and the survey disagree (clusters of the maps' standardised residuals):", "",
                  "| mismatch | x (m) | y (m) | standardised residual |", "|---|---|---|---|"]
        lines += [(f"| {m['what']} | {m['where'][0]:.0f} - {m['where'][2]:.0f} | {m['where'][1]:.0f} - {m['where'][3]:.0f} "
                   if isinstance(m["where"], list) else f"| {m['what']} (a scalar datum) | | ") + f"| {m['z']:+.1f} |"
                  for m in d["located"]]
        if d.get("footprint_mismatches"):
            lines += ["", "The baseline's runs against the mapped footprint (report.md; numbered in the figure):", ""] + \
                [f"- {x}" for x in d["footprint_mismatches"]] + \
                ["", "![the diagnosis' baseline against the mapped footprint](figures/diagnosis_outlines.png)"]
        lines += ["", "Refitted candidates, 2 ln Bayes factor against the baseline: "
                  + (", ".join(f"{k} {v:+.1f}" for k, v in d["candidates"].items()) or "none") + ".", ""]
        det = d.get("detectable", {})
        if det:
            how = "measured on the solver" if any(e["measured"] for e in det.values()) else "linearised"  # report.md
            lines += [f"What these data can reveal on this grid (the screening's detectable switch, {how}: a term "
                      "this strong reaches bf_min in half the noise draws): "
                      + ", ".join(f"{c} never (no own effect)" if not math.isfinite(e["switch"]) else
                                  f"{c} from {e['switch']:.3g}" + ("" if e["within_prior"] else " (beyond its range)")
                                  for c, e in det.items()) + ".", ""]
        for name, e in d.get("at_range_end", {}).items():
            base = ", ".join(f"{k} {v[0]:.3g}-{v[1]:.3g}" for k, v in e["baseline"].items())
            lines += [f"{name} fits best but at the end of its range ({e['param']} 90 % interval {e['hdr90'][0]:.3g}-"
                      f"{e['hdr90'][1]:.3g}, with {base}), so nothing is named.", ""]
    threads = f" on {out['threads']} torch thread{'s' if out['threads'] > 1 else ''}" if out.get("threads") else ""
    lines.append(f"Calibration, prediction and the figures: {out['wall_s']:.0f} s on the 2-core machine{threads} "
                 f"(calibration {out['calibrate_s']:.0f} s).")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=HERE / "_work")
    ap.add_argument("--no-diagnose", action="store_true")
    a = ap.parse_args(argv)
    from torchslide.mapplots import plot_outlines
    from torchslide.survey import cluster_labels
    from torchslide.terrain.io import read_asc_array, read_raster

    t0 = time.perf_counter()
    w = a.work
    case, cal, pred, diag = w / "case", w / "cal", w / "pred", w / "diag"
    if not case.exists():
        assert _cli(["example", "msh2021", "--out", case]) == 0
    resume = ["--resume"] if (cal / "checkpoint.pt").exists() else []
    assert _cli(["calibrate", case / "calibrate.toml", "--out", cal, "--quiet", *resume]) == 0
    t_cal = time.perf_counter() - t0
    assert _cli(["predict", case / "calibrate.toml", "--calibration", cal, "--out", pred, "--n", "32",
                 "--threshold", THRESHOLD, "--overwrite", "--quiet"]) in (0, 1)
    x, cfg, r = _median_run(case, pred)
    dod = read_asc_array(case / "dod.asc")[0]
    p_impact = np.nan_to_num(read_raster(pred / "impact_probability.asc", nodata="fill").z)
    post = json.loads((cal / "posterior.json").read_text())
    info = json.loads((pred / "predictive.json").read_text())
    from torchslide.tradeoff import lines as tradeoff_lines

    dem = cfg.terrain.dem
    mapped = np.isfinite(dod) & (dod != 0)
    out = {"posterior": {k: post[k] for k in ("mean", "sd", "map", "hdr90")}, "inference": post["inference"]["path"],
           "tradeoffs": tradeoff_lines(post["tradeoffs"]), "discrepancy": post["discrepancy"].get("at_best_run", []),
           "predictive": {"figures": info["figures"], "observations": info["observations"],
                          "against": info["against_observations"]["dod"], "mismatches": info["mismatches"]},
           "median_run": x, "h_over_l": h_over_l(cfg, mapped),
           **survey_figures(dod, r.elevation_change[0].numpy(), r.h_max[0].numpy(), p_impact, dem.cellsize ** 2),
           "runout_m": runout(cfg, dod, r.h_max[0].numpy())}
    figs = HERE / "figures"
    figs.mkdir(exist_ok=True)
    plot_dod(dem, case / "hillshade.asc", dod, r.elevation_change[0].numpy(), figs / "dod.png")
    hs, hc, hx, hy = read_asc_array(case / "hillshade.asc")
    clusters = (info.get("mismatches") or {}).get("clusters", [])
    plot_outlines(dem, mapped, {f"median run (mu {x['mu']:.3f}, xi {x['xi']:.0f})": r.h_max[0].numpy() > THRESHOLD,
                                "impact probability >= 0.5": p_impact >= 0.5}, figs / "outlines.png",
                  title=f"mapped and simulated footprints (h_max > {THRESHOLD:g} m)",
                  background=(hs, (hx, hx + hs.shape[1] * hc, hy, hy + hs.shape[0] * hc)),
                  labels=cluster_labels(clusters))
    plot_front_page(pred, figs / "front.png", peer_point(HERE.parents[1]))
    shutil.copyfile(pred / "impact_probability.png", figs / "impact_probability.png")
    shutil.copyfile(cal / "posterior.png", figs / "posterior.png")
    out["wall_s"], out["calibrate_s"], out["threads"] = time.perf_counter() - t0, t_cal, torch.get_num_threads()
    if not a.no_diagnose:
        out["solver_pace_s"] = solver_pace(cfg)
        resume = ["--resume"] if (diag / "diagnosis.pkl").exists() else []
        _cli(["diagnose", case / "diagnose.toml", "--out", diag, "--quiet", *resume])
        out["diagnosis"] = diagnosis_summary(json.loads((diag / "report.json").read_text()))
        if (diag / "outlines.png").is_file():
            shutil.copyfile(diag / "outlines.png", figs / "diagnosis_outlines.png")
    (w / "summary.json").write_text(json.dumps(out, indent=1))
    write_page(out, HERE / "README.md")
    print(json.dumps(out, indent=1))
    return 0


def h_over_l(cfg, mapped: np.ndarray) -> float:
    """The event's H/L: the drop from the release's crown to the lowest mapped cell over the run-out from the
    crown to the farthest mapped cell (torchslide.survey)."""
    from torchslide.survey import crown_cell, runout_from_crown

    z, rel = cfg.terrain.dem.z, cfg.terrain.release
    r0, c0 = crown_cell(z, rel)
    return float((z[r0, c0] - z[mapped].min()) / runout_from_crown(z, rel, mapped, cfg.terrain.dem.cellsize))


if __name__ == "__main__":
    raise SystemExit(main())
