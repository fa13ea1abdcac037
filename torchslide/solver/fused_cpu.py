"""The solver step as one compiled loop nest on the CPU (numba, cached on disk).

``fused_step(F)`` returns a drop-in for ``stepping.make_step(F)``: the same SSP-RK2 step, the same
arithmetic in the same order cell by cell (stepping._stage, scheme.sweep, scheme.frozen_faces,
scheme.draining_factors, friction.apply_friction), so it equals the torch step to round-off (the
sums over the grid, mass, kinetic energy and outflow, add in another order). One pass per stage over
each member's rows and columns replaces the hundreds of whole-array torch operations of a stage:
the torch step's cost on small grids is per operation, not per cell. A stage computes only near each
member's live cells (_live_spans): faces between two dry cells carry exactly nothing, so the result
is the whole grid's to the last bit.

Every term and setting of the torch step is covered: Voellmy with the slope metric (or without), the
no-creep rule, the yield stress, earth pressure, curvature, mu(I), a friction map (mu_scale), a moving
bed (entrainment, deposition: the geometry recomputed per stage), outflow and open boundaries, cells
outside the DEM's domain (outflow or wall). Members run in parallel
(numba prange) on the process's threads (``threads``: OMP_NUM_THREADS, at most NUMBA_NUM_THREADS). The first call compiles (seconds)
and caches the machine code next to this file; later processes load it.
"""
from __future__ import annotations

import math
import os

import numpy as np
import torch

from ..physics import FR_DEP, MU_I_D, MU_I_I0
from .scheme import WAVE_SPEED_MIN

try:
    import numba
    from numba import njit, prange
except ImportError:     # the fused kernel is optional: "eager" needs nothing but torch
    numba = None

SQRT2 = 2.0 ** 0.5
PM = ("mu", "xi", "tau_y", "k_ap", "earth_pressure", "k_act", "k_pass", "curvature", "mu_i", "kappa", "deposition")
"""The per-member parameters the fused stage reads, in its order."""


def available() -> bool:
    return numba is not None


def supported(F, device) -> str | None:
    """None when the fused CPU step covers the call's settings ``F`` (StepFlags) on ``device``, else why not."""
    if numba is None:
        return "numba is not installed (pip install numba)"
    if torch.device(device).type != "cpu":
        return "the fused CPU step runs on the CPU"
    return None


if numba is not None:
    @njit(cache=True, error_model="numpy", inline="always")
    def _dfac(h, h_eps4):
        """friction.desingularised_factor: u = r q."""
        h2 = h * h
        h4 = h2 * h2
        return SQRT2 * h / math.sqrt(h4 + max(h4, h_eps4))

    @njit(cache=True, error_model="numpy", inline="always")
    def _motion(u, v, zx, zy):
        """stepping.motion_stretch: (sigma, c, moving)."""
        n2 = u * u + v * v
        w = zx * u + zy * v
        moving = n2 > 0
        c = w / n2 if moving else 0.0
        return math.sqrt(1.0 + w * c), c, moving

    @njit(cache=True, error_model="numpy", inline="always")
    def _minmod3(a, b, c):
        """scheme.minmod3."""
        return max(min(min(a, b), c), 0.0) + min(max(max(a, b), c), 0.0)

    @njit(cache=True, error_model="numpy")
    def _live_spans(h, hu, hv, rows, cols):
        """The live cells (h, hu or hv not 0; NaN counts as live) of each row and column: rows (2, ny), cols
        (2, nx) their first and last index (first > last: none). A face between two cells that are not
        live carries nothing and a cell whose four neighbours are not live keeps its state, so a stage
        computes only near the live cells (the argument of crop.py's box, cell by cell)."""
        ny, nx = h.shape
        rows[0, :] = nx
        rows[1, :] = -1
        cols[0, :] = ny
        cols[1, :] = -1
        for i in range(ny):
            for j in range(nx):
                if not (h[i, j] == 0 and hu[i, j] == 0 and hv[i, j] == 0):
                    rows[0, i] = min(rows[0, i], j)
                    rows[1, i] = max(rows[1, i], j)
                    cols[0, j] = min(cols[0, j], i)
                    cols[1, j] = max(cols[1, j], i)

    @njit(cache=True, error_model="numpy")
    def _near(rows, k, m, nx, out):
        """out (2, ny): per row the cells within ``k`` rows and ``m`` columns of a live cell (rows:
        _live_spans'), clipped to the grid (first > last: none)."""
        ny = rows.shape[1]
        for i in range(ny):
            lo, hi = nx, -1
            for r in range(max(i - k, 0), min(i + k, ny - 1) + 1):
                if rows[0, r] <= rows[1, r]:
                    lo = min(lo, rows[0, r] - m)
                    hi = max(hi, rows[1, r] + m)
            out[0, i] = max(lo, 0)
            out[1, i] = min(hi, nx - 1)

    @njit(cache=True, error_model="numpy")
    def _pad(q, out, linear, clamp0):
        """Two ghost cells per side: linear extrapolation (pad_linear) or the edge value (pad_replicate)."""
        n = q.shape[0]
        for i in range(n):
            out[i + 2] = q[i]
        if linear:
            out[1] = 2 * q[0] - q[1]
            out[0] = 2 * out[1] - q[0]
            out[n + 2] = 2 * q[n - 1] - q[n - 2]
            out[n + 3] = 2 * out[n + 2] - q[n - 1]
        else:
            out[0] = q[0]
            out[1] = q[0]
            out[n + 2] = q[n - 1]
            out[n + 3] = q[n - 1]
        if clamp0:
            for i in range(n + 4):
                if out[i] < 0.0:
                    out[i] = 0.0

    @njit(cache=True, error_model="numpy")
    def _recon(qp, n, theta, L, R, f0, f1):
        """scheme.reconstruct: L, R face states of faces f0 ... f1 (of the line's n + 1) from a 2-ghost
        padded line."""
        for c in range(f0, f1 + 2):
            qm, qc, qq = qp[c], qp[c + 1], qp[c + 2]
            dm, dp = qc - qm, qq - qc
            s = _minmod3(theta * dm, 0.5 * dm + 0.5 * dp, theta * dp)
            if c <= n:
                L[c] = qc + 0.5 * s
            if c >= 1:
                R[c - 1] = qc - 0.5 * s

    @njit(cache=True, error_model="numpy")
    def _bed_line(z, zp, zL, zR, Bf, bias):
        """scheme.bed_terms along one line."""
        n = z.shape[0]
        _pad(z, zp, True, False)
        for f in range(n + 1):
            zL[f] = zp[f + 1]
            zR[f] = zp[f + 2]
            Bf[f] = 0.5 * (zL[f] + zR[f])
        for c in range(n + 2):
            bias[c] = abs(zp[c + 2] - 2.0 * zp[c + 1] + zp[c]) * 0.25

    @njit(cache=True, error_model="numpy")
    def _geometry(z, dx, slope, hessian, zx, zy, cs, zxx, zxy, zyy, bx, by):
        """stepping.surface_geometry and the bed terms of both sweeps of one member's bed z (ny, nx)."""
        ny, nx = z.shape
        zpx = np.empty((ny, nx + 4))
        for i in range(ny):
            _pad(z[i], zpx[i], True, False)
        zpy = np.empty((ny + 4, nx))
        for j in range(nx):
            _pad(z[:, j], zpy[:, j], True, False)
        dx2 = dx ** 2
        for i in range(ny):
            for j in range(nx):
                gx = (zpx[i, j + 3] - zpx[i, j + 1]) * (1.0 / (2 * dx))
                gy = (zpy[i + 3, j] - zpy[i + 1, j]) * (1.0 / (2 * dx))
                if slope:
                    zx[i, j] = gx
                    zy[i, j] = gy
                    cs[i, j] = 1.0 / math.sqrt(1.0 + gx * gx + gy * gy)
                else:
                    zx[i, j] = 0.0
                    zy[i, j] = 0.0
                    cs[i, j] = 1.0
        if hessian:
            zp2 = np.empty((ny + 4, nx + 4))
            for c in range(nx + 4):
                _pad(zpx[:, c], zp2[:, c], True, False)
            for i in range(ny):
                for j in range(nx):
                    zxx[i, j] = (zpx[i, j + 3] - 2 * z[i, j] + zpx[i, j + 1]) * (1.0 / dx2)
                    zyy[i, j] = (zpy[i + 3, j] - 2 * z[i, j] + zpy[i + 1, j]) * (1.0 / dx2)
                    zxy[i, j] = (zp2[i + 3, j + 3] - zp2[i + 3, j + 1] - zp2[i + 1, j + 3] + zp2[i + 1, j + 1]) * (1.0 / (4 * dx2))
        else:
            zxx[:, :] = 0.0
            zxy[:, :] = 0.0
            zyy[:, :] = 0.0
        for i in range(ny):
            _bed_line(z[i], bx[0][i], bx[1][i], bx[2][i], bx[3][i], bx[4][i])
        for j in range(nx):
            _bed_line(z[:, j], by[0][:, j], by[1][:, j], by[2][:, j], by[3][:, j], by[4][:, j])

    @njit(cache=True, error_model="numpy")
    def _sweep_line(h, un, cn, ct, kg, frozen, has_frozen, zp, zL, zR, Bf, bias, theta, h_wet, wb, g,
                    Fh, Fqn, Fqt, phi, hbar, dB, w, c0, c1):
        """scheme.sweep along one line of n cells, transported by un, carrying (cn, ct) (normal,
        tangential), on its faces c0 ... c1 + 1 (those of its live cells c0 ... c1, _live_spans: every
        other face joins two dry cells, whose fluxes, pressure and hbar are 0, left as the caller's zeros);
        returns the line's largest one-sided speed. ``w``: (17, n + 4) scratch."""
        n = h.shape[0]
        hp, wp, up, tp, kgp = w[0], w[1], w[2], w[3], w[4]
        wL, wR, hLh, hRh, uL, uR, tL, tR = w[5], w[6], w[7], w[8], w[9], w[10], w[11], w[12]
        hLR, cp, UL, UR = w[13], w[14], w[15], w[16]
        _pad(h, hp, True, True)
        for i in range(n + 4):
            wp[i] = hp[i] + zp[i]
        f0, f1 = c0, c1 + 1
        _recon(wp, n, theta, wL, wR, f0, f1)
        _recon(hp, n, theta, hLh, hRh, f0, f1)
        _pad(un, up, False, False)
        _pad(cn, cp, False, False)
        _pad(ct, tp, False, False)
        _pad(kg, kgp, False, False)
        _recon(up, n, theta, uL, uR, f0, f1)
        _recon(cp, n, theta, UL, UR, f0, f1)
        _recon(tp, n, theta, tL, tR, f0, f1)
        amax = 0.0
        for f in range(f0, f1 + 1):
            # wet: the cell left (padded index f) and right (f + 1) of the face, each with both neighbours
            cl = f
            wetL = (min(min(hp[cl], hp[cl + 1]), hp[cl + 2]) > h_wet) and (bias[cl] <= wb * hp[cl + 1])
            cr = f + 1
            wetR = (min(min(hp[cr], hp[cr + 1]), hp[cr + 2]) > h_wet) and (bias[cr] <= wb * hp[cr + 1])
            hL = max(wL[f] - Bf[f], 0.0) if wetL else hLh[f]
            hR = max(wR[f] - Bf[f], 0.0) if wetR else hRh[f]
            kgL, kgR = kgp[f + 1], kgp[f + 2]
            cL = math.sqrt(kgL * hL)
            cR = math.sqrt(kgR * hR)
            ap = max(max(uR[f] + cR, uL[f] + cL), 0.0)
            am = min(min(uR[f] - cR, uL[f] - cL), 0.0)
            den = ap - am
            inv = 1.0 / den if den > WAVE_SPEED_MIN else 0.0
            aL = hL * (ap * inv)
            aR = hR * (am * inv)
            phi[f] = 0.5 * (aL * hL - aR * hR)
            if has_frozen and frozen[f]:
                Fh[f] = 0.0
                Fqn[f] = 0.0
                Fqt[f] = 0.0
            else:
                left = aL * (uL[f] - am)
                right = aR * (ap - uR[f])
                Fh[f] = left + right
                Fqn[f] = left * UL[f] + right * UR[f]
                Fqt[f] = left * tL[f] + right * tR[f]
            hLR[f] = hL
            wp[f] = hR          # (wp no longer needed) the right state of face f
            a = max(ap, -am)
            if a > amax or a != a:
                amax = a
        for c in range(c0, c1 + 1):
            hbar[c] = 0.5 * (wp[c] + hLR[c + 1])
        for c in range(n):
            dB[c] = Bf[c + 1] - Bf[c]
        return amax

    @njit(cache=True, error_model="numpy")
    def _frozen_line(h, kg, rest, zx, zy, cs, mcs, sec, mu, tau, zL, zR, g, dx, along_x, out, w, f0, f1):
        """scheme.frozen_faces along one line on its faces f0 ... f1 (along_x: the faces are x faces), with
        scheme.hold_coefficients computed face by face."""
        n = h.shape[0]
        hp, kgp = w[0], w[1]
        _pad(h, hp, True, True)
        _pad(kg, kgp, False, False)
        for f in range(f0, f1 + 1):
            a, b = max(f - 1, 0), min(f, n - 1)
            hcL, hcR = hp[f + 1], hp[f + 2]
            zxf = 0.5 * (zx[a] + zx[b])
            zyf = 0.5 * (zy[a] + zy[b])
            csf = 0.5 * (cs[a] + cs[b])
            mcf = 0.5 * (mcs[a] + mcs[b])
            secf = 0.5 * (sec[a] + sec[b])
            zn, zt = (zxf, zyf) if along_x else (zyf, zxf)
            T = -g * zt
            c2 = csf * csf
            alpha = 1.0 - c2 * (zn * zn)
            beta = -2.0 * c2 * zn * zt * T
            gamma = T * T * (1.0 - c2 * (zt * zt))
            gdz = g * (zR[f] - zL[f]) * (1.0 / dx)
            hf = 0.5 * (hcL + hcR)
            A = -(0.5 * (kgp[f + 1] + kgp[f + 2]) * (hcR - hcL) * (1.0 / dx) + gdz)
            drive2 = (hf * hf) * ((alpha * A + beta) * A + gamma)
            lim = hf * (mu * (g * mcf)) + tau * secf
            out[f] = rest[a] and rest[b] and (drive2 <= lim * lim)

    @njit(cache=True, error_model="numpy")
    def _stage(h, hu, hv, z, erod, dep, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, inside, pm, dt_in, dt_cap, first,
               c, fl, out_h, out_hu, out_hv, out_z, out_erod, out_dep):
        """stepping._stage for one member: the new state into out_*; returns (dt, outflow). With a moving
        bed (use_ent or use_dep) the geometry (zx ... by) is computed here from z into the arrays given,
        else they hold the static geometry. mus: (ny, nx) mu_scale (ones without it); inside: (ny, nx)
        cells of the DEM's domain; pm: the member's parameters (PM); c, fl: the constants and flags of
        fused_step."""
        g, dx, cfl, theta, h_eps, h_wet, wb = c[0], c[1], c[2], c[3], c[4], c[5], c[6]
        ent_hmin = c[11]
        no_creep, slope, use_ep, use_curv, use_mu_i, inflow = fl[0], fl[1], fl[2], fl[3], fl[4], fl[5]
        use_ent, use_dep, walls, gone_out = fl[6], fl[7], fl[8], fl[9]
        mu0, xi, tau, k_ap, s_ep, k_act, k_pass, curv, mu_i = pm[0], pm[1], pm[2], pm[3], pm[4], pm[5], pm[6], pm[7], pm[8]
        kappa, dep_rate = pm[9], pm[10]
        moving = use_ent or use_dep
        if moving:
            _geometry(z, dx, slope, use_curv, zx, zy, cs, zxx, zxy, zyy, bx, by)
        ghost = 1.0 if inflow else 0.0
        ny, nx = h.shape
        h_eps4 = h_eps ** 4
        zpx, zLx, zRx, Bfx, biasx = bx
        zpy, zLy, zRy, Bfy, biasy = by
        rows = np.empty((2, ny), dtype=np.int64)
        cols = np.empty((2, nx), dtype=np.int64)
        _live_spans(h, hu, hv, rows, cols)
        near1 = np.empty((2, ny), dtype=np.int64)     # the cells a stage can change
        near2 = np.empty((2, ny), dtype=np.int64)     # and those whose fields their faces read
        _near(rows, 1, 1, nx, near1)
        _near(rows, 2, 2, nx, near2)
        u = np.zeros((ny, nx))
        v = np.zeros((ny, nx))
        kg = np.zeros((ny, nx))
        for i in range(ny):
            for j in range(near2[0, i], near2[1, i] + 1):
                r = _dfac(h[i, j], h_eps4)
                u[i, j] = r * hu[i, j]
                v[i, j] = r * hv[i, j]
        if slope:       # the carried surface velocity sigma u (stepping._stage)
            cm = np.zeros((ny, nx))
            mv = np.zeros((ny, nx), dtype=np.bool_)
            sg = np.zeros((ny, nx))
            cu = np.zeros((ny, nx))
            cv = np.zeros((ny, nx))
            for i in range(ny):
                for j in range(near2[0, i], near2[1, i] + 1):
                    sg[i, j], cm[i, j], mv[i, j] = _motion(u[i, j], v[i, j], zx[i, j], zy[i, j])
                    cu[i, j] = sg[i, j] * u[i, j]
                    cv[i, j] = sg[i, j] * v[i, j]
        else:
            cm, mv, sg, cu, cv = u, np.zeros((ny, nx), dtype=np.bool_), u, u, v
        for i in range(ny):
            for j in range(near2[0, i], near2[1, i] + 1):
                k = k_ap
                if use_ep:      # stepping._earth_pressure: active where the flow spreads, passive where it converges
                    div = (u[i, min(j + 1, nx - 1)] - u[i, max(j - 1, 0)]) + (v[min(i + 1, ny - 1), j] - v[max(i - 1, 0), j])
                    ksh = k_act if div >= 0 else k_pass
                    k = (1.0 - s_ep) * k_ap + s_ep * ksh
                kg[i, j] = k * ((g * cs[i, j]) * cs[i, j])
        Fhx, Fqnx, Fqtx, phix = (np.zeros((ny, nx + 1)), np.zeros((ny, nx + 1)), np.zeros((ny, nx + 1)),
                                 np.zeros((ny, nx + 1)))
        Fhy, Fqny, Fqty, phiy = (np.zeros((ny + 1, nx)), np.zeros((ny + 1, nx)), np.zeros((ny + 1, nx)),
                                 np.zeros((ny + 1, nx)))
        hbarx, dBx, hbary, dBy = np.zeros((ny, nx)), np.zeros((ny, nx)), np.zeros((ny, nx)), np.zeros((ny, nx))
        fzx = np.zeros((ny, nx + 1), dtype=np.bool_)
        fzy = np.zeros((ny + 1, nx), dtype=np.bool_)
        m = max(nx, ny) + 4
        wk = np.empty((17, m))
        if no_creep:
            rest = np.empty((ny, nx), dtype=np.bool_)
            mcs = np.empty((ny, nx))
            sec = np.empty((ny, nx))
            for i in range(ny):
                for j in range(near2[0, i], near2[1, i] + 1):
                    rest[i, j] = (hu[i, j] == 0) and (hv[i, j] == 0)
                    mcs[i, j] = mus[i, j] * cs[i, j]     # (mus is 1 without a friction map)
                    sec[i, j] = 1.0 / cs[i, j]
            for i in range(ny):
                if rows[0, i] <= rows[1, i]:
                    _frozen_line(h[i], kg[i], rest[i], zx[i], zy[i], cs[i], mcs[i], sec[i], mu0, tau, zLx[i], zRx[i],
                                 g, dx, True, fzx[i], wk, rows[0, i], rows[1, i] + 1)
            for j in range(nx):
                if cols[0, j] <= cols[1, j]:
                    _frozen_line(h[:, j], kg[:, j], rest[:, j], zx[:, j], zy[:, j], cs[:, j], mcs[:, j], sec[:, j],
                                 mu0, tau, zLy[:, j], zRy[:, j], g, dx, False, fzy[:, j], wk, cols[0, j], cols[1, j] + 1)
        if walls:       # stepping._domain_walls: faces between a cell of the domain and one outside it
            for i in range(ny):
                for f in range(nx + 1):
                    if inside[i, max(f - 1, 0)] != inside[i, min(f, nx - 1)]:
                        fzx[i, f] = True
            for f in range(ny + 1):
                for j in range(nx):
                    if inside[max(f - 1, 0), j] != inside[min(f, ny - 1), j]:
                        fzy[f, j] = True
        has_frozen = no_creep or walls
        ax = 0.0
        for i in range(ny):
            if rows[0, i] > rows[1, i]:
                continue
            a = _sweep_line(h[i], u[i], cu[i], cv[i], kg[i], fzx[i], has_frozen, zpx[i], zLx[i], zRx[i], Bfx[i], biasx[i],
                            theta, h_wet, wb, g, Fhx[i], Fqnx[i], Fqtx[i], phix[i], hbarx[i], dBx[i], wk,
                            rows[0, i], rows[1, i])
            if a > ax or a != a:
                ax = a
        ay = 0.0
        for j in range(nx):
            if cols[0, j] > cols[1, j]:
                continue
            a = _sweep_line(h[:, j], v[:, j], cv[:, j], cu[:, j], kg[:, j], fzy[:, j], has_frozen, zpy[:, j], zLy[:, j],
                            zRy[:, j], Bfy[:, j], biasy[:, j], theta, h_wet, wb, g, Fhy[:, j], Fqny[:, j],
                            Fqty[:, j], phiy[:, j], hbary[:, j], dBy[:, j], wk, cols[0, j], cols[1, j])
            if a > ay or a != a:
                ay = a
        if first:
            dt = min(cfl * dx / (ax + ay), dt_cap)
            if not dt_cap > 0:
                dt = 0.0
        else:
            dt = dt_in
        # draining factors (ghost 0: outflow boundaries)
        fac = np.ones((ny, nx))
        for i in range(ny):
            for j in range(near1[0, i], near1[1, i] + 1):
                o = (max(Fhx[i, j + 1], 0.0) + max(-Fhx[i, j], 0.0)) + (max(Fhy[i + 1, j], 0.0) + max(-Fhy[i, j], 0.0))
                o = o * (dt * (1.0 / dx))
                fac[i, j] = h[i, j] / o if o > h[i, j] else 1.0
        for i in range(ny):
            for f in range(rows[0, i], rows[1, i] + 2):
                F = Fhx[i, f]
                c = (fac[i, f - 1] if f >= 1 else ghost) if F > 0 else (fac[i, f] if f < nx else ghost)
                Fhx[i, f] = F * c
                Fqnx[i, f] = Fqnx[i, f] * c
                Fqtx[i, f] = Fqtx[i, f] * c
        for j in range(nx):
            for f in range(cols[0, j], cols[1, j] + 2):
                F = Fhy[f, j]
                c = (fac[f - 1, j] if f >= 1 else ghost) if F > 0 else (fac[f, j] if f < ny else ghost)
                Fhy[f, j] = F * c
                Fqny[f, j] = Fqny[f, j] * c
                Fqty[f, j] = Fqty[f, j] * c
        lam = dt * (1.0 / dx)
        kturb = (4.0 * g) * dt * (1.0 / xi)     # friction.turbulent_coefficient without the 1 / cos
        bnd_x = 0.0
        bnd_y = 0.0
        for i in range(ny):
            bnd_x += Fhx[i, nx]
        s0 = 0.0
        for i in range(ny):
            s0 += Fhx[i, 0]
        for j in range(nx):
            bnd_y += Fhy[ny, j]
        s1 = 0.0
        for j in range(nx):
            s1 += Fhy[0, j]
        outflow = dt * dx * ((bnd_x - s0) + (bnd_y - s1))
        lost = 0.0
        for i in range(ny):
            for j in range(nx):
                if j < near1[0, i] or j > near1[1, i]:  # no live neighbour: the state stays
                    out_h[i, j] = h[i, j]
                    out_hu[i, j] = hu[i, j]
                    out_hv[i, j] = hv[i, j]
                    if moving:
                        out_z[i, j] = z[i, j]
                    if use_ent or use_dep:
                        out_erod[i, j] = erod[i, j]
                        out_dep[i, j] = dep[i, j]
                    continue
                hn = h[i, j] - lam * ((Fhx[i, j + 1] - Fhx[i, j]) + (Fhy[i + 1, j] - Fhy[i, j]))
                gn = g * cs[i, j]
                px = kg[i, j] * (phix[i, j + 1] - phix[i, j]) + g * hbarx[i, j] * dBx[i, j]
                py = kg[i, j] * (phiy[i + 1, j] - phiy[i, j]) + g * hbary[i, j] * dBy[i, j]
                if slope:   # the surface momentum Q = sigma q, updated and turned back (stepping._stage)
                    a2 = cs[i, j] * cs[i, j] * (zx[i, j] * px + zy[i, j] * py)
                    px = px - zx[i, j] * a2
                    py = py - zy[i, j] * a2
                    sf = sg[i, j]
                    if mv[i, j]:    # stepping.surface_momentum_change
                        cc, uu, vv = cm[i, j], u[i, j], v[i, j]
                        zp = zx[i, j] * px + zy[i, j] * py
                        k = cc * (zp - cc * (uu * px + vv * py)) / sf
                        px, py = sf * px + uu * k, sf * py + vv * k
                    else:           # a flow at rest starts along the force
                        sp = _motion(px, py, zx[i, j], zy[i, j])[0]
                        px, py = sp * px, sp * py
                    qx = sf * hu[i, j] - lam * (((Fqnx[i, j + 1] - Fqnx[i, j]) + (Fqty[i + 1, j] - Fqty[i, j])) + px)
                    qy = sf * hv[i, j] - lam * (((Fqtx[i, j + 1] - Fqtx[i, j]) + (Fqny[i + 1, j] - Fqny[i, j])) + py)
                    n2 = qx * qx + qy * qy       # stepping.horizontal_momentum
                    wq = zx[i, j] * qx + zy[i, j] * qy
                    tq = n2 + wq * wq
                    fq = math.sqrt(n2 / tq) if tq > 0 else 1.0
                    qx = qx * fq
                    qy = qy * fq
                    qn = math.sqrt(n2)
                else:
                    qx = hu[i, j] - lam * (((Fqnx[i, j + 1] - Fqnx[i, j]) + (Fqty[i + 1, j] - Fqty[i, j])) + px)
                    qy = hv[i, j] - lam * (((Fqtx[i, j + 1] - Fqtx[i, j]) + (Fqny[i + 1, j] - Fqny[i, j])) + py)
                    qn = math.sqrt(qx * qx + qy * qy)
                if gone_out and not inside[i, j]:   # what entered a cell outside the domain has left it
                    lost += hn
                    hn, qx, qy, qn = 0.0, 0.0, 0.0, 0.0
                zn = z[i, j]
                if use_ent or use_dep:
                    out_erod[i, j] = erod[i, j]
                    out_dep[i, j] = dep[i, j]
                sc = 1.0 / cs[i, j]
                if moving:      # mass sources, explicit in the stage-start state (stepping._stage)
                    uu, vv = u[i, j], v[i, j]
                    w0 = zx[i, j] * uu + zy[i, j] * vv
                    speed0 = math.sqrt(uu * uu + vv * vv + w0 * w0)
                    if use_ent:
                        rate = kappa * speed0 * sc * (1.0 if cs[i, j] * h[i, j] > ent_hmin else 0.0)
                        de = min(dt * rate, erod[i, j])
                        hn = hn + de
                        out_erod[i, j] = erod[i, j] - de
                        zn = zn - de
                    if use_dep:
                        hsd = max(cs[i, j] * h[i, j], h_eps)
                        froude = speed0 / math.sqrt(max(gn, 1e-12) * hsd)
                        rate = dep_rate * h[i, j] * max(1.0 - froude / FR_DEP, 0.0)
                        hpos = max(hn, 0.0)
                        dd = min(dt * rate, hpos)
                        ratio = (hpos - dd) / hpos if hpos > 0 else 0.0
                        qx = qx * ratio
                        qy = qy * ratio
                        qn = qn * ratio
                        hn = hn - dd
                        out_dep[i, j] = dep[i, j] + dd
                        zn = zn + dd
                    out_z[i, j] = zn
                # friction on the momentum along the surface (friction.apply_friction, with curvature_gn and
                # mu_effective at the stage's new state)
                hnp = max(hn, 0.0)
                mue = mu0 * mus[i, j]
                gne = gn
                if use_curv or use_mu_i:
                    rn = _dfac(hn, h_eps4)
                    un = rn * qx
                    vn = rn * qy
                    if use_curv:
                        gne = max(gn + curv * (cs[i, j] * (zxx[i, j] * un * un + 2.0 * zxy[i, j] * un * vn
                                                           + zyy[i, j] * vn * vn)), 0.0)
                    if use_mu_i:
                        wn = zx[i, j] * un + zy[i, j] * vn
                        spd = math.sqrt(un * un + vn * vn + wn * wn)
                        hs_ = max(cs[i, j] * hnp, h_eps)
                        inertial = 2.5 * MU_I_D * spd / (hs_ * math.sqrt(max(gne, 1e-12) * hs_))
                        mue = mue + mu_i * inertial / (MU_I_I0 + inertial)
                coul = mue * gne * hnp + tau * sc
                if qn > 0:
                    keep = max(1.0 - dt * coul / qn, 0.0)
                else:
                    keep = 0.0
                hs = max(hn, h_eps)
                a4 = (kturb * sc) / (hs * hs)
                factor = keep * 2.0 / (1.0 + math.sqrt(1.0 + a4 * (keep * qn)))
                if hn < h_eps:  # a layer thinner than h_eps keeps its desingularised velocity's momentum
                    factor = factor * (hn * _dfac(hn, h_eps4))
                qx = qx * factor
                qy = qy * factor
                out_h[i, j] = max(hn, 0.0)
                out_hu[i, j] = qx
                out_hv[i, j] = qy
        if gone_out:
            outflow = outflow + lost * (dx * dx)
        return dt, outflow

    @njit(cache=True, error_model="numpy", parallel=True)
    def _step_all(h, hu, hv, z, erod, dep, g6, gx, gy, mus, inside, pm, active, t, t_next, t_end, rzx, rzy, rcs,
                  h_max, v_max, arrival, ke_peak, outflow, steps, failed, stopped, c, fl,
                  h_o, hu_o, hv_o, z_o, erod_o, dep_o, dt_o, scal_o, flags_o):
        """stepping.make_step's step for every member (members in parallel over numba's threads). g6: (6, ny,
        nx) the static zx, zy, cs, zxx, zxy, zyy; gx, gy: the static bed terms of the x and y sweeps packed
        (_unpack_views) (all ignored with a moving bed); c: g, dx, cfl, theta, h_eps, h_wet, wb, dt_max,
        v_max_min_depth, arrival_threshold, stop_ke_fraction, entrain_h_min; scal_o: (B, 5) t, outflow,
        ke, mass, ke_peak; flags_o: (B, 5) hit, active, failed, stopped, steps + active."""
        for b in prange(h.shape[0]):
            _member(b, h, hu, hv, z, erod, dep, g6, gx, gy, mus, inside, pm, active, t, t_next, t_end, rzx, rzy,
                    rcs, h_max, v_max, arrival, ke_peak, outflow, steps, failed, stopped, c, fl,
                    h_o, hu_o, hv_o, z_o, erod_o, dep_o, dt_o, scal_o, flags_o)

    @njit(cache=True, error_model="numpy")
    def _unpack_views(p, n_along, axis):
        """The five bed-term arrays (zp, zL, zR, Bf, bias) of a sweep as views of their packed (5, ., .) form:
        along x (axis 1) they have n + 4, n + 1, n + 1, n + 1, n + 2 columns, along y (axis 0) as many rows."""
        lens = (n_along + 4, n_along + 1, n_along + 1, n_along + 1, n_along + 2)
        if axis == 1:
            return (p[0, :, :lens[0]], p[1, :, :lens[1]], p[2, :, :lens[2]], p[3, :, :lens[3]], p[4, :, :lens[4]])
        return (p[0, :lens[0], :], p[1, :lens[1], :], p[2, :lens[2], :], p[3, :lens[3], :], p[4, :lens[4], :])

    @njit(cache=True, error_model="numpy")
    def _member(b, h, hu, hv, z, erod, dep, g6, gx, gy, mus, inside, pm, active, t, t_next, t_end, rzx, rzy, rcs,
                h_max, v_max, arrival, ke_peak, outflow, steps, failed, stopped, c, fl,
                h_o, hu_o, hv_o, z_o, erod_o, dep_o, dt_o, scal_o, flags_o):
        """Member b of _step_all."""
        dx, h_eps, dt_max, vmin, arr_th, stop_frac = c[1], c[4], c[7], c[8], c[9], c[10]
        use_ent, use_dep = fl[6], fl[7]
        moving = use_ent or use_dep
        h_eps4 = h_eps ** 4
        cell_area = dx * dx
        ny, nx = h.shape[1], h.shape[2]
        rem = t_next[b] - t[b]
        dt_cap = min(rem, dt_max) if active[b] else 0.0
        h1, hu1, hv1 = np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx))
        h2, hu2, hv2 = np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx))
        z1, e1, d1 = np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx))
        z2, e2, d2 = np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx))
        zb = z[b] if moving else z[0]
        eb = erod[b] if use_ent else e1
        db = dep[b] if use_dep else d1
        if moving:      # this member's geometry, computed per stage into these
            g6 = np.empty((6, ny, nx))
            gx = np.empty((5, ny, nx + 4))
            gy = np.empty((5, ny + 4, nx))
        bx = _unpack_views(gx, nx, 1)
        by = _unpack_views(gy, ny, 0)
        zx, zy, cs, zxx, zxy, zyy = g6[0], g6[1], g6[2], g6[3], g6[4], g6[5]
        dt, o1 = _stage(h[b], hu[b], hv[b], zb, eb, db, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, inside, pm[b],
                        0.0, dt_cap, True, c, fl, h1, hu1, hv1, z1, e1, d1)
        _, o2 = _stage(h1, hu1, hv1, z1 if moving else zb, e1, d1, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, inside,
                       pm[b], dt, dt_cap, False, c, fl, h2, hu2, hv2, z2, e2, d2)
        hit = active[b] and (dt >= rem)
        t_new = t_next[b] if hit else t[b] + dt
        rows, cols = np.empty((2, ny), dtype=np.int64), np.empty((2, nx), dtype=np.int64)
        _live_spans(h[b], hu[b], hv[b], rows, cols)
        near = np.empty((2, ny), dtype=np.int64)    # what the two stages can change (a 3 x 3 neighbourhood each)
        _near(rows, 2, 2, nx, near)
        ke_sum = 0.0
        mass_sum = 0.0
        for i in range(ny):
            for j in range(nx):
                if j < near[0, i] or j > near[1, i]:    # dry and at rest before and after: it adds its deposit
                    h_o[b, i, j] = h2[i, j]
                    hu_o[b, i, j] = hu2[i, j]
                    hv_o[b, i, j] = hv2[i, j]
                    if moving:
                        z_o[b, i, j] = z2[i, j]
                    if use_ent:
                        erod_o[b, i, j] = e2[i, j]
                    if use_dep:
                        dep_o[b, i, j] = d2[i, j]
                        mass_sum += d2[i, j]
                    continue
                hN = 0.5 * (h[b, i, j] + h2[i, j])
                stop = hu1[i, j] == 0 and hv1[i, j] == 0 and hu2[i, j] == 0 and hv2[i, j] == 0
                qx = 0.0 if stop else 0.5 * (hu[b, i, j] + hu2[i, j])
                qy = 0.0 if stop else 0.5 * (hv[b, i, j] + hv2[i, j])
                h_o[b, i, j] = hN
                hu_o[b, i, j] = qx
                hv_o[b, i, j] = qy
                if moving:
                    z_o[b, i, j] = 0.5 * (zb[i, j] + z2[i, j])
                if use_ent:
                    erod_o[b, i, j] = 0.5 * (eb[i, j] + e2[i, j])
                hfin = hN
                if use_dep:
                    dN = 0.5 * (db[i, j] + d2[i, j])
                    dep_o[b, i, j] = dN
                    hfin = hN + dN
                w = rzx[i, j] * qx + rzy[i, j] * qy
                spd = _dfac(hN, h_eps4) * math.sqrt(qx * qx + qy * qy + w * w)
                hnorm = rcs[i, j] * hN
                h_max[b, i, j] = max(h_max[b, i, j], rcs[i, j] * hfin)
                v_max[b, i, j] = max(v_max[b, i, j], spd if hnorm >= vmin else 0.0)
                if math.isinf(arrival[b, i, j]) and hnorm > arr_th:
                    arrival[b, i, j] = t_new
                ke_sum += hN * (spd * spd)
                mass_sum += hfin
        ke = 0.5 * ke_sum * cell_area
        mass = mass_sum * cell_area
        peak = max(ke_peak[b], ke)
        finite = math.isfinite(ke) and math.isfinite(mass)
        calm = (peak > 0) and (ke < stop_frac * peak)
        if stop_frac > 0:
            calm = calm or peak == 0
        at_end = hit and (t_next[b] >= t_end)
        dt_o[b] = dt
        scal_o[b, 0] = t_new
        scal_o[b, 1] = outflow[b] + 0.5 * (o1 + o2)
        scal_o[b, 2] = ke
        scal_o[b, 3] = mass
        scal_o[b, 4] = peak
        flags_o[b, 0] = hit
        flags_o[b, 1] = active[b] and finite and not calm and not at_end
        flags_o[b, 2] = failed[b] or (active[b] and not finite)
        flags_o[b, 3] = stopped[b] or (active[b] and finite and calm and not at_end)
        flags_o[b, 4] = steps[b] + (1 if active[b] else 0)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


_TORCH_THREADS = torch.get_num_threads()
"""torch's thread count when this module was imported (numba's OpenMP pool changes what torch reports later)."""


def threads() -> int:
    """The threads the fused step runs its members on: the process's setting (OMP_NUM_THREADS, else torch's
    thread count at import), at most numba's pool (NUMBA_NUM_THREADS), so that N worker processes with one
    thread each never start N x cores threads."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    n = int(env) if env.isdigit() and int(env) > 0 else _TORCH_THREADS
    return max(1, min(n, numba.config.NUMBA_NUM_THREADS))


def fused_step(F):
    """``step(S, P) -> S`` for the settings ``F`` (supported(F, "cpu") must be None): stepping.make_step's
    step on the fused CPU kernel (same inputs and outputs)."""
    consts = np.array([F.g, F.dx, F.cfl, F.theta, F.h_eps, F.h_wet, F.wb_ratio, F.dt_max, F.v_max_min_depth,
                       F.arrival_threshold, F.stop_ke_fraction, F.entrain_h_min], dtype=np.float64)
    fl = np.array([F.no_creep, F.slope_correction, F.use_ep, F.use_curv, F.use_mu_i, F.inflow, F.use_ent,
                   F.use_dep, F.domain == "wall", F.domain == "outflow"], dtype=np.bool_)
    moving = F.use_ent or F.use_dep
    held: list = [None]       # (the static bed of the last call, its geometry), replaced whole
    held_p: list = [None]     # (the per-box inputs of the last call, their arrays), replaced whole

    def static(z: torch.Tensor):
        """(g6, gx, gy) of a bed that does not evolve (z (1, ny, nx)), computed by _geometry like a moving
        bed's (so a member whose switch is 0 in a batch with a moving bed matches a run without it bitwise),
        once per cropping box (the cache entry is one tuple, read and replaced whole: safe across threads)."""
        last = held[0]
        if last is not None and last[0] is z:
            return last[1]
        ny, nx = z.shape[-2:]
        g6 = np.empty((6, ny, nx))
        gx, gy = np.zeros((5, ny, nx + 4)), np.zeros((5, ny + 4, nx))
        _geometry(two(z), F.dx, F.slope_correction, F.use_curv, g6[0], g6[1], g6[2], g6[3], g6[4], g6[5],
                  _unpack_views(gx, nx, 1), _unpack_views(gy, ny, 0))
        held[0] = (z, (g6, gx, gy))
        return g6, gx, gy

    def f64(t: torch.Tensor) -> np.ndarray:
        return _np(t.to(torch.float64))

    def two(a: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(f64(a).reshape(a.shape[-2], a.shape[-1]))

    def box_inputs(P: dict, B: int, ny: int, nx: int) -> tuple:
        """(pm, mus, inside, rzx, rzy, rcs) of the working set's parameters ``P``: the same tensors from one
        step to the next (simulate replaces P when the box or the members change), so converted once."""
        key = tuple(P[k] for k in PM) + (P.get("mu_scale"), P.get("inside")) + tuple(P["rec"])
        last = held_p[0]
        if last is not None and len(last[0]) == len(key) and all(a is b for a, b in zip(last[0], key)) \
                and last[1][0].shape[0] == B:
            return last[1]
        pm = np.ascontiguousarray(np.stack([np.broadcast_to(f64(P[k]).reshape(-1), (B,)) for k in PM], axis=1))
        mus = two(P["mu_scale"]) if F.use_mu_scale else np.ones((ny, nx))
        inside = (_np(P["inside"]).reshape(ny, nx) if F.domain else np.ones((ny, nx), dtype=np.bool_))
        arrays = (pm, mus, inside) + tuple(two(a) for a in P["rec"])
        held_p[0] = (key, arrays)
        return arrays

    def step(S: dict, P: dict) -> dict:
        h = S["h"]
        dtype = h.dtype
        B, ny, nx = h.shape
        if moving:
            g6, gx, gy = np.zeros((6, 1, 1)), np.zeros((5, 1, 1)), np.zeros((5, 1, 1))
        else:
            g6, gx, gy = static(S["z"])
        pm, mus, inside, rzx, rzy, rcs = box_inputs(P, B, ny, nx)
        z = f64(S["z"])
        dummy = np.zeros((1, 1, 1))
        erod = f64(S["erod"]) if F.use_ent else dummy
        dep = f64(S["dep"]) if F.use_dep else dummy
        h_max, v_max, arrival = (f64(S[k]).copy() for k in ("h_max", "v_max", "arrival"))
        h_o, hu_o, hv_o = np.empty((B, ny, nx)), np.empty((B, ny, nx)), np.empty((B, ny, nx))
        z_o = np.empty((B, ny, nx)) if moving else dummy
        erod_o = np.empty((B, ny, nx)) if F.use_ent else dummy
        dep_o = np.empty((B, ny, nx)) if F.use_dep else dummy
        dt_o, scal_o, flags_o = np.empty(B), np.empty((B, 5)), np.empty((B, 5), dtype=np.int64)
        numba.set_num_threads(threads())
        _step_all(f64(h), f64(S["hu"]), f64(S["hv"]), z, erod, dep, g6, gx, gy, mus, inside, pm, _np(S["active"]),
                  f64(S["t"]), f64(S["t_next"]), float(P["t_end"]), rzx, rzy, rcs, h_max, v_max, arrival,
                  f64(S["ke_peak"]), f64(S["outflow"]), _np(S["steps"]), _np(S["failed"]), _np(S["stopped"]),
                  consts, fl, h_o, hu_o, hv_o, z_o, erod_o, dep_o, dt_o, scal_o, flags_o)
        t = lambda a: torch.from_numpy(a).to(dtype)
        out = dict(S)
        out.update(h=t(h_o), hu=t(hu_o), hv=t(hv_o), h_max=t(h_max), v_max=t(v_max), arrival=t(arrival),
                   dt=t(dt_o), t=t(scal_o[:, 0].copy()), outflow=t(scal_o[:, 1].copy()), ke=t(scal_o[:, 2].copy()),
                   mass=t(scal_o[:, 3].copy()), ke_peak=t(scal_o[:, 4].copy()),
                   hit=torch.from_numpy(flags_o[:, 0] != 0), active=torch.from_numpy(flags_o[:, 1] != 0),
                   failed=torch.from_numpy(flags_o[:, 2] != 0), stopped=torch.from_numpy(flags_o[:, 3] != 0),
                   steps=torch.from_numpy(flags_o[:, 4].copy()).to(S["steps"].dtype))
        if moving:
            out["z"] = t(z_o)
        if F.use_ent:
            out["erod"] = t(erod_o)
        if F.use_dep:
            out["dep"] = t(dep_o)
        return out

    return step
