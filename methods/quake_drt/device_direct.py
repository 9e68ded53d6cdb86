"""Seed 001's direct-illumination stage (§4.1, §6.6, Algorithm 6.2) as one Dr.Jit kernel on the run's Mitsuba variant
(``llvm_ad_rgb`` on the CPU, ``cuda_ad_rgb`` on the GPU): the device twin of :func:`methods.quake_drt.direct.shade`
for Lambertian shading points.

One lane per shading point, the points ordered by their light-table row where they take several lights
(:func:`lane_order`). A symbolic loop runs over the point's light samples; each iteration picks a light of the point's
table row (all of them, k distinct ones uniformly by Floyd's algorithm, or k by the row's power or irradiance
distribution), samples a point on it, makes the shadow ray, traces it and adds the unoccluded contribution to the
point's sum. So a packet of the loop holds neighbouring points of one row and, with every light chosen, one light
(more coherent rays than the host's point-major chunks), and no ray ever leaves device memory.

Every operation is the host kernel's (:func:`methods.quake_drt.direct._generate` and ``_accumulate``) in the same
float64 order: the PCG random numbers of (point seed, dimension), the robust origin, the horizon and emitter tests,
the float32 ray, and the sum of the point's unoccluded samples in sample order, so the illumination equals the host
stage's bit for bit on ``llvm_ad_rgb`` (tests/methods/quake_drt/test_device_direct.py). Floyd's duplicate test needs
the point's earlier choices; instead of storing them, sample ``m`` asks whether its candidate ``t`` equals an earlier
candidate (recomputed from its random number) or is the stand-in ``j_m' = n - k + m'`` of an earlier duplicate (one
bit per sample in 64-bit words). Both together are exactly "``t`` was chosen before".

Shadow rays through the primary stage's overlays (faces that cast no shadow) are re-resolved, where the backend finds
them blocked, by a closest-hit walk past those faces: :func:`methods.quake_drt.primary.walk_past`'s steps.
"""
from __future__ import annotations

import numpy as np

from methods.quake_drt.primary import MAX_OVERLAY_LAYERS
from methods.quake_drt.rng import DIM_LIGHTS
from suite.core.device.context import packet_rows
from suite.core.device.rng import pcg as _pcg  # rng.pcg_np on UInt32 lanes
from suite.core.shading import SHADOW_TMAX_SCALE
from suite.core.trace.alpha import MAX_ALPHA_LAYERS
from suite.core.trace.base import MAX_RAY_LENGTH

INV_PI = 0.3183098861837907  # direct._generate's literal 1 / pi
LIGHT_RECORD = 8  # float64 values per light record
TRI_RECORD = 16  # float64 values per light triangle record (a power of two: one packet gather)


def _uniform(dev, seed, dim):
    """:func:`methods.quake_drt.rng.uniform_np`: a float64 in [0, 1) with 24 random bits."""
    U = dev.UInt32
    h = _pcg(dev, seed ^ _pcg(dev, U(dim) + 0x9E3779B9))
    return dev.Float64(h >> 8) * (1.0 / 16777216.0)


def _find(dev, cdf, a, n, u, active):
    """First j in [0, n) with ``cdf[a + j] > u``, clamped to n - 1 (``direct._find``'s binary search)."""
    dr, U = dev.dr, dev.UInt32
    lo = dr.zeros(U, dr.width(u))
    hi = dr.select(active & (n > 0), n - 1, 0)

    def body(lo, hi):
        mid = (lo + hi) // 2
        right = dr.gather(dev.Float64, cdf, a + mid, lo < hi) > u
        return dr.select(lo < hi, dr.select(right, lo, mid + 1), lo), dr.select((lo < hi) & right, mid, hi)

    lo, hi = dr.while_loop((lo, hi), lambda lo, hi: lo < hi, body)
    return lo


class _Tables:
    """The lights and the light table on the device, made per call (a few kB; counted copies)."""

    def __init__(self, dev, lights, table, row_cdf, mode: str):
        from methods.quake_drt.lights import POINT

        self.row_lights = dev.to_device(_nonempty(table.row_lights, np.uint32), dev.UInt32)  # every row may be empty
        self.row_cdf = dev.to_device(_nonempty(row_cdf, np.float64), dev.Float64) if mode != "uniform" else None
        vec3 = lambda a: np.asarray(a, np.float64).reshape(-1, 3)  # noqa: E731
        # one 8-value record per light (position, colour, area, 1 for a point light), read by one packet gather
        self.light_rec = dev.to_device(packet_rows([vec3(lights.position), vec3(lights.rgb), lights.area,
                                                    lights.kind == POINT], np.float64, LIGHT_RECORD, 1), dev.Float64)
        self.tri_off = dev.to_device(np.asarray(lights.tri_offsets, np.uint32), dev.UInt32)
        # one 16-value record per triangle (p0, e1, e2, normal, padding): a packet gather reads it in a few vector
        # loads where twelve scalar gathers cost a gather instruction each
        self.tri_rec = dev.to_device(packet_rows([vec3(a) for a in (lights.tri_p0, lights.tri_e1, lights.tri_e2,
                                                                    lights.tri_normal)], np.float64, TRI_RECORD, 1),
                                     dev.Float64)
        self.tri_cdf = dev.to_device(_nonempty(lights.tri_cdf, np.float64), dev.Float64)
        self.rep_tri = dev.to_device(np.maximum(np.asarray(lights.rep_tri, np.int64), 0).astype(np.uint32), dev.UInt32)


def lane_order(rows: np.ndarray) -> np.ndarray:
    """The points' lane order: by light-table row, stably (points of one row keep their pixel order). A point's loop
    runs as many iterations as its row chooses lights, and iteration ``q`` takes the row's ``q``-th light (k = 0), so
    the lanes of a packet then run the same number of iterations (a packet loops until its last lane is done) and
    trace towards the same light together. The sort is a radix sort of 16-bit keys where the rows fit."""
    rows = np.asarray(rows)
    return np.argsort(rows.astype(np.uint16) if rows.max(initial=0) < 1 << 16 else rows, kind="stable")


def _nonempty(a, dtype) -> np.ndarray:
    """``a`` as ``dtype``, with one zero row when empty (a gather needs a non-empty source; every such gather is
    masked off)."""
    a = np.asarray(a, dtype)
    return a if len(a) else np.zeros((1,) + a.shape[1:], dtype)


def shade(dev, points, lights, table, rows: np.ndarray, k: int, mode: str, soft: bool, min_distance: float,
          skip_faces=None, row_cdf=None, record: list | None = None):
    """(N, 3) float64 illumination of the Lambertian ``points`` and (shadow rays, unoccluded rays, closest-hit queries):
    :func:`methods.quake_drt.direct.shade`'s ``out`` and counts for them. ``record``: a list that receives the shadow
    rays instead, per loop iteration (``("o", Ray3f)``, compacted to the lanes that trace; the benchmark's raw
    replay), and the illumination is not computed."""
    dr, F64, U = dev.dr, dev.Float64, dev.UInt32
    n_pts = len(points)
    if not bool(np.all(points.lambert)):
        raise ValueError("the device direct stage shades Lambertian points only")
    rows = np.asarray(rows, np.int64)
    row_a = np.asarray(table.row_offsets, np.int64)[rows]
    row_n = np.asarray(table.row_offsets, np.int64)[rows + 1] - row_a
    take_host = row_n if k == 0 else np.minimum(row_n, k)
    max_take = int(take_host.max(initial=0))
    tab = _Tables(dev, lights, table, row_cdf, mode)
    p = dev.to_device(np.asarray(points.p, np.float64), dev.Vector3d)
    ng = dev.to_device(np.asarray(points.ng, np.float64), dev.Vector3d)
    ns = dev.to_device(np.asarray(points.ns, np.float64), dev.Vector3d)
    seed = dev.to_device(np.asarray(points.seed, np.uint32), U)
    a = dev.to_device(row_a.astype(np.uint32), U)
    n = dev.to_device(row_n.astype(np.uint32), U)
    # Lanes in row order where a point takes more than one light (lane_order; with one each, every packet loops once
    # anyway): the points' data gathered in that order in the kernel, the sums scattered back to the points' order.
    lane = dev.to_device(lane_order(rows).astype(np.uint32), U) if max_take > 1 else None
    if lane is not None:
        p, ng, ns = (dr.gather(dev.Vector3d, v, lane) for v in (p, ng, ns))
        seed, a, n = (dr.gather(U, v, lane) for v in (seed, a, n))
    skip = None if skip_faces is None else dev.to_device(np.asarray(skip_faces, np.uint32), U)
    take = n if k == 0 else dr.minimum(n, k)
    subsample = take < n  # k < n: k of the n lights (all of them otherwise, weight 1)
    o64 = dev.offset_origin(p, ng)  # once per point (direct._generate: the robust origin along ng)
    o_local = dev.local_f32(o64)
    min_d2 = float(min_distance) ** 2
    words = max(1, -(-int(k) // 64))  # Floyd's duplicate bits, one per sample
    U64 = dev.m.UInt64
    k_mem = dev.opaque(F64, float(k))

    def sample(q, dup):
        """Sample ``q`` of every point: (active, tracing-frame ray, weight (Vector3d), updated duplicate words)."""
        live = q < take
        # -- the light (direct._choose) -----------------------------------------------------------------------
        j_all = q  # every candidate: the light's own index picks its random numbers
        valid = live
        weight = dr.ones(F64, n_pts)
        dimbase = U(DIM_LIGHTS) + 4 * q
        if k == 0:
            j = j_all  # every candidate of every row (k = 0 never subsamples)
        elif mode == "uniform":
            # Floyd: j = n - k + q, t uniform in [0, j]; t chosen before -> j. "Before" is an earlier candidate equal
            # to t, or an earlier duplicate whose stand-in n - k + m' is t.
            jq = n - k + q
            u = _uniform(dev, seed, dimbase)
            t = dr.minimum(U(u * F64(jq + 1)), jq)
            sub = live & subsample

            def earlier(m, hit):
                jm = n - k + m
                tm = dr.minimum(U(_uniform(dev, seed, U(DIM_LIGHTS) + 4 * m) * F64(jm + 1)), jm)
                return m + 1, hit | (tm == t)

            _, seen = dr.while_loop((dr.zeros(U, n_pts), dr.zeros(dev.Bool, n_pts)),
                                    lambda m, hit: sub & (m < q), earlier)
            base = n - k
            mprime = t - base
            as_stand_in = dr.zeros(dev.Bool, n_pts)
            for w in range(words):
                in_word = (t >= base) & (mprime < q) & (mprime // 64 == w)
                as_stand_in |= in_word & (((dup[w] >> U64(mprime % 64)) & U64(1)) != U64(0))
            is_dup = sub & (seen | as_stand_in)
            dup = [dr.select(is_dup & (q // 64 == w), dup[w] | (U64(1) << U64(q % 64)), dup[w]) for w in range(words)]
            j_sub = dr.select(is_dup, jq, t)
            j = dr.select(subsample, j_sub, j_all)
            # float division (5 lights to 2 weigh 2.5) by k in memory: Dr.Jit turns a division by a literal into a
            # product with its reciprocal, which differs from n / k in the last bit
            weight = dr.select(subsample, F64(n) / k_mem, weight)
        elif mode in ("power", "irradiance"):
            sub = live & subsample
            j_sub = _find(dev, tab.row_cdf, a, n, _uniform(dev, seed, dimbase), sub)
            pj = dr.gather(F64, tab.row_cdf, a + j_sub, sub) - \
                dr.select(j_sub > 0, dr.gather(F64, tab.row_cdf, a + j_sub - 1, sub & (j_sub > 0)), 0.0)
            valid = live & (~subsample | (pj > 0.0))
            j = dr.select(subsample, j_sub, j_all)
            weight = dr.select(subsample, 1.0 / (float(k) * pj), weight)
        else:
            raise ValueError(f"unknown light sampling mode '{mode}'")
        light = dr.gather(U, tab.row_lights, a + j, valid)
        dimbase = U(DIM_LIGHTS) + 4 * light if k == 0 else dr.select(subsample, dimbase, U(DIM_LIGHTS) + 4 * light)
        # -- the point on the light (direct._generate) --------------------------------------------------------
        rec = dr.gather(dev.m.ArrayXf64, tab.light_rec, light, valid, shape=(LIGHT_RECORD, n_pts))
        is_point = rec[7] != 0.0
        on_area = valid & ~is_point

        def area_point(on_area):
            """The point on the area light and the light's normal (the lanes of ``on_area``)."""
            if soft:
                ta = dr.gather(U, tab.tri_off, light, on_area)
                tn = dr.gather(U, tab.tri_off, light + 1, on_area) - ta
                tri = ta + _find(dev, tab.tri_cdf, ta, tn, _uniform(dev, seed, dimbase + 1), on_area)
                su = dr.sqrt(_uniform(dev, seed, dimbase + 2))
                b1 = 1.0 - su
                b2 = _uniform(dev, seed, dimbase + 3) * su
            else:
                tri = dr.gather(U, tab.rep_tri, light, on_area)
                b1 = b2 = F64(1.0 / 3.0)
            r = dr.gather(dev.m.ArrayXf64, tab.tri_rec, tri, on_area, shape=(TRI_RECORD, n_pts))
            p0, e1, e2, ny = r[0:3], r[3:6], r[6:9], r[9:12]
            return (*[p0[c] + b1 * e1[c] + b2 * e2[c] for c in range(3)], *ny[0:3])

        if lane is not None:
            # Only in the packets that sample an area light: in lane order (lane_order) a packet's lanes mostly take
            # the same light, and a point light's packet skips the triangle's choice, its record and random numbers.
            zero = dr.zeros(F64, n_pts)
            *y, ny0, ny1, ny2 = dev.where_any(on_area, area_point, rec[0], rec[1], rec[2], zero, zero, zero)
        else:  # lanes in the points' order mix the kinds: every packet would take the area light's branch anyway
            *y_area, ny0, ny1, ny2 = area_point(on_area)
            y = [dr.select(is_point, rec[c], y_area[c]) for c in range(3)]
        ny = (ny0, ny1, ny2)
        tx, ty, tz = y[0] - o64.x, y[1] - o64.y, y[2] - o64.z
        d2 = tx * tx + ty * ty + tz * tz
        dist = dr.sqrt(d2)
        inv = 1.0 / dr.maximum(dist, 1e-30)
        dx, dy, dz = tx * inv, ty * inv, tz * inv
        above = dx * ng.x + dy * ng.y + dz * ng.z > 0.0  # else the surface shadows itself
        cos_x = dx * ns.x + dy * ns.y + dz * ns.z
        g = weight / dr.maximum(d2, min_d2)
        cos_y = -(dx * ny[0] + dy * ny[1] + dz * ny[2])
        facing = is_point | (cos_y > 0.0)  # else behind the one-sided emitter
        g = dr.select(is_point, g, g * (cos_y * rec[6]))
        g = g * (cos_x * INV_PI)
        active = valid & above & (cos_x > 0.0) & facing
        d = dev.Vector3f(dev.Float(dx), dev.Float(dy), dev.Float(dz))
        length = dr.maximum(dev.Float(dist * SHADOW_TMAX_SCALE), 0.0)
        return active, d, length, dev.Vector3d(g * rec[3], g * rec[4], g * rec[5]), dup

    dup0 = [dr.zeros(U64, n_pts) for _ in range(words)]
    if record is not None:
        dup = dup0
        for q in range(max_take):
            active, d, length, _, dup = sample(dr.full(U, q, n_pts), dup)
            dr.eval(dup)
            if dr.any(active):
                record.append(("o", dev.compacted_ray(active, o_local, d, length)))
        return None, 0, 0, 0

    def body(q, acc, rays, visible, extra, dup):
        active, d, length, w, dup = sample(q, dup)
        blocked, traced = dev.occluded_rays(o_local, d, length, active)
        if traced is not None:
            extra = extra + traced
        if skip is not None:
            blocked, walked = _walk_past(dev, o_local, d, length, skip, blocked)
            extra = extra + walked
        lit = active & ~blocked
        acc = dev.Vector3d(acc.x + dr.select(lit, w.x, 0.0), acc.y + dr.select(lit, w.y, 0.0),
                           acc.z + dr.select(lit, w.z, 0.0))
        return (q + 1, acc, rays + dr.select(active, U(1), U(0)), visible + dr.select(lit, U(1), U(0)), extra,
                dup)

    state = (dr.zeros(U, n_pts), dr.zeros(dev.Vector3d, n_pts), dr.zeros(U, n_pts), dr.zeros(U, n_pts),
             dr.zeros(U, n_pts), dup0)
    _, acc, rays, visible, extra, _ = dr.while_loop(state, lambda q, *_: q < take, body)
    if lane is not None:  # back in the points' order
        sums = dr.zeros(dev.Vector3d, n_pts)
        dr.scatter(sums, acc, lane)
        acc = sums
    dev.eval(acc, rays, visible, extra)
    out = dev.to_host(acc, np.float64)
    bound = max(max_take, 1) * (MAX_ALPHA_LAYERS + 2) * (MAX_OVERLAY_LAYERS + 1)
    return out, dev.sum_u32(rays, max_take), dev.sum_u32(visible, max_take), dev.sum_u32(extra, bound)


def _walk_past(dev, o_local, d, length, skip, blocked):
    """(still blocked, closest-hit queries per lane) of shadow rays the backend found ``blocked``, after a closest-hit
    walk past the faces ``skip`` marks (UInt32 per face): :func:`methods.quake_drt.primary.walk_past` on the device,
    in its float64 steps (world origin, ``start`` just past each skipped hit, at most ``MAX_OVERLAY_LAYERS`` of them;
    a ray with more counts as unblocked)."""
    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    s = [float(x) for x in dev.tracer.shift]
    o = dev.Point3d(F64(o_local.x) + s[0], F64(o_local.y) + s[1], F64(o_local.z) + s[2])
    d64 = dev.Vector3d(d)
    tmax = F64(length)
    n = dr.width(d)

    def body(start, todo, prim_out, layers, traced):
        org = dev.Point3d(o.x + d64.x * start, o.y + d64.y * start, o.z + d64.z * start)
        rem = dr.clip(F(dr.maximum(tmax - start, 0.0)), 0.0, float(MAX_RAY_LENGTH))
        t, prim, _, _, tr = dev.closest(dev.local_f32(org), d, rem, todo)
        traced = traced + (dr.select(todo, U(1), U(0)) if tr is None else dr.select(todo, tr, U(0)))
        t_all = start + F64(t)
        hit = todo & (prim >= 0)
        sk = hit & (dr.gather(U, skip, U(dr.maximum(prim, 0)), hit) != 0)
        done = todo & ~sk
        prim_out = dr.select(done, prim, prim_out)
        start = dr.select(sk, t_all + 1e-5 * (1.0 + t_all), start)
        return start, sk, prim_out, layers + 1, traced

    state = (dr.zeros(F64, n), dev.Bool(blocked), dr.full(dev.Int32, -1, n), dr.zeros(U, n), dr.zeros(U, n))
    _, todo, prim, _, traced = dr.while_loop(
        state, lambda start, todo, p, layers, tr: todo & (layers < MAX_OVERLAY_LAYERS + 1), body)
    return ~todo & (prim >= 0) & blocked, traced
