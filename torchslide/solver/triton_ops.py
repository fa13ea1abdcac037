"""The arithmetic of a cell and of a face on the Triton step: the device functions every kernel of
fused_triton's designs shares, each the element-wise twin of a torch function of the reference step
(stepping.py, scheme.py, friction.py), with the same operations in the same order.

Rounding. In float64 (the reference) every division and square root rounds exactly and the kernels launch
without fused multiply-add, so that a kernel's result equals the torch step's to the last bit. In float32
the kernels take the card's fast paths (FAST_FLOAT32): one MUFU instruction for a reciprocal, a square root
or a reciprocal square root (``rcp.approx.ftz``, ``sqrt.approx.ftz``, ``rsqrt``), a multiply for a division,
and fused multiply-add; they are judged by physics (docs/verification.md), not by bits. These
approximations flush subnormal operands to zero, so a guarded division takes no divisor below float32's
smallest normal number there (the constant C_NORMAL). ``TORCHSLIDE_EXACT_FLOAT32=1`` at import rounds
float32 exactly as torch does (bit-equality in float32 too); under Triton's interpreter
``TORCHSLIDE_FLUSH_SUBNORMALS=1`` flushes as the card does.

Constants travel in a table of the state's dtype (C_* index it; Triton takes a Python float as float32).
"""
from __future__ import annotations

import os

try:
    import triton
    import triton.language as tl
except ImportError:     # the Triton step is optional: without triton a GPU runs the torch step
    triton = None

FAST_FLOAT32 = os.environ.get("TORCHSLIDE_EXACT_FLOAT32", "0") != "1"
"""float32 on the fast paths (module docstring); False (environment TORCHSLIDE_EXACT_FLOAT32=1 at import):
exactly rounded division and square root and no fused multiply-add, as float64 always is."""

FLUSH_SUBNORMALS = os.environ.get("TORCHSLIDE_FLUSH_SUBNORMALS", "0") == "1"
"""Under Triton's interpreter: flush float32 subnormals in the fast division and square root to zero, as the
card's approximate instructions do, so that a guard that lets a subnormal divisor through shows up as a
non-finite state without a GPU (environment TORCHSLIDE_FLUSH_SUBNORMALS=1)."""

CONSTANTS = ("g", "dx", "theta", "h_eps4", "h_wet", "wb_ratio", "sqrt2", "wave_speed_min", "h_eps", "entrain_h_min",
             "fr_dep", "mu_i_scale", "mu_i_i0", "tiny", "v_max_min_depth", "arrival_threshold", "inf", "inv_dx",
             "normal", "cfl_dx", "dt_max", "stop_ke_fraction", "cell_area")
"""The entries of the kernels' constant table, in order (fused_triton.constants)."""


def interpreted() -> bool:
    """Whether Triton runs its interpreter (TRITON_INTERPRET=1: the kernels on the CPU, for the tests)."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


if triton is not None:
    C_G, C_DX, C_THETA, C_HEPS4, C_HWET, C_WB, C_SQRT2, C_WSMIN, C_HEPS, C_ENTMIN, C_FRDEP, C_MUI, C_I0, C_TINY, \
        C_VMIN, C_ARR, C_INF, C_INVDX, C_NORMAL, C_CFL_DX, C_DT_MAX, C_STOP_KE, C_AREA = \
        (tl.constexpr(k) for k in range(len(CONSTANTS)))

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

        @triton.jit
        def _over_sqrt(a, b):
            """a / sqrt(b) as the card's approximate reciprocal square root treats subnormals."""
            return _ftz(a / tl.sqrt(_ftz(b)))
    elif FAST_FLOAT32 and interpreted():
        @triton.jit
        def _div(a, b):
            """a / b (the interpreter: numpy's division)."""
            return a / b

        @triton.jit
        def _sqrt(x):
            """sqrt(x) (the interpreter: numpy's)."""
            return tl.sqrt(x)

        @triton.jit
        def _over_sqrt(a, b):
            """a / sqrt(b) (the interpreter: numpy's)."""
            return a / tl.sqrt(b)
    elif FAST_FLOAT32:
        @triton.jit
        def _div(a, b):
            """a / b: IEEE in float64; in float32 a times the card's approximate reciprocal (MUFU.RCP)."""
            if b.dtype == tl.float32:
                r = a * tl.inline_asm_elementwise("rcp.approx.ftz.f32 $0, $1;", "=r,r", [b], dtype=tl.float32,
                                                  is_pure=True, pack=1)
            else:
                r = a / b
            return r

        @triton.jit
        def _sqrt(x):
            """sqrt(x): IEEE in float64; in float32 the card's approximate square root (MUFU.SQRT)."""
            if x.dtype == tl.float32:
                r = tl.inline_asm_elementwise("sqrt.approx.ftz.f32 $0, $1;", "=r,r", [x], dtype=tl.float32,
                                              is_pure=True, pack=1)
            else:
                r = tl.sqrt(x)
            return r

        @triton.jit
        def _over_sqrt(a, b):
            """a / sqrt(b): IEEE in float64; in float32 a times the card's reciprocal square root (MUFU.RSQ)."""
            if b.dtype == tl.float32:
                r = a * tl.rsqrt(b)
            else:
                r = a / tl.sqrt(b)
            return r
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
        def _over_sqrt(a, b):
            """a / sqrt(b), both rounded as IEEE."""
            return _div(a, _sqrt(b))

    @triton.jit
    def _lane(q, index):
        """q at the lanes ``index`` of a strip (a shuffle within the warp: the marching kernels' neighbours along a
        row)."""
        return tl.gather(q, index, 0)

    @triton.jit
    def _wet(h_m, h, h_p, z_m, z, z_p, h_wet, wb):
        """scheme.sweep's wet/dry choice of a cell of clipped thickness h and bed z between its neighbours m and p
        along an axis: the surface w = h + z is reconstructed where the three are thicker than h_wet and the bed's
        curvature offset is small against h (wb: scheme's wb_ratio), else h itself."""
        return (_min(_min(h_m, h), h_p) > h_wet) & (tl.abs(z_p - 2.0 * z + z_m) * 0.25 <= wb * h)

    @triton.jit
    def _k_earth_pressure(div, pm_ptr, b):
        """stepping._earth_pressure's k of member b at cells whose velocity divergence (without 1 / dx) is div:
        (1 - s) k_ap + s k_SH, k_SH active where the flow spreads (div >= 0), passive where it converges (pm:
        fused_triton.PM's table, s its earth_pressure switch)."""
        s = tl.load(pm_ptr + b * 11 + 4)
        ksh = tl.where(div >= 0, tl.load(pm_ptr + b * 11 + 5), tl.load(pm_ptr + b * 11 + 6))
        return (1.0 - s) * tl.load(pm_ptr + b * 11 + 3) + s * ksh

    @triton.jit
    def _dfac(h, sqrt2, heps4):
        """friction.desingularised_factor: r(h) = sqrt(2) h / sqrt(h^4 + max(h^4, h_eps^4)), u = r q."""
        h2 = h * h
        h4 = h2 * h2
        return _over_sqrt(sqrt2 * h, h4 + _max(h4, heps4))

    @triton.jit
    def _motion(u, v, zx, zy, tiny):
        """stepping.motion_stretch: (sigma, c, moving) of the horizontal velocity (u, v)."""
        n2 = u * u + v * v
        w = zx * u + zy * v
        moving = n2 > tiny
        c = tl.where(moving, _div(w, n2), 0.0)
        return _sqrt(1.0 + w * c), c, moving

    @triton.jit
    def _momentum_change(px, py, u, v, sg, c, moving, zx, zy, tiny):
        """stepping.surface_momentum_change: the change of the surface momentum that the force p (its
        horizontal projection along the surface) makes on a flow of horizontal velocity (u, v) (sigma, c,
        moving: _motion's)."""
        zp = zx * px + zy * py
        k = _div(c * (zp - c * (u * px + v * py)), sg)
        sp, _c, _m = _motion(px, py, zx, zy, tiny)
        return tl.where(moving, sg * px + u * k, sp * px), tl.where(moving, sg * py + v * k, sp * py)

    @triton.jit
    def _minmod3(a, b, c):
        """scheme.minmod3."""
        return _max(_min(_min(a, b), c), 0.0) + _min(_max(_max(a, b), c), 0.0)

    @triton.jit
    def _slope(dm, dp, theta):
        """The limited slope of a cell from its differences to the west dm and to the east dp
        (scheme.reconstruct): minmod(theta dm, dm / 2 + dp / 2, theta dp)."""
        return _minmod3(theta * dm, 0.5 * dm + 0.5 * dp, theta * dp)

    @triton.jit
    def _central_upwind(hl, hr, ul, ur, cnl, cnr, tlf, trf, kgl, kgr, wsmin):
        """scheme.central_upwind at a face: (Fh, Fqn, Fqt, phi, max(a+, -a-)) from the left and right
        thickness, normal velocity, carried normal and tangential velocity and pressure coefficient."""
        cl = _sqrt(kgl * hl)
        cr = _sqrt(kgr * hr)
        ap = _max(_max(ur + cr, ul + cl), 0.0)
        am = _min(_min(ur - cr, ul - cl), 0.0)
        den = ap - am
        inv = tl.where(den > wsmin, _div(1.0, den), 0.0)
        al = hl * (ap * inv)
        ar = hr * (am * inv)
        left = al * (ul - am)
        right = ar * (ap - ur)
        return left + right, left * cnl + right * cnr, left * tlf + right * trf, 0.5 * (al * hl - ar * hr), \
            _max(ap, -am)

    @triton.jit
    def _frozen(h1, h2, kgl, kgr, hold, rest, mu, tau, invdx, USE_TAU: tl.constexpr):
        """scheme.frozen_faces at faces between cells a (left) and c (right): both at rest (``rest``) and friction
        holds the face's drive. h1, h2: the clipped padded thickness of a and c; hold: the pointer to the face's
        coefficients (scheme.hold_coefficients: alpha, beta, gamma, m0, gdz, secf, in eights); mu, tau: the
        member's friction and yield stress (USE_TAU)."""
        hf = 0.5 * (h1 + h2)
        a = -(0.5 * (kgl + kgr) * (h2 - h1) * invdx + tl.load(hold + 4))
        drive2 = (hf * hf) * ((tl.load(hold) * a + tl.load(hold + 1)) * a + tl.load(hold + 2))
        if USE_TAU:
            lim = hf * (mu * tl.load(hold + 3)) + tau * tl.load(hold + 5)
        else:
            lim = hf * (mu * tl.load(hold + 3))
        return rest & (drive2 <= lim * lim)

    @triton.jit
    def _hform(zxx, zxy, zyy, u, v):
        """stepping._hessian_form: u^T H u."""
        return zxx * u * u + 2.0 * zxy * u * v + zyy * v * v
