"""Edge-avoiding à-trous filtering: the spatial part of SVGF-style denoisers, shared by every renderer that
denoises a noisy image with its G-buffer.

The filter is the edge-avoiding à-trous wavelet transform of Dammertz et al. (2010, "Edge-avoiding À-Trous
wavelet transform for fast global illumination filtering", §3, eq. 2-4): ``iterations`` passes with steps 1, 2, 4,
... of a (2r + 1)^2 kernel (r = 1: the 3x3 kernel with weights 1, 1/2, 1/4 of q2vkpt / Q2RTX; r = 2: the 5x5 B3
spline of the SVGF paper and Falcor), each tap weighted by the edge-stopping functions of SVGF (Schied et al.
2017, "Spatiotemporal Variance-Guided Filtering", §4.4, eq. 3-6):

* normal: ``max(0, n . n') ^ phi_normal`` (eq. 4),
* depth: ``exp(-|z - z'| / (phi_depth * |grad z| * step * |offset|))`` (eq. 3, with the step of the pass, as
  Falcor's SVGFAtrous does),
* luminance: ``exp(-|l - l'| / (phi_color * sqrt(g3x3(var))))`` (eq. 5), against the 3x3 Gaussian of the
  luminance variance,

and the variance is filtered with the squared weights (eq. 6), so every pass stops at the remaining noise. What is
filtered is normally demodulated illumination (radiance / albedo; the caller multiplies the albedo back in).

:func:`atrous_pass` is a numba kernel parallel over image rows; :func:`atrous_pass_reference` is the same pass as
vectorised numpy over whole images (one array operation per kernel tap). Both work in float64 with the per-pixel
operations in the same fixed order (no fused multiply-adds, no fast-math), so they give the same bits and neither
depends on the machine's thread count (tests/core/test_denoise.py compares them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)  # Rec. 709 luminance


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of (..., 3) linear RGB, float32."""
    return np.asarray(rgb, np.float32) @ LUMA


def _slices(h: int, w: int, dy: int, dx: int):
    """(destination, source) index pairs such that ``dst = a[y, x]`` and ``src = a[y + dy, x + dx]`` both lie in an
    (h, w) image; None when the offset leaves the image."""
    if abs(dy) >= h or abs(dx) >= w:
        return None
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    return (yd, xd), (ys, xs)


def shifted(a: np.ndarray, dy: int, dx: int, fill=0.0) -> np.ndarray:
    """``out[y, x] = a[y + dy, x + dx]``, ``fill`` outside the image."""
    out = np.full_like(a, fill)
    sl = _slices(a.shape[0], a.shape[1], dy, dx)
    if sl is not None:
        out[sl[0]] = a[sl[1]]
    return out


def gaussian3x3(v: np.ndarray, dtype=np.float64) -> np.ndarray:
    """The 3x3 Gaussian (1/4 centre, 1/8 edges, 1/16 corners) of ``v``, zero outside the image, accumulated in
    ``dtype`` in row-major tap order."""
    acc = np.zeros(v.shape, dtype)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            acc += shifted(v, dy, dx).astype(dtype) * ((0.25 if dx == 0 else 0.125) * (1.0 if dy == 0 else 0.5))
    return acc


def depth_fwidth(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """|grad z| per pixel: the largest depth step to a valid 4-neighbour (a screen-space derivative)."""
    d = np.where(valid, depth, 0.0).astype(np.float32)
    out = np.zeros_like(d)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ok = shifted(valid, dy, dx, False)
        out = np.maximum(out, np.where(ok, np.abs(shifted(d, dy, dx) - d), 0.0))
    return out


def kernel(radius: int) -> list[float]:
    """1D à-trous weights from the centre out: r = 1 (1, 1/2) or r = 2 (the B3 spline 1, 2/3, 1/6)."""
    if radius not in (1, 2):
        raise ValueError(f"a-trous radius must be 1 or 2, got {radius}")
    return [1.0, 0.5] if radius == 1 else [1.0, 2.0 / 3.0, 1.0 / 6.0]


def _squarings(r, b, k: int):
    """``r * b ** k`` by repeated squaring (arrays or, compiled, one value): the products of :func:`_pow`."""
    while k > 0:
        if k & 1:
            r = r * b
        b = b * b
        k >>= 1
    return r


_squarings_jit = numba.njit(cache=True, nogil=True, inline="always")(_squarings)


def _pow(x: np.ndarray, e: float) -> np.ndarray:
    """x ** e for x >= 0; by repeated squaring when e is a whole number in [0, 4096] (128: 8 products)."""
    if not (float(e).is_integer() and 0 <= e <= 4096):
        return x ** e
    return _squarings(np.ones_like(x), x, int(e))


@dataclass
class AtrousSettings:
    iterations: int = 5
    radius: int = 1
    phi_color: float = 10.0
    phi_normal: float = 128.0
    phi_depth: float = 1.0


def atrous_pass_reference(c: np.ndarray, v: np.ndarray, z: np.ndarray, n: np.ndarray, fw: np.ndarray,
                          valid: np.ndarray, step: int, s: AtrousSettings):
    """One pass (module docstring) with tap spacing ``step``: (colour float32 (H, W, 3), variance float32 (H, W)).
    ``c`` colour, ``v`` luminance variance, ``z`` depth, ``n`` unit normals (float32), ``fw`` |grad z|, ``valid``
    pixels that show a surface (others pass through, and are never taps)."""
    h, w = v.shape
    kern = kernel(int(s.radius))
    r = int(s.radius)
    c64 = c.astype(np.float64)
    lum = c64[..., 0] * 0.2126 + c64[..., 1] * 0.7152 + c64[..., 2] * 0.0722
    phi_l = s.phi_color * np.sqrt(np.maximum(gaussian3x3(v), 0.0) + 1e-10)
    k00 = kern[0] * kern[0]
    acc = c64 * k00
    vacc = v.astype(np.float64) * k00 * k00
    wsum = np.full((h, w), k00)
    v64 = v.astype(np.float64)
    fw64 = fw.astype(np.float64)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            sl = _slices(h, w, dy * step, dx * step)
            if (dx == 0 and dy == 0) or sl is None:
                continue
            d, q = sl  # the pixels and their taps, as views (no copies of the images)
            tap = valid[d] & valid[q]
            wl = np.abs(lum[d] - lum[q]) / phi_l[d]
            wz = np.abs(z[d] - z[q]) / (s.phi_depth * fw64[d] * step * np.sqrt(dx * dx + dy * dy))
            nd, nq = n[d], n[q]
            dot = (nd[..., 0] * nq[..., 0] + nd[..., 1] * nq[..., 1] + nd[..., 2] * nq[..., 2]).astype(np.float64)
            wq = np.exp(-wl - wz) * _pow(np.maximum(dot, 0.0), s.phi_normal) * kern[abs(dx)] * kern[abs(dy)]
            wq[~tap] = 0.0
            acc[d] += c64[q] * wq[..., None]
            vacc[d] += v64[q] * wq * wq
            wsum[d] += wq
    return (acc / wsum[..., None]).astype(np.float32), (vacc / (wsum * wsum)).astype(np.float32)


def _whole(e: float) -> int:
    """``e`` as the exponent :func:`_pow` squares by, or -1 where it takes ``x ** e``."""
    return int(e) if float(e).is_integer() and 0 <= e <= 4096 else -1


@numba.njit(cache=True, nogil=True, inline="always")
def _pow1(x, e, e_int):
    """:func:`_pow` of one value: ``x ** e``, by repeated squaring where ``e_int`` (:func:`_whole` of ``e``) is not
    -1."""
    if e_int < 0:
        return x ** e
    return _squarings_jit(1.0, x, e_int)


@numba.njit(cache=True, nogil=True, inline="always")
def _lum(c, y, x):
    """The float64 luminance of pixel (y, x) of float32 ``c``, in :func:`atrous_pass_reference`'s order."""
    return (np.float64(c[y, x, 0]) * 0.2126 + np.float64(c[y, x, 1]) * 0.7152) + np.float64(c[y, x, 2]) * 0.0722


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")  # IEEE division, as numpy
def _atrous_pass(c, v, z, n, fw, valid, step, r, kern, phi_c, phi_n, phi_n_int, phi_z, out_c, out_v):
    """:func:`atrous_pass_reference` per pixel, every float operation in its order and precision (float32 depth
    difference and normal dot product, float64 weights and sums; invalid taps add ``colour * 0``)."""
    h, w = v.shape
    k00 = kern[0] * kern[0]
    dist = np.empty((2 * r + 1, 2 * r + 1))  # |offset| of each tap, in pixels of the pass
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            dist[dy + r, dx + r] = math.sqrt(np.float64(dx * dx + dy * dy))
    for y in numba.prange(h):
        for x in range(w):
            g = 0.0  # gaussian3x3(v) at (y, x)
            for dy in range(-1, 2):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-1, 2):
                    xx = x + dx
                    if xx < 0 or xx >= w:
                        continue
                    g += np.float64(v[yy, xx]) * ((0.25 if dx == 0 else 0.125) * (1.0 if dy == 0 else 0.5))
            if g < 0.0:  # np.maximum(g, 0): NaN stays NaN
                g = 0.0
            phi_l = phi_c * math.sqrt(g + 1e-10)
            lum = _lum(c, y, x)
            depth_scale = phi_z * np.float64(fw[y, x]) * step
            a0 = np.float64(c[y, x, 0]) * k00
            a1 = np.float64(c[y, x, 1]) * k00
            a2 = np.float64(c[y, x, 2]) * k00
            va = np.float64(v[y, x]) * k00 * k00
            ws = k00
            centre = valid[y, x]
            for dy in range(-r, r + 1):
                yy = y + dy * step
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-r, r + 1):
                    xx = x + dx * step
                    if (dx == 0 and dy == 0) or xx < 0 or xx >= w:
                        continue
                    wq = 0.0
                    if centre and valid[yy, xx]:
                        wl = abs(lum - _lum(c, yy, xx)) / phi_l
                        wz = abs(z[y, x] - z[yy, xx]) / (depth_scale * dist[dy + r, dx + r])
                        dot = np.float64(n[y, x, 0] * n[yy, xx, 0] + n[y, x, 1] * n[yy, xx, 1]
                                         + n[y, x, 2] * n[yy, xx, 2])
                        if dot < 0.0:
                            dot = 0.0
                        wq = math.exp(-wl - wz) * _pow1(dot, phi_n, phi_n_int) * kern[abs(dx)] * kern[abs(dy)]
                    a0 += np.float64(c[yy, xx, 0]) * wq
                    a1 += np.float64(c[yy, xx, 1]) * wq
                    a2 += np.float64(c[yy, xx, 2]) * wq
                    va += np.float64(v[yy, xx]) * wq * wq
                    ws += wq
            out_c[y, x, 0] = np.float32(a0 / ws)
            out_c[y, x, 1] = np.float32(a1 / ws)
            out_c[y, x, 2] = np.float32(a2 / ws)
            out_v[y, x] = np.float32(va / (ws * ws))


def atrous_pass(c: np.ndarray, v: np.ndarray, z: np.ndarray, n: np.ndarray, fw: np.ndarray, valid: np.ndarray,
                step: int, s: AtrousSettings):
    """One pass (module docstring) with tap spacing ``step``: (colour float32 (H, W, 3), variance float32 (H, W)),
    the numba kernel of :func:`atrous_pass_reference` (same arguments, same bits)."""
    c = np.ascontiguousarray(c, np.float32)
    v = np.ascontiguousarray(v, np.float32)
    out_c, out_v = np.empty_like(c), np.empty_like(v)
    _atrous_pass(c, v, np.ascontiguousarray(z, np.float32), np.ascontiguousarray(n, np.float32),
                 np.ascontiguousarray(fw, np.float32), np.ascontiguousarray(valid, np.bool_), int(step),
                 int(s.radius), np.asarray(kernel(int(s.radius)), np.float64), float(s.phi_color),
                 float(s.phi_normal), _whole(s.phi_normal), float(s.phi_depth), out_c, out_v)
    return out_c, out_v


def atrous(color: np.ndarray, variance: np.ndarray, depth: np.ndarray, normal: np.ndarray, valid: np.ndarray,
           settings: AtrousSettings = AtrousSettings(), feedback_tap: int = 0):
    """``settings.iterations`` passes with steps 1, 2, 4, ...: (filtered colour, filtered variance, the colour
    after pass ``feedback_tap`` or None). ``depth`` is the distance the depth edge-stopping compares (0 where not
    ``valid``), ``normal`` the surface normals."""
    valid = np.asarray(valid, bool)
    z = np.where(valid, np.asarray(depth, np.float32), 0.0).astype(np.float32)
    n = np.ascontiguousarray(normal, np.float32)
    fw = np.maximum(depth_fwidth(z, valid), 1e-8).astype(np.float32)
    c, v = np.asarray(color, np.float32), np.asarray(variance, np.float32)
    tapped = None
    for it in range(int(settings.iterations)):
        c, v = atrous_pass(c, v, z, n, fw, valid, 1 << it, settings)
        if feedback_tap == it + 1:
            tapped = c.copy()
    return c, v, tapped


def atrous_taps(width: int, height: int, settings: AtrousSettings) -> int:
    """Filter taps of :func:`atrous` (a work counter: pixels x kernel taps x passes)."""
    return int(width) * int(height) * (2 * int(settings.radius) + 1) ** 2 * int(settings.iterations)


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")  # IEEE division, as numpy
def _spatial_variance_at(lum, z, n, valid, fw64, phi_n, phi_n_int, r, active, out):
    """:func:`spatial_variance_reference`'s expressions per pixel of ``active`` (the others keep ``out``'s 0), every
    float operation in their order and precision: float32 depth difference and normal dot product, float64
    weights and sums accumulated tap by tap in row-major order, taps outside the image skipped."""
    h, w = lum.shape
    for y in numba.prange(h):
        for x in range(w):
            if not active[y, x]:
                continue
            s1, s2, ws = 0.0, 0.0, 0.0
            for dy in range(-r, r + 1):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-r, r + 1):
                    xx = x + dx
                    if xx < 0 or xx >= w:
                        continue
                    near = abs(z[yy, xx] - z[y, x]) < 2.0 * fw64[y, x] * max(abs(dx), abs(dy), 1)
                    dot = np.float64(n[y, x, 0] * n[yy, xx, 0] + n[y, x, 1] * n[yy, xx, 1] + n[y, x, 2] * n[yy, xx, 2])
                    if dot < 0.0:  # np.maximum(dot, 0): NaN stays NaN
                        dot = 0.0
                    wq = 0.0
                    if valid[y, x] and valid[yy, xx] and near:
                        wq = _pow1(dot, phi_n, phi_n_int)
                    lq = np.float64(lum[yy, xx])
                    s1 += wq * lq
                    s2 += wq * lq * lq
                    ws += wq
            if ws < 1e-12:  # np.maximum(ws, 1e-12): NaN stays NaN
                ws = 1e-12
            m = s1 / ws
            v = s2 / ws - m * m
            if v < 0.0:
                v = 0.0
            out[y, x] = np.float32(v) if valid[y, x] else np.float32(0.0)


def _variance_inputs(lum, depth, normal, valid):
    """(lum, z, n, valid, fw64): the spatial variance's inputs in their dtypes and its depth tolerance per pixel."""
    valid = np.ascontiguousarray(valid, bool)
    z = np.ascontiguousarray(depth, np.float32)
    n = np.ascontiguousarray(normal, np.float32)
    lum = np.ascontiguousarray(lum, np.float32)
    fw64 = np.maximum(depth_fwidth(z, valid), 1e-3 * z).astype(np.float32).astype(np.float64)
    return lum, z, n, valid, fw64


def spatial_variance(lum: np.ndarray, depth: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                     phi_normal: float = 128.0, radius: int = 2, active: np.ndarray | None = None) -> np.ndarray:
    """Luminance variance from a bilateral (2r + 1)^2 window (SVGF §4.2's spatial estimate where a pixel has too
    little history, q2vkpt's 5x5): taps weighted by ``max(0, n . n') ^ phi_normal``, and only those whose depth is
    within 2 depth derivatives per pixel of distance (|grad z| or 0.1 % of the depth, the larger). Float32 (H, W);
    0 where not ``valid``. ``active`` ((H, W) bool, default every pixel): the pixels that need it (0 elsewhere).
    A compiled pass, parallel over rows, with the bits of :func:`spatial_variance_reference`."""
    lum, z, n, valid, fw64 = _variance_inputs(lum, depth, normal, valid)
    out = np.zeros(lum.shape, np.float32)
    active = np.ones(lum.shape, np.bool_) if active is None else np.ascontiguousarray(active, np.bool_)
    _spatial_variance_at(lum, z, n, valid, fw64, float(phi_normal), _whole(phi_normal), int(radius), active, out)
    return out


def spatial_variance_reference(lum: np.ndarray, depth: np.ndarray, normal: np.ndarray, valid: np.ndarray,
                               phi_normal: float = 128.0, radius: int = 2) -> np.ndarray:
    """:func:`spatial_variance` of every pixel as whole-image numpy expressions, one per window tap."""
    lum, z, n, valid, fw64 = _variance_inputs(lum, depth, normal, valid)
    h, w = lum.shape
    s1, s2, ws = np.zeros((h, w)), np.zeros((h, w)), np.zeros((h, w))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            sl = _slices(h, w, dy, dx)
            if sl is None:
                continue
            d, q = sl
            near = np.abs(z[q] - z[d]) < 2.0 * fw64[d] * max(abs(dx), abs(dy), 1)
            nd, nq = n[d], n[q]
            dot = (nd[..., 0] * nq[..., 0] + nd[..., 1] * nq[..., 1] + nd[..., 2] * nq[..., 2]).astype(np.float64)
            wq = np.where(valid[d] & valid[q] & near, _pow(np.maximum(dot, 0.0), phi_normal), 0.0)
            lq = lum[q].astype(np.float64)
            s1[d] += wq * lq
            s2[d] += wq * lq * lq
            ws[d] += wq
    ws = np.maximum(ws, 1e-12)
    return np.where(valid, np.maximum(s2 / ws - (s1 / ws) ** 2, 0.0), 0.0).astype(np.float32)
