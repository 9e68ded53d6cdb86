"""The secondary ray stage's specular chains (seed 001 §4.1, §6.5: mirrors, glass and water to depth 5) on the run's
Mitsuba variant: the device twin of :func:`methods.quake_drt.secondary._chains` with the compiled branches
(:class:`methods.quake_drt.secondary._CompiledBranches`).

A wavefront per depth, every array in device memory: each chain's branches (the conductor Fresnel reflection of a
mirror; the reflection and refraction of glass and water with the dielectric Fresnel term, or one of them picked by
the chain's random number), the rays of the kept branches in the host pass's order (by material, then branch, then
chain: an order found on the host from a few bytes per chain), their offset origins, the closest hits with the alpha
walk, the surfaces through the G-buffer's ``hit_surface`` with float64 barycentrics (the primary stage's surface pass),
and the split into shading points (diffuse, glossy) and the chains that go on (mirror, glass). Every operation is the
host pass's in the same float64 order, so on ``llvm_ad_rgb`` the points, their order, the emission and the query
counts equal the host stage's bit for bit (tests/methods/quake_drt/test_device_secondary.py).

The chains run there on ``cuda_ad_rgb`` (:data:`DEVICES`); on ``llvm_ad_rgb`` the host's compiled passes are faster,
and the tests run this wavefront there to hold it to the host's bits. What comes back to the host, per depth: the
shading points (the direct stage and the guides read them there) and the emission the chains collected, as (pixel,
weighted emission) rows of the surfaces that emit, summed on the host in ray order (a device scatter-add would sum a
pixel's rays in an unspecified order). Chains through transparent
overlays (the walk records layers for the host) and glossy reflections (the cone's trigonometry is numpy's) keep the
host path.
"""
from __future__ import annotations

import numpy as np

from methods.quake_drt.device_direct import _pcg, _uniform
from methods.quake_drt.direct import ShadingPoints
from methods.quake_drt.rng import DIM_SECONDARY
from suite.core.trace.base import MAX_RAY_LENGTH


# The devices the chains run on in a frame. On llvm_ad_rgb they gain nothing over the host's compiled passes: the
# wavefront traces about a thousand Dr.Jit operations from Python and launches about 110 kernels per call whatever the
# size (gallery on 2 cores, interleaved: 19-21 ms against 18-19 ms on the host at 320x180, of which 7 ms run in
# kernels; 49-51 ms for both at 640x360; 99 against 105 ms at 960x540), and a recorded function (dr.freeze) records
# afresh for every new array width, which a wavefront's depths all have.
DEVICES = ("cuda",)


def available(tracer, glossy: bool, skip_faces) -> bool:
    """Whether the device chains serve this stage: a Dr.Jit tracer on one of :data:`DEVICES`, no glossy cone, no
    overlays."""
    dev = getattr(tracer, "device", None)
    return dev is not None and dev.name in DEVICES and not glossy and skip_faces is None


class _Tables:
    """The branches' per-material tables on the device (:class:`~methods.quake_drt.secondary._CompiledBranches`)."""

    def __init__(self, dev, branches):
        b = branches
        self.kind = dev.to_device(b.kind.astype(np.int32), dev.Int32)
        self.twosided = dev.to_device(b.twosided, dev.Bool)
        self.cond_eta = dev.to_device(b.cond_eta, dev.Vector3d)
        self.cond_k = dev.to_device(b.cond_k, dev.Vector3d)
        self.spec_r = dev.to_device(b.spec_r, dev.Vector3d)
        self.spec_t = dev.to_device(b.spec_t, dev.Vector3d)
        self.eta = dev.to_device(b.eta, dev.Float64)
        self.spec = dev.to_device(b.spec, dev.Bool)
        self.lambert = dev.to_device(b.lambert, dev.Bool)
        self.normal_mode = dev.to_device(b.normal_mode.astype(np.int32), dev.Int32)
        self.seeds = dev.to_device(b.seeds, dev.UInt32)
        self.one = dev.opaque(dev.Float64, 1.0)  # 1 / x as a division (a literal numerator may become a reciprocal)


def _dot(a, b):
    """(x + y) + z, the host pass's order."""
    return (a.x * b.x + a.y * b.y) + a.z * b.z


def _max0(dr, x):
    """``np.maximum(x, 0.0)`` (NaN stays NaN)."""
    return dr.select((x >= 0.0) | dr.isnan(x), x, 0.0)


def _fresnel_conductor(dev, cos_i, eta_r, eta_i):
    """:func:`suite.core.bsdf.fresnel_conductor` of one channel, its operations in order."""
    dr = dev.dr
    c2 = cos_i * cos_i
    s2 = 1.0 - c2
    s4 = s2 * s2
    temp_1 = eta_r * eta_r - eta_i * eta_i - s2
    a_2_pb_2 = dr.sqrt(_max0(dr, temp_1 * temp_1 + 4.0 * eta_i * eta_i * eta_r * eta_r))
    a = dr.sqrt(_max0(dr, 0.5 * (a_2_pb_2 + temp_1)))
    term_1 = a_2_pb_2 + c2
    term_2 = 2.0 * cos_i * a
    r_s = (term_1 - term_2) / (term_1 + term_2)
    term_3 = a_2_pb_2 * c2 + s4
    term_4 = term_2 * s2
    r_p = r_s * (term_3 - term_4) / (term_3 + term_4)
    return 0.5 * (r_s + r_p)


def _fresnel_dielectric(dev, tb, cos_i, eta):
    """``secondary._fresnel_dielectric1``: (F, cos_theta_t, eta_ti)."""
    dr = dev.dr
    outside = cos_i >= 0.0
    inv_eta = tb.one / eta
    eta_it = dr.select(outside, eta, inv_eta)
    eta_ti = dr.select(outside, inv_eta, eta)
    cos_theta_t_sqr = 1.0 - (1.0 - cos_i * cos_i) * (eta_ti * eta_ti)
    cos_i_abs = dr.abs(cos_i)
    cos_t_abs = dr.sqrt(_max0(dr, cos_theta_t_sqr))
    a_s = (cos_i_abs - eta_it * cos_t_abs) / (cos_i_abs + eta_it * cos_t_abs)
    a_p = (cos_t_abs - eta_it * cos_i_abs) / (cos_t_abs + eta_it * cos_i_abs)
    r = dr.select(eta == 1.0, 0.0, dr.select(cos_i_abs == 0.0, 1.0, 0.5 * (a_s * a_s + a_p * a_p)))
    return r, dr.select(outside, -cos_t_abs, cos_t_abs), eta_ti


def _stream(dev, tb, pixel, path):
    """The chain's seed: the pixel's, or ``rng.stream_np(seed, path)`` past the first interaction."""
    seed = dev.dr.gather(dev.UInt32, tb.seeds, pixel)
    return seed, _pcg(dev, seed ^ (path * 0x85EBCA6B))


def _branches(dev, tb, v, all_branches: bool, dim: int):
    """Both branches of every chain of ``v``: per branch (0 reflection, 1 refraction) the unnormalised direction,
    the weight (Vector3d) and whether it is kept (``_branch_pass``'s first loop)."""
    dr, V3 = dev.dr, dev.Vector3d
    mid = v["material"]
    w = -v["d"]
    n = V3(v["ns"])
    cos_i = _dot(w, n)
    mirror = dr.gather(dev.Int32, tb.kind, mid) == 0
    # mirror: the reflection about the (two-sided: viewer-side) shading normal
    two_sided = mirror & dr.gather(dev.Bool, tb.twosided, mid)
    n_m = dr.select(two_sided & (cos_i < 0), -n, n)
    cos_m = dr.select(two_sided, dr.abs(cos_i), cos_i)
    eta_c, k_c = dr.gather(V3, tb.cond_eta, mid), dr.gather(V3, tb.cond_k, mid)
    spec_r, spec_t = dr.gather(V3, tb.spec_r, mid), dr.gather(V3, tb.spec_t, mid)
    w_m = V3(*[_fresnel_conductor(dev, cos_m, eta_c[c], k_c[c]) * spec_r[c] for c in range(3)])
    dt_m = 2.0 * _dot(w, n_m)
    wo_m = V3(dt_m * n_m.x - w.x, dt_m * n_m.y - w.y, dt_m * n_m.z - w.z)
    keep_m = (cos_m > 0) & ((w_m.x > 0) | (w_m.y > 0) | (w_m.z > 0))
    # glass / water: reflection (weight F) and refraction (weight (1 - F) eta^2 T)
    f, cos_t, eta_ti = _fresnel_dielectric(dev, tb, cos_i, dr.gather(dev.Float64, tb.eta, mid))
    if all_branches:
        r_w = V3(*[f * spec_r[c] for c in range(3)])
        t_w = V3(*[(1.0 - f) * eta_ti * eta_ti * spec_t[c] for c in range(3)])
    else:
        seed, derived = _stream(dev, tb, v["pixel"], v["path"])
        pick = _uniform(dev, dr.select(v["path"] != 0, derived, seed), dim) < f
        r_w = dr.select(pick, spec_r, V3(0.0))
        t_w = dr.select(pick, V3(0.0), V3(*[eta_ti * eta_ti * spec_t[c] for c in range(3)]))
    dt = cos_i
    k2 = 2.0 * dt
    wo_r = V3(k2 * n.x - w.x, k2 * n.y - w.y, k2 * n.z - w.z)
    kt = dt * eta_ti + cos_t
    wo_t = V3(n.x * kt - w.x * eta_ti, n.y * kt - w.y * eta_ti, n.z * kt - w.z * eta_ti)
    keep_r = (f > 0) & ((r_w.x > 0) | (r_w.y > 0) | (r_w.z > 0))
    keep_t = (f < 1) & ((t_w.x > 0) | (t_w.y > 0) | (t_w.z > 0))
    return ((dr.select(mirror, wo_m, wo_r), dr.select(mirror, w_m, r_w), dr.select(mirror, keep_m, keep_r)),
            (wo_t, t_w, ~mirror & keep_t))


def _rays(dev, tb, v, all_branches: bool, dim: int):
    """The continuation rays of the chains ``v`` in ``_branch_pass``'s order (material, branch, chain): a dict of
    pixel, thr, path, length, org (Point3d, offset origins) and dirs (Vector3d, unit), or None when there are none.
    The order is found on the host from the kept flags and materials (a few bytes per chain), so one gather per
    field makes the rays."""
    dr, V3, U = dev.dr, dev.Vector3d, dev.UInt32
    (wo_r, w_r, keep_r), (wo_t, w_t, keep_t) = _branches(dev, tb, v, all_branches, dim)
    dev.eval(wo_r, w_r, keep_r, wo_t, w_t, keep_t)
    m = dr.width(v["pixel"])
    keep = np.concatenate([dev.to_host(keep_r, bool), dev.to_host(keep_t, bool)])
    sel = np.nonzero(keep)[0]
    if len(sel) == 0:
        return None
    material = dev.to_host(v["material"], np.int64)
    key = 2 * np.concatenate([material, material]) + (np.arange(2 * m) >= m)
    order = sel[np.argsort(key[sel], kind="stable")]  # by material, then branch, then chain
    j = dev.to_device(order.astype(np.uint32), U)
    second = j >= m
    i = dr.select(second, j - m, j)
    wo = dr.select(second, dr.gather(V3, wo_t, i), dr.gather(V3, wo_r, i))
    wt = dr.select(second, dr.gather(V3, w_t, i), dr.gather(V3, w_r, i))
    norm = dr.sqrt((wo.x * wo.x + wo.y * wo.y) + wo.z * wo.z)
    den = dr.select((norm >= 1e-300) | dr.isnan(norm), norm, 1e-300)
    wo = V3(wo.x / den, wo.y / den, wo.z / den)
    ng = dr.gather(V3, v["ng"], i)
    side = dr.select(_dot(wo, ng) >= 0, 1.0, -1.0)
    thr = dr.gather(V3, v["thr"], i)
    out = {"pixel": dr.gather(U, v["pixel"], i), "thr": V3(thr.x * wt.x, thr.y * wt.y, thr.z * wt.z),
           "path": dr.gather(U, v["path"], i) * 3 + dr.select(second, 2, 1),
           "length": dr.gather(dev.Float64, v["length"], i),
           "org": dev.offset_origin(dr.gather(dev.Point3d, v["p"], i), V3(side * ng.x, side * ng.y, side * ng.z)),
           "dirs": wo}
    dev.eval(*out.values())
    return out


def _take(dev, v: dict, idx) -> dict:
    dr = dev.dr
    return {k: dr.gather(type(a), a, idx) for k, a in v.items()}


def chains_in_parts(tracer, parts, *args, record=None):
    """``[secondary._chains(tracer, part, *args) for part in parts]`` as one wavefront over all the parts' chains:
    the host runs the parts (contiguous runs of pixels) one after the other, so its points come part by part, depth
    by depth. Restricted to one part's pixels, a depth of the whole wavefront is that part's depth (the same rays in
    the same order: by material, branch, then chain order, which a part's chains keep), so the points are split by
    part afterwards; the rays per depth are the parts' sums (given with the first part) and a pixel's emission comes in
    the same order."""
    rows = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    found, rays_per_depth = chains(tracer, rows, *args, record=record)
    done = []
    for k, part in enumerate(parts):
        lo, hi = (int(part[0]), int(part[-1])) if len(part) else (0, -1)
        mine = []
        for points, lengths in found:
            sel = (points.pixel >= lo) & (points.pixel <= hi)
            if sel.any():
                mine.append((points.subset(sel), lengths[sel]))
        done.append((mine, rays_per_depth if k == 0 else []))
    return done


def chains(tracer, rows, scene, t_s: float, surface, max_depth: int, skip_faces, branches, emission, record=None):
    """``secondary._chains`` on the tracer's device (module docstring): the same ``(found, rays_per_depth)``, and the
    same emission added to ``emission``. ``record``: a list that gets each depth's rays as ``("i", Ray3f)`` (the
    benchmark's raw replay, :func:`suite.core.trace.recording.device_replay`)."""
    from suite.core.device.gbuffer import hit_surface

    dev = tracer.device
    dr, V3, F64, U = dev.dr, dev.Vector3d, dev.Float64, dev.UInt32
    tables = dev.tables
    tb = _Tables(dev, branches)
    rows = np.asarray(rows, np.int64)
    tracer.update(t_s)
    v = {"pixel": dev.to_device(rows.astype(np.uint32), U), "thr": dr.full(V3, 1.0, len(rows)),
         "path": dr.zeros(U, len(rows)), "length": dev.to_device(np.take(surface.t, rows), F64),
         "p": dev.to_device(np.take(surface.p, rows, axis=0), dev.Point3d),
         "ng": dev.to_device(np.take(surface.ng, rows, axis=0), V3),
         "ns": dev.to_device(np.take(surface.ns, rows, axis=0), V3),
         "d": dev.to_device(np.take(surface.d, rows, axis=0), V3),
         "material": dev.to_device(np.take(surface.material, rows).astype(np.int32), dev.Int32)}
    found, rays_per_depth = [], []
    for depth in range(1, max_depth + 1):
        if dr.width(v["pixel"]) == 0:
            break
        r = _rays(dev, tb, v, branches.all_branches, DIM_SECONDARY + 3 * depth)
        if r is None:
            break
        n = dr.width(r["pixel"])
        rays_per_depth.append(n)
        o_local, d32, length = dev.local_f32(r["org"]), dev.Vector3f(r["dirs"]), dr.full(dev.Float, MAX_RAY_LENGTH, n)
        if record is not None:
            record.append(("i", dev.raw_ray(o_local, d32, length)))
        t, prim, u, uv_v, traced = dev.closest(o_local, d32, length)
        dev.eval(*[x for x in (t, prim, u, uv_v, traced) if x is not None])
        tracer.counters["rays_intersect"] += n if traced is None else dev.sum_u32(traced)
        hit = dr.compress(prim >= 0)
        if dr.width(hit) == 0:
            break
        r = _take(dev, r, hit)
        prim, u, uv_v = dr.gather(dev.Int32, prim, hit), dr.gather(dev.Float, u, hit), dr.gather(dev.Float, uv_v, hit)
        r["length"] = r["length"] + F64(dr.gather(dev.Float, t, hit))
        valid = dr.full(dev.Bool, True, dr.width(hit))
        sf = hit_surface(dev, prim, u, uv_v, valid, dev.Point3d(r["org"]), r["dirs"], r["dirs"], bary64=True)
        mat = sf.mat
        # one kernel for every field the gathers below read (a gather evaluates its source on its own)
        dev.eval(sf.position, sf.ng, sf.ns, sf.ng_raw, sf.ns_raw, sf.albedo, mat, sf.front, r["length"])
        if tables.any_emissive:
            em = tables.front_emission(mat, sf.front)
            glow = dr.compress((em.x > 0) | (em.y > 0) | (em.z > 0))
            if dr.width(glow):
                em = V3(dr.gather(dev.Vector3f, em, glow))
                thr = dr.gather(V3, r["thr"], glow)
                pixel, glowing = dev.to_host_all([dr.gather(U, r["pixel"], glow), V3(thr.x * em.x, thr.y * em.y,
                                                                                      thr.z * em.z)], [np.int64, None])
                np.add.at(emission, pixel, glowing)
        is_spec = dr.gather(dev.Bool, tb.spec, mat)
        lit = dr.compress(~is_spec)
        if dr.width(lit):
            found.append(_points(dev, tb, r, sf, prim, lit))
        if depth < max_depth:
            cont = dr.compress(is_spec)
            v = {"pixel": dr.gather(U, r["pixel"], cont), "thr": dr.gather(V3, r["thr"], cont),
                 "path": dr.gather(U, r["path"], cont), "length": dr.gather(F64, r["length"], cont),
                 "p": dr.gather(dev.Point3d, sf.position, cont), "ng": dr.gather(V3, sf.ng_raw, cont),
                 "ns": dr.gather(V3, sf.ns_raw, cont), "d": dr.gather(V3, r["dirs"], cont),
                 "material": dr.gather(dev.Int32, mat, cont)}
            dr.eval(*v.values())
        else:
            break
    return found, rays_per_depth


def _points(dev, tb, r, sf, prim, lit):
    """The shading points of the hits ``lit`` (diffuse, glossy) with their path lengths, on the host
    (``_split_hits``: the viewer-side or raw normal the BSDF reads, the chain's derived seed)."""
    dr, V3, U = dev.dr, dev.Vector3d, dev.UInt32
    g = lambda T, a: dr.gather(T, a, lit)  # noqa: E731
    pixel, path, mat = g(U, r["pixel"]), g(U, r["path"]), g(dev.Int32, sf.mat)
    d = g(V3, r["dirs"])
    wi = -d
    ns_raw, ns_view = g(V3, sf.ns_raw), g(V3, sf.ns)
    mode = dr.gather(dev.Int32, tb.normal_mode, mat)
    flip = (mode == 1) & (_dot(wi, ns_raw) < 0)
    ns = dr.select(mode == 0, ns_view, dr.select(flip, -ns_raw, ns_raw))
    _, seed = _stream(dev, tb, pixel, path)
    f64 = np.float64
    fields = {"pixel": (pixel, np.int64), "throughput": (g(V3, r["thr"]), f64), "p": (g(dev.Point3d, sf.position), f64),
              "ng": (g(V3, sf.ng), f64), "ns": (ns, f64), "wi": (wi, f64), "albedo": (g(dev.Vector3f, sf.albedo), f64),
              "material": (mat, np.int64), "prim": (g(dev.Int32, prim), np.int64), "seed": (seed, np.uint32),
              "lambert": (dr.gather(dev.Bool, tb.lambert, mat), bool), "length": (g(dev.Float64, r["length"]), f64)}
    host = dict(zip(fields, dev.to_host_all([v for v, _ in fields.values()], [t for _, t in fields.values()])))
    length = host.pop("length")
    return ShadingPoints(**host), length
