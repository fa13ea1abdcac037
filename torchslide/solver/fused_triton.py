"""The solver step as Triton kernels (CUDA; on the CPU under TRITON_INTERPRET=1, for the tests).

``triton_step(F)`` returns a drop-in for ``stepping.make_step(F)``: the same SSP-RK2 step with the same
arithmetic in the same order per cell and per face (stepping._stage, scheme.sweep, scheme.frozen_faces,
scheme.draining_factors, friction.apply_friction). In float64 (the reference) every division and square
root is rounded exactly and nothing fuses into a multiply-add, so on CUDA one step equals the torch step's
to the last bit; only the sums over the grid (mass, kinetic energy, outflow) add in another order. In
float32 the kernels take the card's fast paths (FAST_FLOAT32: approximate division and square root,
fused multiply-add), judged by physics (docs/verification.md), not by bits. Each kernel is one pass over
the grid of every member (the last grid axis = member); the pressure coefficient k g cos^2 is recomputed
from the state where it is needed. A stage computes its faces in one of two designs (FACES):

    "lines"    _velocities (u, v, KP07 Eq. 2.17, once per stage; VELOCITIES = "recomputed" recomputes them
               at each use instead), with the slope metric _carried (the carried surface velocities), then
               _faces for the x and for the y faces, one face per thread: reconstruction, central-upwind
               fluxes (KP07 Eq. 3.11), the no-creep rule, domain walls, the largest one-sided speed per
               block (for the CFL step)
    "tiled"    _tiled: all of that for both axes in one kernel over 2-D tiles with a halo, each position's
               velocities and reconstructions computed once and read by its faces from the tile

and then, in both designs:

    _drain     the draining-flux factor per cell (Bollermann et al. 2013)
    _update    fluxes, bed source and pressure along the surface (Eq. 2-3), entrainment / deposition,
               friction (Eq. 4), outflow per block

and one more per step, ``_combine`` (the Heun average, h_max, v_max, arrival, mass and kinetic energy
per block). Nothing in a step waits for the host: the CFL time step, the end times and the stop test
are per-member tensors on the device. Constants travel in a tensor of the state's dtype (Triton takes
a Python float as float32), switches as compile-time constants (one specialisation per set of terms,
cached on disk by Triton). A bed that evolves has its metric recomputed per stage by
stepping.static_geometry.
"""
from __future__ import annotations

import math
import os

import torch

from ..physics import FR_DEP, MU_I_D, MU_I_I0
from .scheme import WAVE_SPEED_MIN
from .stepping import end_of_step, static_geometry

try:
    import triton
    import triton.language as tl
except ImportError:     # the Triton step is optional: without triton a GPU runs the torch step
    triton = None

PM = ("mu", "xi", "tau_y", "k_ap", "earth_pressure", "k_act", "k_pass", "curvature", "mu_i", "kappa", "deposition")
"""The per-member parameters the kernels read, in their order (columns of the (B, 11) table)."""

BLOCK = 128
"""Cells (or faces) per program: 128 with 4 warps (one cell per thread) ran float64 1.6 times faster than 512
and float32 as fast, on an H200 (20 m grid, batch 256; bench/results/solver_gpu.json)."""

NUM_WARPS = 4
"""Warps per program (bench.bench_solver --launch measures other BLOCK x NUM_WARPS)."""

INTERPRETED_BLOCK = 2048
"""Cells per program under Triton's interpreter (the tests on the CPU), whose cost is mostly per program:
2048 ran the bitwise case of tests/test_solver_triton.py (eight members) in 19-21 s against 34-36 s at 1024,
the two-member nodata case alike (23-31 s, the spread of a loaded machine). The same arithmetic per cell
as any BLOCK; only the per-block partial sums (mass, kinetic energy, outflow) add in another order."""

FAST_FLOAT32 = os.environ.get("TORCHSLIDE_EXACT_FLOAT32", "0") != "1"
"""float32 on the fast paths: Triton's approximate division (2 ulp) and square root and fused multiply-add
(within the verification cases' tolerances of float64). False (environment TORCHSLIDE_EXACT_FLOAT32=1 when
the module is imported; the kernels compile the choice in): exactly rounded division and square root and
no fused multiply-add, as float64 always is, so that float32 too equals the torch step's bits."""

FLUSH_SUBNORMALS = os.environ.get("TORCHSLIDE_FLUSH_SUBNORMALS", "0") == "1"
"""Under Triton's interpreter (the tests on the CPU): flush float32 subnormals in the fast division and
square root to zero, as the card's approximate instructions do, so that a guard that lets a subnormal
divisor through shows up as a non-finite state without a GPU (environment TORCHSLIDE_FLUSH_SUBNORMALS=1)."""

VELOCITIES = "stored"
"""Where the faces and the cell update take the desingularised velocities u, v (KP07 Eq. 2.17) from:
"stored" once per stage by one more kernel (_velocities; two more fields written and read), or
"recomputed" from h, hu, hv at each use (16 exactly rounded divisions and square roots per cell and
stage in the faces alone). The same bits either way; "stored" measured 1.7 times faster in float32 and
2.5 times in float64 on an H200 (20 m grid, batch 256; bench.bench_solver --launch BLOCKxWARPS:stored)."""


FACES = os.environ.get("TORCHSLIDE_TRITON_FACES", "lines")
"""The faces' design (environment TORCHSLIDE_TRITON_FACES at import): "lines", a kernel per axis with one
face per thread (_faces, after _velocities and _carried), which reconstructs each cell once for each of its
two faces along the axis; or "tiled", one kernel (_tiled) per stage over 2-D tiles with a halo, in which each
position's velocities, carried velocities, pressure coefficient and reconstructions along both axes are
computed once and each face reads its left neighbour's from the tile (tl.gather: shared memory). The same
bits either way. "tiled" has 0.65 times the SASS instructions of the lines' faces per float32 cell
(bench/results/triton_profile.json) but 1 program of 16 warps per SM and a barrier per gather; it becomes
the default when a GPU run measures it faster (bench.bench_solver --launch 128x4:tiled)."""

TILE = (32, 32)
"""Positions (rows, columns) of a _tiled program: it holds (32 - 3)^2 = 841 cells, the rest (18 %) is its
halo. Of the tiles compiled for sm_90 (bench.triton_profile --tile), 32 x 32 had the fewest SASS
instructions per cell: 16 x 16 (66 % of its positions held) 1.3 times as many in float32."""

TILE_WARPS = 16
"""Warps per _tiled program: 16 (two positions per thread) kept float32 at 105 and float64 at 128 registers
per thread with no spills; 8 took 182 and 255 for 9 % and 4 % fewer instructions per cell."""

INTERPRETED_TILE = (16, 32)
"""The tile under Triton's interpreter (the tests on the CPU): small enough that the test grids span several
tiles along both axes (their seams are tested), large enough that the cost per program stays low."""


def interpreted() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def supported(F, device) -> str | None:
    """None when the Triton step runs the call's settings ``F`` on ``device``, else why not: it needs
    triton and a CUDA device (or any device under TRITON_INTERPRET=1)."""
    if triton is None:
        return "triton is not installed"
    if torch.device(device).type != "cuda" and not interpreted():
        return "the Triton step runs on CUDA (or under TRITON_INTERPRET=1)"
    return None


if triton is not None:
    # indices into the kernels' constant table (_constants; compile-time constants: Triton reads no other globals)
    C_G, C_DX, C_THETA, C_HEPS4, C_HWET, C_WB, C_SQRT2, C_WSMIN, C_HEPS, C_ENTMIN, C_FRDEP, C_MUI, C_I0, C_TINY, \
        C_VMIN, C_ARR, C_INF, C_INVDX, C_NORMAL = (tl.constexpr(k) for k in range(19))

    @triton.jit
    def _max(a, b):
        return tl.maximum(a, b, propagate_nan=tl.PropagateNan.ALL)

    @triton.jit
    def _min(a, b):
        return tl.minimum(a, b, propagate_nan=tl.PropagateNan.ALL)

    if FAST_FLOAT32 and FLUSH_SUBNORMALS:
        @triton.jit
        def _ftz(x):
            """x with float32 subnormals flushed to zero (as the card's approximate division and sqrt do)."""
            if x.dtype == tl.float32:
                r = tl.where(tl.abs(x) < 1.1754944e-38, 0.0, x)
            else:
                r = x
            return r

        @triton.jit
        def _div(a, b):
            """a / b as the card's approximate float32 division treats subnormal divisors and results."""
            return _ftz(a / _ftz(b))

        @triton.jit
        def _sqrt(x):
            """sqrt(x) as the card's approximate float32 square root treats subnormals."""
            return _ftz(tl.sqrt(_ftz(x)))
    elif FAST_FLOAT32:
        @triton.jit
        def _div(a, b):
            """a / b: IEEE division in float64, Triton's approximate one in float32."""
            return a / b

        @triton.jit
        def _sqrt(x):
            """sqrt(x): IEEE in float64, Triton's approximate one in float32."""
            return tl.sqrt(x)
    else:
        @triton.jit
        def _div(a, b):
            """a / b rounded as IEEE division (torch's, in float32 too; Triton's float32 ``/`` is approximate)."""
            if b.dtype == tl.float32:
                r = tl.div_rn(a, b)
            else:
                r = a / b
            return r

        @triton.jit
        def _sqrt(x):
            """sqrt(x) rounded as IEEE (torch's; Triton's float32 tl.sqrt is approximate)."""
            if x.dtype == tl.float32:
                r = tl.sqrt_rn(x)
            else:
                r = tl.sqrt(x)
            return r

    @triton.jit
    def _desing(h, q, sqrt2, heps4):
        """friction.desingularised_velocity."""
        h4 = h * h * h * h
        return _div(sqrt2 * h * q, _sqrt(h4 + _max(h4, heps4)))

    @triton.jit
    def _unit(px, py):
        """stepping.unit_direction."""
        n = _sqrt(px * px + py * py)
        ok = n > 0      # not n^2 > 0: a fast float32 sqrt flushes a subnormal n^2 to 0
        inv = tl.where(ok, _div(1.0, tl.where(ok, n, 1.0)), 0.0)
        return px * inv, py * inv

    @triton.jit
    def _stretch(ex, ey, zx, zy):
        """stepping.stretch."""
        se = zx * ex + zy * ey
        return _sqrt(1.0 + se * se)

    @triton.jit
    def _minmod3(a, b, c):
        mn = _min(_min(a, b), c)
        mx = _max(_max(a, b), c)
        return tl.where(mn > 0, mn, tl.where(mx < 0, mx, 0.0))

    @triton.jit
    def _lin(ptr, base, c, n, stride, m):
        """The field at cell c (in [-2, n + 1]) of a line of n cells, ghost cells by linear extrapolation
        (scheme.pad_linear)."""
        q = tl.load(ptr + base + tl.minimum(tl.maximum(c, 0), n - 1) * stride, mask=m, other=0.0)
        lo, hi = m & (c < 0), m & (c >= n)
        l0 = tl.load(ptr + base, mask=lo, other=0.0)
        l1 = tl.load(ptr + base + stride, mask=lo, other=0.0)
        r0 = tl.load(ptr + base + (n - 1) * stride, mask=hi, other=0.0)
        r1 = tl.load(ptr + base + (n - 2) * stride, mask=hi, other=0.0)
        q = tl.where(c == -1, 2 * l0 - l1, q)
        q = tl.where(c == -2, 3 * l0 - 2 * l1, q)
        q = tl.where(c == n, 2 * r0 - r1, q)
        return tl.where(c == n + 1, 3 * r0 - 2 * r1, q)

    @triton.jit
    def _vel(h_ptr, q_ptr, w_ptr, at, sqrt2, heps4, m, STORED: tl.constexpr):
        """The desingularised velocity of the momentum component q at the flat cell offsets ``at``: read
        from w (its stored values, _velocities) or computed from h and q."""
        if STORED:
            w = tl.load(w_ptr + at, mask=m, other=0.0)
        else:
            w = _desing(tl.load(h_ptr + at, mask=m, other=0.0), tl.load(q_ptr + at, mask=m, other=0.0), sqrt2, heps4)
        return w

    @triton.jit
    def _face_vel(h_ptr, q_ptr, w_ptr, c0, c1, c2, c3, theta, sqrt2, heps4, m, STORED: tl.constexpr):
        """The velocity of component q reconstructed at a face from the cells c0 .. c3 around it (two left,
        two right): its left and right values (scheme.reconstruct)."""
        v0 = _vel(h_ptr, q_ptr, w_ptr, c0, sqrt2, heps4, m, STORED)
        v1 = _vel(h_ptr, q_ptr, w_ptr, c1, sqrt2, heps4, m, STORED)
        v2 = _vel(h_ptr, q_ptr, w_ptr, c2, sqrt2, heps4, m, STORED)
        v3 = _vel(h_ptr, q_ptr, w_ptr, c3, sqrt2, heps4, m, STORED)
        left = v1 + 0.5 * _minmod3(theta * (v1 - v0), 0.5 * (v2 - v0), theta * (v2 - v1))
        right = v2 - 0.5 * _minmod3(theta * (v2 - v1), 0.5 * (v3 - v1), theta * (v3 - v2))
        return left, right

    @triton.jit
    def _velocities(h_ptr, hu_ptr, hv_ptr, c_ptr, u_ptr, v_ptr, n, BLOCK: tl.constexpr):
        """u, v of the n cells of every member (VELOCITIES = "stored")."""
        idx = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = idx < n
        sqrt2, heps4 = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4)
        h = tl.load(h_ptr + idx, mask=m, other=0.0)
        tl.store(u_ptr + idx, _desing(h, tl.load(hu_ptr + idx, mask=m, other=0.0), sqrt2, heps4), mask=m)
        tl.store(v_ptr + idx, _desing(h, tl.load(hv_ptr + idx, mask=m, other=0.0), sqrt2, heps4), mask=m)

    @triton.jit
    def _carried(h_ptr, hu_ptr, hv_ptr, zx_ptr, zy_ptr, c_ptr, cu_ptr, cv_ptr, ny, nx, s_geo, BLOCK: tl.constexpr):
        """The velocity the momentum flux carries with the slope metric, sigma u and sigma v (stepping._stage:
        the surface speed in the map direction of motion), of every cell of every member."""
        b = tl.program_id(1)
        idx = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        sqrt2, heps4 = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4)
        cb = b * ny * nx + idx
        h = tl.load(h_ptr + cb, mask=m, other=0.0)
        u = _desing(h, tl.load(hu_ptr + cb, mask=m, other=0.0), sqrt2, heps4)
        v = _desing(h, tl.load(hv_ptr + cb, mask=m, other=0.0), sqrt2, heps4)
        ex, ey = _unit(u, v)
        sg = _stretch(ex, ey, tl.load(zx_ptr + b * s_geo + idx, mask=m, other=0.0),
                      tl.load(zy_ptr + b * s_geo + idx, mask=m, other=0.0))
        tl.store(cu_ptr + cb, sg * u, mask=m)
        tl.store(cv_ptr + cb, sg * v, mask=m)

    @triton.jit
    def _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, i, j, ny, nx, g, sqrt2, heps4, m,
            USE_EP: tl.constexpr, STORED: tl.constexpr):
        """The pressure coefficient k g cos^2 at cells (i, j) (stepping._stage with stepping._earth_pressure:
        with earth pressure, k is active where the flow spreads (div u >= 0), passive where it converges;
        the velocities of the four neighbours replicated at the edges). cb, gb: the member's offsets of the
        state and of the geometry."""
        cs = tl.load(cs_ptr + gb + i * nx + j, mask=m, other=1.0)
        k = tl.load(pm_ptr + b * 11 + 3)
        if USE_EP:
            row, col = cb + i * nx, cb + j
            ue = _vel(h_ptr, hu_ptr, u_ptr, row + tl.minimum(j + 1, nx - 1), sqrt2, heps4, m, STORED)
            uw = _vel(h_ptr, hu_ptr, u_ptr, row + tl.maximum(j - 1, 0), sqrt2, heps4, m, STORED)
            vn = _vel(h_ptr, hv_ptr, v_ptr, col + tl.minimum(i + 1, ny - 1) * nx, sqrt2, heps4, m, STORED)
            vs = _vel(h_ptr, hv_ptr, v_ptr, col + tl.maximum(i - 1, 0) * nx, sqrt2, heps4, m, STORED)
            div = (ue - uw) + (vn - vs)
            s = tl.load(pm_ptr + b * 11 + 4)
            ksh = tl.where(div >= 0, tl.load(pm_ptr + b * 11 + 5), tl.load(pm_ptr + b * 11 + 6))
            k = (1.0 - s) * k + s * ksh
        return k * (g * cs) * cs

    @triton.jit
    def _central_upwind(hl, hr, ul, ur, cnl, cnr, tlf, trf, kgl, kgr, wsmin):
        """The central-upwind fluxes at a face (KP07 Eq. 3.11, scheme.sweep) from its left and right
        thickness, normal velocity, carried normal and tangential velocity and pressure coefficient: the mass
        and momentum fluxes, the pressure potential phi and the largest one-sided speed max(a+, -a-)."""
        cl = _sqrt(kgl * hl)
        cr = _sqrt(kgr * hr)
        ap = _max(_max(ur + cr, ul + cl), 0.0)
        am = _min(_min(ur - cr, ul - cl), 0.0)
        den = ap - am
        pos = den > wsmin
        inv = tl.where(pos, _div(1.0, tl.where(pos, den, 1.0)), 0.0)
        apam = ap * am * inv
        ql, qr = hl * ul, hr * ur
        fh = (ap * ql - am * qr) * inv + apam * (hr - hl)
        fqn = (ap * ql * cnl - am * qr * cnr) * inv + apam * (hr * cnr - hl * cnl)
        fqt = (ap * ql * tlf - am * qr * trf) * inv + apam * (hr * trf - hl * tlf)
        phi = 0.5 * (ap * hl * hl - am * hr * hr) * inv
        return fh, fqn, fqt, phi, _max(ap, -am)

    @triton.jit
    def _creep_frozen(h1, h2, z1, z2, kgl, kgr, zxa, zxc, zya, zyc, csa, csc, mua, muc, rest_a, rest_c, pm_ptr,
                      c_ptr, b, AXIS: tl.constexpr, USE_MUS: tl.constexpr):
        """scheme.frozen_faces at faces between cells a (left) and c (right): both at rest and friction holds
        the face's drive. h1, h2 and z1, z2: the clipped padded thickness and the bed of a and c; mua, muc:
        their friction map's factors (USE_MUS)."""
        g = tl.load(c_ptr + C_G)
        hf = 0.5 * (h1 + h2)
        f_n = -(0.5 * (kgl + kgr) * (h2 - h1) + g * (z2 - z1)) * hf * tl.load(c_ptr + C_INVDX)
        zxf = 0.5 * (zxa + zxc)
        zyf = 0.5 * (zya + zyc)
        csf = 0.5 * (csa + csc)
        mu = tl.load(pm_ptr + b * 11)
        tau = tl.load(pm_ptr + b * 11 + 2)
        if USE_MUS:
            mua = mu * mua
            muc = mu * muc
        else:
            mua = mu
            muc = mu
        muf = 0.5 * (mua * (g * csa) + muc * (g * csc))
        tauf = 0.5 * (_div(tau, csa) + _div(tau, csc))
        if AXIS == 0:
            f_t = -g * zyf * hf
            ax, ay = f_n, f_t
        else:
            f_t = -g * zxf * hf
            ax, ay = f_t, f_n
        along = zxf * ax + zyf * ay
        drive2 = ax * ax + ay * ay - csf * csf * along * along
        lim = muf * hf + tauf
        return rest_a & rest_c & (drive2 <= lim * lim)

    @triton.jit
    def _fo(b, ny, nx, AXIS: tl.constexpr):
        """Offset of member b's faces: (ny, nx + 1) x faces or (ny + 1, nx) y faces per member."""
        if AXIS == 0:
            return b * ny * (nx + 1)
        else:
            return b * (ny + 1) * nx

    @triton.jit
    def _faces(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cu_ptr, cv_ptr, zp_ptr, zx_ptr, zy_ptr, cs_ptr, mus_ptr,
               inside_ptr, pm_ptr, c_ptr, fh_ptr, fqn_ptr, fqt_ptr, phi_ptr, hl_ptr, hr_ptr, amax_ptr, ny, nx, s_zp,
               s_geo, AXIS: tl.constexpr, NO_CREEP: tl.constexpr, WALLS: tl.constexpr, USE_MUS: tl.constexpr,
               USE_EP: tl.constexpr, STORED: tl.constexpr, SLOPE: tl.constexpr, BLOCK: tl.constexpr):
        """scheme.sweep (and scheme.frozen_faces, stepping._domain_walls) at the x faces (AXIS 0: (ny, nx + 1)
        per member) or the y faces (AXIS 1: (ny + 1, nx)); face f of a line lies between cells f - 1 and f.
        zp: the bed padded along the axis (scheme.bed_terms' zp); u, v: the stored velocities (STORED);
        cu, cv: the carried velocities (SLOPE, _carried)."""
        b = tl.program_id(1)
        pid = tl.program_id(0)
        idx = pid * BLOCK + tl.arange(0, BLOCK)
        if AXIS == 0:
            n = nx
            m = idx < ny * (nx + 1)
            line, f = idx // (nx + 1), idx % (nx + 1)
            base, st = line * nx, 1
            zbase, zst = line * (nx + 4), 1
        else:
            n = ny
            m = idx < (ny + 1) * nx
            f, line = idx // nx, idx % nx
            base, st = line, nx
            zbase, zst = line, nx
        cb = b * ny * nx
        gb = b * s_geo
        g, dx, theta = tl.load(c_ptr + C_G), tl.load(c_ptr + C_DX), tl.load(c_ptr + C_THETA)
        h_wet, wb, wsmin = tl.load(c_ptr + C_HWET), tl.load(c_ptr + C_WB), tl.load(c_ptr + C_WSMIN)
        # thickness (clipped at 0) and bed at the four cells f - 2 .. f + 1 (padded indices f .. f + 3)
        h0 = _max(_lin(h_ptr, cb + base, f - 2, n, st, m), 0.0)
        h1 = _max(_lin(h_ptr, cb + base, f - 1, n, st, m), 0.0)
        h2 = _max(_lin(h_ptr, cb + base, f, n, st, m), 0.0)
        h3 = _max(_lin(h_ptr, cb + base, f + 1, n, st, m), 0.0)
        zb = zp_ptr + b * s_zp + zbase
        z0 = tl.load(zb + f * zst, mask=m, other=0.0)
        z1 = tl.load(zb + (f + 1) * zst, mask=m, other=0.0)
        z2 = tl.load(zb + (f + 2) * zst, mask=m, other=0.0)
        z3 = tl.load(zb + (f + 3) * zst, mask=m, other=0.0)
        bf = 0.5 * (z1 + z2)
        # surface w = h + z where wet, thickness h at wet/dry fronts (scheme.sweep)
        w0, w1, w2, w3 = h0 + z0, h1 + z1, h2 + z2, h3 + z3
        wl = w1 + 0.5 * _minmod3(theta * (w1 - w0), 0.5 * (w2 - w0), theta * (w2 - w1))
        wr = w2 - 0.5 * _minmod3(theta * (w2 - w1), 0.5 * (w3 - w1), theta * (w3 - w2))
        hlh = h1 + 0.5 * _minmod3(theta * (h1 - h0), 0.5 * (h2 - h0), theta * (h2 - h1))
        hrh = h2 - 0.5 * _minmod3(theta * (h2 - h1), 0.5 * (h3 - h1), theta * (h3 - h2))
        bias_l = tl.abs(z2 - 2.0 * z1 + z0) * 0.25
        bias_r = tl.abs(z3 - 2.0 * z2 + z1) * 0.25
        wet_l = (_min(_min(h0, h1), h2) > h_wet) & (bias_l <= wb * h1)
        wet_r = (_min(_min(h1, h2), h3) > h_wet) & (bias_r <= wb * h2)
        hl = tl.where(wet_l, _max(wl - bf, 0.0), hlh)
        hr = tl.where(wet_r, _max(wr - bf, 0.0), hrh)
        # velocities normal (un) and tangential (ut) to the face, replicated at the edges
        if AXIS == 0:
            qn_ptr, qt_ptr, wn_ptr, wt_ptr, cn_ptr, ct_ptr = hu_ptr, hv_ptr, u_ptr, v_ptr, cu_ptr, cv_ptr
        else:
            qn_ptr, qt_ptr, wn_ptr, wt_ptr, cn_ptr, ct_ptr = hv_ptr, hu_ptr, v_ptr, u_ptr, cv_ptr, cu_ptr
        sqrt2, heps4 = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4)
        c0 = cb + base + tl.minimum(tl.maximum(f - 2, 0), n - 1) * st
        c1 = cb + base + tl.minimum(tl.maximum(f - 1, 0), n - 1) * st
        c2 = cb + base + tl.minimum(f, n - 1) * st
        c3 = cb + base + tl.minimum(f + 1, n - 1) * st
        ul, ur = _face_vel(h_ptr, qn_ptr, wn_ptr, c0, c1, c2, c3, theta, sqrt2, heps4, m, STORED)
        if SLOPE:       # the carried velocities (stored by _carried)
            cnl, cnr = _face_vel(h_ptr, qn_ptr, cn_ptr, c0, c1, c2, c3, theta, sqrt2, heps4, m, True)
            tlf, trf = _face_vel(h_ptr, qt_ptr, ct_ptr, c0, c1, c2, c3, theta, sqrt2, heps4, m, True)
        else:
            cnl, cnr = ul, ur
            tlf, trf = _face_vel(h_ptr, qt_ptr, wt_ptr, c0, c1, c2, c3, theta, sqrt2, heps4, m, STORED)
        a = tl.minimum(tl.maximum(f - 1, 0), n - 1)      # the cells left and right of the face
        c = tl.minimum(f, n - 1)
        if AXIS == 0:
            kgl = _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, line, a, ny, nx, g, sqrt2, heps4,
                      m, USE_EP, STORED)
            kgr = _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, line, c, ny, nx, g, sqrt2, heps4,
                      m, USE_EP, STORED)
        else:
            kgl = _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, a, line, ny, nx, g, sqrt2, heps4,
                      m, USE_EP, STORED)
            kgr = _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, c, line, ny, nx, g, sqrt2, heps4,
                      m, USE_EP, STORED)
        fh, fqn, fqt, phi, speed = _central_upwind(hl, hr, ul, ur, cnl, cnr, tlf, trf, kgl, kgr, wsmin)
        if NO_CREEP or WALLS:
            frozen = tl.zeros([BLOCK], dtype=tl.int1)
            if NO_CREEP:    # scheme.frozen_faces: both cells at rest and friction holds the face's drive
                if USE_MUS:
                    mua = tl.load(mus_ptr + base + a * st, mask=m, other=1.0)
                    muc = tl.load(mus_ptr + base + c * st, mask=m, other=1.0)
                else:
                    mua = 1.0
                    muc = 1.0
                rest_a = (tl.load(hu_ptr + cb + base + a * st, mask=m, other=1.0) == 0) \
                    & (tl.load(hv_ptr + cb + base + a * st, mask=m, other=1.0) == 0)
                rest_c = (tl.load(hu_ptr + cb + base + c * st, mask=m, other=1.0) == 0) \
                    & (tl.load(hv_ptr + cb + base + c * st, mask=m, other=1.0) == 0)
                frozen = _creep_frozen(h1, h2, z1, z2, kgl, kgr,
                                       tl.load(zx_ptr + gb + base + a * st, mask=m, other=0.0),
                                       tl.load(zx_ptr + gb + base + c * st, mask=m, other=0.0),
                                       tl.load(zy_ptr + gb + base + a * st, mask=m, other=0.0),
                                       tl.load(zy_ptr + gb + base + c * st, mask=m, other=0.0),
                                       tl.load(cs_ptr + gb + base + a * st, mask=m, other=1.0),
                                       tl.load(cs_ptr + gb + base + c * st, mask=m, other=1.0),
                                       mua, muc, rest_a, rest_c, pm_ptr, c_ptr, b, AXIS, USE_MUS)
            if WALLS:       # faces between a cell of the domain and one outside it
                ins_a = tl.load(inside_ptr + base + a * st, mask=m, other=0)
                ins_c = tl.load(inside_ptr + base + c * st, mask=m, other=0)
                frozen = frozen | (ins_a != ins_c)
            fh = tl.where(frozen, 0.0, fh)
            fqn = tl.where(frozen, 0.0, fqn)
            fqt = tl.where(frozen, 0.0, fqt)
        fo = _fo(b, ny, nx, AXIS)
        tl.store(fh_ptr + fo + idx, fh, mask=m)
        tl.store(fqn_ptr + fo + idx, fqn, mask=m)
        tl.store(fqt_ptr + fo + idx, fqt, mask=m)
        tl.store(phi_ptr + fo + idx, phi, mask=m)
        tl.store(hl_ptr + fo + idx, hl, mask=m)
        tl.store(hr_ptr + fo + idx, hr, mask=m)
        tl.store(amax_ptr + b * tl.num_programs(0) + pid, tl.max(tl.where(m, speed, 0.0), axis=0))

    @triton.jit
    def _along(q, index, AXIS: tl.constexpr):
        """q at the tile positions ``index`` along the tile's x axis (AXIS 0, its columns) or y axis (AXIS 1,
        its rows): a neighbour's value from the tile itself (shared memory), not from global memory."""
        return tl.gather(q, index, 1 - AXIS)

    @triton.jit
    def _padded(q, inside_line, d, near, AXIS: tl.constexpr):
        """q continued by linear extrapolation at the tile's ghost positions along one axis (scheme.pad_linear):
        at a ghost d cells outside the grid, (1 + d) q0 - d q1 from the edge cell's q0 (what the ghost loaded:
        its clamped cell) and the next cell's q1 (the tile position ``near``)."""
        q1 = _along(q, near, AXIS)
        return tl.where(inside_line, q, tl.where(d == 1, 2 * q - q1, 3 * q - 2 * q1))

    @triton.jit
    def _east_west(q, west, east, theta):
        """The generalised-minmod reconstruction of q at each cell's east and west face (scheme.reconstruct),
        from its neighbours west and east along the axis."""
        s = _minmod3(theta * (q - west), 0.5 * (east - west), theta * (east - q))
        return q + 0.5 * s, q - 0.5 * s

    @triton.jit
    def _tile_faces(hp, z, u_n, U_n, T, kg, hu, hv, zx, zy, cs, mus, ins, sW, sE, pm_ptr, c_ptr, b,
                    AXIS: tl.constexpr, NO_CREEP: tl.constexpr, WALLS: tl.constexpr, USE_MUS: tl.constexpr):
        """scheme.sweep at the west (AXIS 0) or south (AXIS 1) face of every tile position, from the tile's
        padded thickness hp, padded bed z, normal velocity u_n, carried normal and tangential velocities U_n,
        T and pressure coefficient kg; sW, sE: the positions before and after each along the axis. Each
        position's reconstruction is computed once and read by the face after it from the tile."""
        theta = tl.load(c_ptr + C_THETA)
        h_wet, wb, wsmin = tl.load(c_ptr + C_HWET), tl.load(c_ptr + C_WB), tl.load(c_ptr + C_WSMIN)
        hW, hE = _along(hp, sW, AXIS), _along(hp, sE, AXIS)
        zW, zE = _along(z, sW, AXIS), _along(z, sE, AXIS)
        w = hp + z
        w_e, w_w = _east_west(w, hW + zW, hE + zE, theta)
        h_e, h_w = _east_west(hp, hW, hE, theta)
        wet = ((_min(_min(hW, hp), hE) > h_wet) & (tl.abs(zE - 2.0 * z + zW) * 0.25 <= wb * hp)).to(tl.int8)
        u_e, u_w = _east_west(u_n, _along(u_n, sW, AXIS), _along(u_n, sE, AXIS), theta)
        U_e, U_w = _east_west(U_n, _along(U_n, sW, AXIS), _along(U_n, sE, AXIS), theta)
        T_e, T_w = _east_west(T, _along(T, sW, AXIS), _along(T, sE, AXIS), theta)
        # the face's left state: the east values of the position before it
        bf = 0.5 * (zW + z)
        hl = tl.where(_along(wet, sW, AXIS) != 0, _max(_along(w_e, sW, AXIS) - bf, 0.0), _along(h_e, sW, AXIS))
        hr = tl.where(wet != 0, _max(w_w - bf, 0.0), h_w)
        kgl = _along(kg, sW, AXIS)
        fh, fqn, fqt, phi, speed = _central_upwind(hl, hr, _along(u_e, sW, AXIS), u_w, _along(U_e, sW, AXIS), U_w,
                                                   _along(T_e, sW, AXIS), T_w, kgl, kg, wsmin)
        if NO_CREEP or WALLS:
            frozen = tl.zeros(hp.shape, dtype=tl.int1)
            if NO_CREEP:
                rest = ((hu == 0) & (hv == 0)).to(tl.int8)
                frozen = _creep_frozen(hW, hp, zW, z, kgl, kg, _along(zx, sW, AXIS), zx, _along(zy, sW, AXIS), zy,
                                       _along(cs, sW, AXIS), cs, _along(mus, sW, AXIS), mus,
                                       _along(rest, sW, AXIS) != 0, rest != 0, pm_ptr, c_ptr, b, AXIS, USE_MUS)
            if WALLS:
                frozen = frozen | (_along(ins, sW, AXIS) != ins)
            fh = tl.where(frozen, 0.0, fh)
            fqn = tl.where(frozen, 0.0, fqn)
            fqt = tl.where(frozen, 0.0, fqt)
        return fh, fqn, fqt, phi, hl, hr, speed

    @triton.jit
    def _store_faces(fh, fqn, fqt, phi, hl, hr, speed, fh_ptr, fqn_ptr, fqt_ptr, phi_ptr, hl_ptr, hr_ptr, amax_ptr,
                     at, m, tile):
        """A tile's faces (at: their offsets; m: the faces it holds) and their largest one-sided speed."""
        tl.store(fh_ptr + at, fh, mask=m)
        tl.store(fqn_ptr + at, fqn, mask=m)
        tl.store(fqt_ptr + at, fqt, mask=m)
        tl.store(phi_ptr + at, phi, mask=m)
        tl.store(hl_ptr + at, hl, mask=m)
        tl.store(hr_ptr + at, hr, mask=m)
        tl.store(amax_ptr + tile, tl.max(tl.max(tl.where(m, speed, 0.0), axis=1), axis=0))

    @triton.jit
    def _tiled(h_ptr, hu_ptr, hv_ptr, zpx_ptr, zpy_ptr, zx_ptr, zy_ptr, cs_ptr, mus_ptr, inside_ptr, pm_ptr, c_ptr,
               u_ptr, v_ptr, fhx_ptr, fqnx_ptr, fqtx_ptr, phix_ptr, hlx_ptr, hrx_ptr, amx_ptr,
               fhy_ptr, fqny_ptr, fqty_ptr, phiy_ptr, hly_ptr, hry_ptr, amy_ptr, ny, nx, s_zpx, s_zpy, s_geo,
               NO_CREEP: tl.constexpr, WALLS: tl.constexpr, USE_MUS: tl.constexpr, USE_EP: tl.constexpr,
               SLOPE: tl.constexpr, TY: tl.constexpr, TX: tl.constexpr):
        """The velocities, the carried velocities, the pressure coefficient and scheme.sweep's x and y faces
        of a tile of TY x TX positions with a halo (FACES = "tiled"): the tile holds the cells (i, j), i in
        [ty (TY - 3), ty (TY - 3) + TY - 3) and j alike, and reads the two rows and columns before them and
        the one after (ghost positions outside the grid: the thickness and bed extrapolated linearly, the
        rest replicated). It writes the x face west of each cell it holds (j <= nx: the last column's east
        face too), the y face south of each (i <= ny), and u, v."""
        tx, ty, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
        rr = tl.broadcast_to(tl.arange(0, TY)[:, None], (TY, TX))   # tile rows and columns of each position
        ss = tl.broadcast_to(tl.arange(0, TX)[None, :], (TY, TX))
        i0, j0 = ty * (TY - 3) - 2, tx * (TX - 3) - 2                 # the cell of position (0, 0)
        i, j = i0 + rr, j0 + ss
        ic, jc = tl.minimum(tl.maximum(i, 0), ny - 1), tl.minimum(tl.maximum(j, 0), nx - 1)
        cell = ic * nx + jc
        cb, gb = b * ny * nx, b * s_geo
        g = tl.load(c_ptr + C_G)
        sqrt2, heps4 = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4)
        h = tl.load(h_ptr + cb + cell)
        hu = tl.load(hu_ptr + cb + cell)
        hv = tl.load(hv_ptr + cb + cell)
        zx = tl.load(zx_ptr + gb + cell)
        zy = tl.load(zy_ptr + gb + cell)
        cs = tl.load(cs_ptr + gb + cell)
        row_in, col_in = (i >= 0) & (i < ny), (j >= 0) & (j < nx)
        # neighbours along each axis (clamped to the tile) and, at the ghosts, the cell next to the edge one
        sW, sE = tl.maximum(ss - 1, 0), tl.minimum(ss + 1, TX - 1)
        rS, rN = tl.maximum(rr - 1, 0), tl.minimum(rr + 1, TY - 1)
        dj = tl.where(j < 0, -j, j - (nx - 1))
        di = tl.where(i < 0, -i, i - (ny - 1))
        near_x = tl.minimum(tl.maximum(tl.where(j < 0, jc + 1, jc - 1) - j0, 0), TX - 1)
        near_y = tl.minimum(tl.maximum(tl.where(i < 0, ic + 1, ic - 1) - i0, 0), TY - 1)
        hp = _max(tl.where(row_in, _padded(h, col_in, dj, near_x, 0), _padded(h, row_in, di, near_y, 1)), 0.0)
        z = tl.where(row_in,
                     tl.load(zpx_ptr + b * s_zpx + ic * (nx + 4) + tl.minimum(tl.maximum(j, -2), nx + 1) + 2),
                     tl.load(zpy_ptr + b * s_zpy + (tl.minimum(tl.maximum(i, -2), ny + 1) + 2) * nx + jc))
        u = _desing(h, hu, sqrt2, heps4)
        v = _desing(h, hv, sqrt2, heps4)
        own = (rr >= 2) & (rr < TY - 1) & (ss >= 2) & (ss < TX - 1)
        tl.store(u_ptr + cb + cell, u, mask=own & row_in & col_in)
        tl.store(v_ptr + cb + cell, v, mask=own & row_in & col_in)
        if SLOPE:       # the carried velocities (stepping._stage)
            ex, ey = _unit(u, v)
            sg = _stretch(ex, ey, zx, zy)
            cu, cv = sg * u, sg * v
        else:
            cu, cv = u, v
        k = tl.load(pm_ptr + b * 11 + 3)
        if USE_EP:      # _kg: the divergence of the velocities of the (clamped) cell's neighbours
            ue = tl.gather(u, tl.minimum(tl.maximum(tl.minimum(jc + 1, nx - 1) - j0, 0), TX - 1), 1)
            uw = tl.gather(u, tl.minimum(tl.maximum(tl.maximum(jc - 1, 0) - j0, 0), TX - 1), 1)
            vn = tl.gather(v, tl.minimum(tl.maximum(tl.minimum(ic + 1, ny - 1) - i0, 0), TY - 1), 0)
            vs = tl.gather(v, tl.minimum(tl.maximum(tl.maximum(ic - 1, 0) - i0, 0), TY - 1), 0)
            div = (ue - uw) + (vn - vs)
            s = tl.load(pm_ptr + b * 11 + 4)
            ksh = tl.where(div >= 0, tl.load(pm_ptr + b * 11 + 5), tl.load(pm_ptr + b * 11 + 6))
            k = (1.0 - s) * k + s * ksh
        kg = k * (g * cs) * cs
        if USE_MUS:
            mus = tl.load(mus_ptr + cell)
        else:
            mus = cs
        if WALLS:
            ins = tl.load(inside_ptr + cell).to(tl.int8)
        else:
            ins = cs
        tile = b * tl.num_programs(0) * tl.num_programs(1) + ty * tl.num_programs(0) + tx
        fh, fqn, fqt, phi, hl, hr, speed = _tile_faces(hp, z, u, cu, cv, kg, hu, hv, zx, zy, cs, mus, ins, sW, sE,
                                                       pm_ptr, c_ptr, b, 0, NO_CREEP, WALLS, USE_MUS)
        _store_faces(fh, fqn, fqt, phi, hl, hr, speed, fhx_ptr, fqnx_ptr, fqtx_ptr, phix_ptr, hlx_ptr, hrx_ptr, amx_ptr,
                     b * ny * (nx + 1) + ic * (nx + 1) + j, own & row_in & (j <= nx), tile)
        fh, fqn, fqt, phi, hl, hr, speed = _tile_faces(hp, z, v, cv, cu, kg, hu, hv, zx, zy, cs, mus, ins, rS, rN,
                                                       pm_ptr, c_ptr, b, 1, NO_CREEP, WALLS, USE_MUS)
        _store_faces(fh, fqn, fqt, phi, hl, hr, speed, fhy_ptr, fqny_ptr, fqty_ptr, phiy_ptr, hly_ptr, hry_ptr, amy_ptr,
                     b * (ny + 1) * nx + i * nx + jc, own & col_in & (i <= ny), tile)

    @triton.jit
    def _drain(h_ptr, fhx_ptr, fhy_ptr, dt_ptr, c_ptr, fac_ptr, ny, nx, BLOCK: tl.constexpr):
        """scheme.draining_factors' factor per cell: content / outgoing mass where that is below 1."""
        b = tl.program_id(1)
        idx = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        i, j = idx // nx, idx % nx
        xw = b * ny * (nx + 1) + i * (nx + 1) + j
        ys = b * (ny + 1) * nx + idx
        out = (_max(tl.load(fhx_ptr + xw + 1, mask=m, other=0.0), 0.0) + _max(-tl.load(fhx_ptr + xw, mask=m, other=0.0), 0.0)) \
            + (_max(tl.load(fhy_ptr + ys + nx, mask=m, other=0.0), 0.0) + _max(-tl.load(fhy_ptr + ys, mask=m, other=0.0), 0.0))
        out = out * (tl.load(dt_ptr + b) * tl.load(c_ptr + C_INVDX))
        h = tl.load(h_ptr + b * ny * nx + idx, mask=m, other=0.0)
        over = (out > h) & (out >= tl.load(c_ptr + C_NORMAL))
        tl.store(fac_ptr + b * ny * nx + idx, tl.where(over, _div(h, tl.where(over, out, 1.0)), 1.0), mask=m)

    @triton.jit
    def _face_factor(flux, fac_ptr, up, down, has_up, has_down, ghost, m):
        """The draining factor of a face: its upwind cell's (``up`` for flux > 0, else ``down``; ``ghost``
        outside the grid)."""
        f_up = tl.where(has_up, tl.load(fac_ptr + up, mask=m & has_up, other=1.0), ghost)
        f_down = tl.where(has_down, tl.load(fac_ptr + down, mask=m & has_down, other=1.0), ghost)
        return tl.where(flux > 0, f_up, f_down)

    @triton.jit
    def _hform(zxx, zxy, zyy, u, v):
        """stepping._hessian_form: u^T H u."""
        return zxx * u * u + 2.0 * zxy * u * v + zyy * v * v

    @triton.jit
    def _update(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, z_ptr, erod_ptr, dep_ptr, fac_ptr,
                fhx_ptr, fqnx_ptr, fqtx_ptr, phix_ptr, hlx_ptr, hrx_ptr,
                fhy_ptr, fqny_ptr, fqty_ptr, phiy_ptr, hly_ptr, hry_ptr,
                zpx_ptr, zpy_ptr, zx_ptr, zy_ptr, cs_ptr, zxx_ptr, zxy_ptr, zyy_ptr, mus_ptr, inside_ptr,
                pm_ptr, c_ptr, dt_ptr, ho_ptr, huo_ptr, hvo_ptr, zo_ptr, erodo_ptr, depo_ptr, part_ptr,
                ny, nx, s_geo, s_zpx, s_zpy,
                SLOPE: tl.constexpr, USE_CURV: tl.constexpr, USE_MU_I: tl.constexpr, USE_ENT: tl.constexpr,
                USE_DEP: tl.constexpr, USE_MUS: tl.constexpr, GONE_OUT: tl.constexpr, INFLOW: tl.constexpr,
                USE_EP: tl.constexpr, STORED: tl.constexpr, BLOCK: tl.constexpr):
        """The rest of stepping._stage for each cell: draining-limited fluxes, gravity and pressure along
        the surface (Eq. 2-3), entrainment and deposition, friction (Eq. 4, friction.apply_friction). part:
        (B, programs, 2) the block's boundary flux (outward, m^2/s) and the thickness lost outside the domain."""
        b = tl.program_id(1)
        pid = tl.program_id(0)
        idx = pid * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        i, j = idx // nx, idx % nx
        cb = b * ny * nx
        gb = b * s_geo
        g, dx = tl.load(c_ptr + C_G), tl.load(c_ptr + C_DX)
        sqrt2, heps4, h_eps = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4), tl.load(c_ptr + C_HEPS)
        if INFLOW:
            ghost = 1.0
        else:
            ghost = 0.0
        dt = tl.load(dt_ptr + b)
        # draining-limited fluxes at the four faces of the cell
        xw = b * ny * (nx + 1) + i * (nx + 1) + j
        ys = b * (ny + 1) * nx + idx
        fc = fac_ptr + cb
        fhxw, fhxe = tl.load(fhx_ptr + xw, mask=m, other=0.0), tl.load(fhx_ptr + xw + 1, mask=m, other=0.0)
        fhys, fhyn = tl.load(fhy_ptr + ys, mask=m, other=0.0), tl.load(fhy_ptr + ys + nx, mask=m, other=0.0)
        k_w = _face_factor(fhxw, fc, idx - 1, idx, j >= 1, j >= 0, ghost, m)
        k_e = _face_factor(fhxe, fc, idx, idx + 1, j >= 0, j + 1 < nx, ghost, m)
        k_s = _face_factor(fhys, fc, idx - nx, idx, i >= 1, i >= 0, ghost, m)
        k_n = _face_factor(fhyn, fc, idx, idx + nx, i >= 0, i + 1 < ny, ghost, m)
        fhxw, fhxe, fhys, fhyn = fhxw * k_w, fhxe * k_e, fhys * k_s, fhyn * k_n
        fqnxw = tl.load(fqnx_ptr + xw, mask=m, other=0.0) * k_w
        fqnxe = tl.load(fqnx_ptr + xw + 1, mask=m, other=0.0) * k_e
        fqtxw = tl.load(fqtx_ptr + xw, mask=m, other=0.0) * k_w
        fqtxe = tl.load(fqtx_ptr + xw + 1, mask=m, other=0.0) * k_e
        fqnys = tl.load(fqny_ptr + ys, mask=m, other=0.0) * k_s
        fqnyn = tl.load(fqny_ptr + ys + nx, mask=m, other=0.0) * k_n
        fqtys = tl.load(fqty_ptr + ys, mask=m, other=0.0) * k_s
        fqtyn = tl.load(fqty_ptr + ys + nx, mask=m, other=0.0) * k_n
        bnd = tl.where(j == nx - 1, fhxe, 0.0) - tl.where(j == 0, fhxw, 0.0) \
            + (tl.where(i == ny - 1, fhyn, 0.0) - tl.where(i == 0, fhys, 0.0))
        h = tl.load(h_ptr + cb + idx, mask=m, other=0.0)
        lam = dt * tl.load(c_ptr + C_INVDX)
        hn = h - lam * ((fhxe - fhxw) + (fhyn - fhys))
        # gravity and pressure as horizontal gradients (times dx), well-balanced bed source (KP07 Eq. 3.13)
        kg = _kg(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cs_ptr, pm_ptr, b, cb, gb, i, j, ny, nx, g, sqrt2, heps4, m,
                 USE_EP, STORED)
        zpx = zpx_ptr + b * s_zpx + i * (nx + 4) + j
        zpy = zpy_ptr + b * s_zpy + idx
        dbx = 0.5 * (tl.load(zpx + 2, mask=m, other=0.0) + tl.load(zpx + 3, mask=m, other=0.0)) \
            - 0.5 * (tl.load(zpx + 1, mask=m, other=0.0) + tl.load(zpx + 2, mask=m, other=0.0))
        dby = 0.5 * (tl.load(zpy + 2 * nx, mask=m, other=0.0) + tl.load(zpy + 3 * nx, mask=m, other=0.0)) \
            - 0.5 * (tl.load(zpy + nx, mask=m, other=0.0) + tl.load(zpy + 2 * nx, mask=m, other=0.0))
        hbarx = 0.5 * (tl.load(hrx_ptr + xw, mask=m, other=0.0) + tl.load(hlx_ptr + xw + 1, mask=m, other=0.0))
        hbary = 0.5 * (tl.load(hry_ptr + ys, mask=m, other=0.0) + tl.load(hly_ptr + ys + nx, mask=m, other=0.0))
        px = kg * (tl.load(phix_ptr + xw + 1, mask=m, other=0.0) - tl.load(phix_ptr + xw, mask=m, other=0.0)) \
            + g * hbarx * dbx
        py = kg * (tl.load(phiy_ptr + ys + nx, mask=m, other=0.0) - tl.load(phiy_ptr + ys, mask=m, other=0.0)) \
            + g * hbary * dby
        zx = tl.load(zx_ptr + gb + idx, mask=m, other=0.0)
        zy = tl.load(zy_ptr + gb + idx, mask=m, other=0.0)
        cs = tl.load(cs_ptr + gb + idx, mask=m, other=1.0)
        hu = tl.load(hu_ptr + cb + idx, mask=m, other=0.0)
        hv = tl.load(hv_ptr + cb + idx, mask=m, other=0.0)
        u = _vel(h_ptr, hu_ptr, u_ptr, cb + idx, sqrt2, heps4, m, STORED)
        v = _vel(h_ptr, hv_ptr, v_ptr, cb + idx, sqrt2, heps4, m, STORED)
        if USE_CURV:
            zxx = tl.load(zxx_ptr + gb + idx, mask=m, other=0.0)
            zxy = tl.load(zxy_ptr + gb + idx, mask=m, other=0.0)
            zyy = tl.load(zyy_ptr + gb + idx, mask=m, other=0.0)
        if SLOPE:   # along the surface (inverse_metric); the surface momentum Q = sigma q updated and turned back
            a = cs * cs * (zx * px + zy * py)
            px = px - zx * a
            py = py - zy * a
            e1, e2 = _unit(u, v)
            sg = _stretch(e1, e2, zx, zy)
            rest = (e1 == 0) & (e2 == 0)
            f1, f2 = _unit(px, py)
            e1 = tl.where(rest, f1, e1)
            e2 = tl.where(rest, f2, e2)
            sf = tl.where(rest, _stretch(e1, e2, zx, zy), sg)
            along = e1 * px + e2 * py
            tang = _div(along + (zx * e1 + zy * e2) * (zx * px + zy * py), sf)
            px, py = tang * e1 + sf * (px - e1 * along), tang * e2 + sf * (py - e2 * along)
            qx = sg * hu - lam * (((fqnxe - fqnxw) + (fqtyn - fqtys)) + px)
            qy = sg * hv - lam * (((fqtxe - fqtxw) + (fqnyn - fqnys)) + py)
            e1, e2 = _unit(qx, qy)
            sq = _stretch(e1, e2, zx, zy)
            qx = _div(qx, sq)
            qy = _div(qy, sq)
        else:
            qx = hu - lam * (((fqnxe - fqnxw) + (fqtyn - fqtys)) + px)
            qy = hv - lam * (((fqtxe - fqtxw) + (fqnyn - fqnys)) + py)
        lost = tl.zeros([BLOCK], dtype=h.dtype)
        if GONE_OUT:    # what entered a cell outside the domain has left it
            gone = tl.load(inside_ptr + idx, mask=m, other=1) == 0
            lost = tl.where(gone & m, hn, 0.0)
            hn = tl.where(gone, 0.0, hn)
            qx = tl.where(gone, 0.0, qx)
            qy = tl.where(gone, 0.0, qy)
        gn = g * cs
        if USE_ENT or USE_DEP:      # mass sources, explicit in the stage-start state
            w0 = zx * u + zy * v
            speed0 = _sqrt(u * u + v * v + w0 * w0)
            zn = tl.load(z_ptr + cb + idx, mask=m, other=0.0)
            if USE_ENT:
                erod = tl.load(erod_ptr + cb + idx, mask=m, other=0.0)
                rate = _div(tl.load(pm_ptr + b * 11 + 9) * speed0, cs) \
                    * (cs * h > tl.load(c_ptr + C_ENTMIN)).to(h.dtype)
                de = _min(dt * rate, erod)
                hn = hn + de
                tl.store(erodo_ptr + cb + idx, erod - de, mask=m)
                zn = zn - de
            if USE_DEP:
                hs0 = _max(cs * h, h_eps)
                froude = _div(speed0, _sqrt(_max(gn, tl.load(c_ptr + C_TINY)) * hs0))
                rate = tl.load(pm_ptr + b * 11 + 10) * h * _max(1.0 - _div(froude, tl.load(c_ptr + C_FRDEP)), 0.0)
                hpos = _max(hn, 0.0)
                dd = _min(dt * rate, hpos)
                left = (hpos > 0) & (hpos >= tl.load(c_ptr + C_NORMAL))
                ratio = tl.where(left, _div(hpos - dd, tl.where(left, hpos, 1.0)), 0.0)
                qx = qx * ratio
                qy = qy * ratio
                hn = hn - dd
                tl.store(depo_ptr + cb + idx, tl.load(dep_ptr + cb + idx, mask=m, other=0.0) + dd, mask=m)
                zn = zn + dd
            tl.store(zo_ptr + cb + idx, zn, mask=m)
        # friction on the momentum along the surface (Eq. 4)
        mu = tl.load(pm_ptr + b * 11)
        if USE_MUS:
            mu = mu * tl.load(mus_ptr + idx, mask=m, other=1.0)
        gne = gn
        hnp = _max(hn, 0.0)
        if USE_CURV or USE_MU_I:
            un = _desing(hn, qx, sqrt2, heps4)
            vn = _desing(hn, qy, sqrt2, heps4)
            if USE_CURV:
                gne = _max(gn + tl.load(pm_ptr + b * 11 + 7) * (cs * _hform(zxx, zxy, zyy, un, vn)), 0.0)
            if USE_MU_I:
                wn = zx * un + zy * vn
                spd = _sqrt(un * un + vn * vn + wn * wn)
                hs_ = _max(cs * hnp, h_eps)
                inertial = _div(tl.load(c_ptr + C_MUI) * spd, hs_ * _sqrt(_max(gne, tl.load(c_ptr + C_TINY)) * hs_))
                mu = mu + _div(tl.load(pm_ptr + b * 11 + 8) * inertial, tl.load(c_ptr + C_I0) + inertial)
        coul = mu * gne * hnp + _div(tl.load(pm_ptr + b * 11 + 2), cs)
        xi_c = tl.load(pm_ptr + b * 11 + 1) * cs
        w = zx * qx + zy * qy
        qn = _sqrt(qx * qx + qy * qy + w * w)
        moving = qn > 0
        keep = tl.where(moving, _max(1.0 - _div(dt * coul, tl.where(moving, qn, 1.0)), 0.0), 0.0)
        hs = _max(hn, h_eps)
        a4 = _div(4.0 * dt * (_div(1.0, xi_c) * g), hs * hs)   # torch's g / xi is xi.reciprocal() * g
        factor = _div(keep * 2.0, 1.0 + _sqrt(1.0 + a4 * (keep * qn)))
        qx = qx * factor
        qy = qy * factor
        thin = hn < h_eps
        qx = tl.where(thin, hn * _desing(hn, qx, sqrt2, heps4), qx)
        qy = tl.where(thin, hn * _desing(hn, qy, sqrt2, heps4), qy)
        tl.store(ho_ptr + cb + idx, _max(hn, 0.0), mask=m)
        tl.store(huo_ptr + cb + idx, qx, mask=m)
        tl.store(hvo_ptr + cb + idx, qy, mask=m)
        pp = part_ptr + (b * tl.num_programs(0) + pid) * 2
        tl.store(pp, tl.sum(tl.where(m, bnd, 0.0), axis=0))
        tl.store(pp + 1, tl.sum(lost, axis=0))

    @triton.jit
    def _combine(h_ptr, hu_ptr, hv_ptr, hu1_ptr, hv1_ptr, h2_ptr, hu2_ptr, hv2_ptr, z_ptr, z2_ptr, e_ptr, e2_ptr,
                 d_ptr, d2_ptr, rzx_ptr, rzy_ptr, rcs_ptr, hmax_ptr, vmax_ptr, arr_ptr, tnew_ptr, c_ptr,
                 ho_ptr, huo_ptr, hvo_ptr, zo_ptr, eo_ptr, do_ptr, hmaxo_ptr, vmaxo_ptr, arro_ptr, part_ptr, ny, nx,
                 MOVING: tl.constexpr, USE_ENT: tl.constexpr, USE_DEP: tl.constexpr, BLOCK: tl.constexpr):
        """The Heun average of the two stages and the per-step records of stepping.make_step (h_max of the
        normal thickness, v_max of the speed along the surface, arrival time); part: (B, programs, 2) the
        block's sums of h |V|^2 and of the thickness per map area."""
        b = tl.program_id(1)
        pid = tl.program_id(0)
        idx = pid * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        cb = b * ny * nx + idx
        hn = 0.5 * (tl.load(h_ptr + cb, mask=m, other=0.0) + tl.load(h2_ptr + cb, mask=m, other=0.0))
        hu2, hv2 = tl.load(hu2_ptr + cb, mask=m, other=0.0), tl.load(hv2_ptr + cb, mask=m, other=0.0)
        stop = (tl.load(hu1_ptr + cb, mask=m, other=0.0) == 0) & (tl.load(hv1_ptr + cb, mask=m, other=0.0) == 0) \
            & (hu2 == 0) & (hv2 == 0)
        qx = tl.where(stop, 0.0, 0.5 * (tl.load(hu_ptr + cb, mask=m, other=0.0) + hu2))
        qy = tl.where(stop, 0.0, 0.5 * (tl.load(hv_ptr + cb, mask=m, other=0.0) + hv2))
        tl.store(ho_ptr + cb, hn, mask=m)
        tl.store(huo_ptr + cb, qx, mask=m)
        tl.store(hvo_ptr + cb, qy, mask=m)
        if MOVING:
            tl.store(zo_ptr + cb, 0.5 * (tl.load(z_ptr + cb, mask=m, other=0.0) + tl.load(z2_ptr + cb, mask=m, other=0.0)),
                     mask=m)
        if USE_ENT:
            tl.store(eo_ptr + cb, 0.5 * (tl.load(e_ptr + cb, mask=m, other=0.0) + tl.load(e2_ptr + cb, mask=m, other=0.0)),
                     mask=m)
        hfin = hn
        if USE_DEP:
            dn = 0.5 * (tl.load(d_ptr + cb, mask=m, other=0.0) + tl.load(d2_ptr + cb, mask=m, other=0.0))
            tl.store(do_ptr + cb, dn, mask=m)
            hfin = hn + dn
        sqrt2, heps4 = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4)
        un = _desing(hn, qx, sqrt2, heps4)
        vn = _desing(hn, qy, sqrt2, heps4)
        rzx = tl.load(rzx_ptr + idx, mask=m, other=0.0)
        rzy = tl.load(rzy_ptr + idx, mask=m, other=0.0)
        rcs = tl.load(rcs_ptr + idx, mask=m, other=1.0)
        w = rzx * un + rzy * vn
        spd = _sqrt(un * un + vn * vn + w * w)
        hnorm = rcs * hn
        tl.store(hmaxo_ptr + cb, _max(tl.load(hmax_ptr + cb, mask=m, other=0.0), rcs * hfin), mask=m)
        vmax = _max(tl.load(vmax_ptr + cb, mask=m, other=0.0), tl.where(hnorm >= tl.load(c_ptr + C_VMIN), spd, 0.0))
        tl.store(vmaxo_ptr + cb, vmax, mask=m)
        arr = tl.load(arr_ptr + cb, mask=m, other=0.0)
        arrived = (arr == tl.load(c_ptr + C_INF)) & (hnorm > tl.load(c_ptr + C_ARR))
        tl.store(arro_ptr + cb, tl.where(arrived, tl.load(tnew_ptr + b), arr), mask=m)
        pp = part_ptr + (b * tl.num_programs(0) + pid) * 2
        tl.store(pp, tl.sum(tl.where(m, hn * (spd * spd), 0.0), axis=0))
        tl.store(pp + 1, tl.sum(tl.where(m, hfin, 0.0), axis=0))


def _constants(F, dtype, device) -> torch.Tensor:
    """The kernels' constant table (C_* indices) in the state's dtype."""
    vals = [F.g, F.dx, F.theta, F.h_eps ** 4, F.h_wet, F.wb_ratio, 2.0 ** 0.5, WAVE_SPEED_MIN, F.h_eps,
            F.entrain_h_min, FR_DEP, 2.5 * MU_I_D, MU_I_I0, 1e-12, F.v_max_min_depth, F.arrival_threshold, math.inf,
            1.0 / F.dx, _normal(dtype)]
    return torch.tensor(vals, dtype=dtype, device=device)


def _normal(dtype) -> float:
    """The least denominator a guarded division takes (C_NORMAL): float32's smallest normal number on the
    fast paths, whose division and square root flush subnormal operands to zero; else 0 (every positive one)."""
    return torch.finfo(torch.float32).tiny if fp_fusion(dtype) else 0.0


def fp_fusion(dtype) -> bool:
    """Whether the kernels of ``dtype`` may fuse multiply-adds: float32 on the fast paths only (FAST_FLOAT32);
    never float64, whose every operation rounds as in the torch step."""
    return bool(FAST_FLOAT32 and dtype in (torch.float32, "fp32"))


def _launch(dtype) -> dict:
    """Launch options (fused multiply-add: fp_fusion)."""
    return {"BLOCK": _block(), "num_warps": NUM_WARPS, "enable_fp_fusion": fp_fusion(dtype)}


def _block() -> int:
    """Cells per program: BLOCK, or INTERPRETED_BLOCK under the interpreter."""
    return INTERPRETED_BLOCK if interpreted() else BLOCK


def _tile() -> tuple[int, int]:
    """Tile rows and columns of _tiled: TILE, or INTERPRETED_TILE under the interpreter."""
    return INTERPRETED_TILE if interpreted() else TILE


def _stride(t: torch.Tensor) -> int:
    """Member stride of a (1 or B, ...) field: 0 when one field serves every member."""
    return 0 if t.shape[0] == 1 else t[0].numel()


def _line_faces(h, hu, hv, zpx, zpy, zx, zy, cs, mus, inside, pm, c, s_geo, F) -> tuple[list, tuple]:
    """The faces of a stage on the line kernels (FACES = "lines": _velocities, _carried and one _faces per
    axis): ([(x faces, amax), (y faces, amax)], (u, v)) (u, v: the stored velocities, or h where recomputed)."""
    B, ny, nx = h.shape
    cells = (triton.cdiv(ny * nx, _block()), B)
    stored = VELOCITIES == "stored"
    u, v = (torch.empty_like(h), torch.empty_like(h)) if stored else (h, h)
    if stored:
        _velocities[(triton.cdiv(h.numel(), _block()),)](h, hu, hv, c, u, v, h.numel(), **_launch(h.dtype))
    cu, cv = (torch.empty_like(h), torch.empty_like(h)) if F.slope_correction else (h, h)
    if F.slope_correction:
        _carried[cells](h, hu, hv, zx, zy, c, cu, cv, ny, nx, s_geo, **_launch(h.dtype))
    sweeps = []
    for axis, (zp, nf) in enumerate(((zpx, (ny, nx + 1)), (zpy, (ny + 1, nx)))):
        out = [torch.empty((B, *nf), dtype=h.dtype, device=h.device) for _ in range(6)]
        grid = (triton.cdiv(nf[0] * nf[1], _block()), B)
        amax = torch.empty((B, grid[0]), dtype=h.dtype, device=h.device)
        _faces[grid](h, hu, hv, u, v, cu, cv, zp, zx, zy, cs, mus, inside, pm, c, *out, amax, ny, nx,
                     _stride(zp), s_geo, AXIS=axis, NO_CREEP=F.no_creep, WALLS=F.domain == "wall",
                     USE_MUS=F.use_mu_scale, USE_EP=F.use_ep, STORED=stored, SLOPE=F.slope_correction,
                     **_launch(h.dtype))
        sweeps.append((out, amax.amax(dim=1)))
    return sweeps, (u, v)


def triton_step(F):
    """``step(S, P) -> S`` for the settings ``F`` (StepFlags; supported(F, device) must be None):
    stepping.make_step's step on the Triton kernels (same inputs and outputs)."""
    moving = F.use_ent or F.use_dep
    tables: dict = {}

    def consts(dtype, device):
        key = (dtype, str(device))
        if key not in tables:
            tables[key] = _constants(F, dtype, device)
        return tables[key]

    def stage(h, hu, hv, z, erod, dep, dt, dt_cap, pm, c, P, geo):
        """stepping._stage on the kernels: the new (h, hu, hv, z, erod, dep), the outflow (B,) m^3, dt (B,)."""
        B, ny, nx = h.shape
        if geo is None:
            geo = static_geometry(z, F)
        zx, zy, cs, hess, (bx, by) = geo
        zx, zy, cs = (a.contiguous() for a in (zx, zy, cs))
        zxx, zxy, zyy = (a.contiguous() for a in hess) if hess is not None else (zx, zx, zx)
        zpx, zpy = bx[0].contiguous(), by[0].contiguous()
        s_geo = _stride(cs)
        mus = P["mu_scale"].contiguous() if F.use_mu_scale else cs
        inside = P["inside"].contiguous() if F.domain else cs
        cells = (triton.cdiv(ny * nx, _block()), B)
        if FACES == "tiled":
            u, v = torch.empty_like(h), torch.empty_like(h)
            ty, tx = _tile()
            grid = (triton.cdiv(nx + 1, tx - 3), triton.cdiv(ny + 1, ty - 3), B)
            faces = [[torch.empty((B, *nf), dtype=h.dtype, device=h.device) for _ in range(6)]
                     for nf in ((ny, nx + 1), (ny + 1, nx))]
            amax = torch.empty((2, B, grid[0] * grid[1]), dtype=h.dtype, device=h.device)
            _tiled[grid](h, hu, hv, zpx, zpy, zx, zy, cs, mus, inside, pm, c, u, v, *faces[0], amax[0], *faces[1],
                         amax[1], ny, nx, _stride(zpx), _stride(zpy), s_geo, NO_CREEP=F.no_creep,
                         WALLS=F.domain == "wall", USE_MUS=F.use_mu_scale, USE_EP=F.use_ep,
                         SLOPE=F.slope_correction, TY=ty, TX=tx, num_warps=TILE_WARPS,
                         enable_fp_fusion=fp_fusion(h.dtype))
            sweeps = [(faces[0], amax[0].amax(dim=1)), (faces[1], amax[1].amax(dim=1))]
            stored = True
        else:
            sweeps, (u, v) = _line_faces(h, hu, hv, zpx, zpy, zx, zy, cs, mus, inside, pm, c, s_geo, F)
            stored = VELOCITIES == "stored"
        (fx, ax), (fy, ay) = sweeps
        if dt is None:
            dt = torch.minimum(F.cfl * F.dx / (ax + ay), dt_cap)
            dt = torch.where(dt_cap > 0, dt, torch.zeros_like(dt))
        dt = dt.contiguous()
        fac = torch.empty_like(h)
        _drain[cells](h, fx[0], fy[0], dt, c, fac, ny, nx, **_launch(h.dtype))
        h_o, hu_o, hv_o = torch.empty_like(h), torch.empty_like(h), torch.empty_like(h)
        z_o = torch.empty_like(h) if moving else z
        e_o = torch.empty_like(h) if F.use_ent else erod
        d_o = torch.empty_like(h) if F.use_dep else dep
        part = torch.empty((B, cells[0], 2), dtype=h.dtype, device=h.device)
        dummy = h
        _update[cells](h, hu, hv, u, v, z if moving else dummy, erod if F.use_ent else dummy, dep if F.use_dep else dummy,
                       fac, *fx, *fy, zpx, zpy, zx, zy, cs, zxx, zxy, zyy, mus, inside, pm, c, dt,
                       h_o, hu_o, hv_o, z_o if moving else dummy, e_o if F.use_ent else dummy,
                       d_o if F.use_dep else dummy, part, ny, nx, s_geo, _stride(zpx), _stride(zpy),
                       SLOPE=F.slope_correction, USE_CURV=F.use_curv, USE_MU_I=F.use_mu_i, USE_ENT=F.use_ent,
                       USE_DEP=F.use_dep, USE_MUS=F.use_mu_scale, GONE_OUT=F.domain == "outflow",
                       INFLOW=F.inflow, USE_EP=F.use_ep, STORED=stored, **_launch(h.dtype))
        sums = part.sum(dim=1)
        outflow = dt * F.dx * sums[:, 0] + sums[:, 1] * (F.dx * F.dx)
        return h_o, hu_o, hv_o, z_o, e_o, d_o, outflow, dt

    def step(S: dict, P: dict) -> dict:
        h, hu, hv, z, erod, dep = (S[k] if S[k] is None else S[k].contiguous()
                                   for k in ("h", "hu", "hv", "z", "erod", "dep"))
        B, ny, nx = h.shape
        c = consts(h.dtype, h.device)
        pm = torch.stack([P[k].reshape(-1).expand(B) for k in PM], dim=1).contiguous()
        active, t, t_next = S["active"], S["t"], S["t_next"]
        rem = t_next - t
        dt_cap = torch.where(active, torch.clamp(rem, max=F.dt_max), torch.zeros_like(rem))
        geo = None if moving else (P["geo"] if "geo" in P else static_geometry(z, F))
        h1, hu1, hv1, z1, e1, d1, o1, dt = stage(h, hu, hv, z, erod, dep, None, dt_cap, pm, c, P, geo)
        h2, hu2, hv2, z2, e2, d2, o2, _ = stage(h1, hu1, hv1, z1, e1, d1, dt, dt_cap, pm, c, P, geo)
        hit = active & (dt >= rem)
        t_new = torch.where(hit, t_next, t + dt)
        rzx, rzy, rcs = (a.contiguous() for a in P["rec"])
        new = [torch.empty_like(h) for _ in range(3)]
        z_o = torch.empty_like(h) if moving else z
        e_o = torch.empty_like(h) if F.use_ent else erod
        d_o = torch.empty_like(h) if F.use_dep else dep
        rec = [torch.empty_like(h) for _ in range(3)]
        cells = (triton.cdiv(ny * nx, _block()), B)
        part = torch.empty((B, cells[0], 2), dtype=h.dtype, device=h.device)
        some = lambda a: h if a is None else a
        _combine[cells](h, hu, hv, hu1, hv1, h2, hu2, hv2, some(z), some(z2), some(erod), some(e2), some(dep),
                        some(d2), rzx, rzy, rcs, S["h_max"].contiguous(), S["v_max"].contiguous(),
                        S["arrival"].contiguous(), t_new.contiguous(), c, *new, some(z_o) if moving else h,
                        some(e_o) if F.use_ent else h, some(d_o) if F.use_dep else h, *rec, part, ny, nx,
                        MOVING=moving, USE_ENT=F.use_ent, USE_DEP=F.use_dep, **_launch(h.dtype))
        sums = part.sum(dim=1)
        cell_area = F.dx * F.dx
        ke = 0.5 * sums[:, 0] * cell_area
        mass = sums[:, 1] * cell_area
        out = dict(S)
        out.update(h=new[0], hu=new[1], hv=new[2], h_max=rec[0], v_max=rec[1], arrival=rec[2])
        if moving:
            out["z"] = z_o
        if F.use_ent:
            out["erod"] = e_o
        if F.use_dep:
            out["dep"] = d_o
        out["outflow"] = S["outflow"] + 0.5 * (o1 + o2)
        out["t"] = t_new
        out["dt"] = dt
        out["hit"] = hit
        out["steps"] = S["steps"] + active.to(S["steps"].dtype)
        return end_of_step(S, out, P, F, ke, mass)

    return step
