"""Temporal anti-aliasing (seed 001 §4.5, §6.12), after the composition.

As §6.12 describes and q2vkpt's ``asvgf_taa.comp`` (which the thesis's ``asvgf_taa.comp`` copies) does:

1. the mean and standard deviation of the current colour in the 3x3 neighbourhood of each pixel; a centre
   outside the neighbours' ``mean +- 3 sigma`` is replaced by their mean (firefly rejection);
2. the motion vector of the 3x3 neighbourhood with the longest motion (so edges of moving objects reproject
   with the object);
3. the previous output fetched at ``pixel + motion`` with a Catmull-Rom bicubic filter (4x4 taps);
4. that history clamped to ``mean +- clamp_sigma * sigma`` of the 3x3 neighbourhood (centre included);
5. ``out = history + alpha * (current - history)`` with the new frame's weight ``alpha`` = 0.1.

A pixel whose history falls outside the image keeps its current colour. §6.12 says the history is clamped to
``N(mu, 3 sigma)``; q2vkpt's code clamps to one sigma and uses 3 sigma for the firefly test. ``clamp_sigma``
selects (default 1, the code's; the ``paper`` settings use 3, the text's).
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def _catmull_rom(f):
    """Catmull-Rom weights of the taps at -1, 0, 1, 2 for the fractional offset ``f``."""
    f2, f3 = f * f, f * f * f
    return np.array([-0.5 * f3 + f2 - 0.5 * f, 1.5 * f3 - 2.5 * f2 + 1.0, -1.5 * f3 + 2.0 * f2 + 0.5 * f,
                     0.5 * f3 - 0.5 * f2])


@numba.njit(cache=True, nogil=True, parallel=True)
def _taa_pass(c, hist, motion, has_history, alpha, clamp_sigma, firefly_sigma, out):
    """Steps 1-5 of the module docstring for every pixel (numba, parallel over rows)."""
    h, w = c.shape[0], c.shape[1]
    for y in numba.prange(h):
        for x in range(w):
            m1 = np.zeros(3)
            m2 = np.zeros(3)
            for dy in range(-1, 2):
                yy = min(max(y + dy, 0), h - 1)  # the edge pixel repeats beyond the border
                for dx in range(-1, 2):
                    if dx == 0 and dy == 0:
                        continue
                    xx = min(max(x + dx, 0), w - 1)
                    for ch in range(3):
                        m1[ch] += c[yy, xx, ch]
                        m2[ch] += c[yy, xx, ch] * c[yy, xx, ch]
            fire = False
            for ch in range(3):
                m1[ch] /= 8.0
                m2[ch] /= 8.0
                sig = np.sqrt(max(m2[ch] - m1[ch] * m1[ch], 0.0))
                if c[y, x, ch] < m1[ch] - firefly_sigma * sig or c[y, x, ch] > m1[ch] + firefly_sigma * sig:
                    fire = True
            centre = np.empty(3)
            for ch in range(3):
                centre[ch] = m1[ch] if fire else c[y, x, ch]
            if not has_history:
                for ch in range(3):
                    out[y, x, ch] = centre[ch]
                continue
            bx, by = motion[y, x, 0], motion[y, x, 1]
            best = bx * bx + by * by
            for dy in range(-1, 2):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-1, 2):
                    xx = x + dx
                    if xx < 0 or xx >= w:
                        continue
                    ln = motion[yy, xx, 0] ** 2 + motion[yy, xx, 1] ** 2
                    if ln > best:
                        best, bx, by = ln, motion[yy, xx, 0], motion[yy, xx, 1]
            px, py = x + 0.5 + bx, y + 0.5 + by
            if not (px >= 1.0 and px < w - 1.0 and py >= 1.0 and py < h - 1.0):
                for ch in range(3):
                    out[y, x, ch] = centre[ch]
                continue
            tx, ty = px - 0.5, py - 0.5
            x0, y0 = np.floor(tx), np.floor(ty)
            fx, fy = tx - x0, ty - y0
            wx = _catmull_rom(fx)
            wy = _catmull_rom(fy)
            prev = np.zeros(3)
            for j in range(4):
                yi = min(max(int(y0) + j - 1, 0), h - 1)
                for i in range(4):
                    xi = min(max(int(x0) + i - 1, 0), w - 1)
                    wgt = wx[i] * wy[j]
                    for ch in range(3):
                        prev[ch] += hist[yi, xi, ch] * wgt
            for ch in range(3):
                mean = (m1[ch] * 8.0 + centre[ch]) / 9.0
                sq = (m2[ch] * 8.0 + centre[ch] * centre[ch]) / 9.0
                sd = np.sqrt(max(sq - mean * mean, 0.0))
                p = prev[ch] if np.isfinite(prev[ch]) else 0.0
                p = min(max(p, mean - clamp_sigma * sd), mean + clamp_sigma * sd)
                out[y, x, ch] = p + alpha * (centre[ch] - p)


class TAA:
    def __init__(self, alpha: float = 0.1, clamp_sigma: float = 1.0, firefly_sigma: float = 3.0):
        self.alpha = float(alpha)
        self.clamp_sigma = float(clamp_sigma)
        self.firefly_sigma = float(firefly_sigma)
        self.reset()

    def reset(self) -> None:
        self.history = None

    def __call__(self, color: np.ndarray, motion: np.ndarray, st=None) -> np.ndarray:
        c = np.ascontiguousarray(color, np.float64)
        h, w = c.shape[:2]
        has = self.history is not None and self.history.shape == c.shape
        hist = np.ascontiguousarray(self.history, np.float64) if has else c
        out = np.empty_like(c)
        _taa_pass(c, hist, np.ascontiguousarray(motion, np.float64), has, self.alpha, self.clamp_sigma,
                  self.firefly_sigma, out)
        if st is not None:
            st.count(taps=h * w * (9 + 9 + 16))
        self.history = out
        return out.astype(np.float32)
