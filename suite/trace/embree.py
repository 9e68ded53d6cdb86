"""Embree backend through embreex.

embreex traces one ray at a time on one thread and fixes ``tnear`` at 0 (the base class advances origins by
``tmin``). Static geometry and rigidly animated objects live in two Embree scenes, so an animation update
rebuilds only the (small) moving part; queries combine both.
"""
from __future__ import annotations

import numpy as np

from suite.trace.base import Tracer, split_static_dynamic

# embreex reads ray lengths as float32; an infinite length is passed as the largest "far" Embree accepts.
FAR = np.float32(1e37)


def _embree_modules():
    from embreex import mesh_construction, rtcore_scene

    return mesh_construction, rtcore_scene


class _Part:
    """One Embree scene over a subset of faces; ``faces[local_prim]`` is the global face index."""

    def __init__(self, triangles: np.ndarray, faces: np.ndarray):
        mc, rtcs = _embree_modules()
        self.faces = faces
        self.scene = rtcs.EmbreeScene()
        if len(faces):
            mc.TriangleMesh(self.scene, np.ascontiguousarray(triangles, np.float32))

    def intersect(self, o, d, length):
        if len(self.faces) == 0:
            n = len(o)
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32)
        res = self.scene.run(o, d, dists=np.minimum(length, FAR), output=1)
        local = res["primID"]
        prim = np.where(local >= 0, self.faces[np.maximum(local, 0)], -1).astype(np.int32)
        return res["tfar"].astype(np.float32), prim, res["u"], res["v"]

    def occluded(self, o, d, length):
        if len(self.faces) == 0:
            return np.zeros(len(o), bool)
        return self.scene.run(o, d, dists=np.minimum(length, FAR), query="OCCLUDED") != -1


class EmbreeTracer(Tracer):
    name = "embree"

    def __init__(self, scene):
        super().__init__(scene)
        self.static_faces, self.dynamic_faces = split_static_dynamic(scene)
        tri = scene.triangles(self.local_positions(scene.positions))
        self.static = _Part(tri[self.static_faces], self.static_faces)
        self.dynamic = _Part(tri[self.dynamic_faces], self.dynamic_faces) if len(self.dynamic_faces) else None
        self.rebuilds = 0

    def _update(self, t_s: float) -> None:
        positions = self.local_positions(self.scene.positions_at(t_s))
        self.dynamic = _Part(self.scene.triangles(positions)[self.dynamic_faces], self.dynamic_faces)
        self.rebuilds += 1

    def _intersect(self, o, d, length):
        t, prim, u, v = self.static.intersect(o, d, length)
        if self.dynamic is not None:
            t2, prim2, u2, v2 = self.dynamic.intersect(o, d, length)
            closer = (prim2 >= 0) & ((prim < 0) | (t2 < t))
            t, prim = np.where(closer, t2, t), np.where(closer, prim2, prim)
            u, v = np.where(closer, u2, u), np.where(closer, v2, v)
        return t, prim, u, v

    def _occluded(self, o, d, length):
        occ = self.static.occluded(o, d, length)
        if self.dynamic is not None:
            occ |= self.dynamic.occluded(o, d, length)
        return occ

    # Raw access for the overhead benchmark: the same call the suite makes, with no bookkeeping.
    def raw_occluded(self, o, d, length):
        return self.static.scene.run(o, d, dists=length, query="OCCLUDED")

    def raw_intersect(self, o, d, length):
        return self.static.scene.run(o, d, dists=length, output=1)
