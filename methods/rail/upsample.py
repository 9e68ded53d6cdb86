"""Joint bilateral upsampling of a reduced-resolution irradiance channel (seed 004 §3.3, after Kopf et al. [23]
and McGuire and Luebke [30]): weights from 2D bilinear interpolation, normals and depth differences between
the low- and full-resolution G-buffers."""
from __future__ import annotations

import numpy as np

NORMAL_POWER = 8.0        # max(0, n · n_lo)^8
DEPTH_SIGMA_REL = 0.1     # exp(−|z − z_lo| / (0.1 z))


def joint_bilateral_upsample(lo_img, lo_valid, lo_normal, lo_depth, normal, depth, valid, scale: int) -> np.ndarray:
    """(H, W, 3): low-resolution samples taken at full-resolution pixels (i·scale, j·scale), upsampled.

    A pixel whose four low-resolution neighbours all get zero weight (a different surface everywhere) takes the
    plain bilinear value of the valid neighbours."""
    h, w = depth.shape
    hl, wl = lo_depth.shape
    y = np.arange(h) / scale
    x = np.arange(w) / scale
    y0 = np.minimum(np.floor(y).astype(np.int64), hl - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), wl - 1)
    fy = (y - y0)[:, None]
    fx = (x - x0)[None, :]
    num = np.zeros((h, w, 3))
    den = np.zeros((h, w))
    num_b = np.zeros((h, w, 3))
    den_b = np.zeros((h, w))
    z = np.where(valid, depth, 0.0)
    for dy in (0, 1):
        for dx in (0, 1):
            yy = np.minimum(y0 + dy, hl - 1)[:, None]
            xx = np.minimum(x0 + dx, wl - 1)[None, :]
            bil = (fy if dy else 1.0 - fy) * (fx if dx else 1.0 - fx)
            ok = lo_valid[yy, xx] & valid
            cos = np.maximum(0.0, (normal * lo_normal[yy, xx]).sum(axis=-1)) ** NORMAL_POWER
            zl = np.where(lo_valid[yy, xx], lo_depth[yy, xx], 0.0)
            dz = np.exp(-np.abs(z - zl) / np.maximum(DEPTH_SIGMA_REL * z, 1e-6))
            wgt = bil * ok * cos * dz
            val = lo_img[yy, xx]
            num += wgt[..., None] * val
            den += wgt
            wb = bil * ok
            num_b += wb[..., None] * val
            den_b += wb
    out = np.where(den[..., None] > 0, num / np.maximum(den, 1e-300)[..., None],
                   np.where(den_b[..., None] > 0, num_b / np.maximum(den_b, 1e-300)[..., None], 0.0))
    return (out * valid[..., None]).astype(np.float32)
