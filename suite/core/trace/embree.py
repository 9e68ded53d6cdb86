"""Embree backend through embreex.

embreex traces one ray at a time on one thread and fixes ``tnear`` at 0 (the base class advances origins by
``tmin``). It exposes neither instancing nor per-geometry commits, so an animation update rebuilds the one
Embree scene, and only when an object actually moved. A second scene for the moving objects would keep
rebuilds small, but every query would then pay embreex's per-ray call overhead twice (measured: 0.3x the
throughput on ``arena``), while a rebuild of ``arena`` (612 triangles) takes about a millisecond.
"""
from __future__ import annotations

import numpy as np

from suite.core.trace.base import Tracer


def _embree_modules():
    from embreex import mesh_construction, rtcore_scene

    return mesh_construction, rtcore_scene


def build_embree_scene(triangles: np.ndarray):
    """An Embree scene over (F, 3, 3) float32 triangles; primID = index into ``triangles``."""
    mc, rtcs = _embree_modules()
    scene = rtcs.EmbreeScene()
    if len(triangles):
        mc.TriangleMesh(scene, np.ascontiguousarray(triangles, np.float32))
    return scene


class EmbreeGroup:
    """An Embree scene over a subset of the faces (the alpha groups of :meth:`Tracer._occluded_split`)."""

    def __init__(self, faces: np.ndarray, triangles: np.ndarray):
        self.faces = faces
        self.escene = build_embree_scene(triangles[faces]) if len(faces) else None

    def occluded(self, o, d, length):
        if self.escene is None:
            return np.zeros(len(d), bool)
        return self.escene.run(o, d, dists=length, query="OCCLUDED") != -1

    def closest(self, o, d, length):
        n = len(d)
        if self.escene is None:
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32), \
                np.zeros(n, np.float32)
        res = self.escene.run(o, d, dists=length, output=1)
        t, prim, u, v = (np.array(res[k], dt) for k, dt in (("tfar", np.float32), ("primID", np.int32),
                                                             ("u", np.float32), ("v", np.float32)))
        _group_hits()(prim, self.faces, t, u, v)
        return t, prim, u, v


_group_hits_kernel = None


def _group_hits():
    """In place: the group's primitive ids mapped to global faces, misses normalised (t = inf, u = v = 0) in one
    compiled pass."""
    global _group_hits_kernel
    if _group_hits_kernel is None:
        import numba

        def kernel(prim, faces, t, u, v):
            for i in range(prim.shape[0]):
                if prim[i] >= 0:
                    prim[i] = faces[prim[i]]
                else:
                    prim[i], t[i], u[i], v[i] = -1, np.inf, 0.0, 0.0

        _group_hits_kernel = numba.njit(cache=True, nogil=True)(kernel)
    return _group_hits_kernel


class EmbreeTracer(Tracer):
    name = "embree"

    def __init__(self, scene):
        super().__init__(scene)
        self.rebuilds = 0
        self._build(scene.positions)

    def _build(self, positions: np.ndarray) -> None:
        self.escene = build_embree_scene(self.scene.triangles(self.local_positions(positions)))

    def _update(self, t_s: float) -> None:
        if self.scene.moved_objects(self._time_s, t_s):
            self._build(self.scene.positions_at(t_s))
            self.rebuilds += 1

    def _subscene(self, faces, positions):
        return EmbreeGroup(faces, self.scene.triangles(positions))

    def _intersect(self, o, d, length):
        res = self.escene.run(o, d, dists=length, output=1)
        return res["tfar"], res["primID"], res["u"], res["v"]

    def _occluded(self, o, d, length):
        return self.escene.run(o, d, dists=length, query="OCCLUDED") != -1

    # Raw access for the overhead benchmark: the same Embree scene called directly, as a user of embreex would.
    def raw_occluded(self, o, d, length):
        return self.escene.run(o, d, dists=length, query="OCCLUDED")

    def raw_intersect(self, o, d, length):
        return self.escene.run(o, d, dists=length, output=1)
