"""Build the blind test's results page from the run summaries: ``python -m experiments.hidden_physics.make_page
[--runs DIR] [--out DIR]``.

Reads every run summary ``DIR/*.json`` (summary.py; default results/ next to this file, one file per
harness run) and writes ``OUT/README.md`` and ``OUT/figures/`` (default: this folder): an overview of
every run against the targets, then per run the confusion matrix at strength 1, the detection rate
against the effect strength where the run has several, and the thresholds it was decided with.
Every number on the page comes from the summaries.
"""
from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from .scenarios import RELEASE_VOLUME_SD, SCENARIOS
from .summary import MARGIN_MIN

HERE = Path(__file__).parent
LABELS = ["none", "entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i", "deposition", "unexplained",
          "release_volume"]
TRUE_NAMES = {"none": "none (null)", "unexplained": "low-friction patch", "release_volume": "release +25 %"}
NOT_LIBRARY = ("none", "unexplained", "release_volume")   # true labels that are no library term
EITHER = "A or B"
FOUND_NAMES = {"none": "nothing missing", EITHER: "\"A or B\""}
"""How the confusion matrix labels the hidden terms and the verdicts."""
N_SEEDS = 5
TARGET = 4
"""A scenario's target: strict successes in at least TARGET of its N_SEEDS seeds at strength 1."""


def load_runs(folder) -> dict:
    """{run name: summary} of the summaries in ``folder``, ordered by name."""
    runs = {}
    for p in sorted(Path(folder).glob("*.json")):
        s = json.loads(p.read_text())
        if "cases" in s and "settings" in s:
            runs[p.stem] = s
    return runs


def evaluation_rows(summary: dict, strength: float = 1.0) -> list[dict]:
    """The rows of the reported seeds (0 to N_SEEDS - 1) at ``strength``."""
    return [r for r in summary["cases"] if r["strength"] == strength and r["seed"] < N_SEEDS]


def scenario_counts(rows: list[dict]) -> dict:
    """{scenario: (strict successes, cases)} in SCENARIOS' order, scenarios without cases left out."""
    out = {}
    for sc in SCENARIOS:
        rs = [r for r in rows if r["scenario"] == sc]
        if rs:
            out[sc] = (sum(r["strict_success"] for r in rs), len(rs))
    return out


def targets_met(counts: dict) -> tuple[int, int]:
    """(scenarios meeting the target, scenarios with all N_SEEDS seeds)."""
    full = [k for k, (_, n) in counts.items() if n >= N_SEEDS]
    return sum(counts[k][0] >= TARGET for k in full), len(full)


def _found(row: dict) -> str:
    """A row's verdict label; every "A or B" verdict is one column."""
    return EITHER if " or " in row["found"] else row["found"]


def confusion(rows: list[dict]) -> tuple[list[str], list[str], np.ndarray]:
    """(true labels, found labels, counts (len(true), len(found))) of ``rows``."""
    true = [l for l in LABELS if any(r["true"] == l for r in rows)]
    found = [l for l in LABELS + [EITHER] if any(_found(r) == l for r in rows) or l in true]
    M = np.zeros((len(true), len(found)), int)
    for r in rows:
        M[true.index(r["true"]), found.index(_found(r))] += 1
    return true, found, M


def describe(settings: dict) -> str:
    s = f"{settings['terrain']} terrain, {settings['cellsize']:g} m cells"
    if settings.get("fine_terrain"):
        s += ", the recording grid's terrain for the grid-error runs (and their rounds)"
    if "release_volume" in settings.get("candidates", ()):
        s += ", a larger release weighed"
    sd = settings.get("release_volume_sd", 0.0)
    s += f", the release's error stated (sd {sd:g})" if sd else ", the release taken as exact"
    if settings.get("sigmas", "harness") != "harness":
        s += ", likelihood sigmas = the noise drawn"
    if settings.get("budgets"):
        s += ", budgets " + ", ".join(f"{k}={v}" for k, v in settings["budgets"].items())
    return s


def command(summary: dict) -> str:
    """The harness command(s) that make the run of ``summary``: one per group of cases that share their
    strengths and seeds (e.g. the strength-1 seeds, extra null seeds, a ladder of strengths), joined by "; "."""
    settings = summary["settings"]
    base = f"python -m experiments.hidden_physics.harness --terrain {settings['terrain']} --cellsize {settings['cellsize']:g}"
    if settings.get("fine_terrain"):
        base += " --fine-terrain"
    if settings.get("sigmas", "harness") != "harness":
        base += f" --sigmas {settings['sigmas']}"
    for k, v in (settings.get("budgets") or {}).items():
        base += f" --budget {k}={v}"
    if settings.get("release_volume_sd", 0.0) != RELEASE_VOLUME_SD:
        base += f" --budget release_volume_sd={settings.get('release_volume_sd', 0.0):g}"
    groups: dict = {}
    for sc in SCENARIOS:
        rs = [r for r in summary["cases"] if r["scenario"] == sc]
        for x in sorted({r["strength"] for r in rs}):
            seeds = tuple(sorted({r["seed"] for r in rs if r["strength"] == x}))
            groups.setdefault((x, seeds), []).append(sc)
    merged: dict = {}       # strengths that share seeds and scenarios go in one command
    for (x, seeds), scs in groups.items():
        merged.setdefault((seeds, tuple(scs)), []).append(x)
    out = []
    for (seeds, scs), xs in merged.items():
        c = base
        if xs != [1.0]:
            c += " --strengths " + ",".join(f"{x:g}" for x in xs)
        if list(seeds) != list(range(N_SEEDS)):
            c += " --seed-list " + ",".join(str(v) for v in seeds)
        if list(scs) != list(SCENARIOS):
            c += " --scenarios " + ",".join(scs)
        out.append(c + " --out DIR")
    return "; ".join(out)


def _plot_confusion(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    true, found, M = confusion(rows)
    fig, ax = plt.subplots(figsize=(1.6 + 0.9 * len(found), 1.2 + 0.55 * len(true)))
    ax.imshow(M, cmap="Blues", vmin=0)
    for i in range(len(true)):
        for j in range(len(found)):
            ax.text(j, i, str(M[i, j]), ha="center", va="center", color="white" if M[i, j] > M.max() / 2 else "black")
    ax.set_xticks(range(len(found)), [FOUND_NAMES.get(f, f) for f in found], rotation=40, ha="right")
    ax.set_yticks(range(len(true)), [TRUE_NAMES.get(t, t) for t in true])
    ax.set_xlabel("verdict of the diagnosis")
    ax.set_ylabel("hidden term")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _plot_strength(summary: dict, path: Path, title: str) -> None:
    """Rate of the true term named (solid) and of any verdict but "nothing missing" (dashed) per strength."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = [r for r in summary["cases"] if r["seed"] < N_SEEDS and r["true"] != "none"]
    terms = [l for l in LABELS if any(r["true"] == l for r in rows)]
    fig, ax = plt.subplots(figsize=(7.5, 3.4))
    for i, term in enumerate(terms):
        rs = [r for r in rows if r["true"] == term]
        xs = sorted({r["strength"] for r in rs})
        dx = 0.02 * (i - (len(terms) - 1) / 2)      # side by side, so that equal rates stay visible
        label = {"unexplained": "low-friction patch (out of library)",
                 "release_volume": "release larger than stated"}.get(term, term)
        seen = [np.mean([r["found"] != "none" for r in rs if r["strength"] == x]) for x in xs]
        if term not in NOT_LIBRARY:
            named = [np.mean([r["found"] == term for r in rs if r["strength"] == x]) for x in xs]
            ax.plot([x + dx for x in xs], named, "os^vD*"[i % 6] + "-", color=f"C{i}", label=f"{label}: named")
        ax.plot([x + dx for x in xs], seen, "os^vD*"[i % 6] + "--", color=f"C{i}", mfc="none",
                label=f"{label}: not 'nothing missing'")
    ax.set_xlabel("strength of the hidden term (multiple of its nominal value)")
    ax.set_ylabel("share of seeds")
    ax.set_ylim(-0.05, 1.05)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def ladder_rows(summary: dict) -> list[dict]:
    """Per library term and strength: seeds, the median of true switch / detectable switch, and how many
    seeds named the term alone, in an "A or B" verdict, named other library terms only, or said "nothing
    missing" / "unexplained"."""
    out = []
    rows = [r for r in summary["cases"] if r["true"] in LABELS and r["true"] not in NOT_LIBRARY]
    for term in [l for l in LABELS if any(r["true"] == l for r in rows)]:
        for x in sorted({r["strength"] for r in rows if r["true"] == term}):
            rs = [r for r in rows if r["true"] == term and r["strength"] == x]
            ratios = [r["true_switch"] / r["detectable_switch"] for r in rs
                      if r.get("true_switch") is not None and r.get("detectable_switch")]
            out.append({"term": term, "strength": x, "n": len(rs),
                        "ratio_median": float(np.median(ratios)) if ratios else None,
                        "named": sum(r["found"] == term for r in rs),
                        "in_either": sum(r["found"] != term and term in r["found"].split(" or ") for r in rs),
                        "strict": sum(bool(r["strict_success"]) for r in rs),
                        "other_term": sum(r["found"] not in ("none", "unexplained") and
                                          term not in r["found"].split(" or ") for r in rs),
                        "quiet": sum(r["found"] in ("none", "unexplained") for r in rs)})
    return out


def _ladder_section(summary: dict) -> list[str]:
    L = ["Detection against detectability: each library term at several strengths (multiples of its nominal "
         "switch); 'true / detectable' is the median over the seeds of the true switch over the smallest switch "
         "the case's recordings can reveal (the screening's detectable switch at the baseline).", "",
         "| term | strength | true / detectable | named | in \"A or B\" | strict successes | another term named | "
         "nothing missing or unexplained |", "|---|---|---|---|---|---|---|---|"]
    for r in ladder_rows(summary):
        ratio = "-" if r["ratio_median"] is None else f"{r['ratio_median']:.2g}"
        L.append(f"| {r['term']} | {r['strength']:g} | {ratio} | {r['named']}/{r['n']} | {r['in_either']}/{r['n']} | "
                 f"{r['strict']}/{r['n']} | "
                 f"{r['other_term']}/{r['n']} | {r['quiet']}/{r['n']} |")
    return L + [""]


def _overview(runs: dict) -> list[str]:
    L = ["| run | " + " | ".join(SCENARIOS) + " | targets met |", "|---" * (len(SCENARIOS) + 2) + "|"]
    for name, s in runs.items():
        counts = scenario_counts(evaluation_rows(s))
        if not counts:
            continue
        cells = []
        for sc in SCENARIOS:
            if sc not in counts:
                cells.append("-")
                continue
            k, n = counts[sc]
            cells.append(f"**{k}/{n}**" if n >= N_SEEDS and k >= TARGET else f"{k}/{n}")
        met, full = targets_met(counts)
        seeds = sorted({r["seed"] for r in evaluation_rows(s)})
        total = (f"{met} of {len(SCENARIOS)}" if full == len(SCENARIOS) else
                 f"partial run: {len(counts)} scenario{'s' if len(counts) > 1 else ''}, seeds {seeds[0]}-{seeds[-1]}")
        L.append(f"| `{name}`: {describe(s['settings'])} | " + " | ".join(cells) + f" | {total} |")
    return L


def _lr_ratio(rows: list[dict]) -> str:
    """The median over ``rows`` of the fitted 2 ln LR over the predicted one, with its range; '-' where none has both."""
    q = [r["lr_found"] / r["lr_predicted"] for r in rows if r.get("lr_found") is not None and r.get("lr_predicted")]
    return f"{np.median(q):.2f} ({min(q):.2f}-{max(q):.2f})" if q else "-"


def _run_section(name: str, s: dict, figdir: Path, out: Path) -> list[str]:
    rows = evaluation_rows(s)
    strengths = sorted({r["strength"] for r in s["cases"]})
    L = [f"## `{name}`: {describe(s['settings'])}", "", f"Made by `{command(s)}`; "
         f"{len(s['cases'])} cases, decided with the thresholds "
         + ", ".join(f"{k} {v:.3g}" for k, v in s["thresholds"].items() if isinstance(v, (int, float))) + ".", ""]
    if rows:
        L += ["| scenario | strict successes | verdicts (count) | true switch / detectable from (seeds) | "
              "successes against detectability | strict successes above the 4-in-5 switch | 2 ln LR found / predicted "
              "(median) |", "|---|---|---|---|---|---|---|"]
        for sc, (k, n) in scenario_counts(rows).items():
            rs = [r for r in rows if r["scenario"] == sc]
            found = Counter(r["found"] for r in rs)
            det = ", ".join(f"{r['true_switch']:.3g} / {r['detectable_switch']:.3g}" for r in rs
                            if r.get("true_switch") is not None and r.get("detectable_switch") is not None) or "-"
            ds = sum(bool(r.get("detectability_success")) for r in rs)
            above = [r for r in rs if r.get("power_switch") is not None and r["true_switch"] >= r["power_switch"]]
            pw = f"{sum(bool(r['strict_success']) for r in above)}/{len(above)}" if above else "-"
            L.append(f"| {sc} | {k}/{n} | " + ", ".join(f"{f} {c}" for f, c in sorted(found.items()))
                     + f" | {det} | {ds}/{n} | {pw} | {_lr_ratio(rs)} |")
        L += ["", "'Against detectability': below the smallest switch the recordings can reveal (the screening's "
              "detectable switch at the calibrated baseline), a case succeeds when no other library term is named; "
              "above it, only a strict success counts (summary.py). There a term reaches bf_min in half the noise "
              "draws; the sixth column counts the seeds whose true switch is at least the one it reaches in four of "
              "five (summary.power_switch; '-' where none is, or the run's summary predates it). Both rest on the "
              "2 ln likelihood ratio that noise-free data of the term's model give against the refitted baseline, "
              "measured on the solver near those switches (torchslide/diagnose/power.py); the last column is the "
              "median over the seeds of the fitted one at the true switch over it (summary.lr_predicted_and_found): "
              "below 1, the recordings reveal the term less than the report's 'detectable from' promises.", ""]
        f = figdir / f"confusion_{name}.png"
        _plot_confusion(rows, f, f"{name}: strength 1, seeds 0-{N_SEEDS - 1}")
        L += ["", f"![confusion matrix, {name}]({f.relative_to(out).as_posix()})", ""]
    nulls = [r for r in s["cases"] if r["true"] == "none"]
    if nulls:
        seeds = sorted(r["seed"] for r in nulls)
        named = sum(r["found"] not in ("none", "unexplained") for r in nulls)
        L += [f"Null seeds ({', '.join(map(str, seeds))}): nothing missing in "
              f"{sum(r['found'] == 'none' for r in nulls)} of {len(nulls)}, a library term named (false naming) "
              f"in {named}, unexplained in {sum(r['found'] == 'unexplained' for r in nulls)}.", ""]
    if len(strengths) > 1:
        f = figdir / f"detection_vs_strength_{name}.png"
        _plot_strength(s, f, f"{name}: detection against strength")
        L += _ladder_section(s)
        L += [f"![detection against strength, {name}]({f.relative_to(out).as_posix()})", ""]
    paths = Counter(r.get("inference", "emulator") for r in s["cases"])
    L += ["Inference (torchslide/diagnose/pipeline.py): " + ", ".join(
        f"{'local fits on the solver' if k == 'local' else 'GP emulator'} in {v} of {len(s['cases'])} cases"
        for k, v in sorted(paths.items())) + ".", ""]
    lib = [r for r in s["cases"] if r.get("detectability_measured") is not None]     # none in older summaries
    if lib:
        m = sum(bool(r.get("detectability_measured")) for r in lib)
        L += [f"Detectable switches measured on the solver (torchslide/diagnose/power.py; saved cases measured again "
              f"by `python -m experiments.hidden_physics.redetect`) in {m} of the {len(lib)} cases with a hidden "
              f"library term; the others are the screening's linearised prediction.", ""]
    walls = [r["wall_s"] for r in s["cases"] if r.get("wall_s") is not None]
    if walls:
        L += [f"Wall time per case: median {np.median(walls):.0f} s, range {min(walls):.0f}-{max(walls):.0f} s "
              f"(device {s['settings'].get('device', 'cpu')}).", ""]
    return L


def build_page(runs_dir=HERE / "results", out=HERE, thresholds_file=HERE / "thresholds.json") -> Path:
    """Write ``out``/README.md and ``out``/figures from the run summaries in ``runs_dir``; returns the page."""
    out = Path(out)
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    runs = load_runs(runs_dir)
    L = ["# The blind test of the diagnosis", "",
         "Generated by `python -m experiments.hidden_physics.make_page` from the run summaries in "
         "`results/`; do not edit by hand. A run's summary is the `summary.json` the harness writes into its "
         "`--out` folder (`python -m experiments.hidden_physics.summary DIR` rebuilds it from the case files), "
         "kept here as `results/<run>.json`.", "",
         "Each case hides one term (or none) in recordings made on cells half the size of the inversion grid, "
         "adds noise and a release-volume error of U(0.9, 1.1), and runs `torchslide.diagnose` without telling it "
         "the scenario (scenarios.py, harness.py). The recordings: a deposit map, gauge series (flow thickness "
         "and speed every 2 s; two gauges on the channels, three on the fan terrain) and the final volume. The "
         "terrains: the narrow S-bend channel and the bend-to-fan terrain (a steep channel with one 60 deg bend "
         "onto a fan, an erodible reach through the bend), each with its thresholds set on its own null seeds "
         "100-104. Library: entrainment, curvature, earth pressure, yield stress, "
         "mu(I); the low-friction patch lies outside it, and so does a release 25 % larger than stated (an input "
         "error).", "",
         "A **strict success**: for the null scenario \"nothing missing\"; for the out-of-library patch and the "
         f"larger release no library name; for a library term that term named with 2 ln BF >= {MARGIN_MIN:g} over the runner-up, its 90 % "
         "interval covering the true switch, and the misfit reduced. **Target**: at least "
         f"{TARGET} of {N_SEEDS} seeds per scenario, at strength 1 (bold where met).", "",
         "## Every run against the targets", ""]
    if not runs:
        L.append("No run summaries.")
    L += _overview(runs) + [""]
    for name, s in runs.items():
        L += _run_section(name, s, figdir, out)
    thf = Path(thresholds_file)
    if thf.exists():
        t = json.loads(thf.read_text())
        L += ["## The harness' default thresholds", "",
              "`thresholds.json`, set by `python -m experiments.hidden_physics.calibrate_thresholds` on null seeds "
              "100-104 (never reported):", "", "```", t["rule"], "```", "",
              "| null case | largest lower-bound 2 ln BF | largest located score |", "|---|---|---|"]
        L += [f"| {r['case']} | {r['max_two_ln_bf_lower']:.1f} | {r['max_located']:.1f} |" for r in t["null_cases"]]
        L += ["", "Thresholds: " + ", ".join(f"{k} {v:.3g}" for k, v in t["thresholds"].items()
                                              if isinstance(v, (int, float))) + ".", ""]
    page = out / "README.md"
    page.write_text("\n".join(L) + "\n")
    return page


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="the blind test's results page from run summaries")
    p.add_argument("--runs", default=str(HERE / "results"), help="folder of run summaries (summary.py)")
    p.add_argument("--out", default=str(HERE), help="where README.md and figures/ go")
    p.add_argument("--thresholds", default=str(HERE / "thresholds.json"), help="the default thresholds shown")
    a = p.parse_args(argv)
    print(build_page(a.runs, a.out, a.thresholds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
