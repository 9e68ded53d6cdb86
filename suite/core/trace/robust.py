"""Robust secondary-ray origins.

Shadow rays that start exactly on a surface re-hit it because of rounding ("shadow acne"). A fixed epsilon
fails both near the origin (too large: light leaks through corners) and far from it (too small: acne). In the
spirit of Wächter and Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray Tracing Gems,
ch. 6), the offset is a number of float32 ULPs of the point's coordinates, so it scales with their magnitude,
and an absolute floor takes over near the origin where ULPs vanish.

Differences from the chapter, because our inputs are more precise than its ``o + t d`` hit points:

* G-buffer positions are float64 intersections of the primary ray with the hit triangle's plane, so they lie
  on the float32 triangle up to float64 rounding.
* Tracers work in a frame centred on the scene (``Tracer.shift``); the float64 origin is rounded to float32
  only there, relative to that frame. The ULPs that matter are those of the coordinates *in that frame*.
* So a small offset suffices: ``OFFSET_ULPS`` ULPs of the largest tracing-frame coordinate, along the full
  normal. The chapter's 256 ULPs per coordinate would be 0.25 m at 1e4 units and visibly shift contact
  shadows.
"""
from __future__ import annotations

import numpy as np

# Offset in ULPs of the largest coordinate in the tracing frame: covers the float32 rounding of the origin
# (<= 0.87 ULP along any normal) plus the backends' intersection error, with margin.
OFFSET_ULPS = 4.0
# Floor near the origin: 1/65536 of the chapter's "origin" scale (Ray Tracing Gems ch. 6, listing 6-1).
FLOAT_SCALE = 1.0 / 65536.0 / 32.0


def offset_ray_origin(p: np.ndarray, n: np.ndarray, frame_shift=None) -> np.ndarray:
    """Moves points ``p`` along unit normals ``n`` (the side to leave from). Returns float64 (..., 3).

    ``frame_shift`` is the tracer's frame origin (``Tracer.shift``); the offset is sized for the coordinates
    relative to it, where the tracer rounds the origin to float32.
    """
    p64 = np.asarray(p, np.float64)
    n64 = np.asarray(n, np.float64)
    local = p64 - np.asarray(frame_shift, np.float64) if frame_shift is not None else p64
    magnitude = np.abs(local).max(axis=-1, keepdims=True).astype(np.float32)
    step = np.maximum(OFFSET_ULPS * np.spacing(magnitude).astype(np.float64), FLOAT_SCALE)
    return p64 + step * n64
