"""The cell update of a stage on the Triton step, shared by both designs of the faces (fused_triton.FACES):
the draining-flux limiter (scheme.draining_factors), the fluxes' divergence, the momentum change of gravity
and pressure along the surface (Eq. 2-3, made by the faces' kernels), entrainment and deposition, friction
(Eq. 4), and, after the second stage, the Heun average of the step with its records (stepping.make_step).

It reads what the faces' kernels wrote, interleaved in fours: per face (Fh, Fqn, Fqt, phi), per cell (out, mx,
my, sigma), out being the mass a cell's faces carry out per unit time (m^2/s) and (mx, my) the momentum change.
A program is one warp over a strip of W positions (columns j0 - 1 .. j0 + W - 2, the W - 2 inside its own) of
one member, marching down a band of rows: each cell's draining factor is computed once, its neighbours' come
from the lanes beside it and the rows before and after it, and every load lies inside the grid (the halo's
positions read the edge cell) so that none needs a mask.
"""
from __future__ import annotations

from .triton_ops import triton

if triton is not None:
    import triton.language as tl

    from .triton_ops import (C_AREA, C_ARR, C_CFL_DX, C_DT_MAX, C_DX, C_ENTMIN, C_FRDEP, C_G, C_HEPS, C_HEPS4, C_I0,
                             C_INF, C_INVDX, C_MUI, C_NORMAL, C_SQRT2, C_STOP_KE, C_TINY, C_VMIN, _dfac, _div, _hform,
                             _lane, _max, _min, _sqrt)

    @triton.jit
    def _drain(out, h, lam, normal):
        """scheme.draining_factors' factor of a cell: content / outgoing mass where that is below 1 (no divisor
        below ``normal``)."""
        o = out * lam
        over = (o > h) & (o >= normal)
        return tl.where(over, _div(h, o), 1.0)

    @triton.jit
    def _largest(ptr, n, W: tl.constexpr):
        """The largest of n values at ptr, ptr + 2, ..., ptr + 2 (n - 1) (one axis of the faces' speeds)."""
        p = tl.arange(0, W)
        best = tl.zeros([W], dtype=ptr.dtype.element_ty)
        for k in range(0, n, W):
            best = _max(best, tl.load(ptr + (k + p) * 2, mask=k + p < n, other=0.0))
        return tl.max(best, axis=0)

    @triton.jit
    def _time_step(amax_ptr, n_amax, t, t_next, active, c_ptr, W: tl.constexpr):
        """stepping._stage's CFL time step of a member: min(cfl dx / (ax + ay), dt_cap), 0 for an ended one, with
        ax, ay the largest one-sided speeds at its x and y faces (amax: the faces' programs' (n_amax, 2)) and
        dt_cap = min(t_next - t, dt_max) (stepping.make_step)."""
        dt_cap = tl.where(active, _min(t_next - t, tl.load(c_ptr + C_DT_MAX)), 0.0)
        speeds = _largest(amax_ptr, n_amax, W) + _largest(amax_ptr + 1, n_amax, W)
        return tl.where(dt_cap > 0, _min(_div(1.0, speeds) * tl.load(c_ptr + C_CFL_DX), dt_cap), 0.0)

    @triton.jit
    def _update(h_ptr, hu_ptr, hv_ptr, cell_ptr, z_ptr, erod_ptr, dep_ptr, fx_ptr, fy_ptr,
                geo_ptr, zxx_ptr, zxy_ptr, zyy_ptr, mus_ptr, inside_ptr, pm_ptr, c_ptr, dt_ptr, amax_ptr, n_amax,
                t_ptr, tnext_ptr, active_ptr,
                h0_ptr, hu0_ptr, hv0_ptr, z0_ptr, e0_ptr, d0_ptr, rec_ptr, hmax_ptr, vmax_ptr, arr_ptr,
                ho_ptr, huo_ptr, hvo_ptr, zo_ptr, erodo_ptr, depo_ptr, hmaxo_ptr, vmaxo_ptr, arro_ptr, part_ptr,
                ny, nx, s_geo,
                SLOPE: tl.constexpr, USE_CURV: tl.constexpr, USE_MU_I: tl.constexpr, USE_ENT: tl.constexpr,
                USE_DEP: tl.constexpr, USE_MUS: tl.constexpr, USE_TAU: tl.constexpr, GONE_OUT: tl.constexpr,
                INFLOW: tl.constexpr, FIRST: tl.constexpr, COMBINE: tl.constexpr, W: tl.constexpr, BAND: tl.constexpr,
                UNROLL: tl.constexpr):
        """stepping._stage after the sweeps, for the strip program_id(0), the band of rows program_id(1) and the
        member program_id(2): drained fluxes, the new thickness and surface momentum, q = Q / sigma(Q), the mass
        sources, friction. With FIRST (the first stage) the member's time step is found here (_time_step; the
        faces' speeds amax, its clock t, t_next, active) and written to dt; else dt is read. With COMBINE (the
        second stage) the result is averaged with the step's start (h0, hu0, hv0, ...; h, hu, hv are the first
        stage's) and the records h_max, v_max and arrival are updated, as stepping.make_step does.

        geo: fused_triton.geometry_record (in eights); rec: (z_x, z_y, cos) of the initial bed (the records') in
        fours. part: (B, programs, 4) per program the boundary outflow (m^2/s, outward), the
        thickness lost outside the domain (m, GONE_OUT), and with COMBINE the sums of h |V|^2 and of the thickness
        (m)."""
        s, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
        p = tl.arange(0, W)
        j = s * (W - 2) - 1 + p
        jc = tl.minimum(tl.maximum(j, 0), nx - 1)
        own = (p >= 1) & (p < W - 1) & (j >= 0) & (j < nx)
        west, east = tl.maximum(p - 1, 0), tl.minimum(p + 1, W - 1)
        has_w, has_e = j >= 1, j + 1 < nx
        at_w = tl.where(own & (j == 0), 1.0, 0.0)             # the cells whose faces are the grid's edges
        at_e = tl.where(own & (j == nx - 1), 1.0, 0.0)
        at_y = tl.where(own, 1.0, 0.0)
        cb = b * ny * nx
        g = tl.load(c_ptr + C_G)
        sqrt2, heps4, h_eps = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4), tl.load(c_ptr + C_HEPS)
        normal = tl.load(c_ptr + C_NORMAL)
        if INFLOW:
            ghost = 1.0
        else:
            ghost = 0.0
        if FIRST:
            dt = _time_step(amax_ptr + b * n_amax * 2, n_amax, tl.load(t_ptr + b), tl.load(tnext_ptr + b),
                            tl.load(active_ptr + b), c_ptr, W)
            if (s == 0) & (t == 0):
                tl.store(dt_ptr + b, dt)
        else:
            dt = tl.load(dt_ptr + b)
        lam = dt * tl.load(c_ptr + C_INVDX)
        mu0 = tl.load(pm_ptr + b * 11)
        tau = tl.load(pm_ptr + b * 11 + 2)
        kturb = (4.0 * g) * dt * _div(1.0, tl.load(pm_ptr + b * 11 + 1))   # friction.turbulent_coefficient / sec
        if COMBINE:     # the step's new time (stepping.make_step): the output time where the step reaches it
            t0, t_next = tl.load(t_ptr + b), tl.load(tnext_ptr + b)
            t_new = tl.where(tl.load(active_ptr + b) & (dt >= t_next - t0), t_next, t0 + dt)
            vmin, arr_th, inf = tl.load(c_ptr + C_VMIN), tl.load(c_ptr + C_ARR), tl.load(c_ptr + C_INF)
        i0 = t * BAND
        i1 = tl.minimum(i0 + BAND, ny)
        # --- the row before the band (its draining factor; above the grid: the ghost's) and the first row
        rp = tl.maximum(i0 - 1, 0)
        fac_s = tl.where(i0 >= 1, _drain(tl.load(cell_ptr + (cb + rp * nx + jc) * 4), tl.load(h_ptr + cb + rp * nx + jc),
                                         lam, normal), ghost)
        h_c = tl.load(h_ptr + cb + i0 * nx + jc)
        fac_c = _drain(tl.load(cell_ptr + (cb + i0 * nx + jc) * 4), h_c, lam, normal)
        ys = fy_ptr + (b * (ny + 1) * nx + i0 * nx + jc) * 4                # the south face of the first row
        fhs, fqns, fqts = tl.load(ys), tl.load(ys + 1), tl.load(ys + 2)
        # the outflow through the grid's edges: the south edge's faces (the first band's first row), the x edges'
        # in the loop, the north edge's after it
        bnd = tl.where(i0 == 0, -fhs * tl.where(fhs > 0, fac_s, fac_c) * at_y, 0.0)
        lost = tl.zeros([W], dtype=h_c.dtype)
        ke = tl.zeros([W], dtype=h_c.dtype)
        mass = tl.zeros([W], dtype=h_c.dtype)
        for r in tl.range(i0, i1, loop_unroll_factor=UNROLL):
            # the next row's draining factor (below the grid: the ghost's) and the faces north of this row
            rn = tl.minimum(r + 1, ny - 1)
            h_n = tl.load(h_ptr + cb + rn * nx + jc)
            fac_n = tl.where(r + 1 < ny, _drain(tl.load(cell_ptr + (cb + rn * nx + jc) * 4), h_n, lam, normal), ghost)
            yn = fy_ptr + (b * (ny + 1) * nx + (r + 1) * nx + jc) * 4
            fhn, fqnn, fqtn = tl.load(yn), tl.load(yn + 1), tl.load(yn + 2)
            xw = fx_ptr + (b * ny * (nx + 1) + r * (nx + 1) + jc) * 4       # the west face; the east face next to it
            fhw, fqnw, fqtw = tl.load(xw), tl.load(xw + 1), tl.load(xw + 2)
            fhe, fqne, fqte = tl.load(xw + 4), tl.load(xw + 5), tl.load(xw + 6)
            # each face scaled by its upwind cell's factor (a cell outside the grid: the ghost's)
            k_w = tl.where(fhw > 0, tl.where(has_w, _lane(fac_c, west), ghost), fac_c)
            k_e = tl.where(fhe > 0, fac_c, tl.where(has_e, _lane(fac_c, east), ghost))
            k_s = tl.where(fhs > 0, fac_s, fac_c)
            k_n = tl.where(fhn > 0, fac_c, fac_n)
            fhw, fhe, fhs_, fhn_ = fhw * k_w, fhe * k_e, fhs * k_s, fhn * k_n
            dqx = (fqne * k_e - fqnw * k_w) + (fqtn * k_n - fqts * k_s)
            dqy = (fqte * k_e - fqtw * k_w) + (fqnn * k_n - fqns * k_s)
            bnd += fhe * at_e - fhw * at_w
            h = h_c
            hn = h - lam * ((fhe - fhw) + (fhn_ - fhs_))
            c = cb + r * nx + jc
            g_ = b * s_geo + r * nx + jc
            q = cell_ptr + c * 4
            hu, hv = tl.load(hu_ptr + c), tl.load(hv_ptr + c)
            gq = geo_ptr + g_ * 8
            zx, zy, cs, sec, gn = tl.load(gq), tl.load(gq + 1), tl.load(gq + 2), tl.load(gq + 4), tl.load(gq + 5)
            if SLOPE:   # the surface momentum Q = sigma q, turned back into q (stepping.horizontal_momentum)
                qx = tl.load(q + 3) * hu - lam * (dqx + tl.load(q + 1))
                qy = tl.load(q + 3) * hv - lam * (dqy + tl.load(q + 2))
                n2 = qx * qx + qy * qy
                w = zx * qx + zy * qy
                tq = n2 + w * w
                fq = tl.where(tq > normal, _sqrt(_div(n2, tq)), 1.0)
                qx = qx * fq
                qy = qy * fq
                qn = _sqrt(n2)
            else:
                qx = hu - lam * (dqx + tl.load(q + 1))
                qy = hv - lam * (dqy + tl.load(q + 2))
                qn = _sqrt(qx * qx + qy * qy)
            if GONE_OUT:    # what entered a cell outside the domain has left it
                gone = tl.load(inside_ptr + r * nx + jc) == 0
                lost += tl.where(gone & own, hn, 0.0)
                hn = tl.where(gone, 0.0, hn)
                qx = tl.where(gone, 0.0, qx)
                qy = tl.where(gone, 0.0, qy)
                qn = tl.where(gone, 0.0, qn)
            if USE_ENT or USE_DEP:      # mass sources, explicit in the stage-start state
                r0 = _dfac(h, sqrt2, heps4)
                u0, v0 = r0 * hu, r0 * hv
                w0 = zx * u0 + zy * v0
                speed0 = _sqrt(u0 * u0 + v0 * v0 + w0 * w0)
                zn = tl.load(z_ptr + c)
                if USE_ENT:
                    erod = tl.load(erod_ptr + c)
                    rate = tl.load(pm_ptr + b * 11 + 9) * speed0 * sec * (cs * h > tl.load(c_ptr + C_ENTMIN)).to(h.dtype)
                    de = _min(dt * rate, erod)
                    hn = hn + de
                    erod = erod - de
                    zn = zn - de
                if USE_DEP:
                    dep = tl.load(dep_ptr + c)
                    hs0 = _max(cs * h, h_eps)
                    froude = _div(speed0, _sqrt(_max(gn, tl.load(c_ptr + C_TINY)) * hs0))
                    rate = tl.load(pm_ptr + b * 11 + 10) * h * _max(1.0 - _div(froude, tl.load(c_ptr + C_FRDEP)), 0.0)
                    hpos = _max(hn, 0.0)
                    dd = _min(dt * rate, hpos)
                    ratio = tl.where((hpos > 0) & (hpos >= normal), _div(hpos - dd, hpos), 0.0)
                    qx = qx * ratio
                    qy = qy * ratio
                    qn = qn * ratio
                    hn = hn - dd
                    dep = dep + dd
                    zn = zn + dd
            # friction on the momentum along the surface (Eq. 4, friction.apply_friction)
            mu = mu0
            if USE_MUS:
                mu = mu * tl.load(mus_ptr + r * nx + jc)
            gne = gn
            hnp = _max(hn, 0.0)
            if USE_CURV or USE_MU_I:
                rn_ = _dfac(hn, sqrt2, heps4)
                un = rn_ * qx
                vn = rn_ * qy
                if USE_CURV:
                    gne = _max(gn + tl.load(pm_ptr + b * 11 + 7)
                               * (cs * _hform(tl.load(zxx_ptr + g_), tl.load(zxy_ptr + g_), tl.load(zyy_ptr + g_), un,
                                              vn)), 0.0)
                if USE_MU_I:
                    wn = zx * un + zy * vn
                    spd = _sqrt(un * un + vn * vn + wn * wn)
                    hs_ = _max(cs * hnp, h_eps)
                    inertial = _div(tl.load(c_ptr + C_MUI) * spd, hs_ * _sqrt(_max(gne, tl.load(c_ptr + C_TINY)) * hs_))
                    mu = mu + _div(tl.load(pm_ptr + b * 11 + 8) * inertial, tl.load(c_ptr + C_I0) + inertial)
            if USE_TAU:
                coul = mu * gne * hnp + tau * sec
            else:
                coul = mu * gne * hnp
            keep = tl.where(qn > normal, _max(1.0 - _div(dt * coul, qn), 0.0), 0.0)
            hs = _max(hn, h_eps)
            factor = _div(keep * 2.0, 1.0 + _sqrt(1.0 + _div(kturb * sec, hs * hs) * (keep * qn)))
            factor = factor * tl.where(hn < h_eps, hn * _dfac(hn, sqrt2, heps4), 1.0)
            qx = qx * factor
            qy = qy * factor
            hn = _max(hn, 0.0)
            if COMBINE:     # the Heun average of the step and its records (stepping.make_step)
                stop = ((tl.abs(hu) + tl.abs(hv)) + (tl.abs(qx) + tl.abs(qy))) == 0   # no momentum in either stage
                hn = 0.5 * (tl.load(h0_ptr + c) + hn)
                qx = tl.where(stop, 0.0, 0.5 * (tl.load(hu0_ptr + c) + qx))
                qy = tl.where(stop, 0.0, 0.5 * (tl.load(hv0_ptr + c) + qy))
                if USE_ENT or USE_DEP:
                    zn = 0.5 * (tl.load(z0_ptr + c) + zn)
                if USE_ENT:
                    erod = 0.5 * (tl.load(e0_ptr + c) + erod)
                hfin = hn
                if USE_DEP:
                    dep = 0.5 * (tl.load(d0_ptr + c) + dep)
                    hfin = hn + dep
                rq = rec_ptr + (r * nx + jc) * 4
                rzx, rzy, rcs = tl.load(rq), tl.load(rq + 1), tl.load(rq + 2)
                w = rzx * qx + rzy * qy
                spd = _dfac(hn, sqrt2, heps4) * _sqrt(qx * qx + qy * qy + w * w)
                hnorm = rcs * hn
                tl.store(hmaxo_ptr + c, _max(tl.load(hmax_ptr + c), rcs * hfin), mask=own)
                tl.store(vmaxo_ptr + c, _max(tl.load(vmax_ptr + c), tl.where(hnorm >= vmin, spd, 0.0)), mask=own)
                arr = tl.load(arr_ptr + c)
                tl.store(arro_ptr + c, tl.where((arr == inf) & (hnorm > arr_th), t_new, arr), mask=own)
                ke += tl.where(own, hn * (spd * spd), 0.0)
                mass += tl.where(own, hfin, 0.0)
            tl.store(ho_ptr + c, hn, mask=own)
            tl.store(huo_ptr + c, qx, mask=own)
            tl.store(hvo_ptr + c, qy, mask=own)
            if USE_ENT or USE_DEP:
                tl.store(zo_ptr + c, zn, mask=own)
            if USE_ENT:
                tl.store(erodo_ptr + c, erod, mask=own)
            if USE_DEP:
                tl.store(depo_ptr + c, dep, mask=own)
            # --- move down a row
            fac_s, fac_c, h_c = fac_c, fac_n, h_n
            fhs, fqns, fqts = fhn, fqnn, fqtn
        bnd += tl.where(i1 == ny, fhs * tl.where(fhs > 0, fac_s, fac_c) * at_y, 0.0)   # (the last row's north faces)
        pp = part_ptr + (b * tl.num_programs(0) * tl.num_programs(1) + t * tl.num_programs(0) + s) * 4
        tl.store(pp, tl.sum(bnd, axis=0))
        if GONE_OUT:
            tl.store(pp + 1, tl.sum(lost, axis=0))
        if COMBINE:
            tl.store(pp + 2, tl.sum(ke, axis=0))
            tl.store(pp + 3, tl.sum(mass, axis=0))

    @triton.jit
    def _end_step(part1_ptr, part2_ptr, n_part, dt_ptr, t_ptr, tnext_ptr, active_ptr, tend_ptr, outflow_ptr, kep_ptr,
                  failed_ptr, stopped_ptr, steps_ptr, c_ptr, t_o, outflow_o, ke_o, mass_o, kep_o, hit_o, active_o,
                  failed_o, stopped_o, steps_o, GONE_OUT: tl.constexpr, STOP_AT_REST: tl.constexpr, W: tl.constexpr):
        """The end of a step for member program_id(0) (stepping.make_step and stepping.end_of_step): its new time,
        outflow (both stages' boundary flux and, GONE_OUT, thickness lost outside the domain), kinetic energy and
        mass (the sums of the second update's programs, part2), peak kinetic energy, and whether it failed (not
        finite), stopped (calm: its kinetic energy below stop_ke_fraction of its peak, STOP_AT_REST: or no motion
        at all) or stays active."""
        b = tl.program_id(0)
        p = tl.arange(0, W)
        acc1 = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        acc2 = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        lost1 = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        lost2 = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        ke_s = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        mass_s = tl.zeros([W], dtype=dt_ptr.dtype.element_ty)
        for k in range(0, n_part, W):
            m = k + p < n_part
            q1 = part1_ptr + (b * n_part + k + p) * 4
            q2 = part2_ptr + (b * n_part + k + p) * 4
            acc1 += tl.load(q1, mask=m, other=0.0)
            acc2 += tl.load(q2, mask=m, other=0.0)
            if GONE_OUT:
                lost1 += tl.load(q1 + 1, mask=m, other=0.0)
                lost2 += tl.load(q2 + 1, mask=m, other=0.0)
            ke_s += tl.load(q2 + 2, mask=m, other=0.0)
            mass_s += tl.load(q2 + 3, mask=m, other=0.0)
        dt = tl.load(dt_ptr + b)
        dx, area = tl.load(c_ptr + C_DX), tl.load(c_ptr + C_AREA)
        o1 = dt * dx * tl.sum(acc1, axis=0)
        o2 = dt * dx * tl.sum(acc2, axis=0)
        if GONE_OUT:
            o1 = o1 + tl.sum(lost1, axis=0) * area
            o2 = o2 + tl.sum(lost2, axis=0) * area
        tl.store(outflow_o + b, tl.load(outflow_ptr + b) + 0.5 * (o1 + o2))
        ke = 0.5 * tl.sum(ke_s, axis=0) * area
        mass = tl.sum(mass_s, axis=0) * area
        tl.store(ke_o + b, ke)
        tl.store(mass_o + b, mass)
        peak = _max(tl.load(kep_ptr + b), ke)
        tl.store(kep_o + b, peak)
        t0, t_next = tl.load(t_ptr + b), tl.load(tnext_ptr + b)
        active = tl.load(active_ptr + b)
        hit = active & (dt >= t_next - t0)
        tl.store(hit_o + b, hit)
        tl.store(t_o + b, tl.where(hit, t_next, t0 + dt))
        finite = (ke == ke) & (tl.abs(ke) < tl.load(c_ptr + C_INF)) & (mass == mass) & (tl.abs(mass) < tl.load(c_ptr + C_INF))
        calm = (peak > 0) & (ke < tl.load(c_ptr + C_STOP_KE) * peak)
        if STOP_AT_REST:
            calm = calm | (peak == 0)
        at_end = hit & (t_next >= tl.load(tend_ptr))
        tl.store(failed_o + b, tl.load(failed_ptr + b) | (active & ~finite))
        tl.store(stopped_o + b, tl.load(stopped_ptr + b) | (active & finite & calm & ~at_end))
        tl.store(active_o + b, active & finite & ~calm & ~at_end)
        tl.store(steps_o + b, tl.load(steps_ptr + b) + active.to(tl.int64))
