"""The cell update of a stage on the Triton step, shared by both designs of the faces (fused_triton.FACES):
the draining-flux limiter (scheme.draining_factors), the fluxes' divergence, the momentum change of gravity
and pressure along the surface (Eq. 2-3, made by the faces' kernels), entrainment and deposition, friction
(Eq. 4), and, after the second stage, the Heun average of the step with its records (stepping.make_step).

It reads, per cell, what the faces' kernels wrote: out (the mass a cell's faces carry out per unit time,
m^2/s), the momentum change (mx, my) and the stretch sigma of the direction of motion; per face, the mass and
momentum fluxes. A program updates BLOCK cells of one row of one member.
"""
from __future__ import annotations

from ..physics import MU_I_D, MU_I_I0  # noqa: F401  (the constant table carries them: fused_triton.constants)
from .triton_ops import triton

if triton is not None:
    import triton.language as tl

    from .triton_ops import (C_ARR, C_ENTMIN, C_FRDEP, C_G, C_HEPS, C_HEPS4, C_I0, C_INF, C_INVDX, C_MUI, C_NORMAL,
                             C_SQRT2, C_TINY, C_VMIN, _dfac, _div, _hform, _max, _min, _sqrt)

    @triton.jit
    def _drain(out, h, lam_dt, normal):
        """scheme.draining_factors' factor of a cell: content / outgoing mass where that is below 1 (no divisor
        below ``normal``)."""
        o = out * lam_dt
        over = (o > h) & (o >= normal)
        return tl.where(over, _div(h, tl.where(over, o, 1.0)), 1.0)

    @triton.jit
    def _update(h_ptr, hu_ptr, hv_ptr, cell_ptr, z_ptr, erod_ptr, dep_ptr, fx_ptr, fy_ptr,
                zx_ptr, zy_ptr, cs_ptr, sec_ptr, zxx_ptr, zxy_ptr, zyy_ptr, mus_ptr, inside_ptr, pm_ptr, c_ptr, dt_ptr,
                h0_ptr, hu0_ptr, hv0_ptr, z0_ptr, e0_ptr, d0_ptr, rzx_ptr, rzy_ptr, rcs_ptr, hmax_ptr, vmax_ptr,
                arr_ptr, tnew_ptr,
                ho_ptr, huo_ptr, hvo_ptr, zo_ptr, erodo_ptr, depo_ptr, hmaxo_ptr, vmaxo_ptr, arro_ptr, part_ptr,
                ny, nx, s_geo,
                SLOPE: tl.constexpr, USE_CURV: tl.constexpr, USE_MU_I: tl.constexpr, USE_ENT: tl.constexpr,
                USE_DEP: tl.constexpr, USE_MUS: tl.constexpr, GONE_OUT: tl.constexpr, INFLOW: tl.constexpr,
                COMBINE: tl.constexpr, BLOCK: tl.constexpr):
        """stepping._stage after the sweeps, for cells (i, j0 .. j0 + BLOCK) of member b (cell: per cell (out, mx,
        my, sigma), fx and fy: per face (Fh, Fqn, Fqt, phi), interleaved; fused_triton): drained fluxes, the
        new thickness and surface momentum, q = Q / sigma(Q), the mass sources, friction. With COMBINE (the
        second stage) the result is averaged with the step's start (h0, hu0, hv0, ...; h, hu, hv are the first
        stage's) and the records h_max, v_max and arrival are updated, as stepping.make_step does.

        part: (B, programs, 4) per program the boundary outflow (m^2/s, outward), the thickness lost outside
        the domain (m), and with COMBINE the sums of h |V|^2 and of the thickness (m)."""
        jb, i, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
        j = jb * BLOCK + tl.arange(0, BLOCK)
        m = j < nx
        row = i * nx + j
        c = b * ny * nx + row
        g_ = b * s_geo + row
        g = tl.load(c_ptr + C_G)
        sqrt2, heps4, h_eps = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4), tl.load(c_ptr + C_HEPS)
        normal = tl.load(c_ptr + C_NORMAL)
        if INFLOW:
            ghost = 1.0
        else:
            ghost = 0.0
        dt = tl.load(dt_ptr + b)
        lam = dt * tl.load(c_ptr + C_INVDX)
        # the draining factors of the cell and its four neighbours (scheme.draining_factors)
        h = tl.load(h_ptr + c, mask=m)
        q = cell_ptr + c * 4
        fac = _drain(tl.load(q, mask=m), h, lam, normal)
        has_w, has_e = m & (j >= 1), m & (j + 1 < nx)
        iv = i + tl.zeros([BLOCK], dtype=tl.int32)       # the row of every cell
        has_s, has_n = m & (iv >= 1), m & (iv + 1 < ny)
        fac_w = tl.where(has_w, _drain(tl.load(q - 4, mask=has_w), tl.load(h_ptr + c - 1, mask=has_w), lam, normal),
                         ghost)
        fac_e = tl.where(has_e, _drain(tl.load(q + 4, mask=has_e), tl.load(h_ptr + c + 1, mask=has_e), lam, normal),
                         ghost)
        fac_s = tl.where(has_s, _drain(tl.load(q - 4 * nx, mask=has_s), tl.load(h_ptr + c - nx, mask=has_s), lam,
                                       normal), ghost)
        fac_n = tl.where(has_n, _drain(tl.load(q + 4 * nx, mask=has_n), tl.load(h_ptr + c + nx, mask=has_n), lam,
                                       normal), ghost)
        # each face scaled by its upwind cell's factor
        xw = fx_ptr + (b * ny * (nx + 1) + i * (nx + 1) + j) * 4      # the west face; the east face 4 further
        ys = fy_ptr + (b * (ny + 1) * nx + row) * 4                     # the south face; the north face 4 nx further
        fhw, fhe = tl.load(xw, mask=m), tl.load(xw + 4, mask=m)
        fhs, fhn = tl.load(ys, mask=m), tl.load(ys + 4 * nx, mask=m)
        k_w = tl.where(fhw > 0, fac_w, fac)
        k_e = tl.where(fhe > 0, fac, fac_e)
        k_s = tl.where(fhs > 0, fac_s, fac)
        k_n = tl.where(fhn > 0, fac, fac_n)
        fhw, fhe, fhs, fhn = fhw * k_w, fhe * k_e, fhs * k_s, fhn * k_n
        dqx = (tl.load(xw + 5, mask=m) * k_e - tl.load(xw + 1, mask=m) * k_w) \
            + (tl.load(ys + 4 * nx + 2, mask=m) * k_n - tl.load(ys + 2, mask=m) * k_s)
        dqy = (tl.load(xw + 6, mask=m) * k_e - tl.load(xw + 2, mask=m) * k_w) \
            + (tl.load(ys + 4 * nx + 1, mask=m) * k_n - tl.load(ys + 1, mask=m) * k_s)
        bnd = tl.where(j == nx - 1, fhe, 0.0) - tl.where(j == 0, fhw, 0.0) \
            + (tl.where(iv == ny - 1, fhn, 0.0) - tl.where(iv == 0, fhs, 0.0))
        hn = h - lam * ((fhe - fhw) + (fhn - fhs))
        hu = tl.load(hu_ptr + c, mask=m)
        hv = tl.load(hv_ptr + c, mask=m)
        zx = tl.load(zx_ptr + g_, mask=m)
        zy = tl.load(zy_ptr + g_, mask=m)
        cs = tl.load(cs_ptr + g_, mask=m)
        sec = tl.load(sec_ptr + g_, mask=m)
        mx = tl.load(q + 1, mask=m)
        my = tl.load(q + 2, mask=m)
        if SLOPE:   # the surface momentum Q = sigma q, turned back into q (stepping.horizontal_momentum)
            sg = tl.load(q + 3, mask=m)
            qx = sg * hu - lam * (dqx + mx)
            qy = sg * hv - lam * (dqy + my)
            n2 = qx * qx + qy * qy
            w = zx * qx + zy * qy
            t = n2 + w * w
            ok = t > normal
            f = tl.where(ok, _sqrt(_div(n2, tl.where(ok, t, 1.0))), 1.0)
            qx = qx * f
            qy = qy * f
            qn = _sqrt(n2)
        else:
            qx = hu - lam * (dqx + mx)
            qy = hv - lam * (dqy + my)
            qn = _sqrt(qx * qx + qy * qy)
        lost = tl.zeros([BLOCK], dtype=h.dtype)
        if GONE_OUT:    # what entered a cell outside the domain has left it
            gone = tl.load(inside_ptr + row, mask=m) == 0
            lost = tl.where(gone & m, hn, 0.0)
            hn = tl.where(gone, 0.0, hn)
            qx = tl.where(gone, 0.0, qx)
            qy = tl.where(gone, 0.0, qy)
            qn = tl.where(gone, 0.0, qn)
        gn = g * cs
        if USE_ENT or USE_DEP:      # mass sources, explicit in the stage-start state
            r0 = _dfac(h, sqrt2, heps4)
            u0, v0 = r0 * hu, r0 * hv
            w0 = zx * u0 + zy * v0
            speed0 = _sqrt(u0 * u0 + v0 * v0 + w0 * w0)
            zn = tl.load(z_ptr + c, mask=m)
            if USE_ENT:
                erod = tl.load(erod_ptr + c, mask=m)
                rate = tl.load(pm_ptr + b * 11 + 9) * speed0 * sec * (cs * h > tl.load(c_ptr + C_ENTMIN)).to(h.dtype)
                de = _min(dt * rate, erod)
                hn = hn + de
                erod = erod - de
                zn = zn - de
            if USE_DEP:
                dep = tl.load(dep_ptr + c, mask=m)
                hs0 = _max(cs * h, h_eps)
                froude = _div(speed0, _sqrt(_max(gn, tl.load(c_ptr + C_TINY)) * hs0))
                rate = tl.load(pm_ptr + b * 11 + 10) * h * _max(1.0 - _div(froude, tl.load(c_ptr + C_FRDEP)), 0.0)
                hpos = _max(hn, 0.0)
                dd = _min(dt * rate, hpos)
                left = (hpos > 0) & (hpos >= normal)
                ratio = tl.where(left, _div(hpos - dd, tl.where(left, hpos, 1.0)), 0.0)
                qx = qx * ratio
                qy = qy * ratio
                qn = qn * ratio
                hn = hn - dd
                dep = dep + dd
                zn = zn + dd
        # friction on the momentum along the surface (Eq. 4, friction.apply_friction)
        mu = tl.load(pm_ptr + b * 11)
        if USE_MUS:
            mu = mu * tl.load(mus_ptr + row, mask=m)
        gne = gn
        hnp = _max(hn, 0.0)
        if USE_CURV or USE_MU_I:
            rn = _dfac(hn, sqrt2, heps4)
            un = rn * qx
            vn = rn * qy
            if USE_CURV:
                gne = _max(gn + tl.load(pm_ptr + b * 11 + 7) * (cs * _hform(tl.load(zxx_ptr + g_, mask=m),
                                                                           tl.load(zxy_ptr + g_, mask=m),
                                                                           tl.load(zyy_ptr + g_, mask=m),
                                                                           un, vn)), 0.0)
            if USE_MU_I:
                wn = zx * un + zy * vn
                spd = _sqrt(un * un + vn * vn + wn * wn)
                hs_ = _max(cs * hnp, h_eps)
                inertial = _div(tl.load(c_ptr + C_MUI) * spd, hs_ * _sqrt(_max(gne, tl.load(c_ptr + C_TINY)) * hs_))
                mu = mu + _div(tl.load(pm_ptr + b * 11 + 8) * inertial, tl.load(c_ptr + C_I0) + inertial)
        coul = mu * gne * hnp + tl.load(pm_ptr + b * 11 + 2) * sec
        moving = qn > normal
        keep = tl.where(moving, _max(1.0 - _div(dt * coul, tl.where(moving, qn, 1.0)), 0.0), 0.0)
        hs = _max(hn, h_eps)
        turb = ((4.0 * g) * dt * _div(1.0, tl.load(pm_ptr + b * 11 + 1))) * sec
        factor = _div(keep * 2.0, 1.0 + _sqrt(1.0 + _div(turb, hs * hs) * (keep * qn)))
        factor = factor * tl.where(hn < h_eps, hn * _dfac(hn, sqrt2, heps4), 1.0)
        qx = qx * factor
        qy = qy * factor
        hn = _max(hn, 0.0)
        pp = part_ptr + (b * tl.num_programs(0) * tl.num_programs(1) + i * tl.num_programs(0) + jb) * 4
        tl.store(pp, tl.sum(tl.where(m, bnd, 0.0), axis=0))
        if GONE_OUT:
            tl.store(pp + 1, tl.sum(lost, axis=0))
        if COMBINE:     # the Heun average of the step and its records (stepping.make_step)
            stop = (hu == 0) & (hv == 0) & (qx == 0) & (qy == 0)
            hn = 0.5 * (tl.load(h0_ptr + c, mask=m) + hn)
            qx = tl.where(stop, 0.0, 0.5 * (tl.load(hu0_ptr + c, mask=m) + qx))
            qy = tl.where(stop, 0.0, 0.5 * (tl.load(hv0_ptr + c, mask=m) + qy))
            if USE_ENT or USE_DEP:
                zn = 0.5 * (tl.load(z0_ptr + c, mask=m) + zn)
            if USE_ENT:
                erod = 0.5 * (tl.load(e0_ptr + c, mask=m) + erod)
            hfin = hn
            if USE_DEP:
                dep = 0.5 * (tl.load(d0_ptr + c, mask=m) + dep)
                hfin = hn + dep
            rzx = tl.load(rzx_ptr + row, mask=m)
            rzy = tl.load(rzy_ptr + row, mask=m)
            rcs = tl.load(rcs_ptr + row, mask=m)
            w = rzx * qx + rzy * qy
            spd = _dfac(hn, sqrt2, heps4) * _sqrt(qx * qx + qy * qy + w * w)
            hnorm = rcs * hn
            tl.store(hmaxo_ptr + c, _max(tl.load(hmax_ptr + c, mask=m), rcs * hfin), mask=m)
            vmax = _max(tl.load(vmax_ptr + c, mask=m), tl.where(hnorm >= tl.load(c_ptr + C_VMIN), spd, 0.0))
            tl.store(vmaxo_ptr + c, vmax, mask=m)
            arr = tl.load(arr_ptr + c, mask=m)
            arrived = (arr == tl.load(c_ptr + C_INF)) & (hnorm > tl.load(c_ptr + C_ARR))
            tl.store(arro_ptr + c, tl.where(arrived, tl.load(tnew_ptr + b), arr), mask=m)
            tl.store(pp + 2, tl.sum(tl.where(m, hn * (spd * spd), 0.0), axis=0))
            tl.store(pp + 3, tl.sum(tl.where(m, hfin, 0.0), axis=0))
        tl.store(ho_ptr + c, hn, mask=m)
        tl.store(huo_ptr + c, qx, mask=m)
        tl.store(hvo_ptr + c, qy, mask=m)
        if USE_ENT or USE_DEP:
            tl.store(zo_ptr + c, zn, mask=m)
        if USE_ENT:
            tl.store(erodo_ptr + c, erod, mask=m)
        if USE_DEP:
            tl.store(depo_ptr + c, dep, mask=m)
