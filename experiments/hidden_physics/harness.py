"""The blind test of the diagnosis: ``python -m experiments.hidden_physics.harness --out DIR
[--terrain narrow|resolved|fan] [--cellsize M] [--seeds N | --seed-list 100,101] [--scenarios a,b]
[--strengths 0.5,1,2] [--sigmas harness|noise] [--budget NAME=VALUE ...] [--thresholds FILE|defaults]
[--device cuda] [--max-batch N] [--compile]``.

Each case: make a recording (scenarios.make_recording: a hidden term, a finer grid, noise, a release
error), run torchslide.diagnose on it without telling it the scenario, save DIR/<case>.json (+ .npz
with the before/after maps and gauge series), and refresh DIR/summary.json (summary.py). Cases already
saved are skipped, so an interrupted run resumes; a case being run is marked DIR/<case>.running, so
several processes can share one DIR.

Decision thresholds: ``--thresholds`` (default: the design's file next to this one, thresholds.json for
the narrow channel and thresholds_<terrain>.json for the others, ``_fine`` added with ``--fine-terrain``;
written by calibrate_thresholds.py from null seeds that are not reported). Any other design (cell size, sigmas, budgets) needs thresholds from
its own null seeds.
"""
from __future__ import annotations

import argparse
import functools
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets, Thresholds, check_budgets, diagnose
from torchslide.diagnose.candidates import CANDIDATES

from . import scenarios
from .scenarios import (RELEASE_VOLUME_SD, SCENARIOS, SIGMAS, SWITCH, TERRAINS, make_evaluator, make_recording,
                        noise_sigmas, terrain_variant)
from .summary import summarise, write_json

LIBRARY = ["entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i"]
CANDIDATE_NAMES = LIBRARY + ["release_volume"]
"""What the diagnosis weighs in every case: the library's terms and, as the CLI's defaults do, a release larger
than stated (an input error that a term adding mass could be mistaken for)."""
HARNESS_BUDGETS = dict(n_posterior_samples=16, n_posterior_samples_after=12, n_initial=12, n_total=24, n_total_max=36,
                       baseline_n_initial=10, baseline_n_total=16, batch_size=8, top_k=len(CANDIDATE_NAMES),
                       n_perm=49, release_volume_sd=RELEASE_VOLUME_SD)
"""The diagnosis' budgets in every case; the release's error is stated as drawn (scenarios.RELEASE_VOLUME_SD)."""
THRESHOLDS_FILE = Path(__file__).parent / "thresholds.json"


def thresholds_file(terrain: str = "narrow", fine_terrain: bool = False) -> Path:
    """The harness' thresholds file of ``terrain`` (each design's are set on its own null seeds; with
    ``fine_terrain`` the diagnosis runs its grid-error rounds, another design: "_fine")."""
    stem = ("thresholds" if terrain == "narrow" else f"thresholds_{terrain}") + ("_fine" if fine_terrain else "")
    return THRESHOLDS_FILE.with_name(f"{stem}.json")


def load_thresholds(path=THRESHOLDS_FILE) -> Thresholds:
    """The decision thresholds of a calibrate_thresholds.py file; the defaults when it does not exist."""
    path = Path(path)
    if not path.exists():
        return Thresholds()
    return Thresholds(**json.loads(path.read_text())["thresholds"])


def unlike_design(path, release_volume_sd: float = RELEASE_VOLUME_SD) -> str | None:
    """Why the thresholds file ``path`` does not fit the harness' cases: its null cases weighed other candidates
    than CANDIDATE_NAMES, or stated another release error than ``release_volume_sd`` (a thresholds file holds
    for the design it was set on); None when they match or the file does not exist."""
    path = Path(path)
    if not path.exists():
        return None
    t = json.loads(path.read_text())
    set_on, sd = t.get("candidates"), t.get("release_volume_sd")
    why = []
    if sorted(set_on or ()) != sorted(CANDIDATE_NAMES):
        why.append(f"weighed {', '.join(set_on) if set_on else 'candidates not recorded'} (the cases weigh "
                   f"{', '.join(CANDIDATE_NAMES)})")
    if sd is None or abs(sd - release_volume_sd) > 1e-12:
        why.append(f"stated release_volume_sd {'not recorded' if sd is None else f'{sd:g}'} (the cases "
                   f"{release_volume_sd:g})")
    if not why:
        return None
    return (f"{path} was set on null cases that {' and '.join(why)}: set it again on their null seeds "
            f"(calibrate_thresholds.py)")


def out_of_range(scenario: str, strength: float) -> str | None:
    """Why ``scenario`` cannot be recorded at ``strength`` (its scaled switch beyond the switch's range,
    e.g. earth pressure or curvature above 1), else None."""
    term, hidden = SCENARIOS[scenario]
    if term not in SWITCH:
        return None
    v = hidden[SWITCH[term]] * strength
    lo, hi = CANDIDATES[term].prior
    if not lo <= v <= hi:
        return f"switch {SWITCH[term]} = {v:g} beyond its range [{lo:g}, {hi:g}]"
    return None


def coverage(diag: dict, truth: dict, volume_factor: float = 1.0) -> tuple:
    """(true switch in the 90 % interval the diagnosis reports: the profile-likelihood interval where it was
    profiled, else the HDI; true switch in the 'hdr90' interval) of the true term's refit in a
    report.json-style ``diag``; (None, None) when the scenario has no library term or it was not refitted.
    A larger release's true switch is its excess over the stated release, (1 + release_scale) x
    ``volume_factor`` - 1 (the case's drawn release error included).
    The HDI is taken on the prior range (it may include a prior bound, e.g. earth pressure = 1), with a
    tolerance of 1e-9 of the prior width for a grid's last cell edge."""
    term = truth["term"]
    if term not in CANDIDATES:
        return None, None
    param = CANDIDATES[term].param
    c = next((c for c in diag["candidates"] if c["name"] == term), None)
    par = c["parameters"].get(param) if c else None
    if not par:
        return None, None
    lo_p, hi_p = CANDIDATES[term].prior
    tol = 1e-9 * (hi_p - lo_p)
    v = truth[param] if term != "release_volume" else (1.0 + truth[param]) * volume_factor - 1.0
    lo, hi = par.get("profile90") or par.get("hdi90", par["hdr90"])
    lo_e, hi_e = par["hdr90"]
    return bool(lo - tol <= v <= hi + tol), bool(lo_e - tol <= v <= hi_e + tol)


def case_tag(scenario: str, seed: int, strength: float = 1.0) -> str:
    return f"{scenario}_s{seed}" + ("" if strength == 1.0 else f"_x{strength:g}")


def run_case(scenario: str, seed: int, out, cellsize: float = 40.0, strength: float = 1.0,
             budgets: dict | None = None, candidates=None, log=print, thresholds: Thresholds | None = None,
             fine_terrain: bool = False, device: str = "cpu", max_batch: int = 16, fine_factor: int = 2,
             compile_solver: bool = False, sigmas: str = "harness") -> dict:
    """One blind case: the recording, the diagnosis, the case JSON (and its maps) in ``out``. ``sigmas``
    "noise": the likelihood's sigmas are the noise drawn (scenarios.noise_sigmas)."""
    if sigmas not in SIGMAS:
        raise ValueError(f"sigmas must be one of {SIGMAS}, got {sigmas!r}")
    t0 = time.perf_counter()
    out = Path(out)
    rec = make_recording(scenario, seed, cellsize=cellsize, strength=strength, fine_factor=fine_factor)
    if sigmas == "noise":
        rec = dataclasses.replace(rec, observations=noise_sigmas(rec.observations))
    ev = make_evaluator(rec, cellsize=cellsize, fine_terrain=fine_terrain, device=device, max_batch=max_batch,
                        compile_solver=compile_solver)
    bud = Budgets(**{**HARNESS_BUDGETS, **(budgets or {}), "seed": seed})
    d = diagnose(ev, candidates or CANDIDATE_NAMES, bud, thresholds or load_thresholds(), log=log)
    j = d.to_json()
    cover, cover_eq = coverage(j, rec.truth, rec.volume_factor)
    case = {"scenario": scenario, "seed": seed, "strength": strength, "cellsize": cellsize, "terrain": scenarios.TERRAIN,
            "fine_terrain": fine_terrain, "fine_factor": fine_factor, "sigmas": sigmas, "device": str(device),
            "compile_solver": compile_solver, "budgets": budgets or {}, "truth": rec.truth,
            "release_volume_sd": bud.release_volume_sd, "volume_factor": rec.volume_factor,
            "true_term_covered_hdr90": cover,
            "true_term_covered_equal_tailed90": cover_eq, "wall_s": time.perf_counter() - t0, "diagnosis": j}
    tag = case_tag(scenario, seed, strength)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{tag}.json", case)
    arrays = {}
    for stage, loc in (("before", d.localisation), ("after", d.after_localisation)):
        for name, m in (loc.maps.items() if loc is not None else ()):
            for k, v in m.items():
                arrays[f"{stage}/{name}/{k}"] = np.asarray(v)
    np.savez_compressed(out / f"{tag}.npz", **arrays)
    return case


def parse_budgets(items) -> dict:
    """``["local_max_iter=40", ...]`` -> {field: value} of torchslide.diagnose.Budgets, each value
    converted to the field's type; ValueError naming the item otherwise."""
    fields = {f.name: f for f in dataclasses.fields(Budgets)}
    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"--budget {item!r}: expected NAME=VALUE with NAME a Budgets field "
                             f"({', '.join(sorted(fields))})")
        default = getattr(Budgets(), name)
        kind = int if default is None else type(default)
        try:
            out[name] = (value.lower() in ("1", "true", "yes")) if kind is bool else kind(value)
        except (TypeError, ValueError):
            raise ValueError(f"--budget {item!r}: {name} needs a {kind.__name__}") from None
    return out


def _write_summary(out: Path) -> None:
    """Refresh ``out``/summary.json from the cases saved there (none yet: nothing written)."""
    try:
        write_json(out / "summary.json", summarise(out))
    except ValueError:
        pass


def _claim(out: Path, tag: str) -> Path | None:
    """Mark case ``tag`` as taken by this process (``out/<tag>.running``, created atomically) so that
    several harness processes on one ``out`` share the cases; None when another process holds it."""
    out.mkdir(parents=True, exist_ok=True)
    f = out / f"{tag}.running"
    try:
        f.open("x").close()
    except FileExistsError:
        return None
    return f


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="blind test of torchslide diagnose on synthetic recordings")
    p.add_argument("--out", required=True, help="folder of the case files and summary.json")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--seed-list", default=None, help="comma-separated seeds (overrides --seeds)")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--strengths", default="1", help="comma-separated multiples of each hidden term's nominal value")
    p.add_argument("--terrain", default="narrow", choices=sorted(TERRAINS))
    p.add_argument("--cellsize", type=float, default=40.0, help="inversion cell size, m (recordings on half of it)")
    p.add_argument("--fine-factor", type=int, default=2,
                   help="recording grid = inversion cells / this; 1 records on the inversion grid itself (the "
                        "control without discretisation error, with --budget model_error_runs=0 "
                        "--budget release_volume_sd=0)")
    p.add_argument("--fine-terrain", action="store_true",
                   help="give the diagnosis the terrain on the recording grid for its model-error runs")
    p.add_argument("--sigmas", default="harness", choices=SIGMAS,
                   help="the likelihood's sigmas: the harness' (1.7-4 times the noise drawn) or the noise drawn")
    p.add_argument("--budget", action="append", default=[], metavar="NAME=VALUE",
                   help="override a torchslide.diagnose.Budgets field (repeatable)")
    p.add_argument("--thresholds", default=None,
                   help="decision thresholds file (default: the terrain's, thresholds[_<terrain>].json here), or "
                        "\"defaults\": the diagnosis' own defaults, as `torchslide diagnose` decides")
    p.add_argument("--device", default="cpu", help="solver device of the diagnosis (cpu, cuda, ...)")
    p.add_argument("--max-batch", type=int, default=16, help="most members per solver call")
    p.add_argument("--compile", action="store_true", help="torch.compile the diagnosis' solver steps")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run the cases as tasks of a Dask LocalCluster of N processes (torchslide.executor)")
    p.add_argument("--scheduler", default=None, metavar="ADDR", help="... or of the Dask cluster at ADDR")
    a = p.parse_args(argv)
    if a.workers is not None and a.workers < 1:
        p.error(f"--workers must be >= 1, got {a.workers}")
    if a.max_batch < 1:
        p.error(f"--max-batch must be >= 1, got {a.max_batch}")
    if a.fine_factor < 1:
        p.error(f"--fine-factor must be >= 1, got {a.fine_factor}")
    try:
        budgets = parse_budgets(a.budget)
        check_budgets(Budgets(**{**HARNESS_BUDGETS, **budgets}))
        seeds = [int(v) for v in a.seed_list.split(",")] if a.seed_list else list(range(a.seeds))
        strengths = [float(s) for s in a.strengths.split(",")]
    except ValueError as e:
        p.error(str(e))
    unknown = [s for s in a.scenarios.split(",") if s not in SCENARIOS]
    if unknown:
        p.error(f"--scenarios: unknown {unknown} (known: {', '.join(SCENARIOS)})")
    with terrain_variant(a.terrain):
        return _run_all(a, budgets, seeds, strengths)


def _case(a, budgets: dict, th: Thresholds, item: tuple) -> tuple:
    """One case (scenario, seed, strength) run and saved in a.out, unless saved or held by another process
    (its claim file): (tag, verdict, missing physics, wall s) or (tag, why skipped, None, 0)."""
    sc, seed, strength = item
    out = Path(a.out)
    tag = case_tag(sc, seed, strength)
    if (out / f"{tag}.json").exists():
        return tag, "done before", None, 0.0
    claim = _claim(out, tag)
    if claim is None:
        return tag, f"skipped, another process holds {out / (tag + '.running')} (delete it if that process is gone)", \
            None, 0.0
    print(f"=== {tag}", flush=True)
    try:
        with terrain_variant(a.terrain):
            c = run_case(sc, seed, out, cellsize=a.cellsize, strength=strength, budgets=budgets or None,
                         thresholds=th, fine_terrain=a.fine_terrain, device=a.device, max_batch=a.max_batch,
                         fine_factor=a.fine_factor, compile_solver=a.compile, sigmas=a.sigmas,
                         log=lambda s: print(s, flush=True))
    finally:
        claim.unlink(missing_ok=True)
    _write_summary(out)
    return tag, c["diagnosis"]["verdict"], c["diagnosis"]["missing_physics"], c["wall_s"]


def _thresholds_of(path: Path, release_volume_sd: float) -> Thresholds:
    """The thresholds of file ``path`` (the defaults where it does not exist), saying when it is missing or
    was set on another design."""
    if not path.exists():
        print(f"=== {path} does not exist: the cases are decided with the default thresholds (set this terrain's "
              f"on its null seeds with calibrate_thresholds.py)", flush=True)
    unlike = unlike_design(path, release_volume_sd)
    if unlike:
        print(f"=== {unlike}", flush=True)
    return load_thresholds(path)


def _run_all(a, budgets: dict, seeds: list, strengths: list) -> int:
    """Every case of seeds x strengths x scenarios: one after another, or as tasks of a Dask cluster
    (--workers / --scheduler; the cases' files and claims are on this machine's ``out``)."""
    if a.thresholds == "defaults":
        th = Thresholds()
        print("=== the cases are decided with the diagnosis' default thresholds", flush=True)
    else:
        th = _thresholds_of(Path(a.thresholds) if a.thresholds else thresholds_file(a.terrain, a.fine_terrain),
                            {**HARNESS_BUDGETS, **budgets}["release_volume_sd"])
    items = []
    for seed in seeds:
        for strength in strengths:
            for sc in a.scenarios.split(","):
                beyond = out_of_range(sc, strength)
                if beyond:
                    print(f"=== {case_tag(sc, seed, strength)}: skipped, {beyond}", flush=True)
                else:
                    items.append((sc, seed, strength))
    fn = functools.partial(_case, a, budgets, th)
    if a.workers is None and a.scheduler is None:
        results = []
        for it in items:
            results.append(fn(it))
            _report(results[-1])
        return 0
    from torchslide.executor import DaskExecutor

    ex = DaskExecutor(scheduler=a.scheduler, workers=a.workers)
    try:
        for r in ex.map(fn, items, progress=True, desc="cases"):
            _report(r)
    finally:
        ex.close()
    _write_summary(Path(a.out))
    return 0


def _report(r: tuple) -> None:
    tag, verdict, named, wall = r
    if verdict != "done before":
        print(f"=== {tag}: {verdict}" + (f" {named} ({wall:.0f} s)" if wall else ""), flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
