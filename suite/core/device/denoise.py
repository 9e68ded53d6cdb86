""":mod:`suite.core.denoise` on the device: the edge-avoiding à-trous passes and the bilateral spatial variance as
Dr.Jit kernels, one code path for ``llvm_ad_rgb`` and ``cuda_ad_rgb`` (module docstring of suite.core.denoise for
the filter and its equations).

Images are flat row-major arrays of ``width * height`` pixels (:class:`DeviceFrame` holds one frame's guides). The
operations are the host kernels', in their order (invalid taps adding ``colour * 0``, taps outside the image
skipped). The à-trous passes run in float32, weights and sums included (the host's are float64), on tables of rows
of four (colour and variance; normal and depth) that a tap reads with one packet gather each: on ``llvm_ad_rgb`` that
halves a pass (72.5 -> 35.8 ms for five passes at 640x360, 2 cores, interleaved), and on a GPU float32 is the
arithmetic every graphics card runs at full rate. Their results are the host's to float32 rounding (relative 3e-6
at most at 640x360). The spatial variance keeps float64 sums: ``E[l^2] - E[l]^2`` cancels where the variance is small
against the mean. ``exp`` (and ``pow`` for a fractional normal exponent) is Dr.Jit's own polynomial, not the C
library's (tests/core/test_device_denoise.py). One kernel per pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from suite.core.denoise import AtrousSettings, _whole, kernel
from suite.core.device.context import float_rows, read_rows


@dataclass
class DeviceFrame:
    """One frame's filter guides on the device: ``depth`` (Float, 0 where not valid), ``normal`` (Vector3f),
    ``valid`` (Bool), flat row-major."""

    device: object
    width: int
    height: int
    depth: object
    normal: object
    valid: object

    @classmethod
    def from_host(cls, dev, depth, normal, valid) -> "DeviceFrame":
        """Uploads (H, W) depth, (H, W, 3) normals and (H, W) validity (counted copies); depth is zeroed where not
        valid, as :func:`suite.core.denoise.atrous` does."""
        h, w = np.shape(valid)
        valid = np.asarray(valid, bool)
        z = np.where(valid, np.asarray(depth, np.float32), 0.0).astype(np.float32)
        return cls(dev, w, h, dev.to_device(z.reshape(-1), dev.Float),
                   dev.to_device(np.ascontiguousarray(normal, np.float32).reshape(-1, 3), dev.Vector3f),
                   dev.to_device(valid.reshape(-1), dev.Bool))


class PixelGrid:
    """Pixel coordinates of a row-major image and its taps at integer offsets (a gather index and an inside mask):
    the stencil of the device filters here and of quake_drt's (methods/quake_drt/device.py)."""

    def __init__(self, dev, width: int, height: int):
        self.dev, self.w, self.h = dev, int(width), int(height)
        i = dev.arange(self.w * self.h)
        self.y, self.x = dev.Int32(i // self.w), dev.Int32(i % self.w)

    def tap(self, dy, dx):
        """(index of pixel (y + dy, x + dx), whether it lies in the image); None when no pixel's tap does. The
        offsets are ints, or Int32 values read from memory (one kernel for every pass of a filter)."""
        if isinstance(dy, int) and isinstance(dx, int) and (abs(dy) >= self.h or abs(dx) >= self.w):
            return None
        yy, xx = self.y + dy, self.x + dx
        inside = (yy >= 0) & (yy < self.h) & (xx >= 0) & (xx < self.w)
        return self.dev.UInt32(self.dev.dr.select(inside, yy * self.w + xx, 0)), inside

    def window(self, radius: int, step=1, centre: bool = True):
        """The taps of the (2 radius + 1)^2 window at spacing ``step`` (an int, or an Int32 read from memory), in
        row-major order: ``(dy, dx, index, inside)``, without the offsets no pixel's tap reaches (:meth:`tap`) and,
        unless ``centre``, without (0, 0)."""
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0 and not centre:
                    continue
                t = self.tap(dy * step, dx * step)
                if t is not None:
                    yield (dy, dx) + t


def _pow(dev, x, e: float):
    """:func:`suite.core.denoise._pow` (repeated squaring for a whole exponent in [0, 4096])."""
    k = _whole(e)
    if k < 0:
        return dev.dr.power(x, e)
    r, b = None, x
    while k > 0:
        if k & 1:
            r = b if r is None else r * b
        b = b * b
        k >>= 1
    return dev.dr.full(type(x), 1.0, dev.dr.width(x)) if r is None else r


def _dot32(n, m):
    """The float32 dot product in the host's order: (n0 m0 + n1 m1) + n2 m2."""
    return (n.x * m.x + n.y * m.y) + n.z * m.z


def depth_fwidth(frame: DeviceFrame, grid: PixelGrid | None = None):
    """:func:`suite.core.denoise.depth_fwidth` of the frame's (zeroed) depth: the largest |dz| to a valid
    4-neighbour, float32."""
    dev = frame.device
    dr, F = dev.dr, dev.Float
    grid = grid or PixelGrid(dev, frame.width, frame.height)
    d = dr.select(frame.valid, frame.depth, 0.0)
    out = dr.zeros(F, frame.width * frame.height)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        t = grid.tap(dy, dx)
        if t is None:
            continue
        q, inside = t
        ok = inside & dr.gather(dev.Bool, frame.valid, q, inside)
        out = dr.maximum(out, dr.select(ok, dr.abs(dr.gather(F, d, q, inside) - d), 0.0))
    return out


ROW = 4  # float32 values per pixel in the à-trous passes' tables (a power of two: one packet gather)


def _gaussian3x3(dev, grid: PixelGrid, cv):
    """:func:`suite.core.denoise.gaussian3x3` of the variance (the fourth value of ``cv``'s rows), row-major tap
    order, zero outside the image, float32."""
    dr, F = dev.dr, dev.Float
    g = dr.zeros(F, grid.w * grid.h)
    for dy, dx, q, inside in grid.window(1):
        wgt = (0.25 if dx == 0 else 0.125) * (1.0 if dy == 0 else 0.5)
        g = g + dr.select(inside, dr.gather(F, cv, q * ROW + 3, inside) * wgt, 0.0)
    return g


def _lum32(c):
    return (c[0] * 0.2126 + c[1] * 0.7152) + c[2] * 0.0722


def atrous_pass(frame: DeviceFrame, cv, guide, fw, step: int, s: AtrousSettings, grid: PixelGrid | None = None):
    """One pass with tap spacing ``step`` on tables of rows of four (:func:`~suite.core.device.context.float_rows`):
    ``cv`` (colour, variance) in, the filtered ``cv`` out, evaluated; ``guide``: (normal, depth) rows of the frame.
    ``fw``: max(|grad z|, 1e-8) as :func:`atrous` computes it. The host pass's operations in its order, in float32
    (module docstring). The step is read from memory, so every pass runs the same kernel."""
    dev = frame.device
    dr, F = dev.dr, dev.Float
    grid = grid or PixelGrid(dev, frame.width, frame.height)
    size = grid.w * grid.h
    step_i = dev.opaque(dev.Int32, int(step))
    step_f = dev.opaque(F, float(step))
    kern = kernel(int(s.radius))
    r = int(s.radius)
    k00 = kern[0] * kern[0]
    valid = frame.valid
    me = dev.arange(size)
    c = read_rows(dev, cv, me, ROW)
    n = read_rows(dev, guide, me, ROW)
    z = n[3]
    g = _gaussian3x3(dev, grid, cv)
    g = dr.select(g < 0.0, 0.0, g)  # the host's clamp: NaN stays NaN
    phi_l = dev.opaque(F, float(s.phi_color)) * dr.sqrt(g + 1e-10)
    lum = _lum32(c)
    depth_scale = dev.opaque(F, float(s.phi_depth)) * fw * step_f
    a = [c[k] * k00 for k in range(3)]
    va = c[3] * (k00 * k00)
    ws = dr.full(F, k00, size)
    for dy, dx, q, inside in grid.window(r, step_i, centre=False):
        cq = read_rows(dev, cv, q, ROW, inside)
        nq = read_rows(dev, guide, q, ROW, inside)
        tap = inside & valid & dr.gather(dev.Bool, valid, q, inside)
        wl = dr.abs(lum - _lum32(cq)) / phi_l
        wz = dr.abs(z - nq[3]) / (depth_scale * math.sqrt(float(dx * dx + dy * dy)))
        dot = dr.maximum((n[0] * nq[0] + n[1] * nq[1]) + n[2] * nq[2], 0.0)
        wq = dr.exp(-wl - wz) * _pow(dev, dot, float(s.phi_normal)) * (kern[abs(dx)] * kern[abs(dy)])
        wq = dr.select(tap, wq, 0.0)
        # taps outside the image are skipped; invalid ones inside add colour * 0 (the host kernel's sums)
        a = [dr.select(inside, a[k] + cq[k] * wq, a[k]) for k in range(3)]
        va = dr.select(inside, va + cq[3] * wq * wq, va)
        ws = dr.select(inside, ws + wq, ws)
    out = float_rows(dev, a[0] / ws, a[1] / ws, a[2] / ws, va / (ws * ws))
    dr.eval(out)
    return out


def _unpack(dev, cv):
    """(colour Vector3f, variance Float) of a :func:`~suite.core.device.context.float_rows` table."""
    r = read_rows(dev, cv, dev.arange(dev.dr.width(cv) // ROW), ROW)
    return dev.Vector3f(r[0], r[1], r[2]), r[3]


def atrous(frame: DeviceFrame, color, variance, settings: AtrousSettings = AtrousSettings(), feedback_tap: int = 0):
    """:func:`suite.core.denoise.atrous` on the device: ``settings.iterations`` passes with steps 1, 2, 4, ...;
    (filtered colour Vector3f, filtered variance Float, the colour after pass ``feedback_tap`` or None)."""
    if int(settings.iterations) <= 0:
        return color, variance, None
    dev = frame.device
    grid = PixelGrid(dev, frame.width, frame.height)
    fw = dev.dr.maximum(depth_fwidth(frame, grid), 1e-8)
    c = dev.Vector3f(color)
    cv = float_rows(dev, c.x, c.y, c.z, dev.Float(variance))
    nrm = frame.normal
    guide = float_rows(dev, nrm.x, nrm.y, nrm.z, frame.depth)
    dev.dr.eval(fw, guide)
    tapped = None
    for it in range(int(settings.iterations)):
        cv = atrous_pass(frame, cv, guide, fw, 1 << it, settings, grid)
        if feedback_tap == it + 1:
            tapped = _unpack(dev, cv)[0]
    c, v = _unpack(dev, cv)
    dev.dr.eval(c, v, *([tapped] if tapped is not None else []))
    return c, v, tapped


def spatial_variance(frame: DeviceFrame, lum, phi_normal: float = 128.0, radius: int = 2, active=None):
    """:func:`suite.core.denoise.spatial_variance` on the device (``lum`` Float; the frame's depth and normals):
    the luminance variance of a bilateral (2r + 1)^2 window, Float, 0 where not valid. ``active`` (Bool): the pixels
    that need it; the others get 0, and the window is summed only in the packets that hold such a pixel
    (:meth:`~suite.core.device.context.Device.where_any`)."""
    dev = frame.device
    dr, F, F64 = dev.dr, dev.Float, dev.Float64
    grid = PixelGrid(dev, frame.width, frame.height)
    z, n, valid = frame.depth, frame.normal, frame.valid
    size = grid.w * grid.h

    def window(todo):
        fw64 = F64(dr.maximum(depth_fwidth(frame, grid), F(1e-3) * z))
        s1, s2, ws = dr.zeros(F64, size), dr.zeros(F64, size), dr.zeros(F64, size)
        for dy, dx, q, inside in grid.window(radius):
            inside = inside & todo
            near = F64(dr.abs(dr.gather(F, z, q, inside) - z)) < 2.0 * fw64 * float(max(abs(dx), abs(dy), 1))
            dot = dr.maximum(F64(_dot32(n, dr.gather(dev.Vector3f, n, q, inside))), 0.0)
            ok = inside & valid & dr.gather(dev.Bool, valid, q, inside) & near
            wq = dr.select(ok, _pow(dev, dot, float(phi_normal)), 0.0)
            lq = F64(dr.gather(F, lum, q, inside))
            s1 = dr.select(inside, s1 + wq * lq, s1)
            s2 = dr.select(inside, s2 + wq * lq * lq, s2)
            ws = dr.select(inside, ws + wq, ws)
        ws = dr.maximum(ws, 1e-12)
        m = s1 / ws
        return (F(dr.select(valid, dr.maximum(s2 / ws - m * m, 0.0), 0.0)),)

    if active is None:
        out, = window(dev.Bool(True))
    else:
        out, = dev.where_any(active, window, dr.zeros(F, size))
    dr.eval(out)
    return out


def atrous_arrays(dev, color, variance, depth, normal, valid, settings: AtrousSettings = AtrousSettings(),
                  feedback_tap: int = 0):
    """:func:`suite.core.denoise.atrous`'s signature and results (numpy in, numpy out) with the passes on ``dev``:
    the inputs go up and the results come back as counted copies."""
    h, w = np.shape(valid)
    frame = DeviceFrame.from_host(dev, depth, normal, valid)
    c, v, tapped = atrous(frame, dev.to_device(np.asarray(color, np.float32).reshape(-1, 3), dev.Vector3f),
                          dev.to_device(np.asarray(variance, np.float32).reshape(-1), dev.Float), settings,
                          feedback_tap)
    img = lambda x: dev.to_host(x, np.float32).reshape(h, w, 3)  # noqa: E731
    return img(c), dev.to_host(v, np.float32).reshape(h, w), (img(tapped) if tapped is not None else None)


def spatial_variance_arrays(dev, lum, depth, normal, valid, phi_normal: float = 128.0, radius: int = 2):
    """:func:`suite.core.denoise.spatial_variance` (numpy in, numpy out) computed on ``dev``."""
    h, w = np.shape(valid)
    frame = DeviceFrame.from_host(dev, depth, normal, valid)
    out = spatial_variance(frame, dev.to_device(np.asarray(lum, np.float32).reshape(-1), dev.Float), phi_normal,
                           radius)
    return dev.to_host(out, np.float32).reshape(h, w)
