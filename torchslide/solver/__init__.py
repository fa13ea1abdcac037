"""Batched run-out solver on a Cartesian DEM grid.

Formulation
-----------
State per member b (tensors (B, ny, nx)): h, the flow thickness per unit *horizontal* area (m, so the
volume is sum h * cellsize^2), and hu, hv, the horizontal momentum components (m^2/s) along the map
axes x (columns) and y (rows, row 0 south). Per cell g_n = g cos(theta), theta the local DEM slope
(central differences; ``SolverConfig.slope_correction=False`` uses g_n = g). Equations (paper Eq. 1-4
on the DEM grid):

    d_t h   + d_x(h u)                    + d_y(h v)          = Q           (entrainment / deposition)
    d_t(hu) + d_x(h u^2 + k g_n h^2 / 2)  + d_y(h u v)        = -g_n h d_x z - S_x
    d_t(hv) + d_x(h u v)                  + d_y(h v^2 + k g_n h^2 / 2) = -g_n h d_y z - S_y
    S = u/|u| (mu_eff g_n h + g |u|^2 / xi + tau_y)

On a plane z = -x tan(theta) a uniform layer feels g_n tan(theta) - mu g_n, i.e. exactly
a = g cos(theta) (tan(theta) - mu), so the uniform-slope, Voellmy terminal-velocity
(u^2 = xi h (sin - mu cos)) and Mangeney dam-break solutions of docs/verification.md hold with the
grid's x as the along-slope coordinate. On a DEM of a tilted plane in map coordinates the horizontal
acceleration should be g cos(theta) (sin(theta) - mu cos(theta)): this formulation, which has no
metric factors of the surface, moves 1/cos(theta) too fast in map view there.

Scheme
------
Second-order Kurganov-Petrova (2007) central-upwind fluxes (scheme.py): generalised-minmod
reconstruction of the surface w = h + z in wet cells and of h at wet/dry fronts, bed values at faces
(mean of the two cells, exact for a plane), desingularised velocities, and a pressure/bed-source pair
written per cell,

    -(k g_n)_j (Phi_{j+1/2} - Phi_{j-1/2}) / dx  -  (g_n)_j hbar_j (B_{j+1/2} - B_{j-1/2}) / dx,

with Phi the central-upwind average of h^2/2 at a face and hbar the mean face thickness of the cell.
This balances a lake at rest exactly (even where g_n varies from cell to cell) and drives a uniform
layer on a plane exactly (docs/verification.md, cases 1-2). Positivity for any dt: draining-flux limiter (Bollermann
et al. 2013), so the mass update is conservative to round-off (outflow through the boundaries is
counted). The DEM edge is an outflow boundary by default (zero-gradient ghost cells; a face whose flux
points into the domain carries nothing in, so a flow touching the upslope edge is not fed from outside);
SolverConfig(boundary="open") makes it transmissive, as the infinite-plane verification cases need.
SSP-RK2 (Heun) in time; each stage is flux + bed source, then entrainment / deposition, then friction on the whole momentum vector (friction.py: stops, never reverses; turbulent
term implicit). A cell stopped by friction in both stages is set exactly at rest. No creep: a face
between two resting cells whose driving jump |k g_n dh + g_n dz| friction can hold passes no flux
(D-Claw rule).

Per-member time steps: dt_b from the CFL condition, clipped so members land exactly on the output
times; all members advance together with a (B, 1, 1) dt; an ended member has dt_b = 0 (bitwise
unchanged) and is dropped from the working batch at the next check (``SolverConfig.check_every``).
A member ends at t_end or when its kinetic energy falls below ``stop_ke_fraction`` of its peak.
Results of one member do not depend on the other members.
"""
from .config import SolverConfig
from .simulate import simulate

__all__ = ["SolverConfig", "simulate"]
