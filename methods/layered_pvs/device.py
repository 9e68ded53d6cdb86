"""The layered SVGF (seed 002 §4.4.1) as a Dr.Jit kernel on the run's Mitsuba variant: one code path, vectorised and
multi-threaded on ``llvm_ad_rgb`` and on the GPU on ``cuda_ad_rgb`` (the core's device kernels, suite.core.device).

:func:`svgf_passes` is :func:`methods.layered_pvs.server._svgf_passes` (the numba kernel Embree runs): the same
grids in the kernel's (H, W, L[, 3]) layout, one lane per (pixel, layer) slot, every float64 operation in the numba
kernel's order; Dr.Jit's ``exp`` (and ``pow`` for a fractional normal exponent) is its own, so the two agree to
rounding (the stage rounds the result to float32; tests/methods/layered_pvs/test_device.py compares them). The
grids go up once per update and the filtered illumination comes back once (counted copies); between the passes
everything stays on the device, and every pass is the same compiled kernel (its step is read from memory).
"""
from __future__ import annotations

import math

import numpy as np

B3 = (1.0 / 16, 1.0 / 4, 3.0 / 8, 1.0 / 4, 1.0 / 16)    # the 5x5 B3-spline kernel of the numba pass


def _svgf_pass(dev, shape, frags, col, var, pos, nrm, valid, dep, step: int, pix_angle: float, shift_scale: float,
               sigma_l: float, sigma_n: float):
    """One à-trous pass with tap spacing ``step``: the grids are flat (H, W, L) arrays, the lanes the slots that hold
    a fragment (``frags``, their flat indices, ascending); returns the new (colour Vector3d, variance Float64) grids
    (0 in empty slots, as the numba pass leaves them)."""
    dr, F64, I32, U = dev.dr, dev.Float64, dev.Int32, dev.UInt32
    H, W, L = shape
    pix = frags // L
    y, x = I32(pix // W), I32(pix % W)
    step_i = dev.opaque(I32, int(step))
    step_f = dev.opaque(F64, float(step))
    int_n = int(sigma_n) if sigma_n == math.floor(sigma_n) and 0 < sigma_n <= 1024 else 0
    p = dr.gather(dev.Vector3d, pos, frags)
    n = dr.gather(dev.Vector3d, nrm, frags)
    c = dr.gather(dev.Vector3d, col, frags)
    v = dr.gather(F64, var, frags)
    lc = (0.2126 * c.x + 0.7152 * c.y) + 0.0722 * c.z
    sd = dr.sqrt(dr.maximum(v, 0.0))
    foot = dr.gather(F64, dep, frags) * dev.opaque(F64, float(pix_angle))
    shift_scale = dev.opaque(F64, float(shift_scale))
    sigma_l = dev.opaque(F64, float(sigma_l))
    size = dr.width(frags)

    def b3(k):  # B3[k + 2] for an offset k in -2..2 (the table's values, selected)
        a = dr.abs(k)
        return dr.select(a == 0, B3[2], dr.select(a == 1, B3[1], B3[0]))

    # The 25 taps as a symbolic loop (one small kernel; written out, LLVM took seconds to compile each pass shape).
    def body(t, wsum, vsum, acc):
        ty, tx = I32(t // 5) - 2, I32(t % 5) - 2
        yy, xx = y + ty * step_i, x + tx * step_i
        inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
        base = U(dr.select(inside, yy * W + xx, 0)) * L
        radius = dr.sqrt(F64(tx * tx + ty * ty))          # math.sqrt of the same whole number: exact
        shift = shift_scale * foot * radius * step_f
        # §4.4.1: of the fragments at the tap, the one closest to the centre fragment's shifted plane; the search
        # stops at the tap's first empty layer (the gather's mask carries it on)
        def search(m, alive, best, best_d, best_pd):
            alive = alive & dr.gather(dev.Bool, valid, base + U(m), alive)
            q = dr.gather(dev.Vector3d, pos, base + U(m), alive)
            pd = (n.x * (q.x - p.x) + n.y * (q.y - p.y)) + n.z * (q.z - p.z)
            dd = dr.abs(pd - shift)
            better = alive & (dd < best_d)
            return (m + 1, alive, dr.select(better, m, best), dr.select(better, dd, best_d),
                    dr.select(better, pd, best_pd))

        _, _, best, best_d, best_pd = dr.while_loop(
            (dr.zeros(I32, size), inside, dr.full(I32, -1, size), dr.full(F64, 1e300, size), dr.zeros(F64, size)),
            lambda m, alive, *_: alive & (m < L), search)
        found = best >= 0
        j = base + U(dr.maximum(best, 0))
        cb = dr.gather(dev.Vector3d, col, j, found)
        nb = dr.gather(dev.Vector3d, nrm, j, found)
        vb = dr.gather(F64, var, j, found)
        ln = (0.2126 * cb.x + 0.7152 * cb.y) + 0.0722 * cb.z
        ndot = (n.x * nb.x + n.y * nb.y) + n.z * nb.z
        ok = found & (ndot > 0.0)
        if int_n > 0:
            wn, b, e = None, ndot, int_n
            while e:
                if e & 1:
                    wn = b if wn is None else wn * b
                b = b * b
                e >>= 1
        else:
            wn = dr.power(dr.select(ok, ndot, 1.0), float(sigma_n))
        wn = dr.select(ndot == 1.0, 1.0, wn)
        dist_px = radius * step_f
        wzl = dr.exp(-(dr.abs(best_pd) / (foot * (dist_px + 1.0) + 1e-12)
                       + dr.abs(lc - ln) / (sigma_l * sd + 1e-10)))
        wgt = F64(b3(ty)) * F64(b3(tx)) * wn * wzl
        wsum = dr.select(ok, wsum + wgt, wsum)
        vsum = dr.select(ok, vsum + wgt * wgt * vb, vsum)
        acc = dr.select(ok, dev.Vector3d(acc.x + wgt * cb.x, acc.y + wgt * cb.y, acc.z + wgt * cb.z), acc)
        return t + 1, wsum, vsum, acc

    _, wsum, vsum, acc = dr.while_loop((dr.zeros(U, size), dr.zeros(F64, size), dr.zeros(F64, size),
                                        dr.zeros(dev.Vector3d, size)), lambda t, *_: t < 25, body)
    kept = wsum > 1e-150
    out_c = dr.zeros(dev.Vector3d, H * W * L)
    out_v = dr.zeros(F64, H * W * L)
    dr.scatter(out_c, dr.select(kept, acc / wsum, c), frags)
    dr.scatter(out_v, dr.select(kept, vsum / (wsum * wsum), v), frags)
    dr.eval(out_c, out_v)
    return out_c, out_v


def svgf_passes(dev, col, var, pos, nrm, val, dep, pix_angle: float, iterations: int, shift_scale: float = 1.0,
                sigma_l: float = 4.0, sigma_n: float = 128.0) -> np.ndarray:
    """:func:`methods.layered_pvs.server._svgf_passes` on ``dev``: (H, W, L[, 3]) float64 grids (bool ``val``) in,
    the filtered (H, W, L, 3) float64 illumination out."""
    shape = tuple(np.shape(val))
    up3 = lambda a: dev.to_device(np.ascontiguousarray(a, np.float64).reshape(-1, 3), dev.Vector3d)  # noqa: E731
    up1 = lambda a, t: dev.to_device(np.ascontiguousarray(a).reshape(-1), t)  # noqa: E731
    c, v = up3(col), up1(np.asarray(var, np.float64), dev.Float64)
    p, n = up3(pos), up3(nrm)
    valid, d = up1(np.asarray(val, bool), dev.Bool), up1(np.asarray(dep, np.float64), dev.Float64)
    frags = dev.dr.compress(valid)     # the lanes: the slots that hold a fragment (the numba pass skips the others)
    for it in range(int(iterations)):
        c, v = _svgf_pass(dev, shape, frags, c, v, p, n, valid, d, 1 << it, pix_angle, shift_scale, sigma_l,
                          sigma_n)
    return dev.to_host(c, np.float64).reshape(shape + (3,))
