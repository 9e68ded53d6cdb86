"""Primary ray stage (seed 001 §4.1, §6.3, §6.4; Tables 6.3, 6.4; Algorithm 6.1).

One ray per pixel to the first opaque surface, written to a G-buffer. Two buffers come out:

* the **G-buffer** ``g`` of ``suite.core.gbuffer.trace_primary`` (pixel-centre rays): position, normals, albedo,
  material and kind, primitive id, depth and motion vectors. It guides the denoiser (normals, depth, motion),
  like the rasterised G-buffer of q2vkpt.
* the **shading sample** :class:`Surface` of every pixel: the surface the pixel's colour is computed at. Without
  anti-aliasing jitter or depth of field it is the G-buffer's own hit. With ``rt_antialiasing`` the ray goes
  through a random point of the pixel (Table 2.1), with ``rt_dof`` it starts at a random point of a thin lens
  of radius ``dof_aperture_m`` and passes through the point at ``dof_focal_m`` on the pixel's centre ray. It
  keeps the primitive and barycentrics, so that A-SVGF can re-shade exactly that point in the next frame.

**Transparent overlays** (§6.4, Algorithm 6.1). Surfaces that need no shading (flames, glows) are collected
along the primary ray up to the first opaque surface and blended over the shaded colour in the composition
(§6.11): ``ADD`` adds its colour, ``ALPHA`` blends with its opacity. Which faces are overlays comes from the scene:
on Quake III maps the per-face flags of ``scene.q3`` (``blend_add``, ``blend_blend``, ``blend_filter``;
docs/scenes.md). The thesis gathers them in an any-hit shader in arbitrary order and can only order two of them
(the "three-surface limitation", §6.4); here the ray walks them front to back (one closest-hit query per layer,
up to ``MAX_OVERLAY_LAYERS``), so any number blend in the right order: ``C += T * a * c``, ``T *= 1 - a`` for
ALPHA and ``C += T * c`` for ADD, and the pixel shows ``C + T * shaded``. Overlays cast no shadows and are passed
by secondary rays. Alpha-tested surfaces (semi-opaque, §6.5: continued where alpha < 0.5) are handled by the
tracers themselves (``suite.core.trace.alpha``).

The suite's Quake III loader drops additive faces from the geometry (docs/scenes.md, "additive effect: not
geometry"), so on the listed maps only ALPHA-blended faces (e.g. oa_ctf2's jump-pad glows, which the scene model
calls glass) are overlays; ADD blending is exercised by the tests on synthetic scenes.

**Cost.** On a host tracer the shading rays' directions and their surfaces (geometry, texture lookup, facing) are
compiled passes over the pixels (:func:`camera_rays`, :func:`surface_from_hits`, each with the bits of its numpy
reference), and the surfaces are computed on a worker thread while the G-buffer's rays are traced, so that the
stage costs little more than its two closest-hit queries and the G-buffer's own pass (the ``rays`` part of
``splitbench bench quake_drt``). On a Dr.Jit tracer the G-buffer is the device's (suite.core.device.gbuffer) and
jittered pinhole samples are one device kernel (:mod:`methods.quake_drt.device_primary`), both with the host
passes' bits on ``llvm_ad_rgb``; depth of field and overlays keep the host passes.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from methods.quake_drt.direct import jitter_nb
from methods.quake_drt.rng import DIM_JITTER_X, DIM_JITTER_Y, DIM_LENS_U, DIM_LENS_V, uniform_np
from suite.core import gbuffer as _gbuffer, pipeline
from suite.core.gbuffer import material_tables, surface_attributes, texture_table, trace_primary
from suite.core.trace.base import Hits

OVERLAY_NONE, OVERLAY_ADD, OVERLAY_ALPHA = 0, 1, 2
MAX_OVERLAY_LAYERS = 16
TRANSPARENCY_MODES = ("blend", "scene")


@dataclass
class Surface:
    """The shading sample of every pixel (row-major, N = W * H)."""

    valid: np.ndarray  # (N,) bool
    prim: np.ndarray  # (N,) int64, -1 for background
    u: np.ndarray  # (N,) float64 barycentrics of the hit
    v: np.ndarray
    p: np.ndarray  # (N, 3) float64 world position
    ng: np.ndarray  # (N, 3) geometric normal as wound (raw)
    ns: np.ndarray  # (N, 3) interpolated shading normal (raw)
    ng_view: np.ndarray  # (N, 3) geometric normal on the viewer's side
    ns_view: np.ndarray  # (N, 3) shading normal on the viewer's side
    albedo: np.ndarray  # (N, 3) float64
    emission: np.ndarray  # (N, 3) float64 emitted radiance toward the viewer (front side of emitters only)
    material: np.ndarray  # (N,) int64
    o: np.ndarray  # (N, 3) float64 ray origins
    d: np.ndarray  # (N, 3) float64 unit ray directions
    t: np.ndarray  # (N,) float64 hit distance (inf for background)
    overlay_rgb: np.ndarray  # (N, 3) colour of the transparent overlays in front of the surface
    overlay_t: np.ndarray  # (N,) their transmittance (1 = no overlay)

    @property
    def n_overlay_pixels(self) -> int:
        return int(((self.overlay_t < 1.0) | (self.overlay_rgb.sum(axis=1) > 0)).sum())


def overlay_faces(scene, mode: str = "blend") -> np.ndarray | None:
    """(F,) int8 overlay kind of every face (``OVERLAY_*``), or None when the scene marks none (or ``mode`` is
    "scene": every surface is what the scene model says, e.g. glass)."""
    if mode == "scene":
        return None
    info = getattr(scene, "q3", None)
    if info is None or getattr(info, "face_flags", None) is None:
        return None
    from suite.core.scene.q3 import FLAGS

    flags = np.asarray(info.face_flags, np.int64)[np.asarray(info.triangle_face, np.int64)]
    kind = np.zeros(scene.num_faces, np.int8)
    kind[(flags & (FLAGS["blend_blend"] | FLAGS["blend_filter"])) != 0] = OVERLAY_ALPHA
    kind[(flags & FLAGS["blend_add"]) != 0] = OVERLAY_ADD
    return kind if kind.any() else None


def camera_rays(scene, t_s: float, width: int, height: int, seeds: np.ndarray, jitter: bool,
                aperture_m: float = 0.0, focal_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 origins and unit directions of the shading rays: the G-buffer's pinhole camera
    (Mitsuba's perspective sensor, fov along x; suite.core.gbuffer), through a random point of each pixel
    (``jitter``) and from a random point of a thin lens (``aperture_m`` > 0, focused at ``focal_m``)."""
    pose = scene.camera.pose_at(t_s)
    forward, right, up = pose.basis()
    seeds = np.asarray(seeds, np.uint32).reshape(-1)
    jx = uniform_np(seeds, DIM_JITTER_X) - 0.5 if jitter else np.zeros(len(seeds))
    jy = uniform_np(seeds, DIM_JITTER_Y) - 0.5 if jitter else np.zeros(len(seeds))
    tan_x = np.tan(np.radians(scene.camera.fov_deg) / 2.0)
    aspect = width / height
    origin = np.broadcast_to(np.asarray(pose.position, np.float64), (width * height, 3)).copy()
    if aperture_m > 0.0:
        col = np.tile(np.arange(width), height).astype(np.float64)
        row = np.repeat(np.arange(height), width).astype(np.float64)
        px = (2.0 * (col + 0.5 + jx) / width - 1.0) * tan_x
        py = -(2.0 * (row + 0.5 + jy) / height - 1.0) * tan_x / aspect
        d = forward[None, :] + px[:, None] * right[None, :] + py[:, None] * up[None, :]
        focus = origin + d * focal_m  # d has unit length along forward: the plane at focal_m ahead
        r = aperture_m * np.sqrt(uniform_np(seeds, DIM_LENS_U))
        phi = 2.0 * np.pi * uniform_np(seeds, DIM_LENS_V)
        origin = origin + (r * np.cos(phi))[:, None] * right + (r * np.sin(phi))[:, None] * up
        d = focus - origin
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return origin, d
    # A pinhole (jittered or not): one compiled pass over the pixels, the float64 operations of the numpy
    # expressions above in their order (tests/methods/quake_drt/test_kernels.py).
    n = width * height
    d = np.empty((n, 3))
    _kernels()[0](np.asarray(forward, np.float64), np.asarray(right, np.float64), np.asarray(up, np.float64),
                  float(tan_x), aspect, int(width), int(height), 0, int(height),
                  np.ascontiguousarray(np.broadcast_to(jx, (n,)), np.float64),
                  np.ascontiguousarray(np.broadcast_to(jy, (n,)), np.float64), d)
    return origin, d


def camera_rays_reference(scene, t_s: float, width: int, height: int, seeds: np.ndarray, jitter: bool):
    """:func:`camera_rays` of a pinhole camera as whole-array numpy expressions (the reference its compiled pass is
    tested against)."""
    pose = scene.camera.pose_at(t_s)
    forward, right, up = pose.basis()
    seeds = np.asarray(seeds, np.uint32).reshape(-1)
    jx = uniform_np(seeds, DIM_JITTER_X) - 0.5 if jitter else np.zeros(len(seeds))
    jy = uniform_np(seeds, DIM_JITTER_Y) - 0.5 if jitter else np.zeros(len(seeds))
    col = np.tile(np.arange(width), height).astype(np.float64)
    row = np.repeat(np.arange(height), width).astype(np.float64)
    tan_x = np.tan(np.radians(scene.camera.fov_deg) / 2.0)
    aspect = width / height
    px = (2.0 * (col + 0.5 + jx) / width - 1.0) * tan_x
    py = -(2.0 * (row + 0.5 + jy) / height - 1.0) * tan_x / aspect
    d = forward[None, :] + px[:, None] * right[None, :] + py[:, None] * up[None, :]
    origin = np.broadcast_to(np.asarray(pose.position, np.float64), d.shape).copy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return origin, d


def _camera(forward, right, up, tan_x, aspect, width, height, row0, row1, jx, jy, out):
    """Unit directions through the pixels of rows ``row0:row1`` offset by (jx, jy) (``jx``, ``jy`` and ``out`` hold
    the whole image): the float64 operations of :func:`camera_rays_reference` in their order (numpy's norm sums the
    squares as (x + y) + z)."""
    for i in range(row0, row1):
        for j in range(width):
            k = i * width + j
            px = (2.0 * ((np.float64(j) + 0.5) + jx[k]) / width - 1.0) * tan_x
            py = -(2.0 * ((np.float64(i) + 0.5) + jy[k]) / height - 1.0) * tan_x / aspect
            dx = (forward[0] + px * right[0]) + py * up[0]
            dy = (forward[1] + px * right[1]) + py * up[1]
            dz = (forward[2] + px * right[2]) + py * up[2]
            norm = np.sqrt((dx * dx + dy * dy) + dz * dz)
            out[k, 0] = dx / norm
            out[k, 1] = dy / norm
            out[k, 2] = dz / norm


def walk_past(tracer, o: np.ndarray, d: np.ndarray, tmax, skip_faces: np.ndarray, layers: list | None = None) -> Hits:
    """Closest hits of world-space rays that pass the faces where ``skip_faces`` is set (overlays): each such
    hit is recorded in ``layers`` (a list of ``(ray index, prim, u, v, t)`` arrays, front to back) and the ray is
    traced again from just past it. ``t`` of the result is measured from ``o``."""
    n = len(o)
    o = np.asarray(o, np.float64)
    d = np.asarray(d, np.float64)
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (n,)).copy()
    out_t = np.full(n, np.inf)
    out_prim = np.full(n, -1, np.int64)
    out_u = np.zeros(n)
    out_v = np.zeros(n)
    todo = np.arange(n)
    start = np.zeros(n)
    d32 = d.astype(np.float32)
    for _ in range(MAX_OVERLAY_LAYERS + 1):
        if len(todo) == 0:
            break
        org = o[todo] + d[todo] * start[todo, None]
        h = tracer.intersect(org, d32[todo], 0.0, np.maximum(tmax[todo] - start[todo], 0.0).astype(np.float32))
        prim = np.asarray(h.prim, np.int64)
        t = start[todo] + np.asarray(h.t, np.float64)
        hit = prim >= 0
        skip = np.zeros(len(todo), bool)
        skip[hit] = skip_faces[prim[hit]]
        done = ~skip
        r = todo[done]
        out_t[r], out_prim[r] = np.where(hit[done], t[done], np.inf), prim[done]
        out_u[r], out_v[r] = h.u[done], h.v[done]
        if skip.any():
            r = todo[skip]
            if layers is not None:
                layers.append((r, prim[skip], np.asarray(h.u)[skip].astype(np.float64),
                               np.asarray(h.v)[skip].astype(np.float64), t[skip]))
            start[r] = t[skip] + 1e-5 * (1.0 + t[skip])  # just past the overlay
        todo = todo[skip]
    if len(todo):  # more layers than MAX_OVERLAY_LAYERS: the last one counts as opaque
        out_prim[todo] = -1
    return Hits(out_t.astype(np.float32), out_prim.astype(np.int32), out_u.astype(np.float32),
                out_v.astype(np.float32))


def _attributes(scene, t_s, o, d, prim, u, v):
    """Surface attributes of hits, with normals raw and turned toward the ray origin (as the G-buffer does)."""
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)
    p, ng, ns, albedo, emission = surface_attributes(scene, positions, normals, prim, u, v, o, d)
    flip = np.sign(np.einsum("ij,ij->i", ng, d))
    flip[flip == 0] = 1.0
    front = flip < 0
    ng_view = -flip[:, None] * ng
    ns_view = np.where(np.einsum("ij,ij->i", ns, ng_view)[:, None] < 0, -ns, ns)
    return p, ng, ns, ng_view, ns_view, albedo.astype(np.float64), np.where(front[:, None], emission, 0.0)


def surface_from_hits(scene, t_s: float, o: np.ndarray, d: np.ndarray, prim, u, v, t) -> Surface:
    """The shading sample of hits ``(prim, u, v, t)`` of float64 rays ``(o, d)``: position on the ray's plane
    intersection, raw and viewer-side normals, albedo (textures looked up), front-side emission, material. One
    compiled pass over the hits (:func:`_surface_pass`) with the bits of :func:`surface_from_hits_reference`
    (suite.core.gbuffer.surface_attributes and the facing of :func:`_attributes`); scenes whose textures it
    does not take (channels other than 1 or 3) take the reference."""
    textures = _texture_table(scene)
    if textures is None:
        return surface_from_hits_reference(scene, t_s, o, d, prim, u, v, t)
    s = _new_surface(o, d)
    if len(o):
        _fill_surface(scene, t_s, textures, s, 0, len(o), prim, u, v, t)
    return s


def _new_surface(o, d) -> Surface:
    """A Surface for the rays (o, d), its per-hit fields not yet filled (:func:`_fill_surface`)."""
    n = len(o)
    return Surface(valid=np.empty(n, bool), prim=np.empty(n, np.int64), u=np.empty(n), v=np.empty(n),
                   p=np.empty((n, 3)), ng=np.empty((n, 3)), ns=np.empty((n, 3)), ng_view=np.empty((n, 3)),
                   ns_view=np.empty((n, 3)), albedo=np.empty((n, 3)), emission=np.empty((n, 3)),
                   material=np.empty(n, np.int64), o=np.asarray(o, np.float64), d=np.asarray(d, np.float64),
                   t=np.empty(n), overlay_rgb=np.zeros((n, 3)), overlay_t=np.ones(n))


def _fill_surface(scene, t_s: float, textures, s: Surface, a: int, b: int, prim, u, v, t) -> None:
    """Rows ``a:b`` of ``s`` from the hits ``(prim, u, v, t)`` of its rays ``a:b`` (:func:`_surface_pass`)."""
    albedo_table, emission_table, tex_slot, tex_shape, tex_data = textures
    _kernels()[1](np.ascontiguousarray(scene.positions_at(t_s)), np.ascontiguousarray(scene.normals_at(t_s)),
                  scene.faces, scene.face_material, albedo_table, emission_table, tex_slot, tex_shape, tex_data,
                  scene.uvs if scene.uvs is not None else np.zeros((1, 2), np.float32),
                  np.ascontiguousarray(s.o[a:b]), np.ascontiguousarray(s.d[a:b]), np.ascontiguousarray(prim),
                  np.ascontiguousarray(u), np.ascontiguousarray(v), np.ascontiguousarray(t), s.valid[a:b],
                  s.prim[a:b], s.u[a:b], s.v[a:b], s.t[a:b], s.p[a:b], s.ng[a:b], s.ns[a:b], s.ng_view[a:b],
                  s.ns_view[a:b], s.albedo[a:b], s.emission[a:b], s.material[a:b])


def surface_from_hits_reference(scene, t_s: float, o: np.ndarray, d: np.ndarray, prim, u, v, t) -> Surface:
    """:func:`surface_from_hits` through suite.core.gbuffer.surface_attributes and whole-array numpy expressions
    (the reference its compiled pass is tested against)."""
    n = len(o)
    prim = np.asarray(prim, np.int64)
    valid = prim >= 0
    s = empty_surface(n)
    s.o, s.d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    s.valid, s.prim = valid, np.where(valid, prim, -1)
    s.u, s.v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    s.t = np.where(valid, np.asarray(t, np.float64), np.inf)
    idx = np.nonzero(valid)[0]
    if len(idx):
        p, ng, ns, ngv, nsv, alb, em = _attributes(scene, t_s, s.o[idx], s.d[idx], prim[idx], s.u[idx], s.v[idx])
        s.p[idx], s.ng[idx], s.ns[idx], s.ng_view[idx], s.ns_view[idx] = p, ng, ns, ngv, nsv
        s.albedo[idx], s.emission[idx] = alb, em
        s.material[idx] = scene.face_material[prim[idx]]
    return s


def _texture_table(scene):
    """(albedo per material (M, 3) float32, emission per material (M, 3) float32, then
    :func:`suite.core.gbuffer.texture_table`: texture slot per material (-1: constant albedo), (slots, 4) int64 rows
    of height, width, channels and offset, all albedo textures packed flat in one float32 array); None when a
    texture has other than 1 or 3 channels or values float32 does not hold exactly (then the reference path)."""
    mats = scene.materials
    textures = [m.albedo_texture for m in mats if m.albedo_texture is not None]
    if scene.uvs is None and textures:
        return None  # textures without coordinates: the reference's error
    for tex in textures:
        tex = np.asarray(tex)
        if tex.ndim != 3 or tex.shape[2] not in (1, 3) or tex.dtype not in (np.float32, np.uint8, np.uint16):
            return None
    return (*material_tables(scene), *texture_table(scene))


def _surface_pass(positions, normals, faces, face_material, albedo_table, emission_table, tex_slot, tex_shape,
                  tex_data, uvs, o, d, prim, u, v, t, valid, prim_out, u_out, v_out, t_out, p, ng, ns, ng_view,
                  ns_view, albedo, emission, material):
    """Per hit, the fields of :func:`surface_from_hits_reference`: suite.core.gbuffer's float64 hit geometry
    (``_hit_geometry``; barycentrics (1 - u) - v in float64, the position on the ray's plane, normals), the bilinear
    repeating texture lookup of ``lookup_texture`` (rounded to float32 as it returns), and the facing of
    :func:`_attributes` (np.einsum's dot products sum as (x + z) + y); background values for a miss."""
    for i in range(prim.shape[0]):
        f = prim[i]
        b1, b2 = np.float64(u[i]), np.float64(v[i])
        u_out[i], v_out[i] = b1, b2
        if f < 0:
            valid[i] = False
            prim_out[i] = -1
            t_out[i] = np.inf
            material[i] = -1
            for k in range(3):
                p[i, k] = 0.0
                ng[i, k] = 0.0
                ns[i, k] = 0.0
                ng_view[i, k] = 0.0
                ns_view[i, k] = 0.0
                albedo[i, k] = 0.0
                emission[i, k] = 0.0
            continue
        valid[i] = True
        prim_out[i] = f
        t_out[i] = np.float64(t[i])
        b0 = (1.0 - b1) - b2
        f0, f1, f2 = faces[f, 0], faces[f, 1], faces[f, 2]
        rox, roy, roz = o[i, 0], o[i, 1], o[i, 2]
        rdx, rdy, rdz = d[i, 0], d[i, 1], d[i, 2]
        r = _gbuffer._hit_geometry_jit(positions, normals, f0, f1, f2, b0, b1, b2, True, rox, roy, roz, rdx, rdy, rdz)
        px, py, pz, gx, gy, gz, nx, ny, nz = r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]
        p[i, 0], p[i, 1], p[i, 2] = px, py, pz
        ng[i, 0], ng[i, 1], ng[i, 2] = gx, gy, gz
        ns[i, 0], ns[i, 1], ns[i, 2] = nx, ny, nz
        # Facing: sign(ng . d), 0 counted as +1; both normals on the viewer's side.
        flip = -1.0 if ((gx * rdx + gz * rdz) + gy * rdy) < 0.0 else 1.0
        vx, vy, vz = -flip * gx, -flip * gy, -flip * gz
        ng_view[i, 0], ng_view[i, 1], ng_view[i, 2] = vx, vy, vz
        back = ((nx * vx + nz * vz) + ny * vy) < 0.0
        ns_view[i, 0] = -nx if back else nx
        ns_view[i, 1] = -ny if back else ny
        ns_view[i, 2] = -nz if back else nz
        m = face_material[f]
        material[i] = m
        for k in range(3):
            emission[i, k] = np.float64(emission_table[m, k]) if flip < 0.0 else 0.0
        slot = tex_slot[m]
        if slot < 0:
            for k in range(3):
                albedo[i, k] = np.float64(albedo_table[m, k])
            continue
        rgb = _gbuffer._texel_jit(uvs, f0, f1, f2, b0, b1, b2, slot, tex_shape, tex_data)
        for k in range(3):
            albedo[i, k] = np.float64(rgb[k])


_compiled = None


def _kernels():
    """:func:`_camera` and :func:`_surface_pass` compiled (numba, on first use)."""
    global _compiled
    if _compiled is None:
        import numba

        _gbuffer._kernels()  # binds suite.core.gbuffer's compiled hit geometry and texel, which _surface_pass calls
        jit = numba.njit(cache=True, nogil=True, error_model="numpy")
        # _surface_pass is not cached: it calls kernels of suite.core.gbuffer, and numba's cache of a function is
        # keyed by its own file only, so a cached _surface_pass could call code of an older gbuffer.py.
        _compiled = (jit(_camera), numba.njit(cache=False, nogil=True, error_model="numpy")(_surface_pass))
    return _compiled


def empty_surface(n: int) -> Surface:
    z3 = lambda: np.zeros((n, 3))  # noqa: E731
    return Surface(valid=np.zeros(n, bool), prim=np.full(n, -1, np.int64), u=np.zeros(n), v=np.zeros(n), p=z3(),
                   ng=z3(), ns=z3(), ng_view=z3(), ns_view=z3(), albedo=z3(), emission=z3(),
                   material=np.full(n, -1, np.int64), o=z3(), d=z3(), t=np.full(n, np.inf), overlay_rgb=z3(),
                   overlay_t=np.ones(n))


def _surface_from_gbuffer(g, o64, d64, hits) -> Surface:
    n = g.depth.size
    s = empty_surface(n)
    s.valid = g.valid.reshape(-1).copy()
    s.prim = np.where(s.valid, g.prim.reshape(-1), -1).astype(np.int64)
    s.u = np.asarray(hits.u, np.float64).copy()
    s.v = np.asarray(hits.v, np.float64).copy()
    s.p = g.position.reshape(-1, 3).astype(np.float64)
    s.ng_view = g.geo_normal.reshape(-1, 3).astype(np.float64)
    s.ns_view = g.normal.reshape(-1, 3).astype(np.float64)
    s.albedo = g.albedo.reshape(-1, 3).astype(np.float64)
    s.emission = g.emission.reshape(-1, 3).astype(np.float64)
    s.material = g.material.reshape(-1).astype(np.int64)
    s.o, s.d = o64, d64
    s.t = np.where(s.valid, g.depth.reshape(-1).astype(np.float64), np.inf)
    return s


def _raw_normals(scene, t_s, s: Surface, idx: np.ndarray) -> None:
    """Fills the raw (as wound / interpolated) normals of the pixels ``idx`` (secondary rays need them)."""
    if len(idx) == 0:
        return
    _, ng, ns, _, _, _, _ = _attributes(scene, t_s, s.o[idx], s.d[idx], s.prim[idx], s.u[idx], s.v[idx])
    s.ng[idx], s.ns[idx] = ng, ns


def _blend_overlays(scene, t_s, s: Surface, layers, overlay_kind, overlay_alpha: float) -> None:
    """Front-to-back composition of the overlay layers found by :func:`walk_past` (Algorithm 6.1, ordered)."""
    if not layers:
        return
    positions, normals = scene.positions_at(t_s), scene.normals_at(t_s)
    for rows, prim, u, v, _ in layers:  # layers are in front-to-back order per ray
        _, _, _, albedo, emission = surface_attributes(scene, positions, normals, prim, u, v)
        colour = np.where(np.any(emission > 0, axis=1)[:, None], emission, albedo).astype(np.float64)
        kind = overlay_kind[prim]
        t = s.overlay_t[rows]
        alpha = np.where(kind == OVERLAY_ADD, 1.0, overlay_alpha)
        s.overlay_rgb[rows] += (t * alpha)[:, None] * colour
        s.overlay_t[rows] = np.where(kind == OVERLAY_ADD, t, t * (1.0 - overlay_alpha))


def primary_stage(scene, tracer, t_s: float, prev_t_s, resolution, seeds: np.ndarray, jitter: bool = False,
                  aperture_m: float = 0.0, focal_m: float = 1.0, overlay_kind: np.ndarray | None = None,
                  overlay_alpha: float = 0.5):
    """(G-buffer, shading samples) of one frame (module docstring).

    With jitter or depth of field the shading rays are traced first, and a worker thread computes their
    surfaces (a compiled pass that releases the GIL) while the G-buffer's pixel-centre rays are traced: the
    same queries and results as one after the other. On a Dr.Jit tracer jittered pinhole samples without overlays
    are a device kernel instead (:mod:`methods.quake_drt.device_primary`; the same queries and values)."""
    from methods.quake_drt import device_primary  # imports this module's limits

    width, height = resolution
    skip = None if overlay_kind is None else overlay_kind > 0
    textures = _texture_table(scene)
    host = getattr(tracer, "device", None) is None
    if jitter and aperture_m <= 0.0 and skip is None and textures is not None and host:
        # Jittered pinhole rays without overlays on a host tracer: both ray sets in one pipeline of row chunks (the
        # backend traces one chunk while a worker makes the next chunk's rays and the previous chunk's surfaces or
        # pixels). A tracer with a Dr.Jit device takes the branch below, whose G-buffer is the device's
        # (suite.core.device; the same bits): on mitsuba-llvm, oa:aggressor 640x360, 73 ms against 96 pipelined.
        tracer.update(t_s)
        shading_steps, s = _shading_steps(scene, tracer, t_s, width, height, seeds, textures)
        gbuffer_steps, gbuffer = _gbuffer.primary_steps(scene, tracer, t_s, width, height, prev_t_s)
        pipeline.pipelined(shading_steps + gbuffer_steps)
        return gbuffer()[0], s
    if device_primary.available(tracer, jitter, aperture_m, skip, textures):
        # On a Dr.Jit tracer: the samples' rays, hits and surfaces in one device kernel, then the device G-buffer
        # (both the host passes' bits); nothing here reads the pixel-centre rays or hits on the host.
        from suite.core.device.gbuffer import render_gbuffer

        s = device_primary.shading_samples(scene, tracer, t_s, width, height, seeds)
        return render_gbuffer(scene, tracer, t_s, (width, height), prev_t_s).to_host_twin(), s
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending, layers = None, []
        if jitter or aperture_m > 0.0:
            tracer.update(t_s)  # the scene at t_s, as the G-buffer's query below sees it (it updates again: a no-op)
            o, d = camera_rays(scene, t_s, width, height, seeds, jitter, aperture_m, focal_m)
            if skip is None:
                h = tracer.intersect(o, d.astype(np.float32))
            else:
                h = walk_past(tracer, o, d, np.inf, skip, layers)
            pending = pool.submit(surface_from_hits, scene, t_s, o, d, h.prim, h.u, h.v, h.t)
        g, o64, d64, hits = trace_primary(scene, tracer, t_s, (width, height), prev_t_s)
        # Pixel centres whose first hit is an overlay: the opaque surface behind it (the G-buffer's guides, and the
        # shading sample when there is no jitter).
        over, centre, centre_layers = np.zeros(0, np.int64), None, []
        if skip is not None:
            over = np.nonzero(g.valid.reshape(-1) & skip[np.maximum(g.prim.reshape(-1), 0)])[0]
            if len(over):
                h = walk_past(tracer, o64[over], d64[over], np.inf, skip, centre_layers)
                centre = surface_from_hits(scene, t_s, o64[over], d64[over], h.prim, h.u, h.v, h.t)
                centre_layers = [(over[r], p, u, v, t) for r, p, u, v, t in centre_layers]
        if pending is not None:
            # surface_from_hits fills the raw normals of every hit already.
            s = pending.result()
            _blend_overlays(scene, t_s, s, layers, overlay_kind, overlay_alpha)
        else:
            s = _surface_from_gbuffer(g, o64, d64, hits)
            if centre is not None:
                _set_rows(s, over, centre)
                _blend_overlays(scene, t_s, s, centre_layers, overlay_kind, overlay_alpha)
            _raw_normals(scene, t_s, s, np.nonzero(s.valid & np.isin(s.material, _raw_normal_materials(scene)))[0])
    if centre is not None:
        _patch_gbuffer(g, over, centre, scene)
    return g, s


def _shading_steps(scene, tracer, t_s: float, width: int, height: int, seeds: np.ndarray, textures):
    """``(steps, samples)``: :func:`surface_from_hits` of the jittered pinhole rays of :func:`camera_rays` as
    pipeline steps over row chunks (:func:`suite.core.pipeline.pipelined`; the same rays, queries and bits as the
    whole-image passes), and the Surface they fill."""
    pose = scene.camera.pose_at(t_s)
    basis = [np.asarray(b, np.float64) for b in pose.basis()]
    seeds = np.asarray(seeds, np.uint32).reshape(-1)
    jx, jy = np.empty(len(seeds)), np.empty(len(seeds))  # the jitter, made per chunk with its rays
    tan_x = float(np.tan(np.radians(scene.camera.fov_deg) / 2.0))
    n = width * height
    position = np.asarray(pose.position, np.float64)
    o = np.empty((n, 3))  # the camera position, written per chunk with its rays
    d, d32 = np.empty((n, 3)), np.empty((n, 3), np.float32)
    s = _new_surface(o, d)
    camera = _kernels()[0]
    queue, trace, hits = _gbuffer.row_queries(tracer, o, d32, width)

    def make(r0, r1):
        a, b = r0 * width, r1 * width
        for c in range(3):  # column by column: numpy's broadcast of a 3-vector over rows is several times slower
            o[a:b, c] = position[c]
        jitter_nb(seeds, a, b, DIM_JITTER_X, DIM_JITTER_Y, jx, jy)
        camera(*basis, tan_x, width / height, int(width), int(height), r0, r1, jx, jy, d)
        d32[a:b] = d[a:b]
        queue(r0, r1)

    def finish(r0, r1):
        a, b = r0 * width, r1 * width
        _fill_surface(scene, t_s, textures, s, a, b, hits.prim[a:b], hits.u[a:b], hits.v[a:b], hits.t[a:b])

    return _gbuffer.row_steps(height, width, make, trace, finish), s


def _raw_normal_materials(scene) -> np.ndarray:
    """Materials whose secondary rays (mirror, glass) or BSDF orientation (glossy) need the raw normals."""
    return np.array([i for i, m in enumerate(scene.materials) if m.is_specular or m.is_glossy], np.int64)


def _set_rows(s: Surface, rows: np.ndarray, sub: Surface) -> None:
    for f in ("valid", "prim", "u", "v", "p", "ng", "ns", "ng_view", "ns_view", "albedo", "emission", "material",
              "o", "d", "t"):
        put_rows(getattr(s, f), rows, getattr(sub, f))
    # overlay colour and transmittance are filled by _blend_overlays


def put_rows(dst: np.ndarray, rows: np.ndarray, src: np.ndarray) -> None:
    """``dst[rows] = src``; (N, k) rows of one dtype are moved as whole rows (a void view of k values): numpy's
    two-dimensional fancy assignment goes value by value, about twice as slow on (N, 3) float64."""
    if dst.ndim == 2 and dst.flags.c_contiguous and src.dtype == dst.dtype and src.shape[1:] == dst.shape[1:]:
        row = np.dtype((np.void, dst.dtype.itemsize * dst.shape[1]))
        dst.view(row)[rows, 0] = np.ascontiguousarray(src).view(row)[:, 0]
    else:
        dst[rows] = src


def _patch_gbuffer(g, rows: np.ndarray, sub: Surface, scene) -> None:
    """The G-buffer guides of pixels whose centre ray hit an overlay: the opaque surface behind it."""
    from suite.core.scene.model import KIND_CODES

    g.detach()  # a Dr.Jit tracer's G-buffer is the read-only twin of its device G-buffer
    flat = lambda a: a.reshape(-1, *a.shape[2:])  # noqa: E731
    flat(g.valid)[rows] = sub.valid
    flat(g.prim)[rows] = sub.prim
    flat(g.position)[rows] = sub.p
    flat(g.normal)[rows] = sub.ns_view
    flat(g.geo_normal)[rows] = sub.ng_view
    flat(g.albedo)[rows] = sub.albedo
    flat(g.emission)[rows] = sub.emission
    flat(g.depth)[rows] = sub.t
    flat(g.material)[rows] = sub.material
    if g.kind is not None:
        codes = np.array([KIND_CODES[m.shading_kind] for m in scene.materials], np.int8)
        flat(g.kind)[rows] = np.where(sub.valid, codes[np.maximum(sub.material, 0)], -1)


def barycentric_points(tri: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) ``(t0 (1 - u - v) + t1 u) + t2 v`` of (N, 3, 3) triangles: the bits of ``(tri * w).sum(axis=1)``
    (numpy adds the three rows in order) without its (N, 3, 3) temporaries."""
    return (tri[:, 0] * (1.0 - u - v)[:, None] + tri[:, 1] * u[:, None]) + tri[:, 2] * v[:, None]


def forwarded_surface(scene, t_s: float, s: Surface, rows: np.ndarray, prim: np.ndarray, u: np.ndarray,
                      v: np.ndarray) -> None:
    """A-SVGF forward projection (Schied et al. 2018 §4.1; seed 001 Table 6.10 "Object Forward"): the pixels
    ``rows`` shade the previous frame's surface samples ``(prim, u, v)`` instead of their own hits. The samples
    are moved to time ``t_s`` (rigid motion) and seen from the current camera; overlays in front are kept."""
    if len(rows) == 0:
        return
    positions = scene.positions_at(t_s)
    p = barycentric_points(positions[scene.faces[prim]].astype(np.float64), u, v)
    o = np.broadcast_to(np.asarray(scene.camera.pose_at(t_s).position, np.float64), p.shape)
    d = p - o
    t = np.linalg.norm(d, axis=1)
    d = d / np.maximum(t, 1e-30)[:, None]
    sub = surface_from_hits(scene, t_s, o, d, prim, u, v, t)
    # The exact previous point (not the plane intersection of the new ray, which is the same point up to rounding).
    sub.p[sub.valid] = p[sub.valid]
    _set_rows(s, rows, sub)
    _raw_normals(scene, t_s, s, rows[np.isin(s.material[rows], _raw_normal_materials(scene))])
