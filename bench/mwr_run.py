"""landlab's MassWastingRunout (Keck et al. 2024) on the msh2021 example, with the parameters of landlab's own
tutorial for this event (critical slope 0.156, threshold flux 0.766 m, erosion coefficient 0.0337, regolith
1.2 m deep, the mapped failure depths as the landslide's thickness): the peer of bench.msh2021_peers.
Needs ``pip install landlab`` (any Python; torchslide does not need it). Writes DIR/mwr_dod.asc, the
modelled DEM of difference (final minus initial elevation, m) on the example's grid.

    torchslide example msh2021 --out case
    python -m bench.mwr_run case         # in a Python with landlab
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np


def main(folder: str) -> int:
    from landlab.components import DepressionFinderAndRouter, FlowAccumulator, FlowDirectorMFD
    from landlab.components.mass_wasting_runout import MassWastingRunout
    from landlab.io import esri_ascii

    d = Path(folder)
    with open(d / "dem.asc") as f:
        grid = esri_ascii.load(f, name="topographic__elevation", at="node")
    z = grid.at_node["topographic__elevation"]
    with open(d / "source.asc") as f:
        esri_ascii.load(f, name="mass__wasting_id", at="node", out=grid)
    source = grid.at_node["mass__wasting_id"] == 1
    grid.at_node["mass__wasting_id"] = source.astype(int)
    with open(d / "failure_depth.asc") as f:
        esri_ascii.load(f, name="failure_depth", at="node", out=grid)
    thickness = np.full(grid.number_of_nodes, 1.2)                  # regolith depth, m
    thickness[source] = -grid.at_node.pop("failure_depth")[source]   # the mapped failure depths
    grid.add_field("soil__thickness", thickness, at="node")
    grid.at_node["particle__diameter"] = np.full(grid.number_of_nodes, 0.316)
    grid.set_watershed_boundary_condition(z)
    FlowAccumulator(grid, "topographic__elevation", flow_director="FlowDirectorD8").run_one_step()
    DepressionFinderAndRouter(grid).map_depressions()
    z0 = z.copy()
    for name in ("flow__sink_flag", "flow__link_to_receiver_node", "flow__receiver_node", "topographic__steepest_slope"):
        grid.delete_field(loc="node", name=name)
    FlowDirectorMFD(grid, diagonals=True, partition_method="slope").run_one_step()
    mwr = MassWastingRunout(grid=grid, critical_slope=[0.156], threshold_flux=0.766, erosion_coefficient=0.0337443,
                            tracked_attributes=["particle__diameter"], typical_flow_thickness_of_erosion_zone=2.0,
                            typical_slope_of_erosion_zone=0.25, max_flow_depth_observed_in_field=5.0)
    t0 = time.perf_counter()
    mwr.run_one_step()
    dod = (grid.at_node["topographic__elevation"] - z0).reshape(grid.shape)   # row 0 south
    header = (d / "dem.asc").read_text().splitlines()[:6]
    rows = "\n".join(" ".join(f"{v:.6g}" for v in r) for r in dod[::-1])
    (d / "mwr_dod.asc").write_text("\n".join(header) + "\n" + rows + "\n")
    print(f"MassWastingRunout: {time.perf_counter() - t0:.1f} s; wrote {d / 'mwr_dod.asc'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
