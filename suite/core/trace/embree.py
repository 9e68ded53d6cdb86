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
        local = np.asarray(res["primID"], np.int64)
        hit = local >= 0
        prim = np.where(hit, self.faces[np.where(hit, local, 0)], -1).astype(np.int32)
        t = np.where(hit, res["tfar"], np.inf).astype(np.float32)
        return t, prim, np.where(hit, res["u"], 0.0).astype(np.float32), np.where(hit, res["v"], 0.0).astype(np.float32)


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
