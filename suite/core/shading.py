"""Shared direct-lighting kernels, in Mitsuba's units.

Lambertian surfaces (BRDF = rho / pi), lit by

* point lights of intensity I (W/sr): L = rho/pi * I * cos(theta) / d^2, with hard shadows (one shadow ray
  per pixel and light), and
* triangle area lights of radiance L_e (one-sided, emitting along their normal): the area form of the
  rendering equation, L = integral of rho/pi * L_e * cos(theta_x) cos(theta_y) / d^2 dA, estimated with
  ``n`` stratified samples per pixel (soft shadows).

These are the expectations that Mitsuba's ``direct`` integrator estimates, so the images agree with it up to
its noise (see tests/core/test_direct_lighting.py).
"""
from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from suite.core import rng
from suite.core.trace.robust import offset_ray_origin

INV_PI = 1.0 / np.pi
# The visibility pass works on about PIPELINE_CHUNKS chunks of at least PIPELINE_MIN_CHUNK pixels.
PIPELINE_CHUNKS = 4
PIPELINE_MIN_CHUNK = 16384
# A shadow ray stops this fraction short of the light, so the light's own surface (or a surface the light
# sits on) never shadows it.
SHADOW_TMAX_SCALE = 1.0 - 1e-4


def min_light_distance(scene) -> float:
    """Distances below this are clamped, so a light exactly on a surface gives a finite (bright) result."""
    return 1e-4 * max(scene.extent, 1e-6)


def _device_gbuffer(g, tracer):
    """The device G-buffer to shade ``g`` with on ``tracer``'s device path, or None for the host path: ``g`` itself
    when it is a DeviceGBuffer, else its device twin (from ``render_gbuffer`` on the same tracer), else an upload of
    it when the tracer has a device path."""
    from suite.core.device.gbuffer import DeviceGBuffer

    if isinstance(g, DeviceGBuffer):
        return g
    dev = getattr(tracer, "device", None)
    if dev is None:
        return None
    twin = getattr(g, "device", None)
    if twin is not None and twin.device is dev:
        return twin
    return DeviceGBuffer.from_host(dev, g)


def point_light_visibility(g, lights, tracer, chunk_rays: int = 1 << 20):
    """(H, W, L) bool: True where light l is unobstructed from the G-buffer position (one shadow ray each).

    For a :class:`~suite.core.device.DeviceGBuffer` the rays are generated and traced on the device and the result is
    a :class:`~suite.core.device.DeviceVisibility` (bits that stay on the device); a host G-buffer made by a tracer
    with a device path is traced there too and copied back. The rays are the same on both paths.

    A light below the surface's horizon (behind its geometric normal) is shadowed by the surface itself and
    gets no ray: its bit is 0. That is the N.L > 0 test every shader applies anyway; skipping those rays
    saves work and makes the bit independent of how a ray grazing the surface's own triangle is resolved.

    Rays start at ``offset_ray_origin`` of the position (float64), point at the light (float64 direction rounded
    to float32) and stop ``SHADOW_TMAX_SCALE`` short of it. A compiled kernel (:mod:`suite.core.trace.raygen`) writes
    them straight into the tracer's frame, light by light, at most ``chunk_rays`` pixels at a time; the next
    light's rays are generated while the backend traces the current light's.
    """
    from suite.core.device.gbuffer import DeviceGBuffer
    from suite.core.trace.raygen import ShadowRays

    if isinstance(g, DeviceGBuffer) or (getattr(g, "device", None) is not None
                                        and g.device.device is getattr(tracer, "device", None)):
        from suite.core.device import shading as dshade

        vis_dev = dshade.point_light_visibility(_device_gbuffer(g, tracer), lights, tracer)
        return vis_dev if isinstance(g, DeviceGBuffer) else vis_dev.to_host()
    h, w = g.depth.shape
    n_lights = len(lights)
    vis = np.zeros((h * w, n_lights), bool)
    idx_all = np.flatnonzero(g.valid.reshape(-1))
    if n_lights == 0 or len(idx_all) == 0:
        return vis.reshape(h, w, n_lights)
    positions = np.ascontiguousarray(g.position.reshape(-1, 3), np.float64)
    normals = np.ascontiguousarray(g.geo_normal.reshape(-1, 3), np.float64)
    shift = getattr(tracer, "shift", None)
    soa = bool(getattr(tracer, "soa_origins", False))
    # A few chunks even when memory would allow one: only the first chunk's first light is generated while
    # nothing is being traced, so smaller chunks shorten that serial start.
    chunk = max(1, min(int(chunk_rays), max(PIPELINE_MIN_CHUNK, -(-len(idx_all) // PIPELINE_CHUNKS))))
    tasks = [(c0, li) for c0 in range(0, len(idx_all), chunk) for li in range(n_lights)]
    chunks: dict[int, ShadowRays] = {}

    def generate(k):
        c0, li = tasks[k]
        if c0 not in chunks:
            chunks.pop(c0 - chunk, None)  # the previous chunk's rays have all been traced
            chunks[c0] = ShadowRays(positions, normals, idx_all[c0:c0 + chunk], shift, soa, slots=2)
        return chunks[c0].toward(lights[li].position, SHADOW_TMAX_SCALE, k % 2)

    def trace(o, d, length):
        if hasattr(tracer, "occluded_local"):
            return tracer.occluded_local(o, d, length)
        # a tracer outside the suite's hierarchy: world-space rays through the public query
        o_world = (o.T if soa else o).astype(np.float64) + (0.0 if shift is None else shift)
        return tracer.occluded(o_world, d, 0.0, length)

    # Pipelined: a worker thread generates the next (chunk, light) task's rays (compiled, GIL released) while
    # the backend traces the current one's. Buffer slots alternate; results do not depend on the timing.
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(generate, 0)
        for k, (_, li) in enumerate(tasks):
            o, d, length, pixel = pending.result()
            if k + 1 < len(tasks):
                pending = pool.submit(generate, k + 1)
            vis[pixel, li] = ~trace(o, d, length)
    return vis.reshape(h, w, n_lights)


def shade_point_lights(g, lights, visibility, ambient=None, min_distance: float = 0.0) -> np.ndarray:
    """Lambertian point-light shading from a visibility mask (seed 000 §3.1's shading equation).

    ``ambient`` (float or RGB radiance) is added as ``ambient * rho`` where no light is visible (seed 000
    §5.1, Fig. 9). Returns (H, W, 3) float32 radiance including the G-buffer's emission.

    With a :class:`~suite.core.device.DeviceGBuffer` it shades on the device (``visibility`` a DeviceVisibility, or
    an (H, W, L) bool array that is uploaded) and returns a :class:`~suite.core.device.DeviceImage`.
    """
    from suite.core.device.gbuffer import DeviceGBuffer

    if isinstance(g, DeviceGBuffer):
        from suite.core.device import shading as dshade

        if isinstance(visibility, np.ndarray):
            visibility = dshade.DeviceVisibility.from_host(g.device, visibility)
        return dshade.shade_point_lights(g, lights, visibility, ambient, min_distance)
    h, w = g.depth.shape
    out = np.zeros((h, w, 3), np.float64)
    valid = g.valid
    p = g.position.astype(np.float64)
    n = g.normal.astype(np.float64)
    for li, light in enumerate(lights):
        to_light = np.asarray(light.position, np.float64) - p
        dist2 = np.maximum(np.einsum("hwc,hwc->hw", to_light, to_light), min_distance ** 2)
        dist = np.sqrt(dist2)
        cos = np.maximum(np.einsum("hwc,hwc->hw", n, to_light) / np.maximum(dist, 1e-300), 0.0)
        lit = visibility[..., li] & valid
        out += (lit * cos / np.maximum(dist2, 1e-300))[..., None] * np.asarray(light.intensity, np.float64)
    out *= g.albedo.astype(np.float64) * INV_PI
    if ambient is not None and len(lights) > 0:
        dark = valid & ~visibility.any(axis=-1)
        out += dark[..., None] * np.asarray(ambient, np.float64) * g.albedo
    elif ambient is not None:
        out += valid[..., None] * np.asarray(ambient, np.float64) * g.albedo
    out += g.emission
    return out.astype(np.float32)


class AreaLights:
    """The scene's emissive triangles, prepared for sampling proportional to power (area x luminance)."""

    def __init__(self, scene, t_s: float = 0.0):
        lights = scene.area_light_triangles(t_s)  # the model's per-triangle light list
        self.faces = lights.faces
        tri = lights.vertices
        self.p0, self.e1, self.e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        self.area = lights.area
        self.normal = lights.normal
        self.radiance = lights.radiance
        power = self.area * self.radiance.mean(axis=-1) if len(self.faces) else np.zeros(0)
        total = power.sum()
        self.pmf = power / total if total > 0 else np.zeros_like(power)
        self.cdf = np.cumsum(self.pmf)

    def __len__(self) -> int:
        return int((self.pmf > 0).sum())


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over the last axis of 3-vectors, summed (x + y) + z (a fixed order, no fused multiply-add)."""
    return (a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]) + a[..., 2] * b[..., 2]


@numba.njit(cache=True, nogil=True, parallel=True)
def _area_numbers(pixels, samples: int, seed: int):
    """The area-light estimator's random numbers of ``pixels`` (flat image indices): per pixel and sample k, the
    stratum its light choice takes (Kensler's permutation of [0, samples) keyed by TEA of (pixel, seed), at k) and
    three float32 numbers in [0, 1) (TEA of (pixel, seed * 0x632BE5AB + 4 k + j)), widened to float64:
    ``(strata (m, samples) float64, xi (m, samples, 3) float64)``."""
    m = len(pixels)
    stratum = np.empty((m, samples), np.float64)
    xi = np.empty((m, samples, 3), np.float64)
    seed_u = np.uint32(seed)
    perm_key = np.uint32(np.uint32(seed_u * np.uint32(2654435761)) + np.uint32(0x9E3779B9))
    base = np.uint32(seed_u * np.uint32(0x632BE5AB))
    for i in numba.prange(m):
        key = np.uint32(pixels[i])
        perm_seed = rng.tea_u32(key, perm_key)
        for k in range(samples):
            stratum[i, k] = np.float64(rng.permute_kensler(np.uint32(k), samples, perm_seed))
            ctr = np.uint32(base + np.uint32(4 * k))
            for j in range(3):
                xi[i, k, j] = np.float64(rng.tea_float32(key, np.uint32(ctr + np.uint32(j)), rng.TEA_ROUNDS))
    return stratum, xi


def area_light_radiance(g, area_lights: AreaLights, tracer, samples: int = 16, seed: int = 0,
                        min_distance: float = 0.0, chunk_pixels: int = 1 << 16) -> np.ndarray:
    """Soft-shadowed direct light from triangle area lights, ``samples`` stratified samples per pixel.

    Sample k of n picks a light with the stratified number (s + xi)/n through the power CDF, where s is the pixel's
    random permutation of the strata taken at k (decorrelating the light choice from the 2-D stratum), and a point
    on it with a jittered sqrt(n) x sqrt(n) grid over the unit square (warped to the triangle), which lowers the
    variance against independent sampling without bias. The random numbers are counter-based, a function of (pixel,
    seed, sample, dimension) (:func:`_area_numbers`): the device estimator's
    (:func:`suite.core.device.shading.area_light_radiance`), so the two take the same samples and their images agree
    to rounding (up to shadow rays that graze an occluder).
    """
    from suite.core.device.gbuffer import DeviceGBuffer

    if isinstance(g, DeviceGBuffer):  # the device estimator (the same samples): a DeviceImage
        from suite.core.device import shading as dshade

        return dshade.area_light_radiance(g, area_lights, tracer, samples, seed, min_distance)
    h, w = g.depth.shape
    out = np.zeros((h * w, 3), np.float64)
    idx = np.nonzero(g.valid.reshape(-1))[0]
    if len(area_lights) == 0 or len(idx) == 0 or samples <= 0:
        return out.reshape(h, w, 3).astype(np.float32)
    side = max(int(np.ceil(np.sqrt(samples))), 1)
    strata = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
    strata = strata[np.linspace(0, len(strata) - 1, samples).round().astype(int)]
    positions = g.position.reshape(-1, 3)
    normals = g.normal.reshape(-1, 3)
    geo = g.geo_normal.reshape(-1, 3)
    for c0 in range(0, len(idx), chunk_pixels):
        pix = idx[c0:c0 + chunk_pixels]
        m = len(pix)
        stratum, xi = _area_numbers(pix.astype(np.uint32), samples, int(seed) & 0xFFFFFFFF)
        xi_sel = (stratum + xi[..., 0]) * (1.0 / samples)
        light = np.minimum(np.searchsorted(area_lights.cdf, xi_sel * area_lights.cdf[-1], side="right"),
                           len(area_lights.cdf) - 1)
        uv = (strata[None, :, :] + xi[..., 1:]) * (1.0 / side)
        su = np.sqrt(uv[..., 0])
        b1, b2 = 1.0 - su, uv[..., 1] * su  # uniform point on the triangle
        y = area_lights.p0[light] + b1[..., None] * area_lights.e1[light] + b2[..., None] * area_lights.e2[light]
        ny = area_lights.normal[light]
        x = positions[pix].astype(np.float64)[:, None, :]
        origin = offset_ray_origin(np.broadcast_to(positions[pix][:, None, :], y.shape), np.broadcast_to(geo[pix][:, None, :], y.shape),
                                   getattr(tracer, "shift", None))
        to_y = y - x
        # dot products summed (x + y) + z, as the device estimator does (same samples, same rounding)
        dist2 = np.maximum(_dot3(to_y, to_y), min_distance ** 2)
        dist = np.sqrt(dist2)
        wdir = to_y / dist[..., None]
        cos_x = _dot3(wdir, normals[pix].astype(np.float64)[:, None, :])
        cos_y = -_dot3(wdir, ny)
        active = (cos_x > 0) & (cos_y > 0)
        pdf_area = area_lights.pmf[light] / np.maximum(area_lights.area[light], 1e-300)
        weight = np.where(active, cos_x * cos_y / dist2 / np.maximum(pdf_area, 1e-300), 0.0)
        sel = active.reshape(-1)
        if sel.any():
            o = origin.reshape(-1, 3)[sel]
            seg = (y.reshape(-1, 3)[sel] - o.astype(np.float64))
            seg_len = np.sqrt(_dot3(seg, seg))
            d = (seg / np.maximum(seg_len, 1e-30)[:, None]).astype(np.float32)
            occ = tracer.occluded(o, d, 0.0, (seg_len * SHADOW_TMAX_SCALE).astype(np.float32))
            vis = np.zeros(m * samples, bool)
            vis[np.nonzero(sel)[0]] = ~occ
            weight = weight * vis.reshape(m, samples)
        # the samples summed in order, then scaled by 1 / n (the device's loop)
        contrib = np.zeros((m, 3))
        for k in range(samples):
            contrib += weight[:, k, None] * area_lights.radiance[light[:, k]]
        out[pix] = contrib * (1.0 / samples)
    out *= g.albedo.reshape(-1, 3).astype(np.float64) * INV_PI
    return out.reshape(h, w, 3).astype(np.float32)


def direct_lighting(scene, g, tracer, t_s: float, area_samples: int = 16, seed: int = 0,
                    device: bool | None = None):
    """Emission + point lights (hard shadows) + area lights (soft shadows): the ``direct`` integrator's image.

    A tracer with a device path computes it with :func:`suite.core.device.direct_lighting` (for a host G-buffer: on
    its device twin, or an upload of it) and, for a host G-buffer, copies the image back; given a DeviceGBuffer it
    returns the :class:`~suite.core.device.DeviceImage`. Point-light terms equal the host path's, and so do the
    area-light terms on the same G-buffer (the same counter-based samples, :func:`area_light_radiance`).
    ``device=False`` forces the host path for a host G-buffer.
    """
    dg = _device_gbuffer(g, tracer) if device is not False else None
    if dg is not None:
        from suite.core.device import shading as dshade

        img = dshade.direct_lighting(scene, dg, tracer, t_s, area_samples=area_samples, seed=seed)
        return img if dg is g else img.to_host()
    return compose_direct(sys.modules[__name__], scene, g, tracer, t_s, area_samples, seed)


def compose_direct(kernels, scene, g, tracer, t_s: float, area_samples: int, seed: int):
    """Emission + point lights (hard shadows) + area lights (soft shadows) from one set of kernels: this module's
    (host) or :mod:`suite.core.device.shading`'s (device), which share these names and this composition."""
    lights = scene.lights_at(t_s)
    min_d = min_light_distance(scene)
    vis = kernels.point_light_visibility(g, lights, tracer)
    rgb = kernels.shade_point_lights(g, lights, vis, min_distance=min_d)
    area = AreaLights(scene, t_s)
    if len(area):
        rgb = rgb + kernels.area_light_radiance(g, area, tracer, samples=area_samples, seed=seed, min_distance=min_d)
    return rgb
