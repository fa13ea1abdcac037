"""The compact summary of a harness run: one row per case, the targets it is scored against.

``python -m experiments.hidden_physics.summary DIR [--out FILE]`` writes DIR/summary.json (or FILE)
from the case files ``<scenario>_s<seed>[_x<strength>].json`` the harness saved in DIR. The harness
writes it after every case, so a partial run has one too. The results page
(:mod:`experiments.hidden_physics.make_page`) is built from such summaries alone.

A case is a *strict success* (the target of the blind test, >= 4 of 5 seeds per scenario):

* null scenario: the verdict "nothing missing";
* out-of-library term (a low-friction patch) or a release larger than stated: no library term named;
* a library term: that term named, with 2 ln BF >= 6 over the runner-up, its switch's 90 % interval
  covering the truth, and the misfit reduced by the refit; or named in an "A or B" verdict (the
  evidence does not separate the alternatives) with its interval covering the truth.

Measured against detectability (the issue's criterion): a library term whose true switch is below the
smallest switch these recordings can reveal (the screening's detectable switch at the calibrated
baseline, torchslide.diagnose.screen.detectable_switch) counts as a success when no *other* library term
is named ("nothing missing" or "unexplained" are honest there); above it, only a strict success counts.
At that switch a term reaches bf_min in half the noise draws; ``power_switch`` is the one where it does in
four of five, the strength above which the 4-of-5 target applies. Both are measured on the solver
(torchslide.diagnose.power); ``lr_predicted`` / ``lr_found`` compare the prediction with the fits.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

MARGIN_MIN = 6.0
"""2 ln BF over the runner-up that a strict success needs."""

_SETTINGS = {"terrain": "narrow", "cellsize": 40.0, "sigmas": "harness", "fine_factor": 2, "fine_terrain": False,
             "budgets": {}, "device": "cpu"}
"""The settings of a run (harness options) and their defaults."""


def release_sd(case: dict) -> float:
    """The release volume's relative sd that a saved case's diagnosis was told (0: the release taken as exact)."""
    sd = case.get("release_volume_sd")
    return float((case.get("budgets") or {}).get("release_volume_sd", 0.0) if sd is None else sd)


def true_label(case: dict) -> str:
    """The hidden term of a case: "none", a library term, "unexplained" (the out-of-library patch) or
    "release_volume" (a release larger than stated)."""
    t = case["truth"]["term"]
    return "none" if t is None else ("unexplained" if t == "outside" else t)


def found_label(case: dict) -> str:
    """What the diagnosis said: "none", the named term, or "unexplained"."""
    j = case["diagnosis"]
    if j["verdict"] == "missing_physics":
        return j["missing_physics"]
    return "unexplained" if j["verdict"] == "unexplained" else "none"


def strict_success(case: dict) -> bool:
    """Whether a saved case meets the blind test's target (module doc)."""
    j = case["diagnosis"]
    tl = true_label(case)
    if tl == "none":
        return j["verdict"] == "no_missing_physics"
    if tl in ("unexplained", "release_volume"):
        return j["missing_physics"] in (None, "release_volume")
    alts = j["decision"].get("alternatives") or []
    if j["verdict"] == "missing_physics" and len(alts) > 1:
        return tl in alts and bool(case.get("true_term_covered_hdr90"))
    margin = j["decision"].get("two_ln_bf_over_runner_up")
    after = (j.get("fit_after") or {}).get("misfit")
    return (found_label(case) == tl and margin is not None and margin >= MARGIN_MIN
            and bool(case.get("true_term_covered_hdr90")) and after is not None
            and after < j["fit_before"]["misfit"])


def detectability(case: dict) -> tuple[float | None, float | None]:
    """(true switch, the smallest switch the case's recordings can reveal) of a library term, else (None, None)."""
    from .scenarios import SWITCH
    term = case["truth"]["term"]
    if term not in SWITCH:
        return None, None
    det = _detectable(case)
    truth = case["truth"].get(SWITCH[term])
    return (None if truth is None else float(truth)), (None if det.get("switch") is None else float(det["switch"]))


def _detectable(case: dict) -> dict:
    """The screening's detectable-switch entry of a case's hidden library term ({} where there is none)."""
    term = case["truth"]["term"]
    return ((case["diagnosis"].get("screening") or {}).get("candidates") or {}).get(term, {}).get("detectable_switch") or {}


def power_switch(case: dict) -> float | None:
    """The switch a case's recordings reveal in four noise draws of five (power.detectable_switch's
    ``switch_power``; from its whitened effect per unit switch, power.switch_threshold, where a case file has
    only that); None where :func:`detectability` has no true switch (null, patch, larger release)."""
    from torchslide.diagnose.candidates import CANDIDATES
    from torchslide.diagnose.power import switch_threshold
    if detectability(case)[0] is None:
        return None
    det = _detectable(case)
    if det.get("switch_power") is not None:
        return float(det["switch_power"])
    if det.get("per_unit") is None:
        return None
    term, j = case["truth"]["term"], case["diagnosis"]
    return float(switch_threshold(det["per_unit"], CANDIDATES[term].prior, j["thresholds"]["bf_min"])["switch_power"])


def lr_predicted_and_found(case: dict) -> tuple[float | None, float | None]:
    """(the noise-free 2 ln likelihood ratio the screening gives the hidden library term at its true switch, the
    one its fit found): power.lr_at (measured on the solver, or (a s)^2 in case files from the linearised
    prediction), against the fitted candidate's 2 ln (L_c / L_0). Their ratio measures the power the report's
    'detectable from' promises; (None, None) where there is no true switch, either is None where it was not
    recorded."""
    from torchslide.diagnose.power import lr_at
    truth = detectability(case)[0]
    if truth is None:
        return None, None
    det = _detectable(case)
    fit = next((c for c in case["diagnosis"].get("candidates") or () if c.get("name") == case["truth"]["term"]), {})
    lr = fit.get("likelihood_ratio")
    return (None if det.get("per_unit") is None else lr_at(det, truth)), (None if lr is None else float(lr))


def detectability_success(case: dict) -> bool:
    """Success measured against detectability (module doc)."""
    truth, det = detectability(case)
    if truth is None or det is None or truth >= det:
        return strict_success(case)
    return found_label(case) in ("none", "unexplained", true_label(case))


def case_row(case: dict) -> dict:
    """The compact row of one saved case."""
    j = case["diagnosis"]
    d = j.get("decision") or {}
    after = (j.get("fit_after") or {}).get("misfit")
    lr_predicted, lr_found = lr_predicted_and_found(case)
    return {"scenario": case["scenario"], "seed": int(case["seed"]), "strength": float(case.get("strength", 1.0)),
            "true": true_label(case), "found": found_label(case), "verdict": j["verdict"],
            "strict_success": strict_success(case), "two_ln_bf": d.get("two_ln_bf"),
            "two_ln_bf_over_runner_up": d.get("two_ln_bf_over_runner_up"),
            "true_term_covered_hdr90": case.get("true_term_covered_hdr90"),
            "misfit_before": j["fit_before"]["misfit"], "misfit_after": after,
            "inference": (d.get("inference") or {}).get("path", "emulator"), "wall_s": case.get("wall_s"),
            "true_switch": detectability(case)[0], "detectable_switch": detectability(case)[1],
            "power_switch": power_switch(case), "detectability_measured": bool(_detectable(case).get("measured"))
            if detectability(case)[0] is not None else None,
            "lr_predicted": lr_predicted, "lr_found": lr_found,
            "detectability_success": detectability_success(case)}


def summarise(folder) -> dict:
    """The summary of the cases in ``folder``: settings, the thresholds they were decided with, rows."""
    cases = []
    for p in sorted(Path(folder).glob("*_s*.json")):
        c = json.loads(p.read_text())
        if "diagnosis" in c:
            cases.append(c)
    if not cases:
        raise ValueError(f"{folder}: no harness case files (<scenario>_s<seed>.json)")
    first = cases[0]
    settings = {k: default if first.get(k) is None else first[k] for k, default in _SETTINGS.items()}
    settings["candidates"] = sorted(c["name"] for c in first["diagnosis"].get("candidates", ()))
    settings["release_volume_sd"] = release_sd(first)
    settings["budgets"] = {k: v for k, v in settings["budgets"].items() if k != "release_volume_sd"}
    return {"settings": settings,
            "thresholds": first["diagnosis"]["thresholds"],
            "cases": [case_row(c) for c in cases]}


def write_json(path, obj) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (a temporary file in the same folder, then a rename)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=1)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="compact summary of a harness run folder")
    p.add_argument("folder", help="the harness --out folder")
    p.add_argument("--out", default=None, help="summary file (default FOLDER/summary.json)")
    a = p.parse_args(argv)
    try:
        s = summarise(a.folder)
    except (OSError, ValueError) as e:
        p.error(str(e))
    out = Path(a.out) if a.out else Path(a.folder) / "summary.json"
    write_json(out, s)
    print(f"{len(s['cases'])} cases -> {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
