"""Seed 001's per-pixel A-SVGF and TAA passes as Dr.Jit kernels on the run's Mitsuba variant (``llvm_ad_rgb`` on the
CPU, ``cuda_ad_rgb`` on the GPU): the gradient image, gradient à-trous and anti-lag (Table 6.9 stages 3-4), the
temporal accumulation's reprojection (stage 5) and TAA (§6.12), whose histories then stay on the device from frame
to frame. The variance and à-trous stages are the core's device filters (suite.core.device.denoise).

Each kernel is its host twin (:mod:`methods.quake_drt.asvgf`'s numpy stages and numba ``_reproject``,
:func:`methods.quake_drt.taa._taa_pass`) operation for operation; the float32 ``exp`` of the gradient à-trous is
Dr.Jit's, not numpy's, so the frames agree to rounding. TAA keeps its colour and history as rows of four float32 (one
packet gather per tap: 25.0 -> 14.6 ms per 640x360 frame on 2 cores, interleaved, against a Vector3d gather per
tap), its moments in float64 and its history sum in float32: the host's values to float32 rounding. The tests
compare them (tests/methods/quake_drt/test_device_filters.py).
"""
from __future__ import annotations

import numpy as np

from suite.core.device.context import float_rows, read_rows
from suite.core.device.denoise import PixelGrid


def _pixels(dev, w: int, h: int):
    i = dev.arange(w * h)
    return dev.Int32(i // w), dev.Int32(i % w)


def _index(dev, yy, xx, w: int):
    return dev.UInt32(yy * w + xx)


def _catmull_rom(f):
    """Catmull-Rom weights of the taps at -1, 0, 1, 2 for the fractional offset ``f`` (taa._catmull_rom)."""
    f2, f3 = f * f, f * f * f
    return (-0.5 * f3 + f2 - 0.5 * f, 1.5 * f3 - 2.5 * f2 + 1.0, -1.5 * f3 + 2.0 * f2 + 0.5 * f, 0.5 * f3 - 0.5 * f2)


class DeviceTAA:
    """:class:`methods.quake_drt.taa.TAA` with its history on the device: ``__call__`` takes and returns host images
    (the composed frame goes up as float32, the output comes back: counted copies)."""

    def __init__(self, dev, alpha: float, clamp_sigma: float, firefly_sigma: float):
        self.dev = dev
        self.alpha, self.clamp_sigma, self.firefly_sigma = float(alpha), float(clamp_sigma), float(firefly_sigma)
        self.history = None  # (rows of four float32: colour and 0, width, height)

    def set_history(self, image: np.ndarray) -> None:
        """Takes over a host TAA's history (an (H, W, 3) image; a counted copy)."""
        h, w = image.shape[:2]
        self.history = (_colour_rows(self.dev, np.asarray(image).reshape(-1, 3)), w, h)

    def __call__(self, color: np.ndarray, motion: np.ndarray) -> np.ndarray:
        dev = self.dev
        h, w = color.shape[:2]
        c = _colour_rows(dev, np.asarray(color).reshape(-1, 3))
        mv = np.asarray(motion, np.float64).reshape(-1, 2)
        m = (dev.to_device(np.ascontiguousarray(mv[:, 0]), dev.Float64),
             dev.to_device(np.ascontiguousarray(mv[:, 1]), dev.Float64))
        has = self.history is not None and self.history[1:] == (w, h)
        out = taa_pass(dev, c, self.history[0] if has else c, m, w, h, has, self.alpha, self.clamp_sigma,
                       self.firefly_sigma)
        self.history = (out, w, h)
        r = read_rows(dev, out, dev.arange(w * h), 4)
        return dev.to_host(dev.Vector3f(r[0], r[1], r[2]), np.float32).reshape(h, w, 3)


def _colour_rows(dev, rgb: np.ndarray):
    """(N, 3) colours uploaded as float32 (a counted copy) and laid out as rows of four
    (:func:`~suite.core.device.context.float_rows`)."""
    c = dev.to_device(np.asarray(rgb, np.float32), dev.Vector3f)
    return float_rows(dev, c.x, c.y, c.z, dev.dr.zeros(dev.Float, dev.dr.width(c)))


def taa_pass(dev, c, hist, motion, w: int, h: int, has_history: bool, alpha: float, clamp_sigma: float,
             firefly_sigma: float):
    """Steps 1-5 of :mod:`methods.quake_drt.taa` for every pixel: colour and history as rows of four float32 (colour
    and 0: one packet gather per tap), motion in pixels as two Float64 arrays (x, y); returns the output's rows,
    evaluated. The neighbourhood's moments are summed in float64 (their variance, ``E[c^2] - E[c]^2``, cancels where
    the neighbourhood is flat), the reprojected position is float64 (its fraction weighs the history taps) and the
    history's Catmull-Rom sum float32: the host pass's values to float32 rounding."""
    dr, F, F64, I32 = dev.dr, dev.Float, dev.Float64, dev.Int32
    y, x = _pixels(dev, w, h)
    n = w * h
    me = read_rows(dev, c, dev.arange(n), 4)
    cen = [F64(me[k]) for k in range(3)]
    m1, m2 = [dr.zeros(F64, n) for _ in range(3)], [dr.zeros(F64, n) for _ in range(3)]
    for dy in (-1, 0, 1):
        yy = dr.clip(y + dy, 0, h - 1)  # the edge pixel repeats beyond the border
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            q = read_rows(dev, c, _index(dev, yy, dr.clip(x + dx, 0, w - 1), w), 4)
            for k in range(3):
                qk = F64(q[k])
                m1[k], m2[k] = m1[k] + qk, m2[k] + qk * qk
    m1, m2 = [v / 8.0 for v in m1], [v / 8.0 for v in m2]
    fire = dr.full(dev.Bool, False, n)
    for k in range(3):
        sig = dr.sqrt(dr.maximum(m2[k] - m1[k] * m1[k], 0.0))
        fire = fire | (cen[k] < m1[k] - firefly_sigma * sig) | (cen[k] > m1[k] + firefly_sigma * sig)
    centre = [dr.select(fire, m1[k], cen[k]) for k in range(3)]
    if not has_history:
        out = float_rows(dev, *[F(v) for v in centre], dr.zeros(F, n))
        dr.eval(out)
        return out
    bx, by = motion
    best = bx * bx + by * by
    grid = PixelGrid(dev, w, h)
    for _, _, j, inside in grid.window(1):
        qx, qy = dr.gather(F64, motion[0], j, inside), dr.gather(F64, motion[1], j, inside)
        ln = qx * qx + qy * qy
        longer = inside & (ln > best)
        best, bx, by = dr.select(longer, ln, best), dr.select(longer, qx, bx), dr.select(longer, qy, by)
    px, py = F64(x) + 0.5 + bx, F64(y) + 0.5 + by
    usable = (px >= 1.0) & (px < w - 1.0) & (py >= 1.0) & (py < h - 1.0)
    tx, ty = px - 0.5, py - 0.5
    x0, y0 = dr.floor(tx), dr.floor(ty)
    wx, wy = [F(v) for v in _catmull_rom(tx - x0)], [F(v) for v in _catmull_rom(ty - y0)]
    xi0, yi0 = I32(dr.select(usable, x0, 0.0)), I32(dr.select(usable, y0, 0.0))
    prev = [dr.zeros(F, n) for _ in range(3)]
    for j in range(4):
        yi = dr.clip(yi0 + (j - 1), 0, h - 1)
        for i in range(4):
            xi = dr.clip(xi0 + (i - 1), 0, w - 1)
            wgt = wx[i] * wy[j]
            q = read_rows(dev, hist, _index(dev, yi, xi, w), 4, usable)
            prev = [prev[k] + q[k] * wgt for k in range(3)]
    out = []
    for k in range(3):
        mean = (m1[k] * 8.0 + centre[k]) / 9.0
        sq = (m2[k] * 8.0 + centre[k] * centre[k]) / 9.0
        sd = dr.sqrt(dr.maximum(sq - mean * mean, 0.0))
        p = F64(dr.select(dr.isfinite(prev[k]), prev[k], 0.0))
        p = dr.minimum(dr.maximum(p, mean - clamp_sigma * sd), mean + clamp_sigma * sd)
        out.append(F(dr.select(usable, p + alpha * (centre[k] - p), centre[k])))
    res = float_rows(dev, *out, dr.zeros(F, n))
    dr.eval(res)
    return res


def upload_reprojection_guides(dev, guides) -> dict:
    """A frame's reprojection guides on the device (counted copies): validity, float64 points, float32 depth and
    normals, float32 motion (x, y)."""
    motion = np.asarray(guides.motion, np.float32).reshape(-1, 2)
    return {"valid": dev.to_device(np.asarray(guides.valid, bool).reshape(-1), dev.Bool),
            "point": dev.to_device(np.asarray(guides.point, np.float64).reshape(-1, 3), dev.Point3d),
            "depth": dev.to_device(np.asarray(guides.depth, np.float32).reshape(-1), dev.Float),
            "normal": dev.to_device(np.asarray(guides.normal, np.float32).reshape(-1, 3), dev.Vector3f),
            "motion": (dev.to_device(np.ascontiguousarray(motion[:, 0]), dev.Float),
                       dev.to_device(np.ascontiguousarray(motion[:, 1]), dev.Float))}


def reproject(dev, w: int, h: int, cur: dict, tol, prev: dict, cam_prev):
    """:func:`methods.quake_drt.asvgf._reproject` for every pixel: the previous frame's colour, moments and history
    length fetched bilinearly at each pixel's reprojected position, keeping only taps whose depth and normal are
    consistent. ``cur``/``prev``: guides as :func:`upload_reprojection_guides` makes them, ``prev`` with its
    ``color`` (Vector3f), ``moments`` (two Float) and ``hist`` (Float); returns (colour Vector3f, moments, hist,
    reprojected Bool)."""
    dr, F, F64, I32 = dev.dr, dev.Float, dev.Float64, dev.Int32
    y, x = _pixels(dev, w, h)
    valid = cur["valid"]
    px = F64(x) + 0.5 + F64(cur["motion"][0]) - 0.5
    py = F64(y) + 0.5 + F64(cur["motion"][1]) - 0.5
    lx, ly = dr.floor(px), dr.floor(py)
    fx, fy = px - lx, py - ly
    cam = [dev.opaque(F64, float(v)) for v in np.asarray(cam_prev, np.float64)]
    p = cur["point"]
    ex, ey, ez = p.x - cam[0], p.y - cam[1], p.z - cam[2]
    expect = dr.sqrt(ex * ex + ey * ey + ez * ez)
    n = cur["normal"]
    # The history as rows of eight (colour, moments, length, depth, validity) and its normals as rows of four: a tap
    # reads each with one packet gather instead of a gather per value (the same values).
    pc, pn = prev["color"], prev["normal"]
    hist_rows = float_rows(dev, pc.x, pc.y, pc.z, prev["moments"][0], prev["moments"][1], prev["hist"],
                           prev["depth"], dr.select(prev["valid"], F(1.0), F(0.0)))
    normal_rows = float_rows(dev, pn.x, pn.y, pn.z, dr.zeros(F, w * h))
    c = [dr.zeros(F64, w * h) for _ in range(6)]  # colour, moments, history length
    ws = dr.zeros(F64, w * h)
    for k in range(4):
        ox, oy = k % 2, k // 2
        wt = (fx if ox else 1.0 - fx) * (fy if oy else 1.0 - fy)
        tx, ty = I32(dr.select(valid, lx, 0.0)) + ox, I32(dr.select(valid, ly, 0.0)) + oy
        inside = valid & (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
        j = _index(dev, dr.select(inside, ty, 0), dr.select(inside, tx, 0), w)
        r = read_rows(dev, hist_rows, j, 8, inside)
        ok = inside & (r[7] != 0.0)
        ok &= ~(dr.abs(F64(r[6]) - expect) > F64(tol))
        q = read_rows(dev, normal_rows, j, 4, ok)
        ok &= ~(((q[0] * n.x + q[1] * n.y) + q[2] * n.z) <= 0.5)
        c = [dr.select(ok, a + F64(v) * wt, a) for a, v in zip(c, r[0:6])]
        ws = dr.select(ok, ws + wt, ws)
    reprojected = valid & (ws > 1e-3)
    zero = F(0.0)
    out = [dr.select(reprojected, F(a / ws), zero) for a in c]
    return dev.Vector3f(out[0], out[1], out[2]), (out[3], out[4]), out[5], reprojected


def temporal(dev, w: int, h: int, cur_rgb, lum, cur: dict, prev: dict | None, cam_prev, tol, alpha_lag, s):
    """:meth:`methods.quake_drt.asvgf.ASVGF.temporal` on the device: (colour Vector3f, moments (two Float), history
    length Float, reprojected Bool), evaluated. ``cur_rgb`` Vector3f, ``lum`` its luminance (Float), ``alpha_lag``
    Float or None, ``s`` the ASVGFSettings."""
    dr, F = dev.dr, dev.Float
    mom = (lum, lum * lum)
    hist = dr.select(cur["valid"], F(1.0), F(0.0))
    color = cur_rgb
    reprojected = dr.full(dev.Bool, False, w * h)
    if prev is not None:
        prev_c, prev_m, prev_h, reprojected = reproject(dev, w, h, cur, tol, prev, cam_prev)
        hist_r = dr.minimum(prev_h + 1.0, F(float(s.history_cap)))
        a_c = dr.maximum(F(float(s.alpha_color)), 1.0 / hist_r)
        a_m = dr.maximum(F(float(s.alpha_moments)), 1.0 / hist_r)
        if alpha_lag is not None and s.antilag:
            a_c = a_c + (1.0 - a_c) * alpha_lag
            a_m = a_m + (1.0 - a_m) * alpha_lag
        color = dr.select(reprojected, prev_c + (cur_rgb - prev_c) * a_c, cur_rgb)
        mom = tuple(dr.select(reprojected, pm + (m - pm) * a_m, m) for pm, m in zip(prev_m, mom))
        hist = dr.select(reprojected, hist_r, hist)
    dr.eval(color, *mom, hist, reprojected)
    return color, mom, hist, reprojected


GRAD_DWN = 3  # asvgf.GRAD_DWN: the strata and gradient cells are 3x3 pixels


def gradient(dev, w: int, h: int, lum, cur_pixels: np.ndarray, l_prev: np.ndarray):
    """:meth:`methods.quake_drt.asvgf.ASVGF.gradient` on the device (stage 3): per 3x3 cell (delta, max, luminance
    mean, standard deviation) as four Float arrays of the cell grid. ``lum``: the frame's luminance (Float, full
    resolution); ``cur_pixels`` the gradient samples' pixels and ``l_prev`` their previous luminance (host arrays,
    from the forward projection). The cell sums take numpy's order (rows of three, then the rows)."""
    dr, F, I32 = dev.dr, dev.Float, dev.Int32
    cw, ch = -(-w // GRAD_DWN), -(-h // GRAD_DWN)
    i = dev.arange(cw * ch)
    cy, cx = I32(i // cw), I32(i % cw)
    total = total2 = None
    for a in range(GRAD_DWN):
        row = row2 = None
        for b in range(GRAD_DWN):
            y, x = cy * GRAD_DWN + a, cx * GRAD_DWN + b
            inside = (y < h) & (x < w)
            v = dr.gather(F, lum, _index(dev, dr.select(inside, y, 0), dr.select(inside, x, 0), w), inside)
            row, row2 = (v, v * v) if row is None else (row + v, row2 + v * v)
        total, total2 = (row, row2) if total is None else (total + row, total2 + row2)
    mean = total / F(9.0)
    std = dr.sqrt(dr.maximum(total2 / F(9.0) - mean * mean, 0.0))
    delta, mx = dr.zeros(F, cw * ch), dr.zeros(F, cw * ch)
    if len(cur_pixels):
        cur = np.asarray(cur_pixels, np.int64)
        cells = dev.to_device(((cur // w) // GRAD_DWN * cw + (cur % w) // GRAD_DWN).astype(np.uint32), dev.UInt32)
        l_cur = dr.gather(F, lum, dev.to_device(cur.astype(np.uint32), dev.UInt32))
        lp = dev.to_device(np.asarray(l_prev, np.float32), F)
        dr.scatter(delta, l_cur - lp, cells)        # one sample per cell (the forward projection keeps the first)
        dr.scatter(mx, dr.maximum(l_cur, lp), cells)
    dr.eval(delta, mx, mean, std)
    return delta, mx, mean, std


def gradient_atrous(dev, grad, w: int, h: int, s):
    """:meth:`methods.quake_drt.asvgf.ASVGF.gradient_atrous` on the device (stage 4): lambda per cell (Float)."""
    dr, F = dev.dr, dev.Float
    cw, ch = -(-w // GRAD_DWN), -(-h // GRAD_DWN)
    cells = PixelGrid(dev, cw, ch)
    delta, mx, mean, std = grad
    val = [delta, mx]
    var = std * std
    lum = dr.minimum(mean, F(8.0))  # the thesis code's min(lum, 8)

    for it in range(int(s.gradient_iterations)):
        step = 1 << it
        sig = dr.zeros(F, cw * ch)  # denoise.gaussian3x3(var, float32), then doubled
        for dy, dx, j, inside in cells.window(1):  # offsets outside every cell add nothing
            sig = sig + dr.gather(F, var, j, inside) * F((0.25 if dx == 0 else 0.125) * (1.0 if dy == 0 else 0.5))
        sig = dr.maximum(F(float(s.gradient_sigma)) * (F(2.0) * sig), F(1e-8))
        acc, wsum, vacc = list(val), dr.full(F, 1.0, cw * ch), var
        for dy, dx, j, inside in cells.window(1, step, centre=False):
            lq = dr.gather(F, lum, j, inside)
            d = lum - lq
            wq = dr.select(inside, F(1.0), F(0.0)) * dr.exp(-(d * d) / sig)
            acc = [a + dr.gather(F, v, j, inside) * wq for a, v in zip(acc, val)]
            vacc = vacc + dr.gather(F, var, j, inside) * wq * wq
            wsum = wsum + wq
        val = [a / wsum for a in acc]
        var = vacc / (wsum * wsum)
        dr.eval(*val, var)
    delta, mx = dr.abs(val[0]), val[1]
    lam = dr.select(mx > 1e-6, dr.minimum(delta / dr.maximum(mx, F(1e-12)), 1.0), 0.0)
    dr.eval(lam)
    return lam


def antilag(dev, lam, w: int, h: int):
    """:meth:`methods.quake_drt.asvgf.ASVGF.antilag` on the device: per pixel the largest lambda of the 3x3 gradient
    cells around its cell (Float, full resolution)."""
    dr, F = dev.dr, dev.Float
    cw, ch = -(-w // GRAD_DWN), -(-h // GRAD_DWN)
    y, x = _pixels(dev, w, h)
    cy, cx = y // GRAD_DWN, x // GRAD_DWN
    m = dr.zeros(F, w * h)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            yy, xx = cy + dy, cx + dx
            inside = (yy >= 0) & (yy < ch) & (xx >= 0) & (xx < cw)
            q = dr.gather(F, lam, _index(dev, dr.select(inside, yy, 0), dr.select(inside, xx, 0), cw), inside)
            m = dr.maximum(m, q)   # lambda >= 0: the zero outside changes no maximum
    dr.eval(m)
    return m
