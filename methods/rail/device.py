"""RAIL's client reconstruction as Dr.Jit kernels on the run's Mitsuba variant: one code path, vectorised and
multi-threaded on ``llvm_ad_rgb`` and on the GPU on ``cuda_ad_rgb`` (the core's device kernels, suite.core.device).

On a tracer with a device path the client's frame stays on the device from the G-buffer to the composed image:
the G-buffer and direct light are the core's device kernels, and here

* :class:`DeviceGrid` holds the client's G (cell starts, reference lists) and Q's records, uploaded once per full
  transfer (a counted copy: the records arrive in host memory, from the network);
* :func:`idw` is eq. 1-2 through G (§3.3: one cell per lookup), per pixel a loop over the records of its cell;
* :func:`joint_bilateral_upsample` is §3.3's upsampling of a reduced-resolution irradiance channel.

They compute what the host path computes (``grid.idw``'s numba loop, ``upsample.joint_bilateral_upsample``),
operation for operation in the same precision, so that the two agree to rounding (the tests compare them); the
host path is what Embree runs. The per-frame irradiance (eq. 5's interpolation of the cache, one value per
record) is uploaded each frame, and the pixels that need the ambient function (eq. 2 is 0/0, or dynamic geometry)
are copied to the host for F_a·AO (its AO rays go through the tracer's host interface) and the results scattered
back: both counted copies.
"""
from __future__ import annotations

import numpy as np

from .upsample import DEPTH_SIGMA_REL, NORMAL_POWER


class DeviceGrid:
    """G and Q's records on the device (from a :class:`~methods.rail.method.ClientGrid`)."""

    def __init__(self, dev, cg):
        if len(cg.grid.refs) >= 2 ** 32 or len(cg.position) >= 2 ** 32:
            raise ValueError("G holds more references than 32-bit indices address")
        self.dev = dev
        self.geometry = cg.geometry
        before = dev.counters["bytes_to_device"]
        self.cell_start = dev.to_device(cg.grid.cell_start.astype(np.uint32), dev.UInt32)
        self.refs = dev.to_device(cg.grid.refs.astype(np.uint32), dev.UInt32)
        self.position = dev.to_device(np.asarray(cg.position, np.float64).reshape(-1, 3), dev.Vector3d)
        self.normal = dev.to_device(np.asarray(cg.normal, np.float64).reshape(-1, 3), dev.Vector3d)
        self.range_m = dev.to_device(np.asarray(cg.range_m, np.float64).reshape(-1), dev.Float64)
        dev.eval(self.cell_start, self.refs, self.position, self.normal, self.range_m)
        self.nbytes = dev.counters["bytes_to_device"] - before

    def irradiance(self, E):
        """The records' irradiance (N, 3) as a device Vector3d (a counted copy)."""
        return self.dev.to_device(np.ascontiguousarray(E, np.float64).reshape(-1, 3), self.dev.Vector3d)


def cell_index(dev, geometry, p, active):
    """``GridGeometry.cell_index`` on the device: (UInt32 flat cell, Bool inside the grid and active)."""
    dr, F64 = dev.dr, dev.Float64
    origin = [dev.opaque(F64, float(x)) for x in geometry.origin]
    cell_m = dev.opaque(F64, float(geometry.cell_m))
    c = dev.opaque(F64, float(geometry.cells))
    f = [dr.floor((p[a] - origin[a]) / cell_m) for a in range(3)]           # the host's order of operations
    inside = active & (f[0] >= 0.0) & (f[0] < c) & (f[1] >= 0.0) & (f[1] < c) & (f[2] >= 0.0) & (f[2] < c)
    ijk = [dev.UInt32(dr.select(inside, x, 0.0)) for x in f]
    cu = dev.UInt32(c)
    return (ijk[0] * cu + ijk[1]) * cu + ijk[2], inside


def idw(grid: DeviceGrid, E, p, n, active, mu: float = 1.0):
    """Eq. 2 through G on the device: Φ(p) = Σ W q_e / Σ W over the records of p's cell, with eq. 1's
    W = (max(0, r − |p − q|) · max(0, p_n · q_n))^μ. ``p`` Point3d, ``n`` Vector3d (unit), ``active`` Bool per
    lane; returns (Φ Vector3d, weight sum Float64, records visited UInt32), evaluated; Φ = 0 where the weight sum
    is 0 (the caller falls back to the ambient function), and nothing is visited in inactive lanes."""
    dev = grid.dev
    dr, F64, U = dev.dr, dev.Float64, dev.UInt32
    cell, inside = cell_index(dev, grid.geometry, p, active)
    begin = dr.gather(U, grid.cell_start, cell, inside)
    end = dr.gather(U, grid.cell_start, cell + 1, inside)       # 0 where outside: no iteration
    visited = end - begin
    mu = float(mu)
    mu_op = dev.opaque(F64, mu)
    zero3 = dr.zeros(dev.Vector3d, dr.width(begin))

    def body(k, phi, wsum):
        j = dr.gather(U, grid.refs, k)
        q = dr.gather(dev.Vector3d, grid.position, j)
        qn = dr.gather(dev.Vector3d, grid.normal, j)
        r = dr.gather(F64, grid.range_m, j)
        e = dr.gather(dev.Vector3d, E, j)
        d0, d1, d2 = p.x - q.x, p.y - q.y, p.z - q.z
        dist = dr.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        cosn = n.x * qn.x + n.y * qn.y + n.z * qn.z
        base = dr.maximum(0.0, r - dist) * dr.maximum(0.0, cosn)
        ok = base > 0.0
        wgt = base if mu == 1.0 else dr.power(dr.select(ok, base, 1.0), mu_op)
        wsum = wsum + dr.select(ok, wgt, 0.0)
        phi = dev.Vector3d(phi.x + dr.select(ok, wgt * e.x, 0.0), phi.y + dr.select(ok, wgt * e.y, 0.0),
                           phi.z + dr.select(ok, wgt * e.z, 0.0))
        return k + 1, phi, wsum

    k, phi, wsum = dr.while_loop((dev.UInt32(begin), zero3, dr.zeros(F64, dr.width(begin))),
                                 lambda k, phi, wsum: k < end, body)
    pos = wsum > 0.0
    inv = dr.select(pos, wsum, 1.0)
    phi = dr.select(pos, dev.Vector3d(phi.x / inv, phi.y / inv, phi.z / inv), dev.Vector3d(0.0, 0.0, 0.0))
    dr.eval(phi, wsum, visited)
    return phi, wsum, visited


def joint_bilateral_upsample(dev, lo_img, lo_valid, lo_normal, lo_depth, lo_size, normal, depth, valid, size,
                             scale: int):
    """:func:`methods.rail.upsample.joint_bilateral_upsample` on the device: flat row-major arrays, ``lo_size``
    and ``size`` as (width, height); the low-resolution samples were taken at full-resolution pixels
    (i·scale, j·scale). Returns the upsampled irradiance as a Vector3f (0 at invalid pixels), evaluated."""
    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    wl, hl = lo_size
    w, h = size
    idx = dev.arange(w * h)
    row, col = idx // w, idx % w
    s = dev.opaque(F64, float(scale))
    y, x = F64(row) / s, F64(col) / s
    y0 = dr.minimum(U(dr.floor(y)), hl - 1)
    x0 = dr.minimum(U(dr.floor(x)), wl - 1)
    fy, fx = y - F64(y0), x - F64(x0)
    z = dr.select(valid, depth, 0.0)
    num = dr.zeros(dev.Vector3d, w * h)
    den = dr.zeros(F64, w * h)
    num_b = dr.zeros(dev.Vector3d, w * h)
    den_b = dr.zeros(F64, w * h)
    for dy in (0, 1):
        for dx in (0, 1):
            li = dr.minimum(y0 + dy, hl - 1) * wl + dr.minimum(x0 + dx, wl - 1)
            bil = (fy if dy else 1.0 - fy) * (fx if dx else 1.0 - fx)
            lv = dr.gather(dev.Bool, lo_valid, li)
            ok = lv & valid
            ln = dr.gather(dev.Vector3f, lo_normal, li)
            dot = (normal.x * ln.x + normal.y * ln.y) + normal.z * ln.z
            cos = dr.power(dr.maximum(0.0, dot), F(NORMAL_POWER))
            zl = dr.select(lv, dr.gather(F, lo_depth, li), 0.0)
            dz = dr.exp(-dr.abs(z - zl) / dr.maximum(F(DEPTH_SIGMA_REL) * z, 1e-6))
            wb = dr.select(ok, bil, 0.0)
            wgt = wb * F64(cos) * F64(dz)
            val = dev.Vector3d(dr.gather(dev.Vector3f, lo_img, li))
            num = num + val * wgt
            den = den + wgt
            num_b = num_b + val * wb
            den_b = den_b + wb
    out = dr.select(den > 0.0, num / dr.maximum(den, 1e-300),
                    dr.select(den_b > 0.0, num_b / dr.maximum(den_b, 1e-300), dev.Vector3d(0.0, 0.0, 0.0)))
    out = dev.Vector3f(dr.select(valid, out, dev.Vector3d(0.0, 0.0, 0.0)))
    dr.eval(out)
    return out


def shade_points(dev, q_origin, qn, v_pos, v_normal, intensity, clamp_m: float, per: int):
    """§3.2's point-cloud shading on the device (:func:`methods.rail.lighting.shade_points`): one lane per point, a
    loop over the VPLs in order, each pair's shadow ray traced where it is made (device-resident rays). The float64
    operations and the order of the sums are the host pass's (per point the VPLs in order, added to E in batches of
    ``per`` VPLs), and the rays are its rays, so E has its bits on ``llvm_ad_rgb``. Inputs are the host pass's
    (:func:`methods.rail.lighting._shading_inputs`); returns (E (N, 3) float64, shadow rays traced)."""
    from suite.core.trace.base import MAX_RAY_LENGTH

    from .lighting import SHADOW_TMAX_SCALE

    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    V3 = dev.Vector3d
    up3 = lambda a: dev.to_device(np.ascontiguousarray(a, np.float64).reshape(-1, 3), V3)  # noqa: E731
    q, n = up3(q_origin), up3(qn)
    vp, vn, inten = up3(v_pos), up3(v_normal), up3(intensity)
    n_pts, n_vpl = len(q_origin), len(v_pos)
    o_local = dev.local_f32(q)
    clamp2 = dev.opaque(F64, float(clamp_m) ** 2)
    per_op, end_op = dev.opaque(U, int(per)), dev.opaque(U, int(n_vpl))
    alpha = dev.tracer._alpha is not None
    zeros3 = dr.zeros(V3, n_pts)

    def body(j, sums, E, count, extra):
        p = dr.gather(V3, vp, j)
        m = dr.gather(V3, vn, j)
        tx, ty, tz = p.x - q.x, p.y - q.y, p.z - q.z
        d2 = (tx * tx + tz * tz) + ty * ty
        dist = dr.sqrt(dr.maximum(d2, 1e-300))
        wx, wy, wz = tx / dist, ty / dist, tz / dist
        cos_q = (wx * n.x + wz * n.z) + wy * n.y
        cos_v = -((wx * m.x + wz * m.z) + wy * m.y)
        front = (cos_q > 0.0) & (cos_v > 0.0)
        length = dr.clip(F(dist * SHADOW_TMAX_SCALE), 0.0, MAX_RAY_LENGTH)
        blocked, traced = dev.occluded_rays(o_local, dev.Vector3f(F(wx), F(wy), F(wz)), length, front)
        lit = front & ~blocked
        g = cos_q * cos_v / dr.maximum(d2, clamp2)
        i = dr.gather(V3, inten, j)
        sums = V3(sums.x + dr.select(lit, g * i.x, 0.0), sums.y + dr.select(lit, g * i.y, 0.0),
                  sums.z + dr.select(lit, g * i.z, 0.0))
        nxt = j + 1
        batch_end = (nxt % per_op == 0) | (nxt == end_op)     # a batch's sums go to E (the host pass's order)
        E = dr.select(batch_end, E + sums, E)
        sums = dr.select(batch_end, zeros3, sums)
        count = count + dr.select(front, U(1), U(0))
        if traced is not None:
            extra = extra + traced
        return nxt, sums, E, count, extra

    _, _, E, count, extra = dr.while_loop((dr.zeros(U, n_pts), zeros3, zeros3, dr.zeros(U, n_pts),
                                           dr.zeros(U, n_pts)), lambda j, *_: j < end_op, body)
    dr.eval(E, count, extra)
    rays = dev.sum_u32(count, n_vpl)
    dev.tracer.counters["rays_occluded"] += rays
    if alpha:
        dev.tracer.counters["rays_intersect"] += dev.sum_u32(extra)
    return dev.to_host(E, np.float64), rays
