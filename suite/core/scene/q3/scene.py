"""``Q3Scene``: the shared scene model plus a Quake III map's visibility and records.

It is a :class:`~suite.core.scene.model.Scene` (every backend, method and exporter takes it as one) with two
optional attributes: ``visibility`` (:class:`~.visibility.Q3Visibility`) and ``q3`` (:class:`~.convert.Q3Info`).
Code that works on any scene reads them with ``getattr(scene, "visibility", None)``. The two scene operations
that move geometry or drop triangles keep them consistent.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from suite.core.scene.model import Scene


@dataclass(eq=False)
class Q3Scene(Scene):
    visibility: object | None = None  # Q3Visibility: cluster_of(points), pvs(cluster), triangle clusters
    q3: object | None = None  # Q3Info: per-face flags, shader and light records, counts

    def translated(self, offset) -> "Q3Scene":
        moved = super().translated(offset)
        if self.visibility is None:
            return moved
        return dataclasses.replace(moved, visibility=self.visibility.translated(offset))

    def without_degenerate_faces(self, min_area: float = 0.0) -> "Q3Scene":
        area = self.face_areas()
        keep = np.isfinite(area) & (area > min_area)
        if keep.all():
            return self
        vis = None if self.visibility is None else self.visibility.subset_triangles(keep)
        info = self.q3
        if info is not None:
            info = dataclasses.replace(info, triangle_face=info.triangle_face[keep])
        return dataclasses.replace(self, faces=self.faces[keep], face_material=self.face_material[keep],
                                   face_object=self.face_object[keep], visibility=vis, q3=info)
