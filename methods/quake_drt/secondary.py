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
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from methods.quake_drt.direct import ShadingPoints
from methods.quake_drt.rng import DIM_SECONDARY, stream_np, uniform_np
from suite.core.bsdf import fresnel_conductor, fresnel_dielectric, reflect, refract
from suite.core.trace.robust import offset_ray_origin

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


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _cone(axis: np.ndarray, cos_max: float, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Uniform directions in the cone of half-angle acos(cos_max) around the unit vectors ``axis``."""
    cos_t = 1.0 - u1 * (1.0 - cos_max)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t * cos_t))
    phi = 2.0 * np.pi * u2
    helper = np.where(np.abs(axis[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = _unit(np.cross(helper, axis))
    t2 = np.cross(axis, t1)
    return _unit(cos_t[:, None] * axis + (sin_t * np.cos(phi))[:, None] * t1 + (sin_t * np.sin(phi))[:, None] * t2)


def lambert_mask(scene, material: np.ndarray) -> np.ndarray:
    lam = np.array([m.shading_kind == "diffuse" for m in scene.materials], bool)
    return lam[np.asarray(material, np.int64)]


def bsdf_normal(scene, material, ns_view, ns_raw, wi) -> np.ndarray:
    """The normal a material's BSDF is evaluated around (as suite.core.specular): the viewer-side normal for
    diffuse surfaces, the interpolated normal turned toward the viewer for two-sided glossy ones, the raw
    interpolated normal for one-sided glossy ones (whose back is black)."""
    out = np.asarray(ns_view, np.float64).copy()
    for mid in np.unique(material):
        m = scene.materials[int(mid)]
        if m.shading_kind == "diffuse" or not m.is_glossy:
            continue
        sel = material == mid
        if m.twosided:
            out[sel] = np.where(_dot(wi[sel], ns_raw[sel])[:, None] < 0, -ns_raw[sel], ns_raw[sel])
        else:
            out[sel] = ns_raw[sel]
    return out


def secondary_stage(scene, tracer, t_s: float, surface, seeds: np.ndarray, max_depth: int = DEFAULT_MAX_DEPTH,
                    all_branches: bool = True, glossy: bool = False, glossy_cone_deg: float = 5.0,
                    skip_faces=None) -> SecondaryResult:
    """Follows the specular chains of the shading samples ``surface`` (module docstring)."""
    from methods.quake_drt.primary import _attributes, walk_past

    n_pix = len(surface.valid)
    emission = np.zeros((n_pix, 3))
    spec = np.array([m.is_specular for m in scene.materials], bool)
    seeds = np.asarray(seeds, np.uint32).reshape(-1)
    rows = np.nonzero(surface.valid & spec[np.maximum(surface.material, 0)])[0]
    v = {"pixel": rows, "thr": np.ones((len(rows), 3)), "path": np.zeros(len(rows), np.int64),
         "length": surface.t[rows].copy(), "p": surface.p[rows], "ng": surface.ng[rows], "ns": surface.ns[rows],
         "d": surface.d[rows], "material": surface.material[rows]}
    shift = getattr(tracer, "shift", None)
    cos_max = float(np.cos(np.radians(glossy_cone_deg)))
    parts, rays_per_depth = [], []
    for depth in range(1, max_depth + 1):
        if len(v["pixel"]) == 0:
            break
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
                wo = reflect(w, n)
                if glossy:
                    wo = _cone(_unit(wo), cos_max, uniform_np(vseed, dim + 1), uniform_np(vseed, dim + 2))
                    below = _dot(wo, np.where(cos_i[:, None] >= 0, n, -n)) <= 0
                    weight = np.where(below[:, None], 0.0, weight)
                branches.append((cos_i > 0, wo, weight, 1))
            else:  # glass / water
                f, cos_t, _, eta_ti = fresnel_dielectric(cos_i, mat.eta)
                r_w = f[:, None] * mat.specular_reflectance
                t_w = ((1.0 - f) * eta_ti * eta_ti)[:, None] * mat.specular_transmittance
                if not all_branches:
                    pick_r = uniform_np(vseed, dim) < f
                    r_w = np.where(pick_r[:, None], mat.specular_reflectance, 0.0)
                    t_w = np.where(pick_r[:, None], 0.0, (eta_ti * eta_ti)[:, None] * mat.specular_transmittance)
                branches.append((f > 0, reflect(w, n), r_w, 1))
                branches.append((f < 1, refract(w, n, cos_t, eta_ti), t_w, 2))
            for ok, wo, weight, tag in branches:
                keep = ok & np.any(weight > 0, axis=-1)
                if not keep.any():
                    continue
                wo = _unit(wo[keep])
                side = np.where(_dot(wo, ng[keep]) >= 0, 1.0, -1.0)[:, None]
                org.append(offset_ray_origin(p[keep], side * ng[keep], shift))
                dirs.append(wo)
                pix.append(v["pixel"][sel][keep])
                thr.append(v["thr"][sel][keep] * weight[keep])
                path.append(v["path"][sel][keep] * 3 + tag)
                length.append(v["length"][sel][keep])
        if not pix:
            break
        pix, thr, path, length = (np.concatenate(x) for x in (pix, thr, path, length))
        org, dirs = np.concatenate(org), np.concatenate(dirs)
        rays_per_depth.append(len(pix))
        if skip_faces is None:
            h = tracer.intersect(org, dirs.astype(np.float32))
        else:
            h = walk_past(tracer, org, dirs, np.inf, skip_faces)
        hit = np.asarray(h.prim) >= 0
        if not hit.any():
            break
        prim = np.asarray(h.prim, np.int64)[hit]
        o_h, d_h = org[hit], dirs[hit]
        p, ng, ns, ngv, nsv, albedo, em = _attributes(scene, t_s, o_h, d_h, prim, np.asarray(h.u)[hit],
                                                      np.asarray(h.v)[hit])
        pix, thr, path = pix[hit], thr[hit], path[hit]
        length = length[hit] + np.asarray(h.t, np.float64)[hit]
        np.add.at(emission, pix, thr * em)
        material = scene.face_material[prim].astype(np.int64)
        is_spec = spec[material]
        lit = ~is_spec
        if lit.any():
            ps = np.nonzero(lit)[0]
            wi = -d_h[ps]
            pseed = stream_np(seeds[pix[ps]], path[ps] & 0xFFFFFFFF)
            parts.append((ShadingPoints(pixel=pix[ps], throughput=thr[ps], p=p[ps], ng=ngv[ps],
                                        ns=bsdf_normal(scene, material[ps], nsv[ps], ns[ps], wi), wi=wi,
                                        albedo=albedo[ps], material=material[ps], prim=prim[ps], seed=pseed,
                                        lambert=lambert_mask(scene, material[ps])), length[ps]))
        cont = np.nonzero(is_spec)[0] if depth < max_depth else np.zeros(0, np.int64)
        v = {"pixel": pix[cont], "thr": thr[cont], "path": path[cont], "length": length[cont], "p": p[cont],
             "ng": ng[cont], "ns": ns[cont], "d": d_h[cont], "material": material[cont]}
    points = ShadingPoints.concat([pt for pt, _ in parts])
    lengths = np.concatenate([ln for _, ln in parts]) if parts else np.zeros(0)
    # The denoiser's guides for specular pixels: the strongest chain's shading point.
    if len(points):
        strength = points.throughput.sum(axis=1)
        order = np.lexsort((-strength, points.pixel))
        first = order[np.r_[True, np.diff(points.pixel[order]) != 0]]
        guide = (points.pixel[first], points.p[first], points.ns[first], lengths[first])
    else:
        guide = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    return SecondaryResult(points, emission, rays_per_depth, *guide)
