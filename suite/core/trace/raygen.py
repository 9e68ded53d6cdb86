"""Compiled shadow-ray generation (numba).

Generating a shadow ray is a handful of float operations per pixel and light; in numpy each of them is a pass
over memory, and ray generation cost more than Embree's tracing of the rays. Two compiled loops write the rays
straight into the tracer's frame and layout: one offsets the origins once per pixel (they do not depend on the
light; float64, ``suite.core.trace.robust.offset_ray_origin``, rounded once into the tracing frame), one makes each
light's rays in float32 from those origins to the light's tracing-frame position: the segment the backend traces,
in the precision it traces it (see docs/core.md, "Shadow rays"). The device pass
(:func:`suite.core.device.shading.point_light_visibility`) performs the same operations in the same order, so
rays and visibility bits are identical (tests/methods/visibility_bitmap/test_visibility_pass.py test08 and
test09, tests/core/test_device.py).
"""
from __future__ import annotations

import numpy as np

from suite.core.trace.robust import FLOAT_SCALE, OFFSET_ULPS


def _origins_kernel(positions, normals, pixels, shift, offset_ulps, float_scale, origin_local, normal32, soa):
    """``offset_ray_origin`` of ``positions[pixels]`` (float64, world) in the tracing frame (float32, minus
    ``shift``; ``origin_local`` is (3, P) or (P, 3)), and the geometric normals as float32 (``normal32``, (P, 3))."""
    # np.spacing(np.float32(m)) of a normal float32 is its exponent bits with a zero mantissa times 2**-23;
    # below the normal range it is 0 here, and the absolute floor wins anyway.
    m32 = np.empty(1, np.float32)
    m_bits = m32.view(np.uint32)
    e32 = np.empty(1, np.float32)
    e_bits = e32.view(np.uint32)
    for j in range(pixels.shape[0]):
        i = pixels[j]
        px, py, pz = positions[i, 0], positions[i, 1], positions[i, 2]
        m32[0] = max(abs(px - shift[0]), abs(py - shift[1]), abs(pz - shift[2]))
        e_bits[0] = m_bits[0] & np.uint32(0x7F800000)
        step = max(offset_ulps * (np.float64(e32[0]) * 1.1920928955078125e-07), float_scale)  # 2**-23
        ox = px + step * normals[i, 0]
        oy = py + step * normals[i, 1]
        oz = pz + step * normals[i, 2]
        if soa:
            origin_local[0, j], origin_local[1, j], origin_local[2, j] = ox - shift[0], oy - shift[1], oz - shift[2]
        else:
            origin_local[j, 0], origin_local[j, 1], origin_local[j, 2] = ox - shift[0], oy - shift[1], oz - shift[2]
        normal32[j, 0], normal32[j, 1], normal32[j, 2] = normals[i, 0], normals[i, 1], normals[i, 2]


def _rays_kernel(normal32, pixels, origin_local, light, tmax_scale, o_out, d_out, len_out, ray_pixel, soa):
    """Rays from the tracing-frame origins to ``light`` (float32, tracing frame), compacted to the pixels whose
    horizon the light is above, every operation in float32. Returns the ray count; ``ray_pixel[k]`` is the pixel
    (an entry of ``pixels``) of ray k."""
    tiny = np.float32(1e-30)
    zero = np.float32(0.0)
    k = 0
    for j in range(pixels.shape[0]):
        if soa:
            ox, oy, oz = origin_local[0, j], origin_local[1, j], origin_local[2, j]
        else:
            ox, oy, oz = origin_local[j, 0], origin_local[j, 1], origin_local[j, 2]
        tx, ty, tz = light[0] - ox, light[1] - oy, light[2] - oz
        dist = np.sqrt(tx * tx + (ty * ty + tz * tz))  # np.linalg.norm's order over a length-3 axis
        inv = max(dist, tiny)
        dx, dy, dz = tx / inv, ty / inv, tz / inv
        if (dx * normal32[j, 0] + dy * normal32[j, 1]) + dz * normal32[j, 2] <= zero:
            continue  # below the horizon: shadowed by the surface itself, no ray
        if soa:
            o_out[0, k], o_out[1, k], o_out[2, k] = ox, oy, oz
        else:
            o_out[k, 0], o_out[k, 1], o_out[k, 2] = ox, oy, oz
        d_out[k, 0], d_out[k, 1], d_out[k, 2] = dx, dy, dz
        len_out[k] = max(dist * tmax_scale, zero)
        ray_pixel[k] = pixels[j]
        k += 1
    return k


_compiled = None


def _jit():
    global _compiled
    if _compiled is None:
        import numba

        # error_model='numpy': IEEE division (divisors are never 0) without per-division checks.
        jit = numba.njit(cache=True, nogil=True, error_model="numpy")
        _compiled = jit(_origins_kernel), jit(_rays_kernel)
    return _compiled


class ShadowRays:
    """Shadow rays from a set of G-buffer pixels, light after light, in a tracer's frame and layout.

    ``slots`` output buffers let the rays of the next light be generated (in another thread; the kernels
    release the GIL) while the backend traces the current light's.
    """

    def __init__(self, positions, normals, pixels, shift=None, soa: bool = False, slots: int = 1):
        origins, _ = _jit()
        n = len(pixels)
        self.soa = soa
        self.pixels = np.ascontiguousarray(pixels, np.int64)
        self.origin_local = np.empty((3, n) if soa else (n, 3), np.float32)
        self.normal32 = np.empty((n, 3), np.float32)
        self.shift = np.zeros(3) if shift is None else np.asarray(shift, np.float64)
        origins(positions, normals, self.pixels, self.shift, float(OFFSET_ULPS), float(FLOAT_SCALE),
                self.origin_local, self.normal32, soa)
        self.buffers = [(np.empty((3, n) if soa else (n, 3), np.float32), np.empty((n, 3), np.float32),
                         np.empty(n, np.float32), np.empty(n, np.int64)) for _ in range(max(int(slots), 1))]

    def toward(self, light_position, tmax_scale: float, slot: int = 0):
        """(o, d, length, pixel) of the rays toward one light; views into the reused buffers of ``slot``."""
        _, rays = _jit()
        o, d, length, pixel = self.buffers[slot]
        light = (np.asarray(light_position, np.float64) - self.shift).astype(np.float32)  # the tracing frame
        count = int(rays(self.normal32, self.pixels, self.origin_local, light, np.float32(tmax_scale), o, d, length,
                         pixel, self.soa))
        return (o[:, :count] if self.soa else o[:count]), d[:count], length[:count], pixel[:count]
