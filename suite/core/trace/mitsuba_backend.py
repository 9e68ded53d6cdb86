"""Mitsuba 3 / Dr.Jit backend.

Builds a Mitsuba scene with one mesh for static geometry and one for animated objects (so an update
re-uploads only moving vertices). Variants: ``llvm_ad_rgb`` on CPU, ``cuda_ad_rgb`` on a GPU, ``scalar_rgb``
as a last resort (see :mod:`suite.core.env`). Mitsuba rays have no ``tmin``: the base class advances origins.

The tracer keeps its variant (``tracer.variant``) and uses that variant's own types, so switching Mitsuba's active
variant elsewhere in the process (a loader, a reference) does not change what it builds. Hits are mapped to global
face indices through the hit shape's registry id (``ShapePtr`` reinterpreted as an integer), never through
``PreliminaryIntersection.shape_index``: on ``cuda_ad_rgb`` that field is 0 whatever shape was hit, which gave hits
on moving geometry the static mesh's faces.

Besides the numpy interface of :class:`~suite.core.trace.base.Tracer`, the vectorised variants expose
``tracer.device`` (:class:`suite.core.device.Device`): the same queries and the G-buffer, shading and visibility
kernels on Dr.Jit arrays that stay on the device.
"""
from __future__ import annotations

import sys

import numpy as np

from suite.core.trace.base import Tracer, split_static_dynamic


class MitsubaTracer(Tracer):
    name = "mitsuba"
    normalized_hits = True  # misses already carry t = inf, prim = -1, u = v = 0
    soa_origins = True  # Dr.Jit wraps contiguous rows without a copy; strided columns cost a copy each

    def __init__(self, scene, variant: str = "auto"):
        super().__init__(scene)
        from suite.core.env import mitsuba

        mi = mitsuba(variant)  # resolves (and checks) the variant, and makes it active while the scene is built
        self.variant = mi.variant()
        self.mi = mi
        self.m = sys.modules[f"mitsuba.{self.variant}"]  # the variant's own types
        import drjit as dr

        self.dr = dr
        self.static_faces, self.dynamic_faces = split_static_dynamic(scene)
        self._parts = [f for f in (self.static_faces, self.dynamic_faces) if len(f)]
        desc = {"type": "scene"}
        positions = self.local_positions(scene.positions)
        for i, faces in enumerate(self._parts):
            desc[f"part{i}"] = self._mesh(f"part{i}", positions, faces)
        self.mscene = mi.load_dict(desc)
        self.query_scene = self.mscene  # what the queries call (a test may wrap it)
        # Shape order in the scene may differ from insertion order: map by id.
        shapes = list(self.mscene.shapes())
        self._shape_faces = [self._parts[int(s.id()[4:])] for s in shapes]
        # A static scene's only mesh holds the faces in order: primitive index = face index.
        self._identity_prims = len(self._shape_faces) == 1 and np.array_equal(self._shape_faces[0],
                                                                             np.arange(scene.num_faces))
        if not self.is_scalar:
            # Shape with registry id r: its local primitive p is global face _face_table[_first_face_by_id[r] + p].
            m = self.m
            self._face_table = m.Int32(np.concatenate(self._shape_faces).astype(np.int32))
            firsts = np.cumsum([0] + [len(f) for f in self._shape_faces[:-1]]).astype(np.uint32)
            ids = [self.shape_registry_id(s) for s in shapes]
            table = np.zeros(max(ids) + 1, np.uint32)
            table[ids] = firsts
            self._first_face_by_id = m.UInt32(table)
        self._params = mi.traverse(self.mscene) if len(self.dynamic_faces) else None
        self._dynamic_key = None
        if self._params is not None:
            dyn_index = len(self._parts) - 1
            self._dynamic_key = f"part{dyn_index}.vertex_positions"
        self.rebuilds = 0
        self._device = None

    def shape_registry_id(self, shape) -> int:
        """The integer a ``ShapePtr`` to ``shape`` holds on this variant (what hits carry in ``pi.shape``)."""
        m, dr = self.m, self.dr
        return int(dr.reinterpret_array(m.UInt32, m.ShapePtr(shape))[0])

    @property
    def device(self):
        """The Dr.Jit-resident side of this tracer (:class:`suite.core.device.Device`), None for ``scalar_rgb``."""
        if self.is_scalar:
            return None
        if self._device is None:
            from suite.core.device.context import Device

            self._device = Device(self)
        return self._device

    def _mesh(self, name, positions, faces):
        mi = self.mi
        tri = positions[self.scene.faces[faces]].reshape(-1, 3)
        mesh = mi.Mesh(name, len(tri), len(faces))
        params = mi.traverse(mesh)
        # Buffer types differ per variant (mi.Float is a Python float in scalar_rgb): build what is there.
        params["vertex_positions"] = type(params["vertex_positions"])(np.ascontiguousarray(tri, np.float32).reshape(-1))
        params["faces"] = type(params["faces"])(np.arange(len(tri), dtype=np.uint32))
        params.update()
        return mesh

    def describe(self) -> dict:
        return {"backend": self.name, "variant": self.variant}

    def _update(self, t_s: float) -> None:
        positions_world = self.scene.positions_at(t_s)
        positions = self.local_positions(positions_world)
        tri = positions[self.scene.faces[self.dynamic_faces]].reshape(-1)
        buffer_type = type(self._params[self._dynamic_key])
        self._params[self._dynamic_key] = buffer_type(np.ascontiguousarray(tri, np.float32))
        self._params.update()
        self.rebuilds += 1
        if self._device is not None:
            self._device.on_update(positions_world, t_s)

    def _rays(self, o, d, length):
        m = self.m
        ray = m.Ray3f(m.Point3f(o[0], o[1], o[2]), m.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        ray.maxt = m.Float(length)
        return ray

    @property
    def is_scalar(self) -> bool:
        return self.variant.startswith("scalar")

    def _scalar_rays(self, o, d, length):
        """One Mitsuba ray at a time (scalar_rgb, the last-resort variant: correct but slow)."""
        m = self.m
        for i in range(len(d)):
            ray = m.Ray3f([float(x) for x in o[:, i]], [float(x) for x in d[i]])
            ray.maxt = float(length[i])
            yield i, ray

    def _intersect(self, o, d, length):
        n = len(d)
        if self.is_scalar:
            t = np.full(n, np.inf, np.float32)
            prim = np.full(n, -1, np.int32)
            uv = np.zeros((2, n), np.float32)
            shapes = list(self.mscene.shapes())
            for i, ray in self._scalar_rays(o, d, length):
                pi = self.query_scene.ray_intersect_preliminary(ray)
                if pi.is_valid():
                    faces = self._shape_faces[shapes.index(pi.shape) if len(shapes) > 1 else 0]
                    t[i], prim[i] = pi.t, faces[int(pi.prim_index)]
                    uv[:, i] = pi.prim_uv
            return t, prim, uv[0], uv[1]
        # Misses, the global face index and the barycentrics are resolved inside the same Dr.Jit kernel as the
        # traversal (one launch, no numpy passes afterwards): t = inf, prim = -1, u = v = 0 on a miss.
        dev = self.device
        t, prim, u, v = dev.closest_backend(*self._ray_parts(o, d, length))
        self.dr.eval(t, prim, u, v)
        return np.array(t, np.float32), np.array(prim, np.int32), np.array(u, np.float32), np.array(v, np.float32)

    def _ray_parts(self, o, d, length):
        m = self.m
        return (m.Point3f(o[0], o[1], o[2]), m.Vector3f(d[:, 0], d[:, 1], d[:, 2]), m.Float(length))

    def _occluded(self, o, d, length):
        if self.is_scalar:
            out = np.zeros(len(d), bool)
            for i, ray in self._scalar_rays(o, d, length):
                out[i] = bool(self.query_scene.ray_test(ray))
            return out
        return np.array(self.query_scene.ray_test(self._rays(o, d, length)), bool)

    # Raw access for the overhead benchmark: (N, 3) float32 rays handed to Mitsuba directly, as a user would.
    def _subscene(self, faces, positions):
        if self.is_scalar:
            return None
        import mitsuba as mi

        active = mi.variant()
        mi.set_variant(self.variant)  # load_dict builds with the active variant: this tracer's, then the caller's
        try:
            scene = mi.load_dict({"type": "scene", "group": self._mesh("group", positions, faces)}) if len(faces) \
                else None
        finally:
            if active is not None and active != self.variant:
                mi.set_variant(active)
        return MitsubaGroup(self, faces, scene)

    def _raw_ray(self, o, d, length):
        return self._rays(np.asarray(o).T, d, length)

    def raw_occluded(self, o, d, length):
        return np.array(self.mscene.ray_test(self._raw_ray(o, d, length)), bool)

    def raw_intersect(self, o, d, length):
        pi = self.mscene.ray_intersect_preliminary(self._raw_ray(o, d, length), coherent=False)
        self.dr.eval(pi.t, pi.prim_index, pi.prim_uv)
        return np.array(pi.t), np.array(pi.prim_index), np.array(pi.prim_uv)


class MitsubaGroup:
    """A Mitsuba scene over a subset of the faces, one mesh (the alpha groups of ``Tracer._occluded_split``, and of
    the device's shadow rays)."""

    def __init__(self, tracer: MitsubaTracer, faces: np.ndarray, mscene):
        self.tracer, self.faces, self.mscene = tracer, faces, mscene
        self.face_table = tracer.m.Int32(faces.astype(np.int32)) if len(faces) else None  # local prim -> face

    def occluded(self, o, d, length):
        if self.mscene is None:
            return np.zeros(len(d), bool)
        return np.array(self.mscene.ray_test(self.tracer._rays(o, d, length), coherent=False), bool)

    def closest(self, o, d, length):
        n = len(d)
        if self.mscene is None:
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32), np.zeros(n, np.float32), \
                np.zeros(n, np.float32)
        t, prim, u, v = self.tracer.device.closest_backend(*self.tracer._ray_parts(o, d, length), group=self)
        self.tracer.dr.eval(t, prim, u, v)
        return np.array(t, np.float32), np.array(prim, np.int32), np.array(u, np.float32), np.array(v, np.float32)
