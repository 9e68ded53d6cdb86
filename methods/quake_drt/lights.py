"""The light array of seed 001 (§6.9, Table 6.8): point lights and triangle-shaped area lights.

The thesis had no light entities to start from and made its own lights from emissive geometry, "each light
source consisting of more than one triangle [split] into multiple triangle-shaped light sources" (§6.9). The
suite's Quake III scenes have both kinds already (docs/scenes.md, *Lights*): light entities, sun and sky as
point lights, ``q3map_surfacelight`` surfaces as emissive triangles. One entry of the array is

* a **point light** (intensity I in W/sr), or
* an **area light**: emissive triangles of one material (radiance L_e, one-sided, emitting along the triangles'
  stored normals). ``unit = "triangle"`` makes every triangle its own light (the thesis's Table 6.8);
  ``unit = "polygon"`` groups the triangles that share vertices (a Quake III face or Bezier patch, a builder
  quad) into one light whose points are sampled uniformly by area. A tessellated patch is 128 triangles per
  sub-patch, so "triangle" multiplies the light count (and the cost of "all lights") by the tessellation.

Shading a point ``x`` (Algorithm 6.2, in Mitsuba's units): a point light adds ``V * f * cos_x * I / d^2``; an
area light sampled at a uniform point ``y`` of its surface adds ``V * f * cos_x * cos_y * L_e * A / d^2`` (the
area form, pdf 1/A). With soft shadows off (thesis Table 6.1 ``rt_softshadows``) ``y`` is the light's fixed
representative point: the centre of the triangle nearest its area-weighted centroid (a hard shadow, and a point
approximation of the light's irradiance).

``power`` is the emitted flux (4 pi I for a point light, pi A L_e for a one-sided area light, RGB mean), used by
the power-proportional light-subsampling variant.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError

POINT, AREA = 0, 1
UNITS = ("polygon", "triangle")


@dataclass
class LightList:
    """Every light of a frame (points first, then area lights), as arrays."""

    names: list
    kind: np.ndarray  # (L,) int8: POINT or AREA
    position: np.ndarray  # (L, 3) float64: point position / area light's representative point
    normal: np.ndarray  # (L, 3) float64: area light's representative emitting normal (0 for points)
    rgb: np.ndarray  # (L, 3) float64: intensity I (W/sr) of a point light, radiance L_e of an area light
    area: np.ndarray  # (L,) float64 m^2 (0 for points)
    tri_offsets: np.ndarray  # (L + 1,) int64: area light l owns triangles tri_offsets[l]:tri_offsets[l + 1]
    tri_p0: np.ndarray  # (T, 3) float64 corner 0
    tri_e1: np.ndarray  # (T, 3) float64 edge p1 - p0
    tri_e2: np.ndarray  # (T, 3) float64 edge p2 - p0
    tri_normal: np.ndarray  # (T, 3) float64 unit emitting normal
    tri_cdf: np.ndarray  # (T,) float64 cumulative area fraction within the light (last of each light = 1)
    tri_face: np.ndarray  # (T,) int64 global face id
    rep_tri: np.ndarray  # (L,) int64 representative triangle of an area light, -1 for points
    unit: str = "polygon"
    face_light: dict = field(default_factory=dict, repr=False)  # bookkeeping for refresh()

    def __len__(self) -> int:
        return int(len(self.kind))

    @property
    def n_point(self) -> int:
        return int((self.kind == POINT).sum())

    @property
    def n_area(self) -> int:
        return int((self.kind == AREA).sum())

    @property
    def power(self) -> np.ndarray:
        """(L,) emitted flux in W (RGB mean): 4 pi I for point lights, pi A L_e for one-sided area lights."""
        mean = self.rgb.mean(axis=1)
        return np.where(self.kind == POINT, 4.0 * np.pi * mean, np.pi * self.area * mean)

    def triangles_of(self, light: int) -> slice:
        return slice(int(self.tri_offsets[light]), int(self.tri_offsets[light + 1]))


def _group_polygons(scene, faces: np.ndarray) -> np.ndarray:
    """(E,) component label of each emissive triangle: triangles of one material that share vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = len(faces)
    if e == 0:
        return np.zeros(0, np.int64)
    verts = scene.faces[faces].astype(np.int64)  # (E, 3)
    mats = scene.face_material[faces].astype(np.int64)
    key = verts * (int(mats.max()) + 1) + mats[:, None]  # a vertex only links triangles of the same material
    _, vnode = np.unique(key.reshape(-1), return_inverse=True)
    n_nodes = e + int(vnode.max()) + 1
    rows = np.repeat(np.arange(e), 3)
    cols = e + vnode
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_nodes, n_nodes))
    _, labels = connected_components(graph, directed=False)
    # Relabel in order of first appearance, so lights keep the order of their first triangle.
    tri_labels = labels[:e]
    _, first, inverse = np.unique(tri_labels, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inverse].astype(np.int64)


def build_lights(scene, t_s: float, unit: str = "polygon") -> LightList:
    """The light array of ``scene`` at time ``t_s`` (see the module docstring)."""
    if unit not in UNITS:
        raise UserError(f"unknown area_light_unit '{unit}' (choose from {', '.join(UNITS)})")
    points = scene.lights_at(t_s)
    tl = scene.area_light_triangles(t_s)
    group = np.arange(len(tl), dtype=np.int64) if unit == "triangle" else _group_polygons(scene, tl.faces)
    return _assemble(points, tl, group, unit)


def _assemble(points, tl, group, unit) -> LightList:
    n_p = len(points)
    n_a = int(group.max()) + 1 if len(group) else 0
    order = np.argsort(group, kind="stable")  # triangles grouped by light, in face order within a light
    g = group[order]
    counts = np.bincount(g, minlength=n_a) if n_a else np.zeros(0, np.int64)
    tri = np.asarray(tl.vertices, np.float64)[order]
    p0 = tri[:, 0]
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    tri_area = np.asarray(tl.area, np.float64)[order]
    tri_normal = np.asarray(tl.normal, np.float64)[order]
    radiance = np.asarray(tl.radiance, np.float64)[order]
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    light_area = np.add.reduceat(tri_area, starts[:-1]) if n_a else np.zeros(0)
    cum = np.cumsum(tri_area)
    before = np.repeat(cum[starts[:-1]] - tri_area[starts[:-1]], counts) if n_a else np.zeros(0)
    tri_cdf = (cum - before) / np.maximum(np.repeat(light_area, counts), 1e-300) if n_a else np.zeros(0)
    if n_a:
        tri_cdf[starts[1:] - 1] = 1.0  # exact ends: a uniform number below 1 always finds a triangle
    # Representative point: the centre of the triangle nearest the light's area-weighted centroid.
    centre = p0 + (e1 + e2) / 3.0
    rep = np.full(n_a, -1, np.int64)
    if n_a:
        weighted = np.add.reduceat(centre * tri_area[:, None], starts[:-1]) / np.maximum(light_area, 1e-300)[:, None]
        dist = np.linalg.norm(centre - np.repeat(weighted, counts, axis=0), axis=1)
        owner = np.repeat(np.arange(n_a), counts)
        best = np.lexsort((dist, owner))
        rep = best[starts[:-1]]
    # The radiance of an area light: its triangles share a material, so any of them tells it.
    area_rgb = radiance[starts[:-1]] if n_a else np.zeros((0, 3))
    kind = np.concatenate([np.full(n_p, POINT, np.int8), np.full(n_a, AREA, np.int8)])
    position = np.concatenate([np.array([lt.position for lt in points], np.float64).reshape(-1, 3),
                               centre[rep] if n_a else np.zeros((0, 3))])
    normal = np.concatenate([np.zeros((n_p, 3)), tri_normal[rep] if n_a else np.zeros((0, 3))])
    rgb = np.concatenate([np.array([lt.intensity for lt in points], np.float64).reshape(-1, 3), area_rgb])
    area = np.concatenate([np.zeros(n_p), light_area])
    tri_offsets = np.concatenate([np.zeros(n_p, np.int64), starts]).astype(np.int64)
    names = [lt.name for lt in points] + [f"area_{i}" for i in range(n_a)]
    return LightList(names=names, kind=kind, position=position, normal=normal, rgb=rgb, area=area,
                     tri_offsets=tri_offsets, tri_p0=p0, tri_e1=e1, tri_e2=e2, tri_normal=tri_normal,
                     tri_cdf=tri_cdf, tri_face=np.asarray(tl.faces, np.int64)[order], rep_tri=np.concatenate(
                         [np.full(n_p, -1, np.int64), rep + 0]).astype(np.int64), unit=unit,
                     face_light={"group": group})


def refresh(lights: LightList, scene, t_s: float) -> LightList:
    """The same lights (same order and grouping) at another time: point lights move and change intensity with
    ``scene.lights_at``; area lights move with their objects."""
    points = scene.lights_at(t_s)
    if len(points) != lights.n_point:
        raise UserError(f"the scene has {len(points)} point lights at t = {t_s} s, {lights.n_point} when the "
                        f"light array was built")
    if scene.object_animations and lights.n_area:
        out = _assemble(points, scene.area_light_triangles(t_s), lights.face_light["group"], lights.unit)
    else:
        out = _copy(lights)
    n_p = lights.n_point
    if n_p:
        out.position[:n_p] = np.array([lt.position for lt in points], np.float64)
        out.rgb[:n_p] = np.array([lt.intensity for lt in points], np.float64)
    return out


def _copy(lights: LightList) -> LightList:
    import dataclasses

    return dataclasses.replace(lights, position=lights.position.copy(), rgb=lights.rgb.copy())
