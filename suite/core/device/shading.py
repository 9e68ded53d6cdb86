"""Shadow rays, visibility bits and direct lighting as Dr.Jit kernels on a :class:`DeviceGBuffer`.

* :func:`point_light_visibility`: one shadow ray per pixel and point light, generated inside the tracing kernel
  (a loop over the lights per pixel), bit ``l`` of the pixel's record set when light ``l`` is unobstructed. The rays
  are :mod:`suite.core.trace.raygen`'s operation for operation (robust float64 origin rounded into the tracing
  frame, then float32 direction, horizon test and ``dist * SHADOW_TMAX_SCALE`` toward the light's tracing-frame
  position), so the bits equal the host path's.
* :func:`shade_point_lights`: :func:`suite.core.shading.shade_point_lights` in float64, reading the bits from a
  :class:`DeviceVisibility` (made here, or uploaded from a received bitmap).
* :func:`area_light_radiance`: the stratified area-light estimator of :mod:`suite.core.shading` (light chosen by
  power with a stratified number, a jittered sqrt(n) x sqrt(n) grid on the triangle) with the host estimator's
  counter-based random numbers (TEA and Kensler's permutation, whose host twins are :mod:`suite.core.rng`) and its
  operations in its order: on the same G-buffer the image is the host's bit for bit on ``llvm_ad_rgb``.
* :func:`direct_lighting`: emission + point lights + area lights.

Visibility records use the byte layout of the visibility bitmap (:mod:`methods.visibility_bitmap.bitmap`): light
``l`` of pixel ``p`` is bit ``l % 8`` of byte ``p * B + l // 8`` (B bytes per pixel), stored in little-endian
uint32 words, so a received bitmap of any layout is shaded without unpacking.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from suite.core.shading import INV_PI, SHADOW_TMAX_SCALE, AreaLights, compose_direct
from suite.core.trace.alpha import MAX_ALPHA_LAYERS
from suite.core.device.gbuffer import _dot


@dataclass
class DeviceImage:
    """A linear RGB image on the device (flat Vector3f, row-major)."""

    device: object
    width: int
    height: int
    rgb: object  # Vector3f

    def to_host(self, with_bytes: bool = False):
        """(H, W, 3) float32 (an explicit copy; with ``with_bytes`` also the bytes copied)."""
        copy = self.device.to_host(self.rgb, np.float32, with_bytes=True)
        img = copy.array.reshape(self.height, self.width, 3)
        return (img, copy.nbytes) if with_bytes else img

    def __add__(self, other: "DeviceImage") -> "DeviceImage":
        out = DeviceImage(self.device, self.width, self.height, self.rgb + other.rgb)
        self.device.eval(out.rgb)
        return out


@dataclass
class DeviceVisibility:
    """Per-pixel light visibility on the device: ``data`` (UInt32 words) holds ``bytes_per_pixel`` bytes per pixel,
    light ``l`` of pixel ``p`` at bit ``l % 8`` of byte ``p * bytes_per_pixel + l // 8`` (little-endian words)."""

    device: object
    width: int
    height: int
    lights: int
    bytes_per_pixel: int
    data: object  # UInt32
    rays: int = 0  # shadow rays traced to make it (0 when uploaded)

    @property
    def nbytes(self) -> int:
        return self.width * self.height * self.bytes_per_pixel

    def bit(self, light, pixel, active=True):
        """Bool of light ``light`` (UInt32 or int) at pixels ``pixel`` (UInt32), lazily."""
        dev = self.device
        dr, U = dev.dr, dev.UInt32
        light = U(light) if isinstance(light, int) else light
        q = pixel * self.bytes_per_pixel + (light >> 3)
        if self.bytes_per_pixel % 4 == 0:  # words layouts: the bit is light % 32 of word p * B/4 + light / 32
            word = dr.gather(U, self.data, pixel * (self.bytes_per_pixel // 4) + (light >> 5), active)
            return ((word >> (light & 31)) & 1) != 0
        word = dr.gather(U, self.data, q >> 2, active)
        return ((word >> (((q & 3) << 3) + (light & 7))) & 1) != 0

    def to_host_bytes(self, with_bytes: bool = False):
        """The records as (H, W * bytes_per_pixel) uint8 (an explicit copy)."""
        copy = self.device.to_host(self.data, np.uint32, with_bytes=True)
        raw = copy.array.view(np.uint8)[:self.nbytes].reshape(self.height, self.width * self.bytes_per_pixel)
        return (raw, copy.nbytes) if with_bytes else raw

    def to_host(self) -> np.ndarray:
        """(H, W, L) bool (an explicit copy of the records, unpacked on the host)."""
        raw = self.to_host_bytes().reshape(self.height, self.width, self.bytes_per_pixel)
        if self.lights == 0:
            return np.zeros((self.height, self.width, 0), bool)
        bits = np.unpackbits(raw, axis=-1, count=self.lights, bitorder="little")
        return bits.view(bool)

    @classmethod
    def from_host_bytes(cls, device, records: np.ndarray, width: int, height: int, lights: int,
                        bytes_per_pixel: int) -> "DeviceVisibility":
        """Uploads records in the byte layout (e.g. a received bitmap, (H, W * B) uint8) to the device (counted)."""
        raw = np.ascontiguousarray(records, np.uint8).reshape(-1)
        pad = (-len(raw)) % 4
        if pad or len(raw) == 0:
            raw = np.concatenate([raw, np.zeros(pad or 4, np.uint8)])
        data = device.to_device(raw.view("<u4").astype(np.uint32, copy=False), device.UInt32)
        return cls(device, width, height, lights, bytes_per_pixel, data, 0)

    @classmethod
    def from_host(cls, device, visibility: np.ndarray) -> "DeviceVisibility":
        """Uploads an (H, W, L) bool array (as 32-bit words per pixel)."""
        h, w, n_lights = visibility.shape
        words = max(-(-n_lights // 32), 1)
        packed = np.zeros((h, w, 4 * words), np.uint8)
        if n_lights:
            packed[:, :, :-(-n_lights // 8)] = np.packbits(visibility, axis=-1, bitorder="little")
        return cls.from_host_bytes(device, packed, w, h, n_lights, 4 * words)


def _light_table(dev, lights):
    """Point-light positions (float64, flat x, y, z per light) and intensities (float64), uploaded (counted)."""
    pos = np.array([lt.position for lt in lights], np.float64).reshape(-1)
    inten = np.array([lt.intensity for lt in lights], np.float64).reshape(-1)
    if len(pos) == 0:
        pos = inten = np.zeros(3)
    return dev.to_device(pos, dev.Float64), dev.to_device(inten, dev.Float64)


def _check(g, tracer=None):
    from suite.core.device.gbuffer import DeviceGBuffer

    if not isinstance(g, DeviceGBuffer):
        raise TypeError("the device kernels take a DeviceGBuffer (suite.core.device.render_gbuffer)")
    if tracer is not None and getattr(tracer, "device", None) is not g.device:
        raise ValueError("the G-buffer lives on another tracer's device")
    return g.device


def _shadow_ray(dev, o_local, n32, valid, light_local):
    """Direction, length and the horizon test of the shadow rays from tracing-frame origins ``o_local`` to a point
    light at ``light_local`` (tracing frame), all float32: :mod:`suite.core.trace.raygen`'s ``_rays_kernel``
    operation for operation."""
    dr = dev.dr
    tx, ty, tz = light_local.x - o_local.x, light_local.y - o_local.y, light_local.z - o_local.z
    dist = dr.sqrt(tx * tx + (ty * ty + tz * tz))  # raygen's order
    inv = dr.maximum(dist, 1e-30)
    dx, dy, dz = tx / inv, ty / inv, tz / inv
    above = valid & (((dx * n32.x + dy * n32.y) + dz * n32.z) > 0.0)
    length = dr.maximum(dist * SHADOW_TMAX_SCALE, 0.0)
    return dev.Vector3f(dx, dy, dz), length, above


def _light_local(dev, positions):
    """The lights' tracing-frame positions rounded to float32 (the host's ``ShadowRays.toward``), as float64 values
    each float32 holds exactly."""
    return (np.asarray(positions, np.float64).reshape(-1, 3) - dev._shift).astype(np.float32).astype(np.float64)


def shadow_rays(g, lights, tracer) -> list:
    """The shadow rays :func:`point_light_visibility` traces, light by light, compacted to the pixels whose horizon
    the light is above and evaluated into device memory: ``[(Ray3f, pixel UInt32)]`` (benchmarks: the raw
    backend's baseline on the very rays of the pass)."""
    dev = _check(g, tracer)
    dr, F = dev.dr, dev.Float
    o_local = dev.local_f32(dev.offset_origin(g.position, dev.Vector3d(g.geo_normal)))
    n32 = dev.Vector3f(g.geo_normal)
    dev.eval(o_local)
    out = []
    for position in _light_local(dev, [light.position for light in lights]):
        p = dev.Point3f(*[F(dev.opaque(dev.Float64, float(x))) for x in position])
        d, length, above = _shadow_ray(dev, o_local, n32, g.valid, p)
        idx = dr.compress(above)
        ray = dev.ray(dr.gather(dev.Point3f, o_local, idx), dr.gather(dev.Vector3f, d, idx),
                      dr.gather(dev.Float, length, idx))
        dr.eval(ray, idx)
        out.append((ray, idx))
    dev.sync()
    return out


# Lights per kernel (at most a 32-light word) written out one after the other in the kernel, each light's position a
# scalar the kernel broadcasts, rather than a symbolic loop that gathers the position per lane. On llvm_ad_rgb the
# per-lane gathers (AVX2 gathers of float64) cost as much as the ray generation itself: measured on 2 cores,
# living_room 640x360, raw/pass 0.81 looping and 0.96 unrolled; arena (73 lights) 0.52 and 0.80. On cuda_ad_rgb the
# gather of one address by a whole warp is a broadcast from cache, and one trace call site keeps the OptiX kernel
# small, so it loops: measured on an H100 (living_room 1080p, 3 lights) the two shapes take the same device time
# (0.81 ms looping, 0.82 ms unrolled).
# What is left of the gap to raw on llvm_ad_rgb (2 cores, living_room 1080p, 3 lights, 6.05 M shadow rays; raw
# ray_test of the compacted rays, one kernel per light, 64.4 ms): the same rays precomputed and traced in one kernel
# for all lights (each packet's rays to light 0, then 1, then 2) 69.5 ms, and in one kernel per light 64.8 ms; so the
# lights' interleaving costs about 5 ms. One kernel per light with its ray generation took 83.9 ms: each kernel reads
# the G-buffer's positions and normals again. The rays are made in float32 (_shadow_ray): in float64 the pass took
# about 10 % longer (docs/core.md, "Shadow rays are made in float32").
UNROLL_LIGHTS = {"llvm": 32, "cuda": 0}


def point_light_visibility(g, lights, tracer, unroll: int | None = None) -> DeviceVisibility:
    """One shadow ray per pixel and light on the device; the bits as :class:`DeviceVisibility` in the words layout
    (``ceil(L / 32)`` little-endian uint32 per pixel, light ``l`` at bit ``l % 32`` of word ``l // 32``).

    Each 32-light word is one kernel that generates its rays, traces them and sets the bits: unrolled over the lights
    (up to ``unroll`` lights; default :data:`UNROLL_LIGHTS` of the variant) or a symbolic loop over them. Both give
    the same bits."""
    dev = _check(g, tracer)
    dr, U = dev.dr, dev.UInt32
    n, n_lights = g.pixels, len(lights)
    words = -(-n_lights // 32)
    if n_lights == 0:
        return DeviceVisibility(dev, g.width, g.height, 0, 0, dr.zeros(U, 1), 0)
    unroll = UNROLL_LIGHTS[dev.name] if unroll is None else int(unroll)
    positions = _light_local(dev, [lt.position for lt in lights])
    # the lights' positions (read from memory): scalars where a word's lights are written out, a table where it loops
    written_out = [min(n_lights, 32 * k + 32) - 32 * k <= unroll for k in range(words)]
    light_ops = dev.opaques(positions.reshape(-1)) if any(written_out) else []
    lp = dev.to_device(positions.reshape(-1).astype(np.float32), dev.Float) if not all(written_out) else None
    alpha = dev.tracer._alpha is not None
    # recorded once per (pixels, lights, kernel shape) and replayed on later frames (Device.frozen)
    out, count, extra = dev.frozen("visibility", _visibility_kernel, shadow_rays=True)(
        dev, g.position, g.geo_normal, g.prim, light_ops, lp, n, n_lights, unroll, alpha)
    dev.sync()
    rays = dev.sum_u32(count, n_lights)
    dev.tracer.counters["rays_occluded"] += rays
    if alpha:
        dev.tracer.counters["rays_intersect"] += dev.sum_u32(extra, n_lights * (MAX_ALPHA_LAYERS + 1))
    return DeviceVisibility(dev, g.width, g.height, n_lights, 4 * words, out, rays)


def _visibility_kernel(dev, position, geo_normal, prim, light_ops, lp, n: int, n_lights: int, unroll: int,
                       alpha: bool):
    """The bits, shadow rays per pixel and alpha-walk queries per pixel of :func:`point_light_visibility`,
    evaluated."""
    dr, U = dev.dr, dev.UInt32
    words = -(-n_lights // 32)
    valid = prim >= 0
    o_local = dev.local_f32(dev.offset_origin(position, dev.Vector3d(geo_normal)))  # once per pixel
    n32 = dev.Vector3f(geo_normal)
    data = dr.zeros(U, n * words) if words > 1 else None
    pixel = dev.arange(n)
    count = dr.zeros(U, n)  # shadow rays per pixel (above the horizon)
    extra = dr.zeros(U, n)  # closest-hit queries of the alpha walk
    word = None

    def trace_one(light_pos, bit, word, count, extra):
        d, length, above = _shadow_ray(dev, o_local, n32, valid, light_pos)
        blocked, traced = dev.occluded_rays(o_local, d, length, above)
        word = word | dr.select(above & ~blocked, bit, U(0))
        count = count + dr.select(above, U(1), U(0))
        if traced is not None:  # 0 where the backend found no block
            extra = extra + traced
        return word, count, extra

    for k in range(words):
        lo, hi = 32 * k, min(n_lights, 32 * k + 32)
        word = dr.zeros(U, n)
        if hi - lo <= unroll:
            for li in range(lo, hi):
                p = dev.Point3f(*[dev.Float(x) for x in light_ops[3 * li:3 * li + 3]])
                word, count, extra = trace_one(p, dev.opaque(U, 1 << (li - lo)), word, count, extra)
        else:
            base, end = dev.opaque(U, lo), dev.opaque(U, hi)
            light = dr.zeros(U, n) + base

            def body(light, word, count, extra):
                word, count, extra = trace_one(dr.gather(dev.Vector3f, lp, light), U(1) << (light - base), word,
                                               count, extra)
                return light + 1, word, count, extra

            light, word, count, extra = dr.while_loop((light, word, count, extra),
                                                      lambda light, *_: light < end, body)
        if words > 1:
            dr.scatter(data, word, pixel * words + k)
    out = word if words == 1 else data
    dr.eval(out, count, *([extra] if alpha else []))
    return out, count, extra if alpha else None


def shade_point_lights(g, lights, visibility: DeviceVisibility, ambient=None,
                       min_distance: float = 0.0) -> DeviceImage:
    """:func:`suite.core.shading.shade_point_lights` on the device (float64, the host's order of operations):
    Lambertian ``rho/pi * I * cos / d^2`` per visible light, ``ambient * rho`` where no light is visible (when
    ``ambient`` is given), plus the G-buffer's emission."""
    dev = _check(g)
    dr, F64, U = dev.dr, dev.Float64, dev.UInt32
    n, n_lights = g.pixels, len(lights)
    if visibility.lights != n_lights or visibility.width != g.width or visibility.height != g.height:
        raise ValueError(f"visibility of {visibility.lights} lights at {visibility.width}x{visibility.height} does not "
                         f"fit {n_lights} lights at {g.width}x{g.height}")
    p = g.position
    nrm = dev.Vector3d(g.normal)
    acc = dev.Vector3d(0.0, 0.0, 0.0)
    any_lit = dr.full(dev.Bool, False, n)
    if n_lights:
        lp, inten = _light_table(dev, lights)
        pixel = dev.arange(n)
        min_d2 = dev.opaque(F64, float(min_distance) ** 2)
        end = dev.opaque(U, n_lights)
        light = dr.zeros(U, n)
        acc = dr.zeros(dev.Vector3d, n)

        def body(light, acc, any_lit):
            q = dr.gather(dev.Vector3d, lp, light)
            intensity = dr.gather(dev.Vector3d, inten, light)
            to_light = q - p
            dist2 = dr.maximum((to_light.x * to_light.x + to_light.z * to_light.z) + to_light.y * to_light.y, min_d2)
            dist = dr.sqrt(dist2)
            dot = (nrm.x * to_light.x + nrm.z * to_light.z) + nrm.y * to_light.y
            cos = dr.maximum(dot / dr.maximum(dist, 1e-300), 0.0)
            vis = visibility.bit(light, pixel, g.valid)
            lit = vis & g.valid
            scale = dr.select(lit, cos, 0.0) / dr.maximum(dist2, 1e-300)
            return light + 1, acc + scale * intensity, any_lit | vis

        light, acc, any_lit = dr.while_loop((light, acc, any_lit), lambda light, acc, any_lit: light < end, body)
    albedo = dev.Vector3d(g.albedo)
    out = acc * (albedo * INV_PI)
    if ambient is not None:
        amb = np.broadcast_to(np.asarray(ambient, np.float64), (3,))
        dark = g.valid & ~any_lit if n_lights else g.valid
        amb_v = dev.Vector3d(*[dev.opaque(F64, float(x)) for x in amb])
        out = out + dr.select(dark, amb_v * albedo, dev.Vector3d(0.0, 0.0, 0.0))
    if g.emission is not None:
        out = out + dev.Vector3d(g.emission)
    img = DeviceImage(dev, g.width, g.height, dev.Vector3f(out))
    dev.eval(img.rgb)
    return img


class DeviceAreaLights:
    """:class:`suite.core.shading.AreaLights` on the device (float64 tables)."""

    def __init__(self, dev, area: AreaLights):
        self.count = len(area.faces)
        self.sampled = len(area)
        if self.count == 0:
            return
        F64 = dev.Float64
        up = lambda a: dev.to_device(np.ascontiguousarray(a, np.float64).reshape(-1), F64)  # noqa: E731
        self.p0, self.e1, self.e2 = up(area.p0), up(area.e1), up(area.e2)
        self.normal, self.radiance = up(area.normal), up(area.radiance)
        self.pdf_area = up(area.pmf / np.maximum(area.area, 1e-300))
        self.cdf = up(area.cdf)
        self.cdf_last = float(area.cdf[-1])


def area_light_radiance(g, area_lights, tracer, samples: int = 16, seed: int = 0,
                        min_distance: float = 0.0, record: list | None = None) -> DeviceImage:
    """Soft-shadowed direct light from triangle area lights on the device (see the module docstring). The samples are
    a symbolic loop; with ``record`` (a list) they run one after the other instead (the same image), and each
    sample's shadow rays, compacted to the lanes that trace them, are appended to it as ``("o", Ray3f)`` (benchmarks:
    the raw backend on the very rays of the pass)."""
    dev = _check(g, tracer)
    dr, F, F64, U = dev.dr, dev.Float, dev.Float64, dev.UInt32
    n = g.pixels
    zero = DeviceImage(dev, g.width, g.height, dr.zeros(dev.Vector3f, n))
    if not isinstance(area_lights, DeviceAreaLights):
        area_lights = DeviceAreaLights(dev, area_lights)
    if area_lights.sampled == 0 or samples <= 0:
        return zero
    lt = area_lights
    side = max(int(np.ceil(np.sqrt(samples))), 1)
    strata = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
    strata = strata[np.linspace(0, len(strata) - 1, samples).round().astype(int)]
    strata_t = dev.to_device(np.ascontiguousarray(strata, np.uint32).reshape(-1), U)
    pixel = dev.arange(n)
    x = g.position
    ns = dev.Vector3d(g.normal)
    o64 = dev.offset_origin(x, dev.Vector3d(g.geo_normal))
    o_local = dev.local_f32(o64)
    m = dev.m
    key = U(pixel)
    seed_u = dev.opaque(U, int(seed) & 0xFFFFFFFF)
    # A per-pixel random permutation of the light strata decorrelates light choice from the 2-D stratum (the host
    # shuffles them with numpy; here Kensler's hash permutation).
    perm_seed = m.sample_tea_32(key, seed_u * 2654435761 + 0x9E3779B9)[0]
    n_s = dev.opaque(U, samples)
    inv_side = dev.opaque(F64, 1.0 / side)
    inv_n = dev.opaque(F64, 1.0 / samples)
    last = lt.count - 1
    cdf_last = dev.opaque(F64, lt.cdf_last)
    min_d2 = dev.opaque(F64, float(min_distance) ** 2)
    k = dr.zeros(U, n)
    acc = dr.zeros(dev.Vector3d, n)
    count = dr.zeros(U, n)
    extra = dr.zeros(U, n)
    pending = None if record is None else []  # each sample's shadow rays, while recording

    def body(k, acc, count, extra):
        ctr = seed_u * 0x632BE5AB + k * 4
        xi = [F64(m.sample_tea_float32(key, ctr + j)) for j in range(3)]
        stratum = m.permute_kensler(k, samples, perm_seed)
        sel = (F64(stratum) + xi[0]) * inv_n
        target = sel * cdf_last
        light = dr.binary_search(0, last, lambda i: dr.gather(F64, lt.cdf, i) <= target)
        light = dr.minimum(U(light), last)
        sa = dr.gather(U, strata_t, k * 2)
        sb = dr.gather(U, strata_t, k * 2 + 1)
        ua = (F64(sa) + xi[1]) * inv_side
        ub = (F64(sb) + xi[2]) * inv_side
        su = dr.sqrt(ua)
        b1, b2 = 1.0 - su, ub * su
        p0 = dr.gather(dev.Vector3d, lt.p0, light)
        e1 = dr.gather(dev.Vector3d, lt.e1, light)
        e2 = dr.gather(dev.Vector3d, lt.e2, light)
        ny = dr.gather(dev.Vector3d, lt.normal, light)
        y = (p0 + b1 * e1) + b2 * e2
        to_y = y - x
        # dot products summed (x + y) + z, written out as the host estimator writes them
        dist2 = dr.maximum(_dot(to_y, to_y), min_d2)
        dist = dr.sqrt(dist2)
        wdir = to_y / dist
        cos_x = _dot(wdir, ns)
        cos_y = -_dot(wdir, ny)
        active = g.valid & (cos_x > 0.0) & (cos_y > 0.0)
        pdf = dr.gather(F64, lt.pdf_area, light)
        weight = cos_x * cos_y / dist2 / dr.maximum(pdf, 1e-300)
        seg = y - o64
        seg_len = dr.sqrt(_dot(seg, seg))
        d = dev.Vector3f(seg / dr.maximum(seg_len, 1e-30))
        length = F(seg_len * SHADOW_TMAX_SCALE)
        blocked, traced = dev.occluded_rays(o_local, d, length, active)
        if pending is not None:
            pending.append((active, o_local, d, length))
        radiance = dr.gather(dev.Vector3d, lt.radiance, light)
        acc = acc + dr.select(active & ~blocked, weight, 0.0) * radiance
        count = count + dr.select(active, U(1), U(0))
        if traced is not None:
            extra = extra + traced
        return k + 1, acc, count, extra

    if record is None:
        k, acc, count, extra = dr.while_loop((k, acc, count, extra), lambda k, acc, count, extra: k < n_s, body)
    else:
        for _ in range(samples):
            k, acc, count, extra = body(k, acc, count, extra)
            dr.eval(k, acc, count, extra)
        record += [("o", dev.compacted_ray(*rays)) for rays in pending]
    out = acc * inv_n * (dev.Vector3d(g.albedo) * INV_PI)
    img = DeviceImage(dev, g.width, g.height, dev.Vector3f(out))
    dev.eval(img.rgb, count, extra)
    dev.tracer.counters["rays_occluded"] += dev.sum_u32(count)
    if dev.tracer._alpha is not None:
        dev.tracer.counters["rays_intersect"] += dev.sum_u32(extra)
    return img


def direct_lighting(scene, g, tracer, t_s: float, area_samples: int = 16, seed: int = 0) -> DeviceImage:
    """Emission + point lights (hard shadows) + area lights (soft shadows) on the device."""
    return compose_direct(sys.modules[__name__], scene, g, tracer, t_s, area_samples, seed)
