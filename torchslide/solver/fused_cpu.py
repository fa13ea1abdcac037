"""The solver step as one compiled loop nest on the CPU (numba, cached on disk).

``fused_step(F)`` returns a drop-in for ``stepping.make_step(F)``: the same SSP-RK2 step, the same
arithmetic in the same order cell by cell (stepping._stage, scheme.sweep, scheme.frozen_faces,
scheme.draining_factors, friction.apply_friction), so it equals the torch step to round-off (the
sums over the grid, mass, kinetic energy and outflow, add in another order). One pass per stage over
each member's rows and columns replaces the hundreds of whole-array torch operations of a stage:
the torch step's cost on small grids is per operation, not per cell.

Covered (``supported``): Voellmy with the slope metric (or without), the no-creep rule, the yield
stress, earth pressure, curvature, mu(I), a friction map (mu_scale), outflow and open boundaries. A
moving bed (entrainment, deposition) and cells outside the DEM's domain (nodata) run on the torch step. Members run in parallel
(numba prange) on the threads numba is given (NUMBA_NUM_THREADS). The first call compiles (seconds)
and caches the machine code next to this file; later processes load it.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..physics import MU_I_D, MU_I_I0
from .scheme import WAVE_SPEED_MIN

try:
    import numba
    from numba import njit, prange
except ImportError:     # the fused kernel is optional: "eager" needs nothing but torch
    numba = None

SQRT2 = 2.0 ** 0.5
PM = ("mu", "xi", "tau_y", "k_ap", "earth_pressure", "k_act", "k_pass", "curvature", "mu_i")
"""The per-member parameters the fused stage reads, in its order."""


def available() -> bool:
    return numba is not None


def supported(F, device) -> str | None:
    """None when the fused CPU step covers the call's settings ``F`` (StepFlags) on ``device``, else why not."""
    if numba is None:
        return "numba is not installed (pip install numba)"
    if torch.device(device).type != "cpu":
        return "the fused CPU step runs on the CPU"
    terms = [n for n in ("use_ent", "use_dep") if getattr(F, n)]
    if terms or F.domain:
        return f"not covered by the fused CPU step: {', '.join(terms + ([f'domain {F.domain}'] if F.domain else []))}"
    return None


if numba is not None:
    @njit(cache=True, error_model="numpy", inline="always")
    def _desing(h, q, h_eps4):
        h4 = h * h * h * h
        return SQRT2 * h * q / math.sqrt(h4 + max(h4, h_eps4))

    @njit(cache=True, error_model="numpy", inline="always")
    def _minmod3(a, b, c):
        mn = min(min(a, b), c)
        mx = max(max(a, b), c)
        if mn > 0:
            return mn
        if mx < 0:
            return mx
        return 0.0

    @njit(cache=True, error_model="numpy")
    def _pad(q, out, linear, clamp0):
        """Two ghost cells per side: linear extrapolation (pad_linear) or the edge value (pad_replicate)."""
        n = q.shape[0]
        for i in range(n):
            out[i + 2] = q[i]
        if linear:
            out[0] = 3 * q[0] - 2 * q[1]
            out[1] = 2 * q[0] - q[1]
            out[n + 2] = 2 * q[n - 1] - q[n - 2]
            out[n + 3] = 3 * q[n - 1] - 2 * q[n - 2]
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
    def _recon(qp, n, theta, L, R):
        """scheme.reconstruct: L, R (n + 1) face states from a 2-ghost padded line."""
        for c in range(n + 2):
            qm, qc, qq = qp[c], qp[c + 1], qp[c + 2]
            s = _minmod3(theta * (qc - qm), 0.5 * (qq - qm), theta * (qq - qc))
            if c <= n:
                L[c] = qc + 0.5 * s
            if c >= 1:
                R[c - 1] = qc - 0.5 * s

    @njit(cache=True, error_model="numpy")
    def _sweep_line(h, un, ut, kg, frozen, has_frozen, zp, zL, zR, Bf, bias, theta, h_wet, wb, g,
                    Fh, Fqn, Fqt, phi, hbar, dB, w):
        """scheme.sweep along one line of n cells; returns the line's largest one-sided speed.
        ``w``: (14, n + 4) scratch."""
        n = h.shape[0]
        hp, wp, up, tp, kgp = w[0], w[1], w[2], w[3], w[4]
        wL, wR, hLh, hRh, uL, uR, tL, tR = w[5], w[6], w[7], w[8], w[9], w[10], w[11], w[12]
        hLR = w[13]
        _pad(h, hp, True, True)
        for i in range(n + 4):
            wp[i] = hp[i] + zp[i]
        _recon(wp, n, theta, wL, wR)
        _recon(hp, n, theta, hLh, hRh)
        _pad(un, up, False, False)
        _pad(ut, tp, False, False)
        _pad(kg, kgp, False, False)
        _recon(up, n, theta, uL, uR)
        _recon(tp, n, theta, tL, tR)
        amax = 0.0
        for f in range(n + 1):
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
            apam = ap * am * inv
            qL, qR = hL * uL[f], hR * uR[f]
            phi[f] = 0.5 * (ap * hL * hL - am * hR * hR) * inv
            if has_frozen and frozen[f]:
                Fh[f] = 0.0
                Fqn[f] = 0.0
                Fqt[f] = 0.0
            else:
                Fh[f] = (ap * qL - am * qR) * inv + apam * (hR - hL)
                Fqn[f] = (ap * qL * uL[f] - am * qR * uR[f]) * inv + apam * (qR - qL)
                Fqt[f] = (ap * qL * tL[f] - am * qR * tR[f]) * inv + apam * (hR * tR[f] - hL * tL[f])
            hLR[f] = hL
            wp[f] = hR          # (wp no longer needed) the right state of face f
            a = max(ap, -am)
            if a > amax or a != a:
                amax = a
        for c in range(n):
            hbar[c] = 0.5 * (wp[c] + hLR[c + 1])
            dB[c] = Bf[c + 1] - Bf[c]
        return amax

    @njit(cache=True, error_model="numpy")
    def _frozen_line(h, kg, rest, zx, zy, cs, muc, tauc, zL, zR, g, dx, along_x, out, w):
        """scheme.frozen_faces along one line (along_x: the faces are x faces)."""
        n = h.shape[0]
        hp, kgp = w[0], w[1]
        _pad(h, hp, True, True)
        _pad(kg, kgp, False, False)
        for f in range(n + 1):
            a, b = max(f - 1, 0), min(f, n - 1)
            hcL, hcR = hp[f + 1], hp[f + 2]
            hf = 0.5 * (hcL + hcR)
            f_n = -(0.5 * (kgp[f + 1] + kgp[f + 2]) * (hcR - hcL) + g * (zR[f] - zL[f])) * hf / dx
            zxf = 0.5 * (zx[a] + zx[b])
            zyf = 0.5 * (zy[a] + zy[b])
            csf = 0.5 * (cs[a] + cs[b])
            muf = 0.5 * (muc[a] + muc[b])
            tauf = 0.5 * (tauc[a] + tauc[b])
            if along_x:
                f_t = -g * zyf * hf
                ax, ay = f_n, f_t
            else:
                f_t = -g * zxf * hf
                ax, ay = f_t, f_n
            along = zxf * ax + zyf * ay
            drive2 = ax * ax + ay * ay - csf * csf * along * along
            lim = muf * hf + tauf
            out[f] = rest[a] and rest[b] and (drive2 <= lim * lim)

    @njit(cache=True, error_model="numpy")
    def _stage(h, hu, hv, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, pm, dt_in, dt_cap, first,
               g, dx, cfl, theta, h_eps, h_wet, wb, fl, out_h, out_hu, out_hv):
        """stepping._stage for one member without a moving bed: the new state into out_*; returns (dt,
        outflow). mus: (ny, nx) mu_scale (ones without it); pm: the member's mu, xi, tau_y, k_ap,
        earth_pressure, k_act, k_pass, curvature, mu_i; fl: no_creep, slope_correction, use_ep, use_curv,
        use_mu_i, inflow."""
        no_creep, slope, use_ep, use_curv, use_mu_i, inflow = fl[0], fl[1], fl[2], fl[3], fl[4], fl[5]
        mu0, xi, tau, k_ap, s_ep, k_act, k_pass, curv, mu_i = pm[0], pm[1], pm[2], pm[3], pm[4], pm[5], pm[6], pm[7], pm[8]
        ghost = 1.0 if inflow else 0.0
        ny, nx = h.shape
        h_eps4 = h_eps ** 4
        zpx, zLx, zRx, Bfx, biasx = bx
        zpy, zLy, zRy, Bfy, biasy = by
        u = np.empty((ny, nx))
        v = np.empty((ny, nx))
        kg = np.empty((ny, nx))
        for i in range(ny):
            for j in range(nx):
                u[i, j] = _desing(h[i, j], hu[i, j], h_eps4)
                v[i, j] = _desing(h[i, j], hv[i, j], h_eps4)
        for i in range(ny):
            for j in range(nx):
                k = k_ap
                if use_ep:      # stepping._earth_pressure: active where the flow spreads, passive where it converges
                    div = (u[i, min(j + 1, nx - 1)] - u[i, max(j - 1, 0)]) + (v[min(i + 1, ny - 1), j] - v[max(i - 1, 0), j])
                    ksh = k_act if div >= 0 else k_pass
                    k = (1.0 - s_ep) * k_ap + s_ep * ksh
                kg[i, j] = k * (g * cs[i, j]) * cs[i, j]
        Fhx, Fqnx, Fqtx, phix = (np.empty((ny, nx + 1)), np.empty((ny, nx + 1)), np.empty((ny, nx + 1)),
                                 np.empty((ny, nx + 1)))
        Fhy, Fqny, Fqty, phiy = (np.empty((ny + 1, nx)), np.empty((ny + 1, nx)), np.empty((ny + 1, nx)),
                                 np.empty((ny + 1, nx)))
        hbarx, dBx, hbary, dBy = np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx)), np.empty((ny, nx))
        fzx = np.zeros((ny, nx + 1), dtype=np.bool_)
        fzy = np.zeros((ny + 1, nx), dtype=np.bool_)
        m = max(nx, ny) + 4
        wk = np.empty((14, m))
        if no_creep:
            rest = np.empty((ny, nx), dtype=np.bool_)
            muc = np.empty((ny, nx))
            tauc = np.empty((ny, nx))
            for i in range(ny):
                for j in range(nx):
                    rest[i, j] = (hu[i, j] == 0) and (hv[i, j] == 0)
                    muc[i, j] = (mu0 * mus[i, j]) * (g * cs[i, j])
                    tauc[i, j] = tau / cs[i, j]
            for i in range(ny):
                _frozen_line(h[i], kg[i], rest[i], zx[i], zy[i], cs[i], muc[i], tauc[i], zLx[i], zRx[i], g, dx,
                             True, fzx[i], wk)
            for j in range(nx):
                _frozen_line(h[:, j], kg[:, j], rest[:, j], zx[:, j], zy[:, j], cs[:, j], muc[:, j], tauc[:, j],
                             zLy[:, j], zRy[:, j], g, dx, False, fzy[:, j], wk)
        ax = 0.0
        for i in range(ny):
            a = _sweep_line(h[i], u[i], v[i], kg[i], fzx[i], no_creep, zpx[i], zLx[i], zRx[i], Bfx[i], biasx[i],
                            theta, h_wet, wb, g, Fhx[i], Fqnx[i], Fqtx[i], phix[i], hbarx[i], dBx[i], wk)
            if a > ax or a != a:
                ax = a
        ay = 0.0
        for j in range(nx):
            a = _sweep_line(h[:, j], v[:, j], u[:, j], kg[:, j], fzy[:, j], no_creep, zpy[:, j], zLy[:, j],
                            zRy[:, j], Bfy[:, j], biasy[:, j], theta, h_wet, wb, g, Fhy[:, j], Fqny[:, j],
                            Fqty[:, j], phiy[:, j], hbary[:, j], dBy[:, j], wk)
            if a > ay or a != a:
                ay = a
        if first:
            dt = min(cfl * dx / (ax + ay), dt_cap)
            if not dt_cap > 0:
                dt = 0.0
        else:
            dt = dt_in
        # draining factors (ghost 0: outflow boundaries)
        fac = np.empty((ny, nx))
        for i in range(ny):
            for j in range(nx):
                o = (max(Fhx[i, j + 1], 0.0) + max(-Fhx[i, j], 0.0)) + (max(Fhy[i + 1, j], 0.0) + max(-Fhy[i, j], 0.0))
                o = o * (dt / dx)
                fac[i, j] = h[i, j] / o if o > h[i, j] else 1.0
        for i in range(ny):
            for f in range(nx + 1):
                F = Fhx[i, f]
                c = (fac[i, f - 1] if f >= 1 else ghost) if F > 0 else (fac[i, f] if f < nx else ghost)
                Fhx[i, f] = F * c
                Fqnx[i, f] = Fqnx[i, f] * c
                Fqtx[i, f] = Fqtx[i, f] * c
        for f in range(ny + 1):
            for j in range(nx):
                F = Fhy[f, j]
                c = (fac[f - 1, j] if f >= 1 else ghost) if F > 0 else (fac[f, j] if f < ny else ghost)
                Fhy[f, j] = F * c
                Fqny[f, j] = Fqny[f, j] * c
                Fqty[f, j] = Fqty[f, j] * c
        lam = dt / dx
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
        for i in range(ny):
            for j in range(nx):
                hn = h[i, j] - lam * ((Fhx[i, j + 1] - Fhx[i, j]) + (Fhy[i + 1, j] - Fhy[i, j]))
                gn = g * cs[i, j]
                px = kg[i, j] * (phix[i, j + 1] - phix[i, j]) + g * hbarx[i, j] * dBx[i, j]
                py = kg[i, j] * (phiy[i + 1, j] - phiy[i, j]) + g * hbary[i, j] * dBy[i, j]
                if slope:
                    uu, vv = u[i, j], v[i, j]
                    cent = h[i, j] * (zxx[i, j] * uu * uu + 2.0 * zxy[i, j] * uu * vv + zyy[i, j] * vv * vv) * dx
                    px = px + cent * zx[i, j]
                    py = py + cent * zy[i, j]
                    a2 = cs[i, j] * cs[i, j] * (zx[i, j] * px + zy[i, j] * py)
                    px = px - zx[i, j] * a2
                    py = py - zy[i, j] * a2
                qx = hu[i, j] - lam * (((Fqnx[i, j + 1] - Fqnx[i, j]) + (Fqty[i + 1, j] - Fqty[i, j])) + px)
                qy = hv[i, j] - lam * (((Fqtx[i, j + 1] - Fqtx[i, j]) + (Fqny[i + 1, j] - Fqny[i, j])) + py)
                # friction on the momentum along the surface (friction.apply_friction, with curvature_gn and
                # mu_effective at the stage's new state)
                hnp = max(hn, 0.0)
                mue = mu0 * mus[i, j]
                gne = gn
                if use_curv or use_mu_i:
                    un = _desing(hn, qx, h_eps4)
                    vn = _desing(hn, qy, h_eps4)
                    if use_curv:
                        gne = max(gn + curv * (cs[i, j] * (zxx[i, j] * un * un + 2.0 * zxy[i, j] * un * vn
                                                           + zyy[i, j] * vn * vn)), 0.0)
                    if use_mu_i:
                        wn = zx[i, j] * un + zy[i, j] * vn
                        spd = math.sqrt(un * un + vn * vn + wn * wn)
                        hs_ = max(cs[i, j] * hnp, h_eps)
                        inertial = 2.5 * MU_I_D * spd / (hs_ * math.sqrt(max(gne, 1e-12) * hs_))
                        mue = mue + mu_i * inertial / (MU_I_I0 + inertial)
                coul = mue * gne * hnp + tau / cs[i, j]
                w = zx[i, j] * qx + zy[i, j] * qy
                qn = math.sqrt(qx * qx + qy * qy + w * w)
                if qn > 0:
                    keep = max(1.0 - dt * coul / qn, 0.0)
                else:
                    keep = 0.0
                hs = max(hn, h_eps)
                a4 = 4.0 * dt * (g / (xi * cs[i, j])) / (hs * hs)
                factor = keep * 2.0 / (1.0 + math.sqrt(1.0 + a4 * (keep * qn)))
                qx = qx * factor
                qy = qy * factor
                if hn < h_eps:
                    qx = hn * _desing(hn, qx, h_eps4)
                    qy = hn * _desing(hn, qy, h_eps4)
                out_h[i, j] = max(hn, 0.0)
                out_hu[i, j] = qx
                out_hv[i, j] = qy
        return dt, outflow

    @njit(cache=True, error_model="numpy", parallel=True)
    def _step_all(h, hu, hv, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, pm, active, t, t_next, t_end,
                  rzx, rzy, rcs, h_max, v_max, arrival, ke_peak, outflow, steps, failed, stopped, c,
                  fl, h_o, hu_o, hv_o, dt_o, scal_o, flags_o):
        """stepping.make_step's step for every member (members in parallel). ``c``: the float constants
        (g, dx, cfl, theta, h_eps, h_wet, wb, dt_max, v_max_min_depth, arrival_threshold, stop_ke_fraction);
        scal_o: (B, 5) t, outflow, ke, mass, ke_peak; flags_o: (B, 5) hit, active, failed, stopped, steps + active."""
        g, dx, cfl, theta, h_eps, h_wet, wb, dt_max, vmin, arr_th, stop_frac = (
            c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10])
        h_eps4 = h_eps ** 4
        cell_area = dx * dx
        B, ny, nx = h.shape
        for b in prange(B):
            rem = t_next[b] - t[b]
            dt_cap = min(rem, dt_max) if active[b] else 0.0
            h1 = np.empty((ny, nx))
            hu1 = np.empty((ny, nx))
            hv1 = np.empty((ny, nx))
            h2 = np.empty((ny, nx))
            hu2 = np.empty((ny, nx))
            hv2 = np.empty((ny, nx))
            dt, o1 = _stage(h[b], hu[b], hv[b], zx, zy, cs, zxx, zxy, zyy, bx, by, mus, pm[b], 0.0, dt_cap, True,
                            g, dx, cfl, theta, h_eps, h_wet, wb, fl, h1, hu1, hv1)
            _, o2 = _stage(h1, hu1, hv1, zx, zy, cs, zxx, zxy, zyy, bx, by, mus, pm[b], dt, dt_cap, False,
                           g, dx, cfl, theta, h_eps, h_wet, wb, fl, h2, hu2, hv2)
            hit = active[b] and (dt >= rem)
            t_new = t_next[b] if hit else t[b] + dt
            ke_sum = 0.0
            mass_sum = 0.0
            for i in range(ny):
                for j in range(nx):
                    hN = 0.5 * (h[b, i, j] + h2[i, j])
                    stop = hu1[i, j] == 0 and hv1[i, j] == 0 and hu2[i, j] == 0 and hv2[i, j] == 0
                    qx = 0.0 if stop else 0.5 * (hu[b, i, j] + hu2[i, j])
                    qy = 0.0 if stop else 0.5 * (hv[b, i, j] + hv2[i, j])
                    h_o[b, i, j] = hN
                    hu_o[b, i, j] = qx
                    hv_o[b, i, j] = qy
                    uN = _desing(hN, qx, h_eps4)
                    vN = _desing(hN, qy, h_eps4)
                    w = rzx[i, j] * uN + rzy[i, j] * vN
                    spd = math.sqrt(uN * uN + vN * vN + w * w)
                    hnorm = rcs[i, j] * hN
                    h_max[b, i, j] = max(h_max[b, i, j], rcs[i, j] * hN)
                    v_max[b, i, j] = max(v_max[b, i, j], spd if hnorm >= vmin else 0.0)
                    if math.isinf(arrival[b, i, j]) and hnorm > arr_th:
                        arrival[b, i, j] = t_new
                    ke_sum += hN * (spd * spd)
                    mass_sum += hN
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


def fused_step(F):
    """``step(S, P) -> S`` for the settings ``F`` (supported(F, "cpu") must be None): stepping.make_step's
    step on the fused CPU kernel (same inputs and outputs)."""
    from .stepping import static_geometry

    consts = np.array([F.g, F.dx, F.cfl, F.theta, F.h_eps, F.h_wet, F.wb_ratio, F.dt_max, F.v_max_min_depth,
                       F.arrival_threshold, F.stop_ke_fraction], dtype=np.float64)
    fl = np.array([F.no_creep, F.slope_correction, F.use_ep, F.use_curv, F.use_mu_i, F.inflow], dtype=np.bool_)

    def step(S: dict, P: dict) -> dict:
        h = S["h"]
        dtype = h.dtype
        geo = P["geo"] if "geo" in P else static_geometry(S["z"], F)
        zx, zy, cs, hess, (bx, by) = geo
        if hess is None:
            zeros = torch.zeros_like(zx)
            hess = (zeros, zeros, zeros)
        two = lambda a: _np(a.to(torch.float64)).reshape(a.shape[-2], a.shape[-1])
        bxs = tuple(two(a) for a in bx)
        bys = tuple(two(a) for a in by)
        B = h.shape[0]
        pm = np.stack([np.broadcast_to(_np(P[k].to(torch.float64)).reshape(-1), (B,)) for k in PM], axis=1)
        ms = P.get("mu_scale") if F.use_mu_scale else None
        mus = np.ones(h.shape[1:]) if ms is None else two(ms)
        rzx, rzy, rcs = (two(a) for a in P["rec"])
        h_np, hu_np, hv_np = (_np(S[k].to(torch.float64)) for k in ("h", "hu", "hv"))
        h_max = _np(S["h_max"].to(torch.float64)).copy()
        v_max = _np(S["v_max"].to(torch.float64)).copy()
        arrival = _np(S["arrival"].to(torch.float64)).copy()
        h_o, hu_o, hv_o = np.empty_like(h_np), np.empty_like(h_np), np.empty_like(h_np)
        dt_o = np.empty(B)
        scal_o = np.empty((B, 5))
        flags_o = np.empty((B, 5), dtype=np.int64)
        f64 = lambda k: _np(S[k].to(torch.float64))
        _step_all(h_np, hu_np, hv_np, two(zx), two(zy), two(cs), two(hess[0]), two(hess[1]), two(hess[2]), bxs, bys,
                  mus, pm, _np(S["active"]), f64("t"), f64("t_next"), float(P["t_end"]), rzx, rzy, rcs,
                  h_max, v_max, arrival, f64("ke_peak"), f64("outflow"), _np(S["steps"]), _np(S["failed"]),
                  _np(S["stopped"]), consts, fl, h_o, hu_o, hv_o, dt_o, scal_o, flags_o)
        t = lambda a: torch.from_numpy(a).to(dtype)
        out = dict(S)
        out.update(h=t(h_o), hu=t(hu_o), hv=t(hv_o), h_max=t(h_max), v_max=t(v_max), arrival=t(arrival),
                   dt=t(dt_o), t=t(scal_o[:, 0].copy()), outflow=t(scal_o[:, 1].copy()), ke=t(scal_o[:, 2].copy()),
                   mass=t(scal_o[:, 3].copy()), ke_peak=t(scal_o[:, 4].copy()),
                   hit=torch.from_numpy(flags_o[:, 0] != 0), active=torch.from_numpy(flags_o[:, 1] != 0),
                   failed=torch.from_numpy(flags_o[:, 2] != 0), stopped=torch.from_numpy(flags_o[:, 3] != 0),
                   steps=torch.from_numpy(flags_o[:, 4].copy()).to(S["steps"].dtype))
        return out

    return step


def warm() -> bool:
    """Compile the fused step into numba's on-disk cache (one small run; what ``make`` does at install), so
    that a user's first call loads it in about a second. False when numba is not installed."""
    if numba is None:
        return False
    from ..physics import Params
    from ..terrain.grid import DEM
    from .config import SolverConfig
    from .simulate import simulate

    x = np.arange(12) * 10.0
    dem = DEM(z=np.tile(-0.5 * x, (8, 1)), cellsize=10.0)
    rel = np.zeros(dem.shape)
    rel[3:5, 2:4] = 2.0
    simulate(dem, rel, Params.make(mu=[0.2, 0.3], xi=500.0), t_end=2.0, config=SolverConfig(kernel="fused"))
    return True
