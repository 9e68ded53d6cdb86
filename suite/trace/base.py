"""The tracing interface shared by all backends.

Every backend answers two queries on numpy arrays of float32 rays:

* ``intersect(origins, dirs, tmin, tmax) -> Hits``: closest hit (t, global face index, barycentrics u, v),
  with ``t = inf`` and ``prim = -1`` on a miss. Hit point = (1-u-v)·p0 + u·p1 + v·p2 of ``scene.faces[prim]``.
* ``occluded(origins, dirs, tmin, tmax) -> bool``: any hit with tmin < t < tmax (shadow rays).

``tmin`` and ``tmax`` may be scalars or per-ray arrays. Neither backend supports a per-ray ``tmin`` natively
(embreex fixes ``tnear`` at 0), so the origin is advanced by ``tmin`` along the ray and ``t`` is shifted back.
Robust shadow-ray origins are the caller's job (see :func:`suite.trace.robust.offset_ray_origin`).

Backends trace in a frame centred on the scene's bounding box: geometry and ray origins are shifted by the
box centre in float64 before they become float32. A scene far from the origin then gets the precision of a
scene at the origin inside the backend (hit distances, watertight edge tests); only its input coordinates
carry their own rounding.

Animated scenes: ``update(t_s)`` moves the scene's rigidly animated objects; backends keep static and moving
geometry apart so that an update rebuilds only what moved.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.errors import UserError


@dataclass
class Hits:
    t: np.ndarray  # (N,) float32, inf on miss
    prim: np.ndarray  # (N,) int32, -1 on miss
    u: np.ndarray  # (N,) float32
    v: np.ndarray  # (N,) float32

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


def as_rays(origins, dirs, tmin, tmax, shift=None):
    """Validates ray arrays, moves origins into the tracing frame (minus ``shift``) and applies ``tmin`` by
    advancing them. Returns (o, d, tmin, length) as float32."""
    o = np.asarray(origins).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, np.float32).reshape(-1, 3)
    if o.shape != d.shape:
        raise UserError(f"ray origins {o.shape} and directions {d.shape} differ in shape")
    n = len(o)
    tmin_a = np.broadcast_to(np.asarray(tmin, np.float32), (n,))
    tmax_a = np.broadcast_to(np.asarray(tmax, np.float32), (n,))
    if shift is not None:
        o = o.astype(np.float64) - shift
    if np.any(tmin_a > 0):
        o = o.astype(np.float64) + d * tmin_a[:, None].astype(np.float64)
    o = np.ascontiguousarray(o, np.float32)
    length = np.ascontiguousarray(np.maximum(tmax_a - tmin_a, 0.0), np.float32)
    return o, d, tmin_a, length


class Tracer:
    """Base class: counters and the shared ray-argument handling."""

    name = "base"

    def __init__(self, scene):
        self.scene = scene
        self.counters = {"rays_intersect": 0, "rays_occluded": 0}
        self._time_s = 0.0
        lo, hi = scene.bounds()
        self.shift = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))

    def local_positions(self, positions: np.ndarray) -> np.ndarray:
        """Vertex positions in the tracing frame (float32)."""
        return (positions.astype(np.float64) - self.shift).astype(np.float32)

    # subclasses implement _intersect(o, d, length) -> (t, prim, u, v) and _occluded(o, d, length) -> bool
    def intersect(self, origins, dirs, tmin=0.0, tmax=np.inf) -> Hits:
        o, d, tmin_a, length = as_rays(origins, dirs, tmin, tmax, self.shift)
        self.counters["rays_intersect"] += len(o)
        if len(o) == 0:
            z = np.zeros(0, np.float32)
            return Hits(z, np.zeros(0, np.int32), z, z)
        t, prim, u, v = self._intersect(o, d, length)
        miss = prim < 0
        t = np.where(miss, np.float32(np.inf), t + tmin_a).astype(np.float32)
        return Hits(t, prim.astype(np.int32), np.where(miss, 0, u).astype(np.float32),
                    np.where(miss, 0, v).astype(np.float32))

    def occluded(self, origins, dirs, tmin=0.0, tmax=np.inf) -> np.ndarray:
        o, d, _, length = as_rays(origins, dirs, tmin, tmax, self.shift)
        self.counters["rays_occluded"] += len(o)
        if len(o) == 0:
            return np.zeros(0, bool)
        return self._occluded(o, d, length)

    def update(self, t_s: float) -> None:
        """Moves animated objects to their pose at ``t_s`` (no-op for static scenes)."""
        if not self.scene.object_animations or t_s == self._time_s:
            self._time_s = t_s
            return
        self._update(t_s)
        self._time_s = t_s

    def reset_counters(self) -> None:
        for k in self.counters:
            self.counters[k] = 0

    def describe(self) -> dict:
        return {"backend": self.name}

    def _update(self, t_s: float) -> None:
        raise NotImplementedError


def split_static_dynamic(scene):
    """Face indices of static geometry and of rigidly animated objects."""
    moving = np.array(sorted({a.object_id for a in scene.object_animations}), np.int32)
    is_dynamic = np.isin(scene.face_object, moving)
    return np.nonzero(~is_dynamic)[0].astype(np.int32), np.nonzero(is_dynamic)[0].astype(np.int32)
