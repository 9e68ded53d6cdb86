"""Quake III visibility: BSP tree point lookup, cluster PVS, clusters of triangles.

Everything is exposed in scene coordinates (metres, y up); the class keeps the transform to Quake units and
does its lookups there, exactly as the engine does (``CM_PointLeafnum``: at each node go to child 0 when
``dot(p, normal) - dist >= 0``, else child 1; a negative child ``c`` is leaf ``-(c + 1)``). Leaves whose
cluster is -1 are solid or outside the level.

PVS: ``pvs(c)[k]`` is bit ``k`` of cluster ``c``'s row of the visdata, as stored (q3map2 does not make it
symmetric, so ``pvs(a)[b]`` may differ from ``pvs(b)[a]``). A map without visdata sees everything.

Clusters of a triangle: the BSP lists, per leaf, the faces it touches (leaffaces). A triangle of a world face
is in the clusters of those of its face's leaves whose bounds (grown by ``LEAF_EPSILON_UNITS``) overlap the
triangle's bounds; when none overlaps, all of the face's clusters are kept. Triangles of brush entities
(doors, platforms; not in any leaf list) get the clusters of every leaf whose bounds overlap theirs. These
are stored as a CSR list (``triangle_cluster_offsets``, ``triangle_cluster_ids``).

Merge rule for one cluster per triangle (``triangle_cluster``): the cluster of the point one unit in front of
the triangle's centroid along its geometric normal, if that cluster is among the triangle's clusters;
otherwise the smallest of the triangle's clusters; -1 for a triangle in no cluster.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from suite.core.scene.pvs import ClusterPVS

LEAF_EPSILON_UNITS = 1.0

# Quake (x, y, z; z up) -> suite (x, z, -y; y up): a proper rotation, so windings and handedness are kept.
Q3_TO_SCENE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class Q3Visibility(ClusterPVS):
    """Leaves, BSP tree and PVS of a Quake III map, in scene coordinates.

    ``unit_m`` is the length of one Quake unit in scene units; ``offset`` a translation applied after the
    axis change and scale (non-zero only for a translated scene).
    """

    planes_normal: np.ndarray  # (P, 3) float64, Quake coordinates
    planes_dist: np.ndarray  # (P,)
    node_plane: np.ndarray  # (N,) int32
    node_children: np.ndarray  # (N, 2) int32
    leaf_cluster: np.ndarray  # (L,) int32, -1 = solid / outside
    leaf_area: np.ndarray  # (L,) int32
    leaf_mins_q3: np.ndarray  # (L, 3) Quake units
    leaf_maxs_q3: np.ndarray
    pvs_rows: np.ndarray | None  # (C, row_bytes) uint8 as stored, or None (no visdata: all visible)
    n_clusters: int
    triangle_cluster_offsets: np.ndarray  # (F + 1,) int64
    triangle_cluster_ids: np.ndarray  # (K,) int32
    triangle_cluster: np.ndarray  # (F,) int32, merge rule in the module docstring
    unit_m: float = 0.0254
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        self.offset = np.asarray(self.offset, np.float64).reshape(3)
        self._pvs_matrix = None

    # --- coordinates ----------------------------------------------------------------------------
    def to_scene(self, points_q3) -> np.ndarray:
        p = np.asarray(points_q3, np.float64)
        return p @ Q3_TO_SCENE.T * self.unit_m + self.offset

    def to_q3(self, points) -> np.ndarray:
        p = np.asarray(points, np.float64)
        return ((p - self.offset) / self.unit_m) @ Q3_TO_SCENE

    @property
    def leaf_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(L, 3) min and max corners of every leaf in scene coordinates."""
        a, b = self.to_scene(self.leaf_mins_q3), self.to_scene(self.leaf_maxs_q3)
        return np.minimum(a, b), np.maximum(a, b)

    @property
    def num_leaves(self) -> int:
        return int(len(self.leaf_cluster))

    @property
    def num_triangles(self) -> int:
        return int(len(self.triangle_cluster))

    # --- point queries --------------------------------------------------------------------------
    def leaf_of(self, points) -> np.ndarray:
        """(N,) leaf index of each point (scene coordinates), vectorised over points."""
        q = self.to_q3(np.asarray(points, np.float64).reshape(-1, 3))
        return self.leaf_of_q3(q)

    def leaf_of_q3(self, q: np.ndarray) -> np.ndarray:
        n = len(q)
        if len(self.node_plane) == 0:
            return np.zeros(n, np.int64)
        node = np.zeros(n, np.int64)
        active = np.arange(n)
        # Child nodes always come after their parent (validated), so this ends within len(nodes) steps.
        for _ in range(len(self.node_plane) + 1):
            if len(active) == 0:
                break
            cur = node[active]
            plane = self.node_plane[cur]
            d = np.einsum("ij,ij->i", q[active], self.planes_normal[plane]) - self.planes_dist[plane]
            child = np.where(d >= 0, self.node_children[cur, 0], self.node_children[cur, 1])
            node[active] = child
            active = active[child >= 0]
        return -(node + 1)

    def cluster_of(self, points) -> np.ndarray:
        """(N,) cluster of each point; -1 inside solid or outside the level."""
        return self.leaf_cluster[self.leaf_of(points)].astype(np.int64)

    # --- PVS --------------------------------------------------------------------------------------
    @property
    def has_vis(self) -> bool:
        return self.pvs_rows is not None

    # --- storage ------------------------------------------------------------------------------------
    ARRAYS = ("planes_normal", "planes_dist", "node_plane", "node_children", "leaf_cluster", "leaf_area",
              "leaf_mins_q3", "leaf_maxs_q3", "triangle_cluster_offsets", "triangle_cluster_ids", "triangle_cluster")

    def to_arrays(self, prefix: str = "vis_") -> dict[str, np.ndarray]:
        out = {prefix + k: getattr(self, k) for k in self.ARRAYS}
        out[prefix + "pvs_rows"] = self.pvs_rows if self.pvs_rows is not None else np.zeros((0, 0), np.uint8)
        out[prefix + "meta"] = np.array([self.n_clusters, int(self.pvs_rows is not None)], np.int64)
        out[prefix + "unit_m"] = np.array([self.unit_m], np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "vis_") -> "Q3Visibility":
        n_clusters, has_vis = (int(x) for x in arrays[prefix + "meta"])
        kw = {k: np.asarray(arrays[prefix + k]) for k in cls.ARRAYS}
        return cls(pvs_rows=np.asarray(arrays[prefix + "pvs_rows"]) if has_vis else None, n_clusters=n_clusters,
                   unit_m=float(arrays[prefix + "unit_m"][0]), **kw)


def triangle_clusters(bsp, tri_face: np.ndarray, tri_q3: np.ndarray, vis_lookup) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray]:
    """Cluster lists and merged cluster per triangle (see the module docstring).

    ``tri_face`` (F,) BSP face of each triangle; ``tri_q3`` (F, 3, 3) its corners in Quake units;
    ``vis_lookup(points_q3) -> leaf index``.
    """
    leafs = bsp.leafs
    n_faces = len(bsp.faces)
    F = len(tri_face)
    lmin = leafs["mins"].astype(np.float64) - LEAF_EPSILON_UNITS
    lmax = leafs["maxs"].astype(np.float64) + LEAF_EPSILON_UNITS
    tmin, tmax = tri_q3.min(axis=1), tri_q3.max(axis=1)

    # (face, leaf) pairs from the leaffaces lists, leaves with a cluster only.
    from suite.core.scene.q3.bsp import gather_ranges

    has_cluster = leafs["cluster"] >= 0
    leaf_ids = np.nonzero(has_cluster & (leafs["n_leaffaces"] > 0))[0]
    pair_leaf = np.repeat(leaf_ids, leafs["n_leaffaces"][leaf_ids])
    pair_face = gather_ranges(bsp.leaffaces, leafs["leafface"][leaf_ids], leafs["n_leaffaces"][leaf_ids])
    order = np.lexsort((pair_leaf, pair_face))
    pair_leaf, pair_face = pair_leaf[order], pair_face[order]
    face_start = np.searchsorted(pair_face, np.arange(n_faces + 1))

    # Triangles x their face's leaves.
    tf = np.asarray(tri_face, np.int64)
    in_world = tf >= 0
    n_per_tri = np.where(in_world, face_start[np.clip(tf + 1, 0, n_faces)] - face_start[np.clip(tf, 0, n_faces)], 0)
    tri_rep = np.repeat(np.arange(F), n_per_tri)
    pair_idx = gather_ranges(np.arange(len(pair_leaf)), face_start[np.clip(tf, 0, n_faces)][n_per_tri > 0],
                             n_per_tri[n_per_tri > 0])
    cand_leaf = pair_leaf[pair_idx]
    overlap = ((tmin[tri_rep] <= lmax[cand_leaf]) & (tmax[tri_rep] >= lmin[cand_leaf])).all(axis=1)
    # Triangles whose face's leaves none overlaps keep all of them.
    any_overlap = np.zeros(F, bool)
    np.logical_or.at(any_overlap, tri_rep[overlap], True)
    keep = overlap | ~any_overlap[tri_rep]
    rows, cl = tri_rep[keep], leafs["cluster"][cand_leaf[keep]].astype(np.int64)

    # Triangles of brush entities (not in leaf lists): every cluster leaf their bounds overlap.
    others = np.nonzero(~in_world | (n_per_tri == 0))[0]
    if len(others):
        lid = np.nonzero(has_cluster)[0]
        extra_rows, extra_cl = [], []
        for chunk in np.array_split(others, max(1, len(others) // 256 + 1)):
            ov = ((tmin[chunk, None, :] <= lmax[None, lid]) & (tmax[chunk, None, :] >= lmin[None, lid])).all(axis=2)
            r, c = np.nonzero(ov)
            extra_rows.append(chunk[r])
            extra_cl.append(leafs["cluster"][lid[c]].astype(np.int64))
        rows = np.concatenate([rows] + extra_rows)
        cl = np.concatenate([cl] + extra_cl)

    # Unique (triangle, cluster) pairs as CSR.
    key = np.unique(rows * (bsp.n_clusters + 1) + cl)
    rows, cl = key // (bsp.n_clusters + 1), key % (bsp.n_clusters + 1)
    offsets = np.searchsorted(rows, np.arange(F + 1)).astype(np.int64)
    ids = cl.astype(np.int32)

    # Merge rule: the cluster one unit in front of the centroid, if listed; else the smallest listed.
    e1, e2 = tri_q3[:, 1] - tri_q3[:, 0], tri_q3[:, 2] - tri_q3[:, 0]
    n = np.cross(e1, e2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    probe = tri_q3.mean(axis=1) + n
    probe_cluster = leafs["cluster"][vis_lookup(probe)].astype(np.int64)
    counts = np.diff(offsets)
    owner = np.repeat(np.arange(F), counts)
    match = ids == probe_cluster[owner]
    has_match = np.zeros(F, bool)
    np.logical_or.at(has_match, owner[match], True)
    smallest = np.full(F, -1, np.int64)
    nonempty = counts > 0
    smallest[nonempty] = ids[offsets[:-1][nonempty]]  # ids are sorted within a row
    merged = np.where(has_match, probe_cluster, smallest).astype(np.int32)
    return offsets, ids, merged
