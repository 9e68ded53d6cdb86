"""Counter-based random numbers in Dr.Jit kernels: the device twins of :mod:`suite.core.rng`'s PCG hash, the same
bits on every variant (integer operations only)."""
from __future__ import annotations


def pcg(dev, v):
    """The PCG hash of UInt32 lanes (:func:`suite.core.rng.pcg`; wrapping products)."""
    state = v * 747796405 + 2891336453
    word = ((state >> ((state >> 28) + 4)) ^ state) * 277803737
    return (word >> 22) ^ word


def lane_keys(dev, keys, seed_hash):
    """``pcg(key ^ seed_hash)`` per lane: the lane half of :func:`uniform` (``seed_hash``: ``pcg(seed)``, UInt32)."""
    return pcg(dev, dev.UInt32(keys) ^ seed_hash)


def uniform(dev, lane_key, dim_hash):
    """Float64 in [0, 1) with 24 random bits (:func:`suite.core.rng.hashed_uniforms`): ``lane_key`` from
    :func:`lane_keys`, ``dim_hash`` the dimension's ``suite.core.rng.dim_hashes`` (UInt32)."""
    return dev.Float64(pcg(dev, lane_key ^ dim_hash) >> 8) * (1.0 / 16777216.0)

