"""How much the DEM edge fed the harness runs before the solver's edge became an outflow boundary.

Until session 33 the edge was transmissive (SolverConfig(boundary="open") now): where the flow at the
edge moved into the domain, the zero-gradient ghost cells kept supplying mass. On the resolved terrain
the release (radius 120 m, centre 150 m from the upslope edge) reaches the edge's neighbourhood on 40 m
cells, so the inversion grid gained volume through the edge that the 20 m recording grid did not. This
runs every scenario's true parameters (strength 1, nominal volume) on each terrain and grid with both
edges and writes, per run: the volume that came in through the edge (the negative part of the outflow,
m^3, and as a fraction of the release), and the largest |h_final difference| (m) between the edges.

Run: ``python -m experiments.hidden_physics.boundary_inflow [--out results/boundary_inflow.json]`` (a few
minutes on one core).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent


def measure(terrain: str, cellsize: float, scenarios=None) -> dict:
    """{scenario: {inflow_open, inflow_outflow (m^3), inflow_open_fraction, max_abs_dh_final (m)}} on one
    terrain variant and grid."""
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate

    from . import scenarios as S

    out = {}
    with S.terrain_variant(terrain):
        dem, erod = S.terrain(cellsize)
        rel = S.release(dem, S.V_NOMINAL)
        for sc in scenarios or S.SCENARIOS:
            term, hidden = S.SCENARIOS[sc]
            ms = S.mu_scale_patch(dem) if term == "outside" else None
            P = Params.make(**dict(S.TRUE_BASE, **hidden))
            runs = {b: simulate(dem, rel, P, t_end=S.T_END, gauges=S.gauges(), erodible_depth=erod, mu_scale=ms,
                                config=SolverConfig(**S.SOLVER, boundary=b), progress=False)
                    for b in ("open", "outflow")}
            v0 = float(runs["open"].release_volume[0])
            inflow = {b: max(0.0, -float(r.outflow_volume[0])) for b, r in runs.items()}
            out[sc] = {"inflow_open": inflow["open"], "inflow_outflow": inflow["outflow"],
                       "inflow_open_fraction": inflow["open"] / v0,
                       "max_abs_dh_final": float((runs["open"].h_final - runs["outflow"].h_final).abs().max())}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE / "results" / "boundary_inflow.json"))
    ap.add_argument("--terrains", default="narrow,resolved")
    ap.add_argument("--cellsizes", default="40,20", help="inversion grid, recording grid (m)")
    a = ap.parse_args(argv)
    res = {t: {f"{float(c):g}": measure(t, float(c)) for c in a.cellsizes.split(",")} for t in a.terrains.split(",")}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    for t, by in res.items():
        for c, rows in by.items():
            for sc, r in rows.items():
                print(f"{t:8s} {c:>3s} m {sc:20s} inflow open {r['inflow_open']:9.1f} m3 "
                      f"({100 * r['inflow_open_fraction']:.2f} %), outflow edge {r['inflow_outflow']:.1f} m3, "
                      f"max |dh_final| {r['max_abs_dh_final']:.3g} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
