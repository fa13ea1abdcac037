"""``torchslide simulate CONFIG.toml --out DIR``: run the solver and write rasters and a JSON summary.

Output (one batch member, B = 1), all on the DEM grid as ESRI ASCII (``.tif`` GeoTIFFs with the DEM's CRS
instead with ``[output] format = "tif"``)::

    DIR/h_max.asc          maximum flow thickness normal to the slope, m
    DIR/v_max.asc          maximum speed along the surface, m/s
    DIR/p_max.asc          peak pressure density * v_max^2, kPa ([model] density, default 2000 kg/m^3)
    DIR/h_final.asc        final thickness normal to the slope (deposit), m
    DIR/arrival_time.asc   first arrival time, s (nodata where never reached)
    DIR/bed_change.asc     bed elevation change, m (only with entrainment)
    DIR/summary.json       see below
    DIR/config.toml        copy of the configuration

For B > 1 each member gets ``DIR/member-000/``, ``DIR/member-001/``, ... with the same files, and
``DIR/summary.json`` is the batch summary: ``{"batch_size", "config", "members": [member summaries
with a "folder" key], "runtime_s", ...}``.

Member summary.json keys: params {name: value}, release_volume, final_volume, outflow_volume,
entrained_volume (m^3), impact_area, deposit_area (m^2; h > threshold), deposit_volume (m^3; h_final
over cells with h_final > threshold), threshold_m, max_h_max (m), max_v_max (m/s), max_p_max (kPa),
runout {path name: m} (the run-out along each [[paths]] polyline, and a synthetic case's "thalweg"), steps,
t_final (s), stopped, runtime_s (the whole batched call), kernel (the step that ran: fused-cpu,
fused-triton, compiled or eager), failed, failure_reason, gauges {name: {x, y, h_max, v_max, h_final}} (m, m/s, m; from the
gauge series), conventions (torchslide.config.CONVENTIONS, with the input thickness and the density),
against_observations {observation name: figures} when the config maps a footprint (``footprint``,
``impact_map`` or ``elevation_change`` [[observations]]): footprint Jaccard, shares of mapped cells reached
and of reached cells unmapped, run-out from the release's crown, volumes of deposition and erosion
(torchslide.survey).

Nothing is half-written: the config is validated before running, results go to a temporary folder next
to DIR, which is moved into place at the end. Exit code 0; 1 when some member failed (non-finite run;
its files are still written and its summary says why); 2 on bad input.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path
from typing import Any


from ..config import Config, ConfigError, load_config
from ..output_folder import check_output, staged_output

HELP = "run the solver for a TOML config; write h_max/v_max/h_final rasters and summary.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="TOML configuration ([terrain], [model], [run], [[gauges]])")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (must not exist or be empty)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.add_argument("--threshold", type=float, default=0.5, metavar="M",
                   help="thickness threshold for areas and deposit volume, m (default 0.5)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar, no summary lines")


def _f(x) -> Any:
    """JSON-safe float (inf/nan as strings)."""
    v = float(x)
    return v if math.isfinite(v) else str(v)


def member_summary(result, b: int, threshold: float, paths=(), density: float = 2000.0) -> dict[str, Any]:
    """Summary dict of member b of a SimulationResult (keys in the module docstring)."""
    from .. import observe

    r = result.member(b)
    s: dict[str, Any] = {
        "params": {k: _f(v[0]) for k, v in r.params.items()},
        "release_volume": _f(r.release_volume[0]),
        "final_volume": _f(r.final_volume[0]),
        "outflow_volume": _f(r.outflow_volume[0]),
        "entrained_volume": _f(r.entrained_volume[0]),
        "impact_area": _f(observe.impact_area(r, threshold)[0]),
        "deposit_area": _f(observe.deposit_area(r, threshold)[0]),
        "deposit_volume": _f(observe.deposit_volume(r, threshold)[0]),
        "threshold_m": threshold,
        "max_h_max": _f(r.h_max[0].max()),
        "max_v_max": _f(r.v_max[0].max()),
        "max_p_max": _f(r.peak_pressure(density)[0].max()),
    }
    if paths:
        s["runout"] = {p.name: _f(observe.runout_length(r, p.xy, threshold, p.max_offset)[0]) for p in paths}
    s.update({
        "steps": int(r.steps[0]),
        "t_final": _f(r.t_final[0]),
        "stopped": bool(r.stopped[0]),
        "runtime_s": float(result.runtime_s),
        "kernel": result.kernel,
        "failed": bool(r.failed[0]) if r.failed is not None else False,
        "failure_reason": (r.failure_reason[0] if r.failure_reason else None),
        "gauges": {
            name: {"x": g.x, "y": g.y, "h_max": _f(g.h[0].max()), "v_max": _f(g.speed[0].max()),
                   "h_final": _f(g.h[0, -1])}
            for name, g in r.gauges.items()
        },
    })
    return s


def write_member(folder: Path, result, b: int, fmt: str, output_format: str = "asc", density: float = 2000.0) -> None:
    """Rasters of member b into ``folder`` (``output_format`` "asc" with values as ``fmt``, or "tif")."""
    from ..terrain.io import write_named_raster

    def put(name: str, t) -> None:
        write_named_raster(folder, name, t[b].detach().cpu().double().numpy(), result.dem, output_format, fmt)

    put("h_max", result.h_max)
    put("v_max", result.v_max)
    put("p_max", result.peak_pressure(density))
    put("h_final", result.h_final)
    put("arrival_time", result.arrival_time)
    if result.bed_change is not None:
        put("bed_change", result.bed_change)


OUTFLOW_WARN = 0.01
"""Share of the release leaving through the DEM edge above which ``simulate`` warns."""


def observed_footprints(cfg: Config) -> list:
    """The config's [[observations]] that map a footprint (torchslide.survey), validated; [] when none."""
    from ..survey import FOOTPRINT_KINDS

    table = cfg.raw.get("observations")
    if not table:
        return []
    from ..calibration_config import parse_observations

    return [o for o in parse_observations(table, cfg) if getattr(o, "kind", None) in FOOTPRINT_KINDS]


def survey_summary(result, b: int, cfg: Config, observations, threshold: float) -> dict[str, Any]:
    """torchslide.survey.run_figures of member b against the mapped footprints ``observations``."""
    from ..survey import run_figures

    dz = result.elevation_change
    return run_figures(result.h_max[b].detach().cpu().double().numpy(),
                       None if dz is None else dz[b].detach().cpu().double().numpy(), observations,
                       result.dem.z, cfg.terrain.release, result.dem.cellsize, threshold)


def write_outputs(tmp: Path, cfg: Config, result, threshold: float, observations=()) -> list[dict[str, Any]]:
    """Write every member's files and the summaries into ``tmp``; return the member summaries (with the
    figures against the mapped footprints ``observations``, "against_observations", when there are any)."""
    import torch

    fmt = "%.17g" if result.h_max.dtype == torch.float64 else "%.9g"
    paths = cfg.run_out_paths()
    B = result.batch_size
    summaries = []
    for b in range(B):
        folder = tmp if B == 1 else tmp / f"member-{b:03d}"
        folder.mkdir(exist_ok=True)
        write_member(folder, result, b, fmt, cfg.output_format, cfg.model.density)
        s = member_summary(result, b, threshold, paths, cfg.model.density)
        if observations:
            s["against_observations"] = survey_summary(result, b, cfg, observations, threshold)
        s["conventions"] = cfg.conventions()
        (folder / "summary.json").write_text(json.dumps(s, indent=2) + "\n")
        s["folder"] = "." if B == 1 else folder.name
        summaries.append(s)
    if B > 1:
        batch = {
            "batch_size": B,
            "config": str(cfg.path),
            "terrain": cfg.terrain.source,
            "t_end": cfg.run.t_end,
            "runtime_s": float(result.runtime_s),
            "kernel": result.kernel,
            "threshold_m": threshold,
            "conventions": cfg.conventions(),
            "members": summaries,
        }
        (tmp / "summary.json").write_text(json.dumps(batch, indent=2) + "\n")
    shutil.copyfile(cfg.path, tmp / "config.toml")
    return summaries


REACH_MIN = 0.01  # m: a gauge whose h_max stays at or below this in every member was never reached


def unreached_gauges(summaries: list[dict], tol: float = REACH_MIN) -> list[str]:
    """One line per gauge that the flow reaches in no member (h_max <= ``tol`` m throughout)."""
    out = []
    for name, g in (summaries[0]["gauges"] if summaries else {}).items():
        peak = max(float(s["gauges"][name]["h_max"]) for s in summaries)
        if peak <= tol:
            out.append(f"gauge {name} at ({g['x']:g}, {g['y']:g}) is never reached (h_max {peak:.3g} m in every "
                       f"member): check that it lies on the flow path")
    return out


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.threshold) and args.threshold >= 0):
        raise ConfigError(f"--threshold must be >= 0 m, got {args.threshold}")
    cfg = load_config(args.config)
    out = Path(args.out)
    anc = check_output(out, args.overwrite)

    from ..solver import simulate

    kwargs = cfg.simulate_kwargs()
    footprints = observed_footprints(cfg)
    with staged_output(out, anc, "simulate") as tmp:
        result = simulate(**kwargs, progress=not args.quiet)
        summaries = write_outputs(tmp, cfg, result, args.threshold, footprints)
    failed = [i for i, s in enumerate(summaries) if s["failed"]]
    if not args.quiet:
        for i, s in enumerate(summaries):
            tag = f"member {i}" if len(summaries) > 1 else "run"
            print(
                f"{tag}: {', '.join(f'{k}={v:g}' for k, v in s['params'].items() if k in ('mu', 'xi') and isinstance(v, float))}"
                f"  release {s['release_volume']:.4g} m^3, impact area {s['impact_area']:.4g} m^2, "
                f"deposit {s['deposit_volume']:.4g} m^3, t_final {s['t_final']} s, {s['steps']} steps"
            )
            for name, f in s.get("against_observations", {}).items():
                print(f"  against {name}: footprint Jaccard {f['footprint_jaccard']:.2f}, "
                      f"{100 * f['share_of_mapped_reached']:.0f} % of the mapped cells reached, "
                      f"{100 * f['share_of_reached_unmapped']:.0f} % of the reached cells unmapped, run-out "
                      f"{f['runout_m']['run']:.0f} m (mapped {f['runout_m']['mapped']:.0f} m)")
        print(f"wrote {out}")
    for i in failed:
        print(f"torchslide: warning: member {i} failed: {summaries[i]['failure_reason']}", file=sys.stderr)
    for w in unreached_gauges(summaries):
        print(f"torchslide: warning: {w}", file=sys.stderr)
    for i, s in enumerate(summaries):
        share = s["outflow_volume"] / s["release_volume"] if s["release_volume"] > 0 else 0.0
        if share > OUTFLOW_WARN:
            tag = f"member {i}" if len(summaries) > 1 else "the run"
            print(f"torchslide: warning: {tag} lost {100 * share:.1f} % of its release through the DEM edge "
                  f"(outflow_volume {s['outflow_volume']:.4g} m^3); if the run-out should stay inside, extend "
                  f"the DEM", file=sys.stderr)
    return 1 if failed else 0
