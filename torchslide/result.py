"""SimulationResult: what one batched solver call returns (the solver -> observe interface).

All fields are torch tensors on the solver's device and dtype unless stated; B is the number of
parameter sets (batch members), (ny, nx) the DEM grid, T the number of gauge samples.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .terrain.grid import DEM


@dataclass
class GaugeSeries:
    """Flow at one map point sampled at fixed output times.

    Attributes:
        name: gauge name.
        x, y: map coordinates, m.
        t: (T,) output times, s (shared by all members; samples after a member ended repeat its final state).
        h: (B, T) flow thickness normal to the slope, m.
        u, v: (B, T) map components (along +x and +y) of the velocity along the surface, m/s.
        w: (B, T) its vertical component z_x u + z_y v, m/s (None: a horizontal surface, w = 0).
    """

    name: str
    x: float
    y: float
    t: torch.Tensor
    h: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    w: torch.Tensor | None = None

    @property
    def speed(self) -> torch.Tensor:
        """(B, T) speed along the surface sqrt(u^2 + v^2 + w^2), m/s."""
        s2 = self.u**2 + self.v**2
        return torch.sqrt(s2 + self.w**2 if self.w is not None else s2)


@dataclass
class SimulationResult:
    """Per-member outputs of a batched run.

    Attributes:
        dem: the terrain the run used.
        h_max: (B, ny, nx) maximum flow thickness normal to the slope over time, m.
        v_max: (B, ny, nx) maximum speed along the surface over time, m/s.
        h_final: (B, ny, nx) thickness normal to the slope at the end (the deposit), m.
        arrival_time: (B, ny, nx) first time h > arrival threshold, s (inf where never reached).
        cell_area: (ny, nx) surface area of each cell, m^2 (cellsize^2 / cos theta): a normal thickness
            times it is a volume (volume = sum h * cell_area).
        map_cell_area: the map (planimetric) area of a cell, cellsize^2, m^2: areas of the maps
            (impact, deposit) are map areas, as a mapped outline's.
        release_volume, final_volume, outflow_volume, entrained_volume: (B,) m^3.
        steps: (B,) time steps taken per member (int64).
        t_final: (B,) physical end time per member, s.
        stopped: (B,) bool, True when the member ended because motion stopped (not at t_end).
        mass_history, ke_history: (B, K) volume (m^3) and kinetic energy per unit density (m^5/s^2)
            sampled at ``history_t``; history_t: (K,) s.
        gauges: name -> GaugeSeries.
        bed_change: (B, ny, nx) bed elevation change from entrainment, m (None without entrainment).
        runtime_s: wall-clock seconds of the call.
        kernel: the step implementation that ran ("fused-cpu", "fused-triton", "compiled" or "eager").
        elevation_change: (B, ny, nx) the change of the surface's elevation from the release to the end,
            vertical m, as a DEM of difference measures it: + deposition, - erosion (the release's source and an
            eroded bed); the bed's change plus the flow's thickness per map area minus the release's. None in
            results that were not made by the solver.
        params: the per-member parameters the run used, name -> (B,) tensor.
        failed: (B,) bool, True where the run produced non-finite values; failure_reason lists why.
    """

    dem: DEM
    h_max: torch.Tensor
    v_max: torch.Tensor
    h_final: torch.Tensor
    arrival_time: torch.Tensor
    cell_area: torch.Tensor
    map_cell_area: float
    release_volume: torch.Tensor
    final_volume: torch.Tensor
    outflow_volume: torch.Tensor
    entrained_volume: torch.Tensor
    steps: torch.Tensor
    t_final: torch.Tensor
    stopped: torch.Tensor
    history_t: torch.Tensor
    mass_history: torch.Tensor
    ke_history: torch.Tensor
    gauges: dict[str, GaugeSeries] = field(default_factory=dict)
    bed_change: torch.Tensor | None = None
    runtime_s: float = 0.0
    params: dict[str, torch.Tensor] = field(default_factory=dict)
    failed: torch.Tensor | None = None
    failure_reason: list[str | None] = field(default_factory=list)
    kernel: str = ""
    elevation_change: torch.Tensor | None = None

    def peak_pressure(self, density: float) -> torch.Tensor:
        """(B, ny, nx) peak pressure density * v_max^2, kPa (``density`` in kg/m^3)."""
        return density * self.v_max**2 / 1000.0

    @property
    def batch_size(self) -> int:
        return int(self.h_max.shape[0])

    def member(self, b: int) -> "SimulationResult":
        """The b-th member as a batch of one."""
        sl = slice(b, b + 1)
        return SimulationResult(
            dem=self.dem,
            h_max=self.h_max[sl], v_max=self.v_max[sl], h_final=self.h_final[sl],
            arrival_time=self.arrival_time[sl], cell_area=self.cell_area, map_cell_area=self.map_cell_area,
            release_volume=self.release_volume[sl], final_volume=self.final_volume[sl],
            outflow_volume=self.outflow_volume[sl], entrained_volume=self.entrained_volume[sl],
            steps=self.steps[sl], t_final=self.t_final[sl], stopped=self.stopped[sl],
            history_t=self.history_t, mass_history=self.mass_history[sl], ke_history=self.ke_history[sl],
            gauges={k: GaugeSeries(g.name, g.x, g.y, g.t, g.h[sl], g.u[sl], g.v[sl], None if g.w is None else g.w[sl])
                    for k, g in self.gauges.items()},
            bed_change=None if self.bed_change is None else self.bed_change[sl],
            runtime_s=self.runtime_s,
            params={k: v[sl] for k, v in self.params.items()},
            failed=None if self.failed is None else self.failed[sl],
            failure_reason=self.failure_reason[sl] if self.failure_reason else [],
            kernel=self.kernel,
            elevation_change=None if self.elevation_change is None else self.elevation_change[sl],
        )
