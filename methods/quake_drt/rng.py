"""Per-pixel random numbers: the A-SVGF "RNG" stage (seed 001 Table 6.9, first row).

Every random decision of a frame (anti-aliasing jitter, lens sample, glass branch, light choice, point on an
area light) is a pure function of one 32-bit seed per pixel and a *dimension* number, through the PCG hash of
Jarzynski and Olano ("Hash Functions for GPU Rendering", JCGT 2020). That is what makes A-SVGF's gradient
samples possible (Schied et al. 2018, §4; seed 001 Table 6.10 "RNG"): a pixel of the current frame that
re-shades a surface sample of the previous frame with the previous frame's seed repeats its random choices
exactly, so the difference between the two shadings is temporal change, not noise.

The hash is the suite's (:func:`suite.core.rng.pcg_np` for numpy arrays, :func:`suite.core.device.rng.pcg` in
Dr.Jit kernels), written once more in :mod:`.direct` for its numba kernel (kept in that file so that numba's on-disk
cache, which watches only the kernel's own file, sees a change). All give the same bits
(tests/methods/quake_drt/test_rng.py, tests/core/test_rng.py).
"""
from __future__ import annotations

import numpy as np

from suite.core.rng import pcg_np  # the PCG hash of uint32 values (numpy, vectorised)

# Dimension numbers of the decisions of one camera path (per pixel seed).
DIM_JITTER_X, DIM_JITTER_Y = 0, 1          # anti-aliasing: position inside the pixel
DIM_LENS_U, DIM_LENS_V = 2, 3              # depth of field: point on the lens
DIM_SECONDARY = 4                          # + 3 * depth: glass branch, glossy direction (2)
DIM_LIGHTS = 64                            # + 4 * sample: light choice, triangle choice, point (2)

_INV_2_24 = 1.0 / 16777216.0


def uniform_np(seed: np.ndarray, dim) -> np.ndarray:
    """Floats in [0, 1) for (seed, dimension) pairs: 24 random bits, so ``u * n < n`` holds exactly."""
    with np.errstate(over="ignore"):
        h = pcg_np(np.asarray(seed, np.uint32) ^ pcg_np(np.asarray(dim, np.uint32) + np.uint32(0x9E3779B9)))
    return (h >> np.uint32(8)).astype(np.float64) * _INV_2_24


def stream_np(seed: np.ndarray, stream) -> np.ndarray:
    """A derived seed (e.g. one per glass branch of a pixel), decorrelated from the parent seed."""
    with np.errstate(over="ignore"):
        return pcg_np(np.asarray(seed, np.uint32) ^ (np.asarray(stream, np.uint32) * np.uint32(0x85EBCA6B)))


def pixel_seeds(frame_seed: int, width: int, height: int) -> np.ndarray:
    """(H, W) uint32: the RNG stage's seed of every pixel for one frame (a new frame seed gives new seeds)."""
    lo = np.uint32(int(frame_seed) & 0xFFFFFFFF)
    hi = np.uint32((int(frame_seed) >> 32) & 0xFFFFFFFF)
    # A 32-bit key per frame, XORed onto hashed pixel indices: every frame draws a fresh set of seeds (XOR of
    # the raw index with the frame seed would only permute one small set of seeds between frames).
    key = pcg_np(pcg_np(lo) ^ pcg_np(hi + np.uint32(0x68E31DA4)))
    idx = np.arange(width * height, dtype=np.uint32)
    return pcg_np(pcg_np(idx) ^ key).reshape(height, width)


def tea_np(v0: np.ndarray, v1) -> tuple[np.ndarray, np.ndarray]:
    """Tiny Encryption Algorithm, 16 rounds, as q2vkpt's ``asvgf_fwd_project`` uses it to pick the pixel of
    each 3x3 stratum that becomes a gradient sample. Returns both words."""
    key = (np.uint32(0xA341316C), np.uint32(0xC8013EA4), np.uint32(0xAD90777D), np.uint32(0x7E95761E))
    a = np.asarray(v0, np.uint32).copy()
    b = np.broadcast_to(np.asarray(v1, np.uint32), a.shape).copy()
    s = np.uint32(0)
    delta = np.uint32(0x9E3779B9)
    with np.errstate(over="ignore"):
        for _ in range(16):
            s = np.uint32(s + delta)
            a = a + (((b << np.uint32(4)) + key[0]) ^ (b + s) ^ ((b >> np.uint32(5)) + key[1]))
            b = b + (((a << np.uint32(4)) + key[2]) ^ (a + s) ^ ((a >> np.uint32(5)) + key[3]))
    return a, b
