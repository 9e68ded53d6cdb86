"""Counter-based random numbers on the host, the twins of Mitsuba's: the Tiny Encryption Algorithm
(:func:`tea_u32`, :func:`tea_float32`; Zafar, Olano and Curtis, "GPU random numbers via the Tiny Encryption Algorithm",
HPG 2010) and Kensler's hash permutation (:func:`permute_kensler`; Kensler, "Correlated Multi-Jittered Sampling", Pixar
technical memo 13-01, 2013).

The device estimators draw their numbers with ``mi.sample_tea_32``, ``mi.sample_tea_float32`` and
``mi.permute_kensler`` (:mod:`suite.core.device.shading`); a host estimator that draws the same numbers here takes the
same samples, so the Embree and Dr.Jit backends agree to rounding instead of within Monte Carlo noise. Every function
equals Mitsuba's bit for bit (tests/core/test_tea.py compares them on random inputs).
"""
from __future__ import annotations

import numba
import numpy as np

TEA_ROUNDS = 4  # Mitsuba's default


@numba.njit(inline="always")
def tea_pair(v0, v1):
    """TEA's 4-round encryption of (v0, v1): both words (uint32 wrapping arithmetic), ``mi.sample_tea_32``."""
    v0 = np.uint32(v0)
    v1 = np.uint32(v1)
    total = np.uint32(0)
    for _ in range(TEA_ROUNDS):
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
    """The first word of :func:`tea_pair` (``mi.sample_tea_32(v0, v1)[0]``)."""
    return tea_pair(v0, v1)[0]


@numba.njit(inline="always")
def tea_float32(v0, v1):
    """A float32 in [0, 1), ``mi.sample_tea_float32``: the 23 high bits of :func:`tea_pair`'s second word as the
    mantissa of a number in [1, 2), minus 1; that is those bits times 2**-23, exactly."""
    return np.float32(tea_pair(v0, v1)[1] >> np.uint32(9)) * np.float32(1.0 / 8388608.0)


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
def tea_arrays(v0, v1):
    """(:func:`tea_u32`, :func:`tea_float32`) of (N,) uint32 arrays, element by element (tests)."""
    words = np.empty(len(v0), np.uint32)
    floats = np.empty(len(v0), np.float32)
    for i in range(len(v0)):
        words[i] = tea_u32(v0[i], v1[i])
        floats[i] = tea_float32(v0[i], v1[i])
    return words, floats


@numba.njit(cache=True)
def permute_kensler_array(index, size, seed):
    """:func:`permute_kensler` of (N,) uint32 ``index`` and ``seed`` arrays and one ``size`` (tests)."""
    out = np.empty(len(index), np.uint32)
    for i in range(len(index)):
        out[i] = permute_kensler(index[i], size, seed[i])
    return out
