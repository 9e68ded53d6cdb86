"""A frame with every material kind: specular chains (mirror, glass) ending in direct lighting of diffuse and
glossy surfaces, through the tracer interface (so it runs on every backend).

Light transport, per pixel (one pixel-centre primary ray, like the G-buffer):

* every surface a path reaches adds its emission seen from the front (``area`` emitters are one-sided);
* a diffuse or glossy surface (diffuse, rough_conductor, rough_plastic) adds its direct lighting and ends the
  path: point lights with one shadow ray each (``f * cos * I / d^2``), triangle area lights with ``area_samples``
  stratified light samples (the estimator of :mod:`suite.core.shading`, with the full BSDF instead of rho/pi);
* a mirror continues along the reflection about the shading normal, weighted by its Fresnel term x specular
  reflectance; glass continues along *both* the reflected (weight F) and the refracted ray (weight
  (1 - F) eta_ti^2, Mitsuba's radiance scaling for the solid-angle compression at the interface). Total internal
  reflection has F = 1 and no refracted ray;
* alpha-tested surfaces are skipped by the tracer itself where transparent (:mod:`suite.core.trace.alpha`);
* ``max_bounces`` (default 5) is the number of specular interactions a path may make and still be lit at its
  end: a diffuse or glossy surface reached after at most ``max_bounces`` of them gets direct lighting; one more
  specular interaction is traced only to add the emission of what it reaches.

That is what Mitsuba's ``path`` integrator computes with ``max_depth = max_bounces + 2`` on scenes where no light
reaches a diffuse or glossy surface by way of another one (no indirect diffuse light, no caustics): Mitsuba
counts the vertex where a path may still sample a light as depth ``max_depth - 2``. The deterministic branching
(both glass branches, every light) replaces Mitsuba's random choices with their expectations, so point-lit
images are noise-free. BSDFs are Mitsuba's (:mod:`suite.core.bsdf`); tests/core/test_materials.py compares
against Mitsuba.

Sidedness: diffuse surfaces are lit on the side they are seen from (like the G-buffer); mirror and the rough
kinds are black from the back unless ``Material.twosided`` (Mitsuba's conductor/plastic plugins are one-sided);
glass refracts from both sides, with the side given by the interpolated shading normal as in Mitsuba.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from suite.core.bsdf import eval_bsdf, fresnel_conductor, fresnel_dielectric, reflect, refract
from suite.core.gbuffer import GBuffer, surface_attributes, trace_primary
from suite.core.shading import SHADOW_TMAX_SCALE, AreaLights, min_light_distance, point_light_visibility
from suite.core.trace.robust import offset_ray_origin

DEFAULT_MAX_BOUNCES = 5


@dataclass
class MaterialFrame:
    """What :func:`render_materials` returns."""

    image: np.ndarray  # (H, W, 3) float32 linear radiance
    gbuffer: GBuffer  # the primary visibility the frame was shaded from (with material ids and kinds)
    rays_per_bounce: list[int]  # continuation rays traced after specular bounce 1, 2, ... (primary rays excluded)


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


class _Vertices:
    """Path vertices on surfaces: where the rays (o, d) hit, with what each path carries."""

    def __init__(self, scene, positions, normals, pixel, throughput, o, d, hits):
        ok = hits.prim >= 0
        self.pixel, self.throughput = pixel[ok], throughput[ok]
        self.d = d[ok]
        self.prim = hits.prim[ok]
        p, ng, ns, albedo, emission = surface_attributes(scene, positions, normals, self.prim, hits.u[ok],
                                                         hits.v[ok], o[ok], d[ok])
        self.p, self.ng, self.ns = p, ng, ns  # raw orientation: ng from the winding, ns interpolated
        self.albedo = albedo.astype(np.float64)
        self.front = _dot(ng, self.d) < 0  # the ray arrived on the side the winding's normal points to
        self.emission = np.where(self.front[:, None], emission, 0.0).astype(np.float64)
        self.material = scene.face_material[self.prim]
        # Normals on the side the ray came from (what the G-buffer stores).
        self.ng_view = np.where(self.front[:, None], ng, -ng)
        self.ns_view = np.where(_dot(ns, self.ng_view)[:, None] < 0, -ns, ns)

    def __len__(self):
        return len(self.prim)

    def subset(self, sel):
        out = object.__new__(_Vertices)
        for k, v in self.__dict__.items():
            out.__dict__[k] = v[sel]
        return out


def _shading_normal(mat, v: _Vertices):
    """The normal a material's BSDF is evaluated around: for diffuse surfaces the G-buffer's (the side they are
    seen from); for two-sided glossy ones the interpolated normal turned toward the viewer, as Mitsuba's
    ``twosided`` does; for one-sided ones the interpolated normal as stored (their back evaluates to zero)."""
    if mat.shading_kind == "diffuse":
        return v.ns_view
    if mat.twosided:
        return np.where(_dot(-v.d, v.ns)[:, None] < 0, -v.ns, v.ns)
    return v.ns


def _direct(scene, v: _Vertices, tracer, lights, area: AreaLights, area_samples: int, rng, min_d: float):
    """(N, 3) direct lighting (BSDF x cos x light) at diffuse/glossy vertices."""
    n = len(v)
    out = np.zeros((n, 3), np.float64)
    if n == 0:
        return out
    wi = -v.d
    nsh = np.empty((n, 3))
    groups = {}
    for mid in np.unique(v.material):
        sel = np.nonzero(v.material == mid)[0]
        mat = scene.materials[int(mid)]
        groups[int(mid)] = (mat, sel)
        nsh[sel] = _shading_normal(mat, v.subset(sel))

    def bsdf(wo, rows):
        """f * cos(theta_o) for vertex rows ``rows`` and directions ``wo``."""
        val = np.zeros((len(rows), 3))
        mats = v.material[rows]
        for mid, (mat, _) in groups.items():
            s = np.nonzero(mats == mid)[0]
            if len(s):
                r = rows[s]
                val[s] = eval_bsdf(mat, wi[r], wo[s], nsh[r], v.albedo[r])
        return val

    all_rows = np.arange(n)
    if lights:
        g = SimpleNamespace(position=v.p[None], geo_normal=v.ng_view[None], valid=np.ones((1, n), bool),
                            depth=np.zeros((1, n), np.float32))
        vis = point_light_visibility(g, lights, tracer)[0]
        for li, light in enumerate(lights):
            rows = np.nonzero(vis[:, li])[0]
            if len(rows) == 0:
                continue
            to_light = np.asarray(light.position, np.float64) - v.p[rows]
            dist2 = np.maximum(_dot(to_light, to_light), min_d ** 2)
            wo = to_light / np.sqrt(np.maximum(_dot(to_light, to_light), 1e-300))[:, None]
            out[rows] += bsdf(wo, rows) * (np.asarray(light.intensity, np.float64) / dist2[:, None])
    if len(area) and area_samples > 0:
        out += _area_direct(v, nsh, bsdf, all_rows, area, tracer, area_samples, rng, min_d)
    return out


def _area_direct(v, nsh, bsdf, rows, area: AreaLights, tracer, samples, rng, min_d, chunk=1 << 15):
    """Light-sampled triangle area lights (the stratification of :func:`suite.core.shading.area_light_radiance`)."""
    n = len(rows)
    out = np.zeros((n, 3))
    side = max(int(np.ceil(np.sqrt(samples))), 1)
    strata = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
    strata = strata[np.linspace(0, len(strata) - 1, samples).round().astype(int)]
    for c0 in range(0, n, chunk):
        r = rows[c0:c0 + chunk]
        m = len(r)
        xi = (np.arange(samples)[None, :] + rng.random((m, samples))) / samples
        rng.permuted(xi, axis=1, out=xi)
        light = np.minimum(np.searchsorted(area.cdf, xi * area.cdf[-1], side="right"), len(area.cdf) - 1)
        uv = (strata[None, :, :] + rng.random((m, samples, 2))) / side
        su = np.sqrt(uv[..., 0])
        b1, b2 = 1.0 - su, uv[..., 1] * su
        y = area.p0[light] + b1[..., None] * area.e1[light] + b2[..., None] * area.e2[light]
        x = v.p[r][:, None, :]
        to_y = y - x
        d2 = np.einsum("psc,psc->ps", to_y, to_y)
        dist = np.sqrt(np.maximum(d2, 1e-300))
        wdir = to_y / dist[..., None]
        dist2 = np.maximum(d2, min_d ** 2)
        cos_y = -np.einsum("psc,psc->ps", wdir, area.normal[light])
        cos_x = np.einsum("psc,pc->ps", wdir, nsh[r])
        active = (cos_y > 0) & (cos_x > 0)
        pdf_area = area.pmf[light] / np.maximum(area.area[light], 1e-300)
        weight = np.where(active, cos_y / dist2 / np.maximum(pdf_area, 1e-300), 0.0)
        flat = np.nonzero(active.reshape(-1))[0]
        if len(flat):
            pix, smp = np.divmod(flat, samples)
            origin = offset_ray_origin(v.p[r][pix], v.ng_view[r][pix], getattr(tracer, "shift", None))
            seg = y[pix, smp] - origin
            seg_len = np.linalg.norm(seg, axis=-1)
            d = (seg / np.maximum(seg_len, 1e-30)[:, None]).astype(np.float32)
            occ = tracer.occluded(origin, d, 0.0, (seg_len * SHADOW_TMAX_SCALE).astype(np.float32))
            f = bsdf(wdir[pix, smp], r[pix])
            contrib = f * (weight[pix, smp] * ~occ)[:, None] * area.radiance[light[pix, smp]]
            np.add.at(out, c0 + pix, contrib / samples)
    return out


def _continue_specular(scene, v: _Vertices, shift):
    """Continuation rays of mirror and glass vertices: (pixel, throughput, origins, dirs) float64."""
    pix, thr, org, dirs = [], [], [], []
    wi = -v.d
    for mid in np.unique(v.material):
        mat = scene.materials[int(mid)]
        sel = np.nonzero(v.material == mid)[0]
        n, ng, p = v.ns[sel], v.ng[sel], v.p[sel]
        w = wi[sel]
        cos_i = _dot(w, n)
        branches = []
        if mat.kind == "mirror":
            if mat.twosided:
                n = np.where(cos_i[:, None] < 0, -n, n)
                cos_i = np.abs(cos_i)
            ok = cos_i > 0  # one-sided: a mirror seen from the back is black (Mitsuba's conductor)
            weight = fresnel_conductor(cos_i[:, None], mat.conductor_eta.astype(np.float64),
                                       mat.conductor_k.astype(np.float64)) * mat.specular_reflectance
            branches.append((ok, reflect(w, n), weight))
        else:  # glass
            f, cos_t, _, eta_ti = fresnel_dielectric(cos_i, mat.eta)
            branches.append((f > 0, reflect(w, n), f[:, None] * mat.specular_reflectance))
            t_weight = ((1.0 - f) * eta_ti * eta_ti)[:, None] * mat.specular_transmittance
            branches.append((f < 1, refract(w, n, cos_t, eta_ti), t_weight))
        for ok, wo, weight in branches:
            keep = ok & np.any(weight > 0, axis=-1)
            if not keep.any():
                continue
            wo = _unit(wo[keep])
            side = np.where(_dot(wo, ng[keep]) >= 0, 1.0, -1.0)[:, None]
            org.append(offset_ray_origin(p[keep], side * ng[keep], shift))
            dirs.append(wo)
            pix.append(v.pixel[sel][keep])
            thr.append(v.throughput[sel][keep] * weight[keep])
    if not pix:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pix), np.concatenate(thr), np.concatenate(org), np.concatenate(dirs)


def render_materials(scene, tracer, t_s: float, resolution=None, max_bounces: int = DEFAULT_MAX_BOUNCES,
                     area_samples: int = 16, seed: int = 0, prev_t_s: float | None = None) -> MaterialFrame:
    """Renders the scene at ``t_s`` with every material kind (see the module docstring for the transport).

    Equivalent Mitsuba reference: ``path`` with ``max_depth = max_bounces + 2`` (``volpath`` when the scene has
    alpha-tested materials, whose shadow rays Mitsuba's ``path`` does not pass through) on scenes without
    indirect diffuse light. Point lights are exact; area lights use ``area_samples`` samples per vertex.
    ``prev_t_s`` gives the G-buffer's motion vectors (as :func:`suite.core.gbuffer.render_gbuffer`).
    """
    if max_bounces < 0:
        from suite.errors import UserError

        raise UserError(f"max_bounces must be >= 0, got {max_bounces}")
    g, o64, d64, hits = trace_primary(scene, tracer, t_s, resolution, prev_t_s)
    h, w = g.depth.shape
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)
    lights = scene.lights_at(t_s)
    area = AreaLights(scene, t_s)
    min_d = min_light_distance(scene)
    rng = np.random.default_rng(seed)
    shift = getattr(tracer, "shift", None)
    is_specular = np.array([m.is_specular for m in scene.materials], bool)

    image = np.zeros((h * w, 3), np.float64)
    v = _Vertices(scene, positions, normals, np.arange(h * w), np.ones((h * w, 3)), o64, d64, hits)
    rays_per_bounce = []
    for depth in range(max_bounces + 2):
        np.add.at(image, v.pixel, v.throughput * v.emission)
        if depth > max_bounces or len(v) == 0:
            break
        spec = is_specular[v.material]
        surf = v.subset(~spec)
        if len(surf):
            light = _direct(scene, surf, tracer, lights, area, area_samples, rng, min_d)
            np.add.at(image, surf.pixel, surf.throughput * light)
        if not spec.any():
            break
        pix, thr, org, dirs = _continue_specular(scene, v.subset(spec), shift)
        rays_per_bounce.append(len(pix))
        if len(pix) == 0:
            break
        d32 = dirs.astype(np.float32)
        hits_next = tracer.intersect(org, d32)
        v = _Vertices(scene, positions, normals, pix, thr, org, d32.astype(np.float64), hits_next)
    return MaterialFrame(image.reshape(h, w, 3).astype(np.float32), g, rays_per_bounce)
