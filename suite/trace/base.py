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


# The largest ray length handed to a backend (Embree's float32 "far" must stay finite).
MAX_RAY_LENGTH = np.float32(1e37)


@dataclass
class Hits:
    t: np.ndarray  # (N,) float32, inf on miss
    prim: np.ndarray  # (N,) int32, -1 on miss
    u: np.ndarray  # (N,) float32
    v: np.ndarray  # (N,) float32

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


def as_rays(origins, dirs, tmin, tmax, shift=None, soa: bool = False):
    """Validates ray arrays, moves origins into the tracing frame (minus ``shift``) and applies ``tmin`` by
    advancing them. Returns (o, d, tmin, length) as float32; ``o`` is (3, N) with ``soa`` (the layout Dr.Jit
    takes without a copy), else (N, 3).

    The subtraction runs in the origins' own precision (float64 G-buffer points stay exact until they are
    small numbers in the tracing frame) and writes float32 directly, without temporaries: it is on the hot
    path of every query.
    """
    o_in = np.asarray(origins)
    o_in = o_in.reshape(-1, 3)
    d = np.ascontiguousarray(dirs, np.float32).reshape(-1, 3)
    if o_in.shape != d.shape:
        raise UserError(f"ray origins {o_in.shape} and directions {d.shape} differ in shape")
    n = len(o_in)
    o = np.empty((3, n), np.float32) if soa else np.empty((n, 3), np.float32)
    # Column by column: numpy's broadcast over a length-3 inner axis is several times slower.
    for c in range(3):
        np.subtract(o_in[:, c], shift[c] if shift is not None else 0.0, out=o[c] if soa else o[:, c], casting="unsafe")
    scalar_tmin = np.ndim(tmin) == 0
    tmin_a = np.full(n, np.float32(tmin), np.float32) if scalar_tmin else np.asarray(tmin, np.float32).reshape(n)
    if not scalar_tmin or tmin > 0:
        if soa:
            o += d.T * tmin_a[None, :]
        else:
            o += d * tmin_a[:, None]
    # Lengths are clipped to [0, MAX_RAY_LENGTH] in one pass: both backends take a finite float32 far value.
    if np.ndim(tmax) == 0:
        length = np.full(n, np.float32(tmax), np.float32)
    else:
        length = np.array(tmax, np.float32).reshape(n)
    if not scalar_tmin or tmin > 0:
        length -= tmin_a
    np.clip(length, 0.0, MAX_RAY_LENGTH, out=length)
    return o, d, tmin_a, np.ascontiguousarray(length, np.float32)


class Tracer:
    """Base class: counters and the shared ray-argument handling."""

    name = "base"
    soa_origins = False  # backends that take (3, N) origins without a copy set this

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
        o, d, tmin_a, length = as_rays(origins, dirs, tmin, tmax, self.shift, self.soa_origins)
        self.counters["rays_intersect"] += len(d)
        if len(d) == 0:
            z = np.zeros(0, np.float32)
            return Hits(z, np.zeros(0, np.int32), z, z)
        t, prim, u, v = self._intersect(o, d, length)
        t, u, v = (_writable(x) for x in (t, u, v))
        prim = np.asarray(prim, np.int32)
        miss = prim < 0
        if np.ndim(tmin) != 0 or tmin > 0:
            t += tmin_a
        t[miss], u[miss], v[miss] = np.inf, 0.0, 0.0
        return Hits(t, prim, u, v)

    def occluded(self, origins, dirs, tmin=0.0, tmax=np.inf) -> np.ndarray:
        o, d, _, length = as_rays(origins, dirs, tmin, tmax, self.shift, self.soa_origins)
        self.counters["rays_occluded"] += len(d)
        if len(d) == 0:
            return np.zeros(0, bool)
        return self._occluded(o, d, length)

    def occluded_local(self, o, d, length) -> np.ndarray:
        """``occluded`` for rays already in the tracing frame: float32 origins minus ``shift`` (shape (3, N) if
        ``soa_origins`` else (N, 3)), unit float32 directions (N, 3), lengths in [0, MAX_RAY_LENGTH].

        For ray generators that write rays in the backend's frame and layout directly
        (:mod:`suite.trace.raygen`); everything else should call :meth:`occluded`.
        """
        n = len(d)
        self.counters["rays_occluded"] += n
        if n == 0:
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


def _writable(x) -> np.ndarray:
    """float32 array that may be modified in place (copies only when the backend's buffer is read-only)."""
    a = np.asarray(x, np.float32)
    return a if a.flags.writeable and a.flags.owndata else a.copy()


def split_static_dynamic(scene):
    """Face indices of static geometry and of rigidly animated objects."""
    moving = np.array(sorted({a.object_id for a in scene.object_animations}), np.int32)
    is_dynamic = np.isin(scene.face_object, moving)
    return np.nonzero(~is_dynamic)[0].astype(np.int32), np.nonzero(is_dynamic)[0].astype(np.int32)
