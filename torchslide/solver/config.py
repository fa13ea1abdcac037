"""SolverConfig: numerical settings of the run-out solver (not physics; see torchslide.physics)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SolverConfig:
    """Numerical settings.

    Attributes:
        cfl: Courant number; dt_b = cfl * dx / (max a_x + max a_y) per member (a: one-sided local
            speeds |u| + sqrt(k g_n h) of the central-upwind scheme). 0.45 keeps the 2-D scheme stable;
            positivity is guaranteed independently by the draining-flux limiter.
        limiter_theta: generalised-minmod parameter in [1, 2] (1 = minmod, most dissipative).
        h_eps: desingularisation depth, m: velocities of cells thinner than this are damped
            (Kurganov-Petrova u = sqrt(2) h hu / sqrt(h^4 + max(h^4, h_eps^4))).
        h_wet: cells (and their two neighbours along a direction) thicker than this reconstruct the
            free surface w = h + z (well-balanced); elsewhere the thickness h is reconstructed (wet/dry front).
        wb_depth_ratio: the surface is reconstructed only where the bed-curvature offset of the face
            beds |z_{j+1} - 2 z_j + z_{j-1}| / 4 is at most this fraction of h (else h is reconstructed,
            which keeps the gravity drive of thin layers on curved terrain right; the lake at rest is
            exact wherever the surface is reconstructed).
        arrival_threshold: thickness, m, that defines arrival_time.
        v_max_min_depth: thickness, m, from which a cell's speed counts towards v_max (and so towards
            point maxima): the desingularised speed of a nearly empty cell is not a flow speed, and on steep
            slopes it spikes (peak-speed maps of the field's tools use such a threshold too).
        output_interval: s, spacing of gauge / mass / kinetic-energy samples (t_end is always a sample).
        stop_ke_fraction: a member ends when its kinetic energy falls below this fraction of its
            peak (after the peak). 1e-4 means speeds about 1 % of the peak mean speed.
        stop_quiet_time: s; a member also ends once its flow has stopped (torchslide.solver.stop): for
            this long no cell newly reached (h > arrival_threshold) and the thickness changed by less
            than ``stop_quiet_change`` of the volume, while its kinetic energy is below ``stop_quiet_ke`` of its peak
            (tested at the host checks, every ``check_every`` steps). 0 switches this rule off (the
            kinetic-energy rule alone).
        stop_quiet_ke: the kinetic-energy fraction under which that rule applies.
        stop_quiet_change: sum over cells of |h(t) - h(t - stop_quiet_time)| over the volume sum h(t)
            below which the deposit counts as at rest.
        dt_max: s, largest time step (used where nothing moves, e.g. a fully dry or resting domain).
        no_creep: freeze faces between resting cells whose driving jump friction can hold (D-Claw rule).
        slope_correction: use g_n = g cos(theta) per cell (theta the DEM slope); False uses g_n = g.
        entrain_h_min: m, entrainment acts only where h exceeds this.
        check_every: steps between host synchronisations (end test, compaction, progress bar).
        compact: drop ended members from the working batch at each check (they then cost nothing).
        max_steps: a member still running after this many steps is marked failed.
        compile: run the step through torch.compile (first call pays compilation); the same as
            kernel = "compiled", whatever ``kernel`` says.
        kernel: the step's implementation: "fused" (default: on the CPU one compiled loop nest per
            stage, torchslide.solver.fused_cpu (numba); on CUDA two Triton kernels per stage and one
            per step, torchslide.solver.fused_triton; both equal to eager to round-off; eager runs where
            neither is installed), "eager" (torch operations: the reference), "compiled" (torch.compile of
            eager).
        cuda_graphs: on CUDA, replay the steps between two host checks as one CUDA graph
            (torchslide.solver.graphs; "fused" and "eager"): the same kernels and results, without the
            host's launch cost (the Triton step launches five kernels a step and waits for nothing). Off by
            default: whether it is faster for the present step is measured on a GPU by `make bench-solver-gpu`
            (the 10-member runs with and without graphs).
        crop: compute only on the bounding box of the cells the flow has touched (all members), grown
            as the flow spreads. Exact: a dry cell receives mass only from a wet neighbour, so the
            wetted support grows by at most one cell per stage, and the box keeps a margin of
            2 * crop_every + 3 dry cells; outside it every field is exactly zero / unchanged.
        crop_every: steps between two checks of the box (one host synchronisation each).
        boundary: the DEM edge. "outflow" (default): mass and momentum leave through it and nothing
            enters (a boundary face whose flux points into the domain carries only its pressure, like a
            wall), so the volume in the domain never grows through the edge, also where a release or a
            flow touches the upslope edge of the DEM. "open": transmissive, the state continues through
            the edge as on an infinite domain (the uniform-layer verification cases); where a flow at the
            edge moves into the domain this feeds it without limit.
        nodata: cells outside the DEM's domain (``DEM.outside``: nodata in the DEM file). "outflow"
            (default): mass that enters them leaves the domain (counted in the outflow volume), like at
            the DEM edge; "wall": faces between the domain and such cells pass no mass (a reflecting
            wall). The release must not cover them.
    """

    cfl: float = 0.45
    limiter_theta: float = 1.3
    h_eps: float = 1e-3
    h_wet: float = 1e-4
    wb_depth_ratio: float = 0.25
    arrival_threshold: float = 0.1
    v_max_min_depth: float = 0.05
    output_interval: float = 1.0
    stop_ke_fraction: float = 1e-4
    stop_quiet_time: float = 10.0
    stop_quiet_ke: float = 1e-2
    stop_quiet_change: float = 0.01
    dt_max: float = 1.0
    no_creep: bool = True
    slope_correction: bool = True
    entrain_h_min: float = 0.01
    check_every: int = 20
    compact: bool = True
    max_steps: int = 500_000
    compile: bool = False
    crop: bool = True
    crop_every: int = 2
    boundary: str = "outflow"
    nodata: str = "outflow"
    kernel: str = "fused"
    cuda_graphs: bool = False

    def validate(self) -> None:
        def need(ok: bool, name: str, rule: str) -> None:
            if not ok:
                raise ValueError(f"SolverConfig.{name} = {getattr(self, name)!r} is invalid: {rule}")
        need(0 < self.cfl <= 1, "cfl", "need 0 < cfl <= 1")
        need(1 <= self.limiter_theta <= 2, "limiter_theta", "need 1 <= limiter_theta <= 2")
        need(self.h_eps > 0, "h_eps", "need h_eps > 0")
        need(self.h_wet >= 0, "h_wet", "need h_wet >= 0")
        need(self.wb_depth_ratio >= 0, "wb_depth_ratio", "need >= 0")
        need(self.arrival_threshold > 0, "arrival_threshold", "need > 0")
        need(self.v_max_min_depth >= 0, "v_max_min_depth", "need >= 0")
        need(self.output_interval > 0, "output_interval", "need > 0")
        need(0 <= self.stop_ke_fraction < 1, "stop_ke_fraction", "need 0 <= f < 1")
        need(self.stop_quiet_time >= 0, "stop_quiet_time", "need >= 0 s")
        need(0 <= self.stop_quiet_ke < 1, "stop_quiet_ke", "need 0 <= f < 1")
        need(self.stop_quiet_change > 0, "stop_quiet_change", "need > 0")
        need(self.dt_max > 0, "dt_max", "need > 0")
        need(self.entrain_h_min >= 0, "entrain_h_min", "need >= 0")
        need(self.check_every >= 1, "check_every", "need >= 1")
        need(self.max_steps >= 1, "max_steps", "need >= 1")
        need(self.crop_every >= 1, "crop_every", "need >= 1")
        need(self.boundary in ("outflow", "open"), "boundary", "need 'outflow' or 'open'")
        need(self.nodata in ("outflow", "wall"), "nodata", "need 'outflow' or 'wall'")
        need(self.kernel in ("eager", "compiled", "fused"), "kernel", "need 'eager', 'compiled' or 'fused'")
