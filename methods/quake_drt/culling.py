"""PVS light culling (seed 001 §4.3, Table 4.2; §6.6, §6.9).

The thesis keeps a *light visibility texture*: one row per cluster, holding the number of lights whose cluster is
potentially visible from that cluster and then their indices (Table 4.2). Shading a pixel reads the row of the
pixel's cluster and shoots shadow rays only to those lights (or to k random ones of them, §6.6). Here the table
is a CSR list (``row_offsets``, ``row_lights``, int32 light indices, so there is no limit on the light count and
no bit-mask word to overflow).

* **Clusters of a light.** A point light is in the cluster of its position; a light slightly sunk into a wall
  (its position in solid, cluster -1) gets the clusters found around it: points at ``probe * 2^j`` (j = 0..6)
  along 26 directions, the first radius that finds any. An area light is in every cluster any of its triangles
  is in (the visibility's per-triangle cluster lists) plus the cluster just in front of its representative
  point. A light that still has no cluster is treated as visible from everywhere (counted as
  ``lights_unclustered``), so culling never removes it.
* **Visible from a cluster.** Light l is visible from cluster c when one of l's clusters is in the PVS row of c.
  The thesis reads the row of the pixel's cluster only (``vis[cluster >> 3] & (1 << (cluster & 7))``, §4.3).
  q3map2's PVS is not symmetric (docs/scenes.md: 0.05-2.7 % of visible pairs hold one way only), so
  ``symmetric = True`` (the default) also accepts ``c`` in the PVS of l's cluster: a light that sees the pixel's
  cluster is kept even where the stored row says the pixel's cluster does not see it.
* **Cluster of a pixel (cluster merging, §4.3.1).** The thesis stores one cluster per *triangle*; a triangle whose
  vertices lie in different clusters gets a merged cluster "with the combined visibility information" of them.
  ``pixel_cluster = "triangle"``: the row of the hit triangle, merged (the union of the PVS rows of every cluster
  the triangle is in; rows are deduplicated). ``pixel_cluster = "point"``: the cluster of the shading point
  nudged ``probe`` toward the viewer (a point lookup, tighter), falling back to the triangle's merged row when
  that point is in solid. A triangle in no cluster shades with all lights.

Without any visibility (``source = "none"``) every row holds every light: culling is a no-op, and the fact is
recorded in the per-frame output ``pvs_source``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.errors import UserError

PVS_SOURCES = ("auto", "scene", "computed", "none")
PIXEL_CLUSTER_RULES = ("triangle", "point")
PROBE_STEPS = 7


@dataclass
class CullTable:
    """The light visibility table and how pixels find their row."""

    source: str  # "bsp" (the map's own PVS), "computed" (suite.core.scene.cellvis), "none"
    n_clusters: int
    symmetric: bool
    light_cluster_offsets: np.ndarray  # (L + 1,) CSR of each light's clusters
    light_cluster_ids: np.ndarray  # (K,) int64
    light_unclustered: np.ndarray  # (L,) bool: no cluster found, visible from everywhere
    row_offsets: np.ndarray  # (R + 1,) int64: Table 4.2 rows (first n_clusters rows = single clusters)
    row_lights: np.ndarray  # (S,) int32 light indices, ascending within a row
    tri_row: np.ndarray  # (F,) int64: the (merged) row of every triangle; all_row for triangles in no cluster
    all_row: int  # the row that holds every light
    row_centre: np.ndarray | None = None  # (R, 3) centre of the bounds of the row's clusters (the scene's for all_row)
    row_radius: np.ndarray | None = None  # (R,) half the diagonal of those bounds

    @property
    def n_rows(self) -> int:
        return int(len(self.row_offsets) - 1)

    def row_counts(self) -> np.ndarray:
        return np.diff(self.row_offsets)

    def row(self, r: int) -> np.ndarray:
        return self.row_lights[self.row_offsets[r]:self.row_offsets[r + 1]]


def resolve_visibility(scene, tracer, pvs: str):
    """(visibility object or None, source name) for the ``pvs`` parameter (module docstring)."""
    if pvs not in PVS_SOURCES:
        raise UserError(f"unknown pvs '{pvs}' (choose from {', '.join(PVS_SOURCES)})")
    own = getattr(scene, "visibility", None)
    if pvs == "none":
        return None, "none"
    if pvs in ("auto", "scene") and own is not None:
        return own, "bsp" if type(own).__name__ == "Q3Visibility" else "scene"
    if pvs == "scene":
        return None, "none"
    try:  # the computed PVS for scenes without a BSP (suite/core/scene/cellvis.py), where it exists
        from suite.core.scene.cellvis import computed_visibility
    except ImportError:
        if pvs == "computed":
            raise UserError("pvs = 'computed' needs suite.core.scene.cellvis, which this checkout lacks") from None
        return None, "none"
    return computed_visibility(scene, tracer), "computed"


def _probe_directions() -> np.ndarray:
    d = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                 np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def clusters_around(vis, points: np.ndarray, probe: float) -> list[np.ndarray]:
    """For each point: its cluster if it has one, else the clusters found on the first probe sphere (radius
    ``probe * 2^j``) that finds any; an empty array if none does."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    own = vis.cluster_of(points).astype(np.int64)
    out = [np.array([c], np.int64) if c >= 0 else np.zeros(0, np.int64) for c in own]
    todo = np.nonzero(own < 0)[0]
    dirs = _probe_directions()
    for j in range(PROBE_STEPS):
        if len(todo) == 0:
            break
        pts = points[todo][:, None, :] + (probe * 2.0 ** j) * dirs[None]
        cl = vis.cluster_of(pts.reshape(-1, 3)).reshape(len(todo), len(dirs))
        found = []
        for row, i in enumerate(todo):
            c = np.unique(cl[row][cl[row] >= 0])
            if len(c):
                out[i] = c.astype(np.int64)
                found.append(row)
        todo = np.delete(todo, found)
    return out


def light_clusters(vis, lights, probe: float) -> list[np.ndarray]:
    """The clusters of every light (module docstring)."""
    from methods.quake_drt.lights import AREA

    rep_clusters = clusters_around(vis, lights.position, probe)
    out = []
    offsets = getattr(vis, "triangle_cluster_offsets", None)
    ids = getattr(vis, "triangle_cluster_ids", None)
    for li in range(len(lights)):
        cl = [rep_clusters[li]]
        if lights.kind[li] == AREA:
            # The cluster just in front of the light (the space it emits into), and its triangles' clusters.
            front = lights.position[li] + probe * lights.normal[li]
            cl.append(clusters_around(vis, front[None], probe)[0])
            if offsets is not None:
                faces = lights.tri_face[lights.triangles_of(li)]
                starts, ends = offsets[faces], offsets[faces + 1]
                if (ends > starts).any():
                    cl.append(np.concatenate([ids[a:b] for a, b in zip(starts, ends)]).astype(np.int64))
        out.append(np.unique(np.concatenate(cl)).astype(np.int64))
    return out


def _triangle_sets(vis, n_faces: int):
    """(sets, tri_set): the distinct cluster sets of triangles as padded rows (-1 padding), and each triangle's
    set index (-1 for triangles in no cluster)."""
    offsets = np.asarray(vis.triangle_cluster_offsets, np.int64)
    ids = np.asarray(vis.triangle_cluster_ids, np.int64)
    if len(offsets) != n_faces + 1:
        raise UserError(f"the visibility lists clusters for {len(offsets) - 1} triangles, the scene has {n_faces}")
    counts = np.diff(offsets)
    width = int(counts.max()) if len(counts) else 0
    tri_set = np.full(n_faces, -1, np.int64)
    if width == 0:
        return np.zeros((0, 0), np.int64), tri_set
    padded = np.full((n_faces, width), -1, np.int64)
    owner = np.repeat(np.arange(n_faces), counts)
    slot = np.arange(len(ids)) - np.repeat(offsets[:-1], counts)
    padded[owner, slot] = ids
    padded.sort(axis=1)  # -1 padding first, then ascending clusters
    has = counts > 0
    sets, inverse = np.unique(padded[has], axis=0, return_inverse=True)
    tri_set[has] = inverse.reshape(-1)
    return sets, tri_set


def _cluster_bounds(vis, n_clusters: int, scene_bounds):
    """(C, 3) min and max corners of each cluster's leaves (scene bounds where the visibility has no leaf boxes)."""
    lo = np.tile(np.asarray(scene_bounds[0], np.float64), (n_clusters, 1))
    hi = np.tile(np.asarray(scene_bounds[1], np.float64), (n_clusters, 1))
    bounds, leaf_cluster = getattr(vis, "leaf_bounds", None), getattr(vis, "leaf_cluster", None)
    if bounds is None or leaf_cluster is None:
        return lo, hi
    lmin, lmax = (np.asarray(b, np.float64) for b in bounds)
    lc = np.asarray(leaf_cluster, np.int64)
    ok = (lc >= 0) & (lc < n_clusters)
    cmin = np.full((n_clusters, 3), np.inf)
    cmax = np.full((n_clusters, 3), -np.inf)
    np.minimum.at(cmin, lc[ok], lmin[ok])
    np.maximum.at(cmax, lc[ok], lmax[ok])
    found = np.isfinite(cmin).all(axis=1)
    return np.where(found[:, None], cmin, lo), np.where(found[:, None], cmax, hi)


def build_table(vis, source: str, lights, n_faces: int, probe: float, symmetric: bool = True,
                scene_bounds=None) -> CullTable:
    """The light visibility table (Table 4.2) for ``lights`` under ``vis`` (None: no culling)."""
    n_lights = len(lights)
    if scene_bounds is None:
        scene_bounds = (np.full(3, -1.0), np.full(3, 1.0))
    scene_lo, scene_hi = (np.asarray(b, np.float64) for b in scene_bounds)
    scene_centre, scene_radius = 0.5 * (scene_lo + scene_hi), 0.5 * np.linalg.norm(scene_hi - scene_lo)
    if vis is None:
        row_lights = np.arange(n_lights, dtype=np.int32)
        return CullTable(source=source, n_clusters=0, symmetric=symmetric,
                         light_cluster_offsets=np.zeros(n_lights + 1, np.int64),
                         light_cluster_ids=np.zeros(0, np.int64), light_unclustered=np.ones(n_lights, bool),
                         row_offsets=np.array([0, n_lights], np.int64), row_lights=row_lights,
                         tri_row=np.zeros(n_faces, np.int64), all_row=0, row_centre=scene_centre[None],
                         row_radius=np.array([scene_radius]))
    n_clusters = int(vis.n_clusters)
    pvs = np.asarray(vis.pvs_matrix(), bool)
    if symmetric:
        pvs = pvs | pvs.T
    lc = light_clusters(vis, lights, probe)
    unclustered = np.array([len(c) == 0 for c in lc], bool)
    lmask = np.zeros((n_lights, n_clusters), np.float32)
    for li, c in enumerate(lc):
        lmask[li, c] = 1.0
    # visible[c, l]: some cluster of light l is in the PVS of cluster c.
    visible = (pvs.astype(np.float32) @ lmask.T) > 0.5
    visible[:, unclustered] = True
    sets, tri_set = _triangle_sets(vis, n_faces)
    # Merged rows: every distinct multi-cluster set of a triangle (single-cluster sets are the cluster's row).
    set_size = (sets >= 0).sum(axis=1) if len(sets) else np.zeros(0, np.int64)
    multi = np.nonzero(set_size > 1)[0]
    set_row = np.full(len(sets), -1, np.int64)
    single = np.nonzero(set_size == 1)[0]
    if len(single):
        set_row[single] = sets[single, -1]
    merged = np.zeros((len(multi), n_lights), bool)
    if len(multi):
        members = sets[multi]
        for j in range(members.shape[1]):
            col = members[:, j]
            ok = col >= 0
            merged[ok] |= visible[col[ok]]
        set_row[multi] = n_clusters + np.arange(len(multi))
    rows = np.concatenate([visible, merged, np.ones((1, n_lights), bool)])
    all_row = int(len(rows) - 1)
    r_idx, l_idx = np.nonzero(rows)
    row_offsets = np.searchsorted(r_idx, np.arange(len(rows) + 1)).astype(np.int64)
    tri_row = np.where(tri_set >= 0, set_row[np.maximum(tri_set, 0)], all_row).astype(np.int64)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in lc])]).astype(np.int64)
    ids = np.concatenate(lc).astype(np.int64) if lc else np.zeros(0, np.int64)
    # Bounds of each row's clusters (for the irradiance-proportional light choice): clusters, merged sets, all.
    cmin, cmax = _cluster_bounds(vis, n_clusters, (scene_lo, scene_hi))
    mmin, mmax = np.full((len(multi), 3), np.inf), np.full((len(multi), 3), -np.inf)
    if len(multi):
        for j in range(sets.shape[1]):
            col = sets[multi, j]
            ok = col >= 0
            mmin[ok] = np.minimum(mmin[ok], cmin[col[ok]])
            mmax[ok] = np.maximum(mmax[ok], cmax[col[ok]])
    rmin = np.concatenate([cmin, mmin, scene_lo[None]])
    rmax = np.concatenate([cmax, mmax, scene_hi[None]])
    return CullTable(source=source, n_clusters=n_clusters, symmetric=symmetric, light_cluster_offsets=offsets,
                     light_cluster_ids=ids, light_unclustered=unclustered, row_offsets=row_offsets,
                     row_lights=l_idx.astype(np.int32), tri_row=tri_row, all_row=all_row,
                     row_centre=0.5 * (rmin + rmax), row_radius=0.5 * np.linalg.norm(rmax - rmin, axis=1))


def point_rows(table: CullTable, vis, prim: np.ndarray, points: np.ndarray, normals: np.ndarray, rule: str,
               probe: float, cull: bool) -> np.ndarray:
    """(N,) the table row each shading point reads: ``all_row`` when culling is off; the hit triangle's merged
    row (rule "triangle"); the cluster of the point nudged toward the viewer, else the triangle's row ("point")."""
    prim = np.asarray(prim, np.int64)
    if not cull or vis is None or table.n_clusters == 0:
        return np.full(len(prim), table.all_row, np.int64)
    rows = table.tri_row[prim]
    if rule == "point" and len(prim):
        c = vis.cluster_of(np.asarray(points, np.float64) + probe * np.asarray(normals, np.float64)).astype(np.int64)
        rows = np.where(c >= 0, c, rows)
    return rows


def culled_lights(table: CullTable, rows: np.ndarray, n_lights: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (offsets, lights) of the lights each row does *not* hold: what culling removed (for the audit)."""
    keep = np.ones((len(rows), n_lights), bool)
    for i, r in enumerate(np.asarray(rows, np.int64)):
        keep[i, table.row(r)] = False
    r_idx, l_idx = np.nonzero(keep)
    return np.searchsorted(r_idx, np.arange(len(rows) + 1)).astype(np.int64), l_idx.astype(np.int32)
