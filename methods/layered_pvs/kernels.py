"""Compiled passes of the server's path tracer (§4.4) and depth peeling (§4.1.2).

Each pass replaces a chain of whole-array numpy expressions in :mod:`methods.layered_pvs.server` (``*_reference``
there) with one loop over the rays: the numpy chain made a dozen float64 temporaries, fancy-index gathers and
masks per bounce, and cost three times the backend's own time on the same rays (``splitbench bench
layered_pvs``, ``path_trace_ratio`` 0.25). Every float64 operation is written in the order of the numpy
expression it replaces, so the passes give the same bits:

* ``np.einsum("ij,ij->i", a, b)`` over 3 columns adds as ``(a0 b0 + a2 b2) + a1 b1``;
* ``.sum(axis=-1)`` and ``np.linalg.norm(axis=-1)`` over 3 columns add left to right;
* ``np.cross`` is ``a1 b2 - a2 b1`` etc. (two rounded products, then the difference).

No fast-math: LLVM then neither reorders nor contracts into FMAs, so the bits follow the source. Random numbers
still come from the method's numpy ``Generator``, in the same calls and sizes as the reference, so a seeded
update gives the same paths.
"""
from __future__ import annotations

import numpy as np

from suite.core.trace.base import MAX_RAY_LENGTH
from suite.core.trace.robust import FLOAT_SCALE, OFFSET_ULPS

INV_PI = 1.0 / np.pi


# ------------------------------------------------------------------------------------------ shared helpers

def _offset_origin(px, py, pz, nx, ny, nz, shift, offset_ulps, float_scale):
    """:func:`suite.core.trace.robust.offset_ray_origin` for one point: ``offset_ulps`` float32 ULPs of the largest
    tracing-frame coordinate (``np.spacing`` of a non-negative float32 = next float32 up minus it), at least
    ``float_scale``, along the normal."""
    mag = np.float32(max(max(abs(px - shift[0]), abs(py - shift[1])), abs(pz - shift[2])))
    ulp = np.float64(np.nextafter(mag, np.float32(np.inf)) - mag)
    step = max(offset_ulps * ulp, float_scale)
    return px + step * nx, py + step * ny, pz + step * nz


def _bounce(rows, ns, ng, p, thr, use_rr, u_rr, u_dir, shift, offset_ulps, float_scale,
            rows_out, thr_out, o64_out, d64_out, d32_out):
    """One path-tracing bounce before the closest-hit query (§4.4): Russian roulette (survival probability
    ``min(max throughput, 0.95)``, survivors' throughput divided by it) when ``use_rr``, a cosine-weighted
    direction about the shading normal, and the paths that survive both and leave above the geometric normal,
    compacted: row, throughput, float64 ray origins (offset along the geometric normal; the tracer rounds them to
    float32 in its own frame, where the offset is sized), float64 and float32 directions. Returns their count. The
    reference: the loop head of ``server.path_trace_reference`` with ``server._cosine_hemisphere``."""
    k = 0
    two_pi = 2 * np.pi
    for i in range(len(rows)):
        t0, t1, t2 = thr[i, 0], thr[i, 1], thr[i, 2]
        live = True
        if use_rr:
            q = min(max(max(t0, t1), t2), 0.95)
            live = u_rr[i] < q
            qd = max(q, 1e-12)
            t0, t1, t2 = t0 / qd, t1 / qd, t2 / qd
        # Cosine-weighted hemisphere about the shading normal (its pdf cos/pi cancels the Lambertian BRDF's).
        u0 = u_dir[i, 0]
        r = np.sqrt(u0)
        phi = two_pi * u_dir[i, 1]
        lx, ly, lz = r * np.cos(phi), r * np.sin(phi), np.sqrt(max(0.0, 1 - u0))
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        if abs(n0) > 0.9:
            a0, a1, a2 = 0.0, 1.0, 0.0
        else:
            a0, a1, a2 = 1.0, 0.0, 0.0
        c0, c1, c2 = n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0
        cl = np.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
        c0, c1, c2 = c0 / cl, c1 / cl, c2 / cl
        b0, b1, b2 = n1 * c2 - n2 * c1, n2 * c0 - n0 * c2, n0 * c1 - n1 * c0
        d0 = (lx * c0 + ly * b0) + lz * n0
        d1 = (lx * c1 + ly * b1) + lz * n1
        d2 = (lx * c2 + ly * b2) + lz * n2
        g0, g1, g2 = ng[i, 0], ng[i, 1], ng[i, 2]
        if not (live and ((d0 * g0 + d2 * g2) + d1 * g1) > 0):
            continue
        ox, oy, oz = _offset_origin(p[i, 0], p[i, 1], p[i, 2], g0, g1, g2, shift, offset_ulps, float_scale)
        rows_out[k] = rows[i]
        thr_out[k, 0], thr_out[k, 1], thr_out[k, 2] = t0, t1, t2
        o64_out[k, 0], o64_out[k, 1], o64_out[k, 2] = ox, oy, oz
        d64_out[k, 0], d64_out[k, 1], d64_out[k, 2] = d0, d1, d2
        d32_out[k, 0], d32_out[k, 1], d32_out[k, 2] = np.float32(d0), np.float32(d1), np.float32(d2)
        k += 1
    return k


def _compact_hits(prim, u, v, rows, o64, d64, thr, prim_out, u_out, v_out, rows_out, o64_out, d64_out, thr_out):
    """The rays whose closest-hit query found a triangle, compacted (in place is fine: ``k <= i``). Returns their
    count."""
    k = 0
    for i in range(len(prim)):
        if prim[i] < 0:
            continue
        prim_out[k], u_out[k], v_out[k], rows_out[k] = prim[i], u[i], v[i], rows[i]
        for c in range(3):
            o64_out[k, c] = o64[i, c]
            d64_out[k, c] = d64[i, c]
            thr_out[k, c] = thr[i, c]
        k += 1
    return k


def _choose_light(px, py, pz, u, per_point, power, centres, min_d2, cdf, pmf, w):
    """``server.LightSampler.choose`` for one point: (light index, selection probability). ``w``: scratch of one
    float64 per light."""
    n_l = len(power)
    if not per_point:
        # np.searchsorted(cdf, x, side="right"): the first index whose cdf exceeds x.
        x = u * cdf[n_l - 1]
        lo, hi = 0, n_l
        while lo < hi:
            mid = (lo + hi) // 2
            if cdf[mid] <= x:
                lo = mid + 1
            else:
                hi = mid
        j = min(lo, n_l - 1)
        return j, pmf[j]
    # Per-point irradiance bound: the weights and their total in one pass, then the cumulative sum up to the first
    # entry not below u * total (the count of entries below it, clipped to the last light), without the reference's
    # (points x lights) cumulative-sum matrix.
    tot = 0.0
    for li in range(n_l):
        dx, dy, dz = px - centres[li, 0], py - centres[li, 1], pz - centres[li, 2]
        w[li] = power[li] / max((dx * dx + dy * dy) + dz * dz, min_d2)
        tot += w[li]
    x = u * tot
    acc = 0.0
    j = n_l - 1
    for li in range(n_l):
        acc += w[li]
        if not acc < x:
            j = li
            break
    return j, w[j] / max(tot, 1e-300)


def _shade_vertex(rows, p, ng_raw, ns_raw, alb, d64, thr, u_sel, u2, per_point, power, centres, min_d2, cdf, pmf,
                  n_point, point_pos, point_int, tri, tri_n, tri_l, tri_area, shift, offset_ulps, float_scale,
                  shadow_scale, ng_out, ns_out, thr_out, sel_rows, sel_o64, sel_d32, sel_tmax32, sel_contrib):
    """A new path vertex (§4.4): normals turned toward the incoming ray (``server._facing``), throughput times the
    albedo, and next-event estimation towards one light (``server.LightSampler.sample``): for the vertices where
    the light is above the shading normal (and an area light's sample faces the vertex), the compacted shadow
    ray (float64 origin offset to the light's side of the geometric normal, rounded by the tracer in its own frame;
    float32 direction and length short of the light
    by ``shadow_scale``), the path row and the contribution ``throughput * weight * cos / pi`` it adds when the
    ray is unoccluded. Returns the number of shadow rays."""
    k = 0
    w = np.empty(len(power))
    for i in range(len(rows)):
        dx, dy, dz = d64[i, 0], d64[i, 1], d64[i, 2]
        s = (ng_raw[i, 0] * dx + ng_raw[i, 2] * dz) + ng_raw[i, 1] * dy
        flip = 1.0 if s > 0 else (-1.0 if s < 0 else 1.0)
        g0, g1, g2 = -flip * ng_raw[i, 0], -flip * ng_raw[i, 1], -flip * ng_raw[i, 2]
        n0, n1, n2 = ns_raw[i, 0], ns_raw[i, 1], ns_raw[i, 2]
        if ((n0 * g0 + n2 * g2) + n1 * g1) < 0:
            n0, n1, n2 = -n0, -n1, -n2
        ng_out[i, 0], ng_out[i, 1], ng_out[i, 2] = g0, g1, g2
        ns_out[i, 0], ns_out[i, 1], ns_out[i, 2] = n0, n1, n2
        t0, t1, t2 = thr[i, 0] * alb[i, 0], thr[i, 1] * alb[i, 1], thr[i, 2] * alb[i, 2]
        thr_out[i, 0], thr_out[i, 1], thr_out[i, 2] = t0, t1, t2
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        j, pmf_j = _choose_light(px, py, pz, u_sel[i], per_point, power, centres, min_d2, cdf, pmf, w)
        if j < n_point:
            yx, yy, yz = point_pos[j, 0], point_pos[j, 1], point_pos[j, 2]
            ex, ey, ez = yx - px, yy - py, yz - pz
            d2 = max((ex * ex + ey * ey) + ez * ez, 1e-12)
            w0 = point_int[j, 0] / d2 / pmf_j
            w1 = point_int[j, 1] / d2 / pmf_j
            w2 = point_int[j, 2] / d2 / pmf_j
            good = True
        else:
            jt = j - n_point
            su = np.sqrt(u2[i, 0])
            b1, b2 = 1 - su, u2[i, 1] * su
            # the triangle's edges in its own precision (float32 light vertices subtract in float32)
            yx = (tri[jt, 0, 0] + b1 * (tri[jt, 1, 0] - tri[jt, 0, 0])) + b2 * (tri[jt, 2, 0] - tri[jt, 0, 0])
            yy = (tri[jt, 0, 1] + b1 * (tri[jt, 1, 1] - tri[jt, 0, 1])) + b2 * (tri[jt, 2, 1] - tri[jt, 0, 1])
            yz = (tri[jt, 0, 2] + b1 * (tri[jt, 1, 2] - tri[jt, 0, 2])) + b2 * (tri[jt, 2, 2] - tri[jt, 0, 2])
            ex, ey, ez = yx - px, yy - py, yz - pz
            d2 = max((ex * ex + ey * ey) + ez * ez, 1e-12)
            sd = np.sqrt(d2)
            wx, wy, wz = ex / sd, ey / sd, ez / sd
            cos_y = -((wx * tri_n[jt, 0] + wy * tri_n[jt, 1]) + wz * tri_n[jt, 2])
            good = cos_y > 0
            f = cos_y * tri_area[jt] / d2 / pmf_j
            w0, w1, w2 = tri_l[jt, 0] * f, tri_l[jt, 1] * f, tri_l[jt, 2] * f
        ex, ey, ez = yx - px, yy - py, yz - pz
        dist = np.sqrt((ex * ex + ey * ey) + ez * ez)
        dd = max(dist, 1e-30)
        wx, wy, wz = ex / dd, ey / dd, ez / dd
        cos_x = (wx * n0 + wz * n2) + wy * n1
        if not (good and cos_x > 0):
            continue
        if ((wx * g0 + wz * g2) + wy * g1) >= 0:
            sx, sy, sz = g0, g1, g2
        else:
            sx, sy, sz = -g0, -g1, -g2
        ox, oy, oz = _offset_origin(px, py, pz, sx, sy, sz, shift, offset_ulps, float_scale)
        qx, qy, qz = (px + wx * dist) - ox, (py + wy * dist) - oy, (pz + wz * dist) - oz
        seg = np.sqrt((qx * qx + qy * qy) + qz * qz)
        c = cos_x / np.pi
        sel_rows[k] = rows[i]
        sel_o64[k, 0], sel_o64[k, 1], sel_o64[k, 2] = ox, oy, oz
        sel_d32[k, 0], sel_d32[k, 1], sel_d32[k, 2] = np.float32(wx), np.float32(wy), np.float32(wz)
        sel_tmax32[k] = np.float32(seg * shadow_scale)
        sel_contrib[k, 0], sel_contrib[k, 1], sel_contrib[k, 2] = t0 * w0 * c, t1 * w1 * c, t2 * w2 * c
        k += 1
    return k


def _add_unoccluded(sample, rows, contrib, occluded):
    """``sample[rows[~occluded]] += contrib[~occluded]`` (rows are unique within a wavefront)."""
    for i in range(len(rows)):
        if not occluded[i]:
            r = rows[i]
            for c in range(3):
                sample[r, c] += contrib[i, c]


def _shade_point_lights(p, nrm, light_pos, light_int, vis, min_d2, out):
    """:func:`suite.core.shading.shade_point_lights` for an (N, 1) G-buffer of albedo 1 without emission: per
    fragment the sum over lights of ``visible * max(n . l / |l|, 0) / d^2 * I`` (``d^2`` clamped to ``min_d2``),
    times 1/pi, rounded to float32 (``einsum("hwc,hwc->hw")`` adds as ``(x + z) + y``)."""
    inv_pi = 1.0 * INV_PI
    for i in range(len(p)):
        o0, o1, o2 = 0.0, 0.0, 0.0
        n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        for li in range(len(light_pos)):
            tx, ty, tz = light_pos[li, 0] - p[i, 0], light_pos[li, 1] - p[i, 1], light_pos[li, 2] - p[i, 2]
            dist2 = max((tx * tx + tz * tz) + ty * ty, min_d2)
            dist = np.sqrt(dist2)
            cos = max(((n0 * tx + n2 * tz) + n1 * ty) / max(dist, 1e-300), 0.0)
            f = (cos if vis[i, li] else 0.0) / max(dist2, 1e-300)
            o0 += f * light_int[li, 0]
            o1 += f * light_int[li, 1]
            o2 += f * light_int[li, 2]
        out[i, 0], out[i, 1], out[i, 2] = np.float32(o0 * inv_pi), np.float32(o1 * inv_pi), np.float32(o2 * inv_pi)


# ------------------------------------------------------------------------------------------ depth peeling

def _past(t, scale32):
    """``server.past`` for one float32 distance: ``t * (1 + PEEL_REL_EPS)`` in float32, then the next float32 up."""
    return np.nextafter(t * scale32, np.float32(np.inf))


def _path_moments(sample, direct, n, spp, illum, m1, m2):
    """Per fragment ``i``: its ``spp`` path samples (rows ``k * n + i`` of ``sample``), each with the direct light
    (float64) added, summed in sample order into the mean illumination (float32) and the first two moments of the
    luminance ``(0.2126 r + 0.7152 g) + 0.0722 b`` (``server._path_moments_reference``'s bits)."""
    for i in range(n):
        d0, d1, d2 = np.float64(direct[i, 0]), np.float64(direct[i, 1]), np.float64(direct[i, 2])
        a0 = a1 = a2 = s1 = s2 = 0.0
        for k in range(spp):
            r = k * n + i
            x0, x1, x2 = sample[r, 0] + d0, sample[r, 1] + d1, sample[r, 2] + d2
            lum = (x0 * 0.2126 + x1 * 0.7152) + x2 * 0.0722
            if k == 0:  # the first sample as it is (a sum started at 0.0 would turn -0.0 into 0.0)
                a0, a1, a2, s1, s2 = x0, x1, x2, lum, lum * lum
            else:
                a0, a1, a2, s1, s2 = a0 + x0, a1 + x1, a2 + x2, s1 + lum, s2 + lum * lum
        illum[i, 0], illum[i, 1], illum[i, 2] = np.float32(a0 / spp), np.float32(a1 / spp), np.float32(a2 / spp)
        m1[i], m2[i] = s1 / spp, s2 / spp


def _peel_hits(prim, t, u, v, idx, start, keep_mask, use_keep, k, scale32, t_out, p_out, u_out, v_out, origins, dirs,
               shift, max_length, idx_out, start_out, o_out, d_out, len_out, queue_next, c_next, idx_nx, start_nx,
               o_nx, d_nx, len_nx):
    """One closest-hit query of layer ``k`` of the depth peeling (§4.1.2) taken in: a hit on a kept triangle (any
    hit without ``use_keep``) becomes the ray's fragment of layer k, and with ``queue_next`` its ray is queued for
    layer k+1 from just past it (slots from ``c_next`` on of the ``*_nx`` query); a hit outside the PVS is stepped
    over, the ray (pixel ``idx[i]``) queued again from just past it (:func:`_queue_ray`); a miss ends the ray. The
    query's ``t`` is measured from its advanced origin: the ray's distance is ``t + start`` (the float32 sum
    ``Tracer.intersect`` makes). ``idx`` and ``start`` may be ``idx_out`` and ``start_out`` themselves (compaction
    in place: slot ``i`` is read before any slot up to it is written). Returns the number of rays to trace again
    and the next layer's count."""
    c = 0
    for i in range(len(prim)):
        f = prim[i]
        if f < 0:
            continue
        j = idx[i]
        ti = np.float32(t[i] + start[i])
        if not use_keep or keep_mask[f]:
            t_out[k, j], p_out[k, j], u_out[k, j], v_out[k, j] = ti, f, u[i], v[i]
            if queue_next:
                _queue_ray(c_next, j, _past(ti, scale32), origins, dirs, shift, max_length, idx_nx, start_nx, o_nx,
                           d_nx, len_nx)
                c_next += 1
            continue
        _queue_ray(c, j, _past(ti, scale32), origins, dirs, shift, max_length, idx_out, start_out, o_out, d_out,
                   len_out)
        c += 1
    return c, c_next


def _queue_ray(c, j, start, origins, dirs, shift, max_length, idx_out, start_out, o_out, d_out, len_out):
    """Slot ``c`` of the next query: pixel ``j``'s ray from ``start`` on, in the tracing frame as
    :func:`suite.core.trace.base.as_rays` puts it (the bits of its compiled shift pass and of its lengths): origin
    ``float32(float64(o) - shift)`` advanced by ``float32(d * start)`` in float32, length ``max_length - start``
    clipped to [0, ``max_length``]."""
    idx_out[c] = j
    start_out[c] = start
    for a in range(3):
        x = np.float32(np.float64(origins[j, a]) - shift[a])
        o_out[c, a] = np.float32(x + np.float32(dirs[j, a] * start))
        d_out[c, a] = dirs[j, a]
    len_out[c] = min(max(np.float32(max_length - start), np.float32(0.0)), max_length)


def _peel_first(origins, dirs, shift, max_length, idx_out, start_out, o_out, d_out, len_out):
    """The rays of layer 0: every pixel from its camera origin. Returns their count."""
    for j in range(len(dirs)):
        _queue_ray(j, j, np.float32(0.0), origins, dirs, shift, max_length, idx_out, start_out, o_out, d_out, len_out)
    return len(dirs)


def _gather_fragments(k, y, x, prim_l, u_l, v_l, origins, dirs, prim, u, v, o, d):
    """The layer samples of the fragments (``k``, ``y``, ``x``): triangle, barycentrics, and the ray of their pixel
    (``fragments``' gathers)."""
    w = prim_l.shape[2]
    for i in range(len(k)):
        prim[i], u[i], v[i] = prim_l[k[i], y[i], x[i]], u_l[k[i], y[i], x[i]], v_l[k[i], y[i], x[i]]
        pix = y[i] * w + x[i]
        for c in range(3):
            o[i, c] = origins[pix, c]
            d[i, c] = dirs[pix, c]


def _face_fragments(ng, ns, d, em, ng_out, ns_out, em_out, front):
    """``server._facing`` and the front-facing emission per fragment, with its bits: the geometric normal turned
    towards the ray's origin (``-sign(ng . d) ng``, sign 0 taken as 1), the shading normal onto its side, emission
    kept on front faces only (einsum's dot order)."""
    for i in range(ng.shape[0]):
        dot = (ng[i, 0] * d[i, 0] + ng[i, 2] * d[i, 2]) + ng[i, 1] * d[i, 1]
        flip = 1.0 if dot > 0 else (-1.0 if dot < 0 else (1.0 if dot == 0 else dot))
        for c in range(3):
            ng_out[i, c] = -flip * ng[i, c]
        side = (ns[i, 0] * ng_out[i, 0] + ns[i, 2] * ng_out[i, 2]) + ns[i, 1] * ng_out[i, 1]
        front[i] = flip < 0
        for c in range(3):
            ns_out[i, c] = -ns[i, c] if side < 0 else ns[i, c]
            em_out[i, c] = em[i, c] if front[i] else 0.0


def _reproject_match(x_world, xy, z, prim, eye, tri_normals, depth, depth_tol, pix_angle, width, height, ix_out,
                     iy_out, layer_out, inside_out, matched_out):
    """Algorithm 4.1 on the client, per visible point (§4.3.2): its pixel in the update's view (inside the enlarged
    frustum or not), and the layer whose depth there is closest to the point's distance from the update's eye, a
    match when within the depth tolerance (relative ``depth_tol``, plus the depth change across one layer pixel on
    a surface at the point's slant). The float64 operations of the numpy expressions it replaced, in their order."""
    L = depth.shape[0]
    for i in range(len(prim)):
        fx, fy = np.floor(xy[i, 0]), np.floor(xy[i, 1])
        inside = z[i] > 0 and fx >= 0 and fx < width and fy >= 0 and fy < height
        inside_out[i] = inside
        matched_out[i] = False
        if not inside:
            continue
        ix, iy = int(fx), int(fy)
        t0, t1, t2 = x_world[i, 0] - eye[0], x_world[i, 1] - eye[1], x_world[i, 2] - eye[2]
        dist = np.sqrt((t0 * t0 + t1 * t1) + t2 * t2)
        md = max(dist, 1e-30)
        f = prim[i]
        cos = abs((t0 / md * tri_normals[f, 0] + t1 / md * tri_normals[f, 1]) + t2 / md * tri_normals[f, 2])
        tol = dist * (depth_tol + 1.5 * pix_angle * np.sqrt(max(1 - cos * cos, 0.0)) / max(cos, 0.05))
        best, layer = np.inf, 0
        for k in range(L):
            dl = depth[k, iy, ix]
            e = abs(np.float64(dl) - dist) if np.isfinite(dl) else np.inf
            if e < best:
                best, layer = e, k
        ix_out[i], iy_out[i], layer_out[i] = ix, iy, layer
        matched_out[i] = best <= tol


_compiled = None


def jit():
    """The passes compiled (numba, on first use; cached on disk)."""
    global _compiled
    if _compiled is None:
        import numba

        # error_model="numpy": IEEE division (the divisors are clamped or unit lengths) without per-division checks.
        j = numba.njit(cache=True, nogil=True, error_model="numpy")
        # the helpers are compiled first: the passes that call them are typed against the compiled versions
        global _offset_origin, _choose_light, _past, _queue_ray
        _offset_origin, _choose_light, _past, _queue_ray = j(_offset_origin), j(_choose_light), j(_past), j(_queue_ray)
        _compiled = {f.__name__: j(f) for f in (_bounce, _compact_hits, _shade_vertex, _add_unoccluded, _peel_hits,
                                                 _peel_first, _shade_point_lights, _reproject_match, _path_moments,
                                                 _gather_fragments, _face_fragments)}
    return _compiled


OFFSET = (float(OFFSET_ULPS), float(FLOAT_SCALE))


def warm_up() -> None:
    """Compiles (or loads) every pass for the argument types the server gives them, on one-row arrays."""
    k = jit()
    f64, f32, i64 = np.zeros((1, 3)), np.zeros((1, 3), np.float32), np.zeros(1, np.int64)
    one, one32, b = np.ones(1), np.ones(1, np.float32), np.zeros(1, np.bool_)
    shift = np.zeros(3)
    k["_bounce"](i64, f64, f64, f64, f64.copy(), True, one, np.zeros((1, 2)), shift, *OFFSET, i64.copy(), f64.copy(),
                 f64.copy(), f64.copy(), f32.copy())
    k["_compact_hits"](np.zeros(1, np.int32), one32, one32, i64, f64, f64, f64, np.zeros(1, np.int32), one32.copy(),
                       one32.copy(), i64.copy(), f64.copy(), f64.copy(), f64.copy())
    for per_point in (True, False):
        k["_shade_vertex"](i64, f64, f64, f64, f32, f64, f64, one, np.zeros((1, 2)), per_point, one, f64, 1.0, one, one,
                           1, f64, f64, np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), shift,
                           *OFFSET, 1.0, f64.copy(), f64.copy(), f64.copy(), i64.copy(), f64.copy(), f32.copy(),
                           np.zeros(1, np.float32), f64.copy())
    k["_add_unoccluded"](f64.copy(), i64, f64, b)
    k["_path_moments"](f64, f64, 1, 1, f32.copy(), one.copy(), one.copy())
    k["_shade_point_lights"](f64, f64, f64, f64, np.zeros((1, 1), np.bool_), 1.0, f32.copy())
    big = MAX_RAY_LENGTH
    peel_out = (i64.copy(), one32.copy(), f32.copy(), f32.copy(), one32.copy())
    for prim_type in (np.int32, np.int64):  # the tracers' hits, and the client geometry's
        k["_peel_hits"](np.zeros(1, prim_type), one32, one32, one32, i64, one32, b, True, 0, np.float32(1),
                        np.zeros((1, 1), np.float32), np.zeros((1, 1), np.int64), np.zeros((1, 1), np.float32),
                        np.zeros((1, 1), np.float32), f32, f32, shift, big, *peel_out, True, 0, *peel_out)
    k["_peel_first"](f32, f32, shift, big, *peel_out)
