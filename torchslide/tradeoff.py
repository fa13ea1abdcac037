"""What the model cannot meet together: data that no run fits at once, from the runs a command made.

A calibration's runs cover the prior box; where a model cannot reproduce the recordings, some data pull
the parameters one way and others another (on msh2021 a long run-out needs a low friction that wets
twice the mapped area). A posterior that treats the model as right then settles on a compromise that
meets neither, and nothing tells the user. This module says it with numbers:

* ``conflicts``: for every pair of scalar observations (a, b) that some runs meet (|y - d| <= sigma,
  the stated sigma) but none meets together, the best run (largest z) that meets a and what it gives
  for b, and the other way round; every scalar that no run meets, with the closest run's value;
* ``front``: per run, the figures a modeller weighs against each other on a mapped event: the run-out
  from the release's crown and the share of the reached cells outside the mapped footprint
  (torchslide.survey), for the front figure (figures.plot_front).

Inputs are run records (torchslide.evaluator.RunRecord: x, predictions, z, figures) and the evaluator's
observation blocks; nothing is run here.
"""
from __future__ import annotations

import numpy as np


def _scalars(evaluator) -> list:
    """[(name, index in the data vector, recorded value, stated sd, unit)] of the scalar observations."""
    sd = evaluator.observation_sd()
    return [(b.name, b.start, float(evaluator.data_recorded[b.start]), float(sd[b.start]), b.obs.spec.unit)
            for b in evaluator.blocks if not b.is_vector]


def _ok(records) -> list:
    return [r for r in records if not r.failed and np.all(np.isfinite(r.predictions)) and np.isfinite(r.z)]


def _x(r, evaluator) -> dict:
    return {n: float(v) for n, v in zip(evaluator.names, r.x)}


def conflicts(records, evaluator) -> dict:
    """{"n_runs", "pairs": [...], "unmet": [...]} (module doc). Each pair: {"a", "b", "best_meeting_a":
    {"x", "value_b", "miss_b_sigma"}, "best_meeting_b": {"x", "value_a", "miss_a_sigma"}}; each unmet
    scalar: {"name", "value", "sigma", "closest", "miss_sigma", "x"}."""
    ok = _ok(records)
    data = _scalars(evaluator)
    out = {"n_runs": len(ok), "pairs": [], "unmet": []}
    if not ok or not data:
        return out
    P = np.array([r.predictions for r in ok])
    z = np.array([r.z for r in ok])
    miss = {name: (P[:, i] - v) / s for name, i, v, s, _ in data}
    met = {name: np.abs(m) <= 1.0 for name, m in miss.items()}
    info = {name: (i, v, s, unit) for name, i, v, s, unit in data}
    for name, m in miss.items():
        if not met[name].any():
            j = int(np.argmin(np.abs(m)))
            i, v, s, unit = info[name]
            out["unmet"].append({"name": name, "value": v, "sigma": s, "unit": unit, "closest": float(P[j, i]),
                                 "miss_sigma": float(m[j]), "x": _x(ok[j], evaluator)})
    names = [d[0] for d in data]
    for ia, a in enumerate(names):
        for b in names[ia + 1:]:
            if not met[a].any() or not met[b].any() or (met[a] & met[b]).any():
                continue
            ja = int(np.flatnonzero(met[a])[np.argmax(z[met[a]])])
            jb = int(np.flatnonzero(met[b])[np.argmax(z[met[b]])])
            out["pairs"].append({
                "a": a, "b": b,
                "best_meeting_a": {"x": _x(ok[ja], evaluator), "value_b": float(P[ja, info[b][0]]),
                                   "miss_b_sigma": float(miss[b][ja])},
                "best_meeting_b": {"x": _x(ok[jb], evaluator), "value_a": float(P[jb, info[a][0]]),
                                   "miss_a_sigma": float(miss[a][jb])}})
    for p in out["pairs"]:
        p["sentence"] = sentence(p, info)
    return out


def _fmt(v: float, unit: str) -> str:
    return f"{v:,.0f} {unit}" if abs(v) >= 100 else f"{v:.3g} {unit}"


def sentence(pair: dict, info: dict) -> str:
    """One line for a conflicting pair: "no run meets a and b together: the best run with a met gives b =
    ... (recorded ... +- ..., +k sigma); the best with b met gives a = ... (...)"."""
    a, b = pair["a"], pair["b"]
    _, va, sa, ua = info[a]
    _, vb, sb, ub = info[b]
    ma, mb = pair["best_meeting_a"], pair["best_meeting_b"]
    return (f"no run meets {a} and {b} together: the best run with {a} met gives {b} = {_fmt(ma['value_b'], ub)} "
            f"(recorded {_fmt(vb, ub)} +- {_fmt(sb, ub)}, {ma['miss_b_sigma']:+.1f} sigma); the best with {b} met "
            f"gives {a} = {_fmt(mb['value_a'], ua)} (recorded {_fmt(va, ua)} +- {_fmt(sa, ua)}, "
            f"{mb['miss_a_sigma']:+.1f} sigma)")


def lines(c: dict) -> list[str]:
    """The report's lines of ``conflicts``' result: each conflicting pair's sentence, each unmet datum."""
    out = [p["sentence"] for p in c["pairs"]]
    for u in c["unmet"]:
        out.append(f"no run of {c['n_runs']} meets {u['name']} ({_fmt(u['value'], u['unit'])} +- "
                   f"{_fmt(u['sigma'], u['unit'])}): the closest gives {_fmt(u['closest'], u['unit'])} "
                   f"({u['miss_sigma']:+.1f} sigma)")
    return out


def front(records, name: str | None = None) -> dict:
    """{"footprint": the mapped footprint's observation name, "x": [run parameters], "runout_m": (n,),
    "share_of_reached_unmapped": (n,), "jaccard": (n,), "mapped_runout_m"} over the records that carry
    survey figures (torchslide.survey.run_figures: the first footprint, or ``name``); None when none does."""
    ok = [r for r in _ok(records) if getattr(r, "figures", None)]
    if not ok:
        return None
    name = name or next(iter(ok[0].figures))
    f = [r.figures[name] for r in ok if name in r.figures]
    return {"footprint": name, "x": [np.asarray(r.x, float).tolist() for r in ok if name in r.figures],
            "runout_m": [g["runout_m"]["run"] for g in f],
            "share_of_reached_unmapped": [g["share_of_reached_unmapped"] for g in f],
            "jaccard": [g["footprint_jaccard"] for g in f], "mapped_runout_m": f[0]["runout_m"]["mapped"]}
