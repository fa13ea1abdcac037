"""The faces of a stage as one marching kernel (fused_triton.FACES = "march"): each cell's velocities, limited
slopes and wet/dry choice and each face's central-upwind flux computed once per stage, with no barrier.

A program is one warp over a strip of W positions (columns j0 - 2 .. j0 + W - 3) of one member, marching
row by row through a band of rows. It holds three rows in registers: the older row f - 1, the newer row f and
the new row f + 1 it has just loaded. Per row it

- derives the new row's velocities (KP07 Eq. 2.17), carried surface velocities and pressure coefficient;
- reconstructs the newer row along y (its differences to the rows before and after it: each difference once)
  and computes the y face f between the older and the newer row;
- reconstructs the older row along x (a neighbour's value from its lane: one shuffle) and computes the x face
  west of each position;
- writes the older row's cells: the mass their faces carry out (for the draining limiter), the momentum change
  of gravity and pressure along the surface (Eq. 2-3) and the stretch of the direction of motion.

Ghost positions outside the grid follow scheme.py's padding: thickness and bed extrapolated linearly (the
bed from the padded bed zpp, the thickness from the rows or lanes inside), everything else replicated (the
clamped cell's state and fields). The strip owns its positions 2 .. W - 3 (each needs two neighbours on
either side), the band its rows: every face and cell is written by exactly one program. The arithmetic is
the torch step's (stepping._stage, scheme.sweep, scheme.frozen_faces), operation by operation.
"""
from __future__ import annotations

from .triton_ops import triton

if triton is not None:
    import triton.language as tl

    from .triton_ops import (C_G, C_HEPS4, C_HWET, C_INVDX, C_NORMAL, C_SQRT2, C_THETA, C_WB, C_WSMIN, _central_upwind,
                             _dfac, _frozen, _k_earth_pressure, _lane, _max, _minmod3, _momentum_change, _motion,
                             _slope, _wet)

    @triton.jit
    def _store3(ptr, a, b, c, mask):
        """Three values per position, interleaved at ptr, ptr + 1, ptr + 2 (one address, three stores)."""
        tl.store(ptr, a, mask=mask)
        tl.store(ptr + 1, b, mask=mask)
        tl.store(ptr + 2, c, mask=mask)

    @triton.jit
    def _load_row(r, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr,
                  cb, gb, zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny,
                  SLOPE: tl.constexpr, WALLS: tl.constexpr):
        """Row r (clamped into the grid for the state and the fields, replicated; the bed from the padded zpp) at
        every position of the strip: (h, z, u, v, cu, cv, sg, c, moving, g cos^2, |hu| + |hv| (0: at rest), zx, zy,
        cs, inside).
        h is extrapolated linearly at the ghost columns (``far``: 1 or 2 columns outside; ``edge``, ``edge1``:
        the lanes of the edge column and the one inside it); the velocities are those of the clamped cell."""
        rc = tl.minimum(tl.maximum(r, 0), ny - 1)
        cell = rc * nx + jc
        h = tl.load(h_ptr + cb + cell)
        hu = tl.load(hu_ptr + cb + cell)
        hv = tl.load(hv_ptr + cb + cell)
        z = tl.load(zpp_ptr + zb + (r + 2) * (nx + 4) + jp)
        q = geo_ptr + (gb + cell) * 8
        zx, zy, cs, gc2 = tl.load(q), tl.load(q + 1), tl.load(q + 2), tl.load(q + 3)
        if WALLS:
            ins = tl.load(ins_ptr + cell).to(tl.int8)
        else:
            ins = tl.zeros(h.shape, dtype=tl.int8)
        rf = _dfac(h, sqrt2, heps4)
        u = rf * hu
        v = rf * hv
        if SLOPE:
            sg, c, moving = _motion(u, v, zx, zy, tiny)
            cu = sg * u
            cv = sg * v
        else:
            sg = tl.full(h.shape, 1.0, h.dtype)
            c = tl.zeros(h.shape, h.dtype)
            moving = u == u
            cu = u
            cv = v
        he = _lane(h, edge)
        g1 = 2 * he - _lane(h, edge1)
        hx = tl.where(col_in, h, tl.where(far == 1, g1, 2 * g1 - he))
        rest = tl.abs(hu) + tl.abs(hv)
        return hx, z, u, v, cu, cv, sg, c, moving.to(tl.int8), gc2, rest, zx, zy, cs, ins

    @triton.jit
    def _kg_ep(gc2, u, v_s, v_n, ue_i, uw_i, pm_ptr, b):
        """The pressure coefficient k g cos^2 with earth pressure (stepping._earth_pressure): k active where the
        velocities of the (clamped) cell's neighbours spread, passive where they converge; u: the row's
        velocities (east and west neighbours at the lanes ue_i, uw_i), v_s, v_n: the rows before and after."""
        div = (_lane(u, ue_i) - _lane(u, uw_i)) + (v_n - v_s)
        return _k_earth_pressure(div, pm_ptr, b) * gc2

    @triton.jit
    def _ends(q, dm, dp, theta):
        """A cell's reconstructed values at its two faces along an axis (scheme.reconstruct), from its
        differences to the neighbour before (dm) and after (dp): (before, after)."""
        s = _slope(dm, dp, theta)
        return q - 0.5 * s, q + 0.5 * s

    @triton.jit
    def _ends_t(q, tdm, hdm, tdp, hdp):
        """_ends from the differences' theta d and d / 2 (each computed once, for the two cells it serves)."""
        s = _minmod3(tdm, hdm + hdp, tdp)
        return q - 0.5 * s, q + 0.5 * s

    @triton.jit
    def _thickness_ends(hp, z, d_hm, d_hp, d_wm, d_wp, h_m, h_p, z_m, z_p, theta, h_wet, wb):
        """A cell's thickness at its two faces along an axis (scheme.sweep): the surface w = h + z reconstructed
        where the layer is wet (its neighbours h_m, h_p thicker than h_wet and the bed's curvature offset
        small against it), less the face bed, else h itself; and the two face beds. d_*: the differences of
        h and w to the neighbour before (m) and after (p). Returns (h before, h after, bed before, bed after)."""
        wet = _wet(h_m, hp, h_p, z_m, z, z_p, h_wet, wb)
        q_m, q_p = _ends(tl.where(wet, hp + z, hp), tl.where(wet, d_wm, d_hm), tl.where(wet, d_wp, d_hp), theta)
        bf_m = 0.5 * (z_m + z)
        bf_p = 0.5 * (z + z_p)
        return tl.where(wet, _max(q_m - bf_m, 0.0), q_m), tl.where(wet, _max(q_p - bf_p, 0.0), q_p), bf_m, bf_p

    @triton.jit
    def _march(h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, hx_ptr, hy_ptr, ins_ptr, pm_ptr,
               c_ptr, fx_ptr, fy_ptr, cell_ptr, amax_ptr, ny, nx, s_geo, s_zpp, s_hx, s_hy,
               NO_CREEP: tl.constexpr, WALLS: tl.constexpr, USE_EP: tl.constexpr, USE_TAU: tl.constexpr,
               SLOPE: tl.constexpr, CFL: tl.constexpr, W: tl.constexpr, BAND: tl.constexpr, UNROLL: tl.constexpr):
        """The faces and cell terms of a stage (module docstring) for the strip program_id(0), the band of rows
        program_id(1) and the member program_id(2). Writes the x faces (B, ny, nx + 1, 4) west of the cells it
        owns (and the grid's east edge) and the y faces (B, ny + 1, nx, 4) south of them (and the north edge),
        each (Fh, Fqn, Fqt) in the first three of four; per cell (B, ny, nx, 4) (out, mx, my, sigma); and with CFL
        (the first stage, whose time step they set) its largest one-sided speeds along x and y to amax (B,
        programs, 2). geo: fused_triton.geometry_record (in eights); hx, hy: the
        no-creep rule's coefficients at the x and y faces (scheme.hold_coefficients, in eights; s_hx, s_hy: their
        member strides in faces, 0 for one bed of every member); UNROLL: the
        loop over rows unrolled (3: the rows' rotation)."""
        s, t, b = tl.program_id(0), tl.program_id(1), tl.program_id(2)
        p = tl.arange(0, W)
        j0 = s * (W - 4) - 2
        j = j0 + p
        jc = tl.minimum(tl.maximum(j, 0), nx - 1)
        jp = tl.minimum(tl.maximum(j + 2, 0), nx + 3)
        col_in = (j >= 0) & (j < nx)
        far = tl.where(j < 0, -j, j - (nx - 1))
        edge = tl.minimum(tl.maximum(tl.where(j < 0, 0, nx - 1) - j0, 0), W - 1)
        edge1 = tl.minimum(tl.maximum(tl.where(j < 0, 1, nx - 2) - j0, 0), W - 1)
        west, east = tl.maximum(p - 1, 0), tl.minimum(p + 1, W - 1)
        ue_i = tl.minimum(tl.maximum(tl.minimum(jc + 1, nx - 1) - j0, 0), W - 1)
        uw_i = tl.minimum(tl.maximum(tl.maximum(jc - 1, 0) - j0, 0), W - 1)
        own = (p >= 2) & (p < W - 2)
        cb, gb, zb = b * ny * nx, b * s_geo, b * s_zpp
        g, invdx, theta = tl.load(c_ptr + C_G), tl.load(c_ptr + C_INVDX), tl.load(c_ptr + C_THETA)
        h_wet, wb, wsmin = tl.load(c_ptr + C_HWET), tl.load(c_ptr + C_WB), tl.load(c_ptr + C_WSMIN)
        sqrt2, heps4, tiny = tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4), tl.load(c_ptr + C_NORMAL)
        k_ap = tl.load(pm_ptr + b * 11 + 3)
        mu0 = tl.load(pm_ptr + b * 11)
        tau = tl.load(pm_ptr + b * 11 + 2)
        i0 = t * BAND
        i1 = tl.minimum(i0 + BAND, ny)
        # --- the rows i0 - 2 .. i0 + 1; ghost rows above the grid extrapolate the thickness (scheme.pad_linear)
        hA, zA, uA, vA, cuA, cvA, sgA, cA, mvA, g2A, rsA, zxA, zyA, csA, inA = _load_row(
            i0 - 2, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr, cb, gb,
            zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny, SLOPE, WALLS)
        hO, zO, uO, vO, cuO, cvO, sgO, cO, mvO, g2O, rsO, zxO, zyO, csO, inO = _load_row(
            i0 - 1, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr, cb, gb,
            zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny, SLOPE, WALLS)
        hN, zN, uN, vN, cuN, cvN, sgN, cN, mvN, g2N, rsN, zxN, zyN, csN, inN = _load_row(
            i0, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr, cb, gb,
            zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny, SLOPE, WALLS)
        hB, zB, uB, vB, cuB, cvB, sgB, cB_, mvB, g2B, rsB, zxB, zyB, csB, inB = _load_row(
            i0 + 1, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr, cb, gb,
            zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny, SLOPE, WALLS)
        hO = tl.where(i0 >= 1, hO, 2 * hN - hB)
        hA = tl.where(i0 >= 2, hA, 2 * hO - hN)
        kgO = k_ap * g2O
        kgN = k_ap * g2N
        if USE_EP:      # the older row's coefficient (a ghost row's: the edge row's)
            kgO = tl.where(i0 >= 1, _kg_ep(g2O, uO, vA, vN, ue_i, uw_i, pm_ptr, b),
                           _kg_ep(g2N, uN, vO, vB, ue_i, uw_i, pm_ptr, b))
        # the older row's reconstruction along y: its north values are the left state of the face i0
        hpA, hpO, hpN = _max(hA, 0.0), _max(hO, 0.0), _max(hN, 0.0)
        d_h, d_w = hpN - hpO, (hpN + zN) - (hpO + zO)       # the differences between the older and newer row
        d_v, d_cv, d_cu = vN - vO, cvN - cvO, cuN - cuO
        t_v, t_cv, t_cu = theta * d_v, theta * d_cv, theta * d_cu          # their theta d and d / 2, carried
        g_v, g_cv, g_cu = 0.5 * d_v, 0.5 * d_cv, 0.5 * d_cu
        _x, hl_y, _b0, _b1 = _thickness_ends(hpO, zO, hpO - hpA, d_h, (hpO + zO) - (hpA + zA), d_w, hpA, hpN, zA, zN,
                                             theta, h_wet, wb)
        _x, vl_y = _ends(vO, vO - vA, d_v, theta)
        _x, cvl_y = _ends(cvO, cvO - cvA, d_cv, theta)
        _x, cul_y = _ends(cuO, cuO - cuA, d_cu, theta)
        fh_s = tl.zeros([W], dtype=hN.dtype)     # the y face south of the older row, and its pressure potential
        phi_s = tl.zeros([W], dtype=hN.dtype)
        hbar_y = tl.zeros([W], dtype=hN.dtype)   # the older row's mean y face thickness and bed difference
        db_y = tl.zeros([W], dtype=hN.dtype)
        amx = tl.zeros([W], dtype=hN.dtype)
        amy = tl.zeros([W], dtype=hN.dtype)
        for f in tl.range(i0, i1 + 1, loop_unroll_factor=UNROLL):
            # --- the new row f + 1 (a ghost row below the grid: the thickness continues the line of the two above)
            hW, zW, uW, vW, cuW, cvW, sgW, cW, mvW, g2W, rsW, zxW, zyW, csW, inW = _load_row(
                f + 1, h_ptr, hu_ptr, hv_ptr, zpp_ptr, geo_ptr, ins_ptr, cb,
                gb, zb, jc, jp, col_in, far, edge, edge1, ny, nx, sqrt2, heps4, tiny, SLOPE, WALLS)
            hW = tl.where(f + 1 < ny, hW, 2 * hN - hO)
            kgW = k_ap * g2W
            if USE_EP:      # the newer row's coefficient, now that the rows on both sides are here
                kgN = tl.where(f < ny, _kg_ep(g2N, uN, vO, vW, ue_i, uw_i, pm_ptr, b), kgO)
            hpW = _max(hW, 0.0)
            # --- the newer row reconstructed along y, and the y face f between the older and the newer row
            e_h, e_w = hpW - hpN, (hpW + zW) - (hpN + zN)
            e_v, e_cv, e_cu = vW - vN, cvW - cvN, cuW - cuN
            te_v, te_cv, te_cu = theta * e_v, theta * e_cv, theta * e_cu
            ge_v, ge_cv, ge_cu = 0.5 * e_v, 0.5 * e_cv, 0.5 * e_cu
            hr_y, hn_y, bfs, bfn = _thickness_ends(hpN, zN, d_h, e_h, d_w, e_w, hpO, hpW, zO, zW, theta, h_wet, wb)
            vr_y, vn_y = _ends_t(vN, t_v, g_v, te_v, ge_v)
            cvr_y, cvn_y = _ends_t(cvN, t_cv, g_cv, te_cv, ge_cv)
            cur_y, cun_y = _ends_t(cuN, t_cu, g_cu, te_cu, ge_cu)
            fh_n, fqn_n, fqt_n, phi_n, speed = _central_upwind(hl_y, hr_y, vl_y, vr_y, cvl_y, cvr_y, cul_y, cur_y,
                                                               kgO, kgN, wsmin)
            if NO_CREEP or WALLS:
                frozen = tl.zeros([W], dtype=tl.int1)
                if NO_CREEP:
                    frozen = _frozen(hpO, hpN, kgO, kgN, hy_ptr + (b * s_hy + f * nx + jc) * 8, rsO + rsN == 0,
                                     mu0, tau, invdx, USE_TAU)
                if WALLS:
                    frozen = frozen | (inO != inN)
                fh_n = tl.where(frozen, 0.0, fh_n)
                fqn_n = tl.where(frozen, 0.0, fqn_n)
                fqt_n = tl.where(frozen, 0.0, fqt_n)
            fv = f + p * 0      # the face row at every lane
            keep_y = own & col_in & ((fv < i0 + BAND) | (fv == ny))
            _store3(fy_ptr + (b * (ny + 1) * nx + f * nx + j) * 4, fh_n, fqn_n, fqt_n, keep_y)
            if CFL:
                amy = _max(amy, tl.where(keep_y, speed, 0.0))
            # --- the older row f - 1 reconstructed along x, and the x face west of each of its positions
            hpw, hpe = _lane(hpO, west), _lane(hpO, east)
            zw, ze = _lane(zO, west), _lane(zO, east)
            dhx = hpO - hpw
            dwx = (hpO + zO) - (hpw + zw)
            hw_x, he_x, bfw, bfe = _thickness_ends(hpO, zO, dhx, _lane(dhx, east), dwx, _lane(dwx, east), hpw, hpe, zw,
                                                   ze, theta, h_wet, wb)
            dux = uO - _lane(uO, west)
            uw_x, ue_x = _ends(uO, dux, _lane(dux, east), theta)
            dcux = cuO - _lane(cuO, west)
            cuw_x, cue_x = _ends(cuO, dcux, _lane(dcux, east), theta)
            dcvx = cvO - _lane(cvO, west)
            cvw_x, cve_x = _ends(cvO, dcvx, _lane(dcvx, east), theta)
            kgw = _lane(kgO, west)
            fh_x, fqn_x, fqt_x, phi_x, speed = _central_upwind(_lane(he_x, west), hw_x, _lane(ue_x, west), uw_x,
                                                               _lane(cue_x, west), cuw_x, _lane(cve_x, west), cvw_x,
                                                               kgw, kgO, wsmin)
            if NO_CREEP or WALLS:
                frozen = tl.zeros([W], dtype=tl.int1)
                if NO_CREEP:
                    hold = hx_ptr + (b * s_hx + tl.maximum(f - 1, 0) * (nx + 1) + tl.minimum(tl.maximum(j, 0), nx)) * 8
                    frozen = _frozen(hpw, hpO, kgw, kgO, hold, _lane(rsO, west) + rsO == 0, mu0, tau, invdx,
                                     USE_TAU)
                if WALLS:
                    frozen = frozen | (_lane(inO, west) != inO)
                fh_x = tl.where(frozen, 0.0, fh_x)
                fqn_x = tl.where(frozen, 0.0, fqn_x)
                fqt_x = tl.where(frozen, 0.0, fqt_x)
            row_ok = (fv - 1 >= i0) & (fv - 1 < i1)
            keep_x = own & row_ok & (j >= 0) & (j <= nx)
            _store3(fx_ptr + (b * ny * (nx + 1) + (f - 1) * (nx + 1) + j) * 4, fh_x, fqn_x, fqt_x, keep_x)
            if CFL:
                amx = _max(amx, tl.where(keep_x, speed, 0.0))
            # --- the older row's cells: outgoing mass, the momentum change of gravity and pressure (Eq. 2-3)
            fh_e = _lane(fh_x, east)
            out = (_max(fh_e, 0.0) + _max(-fh_x, 0.0)) + (_max(fh_n, 0.0) + _max(-fh_s, 0.0))
            px = kgO * (_lane(phi_x, east) - phi_x) + g * (0.5 * (hw_x + he_x)) * (bfe - bfw)
            py = kgO * (phi_n - phi_s) + g * hbar_y * db_y
            if SLOPE:   # along the surface (stepping.inverse_metric), then the change of Q = sigma q
                a = csO * csO * (zxO * px + zyO * py)
                px = px - zxO * a
                py = py - zyO * a
                px, py = _momentum_change(px, py, uO, vO, sgO, cO, mvO != 0, zxO, zyO, tiny)
            at = cell_ptr + (cb + (f - 1) * nx + j) * 4
            _store3(at, out, px, py, own & row_ok & col_in)
            if SLOPE:
                tl.store(at + 3, sgO, mask=own & row_ok & col_in)
            # --- move down a row
            fh_s, phi_s = fh_n, phi_n
            hbar_y, db_y = 0.5 * (hr_y + hn_y), bfn - bfs
            hl_y, vl_y, cvl_y, cul_y = hn_y, vn_y, cvn_y, cun_y
            d_h, d_w = e_h, e_w
            t_v, t_cv, t_cu, g_v, g_cv, g_cu = te_v, te_cv, te_cu, ge_v, ge_cv, ge_cu
            hO, zO, uO, vO, cuO, cvO, sgO, cO, mvO, g2O, kgO, rsO, zxO, zyO, csO, inO = \
                hN, zN, uN, vN, cuN, cvN, sgN, cN, mvN, g2N, kgN, rsN, zxN, zyN, csN, inN
            hN, zN, uN, vN, cuN, cvN, sgN, cN, mvN, g2N, kgN, rsN, zxN, zyN, csN, inN = \
                hW, zW, uW, vW, cuW, cvW, sgW, cW, mvW, g2W, kgW, rsW, zxW, zyW, csW, inW
            hpO, hpN = hpN, hpW
        if CFL:
            at = (b * tl.num_programs(0) * tl.num_programs(1) + t * tl.num_programs(0) + s) * 2
            tl.store(amax_ptr + at, tl.max(amx, axis=0))
            tl.store(amax_ptr + at + 1, tl.max(amy, axis=0))
