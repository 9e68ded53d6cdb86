"""What every cluster visibility shares (a BSP's, :class:`suite.core.scene.q3.Q3Visibility`, and the computed
one, :class:`suite.core.scene.cellvis.CellVisibility`): the PVS as packed bit rows, and triangles by cluster.

A subclass provides ``n_clusters``, ``num_triangles``, ``pvs_rows`` ((C, ceil(C/8)) uint8,
little-endian bit order, or None when every cluster sees every other), ``triangle_cluster_offsets`` and
``triangle_cluster_ids`` (CSR lists of the clusters each triangle is in), ``triangle_cluster`` (one per triangle)
and ``offset`` (the scene-frame translation), is a dataclass, and sets ``self._pvs_matrix = None``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from suite.errors import UserError


class ClusterPVS:
    def translated(self, offset):
        """The same visibility for the scene moved by ``offset``."""
        return dataclasses.replace(self, offset=self.offset + np.asarray(offset, np.float64).reshape(3))

    def subset_triangles(self, keep: np.ndarray):
        """The same visibility for a scene that kept only the triangles where ``keep`` is True."""
        keep = np.asarray(keep, bool)
        counts = np.diff(self.triangle_cluster_offsets)
        owner = np.repeat(np.arange(len(counts)), counts)
        ids = self.triangle_cluster_ids[keep[owner]]
        offsets = np.concatenate([[0], np.cumsum(counts[keep])]).astype(np.int64)
        return dataclasses.replace(self, triangle_cluster_offsets=offsets, triangle_cluster_ids=ids,
                                   triangle_cluster=self.triangle_cluster[keep])

    def pvs(self, cluster: int) -> np.ndarray:
        """(C,) bool: clusters potentially visible from ``cluster`` (the stored row; all False for -1, all True
        without stored rows)."""
        c = int(cluster)
        if c < 0:
            return np.zeros(self.n_clusters, bool)
        if c >= self.n_clusters:
            raise UserError(f"cluster {c} is out of range 0..{self.n_clusters - 1}")
        if self.pvs_rows is None:
            return np.ones(self.n_clusters, bool)
        return np.unpackbits(self.pvs_rows[c], bitorder="little")[:self.n_clusters].astype(bool)

    def pvs_matrix(self) -> np.ndarray:
        """(C, C) bool, row c = ``pvs(c)``."""
        if self._pvs_matrix is None:
            if self.pvs_rows is None:
                self._pvs_matrix = np.ones((self.n_clusters, self.n_clusters), bool)
            else:
                bits = np.unpackbits(self.pvs_rows, axis=1, bitorder="little")
                self._pvs_matrix = bits[:, :self.n_clusters].astype(bool)
        return self._pvs_matrix

    def symmetry(self) -> dict:
        """How far the PVS is from symmetric: pairs (a, b), a != b, with exactly one direction set."""
        m = self.pvs_matrix()
        off = ~np.eye(len(m), dtype=bool)
        visible_pairs = int((m & off).sum())
        one_way = int(((m != m.T) & off).sum())
        return {"clusters": int(len(m)), "visible_ordered_pairs": visible_pairs, "one_way_ordered_pairs": one_way,
                "one_way_fraction": one_way / max(visible_pairs, 1), "diagonal_all_set": bool(np.diag(m).all())}

    def clusters_of_triangle(self, i: int) -> np.ndarray:
        a, b = self.triangle_cluster_offsets[i], self.triangle_cluster_offsets[i + 1]
        return self.triangle_cluster_ids[a:b]

    def triangles_in(self, clusters) -> np.ndarray:
        """(F,) bool: triangles in at least one of ``clusters`` (a cluster id list or a (C,) bool mask)."""
        mask = np.asarray(clusters)
        if mask.dtype != bool:
            sel = np.zeros(self.n_clusters, bool)
            sel[np.asarray(clusters, np.int64).reshape(-1)] = True
            mask = sel
        owner = np.repeat(np.arange(self.num_triangles), np.diff(self.triangle_cluster_offsets))
        out = np.zeros(self.num_triangles, bool)
        out[owner[mask[self.triangle_cluster_ids]]] = True
        return out

    def visible_triangles(self, cluster: int) -> np.ndarray:
        """(F,) bool: triangles in the PVS of ``cluster`` (what would be drawn from there before frustum
        culling). From cluster -1 (inside a wall, outside the scene) nothing is visible."""
        return self.triangles_in(self.pvs(cluster))
