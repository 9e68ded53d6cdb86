"""Counter-based random numbers on the host, the twins of the device kernels': every number is a pure function of a
key (a pixel, a path) and a counter, so a host estimator that draws the same numbers takes the same samples as its
device twin, and the Embree and Dr.Jit backends agree to rounding instead of within Monte Carlo noise.

* The Tiny Encryption Algorithm (:func:`tea_u32`, :func:`tea_float32`; Zafar, Olano and Curtis, "GPU random numbers
  via the Tiny Encryption Algorithm", HPG 2010) and Kensler's hash permutation (:func:`permute_kensler`; Kensler,
  "Correlated Multi-Jittered Sampling", Pixar technical memo 13-01, 2013): Mitsuba's ``mi.sample_tea_32``,
  ``mi.sample_tea_float32`` and ``mi.permute_kensler``, which the device's area-light estimator draws with
  (:mod:`suite.core.device.shading`). Equal to Mitsuba's bit for bit (tests/core/test_rng.py).
* The PCG hash (:func:`pcg`; Jarzynski and Olano, "Hash Functions for GPU Rendering", JCGT 2020: two multiplies and
  a few shifts, about an eighth of the work of TEA's eight rounds; the paper's recommendation for its quality at its
  cost) and :func:`hashed_uniforms`, the numbers of a path tracer's lane:
  ``u = (pcg(pcg(key ^ pcg(seed)) ^ pcg(dim + 0x9E3779B9)) >> 8) / 2**24``. The device twins are
  :mod:`suite.core.device.rng`.
"""
from __future__ import annotations

import numba
import numpy as np

TEA_ROUNDS = 4  # Mitsuba's default


@numba.njit(inline="always")
def tea_pair(v0, v1, rounds):
    """TEA's ``rounds``-round encryption of (v0, v1): both words (uint32 wrapping arithmetic),
    ``mi.sample_tea_32(v0, v1, rounds)``."""
    v0 = np.uint32(v0)
    v1 = np.uint32(v1)
    total = np.uint32(0)
    for _ in range(rounds):
        total = np.uint32(total + np.uint32(0x9E3779B9))
        v0 = np.uint32(v0 + (np.uint32(np.uint32(v1 << np.uint32(4)) + np.uint32(0xA341316C))
                             ^ np.uint32(v1 + total)
                             ^ np.uint32(np.uint32(v1 >> np.uint32(5)) + np.uint32(0xC8013EA4))))
        v1 = np.uint32(v1 + (np.uint32(np.uint32(v0 << np.uint32(4)) + np.uint32(0xAD90777D))
                             ^ np.uint32(v0 + total)
                             ^ np.uint32(np.uint32(v0 >> np.uint32(5)) + np.uint32(0x7E95761E))))
    return v0, v1


@numba.njit(inline="always")
def tea_u32(v0, v1):
    """The first word of :func:`tea_pair` with 4 rounds (``mi.sample_tea_32(v0, v1)[0]``)."""
    return tea_pair(v0, v1, TEA_ROUNDS)[0]


@numba.njit(inline="always")
def tea_float32(v0, v1, rounds):
    """A float32 in [0, 1), ``mi.sample_tea_float32(v0, v1, rounds)``: the 23 high bits of :func:`tea_pair`'s second
    word as the mantissa of a number in [1, 2), minus 1; that is those bits times 2**-23, exactly."""
    return np.float32(tea_pair(v0, v1, rounds)[1] >> np.uint32(9)) * np.float32(1.0 / 8388608.0)


@numba.njit(inline="always")
def permute_kensler(index, size, seed):
    """Element ``index`` of the pseudo-random permutation of [0, ``size``) that ``seed`` selects (cycle-walking a
    hash over the next power of two)."""
    w = np.uint32(size - 1)
    w |= w >> np.uint32(1)
    w |= w >> np.uint32(2)
    w |= w >> np.uint32(4)
    w |= w >> np.uint32(8)
    w |= w >> np.uint32(16)
    p = np.uint32(seed)
    i = np.uint32(index)
    while True:
        i ^= p
        i = np.uint32(i * np.uint32(0xE170893D))
        i ^= p >> np.uint32(16)
        i ^= (i & w) >> np.uint32(4)
        i ^= p >> np.uint32(8)
        i = np.uint32(i * np.uint32(0x0929EB3F))
        i ^= p >> np.uint32(23)
        i ^= (i & w) >> np.uint32(1)
        i = np.uint32(i * np.uint32(np.uint32(1) | (p >> np.uint32(27))))
        i = np.uint32(i * np.uint32(0x6935FA69))
        i ^= (i & w) >> np.uint32(11)
        i = np.uint32(i * np.uint32(0x74DCB303))
        i ^= (i & w) >> np.uint32(2)
        i = np.uint32(i * np.uint32(0x9E501CC3))
        i ^= (i & w) >> np.uint32(2)
        i = np.uint32(i * np.uint32(0xC860A3DF))
        i &= w
        i ^= i >> np.uint32(5)
        if i < np.uint32(size):
            break
    return np.uint32(np.uint32(i + p) % np.uint32(size))


@numba.njit(cache=True)
def tea_arrays(v0, v1, rounds):
    """(:func:`tea_u32`, :func:`tea_float32` with ``rounds``) of (N,) uint32 arrays, element by element (tests)."""
    words = np.empty(len(v0), np.uint32)
    floats = np.empty(len(v0), np.float32)
    for i in range(len(v0)):
        words[i] = tea_u32(v0[i], v1[i])
        floats[i] = tea_float32(v0[i], v1[i], rounds)
    return words, floats


@numba.njit(cache=True)
def permute_kensler_array(index, size, seed):
    """:func:`permute_kensler` of (N,) uint32 ``index`` and ``seed`` arrays and one ``size`` (tests)."""
    out = np.empty(len(index), np.uint32)
    for i in range(len(index)):
        out[i] = permute_kensler(index[i], size, seed[i])
    return out


PCG_DIM_SALT = 0x9E3779B9  # added to a dimension before it is hashed (dimension 0 hashes like any other)


@numba.njit(inline="always")
def pcg(v):
    """The PCG hash of a uint32 (wrapping products)."""
    state = np.uint32(np.uint32(v) * np.uint32(747796405) + np.uint32(2891336453))
    word = np.uint32((np.uint32(state >> np.uint32(np.uint32(state >> np.uint32(28)) + np.uint32(4))) ^ state)
                     * np.uint32(277803737))
    return np.uint32(np.uint32(word >> np.uint32(22)) ^ word)


def pcg_np(v) -> np.ndarray:
    """:func:`pcg` of uint32 values (numpy, vectorised)."""
    v = np.asarray(v, np.uint32)
    with np.errstate(over="ignore"):
        state = v * np.uint32(747796405) + np.uint32(2891336453)
        word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)
    return (word >> np.uint32(22)) ^ word


def dim_hashes(dims) -> np.ndarray:
    """``pcg(dim + PCG_DIM_SALT)`` of each dimension (uint32): the per-draw half of :func:`hashed_uniforms`."""
    with np.errstate(over="ignore"):
        return pcg_np(np.asarray(dims, np.int64).astype(np.uint32) + np.uint32(PCG_DIM_SALT))


@numba.njit(cache=True, nogil=True)
def hashed_uniforms(keys, seed_hash, dim_hash):
    """(M, D) float64 in [0, 1) with 24 random bits: for key ``k`` (uint32) and dimension ``j``,
    ``(pcg(pcg(k ^ seed_hash) ^ dim_hash[j]) >> 8) * 2**-24``, where ``seed_hash = pcg(seed)`` and ``dim_hash`` is
    :func:`dim_hashes` of the dimensions."""
    out = np.empty((len(keys), len(dim_hash)), np.float64)
    sh = np.uint32(seed_hash)
    for i in range(len(keys)):
        lane = pcg(np.uint32(np.uint32(keys[i]) ^ sh))
        for j in range(len(dim_hash)):
            h = pcg(np.uint32(lane ^ np.uint32(dim_hash[j])))
            out[i, j] = np.float64(h >> np.uint32(8)) * (1.0 / 16777216.0)
    return out
