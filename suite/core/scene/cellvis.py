"""Computed visibility for scenes without a BSP: a cell grid whose cell-to-cell PVS is sampled by rays.

``computed_visibility(scene, tracer_or_backend)`` returns a :class:`CellVisibility` with the interface of the
Quake III :class:`~suite.core.scene.q3.visibility.Q3Visibility` (``cluster_of``, ``pvs``, ``pvs_matrix``,
``triangle_cluster_offsets``/``ids``, ``triangle_cluster``, ``visible_triangles``, ``triangles_in``, ...), so
PVS-based methods run on every scene: embedded, Mitsuba, OBJ. ``visibility_for(scene)`` returns a Quake III
map's own visibility and computes one for any other scene.

* **Cells (clusters)**: the scene's bounding box (geometry at t = 0) is divided into cubes of ``cell_size_m``;
  every cube is a cluster, ``cluster_of(p)`` is the cube holding ``p`` (-1 outside the grid). Without a
  ``cell_size_m`` the size is the smallest that keeps the grid within ``max_cells`` cubes.
* **Endpoints**: each cell gets ``points_per_cell`` random points; a point is *in solid* when at least half of
  ``probe_rays`` rays from it hit geometry and every hit is a back face. Segments join *air* points (a cell with
  fewer than two keeps all its points, so inconsistent winding loses nothing).
* **PVS**: two cells see each other when some segment between an air point of one and one of the other reaches
  its end unblocked (``Tracer.occluded``; alpha-tested texels let rays through). Up to ``rays_per_pair``
  segments are tried per unordered pair, in rounds: round r traces segment r of every pair that no earlier
  segment found visible, in batches, so the cost is about ``rays_per_pair`` rays per hidden pair and one or two
  per visible pair. **Refinement**: hidden pairs within one cell of a visible pair get ``refine_rays`` more
  segments, repeated ``refine_iterations`` times on the new frontier (small openings hide there). Segments are
  symmetric, so the PVS is symmetric; a cell sees itself.
* **Conservative in the sampling sense**: a pair reported hidden had all its segments blocked, so a pair whose
  unblocked fraction of segments is ``f`` is missed with probability about ``(1 - f)^n`` for its ``n`` segments.
  A false negative (hidden here, visible under dense sampling) needs a pair that sees each other through a small
  opening. :func:`false_negative_rate` measures it against ``dense_rays`` segments per pair on a random sample of
  pairs (docs/scenes.md has the measured rates). ``dilate = k`` adds every cell within ``k`` cells (Chebyshev
  distance) of a visible one, trading false negatives for false positives.
* **Triangles**: a triangle is in every cell its surface overlaps (exact triangle-box test, separating axes);
  ``triangle_cluster`` merges them like the Quake III rule: the cell just in front of the centroid (along the
  geometric normal, a thousandth of a cell away) when it is one of the triangle's cells, else the smallest one.
* **Determinism and cache**: random numbers come from ``numpy.random.default_rng([seed, ...])`` over all pairs of
  a round, so results depend only on the scene, the parameters and the backend. Results are cached as ``.npz`` in
  ``$SPLITBENCH_CACHE/visibility/`` keyed by a SHA-256 of the geometry (positions, faces, alpha-tested
  materials' opacity maps and thresholds), the parameters, the backend name and :data:`VERSION`.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.pvs import ClusterPVS

VERSION = 1
DEFAULT_RAYS_PER_PAIR = 16
DEFAULT_MAX_CELLS = 2048
DEFAULT_POINTS_PER_CELL = 256
DEFAULT_PROBE_RAYS = 6
DEFAULT_REFINE_RAYS = 64
DEFAULT_REFINE_ITERATIONS = 4
BATCH_RAYS = 1 << 20
FRONT_PROBE_CELLS = 1e-3


@dataclass
class CellVisibility(ClusterPVS):
    """A cell grid with a sampled PVS (module docstring); the interface of ``Q3Visibility``."""

    origin: np.ndarray  # (3,) min corner of the grid
    cell_size: float
    dims: np.ndarray  # (3,) cells along x, y, z
    pvs_rows: np.ndarray  # (C, ceil(C / 8)) uint8, bit k of row c (little bit order) = c sees k
    triangle_cluster_offsets: np.ndarray  # (F + 1,) int64
    triangle_cluster_ids: np.ndarray  # (K,) int32
    triangle_cluster: np.ndarray  # (F,) int32
    params: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        self.origin = np.asarray(self.origin, np.float64).reshape(3)
        self.dims = np.asarray(self.dims, np.int64).reshape(3)
        self.offset = np.asarray(self.offset, np.float64).reshape(3)
        self.cell_size = float(self.cell_size)
        self._pvs_matrix = None

    # --- grid ---------------------------------------------------------------------------------------
    @property
    def n_clusters(self) -> int:
        return int(np.prod(self.dims))

    @property
    def num_leaves(self) -> int:
        return self.n_clusters

    @property
    def num_triangles(self) -> int:
        return int(len(self.triangle_cluster))

    @property
    def has_vis(self) -> bool:
        return True

    @property
    def leaf_cluster(self) -> np.ndarray:
        """(C,) every cell is its own cluster (the Q3Visibility leaf -> cluster map)."""
        return np.arange(self.n_clusters, dtype=np.int32)

    def cell_index(self, clusters) -> np.ndarray:
        """(N, 3) integer grid coordinates of clusters."""
        return np.stack(np.unravel_index(np.asarray(clusters, np.int64), tuple(self.dims)), axis=-1)

    def cell_bounds(self, clusters) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) min and max corners of clusters (scene coordinates)."""
        lo = self.origin + self.offset + self.cell_index(clusters) * self.cell_size
        return lo, lo + self.cell_size

    @property
    def leaf_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.cell_bounds(np.arange(self.n_clusters))

    def cluster_of(self, points) -> np.ndarray:
        """(N,) cell of each point (scene coordinates); -1 outside the grid. Vectorised."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        ijk = np.floor((p - self.origin - self.offset) / self.cell_size)
        inside = ((ijk >= 0) & (ijk < self.dims)).all(axis=1) & np.isfinite(ijk).all(axis=1)
        out = np.full(len(p), -1, np.int64)
        if inside.any():
            out[inside] = np.ravel_multi_index(tuple(ijk[inside].astype(np.int64).T), tuple(self.dims))
        return out

    leaf_of = cluster_of

    # --- storage ------------------------------------------------------------------------------------
    ARRAYS = ("origin", "dims", "pvs_rows", "triangle_cluster_offsets", "triangle_cluster_ids", "triangle_cluster")

    def to_arrays(self) -> dict:
        out = {k: getattr(self, k) for k in self.ARRAYS}
        out["meta_json"] = np.frombuffer(json.dumps({"cell_size": self.cell_size, "params": self.params,
                                                      "stats": self.stats}).encode(), np.uint8)
        return out

    @classmethod
    def from_arrays(cls, z) -> "CellVisibility":
        meta = json.loads(bytes(z["meta_json"]).decode())
        return cls(cell_size=meta["cell_size"], params=meta["params"], stats=meta["stats"],
                   **{k: np.asarray(z[k]) for k in cls.ARRAYS})


# --- grid and triangles -------------------------------------------------------------------------------

def make_grid(lo, hi, cell_size_m: float | None, max_cells: int) -> tuple[np.ndarray, float, np.ndarray]:
    """(origin, cell size, dims) of a grid of cubes covering [lo, hi], centred on it."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = np.maximum(hi - lo, 1e-6)
    if cell_size_m is None:
        cell = float(np.cbrt(np.prod(size) / max_cells))
        while np.prod(np.ceil(size / cell - 1e-9)) > max_cells:
            cell *= 1.02
    else:
        cell = float(cell_size_m)
        if not (np.isfinite(cell) and cell > 0):
            raise UserError(f"cell_size_m must be positive, got {cell_size_m}")
    dims = np.maximum(np.ceil(size / cell - 1e-9), 1).astype(np.int64)
    if np.prod(dims) > 1 << 16:
        raise UserError(f"a {cell} m cell grid over a {size.round(2).tolist()} m scene has {int(np.prod(dims))} "
                        f"cells; use a larger cell_size_m (at most 65536 cells)")
    origin = 0.5 * (lo + hi) - 0.5 * dims * cell
    return origin, cell, dims


def triangle_cells(tri: np.ndarray, origin: np.ndarray, cell: float, dims: np.ndarray,
                   chunk: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """(triangle, cell) pairs whose triangle overlaps the cell (separating-axis test), sorted by triangle."""
    tri = (np.asarray(tri, np.float64) - origin) / cell  # grid units: cell (i, j, k) is [i, i+1] x ...
    eps = 1e-9
    lo = np.clip(np.floor(tri.min(axis=1) - eps), 0, dims - 1).astype(np.int64)
    hi = np.clip(np.floor(tri.max(axis=1) + eps), 0, dims - 1).astype(np.int64)
    ext = hi - lo + 1
    n = ext.prod(axis=1)
    rows, cells = [], []
    start = 0
    F = len(tri)
    cum = np.concatenate([[0], np.cumsum(n)])
    while start < F:
        end = int(np.searchsorted(cum, cum[start] + chunk, side="right")) - 1
        end = min(max(end, start + 1), F)
        t = np.repeat(np.arange(start, end), n[start:end])
        j = np.arange(len(t)) - np.repeat(cum[start:end] - cum[start], n[start:end])
        e = ext[t]
        ijk = lo[t] + np.stack([j // (e[:, 1] * e[:, 2]), (j // e[:, 2]) % e[:, 1], j % e[:, 2]], axis=1)
        ok = _tri_box_overlap(tri[t], ijk + 0.5, 0.5 + eps)
        rows.append(t[ok])
        cells.append(np.ravel_multi_index(tuple(ijk[ok].T), tuple(dims)))
        start = end
    return np.concatenate(rows), np.concatenate(cells)


def _tri_box_overlap(tri: np.ndarray, centre: np.ndarray, half: float) -> np.ndarray:
    """Akenine-Moeller's triangle / axis-aligned box test, vectorised: (N, 3, 3) triangles, (N, 3) box centres,
    cube half-size. The boxes already overlap the triangles' bounds (the three box axes)."""
    v = tri - centre[:, None, :]
    e = [v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]]
    ok = np.ones(len(tri), bool)
    for edge in e:
        for a in range(3):
            axis = np.zeros((len(tri), 3))
            # axis = unit(a) x edge
            b, c = (a + 1) % 3, (a + 2) % 3
            axis[:, b] = -edge[:, c]
            axis[:, c] = edge[:, b]
            p = np.einsum("nvk,nk->nv", v, axis)
            r = half * np.abs(axis).sum(axis=1)
            ok &= ~((p.min(axis=1) > r) | (p.max(axis=1) < -r))
    normal = np.cross(e[0], e[1])
    d = np.einsum("nk,nk->n", normal, v[:, 0])
    r = half * np.abs(normal).sum(axis=1)
    ok &= np.abs(d) <= r
    return ok


def _merge_rule(tri: np.ndarray, offsets, ids, vis_lookup, cell: float) -> np.ndarray:
    F = len(tri)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    probe = vis_lookup(tri.mean(axis=1) + FRONT_PROBE_CELLS * cell * n)
    counts = np.diff(offsets)
    owner = np.repeat(np.arange(F), counts)
    has = np.zeros(F, bool)
    np.logical_or.at(has, owner[ids == probe[owner]], True)
    smallest = np.full(F, -1, np.int64)
    nonempty = counts > 0
    smallest[nonempty] = ids[offsets[:-1][nonempty]]
    return np.where(has, probe, smallest).astype(np.int32)


# --- PVS sampling ---------------------------------------------------------------------------------------

def air_points(tracer, face_normals: np.ndarray, origin, cell, dims, per_cell: int, probes: int, seed: int):
    """(C, per_cell, 3) sample points per cell, air points first, and (C,) how many are air.

    A point is *in solid* when at least half of ``probes`` rays from it (fixed spread directions) hit something and
    every hit is a back face (the side its geometric normal points away from): it is enclosed by geometry facing
    away from it. Other points are *air*. A cell with fewer than two air points keeps all its points, so no cell is
    left without endpoints whatever the scene's winding."""
    C = int(np.prod(dims))
    rng = np.random.default_rng([int(seed), 1 << 20])
    lo = origin + np.stack(np.unravel_index(np.arange(C), tuple(dims)), axis=1) * cell
    pts = lo[:, None, :] + rng.random((C, per_cell, 3)) * cell
    dirs = _spread_directions(probes)
    o = np.repeat(pts.reshape(-1, 3), probes, axis=0)
    d = np.tile(dirs, (C * per_cell, 1))
    hits = tracer.intersect(o.astype(np.float32), d.astype(np.float32))
    hit = hits.prim >= 0
    back = np.zeros(len(d), bool)
    back[hit] = np.einsum("ij,ij->i", face_normals[hits.prim[hit]], d[hit]) > 0
    hit, back = hit.reshape(-1, probes), back.reshape(-1, probes)
    solid = (hit.sum(axis=1) >= (probes + 1) // 2) & (back == hit).all(axis=1)
    solid = solid.reshape(C, per_cell)
    n_air = (~solid).sum(axis=1)
    order = np.argsort(solid, axis=1, kind="stable")  # air points first
    pts = np.take_along_axis(pts, order[:, :, None], axis=1)
    usable = np.where(n_air >= 2, n_air, per_cell)
    return pts, usable, {"air_points": int(n_air.sum()), "pool_points": int(C * per_cell),
                         "probe_rays": int(len(d)), "cells_without_air": int((n_air == 0).sum())}


def _spread_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread over the sphere (a Fibonacci lattice, rotated off the axes)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5 ** 0.5) * i + 0.3
    r = np.sqrt(1.0 - z * z)
    d = np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _trace_pairs(tracer, a, b, n_rays: int, seed, draw, bar=None) -> tuple[np.ndarray, int]:
    """Up to ``n_rays`` segments per pair (a[i], b[i]) in rounds with early out; returns (visible, rays traced).
    ``draw(rng_seed, cells, n)`` gives (n, 3) endpoints in ``cells``; round r's random numbers come from
    ``default_rng([*seed, r])`` over all pairs, so a pair's segments do not depend on which others remain."""
    visible = np.zeros(len(a), bool)
    remaining = np.arange(len(a))
    rays = 0
    for r in range(n_rays):
        if len(remaining) == 0:
            break
        u = np.random.default_rng([*seed, r]).random((len(a), 2), dtype=np.float64)
        for chunk in np.array_split(remaining, max(1, int(np.ceil(len(remaining) / BATCH_RAYS)))):
            p, q = draw(a[chunk], u[chunk, 0]), draw(b[chunk], u[chunk, 1])
            d = q - p
            length = np.linalg.norm(d, axis=1)
            d /= np.maximum(length, 1e-300)[:, None]
            blocked = tracer.occluded(p.astype(np.float32), d.astype(np.float32), 0.0, length.astype(np.float32))
            visible[chunk[~blocked]] = True
            rays += len(chunk)
        remaining = remaining[~visible[remaining]]
        if bar is not None:
            bar.update(1)
            bar.set_postfix(hidden_pairs=len(remaining), rays=rays)
    return visible, rays


def _sample_pvs(tracer, scene_normals, origin, cell, dims, rays_per_pair: int, seed: int, per_cell: int, probes: int,
                refine_rays: int, refine_iterations: int, show_progress: bool) -> tuple[np.ndarray, dict]:
    from suite.progress import progress

    C = int(np.prod(dims))
    pts, usable, pool_stats = air_points(tracer, scene_normals, origin, cell, dims, per_cell, probes, seed)

    def draw(cells, u):
        """A pool point of each cell: index from a uniform number (air points first, see air_points)."""
        k = np.minimum((u * usable[cells]).astype(np.int64), usable[cells] - 1)
        return pts[cells, k]

    a, b = np.triu_indices(C, k=1)
    rounds = rays_per_pair + refine_rays * refine_iterations
    bar = progress(total=rounds, desc=f"cell PVS ({C} cells, {len(a)} pairs)", unit="round") \
        if show_progress else None
    stats = dict(pool_stats)
    try:
        vis, rays = _trace_pairs(tracer, a, b, rays_per_pair, (int(seed), 0), draw, bar)
        m = np.eye(C, dtype=bool)
        m[a[vis], b[vis]] = m[b[vis], a[vis]] = True
        stats.update(pairs=int(len(a)), visible_pairs_sampled=int(vis.sum()), rays_sampling=int(rays))
        # Frontier refinement: hidden pairs next to visible ones (one cell away on either side) are where small
        # openings hide; they get refine_rays more segments, until no new pair turns visible.
        tested = np.zeros_like(m)
        refined = found = refine_total = 0
        for it in range(refine_iterations if refine_rays > 0 else 0):
            front = np.triu(dilate_pvs(m, dims, 1) & ~m & ~tested, 1)
            fa, fb = np.nonzero(front)
            tested[fa, fb] = True
            if len(fa) == 0:
                break
            v2, r2 = _trace_pairs(tracer, fa, fb, refine_rays, (int(seed), 1, it), draw, bar)
            m[fa[v2], fb[v2]] = m[fb[v2], fa[v2]] = True
            refined += len(fa)
            found += int(v2.sum())
            refine_total += r2
            if not v2.any():
                break
        stats.update(refined_pairs=int(refined), refined_found_visible=int(found), rays_refinement=int(refine_total),
                     rays=int(pool_stats["probe_rays"] + rays + refine_total),
                     visible_pairs=int((np.triu(m, 1)).sum()))
    finally:
        if bar is not None:
            bar.close()
    return m, stats


def dilate_pvs(m: np.ndarray, dims, k: int) -> np.ndarray:
    """Every cell within Chebyshev distance ``k`` of a visible cell becomes visible (rows and columns)."""
    if k <= 0:
        return m
    C = len(m)
    grid = m.reshape(C, *tuple(int(d) for d in dims))
    out = grid.copy()
    for axis in (1, 2, 3):
        acc = out.copy()
        for s in range(1, k + 1):
            for sign in (1, -1):
                shifted = np.roll(out, sign * s, axis=axis)
                idx = [slice(None)] * 4
                idx[axis] = slice(0, s) if sign > 0 else slice(-s, None)
                shifted[tuple(idx)] = False
                acc |= shifted
        out = acc
    out = out.reshape(C, C)
    return out | out.T


def _geometry_key(scene) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(scene.positions_at(0.0), np.float32).tobytes())
    h.update(np.ascontiguousarray(scene.faces, np.int32).tobytes())
    alpha = [i for i, m in enumerate(scene.materials) if m.is_alpha_tested]
    if alpha:
        h.update(np.ascontiguousarray(scene.face_material, np.int32).tobytes())
        for i in alpha:
            m = scene.materials[i]
            h.update(f"{i}|{m.alpha_threshold}".encode())
            h.update(np.ascontiguousarray(m.opacity_texture, np.float32).tobytes())
    return h.hexdigest()


def cache_dir() -> Path:
    root = os.environ.get("SPLITBENCH_CACHE") or os.path.join(os.getcwd(), "cache")
    return Path(root) / "visibility"


def computed_visibility(scene, tracer_or_backend="embree", *, cell_size_m: float | None = None,
                        rays_per_pair: int = DEFAULT_RAYS_PER_PAIR, seed: int = 0, dilate: int = 0,
                        max_cells: int = DEFAULT_MAX_CELLS, points_per_cell: int = DEFAULT_POINTS_PER_CELL,
                        probe_rays: int = DEFAULT_PROBE_RAYS, refine_rays: int = DEFAULT_REFINE_RAYS,
                        refine_iterations: int = DEFAULT_REFINE_ITERATIONS, use_cache: bool = True,
                        show_progress: bool = True) -> CellVisibility:
    """A sampled cell PVS for ``scene`` (module docstring). ``tracer_or_backend``: a tracer made for this scene,
    or a backend name for :func:`suite.core.trace.make`. Geometry is taken at t = 0."""
    if int(rays_per_pair) < 1:
        raise UserError(f"rays_per_pair must be >= 1, got {rays_per_pair}")
    if int(dilate) < 0 or int(max_cells) < 1 or int(points_per_cell) < 2 or int(probe_rays) < 1 \
            or int(refine_rays) < 0 or int(refine_iterations) < 0:
        raise UserError(f"dilate, refine_rays and refine_iterations must be >= 0, max_cells and probe_rays >= 1, "
                        f"points_per_cell >= 2 (got {dilate}, {refine_rays}, {refine_iterations}, {max_cells}, "
                        f"{probe_rays}, {points_per_cell})")
    t0 = time.perf_counter()
    tracer = tracer_or_backend
    if isinstance(tracer_or_backend, str):
        from suite.core.trace import make

        tracer = make(tracer_or_backend, scene)
    backend = getattr(tracer, "name", type(tracer).__name__)
    positions = scene.positions_at(0.0)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    origin, cell, dims = make_grid(lo, hi, cell_size_m, int(max_cells))
    params = {"cell_size_m": cell, "requested_cell_size_m": cell_size_m, "rays_per_pair": int(rays_per_pair),
              "seed": int(seed), "dilate": int(dilate), "max_cells": int(max_cells), "points_per_cell": int(points_per_cell),
              "probe_rays": int(probe_rays), "refine_rays": int(refine_rays),
              "refine_iterations": int(refine_iterations), "backend": backend}
    key = hashlib.sha256(f"{_geometry_key(scene)}|{json.dumps(params, sort_keys=True)}|v{VERSION}".encode())
    digest = key.hexdigest()
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(getattr(scene, "name", "scene")))[:40]
    path = cache_dir() / f"{stem}-{digest[:24]}.npz"
    if use_cache and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                vis = CellVisibility.from_arrays(z)
            vis.stats = dict(vis.stats, cached=True, load_s=time.perf_counter() - t0)
            return vis
        except Exception:  # a damaged or foreign cache file is recomputed
            pass

    prev_t = getattr(tracer, "_time_s", 0.0)
    if scene.object_animations:
        tracer.update(0.0)
    try:
        t1 = time.perf_counter()
        m, sample_stats = _sample_pvs(tracer, scene.face_normals(positions).astype(np.float64), origin, cell, dims,
                                      int(rays_per_pair), int(seed), int(points_per_cell), int(probe_rays),
                                      int(refine_rays), int(refine_iterations), show_progress)
        t_rays = time.perf_counter() - t1
    finally:
        if scene.object_animations:
            tracer.update(prev_t)
    m = dilate_pvs(m, dims, int(dilate))
    t2 = time.perf_counter()
    tri = positions[scene.faces].astype(np.float64)
    rows, cells = triangle_cells(tri, origin, cell, dims)
    order = np.lexsort((cells, rows))
    rows, cells = rows[order], cells[order]
    offsets = np.searchsorted(rows, np.arange(len(tri) + 1)).astype(np.int64)
    ids = cells.astype(np.int32)
    probe = CellVisibility(origin, cell, dims, np.zeros((0, 0), np.uint8), offsets, ids, np.zeros(0, np.int32))
    merged = _merge_rule(tri, offsets, ids, probe.cluster_of, cell)
    stats = {**sample_stats, "cells": int(np.prod(dims)), "dims": dims.tolist(),
             "visible_ordered_pairs": int(m.sum() - len(m)), "trace_s": round(t_rays, 3),
             "rays_per_s": round(sample_stats["rays"] / max(t_rays, 1e-9)), "triangles_s": round(time.perf_counter() - t2, 3),
             "total_s": round(time.perf_counter() - t0, 3), "triangle_cell_pairs": int(len(ids)),
             "triangles_without_cell": int((np.diff(offsets) == 0).sum()), "cached": False}
    vis = CellVisibility(origin, cell, dims, np.packbits(m, axis=1, bitorder="little"), offsets, ids, merged,
                         params=params, stats=stats)
    if use_cache:
        from suite.fileio import atomic_target

        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_target(path, suffix=".tmp.npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **vis.to_arrays())
    return vis


def visibility_for(scene, tracer_or_backend="embree", **kwargs):
    """The scene's own visibility (a Quake III map's BSP PVS) when it has one, else :func:`computed_visibility`."""
    own = getattr(scene, "visibility", None)
    if own is not None:
        return own
    return computed_visibility(scene, tracer_or_backend, **kwargs)


def false_negative_rate(vis: CellVisibility, scene, tracer_or_backend="embree", *, pairs: int = 4000,
                        dense_rays: int = 512, seed: int = 1) -> dict:
    """Measures ``vis`` against dense sampling: for ``pairs`` random unordered cell pairs, ``dense_rays`` segments
    between random points of the two cells (independent of ``vis``'s own). A pair is visible under dense sampling
    when one segment is unblocked; the false-negative rate is the fraction of those pairs that ``vis`` reports
    hidden. Dilation counts as ``vis`` reports it."""
    tracer = tracer_or_backend
    if isinstance(tracer, str):
        from suite.core.trace import make

        tracer = make(tracer, scene)
    rng = np.random.default_rng(seed)
    C = vis.n_clusters
    a = rng.integers(0, C, pairs)
    b = rng.integers(0, C, pairs)
    keep = a != b
    a, b = a[keep], b[keep]
    lo_a, _ = vis.cell_bounds(a)
    lo_b, _ = vis.cell_bounds(b)
    dense = np.zeros(len(a), bool)
    per_batch = max(1, BATCH_RAYS // dense_rays)
    for s in range(0, len(a), per_batch):
        sl = slice(s, s + per_batch)
        n = len(a[sl])
        u = rng.random((n, dense_rays, 6))
        p = lo_a[sl, None, :] + u[..., :3] * vis.cell_size
        q = lo_b[sl, None, :] + u[..., 3:] * vis.cell_size
        d = (q - p).reshape(-1, 3)
        length = np.linalg.norm(d, axis=1)
        d /= np.maximum(length, 1e-300)[:, None]
        blocked = tracer.occluded(p.reshape(-1, 3).astype(np.float32), d.astype(np.float32), 0.0,
                                  length.astype(np.float32)).reshape(n, dense_rays)
        dense[sl] = ~blocked.all(axis=1)
    m = vis.pvs_matrix()
    reported = m[a, b]
    fn = dense & ~reported
    return {"pairs": int(len(a)), "dense_rays": int(dense_rays), "dense_visible": int(dense.sum()),
            "reported_visible": int(reported.sum()), "false_negatives": int(fn.sum()),
            "false_negative_rate": float(fn.sum() / max(int(dense.sum()), 1)),
            "false_positive_pairs": int((reported & ~dense).sum())}
