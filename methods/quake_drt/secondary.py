"""Secondary ray stage (seed 001 §4.1, §6.5): mirrors, glass and water, to a depth of ``max_depth`` (5).

Pixels whose shading sample is a mirror continue along the reflection about the shading normal (weight:
conductor Fresnel x specular reflectance); glass and water split into a reflected ray (weight F) and a refracted
ray (weight (1 - F) eta^2 x transmittance, Mitsuba's radiance scaling), total internal reflection reflects only.
The transport and the BSDF formulas are those of ``suite.core.specular.render_materials`` (through the public
``suite.core.bsdf`` functions), so a frame without distribution effects matches that kernel.

* ``all_branches = True`` (the thesis's noise-free mode, §7.2 / Fig. 7.5: "we traced all the rays recursively"):
  both glass branches are followed, so one pixel can end on several surfaces.
* ``all_branches = False`` (the variant of §7.5): one branch per interface, reflection with probability F,
  weight divided by that probability: unbiased and noisy, one surface per pixel.
* ``glossy`` (Table 2.1's glossy reflections, Cook et al. 1984): a mirror's reflected direction is drawn
  uniformly in a cone of half-angle ``glossy_cone_deg`` around the mirror direction (a blurred reflection);
  directions that fall below the surface are lost.

Every surface a chain reaches adds its emission (front side) times the chain's weight; diffuse and glossy ones
become shading points for the direct illumination stage. A specular surface reached after ``max_depth``
interactions ends the chain. Overlays are passed without blending (they belong to the primary ray, §6.4).

For the denoiser the thesis overwrites the G-buffer of these pixels with the secondary hit (§6.5); here the
guides (normal, depth = path length) of a specular pixel are those of its strongest chain's last surface.

**Cost.** Each depth is one closest-hit query between compiled passes (the branches, the surfaces, the split into
shading points and chains), in parts on two threads so that one part's passes overlap the other's query
(:func:`secondary_stage`; each part puts its rays in the tracing frame itself, so only the query holds the
tracer); :func:`secondary_stage_reference` is the same in whole-array numpy, and the tests hold
the two to the same bits. On ``cuda_ad_rgb`` the chains are a device wavefront with the same bits on
``llvm_ad_rgb`` (:mod:`methods.quake_drt.device_secondary`). ``splitbench bench quake_drt`` times the stage against the
backend's raw query on its rays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from methods.quake_drt.direct import ShadingPoints, pcg_nb, uniform_nb
from methods.quake_drt.rng import DIM_SECONDARY, stream_np, uniform_np
from suite.core.bsdf import fresnel_conductor, fresnel_dielectric
from suite.core.trace.robust import FLOAT_SCALE, OFFSET_ULPS, offset_ray_origin

DEFAULT_MAX_DEPTH = 5


@dataclass
class SecondaryResult:
    points: ShadingPoints  # diffuse / glossy surfaces the chains reached
    emission: np.ndarray  # (N, 3) emission collected along the chains (already weighted)
    rays_per_depth: list  # continuation rays traced at depth 1, 2, ...
    guide_pixel: np.ndarray  # pixels whose denoiser guides the strongest chain replaces
    guide_p: np.ndarray
    guide_n: np.ndarray
    guide_depth: np.ndarray  # path length to that surface

    @property
    def rays(self) -> int:
        return int(sum(self.rays_per_depth))


# Dot products and norms in one written order, ((x0 y0 + x1 y1) + x2 y2), which the compiled pass repeats: einsum and
# linalg.norm choose their own summation order (SIMD dependent; einsum's is not this one).
def _dot(a, b):
    return (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]


def _unit(v):
    return v / np.maximum(np.sqrt(_dot(v, v)), 1e-300)[:, None]


def _reflect(wi, n):
    """:func:`suite.core.bsdf.reflect` with :func:`_dot`: ``2 (wi.n) n - wi``."""
    return (2.0 * _dot(wi, n))[:, None] * n - wi


def _refract(wi, n, cos_theta_t, eta_ti):
    """:func:`suite.core.bsdf.refract` with :func:`_dot`."""
    return n * (_dot(wi, n) * eta_ti + cos_theta_t)[:, None] - wi * np.asarray(eta_ti)[:, None]


def _cone(axis: np.ndarray, cos_max: float, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Uniform directions in the cone of half-angle acos(cos_max) around the unit vectors ``axis``."""
    cos_t = 1.0 - u1 * (1.0 - cos_max)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * np.pi * u2
    helper = np.where(np.abs(axis[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = _unit(np.cross(helper, axis))
    t2 = np.cross(axis, t1)
    return _unit(cos_t[:, None] * axis + (sin_t * np.cos(phi))[:, None] * t1 + (sin_t * np.sin(phi))[:, None] * t2)


class _NumpyBranches:
    """One depth's continuation rays as whole-array numpy expressions, material by material (ascending ids), each
    material's branches in order (mirror: the reflection; glass and water: reflection, then refraction), each
    branch's rays in chain order: ``(pixel, throughput, path, length, origins, unit directions)``."""

    def __init__(self, scene, seeds, all_branches: bool, glossy: bool, glossy_cone_deg: float, shift):
        self.scene, self.seeds, self.all_branches, self.glossy = scene, seeds, all_branches, glossy
        self.cos_max = float(np.cos(np.radians(glossy_cone_deg)))
        self.shift = shift
        self.spec = _specular(scene)

    def __call__(self, v, depth: int):
        scene, seeds, cos_max = self.scene, np.asarray(self.seeds, np.uint32).reshape(-1), self.cos_max
        pix, thr, path, length, org, dirs = [], [], [], [], [], []
        wi_all = -v["d"]
        for mid in np.unique(v["material"]):
            mat = scene.materials[int(mid)]
            sel = np.nonzero(v["material"] == mid)[0]
            n, ng, p, w = v["ns"][sel], v["ng"][sel], v["p"][sel], wi_all[sel]
            vseed = np.where(v["path"][sel] == 0, seeds[v["pixel"][sel]],
                             stream_np(seeds[v["pixel"][sel]], v["path"][sel] & 0xFFFFFFFF))
            dim = DIM_SECONDARY + 3 * depth
            cos_i = _dot(w, n)
            branches = []
            if mat.kind == "mirror":
                if mat.twosided:
                    n = np.where(cos_i[:, None] < 0, -n, n)
                    cos_i = np.abs(cos_i)
                weight = fresnel_conductor(cos_i[:, None], mat.conductor_eta.astype(np.float64),
                                           mat.conductor_k.astype(np.float64)) * mat.specular_reflectance
                wo = _reflect(w, n)
                if self.glossy:
                    wo = _cone(_unit(wo), cos_max, uniform_np(vseed, dim + 1), uniform_np(vseed, dim + 2))
                    below = _dot(wo, np.where(cos_i[:, None] >= 0, n, -n)) <= 0
                    weight = np.where(below[:, None], 0.0, weight)
                branches.append((cos_i > 0, wo, weight, 1))
            else:  # glass / water
                f, cos_t, _, eta_ti = fresnel_dielectric(cos_i, mat.eta)
                r_w = f[:, None] * mat.specular_reflectance
                t_w = ((1.0 - f) * eta_ti * eta_ti)[:, None] * mat.specular_transmittance
                if not self.all_branches:
                    pick_r = uniform_np(vseed, dim) < f
                    r_w = np.where(pick_r[:, None], mat.specular_reflectance, 0.0)
                    t_w = np.where(pick_r[:, None], 0.0, (eta_ti * eta_ti)[:, None] * mat.specular_transmittance)
                branches.append((f > 0, _reflect(w, n), r_w, 1))
                branches.append((f < 1, _refract(w, n, cos_t, eta_ti), t_w, 2))
            for ok, wo, weight, tag in branches:
                keep = ok & np.any(weight > 0, axis=-1)
                if not keep.any():
                    continue
                wo = _unit(wo[keep])
                side = np.where(_dot(wo, ng[keep]) >= 0, 1.0, -1.0)[:, None]
                org.append(offset_ray_origin(p[keep], side * ng[keep], self.shift))
                dirs.append(wo)
                pix.append(v["pixel"][sel][keep])
                thr.append(v["thr"][sel][keep] * weight[keep])
                path.append(v["path"][sel][keep] * 3 + tag)
                length.append(v["length"][sel][keep])
        if not pix:
            return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
                    np.zeros((0, 3)))
        return (*(np.concatenate(x) for x in (pix, thr, path, length)), np.concatenate(org), np.concatenate(dirs))

    def surfaces(self, t_s: float, h, rays, emission, more: bool):
        """The hits ``h`` of ``rays``: their emission added to ``emission`` (per pixel, in ray order), the shading
        points of the diffuse and glossy ones with their path lengths (None if there are none), and the chains that
        go on from the specular ones (none when ``more`` is false)."""
        from methods.quake_drt.primary import surface_from_hits_reference

        scene, seeds, spec = self.scene, np.asarray(self.seeds, np.uint32).reshape(-1), self.spec
        pix, thr, path, length, org, dirs = rays
        hit = np.asarray(h.prim) >= 0
        prim = np.asarray(h.prim, np.int64)[hit]
        o_h, d_h = org[hit], dirs[hit]
        u_h, v_h, t_h = np.asarray(h.u)[hit], np.asarray(h.v)[hit], np.asarray(h.t, np.float64)[hit]
        sf = surface_from_hits_reference(scene, t_s, o_h, d_h, prim, u_h, v_h, t_h)
        p, ng, ns, ngv, nsv, albedo, em = sf.p, sf.ng, sf.ns, sf.ng_view, sf.ns_view, sf.albedo, sf.emission
        pix, thr, path = pix[hit], thr[hit], path[hit]
        length = length[hit] + t_h
        np.add.at(emission, pix, thr * em)
        material = scene.face_material[prim].astype(np.int64)
        is_spec = spec[material]
        lit = None
        if (~is_spec).any():
            ps = np.nonzero(~is_spec)[0]
            wi = -d_h[ps]
            pseed = stream_np(seeds[pix[ps]], path[ps] & 0xFFFFFFFF)
            lit = (ShadingPoints(pixel=pix[ps], throughput=thr[ps], p=p[ps], ng=ngv[ps],
                                 ns=bsdf_normal(scene, material[ps], nsv[ps], ns[ps], wi), wi=wi, albedo=albedo[ps],
                                 material=material[ps], prim=prim[ps], seed=pseed,
                                 lambert=lambert_mask(scene, material[ps])), length[ps])
        cont = np.nonzero(is_spec)[0] if more else np.zeros(0, np.int64)
        return lit, {"pixel": pix[cont], "thr": thr[cont], "path": path[cont], "length": length[cont],
                     "p": p[cont], "ng": ng[cont], "ns": ns[cont], "d": d_h[cont], "material": material[cont]}


class _CompiledBranches:
    """:class:`_NumpyBranches` (without glossy reflections) as one compiled pass per depth, :func:`_branch_pass`."""

    def __init__(self, scene, seeds, all_branches: bool, shift):
        mats = scene.materials
        self.seeds = np.asarray(seeds, np.uint32).reshape(-1)
        self.all_branches = bool(all_branches)
        self.shift = np.zeros(3) if shift is None else np.asarray(shift, np.float64)
        self.kind = np.array([_MIRROR if m.kind == "mirror" else _DIELECTRIC for m in mats], np.int64)
        self.twosided = np.array([m.twosided for m in mats], np.bool_)
        table = lambda attr: np.array([getattr(m, attr) for m in mats], np.float64).reshape(-1, 3)  # noqa: E731
        self.cond_eta, self.cond_k = table("conductor_eta"), table("conductor_k")
        self.spec_r, self.spec_t = table("specular_reflectance"), table("specular_transmittance")
        self.eta = np.array([m.eta if m.kind != "mirror" and m.is_specular else 1.0 for m in mats], np.float64)
        self.scene = scene
        self.spec = _specular(scene)
        self.lambert = np.array([m.shading_kind == "diffuse" for m in mats], np.bool_)
        # bsdf_normal per material: 0 the viewer-side normal, 1 the raw one turned to the viewer, 2 the raw one
        self.normal_mode = np.array([0 if (m.shading_kind == "diffuse" or not m.is_glossy) else (1 if m.twosided else 2)
                                     for m in mats], np.int64)
        self.face_material = np.ascontiguousarray(scene.face_material, np.int64)

    def __call__(self, v, depth: int):
        m = len(v["pixel"])
        pix, path = np.empty(2 * m, np.int64), np.empty(2 * m, np.int64)
        thr, org, dirs = np.empty((2 * m, 3)), np.empty((2 * m, 3)), np.empty((2 * m, 3))
        length = np.empty(2 * m)
        f = lambda a, t=np.float64: np.ascontiguousarray(a, t)  # noqa: E731
        k = _branch_pass(f(v["pixel"], np.int64), f(v["thr"]), f(v["path"], np.int64), f(v["length"]), f(v["p"]),
                         f(v["ng"]), f(v["ns"]), f(v["d"]), f(v["material"], np.int64), self.seeds, self.kind,
                         self.twosided, self.cond_eta, self.cond_k, self.spec_r, self.spec_t, self.eta,
                         self.all_branches, DIM_SECONDARY + 3 * depth, self.shift, OFFSET_ULPS, FLOAT_SCALE,
                         pix, thr, path, length, org, dirs)
        return pix[:k], thr[:k], path[:k], length[:k], org[:k], dirs[:k]

    def surfaces(self, t_s: float, h, rays, emission, more: bool):
        """:meth:`_NumpyBranches.surfaces` in two compiled passes around the primary stage's compiled surface pass:
        :func:`_compact_hits`, :func:`.primary.surface_from_hits`, :func:`_split_hits`."""
        from methods.quake_drt.primary import surface_from_hits

        pix, thr, path, length, org, dirs = rays
        m = len(pix)
        prim, hu, hv = np.empty(m, np.int64), np.empty(m, np.float32), np.empty(m, np.float32)
        t, c_pix, c_path, c_len = np.empty(m), np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m)
        c_thr, c_org, c_dir = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
        k = _compact_hits(np.asarray(h.prim), np.asarray(h.u, np.float32), np.asarray(h.v, np.float32),
                          np.asarray(h.t), pix, thr, path, length, org, dirs, prim, hu, hv, t, c_pix, c_thr, c_path,
                          c_len, c_org, c_dir)
        sf = surface_from_hits(self.scene, t_s, c_org[:k], c_dir[:k], prim[:k], hu[:k], hv[:k], t[:k])
        lit = ShadingPoints(np.empty(k, np.int64), np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3)),
                            np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3)), np.empty(k, np.int64),
                            np.empty(k, np.int64), np.empty(k, np.uint32), np.empty(k, np.bool_))
        lit_len = np.empty(k)
        z3 = lambda: np.empty((k, 3))  # noqa: E731
        v = {"pixel": np.empty(k, np.int64), "thr": z3(), "path": np.empty(k, np.int64), "length": np.empty(k),
             "p": z3(), "ng": z3(), "ns": z3(), "d": z3(), "material": np.empty(k, np.int64)}
        n_lit, n_cont = _split_hits(
            c_pix[:k], c_thr[:k], c_path[:k], c_len[:k], c_dir[:k], prim[:k], sf.p, sf.ng, sf.ns, sf.ng_view,
            sf.ns_view, sf.albedo, sf.emission, self.face_material, self.spec, self.lambert, self.normal_mode,
            self.seeds, emission, more,
            lit.pixel, lit.throughput, lit.p, lit.ng, lit.ns, lit.wi, lit.albedo, lit.material, lit.prim, lit.seed,
            lit.lambert, lit_len,
            v["pixel"], v["thr"], v["path"], v["length"], v["p"], v["ng"], v["ns"], v["d"], v["material"])
        lit = lit.subset(slice(0, n_lit))
        return ((lit, lit_len[:n_lit]) if n_lit else None), {key: a[:n_cont] for key, a in v.items()}



_MIRROR, _DIELECTRIC = 0, 1
_U32 = 0xFFFFFFFF


# Compiled on first use and not cached: _branch_pass calls the RNG twins of .direct, and numba's cache of a function
# is keyed by its own file only.
_inline = numba.njit(inline="always", error_model="numpy")


@_inline
def _max0(x):
    """``np.maximum(x, 0.0)`` of a scalar (NaN stays NaN)."""
    return x if (x >= 0.0 or x != x) else 0.0


# Mitsuba's conductor Fresnel term, the one expression of :func:`suite.core.bsdf.fresnel_conductor`, compiled for one
# channel (np.maximum and np.sqrt of scalars: the numpy operations in their order, so the bits of the reference).
_fresnel_conductor1 = _inline(fresnel_conductor)


@_inline
def _fresnel_dielectric1(cos_i, eta):
    """:func:`suite.core.bsdf.fresnel_dielectric` of one ray: (F, cos_theta_t, eta_ti)."""
    outside = cos_i >= 0.0
    eta_it = eta if outside else 1.0 / eta
    eta_ti = 1.0 / eta if outside else eta
    cos_theta_t_sqr = 1.0 - (1.0 - cos_i * cos_i) * (eta_ti * eta_ti)
    cos_i_abs = abs(cos_i)
    cos_t_abs = np.sqrt(_max0(cos_theta_t_sqr))
    if eta == 1.0:
        r = 0.0
    elif cos_i_abs == 0.0:
        r = 1.0
    else:
        a_s = (cos_i_abs - eta_it * cos_t_abs) / (cos_i_abs + eta_it * cos_t_abs)
        a_p = (cos_t_abs - eta_it * cos_i_abs) / (cos_t_abs + eta_it * cos_i_abs)
        r = 0.5 * (a_s * a_s + a_p * a_p)
    return r, (-cos_t_abs if outside else cos_t_abs), eta_ti


@numba.njit(nogil=True, error_model="numpy")
def _branch_pass(pixel, thr, path, length, p, ng, ns, d, material, seeds, kind, twosided, cond_eta, cond_k, spec_r,
                 spec_t, eta, all_branches, dim, shift, offset_ulps, float_scale,
                 out_pix, out_thr, out_path, out_len, out_org, out_dir):
    """One depth of :class:`_NumpyBranches` (no glossy cone): the branches of every chain computed once (unit
    direction, weight, whether it continues), then written in the reference's order (material, branch, chain)
    with their offset origins. Returns the number of rays written."""
    m = pixel.shape[0]
    n_mat = kind.shape[0]
    wo = np.empty((m, 2, 3))
    wt = np.empty((m, 2, 3))
    keep = np.zeros((m, 2), np.bool_)
    count = np.zeros((n_mat, 2), np.int64)
    for i in range(m):
        mid = material[i]
        wx, wy, wz = -d[i, 0], -d[i, 1], -d[i, 2]
        nx, ny, nz = ns[i, 0], ns[i, 1], ns[i, 2]
        cos_i = (wx * nx + wy * ny) + wz * nz
        if kind[mid] == 0:  # mirror: the reflection about the (two-sided: viewer-side) shading normal
            if twosided[mid]:
                if cos_i < 0:
                    nx, ny, nz = -nx, -ny, -nz
                cos_i = abs(cos_i)
            positive = False
            for c in range(3):
                w = _fresnel_conductor1(cos_i, cond_eta[mid, c], cond_k[mid, c]) * spec_r[mid, c]
                wt[i, 0, c] = w
                positive = positive or w > 0
            dt = 2.0 * ((wx * nx + wy * ny) + wz * nz)
            wo[i, 0, 0], wo[i, 0, 1], wo[i, 0, 2] = dt * nx - wx, dt * ny - wy, dt * nz - wz
            keep[i, 0] = cos_i > 0 and positive
        else:  # glass / water: reflection (weight F) and refraction (weight (1 - F) eta^2 T)
            f, cos_t, eta_ti = _fresnel_dielectric1(cos_i, eta[mid])
            pick = True
            if not all_branches:
                seed = seeds[pixel[i]]
                if path[i] != 0:
                    seed = pcg_nb((np.uint64(seed) ^ ((np.uint64(path[i] & _U32) * np.uint64(0x85EBCA6B))
                                                       & np.uint64(_U32))))
                pick = uniform_nb(seed, dim) < f
            pos_r, pos_t = False, False
            for c in range(3):
                if all_branches:
                    r_w = f * spec_r[mid, c]
                    t_w = (1.0 - f) * eta_ti * eta_ti * spec_t[mid, c]
                else:
                    r_w = spec_r[mid, c] if pick else 0.0
                    t_w = 0.0 if pick else eta_ti * eta_ti * spec_t[mid, c]
                wt[i, 0, c], wt[i, 1, c] = r_w, t_w
                pos_r, pos_t = pos_r or r_w > 0, pos_t or t_w > 0
            dt = (wx * nx + wy * ny) + wz * nz
            k2 = 2.0 * dt
            wo[i, 0, 0], wo[i, 0, 1], wo[i, 0, 2] = k2 * nx - wx, k2 * ny - wy, k2 * nz - wz
            kt = dt * eta_ti + cos_t
            wo[i, 1, 0], wo[i, 1, 1], wo[i, 1, 2] = nx * kt - wx * eta_ti, ny * kt - wy * eta_ti, nz * kt - wz * eta_ti
            keep[i, 0] = f > 0 and pos_r
            keep[i, 1] = f < 1 and pos_t
        for b in range(2):
            if keep[i, b]:
                count[mid, b] += 1
    nxt = np.empty((n_mat, 2), np.int64)
    total = 0
    for mid in range(n_mat):
        for b in range(2):
            nxt[mid, b] = total
            total += count[mid, b]
    for i in range(m):
        mid = material[i]
        for b in range(2):
            if not keep[i, b]:
                continue
            j = nxt[mid, b]
            nxt[mid, b] = j + 1
            x, y, z = wo[i, b, 0], wo[i, b, 1], wo[i, b, 2]
            norm = np.sqrt((x * x + y * y) + z * z)
            den = norm if (norm >= 1e-300 or norm != norm) else 1e-300
            x, y, z = x / den, y / den, z / den
            gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
            side = 1.0 if ((x * gx + y * gy) + z * gz) >= 0 else -1.0
            # suite.core.trace.robust.offset_ray_origin along side * ng
            mag = np.float32(max(max(abs(p[i, 0] - shift[0]), abs(p[i, 1] - shift[1])), abs(p[i, 2] - shift[2])))
            step = max(offset_ulps * np.float64(np.spacing(mag)), float_scale)
            out_org[j, 0] = p[i, 0] + step * (side * gx)
            out_org[j, 1] = p[i, 1] + step * (side * gy)
            out_org[j, 2] = p[i, 2] + step * (side * gz)
            out_dir[j, 0], out_dir[j, 1], out_dir[j, 2] = x, y, z
            out_pix[j] = pixel[i]
            for c in range(3):
                out_thr[j, c] = thr[i, c] * wt[i, b, c]
            out_path[j] = path[i] * 3 + (b + 1)
            out_len[j] = length[i]
    return total


@numba.njit(nogil=True, error_model="numpy")
def _compact_hits(h_prim, h_u, h_v, h_t, pix, thr, path, length, org, dirs,
                  prim, u, v, t, o_pix, o_thr, o_path, o_len, o_org, o_dir):
    """The rays that hit something, in order, with their hit (``t`` and the path length ``length + t`` in float64).
    Returns how many."""
    k = 0
    for i in range(h_prim.shape[0]):
        if h_prim[i] < 0:
            continue
        prim[k], u[k], v[k] = h_prim[i], h_u[i], h_v[i]
        t[k] = np.float64(h_t[i])
        o_pix[k], o_path[k] = pix[i], path[i]
        o_len[k] = length[i] + t[k]
        for c in range(3):
            o_thr[k, c], o_org[k, c], o_dir[k, c] = thr[i, c], org[i, c], dirs[i, c]
        k += 1
    return k


@numba.njit(nogil=True, error_model="numpy")
def _split_hits(pix, thr, path, length, d, prim, p, ng, ns, ngv, nsv, albedo, em, face_material, spec, lambert,
                normal_mode, seeds, emission, more,
                l_pix, l_thr, l_p, l_ng, l_ns, l_wi, l_albedo, l_material, l_prim, l_seed, l_lambert, l_len,
                c_pix, c_thr, c_path, c_len, c_p, c_ng, c_ns, c_d, c_material):
    """The surfaces the rays reached: emission added per pixel in ray order (``np.add.at``), then each one either a
    shading point (diffuse, glossy: :func:`bsdf_normal`, :func:`lambert_mask`, the chain's derived seed) or, when
    ``more``, a chain that goes on (mirror, glass). Returns (points, chains)."""
    n_lit = 0
    n_cont = 0
    for i in range(pix.shape[0]):
        q = pix[i]
        for c in range(3):
            emission[q, c] += thr[i, c] * em[i, c]
        mat = face_material[prim[i]]
        if spec[mat]:
            if not more:
                continue
            j = n_cont
            n_cont += 1
            c_pix[j], c_path[j], c_len[j], c_material[j] = q, path[i], length[i], mat
            for c in range(3):
                c_thr[j, c], c_p[j, c], c_d[j, c] = thr[i, c], p[i, c], d[i, c]
                c_ng[j, c], c_ns[j, c] = ng[i, c], ns[i, c]
            continue
        j = n_lit
        n_lit += 1
        l_pix[j], l_material[j], l_prim[j], l_lambert[j], l_len[j] = q, mat, prim[i], lambert[mat], length[i]
        stream = (np.uint64(path[i] & _U32) * np.uint64(0x85EBCA6B)) & np.uint64(_U32)
        l_seed[j] = pcg_nb(np.uint64(seeds[q]) ^ stream)
        wx, wy, wz = -d[i, 0], -d[i, 1], -d[i, 2]
        mode = normal_mode[mat]
        flip = mode == 1 and ((wx * ns[i, 0] + wy * ns[i, 1]) + wz * ns[i, 2]) < 0
        for c in range(3):
            l_thr[j, c], l_p[j, c], l_ng[j, c], l_albedo[j, c] = thr[i, c], p[i, c], ngv[i, c], albedo[i, c]
            l_ns[j, c] = nsv[i, c] if mode == 0 else (-ns[i, c] if flip else ns[i, c])
        l_wi[j, 0], l_wi[j, 1], l_wi[j, 2] = wx, wy, wz
    return n_lit, n_cont


@numba.njit(nogil=True, error_model="numpy")
def _strongest(pixel, throughput, n_pixels):
    """Per pixel, the index of its point of largest ``throughput.sum(axis=1)`` (the first of equals; a NaN sum
    loses to any number, as in ``np.lexsort``), -1 for pixels without a point."""
    best = np.full(n_pixels, -1, np.int64)
    best_s = np.zeros(n_pixels)
    for i in range(pixel.shape[0]):
        s = (throughput[i, 0] + throughput[i, 1]) + throughput[i, 2]
        q = pixel[i]
        b = best_s[q]
        if best[q] < 0 or s > b or (b != b and s == s):
            best[q] = i
            best_s[q] = s
    return best


def lambert_mask(scene, material: np.ndarray) -> np.ndarray:
    lam = np.array([m.shading_kind == "diffuse" for m in scene.materials], bool)
    return lam[np.asarray(material, np.int64)]


def bsdf_normal(scene, material, ns_view, ns_raw, wi) -> np.ndarray:
    """The normal a material's BSDF is evaluated around (as suite.core.specular): the viewer-side normal for
    diffuse surfaces, the interpolated normal turned toward the viewer for two-sided glossy ones, the raw
    interpolated normal for one-sided glossy ones (whose back is black)."""
    out = np.asarray(ns_view, np.float64).copy()
    glossy = [i for i, m in enumerate(scene.materials) if m.shading_kind != "diffuse" and m.is_glossy]
    if not glossy or len(out) == 0:
        return out
    # The materials present, by counting (np.unique sorts: 1 ms of a 320x180 frame's shading points).
    present = np.bincount(np.maximum(np.asarray(material, np.int64), 0), minlength=len(scene.materials)) > 0
    for mid in glossy:
        if not present[mid]:
            continue
        m = scene.materials[mid]
        sel = material == mid
        if m.twosided:
            out[sel] = np.where(_dot(wi[sel], ns_raw[sel])[:, None] < 0, -ns_raw[sel], ns_raw[sel])
        else:
            out[sel] = ns_raw[sel]
    return out


def secondary_stage(scene, tracer, t_s: float, surface, seeds: np.ndarray, max_depth: int = DEFAULT_MAX_DEPTH,
                    all_branches: bool = True, glossy: bool = False, glossy_cone_deg: float = 5.0,
                    skip_faces=None, record=None) -> SecondaryResult:
    """Follows the specular chains of the shading samples ``surface`` (module docstring).

    The chains are split into :data:`PARTS` parts (contiguous runs of pixels: a pixel's chains stay in one part),
    each followed depth by depth: the continuation rays from one compiled pass (:func:`_branch_pass`), their
    surfaces from the primary stage's compiled pass (:func:`.primary.surface_from_hits`) and :func:`_split_hits`.
    On a host tracer the parts run on threads of their own that take turns at the tracer (one query at a time,
    :class:`suite.core.pipeline.SerialTracer`), so one part's compiled passes (the GIL released) overlap another's
    query. The result has the bits of :func:`secondary_stage_reference`, which runs the same parts one after the
    other: each pixel's emission and shading points come in the same order whatever the scheduling. Glossy
    reflections (a cone sampled with trigonometric functions, whose numpy and compiled versions need not round
    alike) take the reference. Where the chains run on the device (:mod:`methods.quake_drt.device_secondary`),
    ``record`` (a list) gets their rays per depth."""
    if glossy:
        return secondary_stage_reference(scene, tracer, t_s, surface, seeds, max_depth, all_branches, glossy,
                                         glossy_cone_deg, skip_faces)
    branches = _CompiledBranches(scene, seeds, all_branches, getattr(tracer, "shift", None))
    return _stage(scene, tracer, surface, max_depth, skip_faces, branches, t_s, compiled=True, record=record)


def secondary_stage_reference(scene, tracer, t_s: float, surface, seeds: np.ndarray,
                              max_depth: int = DEFAULT_MAX_DEPTH, all_branches: bool = True, glossy: bool = False,
                              glossy_cone_deg: float = 5.0, skip_faces=None) -> SecondaryResult:
    """:func:`secondary_stage` with each depth's branches and surfaces as whole-array numpy expressions per
    material, the parts one after the other (the reference the compiled passes are tested against)."""
    branches = _NumpyBranches(scene, seeds, all_branches, glossy, glossy_cone_deg, getattr(tracer, "shift", None))
    return _stage(scene, tracer, surface, max_depth, skip_faces, branches, t_s, compiled=False)


# Parts of the specular chains (runs of pixels followed on their own threads: one traced while another's compiled
# passes run), and the fewest chains worth a second part.
PARTS = 2
PART_MIN_CHAINS = 2048


def part_bounds(weight: np.ndarray, count: int) -> np.ndarray:
    """``count + 1`` bounds of contiguous runs of rows whose summed ``weight`` (positive) is as even as whole rows
    allow: each run ends at the first row whose prefix sum reaches its share."""
    cum = np.cumsum(np.asarray(weight, np.float64))
    if count <= 1 or len(cum) == 0:
        return np.array([0, len(cum)], np.int64)
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, count) / count, side="left") + 1
    return np.concatenate([[0], np.minimum(cuts, len(cum)), [len(cum)]]).astype(np.int64)


def _specular(scene) -> np.ndarray:
    """Per material: mirror or glass (its chains go on)."""
    return np.array([m.is_specular for m in scene.materials], np.bool_)


def _stage(scene, tracer, surface, max_depth: int, skip_faces, branches, t_s: float, compiled: bool, record=None):
    """The chains of every specular pixel of ``surface`` in :data:`PARTS` parts (:func:`_chains`), merged; with
    ``compiled`` the parts run on threads on a host tracer and the guides come from :func:`_strongest`."""
    rows = np.nonzero(surface.valid & branches.spec[np.maximum(surface.material, 0)])[0]
    emission = np.zeros((len(surface.valid), 3))
    count = PARTS if len(rows) >= PART_MIN_CHAINS else 1
    # Parts of about equal work, not equal pixel counts: a glass or water chain that takes both branches traces
    # two rays per depth where a mirror's traces one (gallery 320x180: 0.663 of the raw rate with equal pixel
    # counts, parts of 28 k and 13 k rays; 0.695 balanced). A pixel's points keep their order in any split.
    two = np.array([m.kind != "mirror" and branches.all_branches for m in scene.materials], np.bool_)
    bounds = part_bounds(np.where(two[surface.material[rows]], 2.0, 1.0), count)
    parts = [rows[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    args = (scene, t_s, surface, max_depth, skip_faces, branches, emission)
    if compiled and count > 1 and getattr(tracer, "device", None) is None:
        import threading
        from concurrent.futures import ThreadPoolExecutor
        from contextlib import nullcontext

        from suite.core.pipeline import SerialTracer, kept_worker

        serial = SerialTracer(tracer, threading.Lock())

        def run(part):  # more parts than two: each part's passes take one of SerialTracer's core slots
            with serial.part() if count > 2 else nullcontext():
                return _chains(serial, part, *args)

        # two parts: the process's kept worker thread (a new thread costs about 0.3 ms)
        with kept_worker() if count == 2 else ThreadPoolExecutor(count - 1) as pool:
            pending = [pool.submit(run, part) for part in parts[1:]]
            done = [run(parts[0])] + [f.result() for f in pending]
    else:  # the reference, and Dr.Jit (driven from one thread): the parts one after the other
        from methods.quake_drt import device_secondary

        if compiled and device_secondary.available(tracer, False, skip_faces):
            # on a Dr.Jit tracer the compiled chains run on the device (methods/quake_drt/device_secondary.py)
            done = device_secondary.chains_in_parts(tracer, parts, *args, record=record)
        else:
            done = [_chains(tracer, part, *args) for part in parts]
    found = [pt for points, _ in done for pt in points]
    depths = max((len(r) for _, r in done), default=0)
    rays_per_depth = [sum(r[k] for _, r in done if k < len(r)) for k in range(depths)]
    points = ShadingPoints.concat([pt for pt, _ in found])
    lengths = np.concatenate([ln for _, ln in found]) if found else np.zeros(0)
    # The denoiser's guides for specular pixels: the strongest chain's shading point (the first of equals), by
    # pixel.
    if len(points):
        if compiled:
            best = _strongest(points.pixel, points.throughput, len(surface.valid))
            first = best[best >= 0]
        else:
            strength = points.throughput.sum(axis=1)
            order = np.lexsort((-strength, points.pixel))
            first = order[np.r_[True, np.diff(points.pixel[order]) != 0]]
        guide = (points.pixel[first], points.p[first], points.ns[first], lengths[first])
    else:
        guide = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    return SecondaryResult(points, emission, rays_per_depth, *guide)


def _chains(tracer, rows, scene, t_s: float, surface, max_depth: int, skip_faces, branches, emission):
    """The chains of the pixels ``rows``, depth by depth: ``branches(v, depth)`` makes the continuation rays of the
    chains ``v``, the tracer finds their surfaces, and ``branches.surfaces`` adds their emission (to ``emission``,
    rows of these pixels only) and splits them into shading points (diffuse, glossy) and the next depth's chains
    (mirror, glass). Returns ([(shading points, path lengths)] per depth, rays per depth)."""
    from methods.quake_drt.primary import walk_past
    from suite.core.pipeline import local_rays, trace_local

    v = {"pixel": rows, "thr": np.ones((len(rows), 3)), "path": np.zeros(len(rows), np.int64),
         "length": np.take(surface.t, rows), "p": np.take(surface.p, rows, axis=0),
         "ng": np.take(surface.ng, rows, axis=0), "ns": np.take(surface.ns, rows, axis=0),
         "d": np.take(surface.d, rows, axis=0), "material": np.take(surface.material, rows)}
    found, rays_per_depth = [], []
    for depth in range(1, max_depth + 1):
        if len(v["pixel"]) == 0:
            break
        pix, thr, path, length, org, dirs = branches(v, depth)
        if len(pix) == 0:
            break
        rays_per_depth.append(len(pix))
        if skip_faces is None:
            # The rays moved into the tracing frame on this part's thread: only the query holds a shared tracer.
            h = trace_local(tracer, local_rays(tracer, org, dirs), org, dirs.astype(np.float32))
        else:
            h = walk_past(tracer, org, dirs, np.inf, skip_faces)
        if not (np.asarray(h.prim) >= 0).any():
            break
        lit, v = branches.surfaces(t_s, h, (pix, thr, path, length, org, dirs), emission, depth < max_depth)
        if lit is not None:
            found.append(lit)
    return found, rays_per_depth
