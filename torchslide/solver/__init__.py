"""Batched run-out solver on a Cartesian DEM grid.

Formulation
-----------
The paper's Eq. 1-4 in surface-induced coordinates (Savage & Hutter 1991; Fischer et al. 2012, as
RAMMS and r.avaflow use them), written on the horizontal DEM grid with the metric of the surface.
For the bed z(x, y), per cell (central differences): grad z = (z_x, z_y), cos(theta) =
1 / sqrt(1 + |grad z|^2), the metric G = I + grad z grad z^T and G^-1 p = p - cos^2 grad z (grad z . p).

State per member b (tensors (B, ny, nx)): h, the thickness per unit *map* area (the vertical thickness,
m; volume = sum h cellsize^2), and (hu, hv), the horizontal momentum (m^2/s) of the horizontal velocity
u = (u, v), the map projection of the velocity V = (u, v, z_x u + z_y v) along the surface. The flow
thickness normal to the slope is h_n = cos h; its speed |V| = sqrt(|u|^2 + (grad z . u)^2).

    d_t h + div(h u)              = Q                                                  (mass)
    d_t Q + div(Q (x) u)          = F(A) - S / cos,   Q = sigma q,   sigma = |V| / |u|      (momentum)
    A = -G^-1 [ g h grad z + grad(k g_n h_n^2 / 2) / cos ]
    S = V/|V| (mu_eff g_n h_n + tau_y + g |V|^2 / xi)  projected on the map,  g_n = g cos(theta)

The momentum that the fluxes carry is the surface momentum Q = h |V| e (e the map direction of motion):
material passing from one cell to the next keeps its speed along the surface while its horizontal
velocity takes the new cell's slope (q = Q / sigma there), as a point mass keeps its speed where the
bed bends. F turns the force A (the horizontal projection of gravity and pressure along the surface)
into the change of Q: along e its component along the surface, e^T G A / sigma; across e sigma times
A's, which turns the flow without changing its speed (stepping.surface_momentum_change). The bed's
curvature thus needs no Hessian: on a stepped or rough DEM a curvature reaction u^T H u from the cell
Hessian would do work of either sign at every step and put peak speeds far above the energy line
(tests/test_solver_energy.py). The pressure is the hydrostatic one of the normal thickness,
k g_n h_n^2 / 2 per unit bed width. Friction (friction.py) acts along the surface on Q and so stops but
never reverses. Entrainment erodes kappa |V| normal to the bed per unit bed area; the candidate terms
use h_n, |V| and g_n (torchslide.physics).

On a plane of slope theta this gives, for a uniform layer, the horizontal acceleration
g cos(theta) (sin(theta) - mu cos(theta)) along the dip, i.e. g (sin - mu cos) along the surface, in any
plan orientation; the Voellmy terminal speed |V|^2 = xi h_n (sin - mu cos); the Mangeney dam break and
the Savage-Hutter similarity solution mapped to map coordinates (x_map = x cos(theta)); and a release
of normal thickness h_n on the plane holds h_n x its surface area (docs/verification.md).
``SolverConfig.slope_correction=False`` drops the metric (cos = 1, G = I): the classic shallow-water
equations of a fluid with vertical hydrostatic pressure (a lake at rest is then exact on any bed).

Inputs and outputs follow the field's conventions: the release and erodible depths are normal to the
slope (``simulate(thickness="normal")``, the default; "vertical" takes them per unit map area); h_max,
h_final and gauge h are normal thicknesses, v_max and gauge speeds are along the surface;
``SimulationResult.cell_area`` is the surface area of each cell (volume = sum h_n cell_area).

Scheme
------
Second-order Kurganov-Petrova (2007) central-upwind fluxes (scheme.py): generalised-minmod
reconstruction of the surface w = h + z in wet cells and of h at wet/dry fronts, bed values at faces
(mean of the two cells, exact for a plane), desingularised velocities, and a pressure/bed-source pair
written per cell,

    -(k g_n cos)_j (Phi_{j+1/2} - Phi_{j-1/2}) / dx  -  g hbar_j (B_{j+1/2} - B_{j-1/2}) / dx,

with Phi the central-upwind average of h^2/2 at a face and hbar the mean face thickness of the cell;
this horizontal gradient is then turned along the surface by G^-1 per cell and into the change of Q. Without the metric it balances a lake at rest exactly, and with it it drives a uniform layer on a
plane exactly (docs/verification.md, cases 1-2). Positivity for any dt: draining-flux limiter (Bollermann
et al. 2013), so the mass update is conservative to round-off (outflow through the boundaries is
counted). The DEM edge is an outflow boundary by default (zero-gradient ghost cells; a face whose flux
points into the domain carries nothing in, so a flow touching the upslope edge is not fed from outside);
SolverConfig(boundary="open") makes it transmissive, as the infinite-plane verification cases need.
SSP-RK2 (Heun) in time; each stage is flux + bed source, then entrainment / deposition, then friction on the whole momentum vector (friction.py: stops, never reverses; turbulent
term implicit). A cell stopped by friction in both stages is set exactly at rest. No creep: a face
between two resting cells where friction can hold the driving force, measured along the surface, passes
no flux (the D-Claw rule; scheme.frozen_faces).

Per-member time steps: dt_b from the CFL condition, clipped so members land exactly on the output
times; all members advance together with a (B, 1, 1) dt; an ended member has dt_b = 0 (bitwise
unchanged) and is dropped from the working batch at the next check (``SolverConfig.check_every``).
A member ends at t_end, when its kinetic energy falls below ``stop_ke_fraction`` of its peak, or once
its flow has stopped (torchslide.solver.stop: footprint and deposit quiet for ``stop_quiet_time``).
Results of one member do not depend on the other members.
"""
from .config import SolverConfig
from .simulate import simulate

__all__ = ["SolverConfig", "simulate"]
