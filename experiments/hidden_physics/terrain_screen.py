"""Would another terrain of the same family put a hidden term within reach? ``python -m
experiments.hidden_physics.terrain_screen [--scenario curvature] [--variants NAME=key:value;...,...]
[--search-iters N] [--sigmas harness|noise] [--out FILE]``

For each terrain variant (a harness terrain, ``narrow`` or ``resolved``, with some of its
channel_with_bends keywords changed, e.g. ``resolved_theta35=resolved;theta_deg:35``) the scenario's
recording is made noise-free (noise_scale 0, the nominal release) on the recording grid (20 m cells,
half the 40 m inversion grid), and the baseline is compared with it on that grid itself
(``finer_grid_profile.finer_grid_evaluator`` over the recording's own terrain), the measurement errors
alone in the likelihood:

* ``raw``: 2 x (ln L of the true model - ln L of the baseline at the true mu, xi), the term's whole
  effect in the likelihood's units;
* ``unmimicked``: 2 x (ln L of the true model - the best ln L of the baseline after a local search
  over mu, xi (polish.local_search, the switch held at 0, started at the true mu, xi)), what re-tuning
  the baseline cannot absorb: the most an oracle could gain from a noise-free recording (a noisy one
  gives about this plus or minus its noise). An upper bound: the search is short (4 iterations of 6 runs from
  one start), and a longer one can only absorb more.

``--sigmas noise``: the likelihood states each gauge series' and the deposit map's sigma as the sd of the
noise the harness draws for it (scenarios.noise_sigmas: h 0.2 m, speed 0.5 m/s, deposit
0.3 m) instead of the harness' larger ones (0.5 m, 2 m/s, 0.5 m; the final volume's sigma, the release
error's, is kept): what recordings with honestly stated errors would hold.

A scenario whose ``unmimicked`` stays near the naming margin (2 ln 6, plus the switch's Occam factor)
on every variant is out of reach of any inversion on such recordings, whatever its grid. Diagnostic
only: the harness' terrains are not changed by it. Rows go to ``--out`` (default
results/terrain_screen.json, one row per (variant, scenario, sigmas); an existing row is kept: resume).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchslide.diagnose.polish import local_search
from torchslide.diagnose.refit import candidate_evaluator

from . import scenarios
from .finer_grid_profile import finer_grid_evaluator

HERE = Path(__file__).parent
DEFAULT_VARIANTS = ("narrow=narrow,resolved=resolved,resolved_theta35=resolved;theta_deg:35,"
                    "resolved_tr100=resolved;transition:100,resolved_amp150=resolved;amplitude:150,"
                    "resolved_theta35_amp150=resolved;theta_deg:35;amplitude:150")
GEOM_KEYS = ("theta_deg", "transition", "amplitude", "channel_halfwidth", "channel_depth", "side_slope_deg")


def parse_variants(spec: str) -> dict:
    """``NAME=TERRAIN[;key:value...],...`` -> {NAME: (TERRAIN, {key: value})}; keys from GEOM_KEYS, values
    finite numbers, TERRAIN a key of scenarios.TERRAINS. Bad input raises ValueError naming it."""
    out = {}
    for item in (s for s in spec.split(",") if s):
        name, _, rest = item.partition("=")
        parts = rest.split(";")
        if not name or not rest or parts[0] not in scenarios.TERRAINS:
            raise ValueError(f"variant {item!r} is not NAME=TERRAIN[;key:value...] with TERRAIN in "
                             f"{sorted(scenarios.TERRAINS)}")
        geom = {}
        for kv in parts[1:]:
            k, _, v = kv.partition(":")
            if k not in GEOM_KEYS:
                raise ValueError(f"variant {name!r}: unknown terrain key {k!r} (known: {', '.join(GEOM_KEYS)})")
            try:
                geom[k] = float(v)
            except ValueError:
                raise ValueError(f"variant {name!r}: {k} = {v!r} is not a number") from None
            if not np.isfinite(geom[k]):
                raise ValueError(f"variant {name!r}: {k} = {v!r} is not finite")
        out[name] = (parts[0], geom)
    if not out:
        raise ValueError(f"no variant in {spec!r}")
    return out


def screen(evc, true_x, bounds, n_iter: int = 4, seed: int = 0) -> dict:
    """``evc``: the candidate's evaluator on the recording grid (callable on (n, p) points, switch last,
    returning .z and .failed); ``true_x`` (p,) the truth. Returns {raw, unmimicked, best_baseline (p,),
    runs} (module doc)."""
    true_x = np.asarray(true_x, float)
    base0 = true_x.copy()
    base0[-1] = 0.0
    r = evc(torch.as_tensor(np.stack([true_x, base0])))
    z = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
    if not np.isfinite(z).all():
        raise RuntimeError(f"the true model or its baseline failed: z = {z.tolist()}")
    hold = np.zeros(len(true_x), bool)
    hold[-1] = True
    ls = local_search(evc, base0[None], z[1:], bounds, n_iter=n_iter, pop=6, n_starts=1, seed=seed, hold=hold)
    zb = max(float(z[1]), float(ls["best_z"]))
    xb = base0 if zb == float(z[1]) else np.asarray(ls["best_x"], float)
    return {"raw": float(2 * (z[0] - z[1])), "unmimicked": float(2 * (z[0] - zb)), "best_baseline": xb.tolist(),
            "runs": 2 + len(ls["z"])}


def screen_variant(name: str, terrain: str, geom: dict, scenario: str, n_iter: int = 4, seed: int = 0,
                   sigmas: str = "harness") -> dict:
    """One row: the noise-free recording of ``scenario`` on ``terrain`` with ``geom`` changed (registered
    as scenarios.TERRAINS[name] for the call, removed or restored after), screened on its recording grid with the
    likelihood's ``sigmas`` ("harness" or "noise": scenarios.noise_sigmas)."""
    if sigmas not in scenarios.SIGMAS:
        raise ValueError(f"sigmas must be one of {scenarios.SIGMAS}, got {sigmas!r}")
    term, hidden = scenarios.SCENARIOS[scenario]
    if term not in scenarios.SWITCH:
        raise ValueError(f"scenario {scenario!r} has no library term to screen (one of "
                         f"{sorted(s for s, (t, _) in scenarios.SCENARIOS.items() if t in scenarios.SWITCH)})")
    geom0, radius, g2 = scenarios.TERRAINS[terrain]
    previous = scenarios.TERRAINS.get(name)        # a variant named like a harness terrain replaces it for the call
    scenarios.TERRAINS[name] = (dict(geom0, **geom), radius, g2)
    t0 = time.perf_counter()
    try:
        with scenarios.terrain_variant(name):
            rec = scenarios.make_recording(scenario, seed, noise_scale=0.0, volume_factor=1.0)
            if sigmas == "noise":
                rec = dataclasses.replace(rec, observations=scenarios.noise_sigmas(rec.observations))
            ev = scenarios.make_evaluator(rec, fine_terrain=True)
    finally:
        if previous is None:
            del scenarios.TERRAINS[name]
        else:
            scenarios.TERRAINS[name] = previous
    evc = finer_grid_evaluator(candidate_evaluator(ev, term))
    sw = scenarios.SWITCH[term]
    true_x = [rec.truth[k] for k in evc.prior.names]
    row = screen(evc, true_x, evc.prior.bounds.numpy(), n_iter=n_iter, seed=seed)
    return {"variant": name, "terrain": terrain, "geom": geom, "scenario": scenario, "sigmas": sigmas, "param": sw,
            "truth": rec.truth[sw], **row, "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--scenario", default="curvature", help="a scenario with a library term")
    a.add_argument("--variants", default=DEFAULT_VARIANTS, help="NAME=TERRAIN[;key:value...],...")
    a.add_argument("--search-iters", type=int, default=4, help="local-search iterations over mu, xi")
    a.add_argument("--sigmas", default="harness", choices=scenarios.SIGMAS,
                   help="the likelihood's sigmas: the harness' (default) or the sd of the noise it draws")
    a.add_argument("--out", default=str(HERE / "results" / "terrain_screen.json"))
    args = a.parse_args(argv)
    try:
        variants = parse_variants(args.variants)
    except ValueError as e:
        raise SystemExit(f"--variants: {e}") from None
    term = scenarios.SCENARIOS.get(args.scenario, (None,))[0]
    if term not in scenarios.SWITCH:
        raise SystemExit(f"--scenario: {args.scenario!r} is not a scenario with a library term "
                         f"({', '.join(s for s, (t, _) in scenarios.SCENARIOS.items() if t in scenarios.SWITCH)})")
    if args.search_iters < 1:
        raise SystemExit(f"--search-iters: {args.search_iters!r} is not a positive number of iterations")
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.exists() else []
    out.parent.mkdir(parents=True, exist_ok=True)
    for name, (terrain, geom) in variants.items():
        if any(r["variant"] == name and r["scenario"] == args.scenario and r.get("sigmas", "harness") == args.sigmas
               for r in rows):
            print("already in", out, name, args.scenario)
            continue
        row = screen_variant(name, terrain, geom, args.scenario, n_iter=args.search_iters, sigmas=args.sigmas)
        print(name, args.scenario, args.sigmas, f"raw {row['raw']:.1f}", f"unmimicked {row['unmimicked']:.1f}", flush=True)
        rows.append(row)
        out.write_text(json.dumps(rows, indent=1))      # after every variant: an interrupted run loses one
    print("wrote", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
