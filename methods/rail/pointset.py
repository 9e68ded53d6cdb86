"""The offline point set Q (seed 004, RAIL §3.1; Algorithm 1 line 1).

Following Bikker and Reijerse (the paper's [6]): light tracing places dart sources on the scene's surfaces;
darts thrown from them (cosine-distributed around each source's normal) land on static geometry; a landing
point is kept when no kept point with a similar normal lies within the Poisson-disk radius (dart throwing,
not necessarily maximal, §3.1). Each record's area of effect comes from ambient occlusion: q_o is the
cosine-weighted unoccluded fraction of its hemisphere (eq. 4's integral, traced), and its range
r = r_min + (r_max − r_min) q_o, so records in corners and crevices reach less far.

Points are sorted by the cell of the reconstruction grid G that contains them (stable), which makes the order
deterministic and lets an update name a cell and then list its points' irradiance without indices (§4.1).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suite.core.gbuffer import surface_attributes
from suite.core.trace.robust import offset_ray_origin

from .grid import GridGeometry
from .lighting import cosine_directions, trace_light_paths

try:  # numba compiles the sequential Poisson-disk test; the pure-Python loop is the same algorithm
    from numba import njit
except ImportError:  # pragma: no cover
    def njit(*args, **kwargs):
        return (lambda f: f) if not (args and callable(args[0])) else args[0]

# Random sequential adsorption of disks of diameter R saturates at a coverage of 0.547: at most
# 0.547 A / (π R²/4) ≈ 0.696 A / R² points on an area A.
RSA_DENSITY = 0.696
# A kept point blocks candidates within the radius whose normals make less than ~75° with its own.
NORMAL_DOT_MIN = 0.25


@dataclass
class PointSet:
    """Q as a structure of arrays, in the deterministic order of the wire format."""

    position: np.ndarray   # (N, 3) float32
    normal: np.ndarray     # (N, 3) float32 unit
    range_m: np.ndarray    # (N,) float32 area of effect r (eq. 1)
    ao: np.ndarray         # (N,) float32 q_o, unoccluded cosine-weighted fraction (eq. 3's weight)
    face: np.ndarray       # (N,) int32
    spacing_m: float       # Poisson-disk radius
    candidates: int        # darts that landed on static geometry
    sources: int           # dart sources

    def __len__(self) -> int:
        return int(len(self.position))


@njit(cache=True)
def _poisson_accept(pos, nrm, radius, origin, inv_cell, dims, dot_min):
    """Sequential dart acceptance with a hash grid of cell size ``radius`` (27-cell neighbourhood)."""
    n = pos.shape[0]
    ncell = dims[0] * dims[1] * dims[2]
    head = np.full(ncell, -1, np.int64)
    nxt = np.full(n, -1, np.int64)
    keep = np.zeros(n, np.bool_)
    r2 = radius * radius
    for i in range(n):
        cx = int((pos[i, 0] - origin[0]) * inv_cell)
        cy = int((pos[i, 1] - origin[1]) * inv_cell)
        cz = int((pos[i, 2] - origin[2]) * inv_cell)
        ok = True
        for dx in range(-1, 2):
            x = cx + dx
            if x < 0 or x >= dims[0] or not ok:
                continue
            for dy in range(-1, 2):
                y = cy + dy
                if y < 0 or y >= dims[1] or not ok:
                    continue
                for dz in range(-1, 2):
                    z = cz + dz
                    if z < 0 or z >= dims[2]:
                        continue
                    j = head[(x * dims[1] + y) * dims[2] + z]
                    while j >= 0:
                        d0 = pos[i, 0] - pos[j, 0]
                        d1 = pos[i, 1] - pos[j, 1]
                        d2 = pos[i, 2] - pos[j, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 < r2 and (
                                nrm[i, 0] * nrm[j, 0] + nrm[i, 1] * nrm[j, 1] + nrm[i, 2] * nrm[j, 2]) > dot_min:
                            ok = False
                            break
                        j = nxt[j]
                    if not ok:
                        break
        if ok:
            keep[i] = True
            c = (cx * dims[1] + cy) * dims[2] + cz
            nxt[i] = head[c]
            head[c] = i
    return keep


def poisson_accept(pos: np.ndarray, nrm: np.ndarray, radius: float, dot_min: float = NORMAL_DOT_MIN) -> np.ndarray:
    """(N,) bool: which candidates, taken in order, are kept by the Poisson-disk test."""
    if len(pos) == 0:
        return np.zeros(0, bool)
    lo = pos.min(axis=0) - radius
    dims = np.maximum(1, np.ceil((pos.max(axis=0) + radius - lo) / radius)).astype(np.int64)
    return _poisson_accept(np.ascontiguousarray(pos, np.float64), np.ascontiguousarray(nrm, np.float64),
                           float(radius), lo.astype(np.float64), 1.0 / float(radius), dims, float(dot_min))


def static_face_mask(scene) -> np.ndarray:
    """Faces Q may sample: not on an animated object, not emissive (§3.4: dynamic objects use the ambient grid)."""
    mask = np.ones(scene.num_faces, bool)
    for anim in scene.object_animations:
        mask &= scene.face_object != anim.object_id
    mask[scene.emissive_faces()] = False
    return mask


def ambient_occlusion(points, normals, tracer, n_rays: int, distance_m: float, rng) -> np.ndarray:
    """(N,) cosine-weighted unoccluded fraction within ``distance_m`` ((1/π)∫V cos dω of eq. 4, traced)."""
    n = len(points)
    if n == 0 or n_rays <= 0:
        return np.ones(n, np.float32)
    origin = offset_ray_origin(np.repeat(points, n_rays, axis=0), np.repeat(normals, n_rays, axis=0),
                               getattr(tracer, "shift", None))
    u = rng.random((n * n_rays, 2))
    d = cosine_directions(np.repeat(np.asarray(normals, np.float64), n_rays, axis=0), u[:, 0], u[:, 1])
    occ = tracer.occluded(origin, d.astype(np.float32), 0.0, float(distance_m))
    return (1.0 - occ.reshape(n, n_rays).mean(axis=1)).astype(np.float32)


def point_spacing(scene, target_points: int, spacing_m: float = 0.0) -> float:
    """The Poisson-disk radius R: ``spacing_m`` if > 0, else the radius at which a saturated dart throw on the
    static surface area would give ``target_points``."""
    if spacing_m > 0:
        return float(spacing_m)
    area = float(scene.face_areas()[static_face_mask(scene)].sum())
    return float(np.sqrt(RSA_DENSITY * area / max(1, int(target_points))))


def generate_point_set(scene, tracer, grid: GridGeometry, *, target_points: int, spacing_m: float,
                       dart_sources: int, darts_per_source: int, source_bounces: int, ao_rays: int,
                       range_min: float, range_max: float, seed: int) -> PointSet:
    """Q for ``scene`` at t = 0 (§3.1). ``spacing_m`` = 0 derives the radius from ``target_points`` and the
    static surface area."""
    rng = np.random.default_rng([int(seed), 4004])
    static = static_face_mask(scene)
    radius = point_spacing(scene, target_points, spacing_m)
    lights = scene.lights_at(0.0)
    lpos = np.array([lt.position for lt in lights], np.float64).reshape(-1, 3)
    lint = np.array([lt.intensity for lt in lights], np.float64).reshape(-1, 3)
    area_lights = scene.area_light_triangles(0.0)
    # Dart sources: light-path vertices (§3.1, after [6, 7]).
    src = trace_light_paths(scene, tracer, 0.0, lpos, lint, int(dart_sources), int(source_bounces), rng,
                            area_lights)
    if len(src) == 0:
        empty = np.zeros((0, 3), np.float32)
        return PointSet(empty, empty, np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32),
                        radius, 0, 0)
    k = int(darts_per_source)
    shift = getattr(tracer, "shift", None)
    origin = offset_ray_origin(np.repeat(src.position, k, axis=0), np.repeat(src.normal, k, axis=0), shift)
    u = rng.random((len(origin), 2))
    direction = cosine_directions(np.repeat(src.normal, k, axis=0), u[:, 0], u[:, 1])
    hits = tracer.intersect(origin, direction.astype(np.float32))  # float64 origins: rounded in the tracing frame
    ok = hits.prim >= 0
    ok[ok] = static[hits.prim[ok]]
    p, ng, _, _, _ = surface_attributes(scene, scene.positions, scene.normals, hits.prim[ok], hits.u[ok],
                                        hits.v[ok], origin[ok], direction[ok])
    ng = np.where((np.einsum("ij,ij->i", ng, direction[ok]) > 0)[:, None], -ng, ng)
    face = hits.prim[ok].astype(np.int32)
    order = rng.permutation(len(p))          # darts in random order: no source is favoured
    p, ng, face = p[order], ng[order], face[order]
    inside = grid.cell_index(p) >= 0
    p, ng, face = p[inside], ng[inside], face[inside]
    keep = poisson_accept(p, ng, radius)
    p, ng, face = p[keep], ng[keep], face[keep]
    ao = ambient_occlusion(p, ng, tracer, int(ao_rays), range_max * radius, rng)
    rng_m = (range_min + (range_max - range_min) * ao) * radius
    p = p.astype(np.float32)   # the cell of a point is computed from the float32 position both ends hold
    order = np.argsort(grid.cell_index(p), kind="stable")
    return PointSet(p[order], ng[order].astype(np.float32), rng_m[order].astype(np.float32),
                    ao[order], face[order], radius, int(len(keep)), int(len(src)))
