"""The faces of a stage as line kernels (fused_triton.FACES = "lines"), one face or cell per thread:

    _velocities   u, v (KP07 Eq. 2.17) and, with the slope metric, the carried surface velocities sigma u,
                  sigma v and the stretch sigma, once per stage
    _faces        the x faces (AXIS 0) or the y faces (AXIS 1): reconstruction, central-upwind fluxes
                  (KP07 Eq. 3.11), the no-creep rule, domain walls, the largest one-sided speed per block
    _cells        per cell the outgoing mass and the momentum change of gravity and pressure along the surface
                  (Eq. 2-3), from the faces' pressure potentials and thicknesses

Each face reconstructs the four cells around it, so every cell is reconstructed once for each of its two
faces along an axis (fused_triton.FACES = "march" does it once). The arithmetic is the torch step's,
operation by operation; the bed comes padded on both axes (zpp, fused_triton.padded_bed).
"""
from __future__ import annotations

from .triton_ops import triton

if triton is not None:
    import triton.language as tl

    from .triton_ops import (C_G, C_HEPS4, C_HWET, C_INVDX, C_NORMAL, C_SQRT2, C_THETA, C_WB, C_WSMIN, _central_upwind,
                             _dfac, _frozen, _k_earth_pressure, _max, _momentum_change, _motion, _slope, _wet)

    @triton.jit
    def _velocities(h_ptr, hu_ptr, hv_ptr, geo_ptr, c_ptr, u_ptr, v_ptr, cu_ptr, cv_ptr, sg_ptr, ny, nx, s_geo,
                    SLOPE: tl.constexpr, BLOCK: tl.constexpr):
        """u, v of every cell of every member and, with SLOPE, sigma u, sigma v and sigma (stepping._stage)."""
        b = tl.program_id(1)
        idx = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        cb = b * ny * nx + idx
        h = tl.load(h_ptr + cb, mask=m, other=0.0)
        r = _dfac(h, tl.load(c_ptr + C_SQRT2), tl.load(c_ptr + C_HEPS4))
        u = r * tl.load(hu_ptr + cb, mask=m, other=0.0)
        v = r * tl.load(hv_ptr + cb, mask=m, other=0.0)
        tl.store(u_ptr + cb, u, mask=m)
        tl.store(v_ptr + cb, v, mask=m)
        if SLOPE:
            gq = geo_ptr + (b * s_geo + idx) * 8
            sg, _c, _m = _motion(u, v, tl.load(gq, mask=m), tl.load(gq + 1, mask=m), tl.load(c_ptr + C_NORMAL))
            tl.store(cu_ptr + cb, sg * u, mask=m)
            tl.store(cv_ptr + cb, sg * v, mask=m)
            tl.store(sg_ptr + cb, sg, mask=m)

    @triton.jit
    def _lin(ptr, base, c, n, stride, m):
        """The field at cell c (in [-2, n + 1]) of a line of n cells, ghost cells by linear extrapolation
        (scheme.pad_linear: g1 = 2 q0 - q1 beside the edge cell q0, then 2 g1 - q0)."""
        q = tl.load(ptr + base + tl.minimum(tl.maximum(c, 0), n - 1) * stride, mask=m, other=0.0)
        lo, hi = m & (c < 0), m & (c >= n)
        l0 = tl.load(ptr + base, mask=lo, other=0.0)
        gl = 2 * l0 - tl.load(ptr + base + stride, mask=lo, other=0.0)
        r0 = tl.load(ptr + base + (n - 1) * stride, mask=hi, other=0.0)
        gr = 2 * r0 - tl.load(ptr + base + (n - 2) * stride, mask=hi, other=0.0)
        q = tl.where(c == -1, gl, q)
        q = tl.where(c == -2, 2 * gl - l0, q)
        q = tl.where(c == n, gr, q)
        return tl.where(c == n + 1, 2 * gr - r0, q)

    @triton.jit
    def _face_lr(q0, q1, q2, q3, theta):
        """A field reconstructed at the face between cells 1 and 2 from cells 0 .. 3 (scheme.reconstruct):
        (cell 1's east value, cell 2's west value)."""
        d1 = q2 - q1
        return q1 + 0.5 * _slope(q1 - q0, d1, theta), q2 - 0.5 * _slope(d1, q3 - q2, theta)

    @triton.jit
    def _face_h(h0, h1, h2, h3, z0, z1, z2, z3, theta, h_wet, wb):
        """The thickness left and right of the face between cells 1 and 2 (scheme.sweep): the surface w = h + z
        reconstructed where a cell is wet, less the face bed, else h; and the face bed."""
        bf = 0.5 * (z1 + z2)
        w0, w1, w2, w3 = h0 + z0, h1 + z1, h2 + z2, h3 + z3
        wet_l = _wet(h0, h1, h2, z0, z1, z2, h_wet, wb)
        wet_r = _wet(h1, h2, h3, z1, z2, z3, h_wet, wb)
        dm_l = tl.where(wet_l, w1 - w0, h1 - h0)
        dp_l = tl.where(wet_l, w2 - w1, h2 - h1)
        ql = tl.where(wet_l, w1, h1) + 0.5 * _slope(dm_l, dp_l, theta)
        dm_r = tl.where(wet_r, w2 - w1, h2 - h1)
        dp_r = tl.where(wet_r, w3 - w2, h3 - h2)
        qr = tl.where(wet_r, w2, h2) - 0.5 * _slope(dm_r, dp_r, theta)
        return tl.where(wet_l, _max(ql - bf, 0.0), ql), tl.where(wet_r, _max(qr - bf, 0.0), qr), bf

    @triton.jit
    def _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, i, j, ny, nx, m, USE_EP: tl.constexpr):
        """The pressure coefficient k g cos^2 at cells (i, j) (stepping._stage with stepping._earth_pressure:
        with earth pressure, k is active where the flow spreads (div u >= 0), passive where it converges;
        the velocities of the four neighbours replicated at the edges). cb, gb: the member's offsets of the
        state and of the geometry."""
        gc2 = tl.load(gc2_ptr + gb + i * nx + j, mask=m, other=0.0)
        if USE_EP:
            row, col = cb + i * nx, cb + j
            div = (tl.load(u_ptr + row + tl.minimum(j + 1, nx - 1), mask=m, other=0.0)
                   - tl.load(u_ptr + row + tl.maximum(j - 1, 0), mask=m, other=0.0)) \
                + (tl.load(v_ptr + col + tl.minimum(i + 1, ny - 1) * nx, mask=m, other=0.0)
                   - tl.load(v_ptr + col + tl.maximum(i - 1, 0) * nx, mask=m, other=0.0))
            k = _k_earth_pressure(div, pm_ptr, b)
        else:
            k = tl.load(pm_ptr + b * 11 + 3)
        return k * gc2

    @triton.jit
    def _fo(b, ny, nx, AXIS: tl.constexpr):
        """Offset of member b's faces: (ny, nx + 1) x faces or (ny + 1, nx) y faces per member."""
        if AXIS == 0:
            return b * ny * (nx + 1)
        else:
            return b * (ny + 1) * nx

    @triton.jit
    def _faces(h_ptr, hu_ptr, hv_ptr, u_ptr, v_ptr, cu_ptr, cv_ptr, zpp_ptr, gc2_ptr, hold_ptr,
               inside_ptr, pm_ptr, c_ptr, f_ptr, hl_ptr, hr_ptr, amax_ptr, n_amax, ny, nx, s_zpp, s_geo, s_hold,
               AXIS: tl.constexpr, NO_CREEP: tl.constexpr, WALLS: tl.constexpr, USE_EP: tl.constexpr,
               USE_TAU: tl.constexpr, SLOPE: tl.constexpr, CFL: tl.constexpr, BLOCK: tl.constexpr):
        """scheme.sweep (and scheme.frozen_faces, stepping._domain_walls) at the x faces (AXIS 0: (ny, nx + 1)
        per member) or the y faces (AXIS 1: (ny + 1, nx)); face f of a line lies between cells f - 1 and f.
        zpp: the bed padded on both axes; u, v: the velocities, cu, cv: the carried velocities (SLOPE); hold: the
        no-creep rule's coefficients of the faces (scheme.hold_coefficients, in eights). Writes per
        face (Fh, Fqn, Fqt, phi) interleaved (f) and the thickness left and right of it (hl, hr); with CFL (the
        first stage) the largest one-sided speed of each program's faces to amax (B, n_amax, 2) at [b, pid, AXIS]."""
        b = tl.program_id(1)
        pid = tl.program_id(0)
        idx = pid * BLOCK + tl.arange(0, BLOCK)
        if AXIS == 0:
            n = nx
            m = idx < ny * (nx + 1)
            line, f = idx // (nx + 1), idx % (nx + 1)
            base, st = line * nx, 1
            zbase, zst = (line + 2) * (nx + 4), 1
        else:
            n = ny
            m = idx < (ny + 1) * nx
            f, line = idx // nx, idx % nx
            base, st = line, nx
            zbase, zst = line + 2, nx + 4
        cb = b * ny * nx
        gb = b * s_geo
        theta = tl.load(c_ptr + C_THETA)
        h_wet, wb, wsmin = tl.load(c_ptr + C_HWET), tl.load(c_ptr + C_WB), tl.load(c_ptr + C_WSMIN)
        # thickness (clipped at 0) and bed at the four cells f - 2 .. f + 1 (padded indices f .. f + 3)
        h0 = _max(_lin(h_ptr, cb + base, f - 2, n, st, m), 0.0)
        h1 = _max(_lin(h_ptr, cb + base, f - 1, n, st, m), 0.0)
        h2 = _max(_lin(h_ptr, cb + base, f, n, st, m), 0.0)
        h3 = _max(_lin(h_ptr, cb + base, f + 1, n, st, m), 0.0)
        zb = zpp_ptr + b * s_zpp + zbase
        z0 = tl.load(zb + f * zst, mask=m, other=0.0)
        z1 = tl.load(zb + (f + 1) * zst, mask=m, other=0.0)
        z2 = tl.load(zb + (f + 2) * zst, mask=m, other=0.0)
        z3 = tl.load(zb + (f + 3) * zst, mask=m, other=0.0)
        hl, hr, bf = _face_h(h0, h1, h2, h3, z0, z1, z2, z3, theta, h_wet, wb)
        # velocities normal (un) and tangential (ut) to the face, replicated at the edges
        if AXIS == 0:
            wn_ptr, wt_ptr, cn_ptr, ct_ptr = u_ptr, v_ptr, cu_ptr, cv_ptr
        else:
            wn_ptr, wt_ptr, cn_ptr, ct_ptr = v_ptr, u_ptr, cv_ptr, cu_ptr
        if not SLOPE:
            cn_ptr, ct_ptr = wn_ptr, wt_ptr
        c0 = cb + base + tl.minimum(tl.maximum(f - 2, 0), n - 1) * st
        c1 = cb + base + tl.minimum(tl.maximum(f - 1, 0), n - 1) * st
        c2 = cb + base + tl.minimum(f, n - 1) * st
        c3 = cb + base + tl.minimum(f + 1, n - 1) * st
        ul, ur = _face_lr(tl.load(wn_ptr + c0, mask=m, other=0.0), tl.load(wn_ptr + c1, mask=m, other=0.0),
                          tl.load(wn_ptr + c2, mask=m, other=0.0), tl.load(wn_ptr + c3, mask=m, other=0.0), theta)
        cnl, cnr = _face_lr(tl.load(cn_ptr + c0, mask=m, other=0.0), tl.load(cn_ptr + c1, mask=m, other=0.0),
                            tl.load(cn_ptr + c2, mask=m, other=0.0), tl.load(cn_ptr + c3, mask=m, other=0.0), theta)
        tlf, trf = _face_lr(tl.load(ct_ptr + c0, mask=m, other=0.0), tl.load(ct_ptr + c1, mask=m, other=0.0),
                            tl.load(ct_ptr + c2, mask=m, other=0.0), tl.load(ct_ptr + c3, mask=m, other=0.0), theta)
        a = tl.minimum(tl.maximum(f - 1, 0), n - 1)      # the cells left and right of the face
        c = tl.minimum(f, n - 1)
        if AXIS == 0:
            kgl = _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, line, a, ny, nx, m, USE_EP)
            kgr = _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, line, c, ny, nx, m, USE_EP)
        else:
            kgl = _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, a, line, ny, nx, m, USE_EP)
            kgr = _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, c, line, ny, nx, m, USE_EP)
        fh, fqn, fqt, phi, speed = _central_upwind(hl, hr, ul, ur, cnl, cnr, tlf, trf, kgl, kgr, wsmin)
        if NO_CREEP or WALLS:
            frozen = tl.zeros([BLOCK], dtype=tl.int1)
            if NO_CREEP:    # scheme.frozen_faces: both cells at rest and friction holds the face's drive
                rest_a = (tl.load(hu_ptr + cb + base + a * st, mask=m, other=1.0) == 0) \
                    & (tl.load(hv_ptr + cb + base + a * st, mask=m, other=1.0) == 0)
                rest_c = (tl.load(hu_ptr + cb + base + c * st, mask=m, other=1.0) == 0) \
                    & (tl.load(hv_ptr + cb + base + c * st, mask=m, other=1.0) == 0)
                nf = (ny * (nx + 1)) if AXIS == 0 else ((ny + 1) * nx)
                frozen = _frozen(h1, h2, kgl, kgr, hold_ptr + (b * s_hold + tl.minimum(idx, nf - 1)) * 8,
                                 rest_a & rest_c, tl.load(pm_ptr + b * 11), tl.load(pm_ptr + b * 11 + 2),
                                 tl.load(c_ptr + C_INVDX), USE_TAU)
            if WALLS:       # faces between a cell of the domain and one outside it
                ins_a = tl.load(inside_ptr + base + a * st, mask=m, other=0)
                ins_c = tl.load(inside_ptr + base + c * st, mask=m, other=0)
                frozen = frozen | (ins_a != ins_c)
            fh = tl.where(frozen, 0.0, fh)
            fqn = tl.where(frozen, 0.0, fqn)
            fqt = tl.where(frozen, 0.0, fqt)
        fo = _fo(b, ny, nx, AXIS)
        q = f_ptr + (fo + idx) * 4
        tl.store(q, fh, mask=m)
        tl.store(q + 1, fqn, mask=m)
        tl.store(q + 2, fqt, mask=m)
        tl.store(q + 3, phi, mask=m)
        tl.store(hl_ptr + fo + idx, hl, mask=m)
        tl.store(hr_ptr + fo + idx, hr, mask=m)
        if CFL:     # the first stage's faces set its time step
            tl.store(amax_ptr + (b * n_amax + pid) * 2 + AXIS, tl.max(tl.where(m, speed, 0.0), axis=0))

    @triton.jit
    def _cells(u_ptr, v_ptr, sg_ptr, zpp_ptr, geo_ptr, gc2_ptr, pm_ptr, c_ptr,
               fx_ptr, hlx_ptr, hrx_ptr, fy_ptr, hly_ptr, hry_ptr, cell_ptr,
               ny, nx, s_zpp, s_geo, USE_EP: tl.constexpr, SLOPE: tl.constexpr, BLOCK: tl.constexpr):
        """Per cell (out, mx, my, sigma), interleaved: out, the mass its faces carry out (scheme.draining_factors),
        (mx, my), the horizontal gradient of gravity and pressure (Eq. 2-3, KP07 Eq. 3.13) turned along the surface
        and into the change of the surface momentum (stepping.inverse_metric, stepping.surface_momentum_change),
        and the stretch sigma of the direction of motion."""
        b = tl.program_id(1)
        idx = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        m = idx < ny * nx
        i, j = idx // nx, idx % nx
        cb = b * ny * nx
        gb = b * s_geo
        g = tl.load(c_ptr + C_G)
        xw = b * ny * (nx + 1) + i * (nx + 1) + j
        ys = b * (ny + 1) * nx + idx
        fhw, fhe = tl.load(fx_ptr + xw * 4, mask=m), tl.load(fx_ptr + xw * 4 + 4, mask=m)
        fhs, fhn = tl.load(fy_ptr + ys * 4, mask=m), tl.load(fy_ptr + (ys + nx) * 4, mask=m)
        out = (_max(fhe, 0.0) + _max(-fhw, 0.0)) + (_max(fhn, 0.0) + _max(-fhs, 0.0))
        kg = _kg(gc2_ptr, u_ptr, v_ptr, pm_ptr, b, cb, gb, i, j, ny, nx, m, USE_EP)
        zr = zpp_ptr + b * s_zpp + (i + 2) * (nx + 4) + j + 2
        zc = tl.load(zr, mask=m, other=0.0)
        dbx = 0.5 * (zc + tl.load(zr + 1, mask=m, other=0.0)) - 0.5 * (tl.load(zr - 1, mask=m, other=0.0) + zc)
        dby = 0.5 * (zc + tl.load(zr + (nx + 4), mask=m, other=0.0)) - 0.5 * (tl.load(zr - (nx + 4), mask=m, other=0.0)
                                                                             + zc)
        hbarx = 0.5 * (tl.load(hrx_ptr + xw, mask=m, other=0.0) + tl.load(hlx_ptr + xw + 1, mask=m, other=0.0))
        hbary = 0.5 * (tl.load(hry_ptr + ys, mask=m, other=0.0) + tl.load(hly_ptr + ys + nx, mask=m, other=0.0))
        px = kg * (tl.load(fx_ptr + xw * 4 + 7, mask=m) - tl.load(fx_ptr + xw * 4 + 3, mask=m)) + g * hbarx * dbx
        py = kg * (tl.load(fy_ptr + (ys + nx) * 4 + 3, mask=m) - tl.load(fy_ptr + ys * 4 + 3, mask=m)) + g * hbary * dby
        if SLOPE:   # along the surface (stepping.inverse_metric), then the change of Q = sigma q
            gq = geo_ptr + (gb + idx) * 8
            zx, zy, cs = tl.load(gq, mask=m), tl.load(gq + 1, mask=m), tl.load(gq + 2, mask=m)
            a = cs * cs * (zx * px + zy * py)
            px = px - zx * a
            py = py - zy * a
            u = tl.load(u_ptr + cb + idx, mask=m, other=0.0)
            v = tl.load(v_ptr + cb + idx, mask=m, other=0.0)
            tiny = tl.load(c_ptr + C_NORMAL)
            sg, c, moving = _motion(u, v, zx, zy, tiny)
            px, py = _momentum_change(px, py, u, v, sg, c, moving, zx, zy, tiny)
        q = cell_ptr + (cb + idx) * 4
        tl.store(q, out, mask=m)
        tl.store(q + 1, px, mask=m)
        tl.store(q + 2, py, mask=m)
        if SLOPE:
            tl.store(q + 3, tl.load(sg_ptr + cb + idx, mask=m), mask=m)
