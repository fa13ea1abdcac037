"""Write a Diagnosis: report.json, report.md and figures (residual maps, gauge series, posteriors)."""
from __future__ import annotations

import json
import math
from pathlib import Path


def _fmt(v, f="{:.3g}"):
    return "-" if v is None else f.format(v)


def write_figures(diag, out: Path) -> list[str]:
    import matplotlib
    import numpy as np
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    from ..files import save_figure
    from ..physics import label

    files = []
    before = diag.localisation.maps
    after = diag.after_localisation.maps if diag.after_localisation is not None else {}
    dem = diag.evaluator.dem
    ext = [dem.xll, dem.xll + dem.nx * dem.cellsize, dem.yll, dem.yll + dem.ny * dem.cellsize]
    for name, m in before.items():
        safe = name.replace(":", "_").replace("/", "_")
        if "t" not in m:  # map
            ncol = 2 if name in after else 1
            fig, axs = plt.subplots(1, ncol, figsize=(5.5 * ncol, 3.2), squeeze=False)
            for ax, (lab, mm) in zip(axs[0], [("before", m)] + ([("after", after[name])] if name in after else [])):
                im = ax.imshow(mm["z"], origin="lower", extent=ext, cmap="RdBu_r", vmin=-4, vmax=4)
                ax.set_title(f"{name}: standardised residual, {lab}", fontsize=9)
                ax.set_xlabel("x (m)")
                ax.set_ylabel("y (m)")
                cax = make_axes_locatable(ax).append_axes("right", size="3%", pad=0.08)
                fig.colorbar(im, cax=cax, label="standardised residual (-)")
            for loc in diag.localisation.located:
                if isinstance(loc["where"], list):
                    x0, y0, x1, y1 = loc["where"]
                    axs[0][0].add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="k", lw=1.2))
            fig.tight_layout()
            f = out / f"residual_map_{safe}.png"
            save_figure(fig, f, dpi=90)
            plt.close(fig)
            files.append(f.name)
        else:
            fig, ax = plt.subplots(figsize=(6, 3))
            rec, off = m.get("recorded", m["data"]), m.get("offset", np.zeros_like(m["data"]))
            corrected = bool(np.any(off != 0))
            ax.plot(m["t"], rec, "k.", ms=3, label="recording")
            top = m["pred"] + off
            ax.plot(m["t"], top, "C0-", label="baseline + the grid's mean error" if corrected else "baseline")
            ax.fill_between(m["t"], top - 2 * m["pred_sd"], top + 2 * m["pred_sd"], color="C0", alpha=0.2)
            if corrected:
                ax.plot(m["t"], m["pred"], "C0:", lw=1, label="baseline on the inversion grid")
            if name in after:
                a = after[name]
                ax.plot(a["t"], a["pred"] + a.get("offset", 0.0), "C3-", label=f"refit ({diag.fit_after.get('model')})")
            ax.set_xlabel("t (s)")
            ax.set_ylabel({"h": "flow thickness (m)", "speed": "speed (m/s)"}.get(name.rsplit(":", 1)[-1], name))
            ax.set_title(name)
            ax.legend(fontsize=7)
            fig.tight_layout()
            f = out / f"gauge_{safe}.png"
            save_figure(fig, f, dpi=90)
            plt.close(fig)
            files.append(f.name)
    if diag.mismatches and "clusters" in diag.mismatches:
        from ..mapplots import plot_outlines
        from ..survey import cluster_labels

        m = diag.mismatches
        plot_outlines(dem, m["mapped"], {"baseline: P(reached) >= 0.5": m["p_reached"] >= 0.5}, out / "outlines.png",
                      title=f"mapped and simulated footprints (h_max > {m['threshold']:g} m)",
                      labels=cluster_labels(m["clusters"]))
        files.append("outlines.png")
    # posteriors of the refit switches: 1-D marginal of the samples (histogram) or of the grid posterior,
    # on the switch's prior range
    refits = [(c, cal) for c, (_, cal) in diag.refits.items()
              if getattr(cal, "samples", None) is not None or getattr(cal, "posterior_grid", None) is not None]
    if refits:
        from ..posterior import marginals

        fig, axs = plt.subplots(1, len(refits), figsize=(3.5 * len(refits), 2.8), squeeze=False)
        for ax, (c, cal) in zip(axs[0], refits):
            i = len(cal.names) - 1
            if cal.samples is not None:
                ax.hist(cal.samples[:, i], bins=30, color="C2", density=True)
            else:
                m = marginals(cal.posterior_grid, cal.grid_axes)[i]
                ax.fill_between(cal.grid_axes[i], m, color="C2", alpha=0.6, step="mid")
            ax.set_xlim(float(cal.bounds[0][i]), float(cal.bounds[1][i]))
            ax.set_xlabel(label(cal.names[i]))
            ax.set_ylabel("posterior density")
            ax.set_title(c)
        fig.tight_layout()
        f = out / "posteriors.png"
        save_figure(fig, f, dpi=90)
        plt.close(fig)
        files.append(f.name)
    return files


def _refit_check(c: dict) -> str:
    """One cell: the local path's checks, or whether the emulator path's verified evidence converged
    ('-' when not refitted)."""
    if c.get("log_evidence") is None:
        return "-"
    if c.get("inference") == "laplace":
        return _local_check(c)
    if "evidence_converged" in c:
        return "evidence converged" if c["evidence_converged"] else "evidence NOT converged"
    return "-"


def _local_check(c: dict) -> str:
    """A local-path candidate's checks: the likelihood ratio and its boundary-corrected p-value, and the
    profile's 2 ln drops at the ends of the switch's 90 % interval against a Gaussian's."""
    out = (f"local fit (Laplace); 2 ln LR {_fmt(c.get('likelihood_ratio'), '{:.1f}')}, p "
           f"{_fmt(c.get('lr_pvalue'), '{:.2g}')} (switch at its bound 0: chi2_0 / 2 + chi2_1 / 2)")
    pe = c.get("profile_ends")
    if pe:
        out += ("; profile 2 ln drop at the 90 % ends " + " / ".join(f"{v:.2f}" for v in pe["two_ln_drop"])
                + f" (Gaussian {pe['gaussian']:.2f})")
    if c.get("two_ln_bf_laplace") is not None:
        out += f"; log Z with the switch's profile (Laplace: 2 ln BF {c['two_ln_bf_laplace']:.1f})"
    return out


def write_markdown(j: dict, figures: list[str]) -> str:
    """report.md from a report.json-style ``j``: the verdict, where the baseline disagrees, the subset
    consistency, the screening, the candidates, the fit before and after, the figures."""
    L = _verdict_section(j) + _null_section(j.get("null_calibration"), j.get("candidates"))
    me = j.get("model_error")
    if me:
        L += [f"Approximation error of the grid in every likelihood: {me['n']} run pairs on cells {me['factor']} "
              f"times smaller (rms of the mean / sd per observable: " +
              ", ".join(f"{k} {v['rms_mean']:.3g} / {v['rms_sd']:.3g}" for k, v in me["blocks"].items()) + ").", ""]
    L += _tradeoff_section(j.get("tradeoffs")) + _located_section(j) + _mismatch_section(j.get("mismatches"))
    L += _consistency_section(j.get("subset_consistency"))
    L += _screening_section((j.get("screening") or {}).get("candidates") or {})
    L += _candidates_section(j["candidates"], j["decision"].get("explained_shares") or {}) + _fit_section(j)
    L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(L) + "\n"


def _tradeoff_section(t: dict | None) -> list[str]:
    """What the baseline's runs cannot meet together (torchslide.tradeoff), when anything."""
    from ..tradeoff import lines

    got = lines(t) if t else []
    if not got:
        return []
    return ["## What the baseline cannot meet together", "",
            f"Over the baseline's {t['n_runs']} runs (the stated sigmas; docs/model-error.md):", ""] + \
        [f"- {x}." for x in got] + [""]


def _mismatch_section(m: dict | None) -> list[str]:
    """The baseline's runs against the mapped footprint (diagnose.predictive.map_mismatches), when one is mapped."""
    from ..survey import mismatch_line, width_line

    if not m:
        return []
    if "failed" in m:
        return ["## Where the baseline and the map differ", "", f"Not measured: {m['failed']}.", ""]
    return ["## Where the baseline and the map differ", "",
            f"Over {m['n_runs']} of the baseline's posterior runs against {m['footprint']} (reached: h_max > "
            f"{m['threshold']:g} m; a cluster: 3 or more 8-connected cells the runs reach with probability >= 0.5 "
            f"off the map, or < 0.5 on it; numbered on outlines.png):", "",
            f"- {mismatch_line(m['runout'])}."] + \
        [f"{i + 1}. {mismatch_line(c)}." for i, c in enumerate(m["clusters"][:9])] + \
        ([f"- The grid: {width_line(m['path_width'])}.", ""] if m.get("path_width", {}).get("n_rings") else [""])


def _verdict_section(j: dict) -> list[str]:
    L = ["# Missing-physics diagnosis", "", f"**Verdict: {j['verdict']}**" +
         (f" — missing physics: **{j['missing_physics']}**" if j["missing_physics"] else ""), "",
         f"Reason: {j['decision']['reason']}", ""]
    if j["missing_physics"] == "release_volume":
        rs = next((c["parameters"].get("release_scale") for c in j["candidates"] if c["name"] == "release_volume"), None)
        size = f" by {100 * rs['mean']:.0f} % (90 %: {100 * rs['hdr90'][0]:.0f} to {100 * rs['hdr90'][1]:.0f} %)" \
            if rs and rs.get("hdr90") else ""
        L += [f"Not a physics term: the recordings hold more mass than the stated release{size}, as if from the "
              f"start. Either the release is larger than stated, or the flow gained mass along its path in a way "
              f"the entrainment candidate (its erodible depth and rate law as set up) does not reproduce; check "
              f"the release's thickness and outline, and the erodible depth.", ""]
    for c in j["candidates"]:
        if c.get("at_range_end"):
            iv = (c["parameters"].get(c["param"]) or {}).get("hdr90")
            L += [f"{c['name']} fits at the end of its range ({c['param']} 90 % interval {iv}): the data want more "
                  f"than the range allows, so it is not named.", ""]
    inf = j["decision"].get("inference")
    if inf:
        L += [f"Inference: {'local fits on the solver with Laplace evidence' if inf['path'] == 'local' else 'GP emulator over the prior box'}"
              f" ({inf['why']}).", ""]
    unseen = [c for c, v in ((j.get("screening") or {}).get("candidates") or {}).items()
              if v.get("detectable_switch") and not v["detectable_switch"].get("within_prior")]
    if unseen:
        L += [f"Beyond what these data can detect on this grid at any strength in its prior (see "
              f"Screening): {', '.join(unseen)}. The verdict says nothing about {'it' if len(unseen) == 1 else 'them'}.",
              ""]
    if j["decision"].get("partial"):
        rem = j["decision"].get("remainder") or []
        L += [f"Partial: {j['missing_physics']} removes {100 * j['decision']['explained_share']:.0f} % of the located "
              f"mismatch (sum of squared scores); the recordings differ from the model in another way too."
              + (" Unexplained after it:" if rem else ""), ""]
        if rem:
            L += ["| located mismatch | where | score before | score after |", "|---|---|---|---|"]
            L += [f"| {r['what']} | {r['where']} | {r['before']:.1f} | {r['after']:.1f} |" for r in rem] + [""]
    if j["decision"].get("ambiguous"):
        alts = j["decision"].get("alternatives") or []
        L += [f"Ambiguous: {' or '.join(alts)}; the data do not separate them, so no single term is named.", ""]
        sep = j["decision"].get("separate") or {}
        if sep.get("values"):
            L += ["What would separate them: the observations where their refits differ most (difference of the "
                  "posterior-predictive means over the likelihood's sigma); record these more precisely, or add "
                  "a gauge where they differ (`--design --discriminate A,B`).", "", "| observation | difference / sigma |", "|---|---|"]
            L += [f"| {v['observation']} | {v['difference_sigma']:.2f} |" for v in sep["values"]]
            L += ["", "| observation block | root sum of squares |", "|---|---|"]
            L += [f"| {b['block']} | {b['difference_sigma_rss']:.2f} |" for b in sep["blocks"]] + [""]
    res = j["decision"].get("resolution")
    if res:
        L += [f"Resolution: {len(res)} mismatch(es) of the calibrated baseline with the recordings as given are the "
              f"inversion grid's own: runs on cells half as large account for them (the grid's approximation "
              f"error), so they are not read as missing physics.", "",
              "| located mismatch (without the grid's error) | where | standardised residual |", "|---|---|---|"]
        L += [f"| {r['what']} | {r['where']} | {r['standardised_residual']:.1f} |" for r in res] + [""]
    fg = j["decision"].get("finer_grid")
    if fg:
        rows = [c for c in j["candidates"] if c.get("finer_grid")]
        L += [f"Finer grid: {fg['why']}; the baseline and {', '.join(fg['candidates'])} were fitted again on the "
              f"finer grid and their evidence is taken there (the inversion grid's error cannot then be read as a "
              f"term)." + ("" if fg.get("baseline_converged", True) else f" The baseline's fit there did not "
              f"converge ({fg.get('baseline_message')}): no candidate's evidence there counts as reliable."), "",
              "| candidate | 2 ln BF, inversion grid | 2 ln BF, finer grid | switch, inversion grid | switch, finer grid |",
              "|---|---|---|---|---|"]
        L += [f"| {c['name']} | {c['finer_grid']['two_ln_bf_inversion_grid']:.1f} | {c['two_ln_bf']:.1f} | "
              f"{c['finer_grid'][c['param'] + '_inversion_grid']:.4g} | {c['best_x'][-1]:.4g} |" for c in rows] + [""]
    g = j.get("grid")
    if g:
        L += [f"Inversion grid: {g['cellsize']:g} m, chosen by its own error (`cellsize = \"auto\"`): {g['reason']}.", "",
              "| cells, m | cells | the grid's error / stated noise (rms per observable) |", "|---|---|---|"]
        L += [f"| {t['cellsize']:g} | {t.get('cells', '')} | " +
              (", ".join(f"{k} {v:.2g}" for k, v in t["ratio"].items()) if "ratio" in t else t.get("skipped", "")) + " |"
              for t in g["tried"]] + [""]
    db = j["decision"].get("decision_before")
    if db:
        L += [f"Thresholds {j['decision'].get('thresholds_source')}; with the thresholds given before, the verdict "
              f"was {db['verdict']}" + (f" ({db['missing_physics']})" if db.get("missing_physics") else "") + ".", ""]
    return L


def _located_section(j: dict) -> list[str]:
    L = ["## Where the baseline disagrees with the data", "", "| what | where | standardised residual |", "|---|---|---|"]
    for l in j["located"]:
        L.append(f"| {l['what']} | {l['where']} | {l['standardised_residual']:.2f} |")
    for f in j["decision"].get("fit_flags") or []:
        L.append(f"| whole-observable fit of the calibrated baseline (Z_fit > fit_max {f['fit_max']:.2f}) | {f['observable']} | Z_fit {f['Z_fit']:.2f} |")
    if not j["located"] and not j["decision"].get("fit_flags"):
        L.append("| (nothing located) | | |")
    return L


def _consistency_section(sc: list | None) -> list[str]:
    if not sc:
        return []
    fmtw = lambda w: ", ".join(f"{k} {v:.4g}" for k, v in w.items()) if w else "-"
    L = ["", "## Do the observations agree on the baseline's parameters? (subset consistency)", "",
         "Each observation against all the others, linearised at the baseline (torchslide/diagnose/"
         "consistency.py): T is the chi-square a common parameter shift costs over separate ones, ~ chi2(df) "
         "when the model is right; 'disagrees' at p < 0.01 / number of observations. A diagnostic of where, "
         "not part of the verdict; its p-values are not calibrated on null data, and a coarse grid's own error "
         "can make an observation disagree where nothing is missing.", "",
         "| observation | values | T | df | p | disagrees | it alone wants | the rest wants |",
         "|---|---|---|---|---|---|---|---|"]
    for e in sc:
        L.append(f"| {e['block']} | {e['k']} | {e['statistic']:.1f} | {e['df']} | {e['p_value']:.2g} | "
                 f"{'yes' if e['conflict'] else 'no'} | {fmtw(e['wants'])} | {fmtw(e['rest_wants'])} |")
    return L


def _screening_section(scr: dict) -> list[str]:
    if not any("detectable_switch" in v for v in scr.values()):
        return []
    from .candidates import CANDIDATES
    measured = any((v.get("detectable_switch") or {}).get("measured") for v in scr.values())
    how = ("measured on the solver near that switch (torchslide/diagnose/power.py)" if measured else
           "linearised over the screening's step ([diagnose] detectability = \"linearised\": not measured on the "
           "solver, and off by a factor 2-3 for threshold and saturating terms)")
    L = ["", "## Screening", "",
         "One batched solver call at the baseline's mode (torchslide/diagnose/screen.py). 'Detectable from': the "
         "smallest switch at which noise-free data of the candidate's model would give the baseline, refitted to "
         "them, a 2 ln likelihood ratio reaching the evidence threshold bf_min (the likelihood's covariance, the "
         f"grid's error included), {how}. "
         "Beyond the prior range: these data cannot name the term on "
         "this grid at any strength, so 'nothing missing' does not rule it out. Within it: a weaker term, or one "
         "the grid biases or another term mimics, can still be missed. At 'detectable from' a term reaches bf_min "
         "in half the noise draws; 'found 4 in 5 from': in four of five. On the project's blind tests the fits' "
         "2 ln likelihood ratio at the true switch was, in the median per term and terrain, 0.9 to 2.3 times the "
         "measured one (more where the grid's own error can resemble the term; docs/diagnosis.md).", "",
         "| candidate | screening score | mimic by mu, xi | detectable from | found 4 in 5 from | prior range |",
         "|---|---|---|---|---|---|"]
    for c, v in scr.items():
        d = v.get("detectable_switch") or {}
        lo, hi = CANDIDATES[c].prior if c in CANDIDATES else (None, None)
        sw = d.get("switch")
        det = "-" if not d else ("never (no own effect)" if sw is None else
                                 f"{sw:.3g}" + ("" if d.get("within_prior") else " (beyond the prior)"))
        pw = d.get("switch_power")
        pw = "-" if pw is None or not math.isfinite(pw) else f"{pw:.3g}"
        L.append(f"| {c} | {_fmt(v.get('score'), '{:.1f}')} | {_fmt(v.get('mimic'), '{:.2f}')} | {det} | {pw} | "
                 f"{'-' if lo is None else f'[{lo:g}, {hi:g}]'} |")
    return L


def _candidates_section(candidates: list, shares: dict) -> list[str]:
    L = ["", "## Candidates", "",
         "'refit check': on the local path, the likelihood ratio with its boundary-corrected p-value and the profile "
         "at the ends of the switch's 90 % interval; on the emulator path, whether the verified evidence converged. "
         "'90 % interval': where the candidate was profiled, the profile-likelihood interval (2 ln drop 2.71; "
         "'open' where the drop stays below it up to the prior's bound), else the posterior's 90 % HDI. 'explains': "
         "the share of the significant located mismatches' sum of squared scores that the refit removes.", "",
         "| candidate | screening score | mimic by mu, xi | log Z | 2 ln BF vs baseline | switch mean | 90 % interval | "
         "explains | refit check |",
         "|---|---|---|---|---|---|---|---|---|"]
    for c in candidates:
        p = c["parameters"].get(c["param"], {}) if c["parameters"] else {}
        L.append(f"| {c['name']} | {_fmt(c['screening_score'], '{:.1f}')} | {_fmt(c.get('mimic'), '{:.2f}')} | "
                 f"{_fmt(c['log_evidence'], '{:.2f}')} | {_fmt(c['two_ln_bf'], '{:.1f}')} | {_fmt(p.get('mean'))} | "
                 f"{_interval(p)} | {_fmt(shares.get(c['name']), '{:.0%}')} | {_refit_check(c)} |")
    return L


def _interval(p: dict) -> str:
    """A switch's reported 90 % interval: the profile-likelihood one where computed (module doc of
    local_path.profile_interval90), else the HDI."""
    if not p:
        return "-"
    if p.get("profile90"):
        ends = [f"{v:.5g}" + ("" if ok else " (open)") for v, ok in zip(p["profile90"], p.get("profile90_closed", [True, True]))]
        return f"[{', '.join(ends)}] (profile)"
    return str([round(v, 5) for v in p.get("hdi90", p["hdr90"])])


def _fit_section(j: dict) -> list[str]:
    fb, fa = j["fit_before"], j["fit_after"]
    L = ["", "## Fit before / after", "", f"- baseline: log Z {_fmt(fb['log_evidence'], '{:.2f}')}, misfit {_fmt(fb['misfit'], '{:.1f}')} (k = {fb['k']})"]
    src = (j["decision"].get("baseline_verification") or {}).get("source")
    if src:
        L[-1] += f"; evidence from the {src}"
    if fa:
        L.append(f"- after ({fa.get('model')}): log Z {_fmt(fa['log_evidence'], '{:.2f}')}, misfit {_fmt(fa['misfit'], '{:.1f}')}")
    L += ["", "'fit Z': the block's chi-square with the likelihood's own covariance (grid error included) as a "
          "normal score (0 = as expected; localise.block_fit).", "",
          "| observable | before | after | fit Z before | fit Z after |", "|---|---|---|---|---|"]
    for name, r in fb["residuals"].items():
        a = fa.get("residuals", {}).get(name, {}) if fa else {}
        key = "z" if "z" in r else "rms_z"
        L.append(f"| {name} ({'z' if key == 'z' else 'rms z'}) | {_fmt(r.get(key), '{:.2f}')} | {_fmt(a.get(key), '{:.2f}')} "
                 f"| {_fmt(r.get('Z_fit'), '{:.1f}')} | {_fmt(a.get('Z_fit'), '{:.1f}')} |")
    return L + _fit_notes(fb["residuals"])


def _best(lower: dict | None):
    """(name, value) of the largest lower-bound 2 ln BF in {candidate: value}, or None."""
    if not lower:
        return None
    name = max(lower, key=lower.get)
    return name, lower[name]


def _null_best_lines(cases: list, data_candidates: list | None) -> list[str]:
    """How often each candidate came out best (largest lower-bound 2 ln BF) on the null runs, and whether the
    data's best candidate is among them: a term the grid's error favours when nothing is missing is the best
    candidate there too, so on its own its coming out best is no sign of it. [] for null cases without
    the per-candidate values."""
    known = [c["lower_by_candidate"] for c in cases if c.get("lower_by_candidate")]
    if not known:
        return []
    wins, top = {}, {}
    for lower in known:
        name, v = _best(lower)
        wins[name] = wins.get(name, 0) + 1
        top[name] = max(top.get(name, v), v)
    n = len(known)
    L = ["Best candidate on the null runs (largest lower-bound 2 ln BF; nothing is missing there): "
         + ", ".join(f"{k} in {w} of {n} (up to {top[k]:.1f})" for k, w in sorted(wins.items(), key=lambda kv: -kv[1]))
         + "."]
    data = _best({c["name"]: c["two_ln_bf_lower"] for c in data_candidates or []
                  if c.get("two_ln_bf_lower") is not None})
    if data:
        name, v = data
        k = wins.get(name, 0)
        L.append(f"On these data the best candidate is {name} (lower-bound 2 ln BF {v:.1f}); on the null runs it was "
                 f"the best in {k} of {n}" + (": coming out best is, on its own, no sign of it here; its evidence "
                                              "has to clear bf_min, which these runs set." if k else "."))
    return L + [""]


def _null_section(nc: dict | None, data_candidates: list | None = None) -> list[str]:
    """report.md lines on the thresholds set on null simulations of this design (diagnose.null), if any;
    ``data_candidates``: report.json's candidates of the data, to say whether their best is also the null
    runs' best (_null_best_lines)."""
    if not nc:
        return []
    th = nc["thresholds"]
    fm = th.get("fit_max")
    fm = (", ".join(f"{k} {v:.2f}" for k, v in fm.items()) if isinstance(fm, dict) else _fmt(fm, "{:.2f}"))
    sd = nc.get("release_volume_sd")
    rel = ("the release volume as given (release_volume_sd 0: an error in it is not in these runs)" if sd == 0
           else f"the release volume's error (relative sd {sd:g})" if sd is not None else "the release volume's error")
    ter = {"fine_terrain": "over the finer DEM given as fine_terrain",
           "interpolated": "over the DEM interpolated bilinearly (no fine_terrain given: what the DEM smooths of the "
                           "terrain is not in these runs)"}.get(nc.get("terrain"), "")
    L = ["## Thresholds set on null simulations of this design", "",
         f"{nc['n']} recordings made from the baseline (the posterior draws the verdict rests on, run on the finer "
         f"grid{' ' + ter if ter else ''}, {rel}, noise drawn from the stated error model: sigma with its correlation "
         "length) and diagnosed "
         "like the data; rule: " + nc["rule"] + ".", "",
         f"bf_min {th['bf_min']:.1f}, located_min {th['located_min']:.1f}, fit_max: {fm}.", "",
         "They know only the errors stated: an observable flagged against these fit_max levels fits worse than "
         "null data of the stated error model would, which a term outside the library does, and so does an error "
         "not stated (a release volume taken as exact, a DEM coarser than the terrain, a gauge's timing).", "",
         "| null case | largest lower 2 ln BF | best candidate | largest located | verdict (thresholds given) |",
         "|---|---|---|---|---|"]
    for i, c in enumerate(nc["cases"]):
        best = _best(c.get("lower_by_candidate"))
        L.append(f"| {i} | {_fmt(c['max_two_ln_bf_lower'], '{:.1f}')} | {best[0] if best else '-'} | "
                 f"{c['max_located']:.1f} | {c['verdict']}"
                 + (f" ({c['missing_physics']})" if c.get("missing_physics") else "") + " |")
    return L + [""] + _null_best_lines(nc["cases"], data_candidates)


def _fit_notes(residuals: dict, level: float = 3.0) -> list[str]:
    """Lines naming the observables whose baseline fit Z is beyond +-``level``: below, the likelihood's
    covariance is wider than the data need (every term's evidence is weaker than it could be); above, a
    mismatch beyond it."""
    wide = [f"{n} ({r['Z_fit']:.1f})" for n, r in residuals.items() if r.get("Z_fit") is not None and r["Z_fit"] <= -level]
    bad = [f"{n} ({r['Z_fit']:.1f})" for n, r in residuals.items() if r.get("Z_fit") is not None and r["Z_fit"] >= level]
    L = []
    if wide:
        L += ["", f"- The data fit better than the likelihood's covariance expects at {', '.join(wide)}: its sigmas "
                  "(or correlation lengths) are wider than these data need there, so every term's evidence is weaker "
                  "than it could be."]
    if bad:
        L += ["", f"- Mismatch beyond the likelihood's covariance at {', '.join(bad)}."]
    return L


def write_report(diag, out, conventions: dict | None = None) -> Path:
    """report.json (with ``conventions``, what its numbers measure, when given), report.md and figures."""
    from ..files import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    j = diag.to_json()
    if conventions is not None:
        j["conventions"] = conventions
    write_text_atomic(out / "report.json", json.dumps(j, indent=1))
    try:
        figs = write_figures(diag, out)
    except Exception as e:  # figures are a convenience; the report must still be written
        figs = []
        j.setdefault("warnings", []).append(f"figures failed: {e}")
    write_text_atomic(out / "report.md", write_markdown(j, figs))
    return out
