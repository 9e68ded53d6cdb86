"""A-SVGF (Schied, Peters and Dachsbacher 2018), the denoiser of seed 001 (§4.4, §6.10, Tables 6.9 and 6.10).

Stages in the order of Table 6.9 (TAA is :mod:`.taa`):

1. **RNG** (:mod:`.rng`): a seed per pixel for the frame.
2. **Forward projection** (:meth:`ASVGF.forward_project`), before any ray is traced: the previous frame is cut
   into 3x3 strata (``GRAD_DWN``); one pixel per stratum, chosen with q2vkpt's TEA hash, has its shading sample
   (primitive, barycentrics) moved to the current frame and projected; the first sample that lands in a 3x3
   cell of the current frame becomes that cell's *gradient sample*: its pixel shades the previous frame's
   surface point with the previous frame's seed (so with the same random numbers). A sample whose point is
   hidden in the current frame (its distance differs from the G-buffer's depth there) is dropped.
3. **Gradient image** (:meth:`ASVGF.gradient`), one texel per 3x3 cell: ``delta = l_curr - l_prev`` of the
   gradient sample's illumination luminance and ``max(l_curr, l_prev)``, plus the cell's luminance mean and
   standard deviation (for edge stopping).
4. **Gradient a-trous** (:meth:`ASVGF.gradient_atrous`): ``gradient_iterations`` a-trous passes (steps 1, 2,
   4, ...) reconstruct a dense gradient from the sparse one, stopping at luminance edges
   (``exp(-dl^2 / (gradient_sigma * var))``, the thesis code's ``asvgf_grad_atrous``); then
   ``lambda = min(1, |delta| / max)`` (Schied et al. 2018, eq. 7), 0 where nothing was lit.
5. **Temporal accumulation** (:meth:`ASVGF.temporal`): the history is reprojected with the motion vectors
   (bilinear taps, each kept only if its depth is within ``depth_tolerance`` depth-derivatives of the expected
   one and its normal within 60 degrees, q2vkpt / Q2RTX); ``hist_len = min(hist_len + 1, history_cap)``,
   ``alpha = max(alpha_min, 1 / hist_len)`` mixed toward 1 by the largest ``lambda`` of the 3x3 gradient cells
   around the pixel (the anti-lag of q2vkpt's ``get_antilag_alpha``). Colour and luminance moments are blended
   with their own minimum alphas.
6. **Moments / variance** (:meth:`ASVGF.variance`): luminance variance from the temporal moments; where the
   history is shorter than 4 frames from a 5x5 bilateral spatial estimate (q2vkpt's fallback); boosted by
   ``max(1, 4 / hist_len)`` (Falcor's SVGFFilterMoments).
7. **Spatial a-trous** (:meth:`ASVGF.atrous`): ``atrous_iterations`` (5) passes with steps 1, 2, 4, 8, 16 of a
   (2r+1)^2 kernel (r = ``atrous_radius``; q2vkpt's 3x3 with weights 1, 1/2, 1/4, or SVGF's 5x5 B3 kernel),
   edge-stopping on normal (``max(0, n.n')^phi_normal``), depth (``|dz| / (phi_depth * |grad z| * step *
   |offset|)``) and luminance relative to the filtered standard deviation (``|dl| / (phi_color * sqrt(g3x3(var)))``),
   the weights of SVGF (Schied et al. 2017) and Falcor's SVGFPass; the variance is filtered with the squared
   weights. ``feedback_tap`` = k >= 1 writes the output of pass k into the colour history (q2vkpt and SVGF use
   1); the default 0 keeps the history unfiltered, as the thesis requires ("it is important to not add
   filtered data to the accumulation buffer", §4.4).

What is filtered is demodulated illumination (radiance / albedo), and the result is multiplied by the albedo again
in the composition (§6.11), as q2vkpt does. The reprojection is a numba kernel parallel over image rows; the spatial
variance and the spatial a-trous are the suite's shared filters (:func:`suite.core.denoise.spatial_variance`,
:func:`suite.core.denoise.atrous`), and they and the rest are vectorised numpy. On a tracer with a Dr.Jit device
(Mitsuba llvm/cuda) stages 3-7 run as device kernels (the gradients, reprojection and accumulation of
:mod:`methods.quake_drt.device`, the filters of :mod:`suite.core.device.denoise`; the same values to rounding: the
gradient a-trous's float32 ``exp`` is Dr.Jit's, not numpy's) and the colour, moments and history length stay on
the device between frames; the frame's inputs go up once and the filtered colour comes back (counted copies,
``copied_bytes``). Stages 1-2 (the seeds and the forward projection, which reads the scene's triangles) stay on the
host; the work counters count one tap per
pixel and kernel tap and pass.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from methods.quake_drt.primary import barycentric_points
from methods.quake_drt.rng import tea_np
from suite.core import denoise
from suite.core.denoise import depth_fwidth, luminance, shifted

GRAD_DWN = 3


@dataclass
class ASVGFSettings:
    antilag: bool = True
    gradient_iterations: int = 5
    gradient_sigma: float = 4.0
    history_cap: int = 256
    alpha_color: float = 0.075
    alpha_moments: float = 0.1
    depth_tolerance: float = 2.0
    atrous_iterations: int = 5
    atrous_radius: int = 1
    phi_color: float = 10.0
    phi_normal: float = 128.0
    phi_depth: float = 1.0
    feedback_tap: int = 0


@dataclass
class Guides:
    """What the filters are guided by (pixel arrays (H, W, ...))."""

    valid: np.ndarray  # (H, W) bool
    point: np.ndarray  # (H, W, 3) float64 primary surface point (reprojection)
    depth: np.ndarray  # (H, W) primary distance (reprojection test)
    normal: np.ndarray  # (H, W, 3) primary normal (reprojection test)
    motion: np.ndarray  # (H, W, 2) previous position - current, pixels
    filter_depth: np.ndarray  # (H, W) distance along the path to the shaded surface (edge stopping)
    filter_normal: np.ndarray  # (H, W, 3) normal of the shaded surface (edge stopping)
    camera: np.ndarray  # (3,) camera position


@dataclass
class GradientSamples:
    cur: np.ndarray  # (M,) current pixel (row-major)
    prev: np.ndarray  # (M,) previous pixel it comes from
    prim: np.ndarray  # (M,) previous shading sample
    u: np.ndarray
    v: np.ndarray
    dist: np.ndarray  # (M,) distance of the moved point from the current camera

    def __len__(self) -> int:
        return int(len(self.cur))

    def subset(self, keep) -> "GradientSamples":
        return GradientSamples(*(getattr(self, f)[keep] for f in ("cur", "prev", "prim", "u", "v", "dist")))


# --- compiled per-pixel pass (numba, parallel over rows) ---------------------------------------------------------

@numba.njit(cache=True, nogil=True, parallel=True)
def _reproject(motion, valid, point, cam_prev, tol, p_valid, p_depth, p_normal, normal, p_color, p_moments, p_hist,
               out_c, out_m, out_h, out_ok):
    """Bilinear fetch of the previous frame's history at each pixel's reprojected position, keeping only taps
    whose depth and normal are consistent (stage 5)."""
    h, w = valid.shape
    for y in numba.prange(h):
        for x in range(w):
            out_ok[y, x] = False
            if not valid[y, x]:
                continue
            px = x + 0.5 + motion[y, x, 0] - 0.5
            py = y + 0.5 + motion[y, x, 1] - 0.5
            lx, ly = np.floor(px), np.floor(py)
            fx, fy = px - lx, py - ly
            ex = point[y, x, 0] - cam_prev[0]
            ey = point[y, x, 1] - cam_prev[1]
            ez = point[y, x, 2] - cam_prev[2]
            expect = np.sqrt(ex * ex + ey * ey + ez * ez)
            c0 = c1 = c2 = m0 = m1 = hs = ws = 0.0
            for k in range(4):
                ox, oy = k % 2, k // 2
                wt = (fx if ox else 1.0 - fx) * (fy if oy else 1.0 - fy)
                tx, ty = int(lx) + ox, int(ly) + oy
                if tx < 0 or tx >= w or ty < 0 or ty >= h or not p_valid[ty, tx]:
                    continue
                if abs(p_depth[ty, tx] - expect) > tol[y, x]:
                    continue
                dot = (p_normal[ty, tx, 0] * normal[y, x, 0] + p_normal[ty, tx, 1] * normal[y, x, 1]
                       + p_normal[ty, tx, 2] * normal[y, x, 2])
                if dot <= 0.5:
                    continue
                c0 += p_color[ty, tx, 0] * wt
                c1 += p_color[ty, tx, 1] * wt
                c2 += p_color[ty, tx, 2] * wt
                m0 += p_moments[ty, tx, 0] * wt
                m1 += p_moments[ty, tx, 1] * wt
                hs += p_hist[ty, tx] * wt
                ws += wt
            if ws > 1e-3:
                out_ok[y, x] = True
                out_c[y, x, 0], out_c[y, x, 1], out_c[y, x, 2] = c0 / ws, c1 / ws, c2 / ws
                out_m[y, x, 0], out_m[y, x, 1] = m0 / ws, m1 / ws
                out_h[y, x] = hs / ws


class ASVGF:
    """The denoiser's state between frames and its stages (module docstring)."""

    def __init__(self, settings: ASVGFSettings, width: int, height: int):
        self.s = settings
        self.w, self.h = int(width), int(height)
        self.cw, self.ch = -(-self.w // GRAD_DWN), -(-self.h // GRAD_DWN)
        self.reset()

    def reset(self) -> None:
        self.frame = 0
        self.prev = None  # dict of the previous frame's buffers
        self.device = None  # a suite.core.device.Device: stages 5-7 run there (set per frame by the pipeline)
        # (Guides, dict): the frame's guides on the device, uploaded on first use: "filter" (a DeviceFrame of the
        # edge-stopping guides) and "reprojection" (methods.quake_drt.device.upload_reprojection_guides)
        self._frame = None
        self._frame_colour = None  # (illum, dict, host luminance): the frame's colour and luminance on the device
        self.prev_dev = None  # the history on the device (colour, moments, length, guides) after a device frame
        self.copied_bytes = 0  # bytes stages 5-7 copied between host and device memory (device path)

    def _frame_on_device(self, guides: Guides) -> dict:
        """The frame's guides on the device so far (a new frame's guides start empty)."""
        if self._frame is None or self._frame[0] is not guides:
            self._frame = (guides, {})
        return self._frame[1]

    def _device_frame(self, guides: Guides):
        """The filter guides on the device (uploaded on the frame's first use, a counted copy)."""
        from suite.core.device.denoise import DeviceFrame

        frame = self._frame_on_device(guides)
        if "filter" not in frame:
            frame["filter"] = DeviceFrame.from_host(self.device, guides.filter_depth, guides.filter_normal,
                                                    guides.valid)
        return frame["filter"]

    def counted_copies(self, fn):
        """Runs ``fn`` and adds what it copied between host and device memory to :attr:`copied_bytes` (the
        denoiser's stages and the pipeline's TAA on a device)."""
        before = self.device.copied_bytes
        out = fn()
        self.copied_bytes += self.device.copied_bytes - before
        return out

    # -- 2. forward projection ---------------------------------------------------------------------------

    def forward_project(self, scene, t_s: float) -> GradientSamples:
        """Gradient samples for this frame (before tracing)."""
        from suite.core.gbuffer import project

        empty = GradientSamples(*(np.zeros(0, np.int64),) * 3, np.zeros(0), np.zeros(0), np.zeros(0))
        if self.prev is None:
            return empty
        w, h = self.w, self.h
        gx, gy = np.meshgrid(np.arange(self.cw), np.arange(self.ch))
        gx, gy = gx.reshape(-1), gy.reshape(-1)
        a, b = tea_np((gx + gy * w).astype(np.uint32), np.uint32(self.frame & 0xFFFFFFFF))
        px = gx * GRAD_DWN + (a % GRAD_DWN).astype(np.int64)
        py = gy * GRAD_DWN + (b % GRAD_DWN).astype(np.int64)
        inside = (px < w) & (py < h)
        prev_pix = (py * w + px)[inside]
        prev_pix = prev_pix[self.prev["sample_valid"][prev_pix]]
        if len(prev_pix) == 0:
            return empty
        prim = self.prev["prim"][prev_pix]
        u, v = self.prev["u"][prev_pix], self.prev["v"][prev_pix]
        pts = barycentric_points(scene.positions_at(t_s)[scene.faces[prim]].astype(np.float64), u, v)
        pose = scene.camera.pose_at(t_s)
        xy, z = project(pts, pose, scene.camera.fov_deg, w, h)
        ok = (z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
        ix = np.floor(xy[:, 0]).astype(np.int64)
        iy = np.floor(xy[:, 1]).astype(np.int64)
        cur = iy * w + ix
        cell = (iy // GRAD_DWN) * self.cw + ix // GRAD_DWN
        idx = np.nonzero(ok)[0]
        # One sample per cell: the first (in stratum order) wins, like q2vkpt's atomic compare-and-swap.
        _, first = np.unique(cell[idx], return_index=True)
        keep = idx[first]
        dist = np.linalg.norm(pts[keep] - np.asarray(pose.position, np.float64), axis=1)
        return GradientSamples(cur[keep], prev_pix[keep], prim[keep], u[keep], v[keep], dist)

    def seeds_with_gradients(self, seeds: np.ndarray, fwd: GradientSamples) -> np.ndarray:
        """The frame's seeds with each gradient sample's pixel given the previous frame's seed."""
        seeds = np.asarray(seeds, np.uint32).reshape(-1).copy()
        if len(fwd):
            seeds[fwd.cur] = self.prev["seeds"][fwd.prev]
        return seeds

    @staticmethod
    def visible(fwd: GradientSamples, g) -> np.ndarray:
        """(M,) bool: the moved point is what the current G-buffer sees at its pixel (not hidden, not off)."""
        if len(fwd) == 0:
            return np.zeros(0, bool)
        depth = g.depth.reshape(-1)[fwd.cur].astype(np.float64)
        valid = g.valid.reshape(-1)[fwd.cur]
        return valid & (np.abs(depth - fwd.dist) <= 0.01 * depth + 1e-3)

    # -- 3. gradient image ----------------------------------------------------------------------------------

    def gradient(self, illum: np.ndarray, fwd: GradientSamples, st=None) -> np.ndarray:
        """(ch, cw, 4): delta, max, cell luminance mean and standard deviation (one tap per pixel); on a device the
        four as Float arrays of the cell grid."""
        w, h, cw, ch = self.w, self.h, self.cw, self.ch
        if self.device is not None:
            from methods.quake_drt import device as qd

            has = fwd is not None and len(fwd) and self.prev is not None
            out = self.counted_copies(lambda: qd.gradient(
                self.device, w, h, self._device_colour(illum)["lum"], fwd.cur if has else np.zeros(0, np.int64),
                self.prev["lum"][fwd.prev] if has else np.zeros(0, np.float32)))
            if st is not None:
                st.count(taps=w * h)
            return out
        lum = luminance(illum.reshape(h, w, 3))
        pad = np.zeros((ch * GRAD_DWN, cw * GRAD_DWN), np.float32)
        pad[:h, :w] = lum
        blocks = pad.reshape(ch, GRAD_DWN, cw, GRAD_DWN)
        mean = blocks.mean(axis=(1, 3))
        std = np.sqrt(np.maximum((blocks * blocks).mean(axis=(1, 3)) - mean * mean, 0.0))
        out = np.zeros((ch, cw, 4), np.float32)
        out[..., 2], out[..., 3] = mean, std
        if len(fwd) and self.prev is not None:
            l_cur = lum.reshape(-1)[fwd.cur]
            l_prev = self.prev["lum"][fwd.prev]
            cy, cx = (fwd.cur // w) // GRAD_DWN, (fwd.cur % w) // GRAD_DWN
            out[cy, cx, 0] = l_cur - l_prev
            out[cy, cx, 1] = np.maximum(l_cur, l_prev)
        if st is not None:
            st.count(taps=w * h)
        return out

    # -- 4. gradient a-trous ----------------------------------------------------------------------------------

    def gradient_atrous(self, grad: np.ndarray, st=None) -> np.ndarray:
        """(ch, cw) lambda in [0, 1]: how much of the history is invalid (a Float of the cell grid on a device)."""
        if self.device is not None:
            from methods.quake_drt import device as qd

            if isinstance(grad, np.ndarray):  # benchmarks hand in the host's gradient image
                grad = tuple(self.device.to_device(np.ascontiguousarray(grad[..., k]).reshape(-1), self.device.Float)
                             for k in range(4))
            lam = qd.gradient_atrous(self.device, grad, self.w, self.h, self.s)
            if st is not None:
                st.count(taps=self.cw * self.ch * 9 * 2 * self.s.gradient_iterations)
            return lam
        val = grad[..., :2].copy()
        var = (grad[..., 3] ** 2).astype(np.float32)
        lum = np.minimum(grad[..., 2], 8.0)  # the thesis code's min(lum, 8)
        for it in range(self.s.gradient_iterations):
            step = 1 << it
            # sigma from the 3x3 neighbourhood of the cell's luminance variance
            # (twice the 3x3 Gaussian, as the thesis code's weights 1/2, 1/4, 1/8 sum to 2)
            sig = 2.0 * denoise.gaussian3x3(var, np.float32)
            sig = np.maximum(self.s.gradient_sigma * sig, 1e-8)
            acc, wsum, vacc = val.copy(), np.ones_like(lum), var.copy()
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if dx == 0 and dy == 0:
                        continue
                    inside = shifted(np.ones_like(lum), dy * step, dx * step)
                    lq = shifted(lum, dy * step, dx * step)
                    wq = inside * np.exp(-((lum - lq) ** 2) / sig)
                    acc += shifted(val, dy * step, dx * step) * wq[..., None]
                    vacc += shifted(var, dy * step, dx * step) * wq * wq
                    wsum += wq
            val = acc / wsum[..., None]
            var = vacc / (wsum * wsum)
        if st is not None:
            st.count(taps=int(lum.size) * 9 * 2 * self.s.gradient_iterations)
        delta, mx = np.abs(val[..., 0]), val[..., 1]
        return np.where(mx > 1e-6, np.minimum(delta / np.maximum(mx, 1e-12), 1.0), 0.0).astype(np.float32)

    def antilag(self, lam: np.ndarray) -> np.ndarray:
        """(H, W): the largest lambda of the 3x3 gradient cells around each pixel's cell (a Float on a device)."""
        if self.device is not None and not isinstance(lam, np.ndarray):
            from methods.quake_drt import device as qd

            return qd.antilag(self.device, lam, self.w, self.h)
        m = lam.copy()
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                m = np.maximum(m, shifted(lam, dy, dx))
        full = np.repeat(np.repeat(m, GRAD_DWN, axis=0), GRAD_DWN, axis=1)
        return full[:self.h, :self.w]

    # -- 5. temporal accumulation ----------------------------------------------------------------------------

    def temporal(self, illum: np.ndarray, guides: Guides, alpha_lag: np.ndarray | None, st=None):
        """(colour, moments, hist_len, reprojected) after accumulating ``illum`` (H, W, 3) into the history. On a
        device (:attr:`device`) the four are Dr.Jit arrays that stay there (moments as two Float)."""
        h, w = self.h, self.w
        if self.device is not None:
            out = self.counted_copies(lambda: self._temporal_device(illum, guides, alpha_lag))
            if st is not None:
                st.count(taps=h * w * 4)
            return out
        cur = illum.reshape(h, w, 3).astype(np.float32)
        lum = luminance(cur)
        mom_cur = np.stack([lum, lum * lum], axis=-1)
        valid = guides.valid
        color = cur.copy()
        moments = mom_cur.copy()
        hist = np.where(valid, 1.0, 0.0).astype(np.float32)
        reprojected = np.zeros((h, w), bool)
        if self.prev is not None:
            p = self.prev
            tol = self.s.depth_tolerance * np.maximum(depth_fwidth(guides.depth, valid),
                                                      1e-3 * guides.depth.astype(np.float32))
            prev_c = np.zeros((h, w, 3), np.float32)
            prev_m = np.zeros((h, w, 2), np.float32)
            prev_h = np.zeros((h, w), np.float32)
            reprojected = np.zeros((h, w), bool)
            _reproject(np.ascontiguousarray(guides.motion, np.float32), valid,
                       np.ascontiguousarray(guides.point, np.float64), np.asarray(p["camera"], np.float64),
                       tol.astype(np.float32), p["valid"], p["depth"], p["normal"],
                       np.ascontiguousarray(guides.normal, np.float32), p["color"], p["moments"], p["hist"],
                       prev_c, prev_m, prev_h, reprojected)
            hist_r = np.minimum(prev_h + 1.0, float(self.s.history_cap))
            a_c = np.maximum(self.s.alpha_color, 1.0 / hist_r)
            a_m = np.maximum(self.s.alpha_moments, 1.0 / hist_r)
            if alpha_lag is not None and self.s.antilag:
                a_c = a_c + (1.0 - a_c) * alpha_lag
                a_m = a_m + (1.0 - a_m) * alpha_lag
            color = np.where(reprojected[..., None], prev_c + (cur - prev_c) * a_c[..., None], cur)
            moments = np.where(reprojected[..., None], prev_m + (mom_cur - prev_m) * a_m[..., None], mom_cur)
            hist = np.where(reprojected, hist_r, hist)
        if st is not None:
            st.count(taps=h * w * 4)
        return color.astype(np.float32), moments.astype(np.float32), hist.astype(np.float32), reprojected

    # -- 6. variance -------------------------------------------------------------------------------------------

    def variance(self, illum: np.ndarray, moments: np.ndarray, hist: np.ndarray, guides: Guides, st=None):
        """(H, W) luminance variance (module docstring, stage 6); a device Float on a device."""
        if self.device is not None:
            var, short = self.counted_copies(lambda: self._variance_device(illum, moments, hist, guides))
            if short and st is not None:
                st.count(taps=self.h * self.w * 25)
            return var
        var_t = np.maximum(moments[..., 1] - moments[..., 0] ** 2, 0.0)
        short = hist < 4.0
        var = var_t
        if short.any():
            lum = luminance(illum.reshape(self.h, self.w, 3))
            var_s = denoise.spatial_variance(lum, guides.filter_depth, guides.filter_normal, guides.valid,
                                             float(self.s.phi_normal), active=short)  # only where it is taken
            var = np.where(short, var_s, var_t)
            if st is not None:
                st.count(taps=self.h * self.w * 25)
        return (var * np.maximum(1.0, 4.0 / np.maximum(hist, 1.0))).astype(np.float32)

    # -- 7. spatial a-trous ------------------------------------------------------------------------------------

    def atrous(self, color: np.ndarray, var: np.ndarray, guides: Guides, st=None):
        """(filtered colour, colour to store as history or None) after the a-trous passes
        (:func:`suite.core.denoise.atrous` on the filter guides)."""
        s = self.s
        settings = denoise.AtrousSettings(s.atrous_iterations, int(s.atrous_radius), float(s.phi_color),
                                          float(s.phi_normal), float(s.phi_depth))
        if self.device is not None:
            c, history = self.counted_copies(lambda: self._atrous_device(color, var, guides, settings))
        else:
            c, _, history = denoise.atrous(color, var, guides.filter_depth, guides.filter_normal, guides.valid,
                                           settings, s.feedback_tap)
        if st is not None:
            st.count(taps=denoise.atrous_taps(self.w, self.h, settings))
        return c, history

    # -- the device path (stages 5-7 as Dr.Jit kernels; methods/quake_drt/device.py, suite.core.device.denoise) ----

    def _device_colour(self, illum) -> dict:
        """The frame's colour and luminance on the device (uploaded once per frame)."""
        if self._frame_colour is None or self._frame_colour[0] is not illum:
            dev = self.device
            cur = np.asarray(illum, np.float32).reshape(self.h, self.w, 3)
            lum = luminance(cur)  # numpy's rounding of the product (a matrix product on the host)
            self._frame_colour = (illum, {"rgb": dev.to_device(cur.reshape(-1, 3), dev.Vector3f),
                                          "lum": dev.to_device(lum.reshape(-1), dev.Float)}, lum)
        return self._frame_colour[1]

    def _device_inputs(self, illum, guides: Guides) -> dict:
        """The frame's reprojection guides, colour and luminance on the device (uploaded once per frame)."""
        from methods.quake_drt import device as qd

        frame = self._frame_on_device(guides)
        if "reprojection" not in frame:
            frame["reprojection"] = qd.upload_reprojection_guides(self.device, guides)
        return {**frame["reprojection"], **self._device_colour(illum)}

    def _previous_on_device(self) -> dict | None:
        """The history as the device kernels read it (uploaded from the host when the last frame ran there)."""
        if self.prev is None:
            return None
        if self.prev_dev is None:
            dev, p = self.device, self.prev
            up = lambda a, t: dev.to_device(np.ascontiguousarray(a).reshape((-1, 3) if a.ndim == 3 else -1), t)  # noqa
            self.prev_dev = {"valid": up(p["valid"], dev.Bool), "depth": up(p["depth"], dev.Float),
                             "normal": up(p["normal"], dev.Vector3f), "color": up(p["color"], dev.Vector3f),
                             "moments": (up(p["moments"][..., 0], dev.Float), up(p["moments"][..., 1], dev.Float)),
                             "hist": up(p["hist"], dev.Float)}
        return self.prev_dev

    def _temporal_device(self, illum, guides: Guides, alpha_lag):
        from types import SimpleNamespace

        from methods.quake_drt import device as qd
        from suite.core.device import denoise as dden

        dev, w, h = self.device, self.w, self.h
        dr, F = dev.dr, dev.Float
        cur = self._device_inputs(illum, guides)
        prev = self._previous_on_device()
        tol = None
        if prev is not None:
            fw = dden.depth_fwidth(SimpleNamespace(device=dev, width=w, height=h, depth=cur["depth"],
                                                   valid=cur["valid"]))
            tol = F(float(self.s.depth_tolerance)) * dr.maximum(fw, F(1e-3) * cur["depth"])
        lag = alpha_lag
        if isinstance(alpha_lag, np.ndarray):
            lag = dev.to_device(np.asarray(alpha_lag, np.float32).reshape(-1), F)
        return qd.temporal(dev, w, h, cur["rgb"], cur["lum"], cur, prev,
                           self.prev["camera"] if self.prev is not None else None, tol, lag, self.s)

    def _on_device(self, a, components: int):
        """A stage input on the device: Dr.Jit arrays as they are, host arrays uploaded (benchmarks mix the two)."""
        if not isinstance(a, np.ndarray):
            return a
        dev = self.device
        a = np.asarray(a, np.float32)
        if components == 3:
            return dev.to_device(a.reshape(-1, 3), dev.Vector3f)
        if components == 2:
            return tuple(dev.to_device(np.ascontiguousarray(a[..., k]).reshape(-1), dev.Float) for k in range(2))
        return dev.to_device(a.reshape(-1), dev.Float)

    def _variance_device(self, illum, moments, hist, guides: Guides):
        """Stage 6 on the device: (variance Float, whether a pixel took the spatial estimate)."""
        from suite.core.device import denoise as dden

        dev = self.device
        dr, F = dev.dr, dev.Float
        m0, m1 = self._on_device(moments, 2)
        hist = self._on_device(hist, 1)
        var = dr.maximum(m1 - m0 * m0, 0.0)
        short = hist < 4.0
        any_short = bool(dr.any(short))
        if any_short:
            lum = self._device_inputs(illum, guides)["lum"]
            # the spatial estimate only where the history is short (in the packets that hold such a pixel)
            var = dr.select(short, dden.spatial_variance(self._device_frame(guides), lum, float(self.s.phi_normal),
                                                         active=short), var)
        var = var * dr.maximum(F(1.0), 4.0 / dr.maximum(hist, F(1.0)))
        dr.eval(var)
        return var, any_short

    def _atrous_device(self, color, var, guides: Guides, settings):
        """Stage 7 on the device: (filtered colour on the host, the colour to keep as history on the device or
        None)."""
        from suite.core.device import denoise as dden

        dev = self.device
        c, _, tapped = dden.atrous(self._device_frame(guides), self._on_device(color, 3), self._on_device(var, 1),
                                   settings, self.s.feedback_tap)
        return dev.to_host(c, np.float32).reshape(self.h, self.w, 3), tapped

    def stats(self, a, valid) -> tuple[float, float]:
        """(mean over the valid pixels, largest value) of a per-pixel stage output (host or device), e.g.
        :meth:`temporal`'s history length or :meth:`antilag`'s lambda."""
        if isinstance(a, np.ndarray):
            return (float(a[valid].mean()) if valid.any() else 0.0), (float(a.max()) if a.size else 0.0)
        dr = self.device.dr
        v = self._device_inputs_valid(valid)
        n = int(dr.count(v)[0])
        total = float(dr.sum(self.device.Float64(dr.select(v, a, 0.0)))[0])
        return (total / n if n else 0.0), float(dr.max(a)[0])

    def _device_inputs_valid(self, valid):
        if self._frame is not None and "reprojection" in self._frame[1]:
            return self._frame[1]["reprojection"]["valid"]
        return self.device.to_device(np.asarray(valid, bool).reshape(-1), self.device.Bool)

    # -- end of frame ------------------------------------------------------------------------------------------

    def end_frame(self, surface, seeds, illum, color, moments, hist, guides: Guides) -> None:
        """Keeps what the next frame needs: shading samples and seeds (forward projection), raw luminance
        (gradients), history colour, moments and length, and the reprojection guides; after a device frame the
        last four stay on the device."""
        h, w = self.h, self.w
        on_device = not isinstance(color, np.ndarray)
        lum = self._frame_colour[2] if on_device and self._frame_colour[0] is illum else \
            luminance(illum.reshape(h, w, 3))
        self.prev = {"sample_valid": surface.valid.copy(), "prim": surface.prim.copy(), "u": surface.u.copy(),
                     "v": surface.v.copy(), "seeds": np.asarray(seeds, np.uint32).reshape(-1).copy(),
                     "lum": lum.reshape(-1), "camera": np.asarray(guides.camera, np.float64)}
        if on_device:
            cur = self._frame[1]["reprojection"]
            self.prev_dev = {"valid": cur["valid"], "depth": cur["depth"], "normal": cur["normal"], "color": color,
                             "moments": moments, "hist": hist}
        else:
            self.prev_dev = None
            self.prev.update(color=color.astype(np.float32), moments=moments.astype(np.float32),
                             hist=hist.astype(np.float32), depth=guides.depth.astype(np.float32),
                             normal=guides.normal.astype(np.float32), valid=guides.valid.copy())
        self.frame += 1
