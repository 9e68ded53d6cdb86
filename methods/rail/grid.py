"""Reconstruction structures of seed 004 (RAIL): the multiple-reference grid G with inverse-distance weighting
(§3.3, eq. 1-2), view-frustum clipping at cell granularity (§4.1) and the ambient grid A (§3.4-3.5, eq. 3,
Algorithm 2, trilinear F_a).

Everything is numpy on structure-of-arrays records; the brute-force forms (:func:`idw_brute_force`,
:func:`frustum_cells_brute_force`) exist for the tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

try:  # numba compiles the per-pixel IDW loop; without it the loop runs as plain Python (same results)
    from numba import njit
except ImportError:  # pragma: no cover
    def njit(*args, **kwargs):
        return (lambda f: f) if not (args and callable(args[0])) else args[0]

INV_SQRT3 = 1.0 / np.sqrt(3.0)


@dataclass(frozen=True)
class GridGeometry:
    """A cube of ``cells``³ cells of edge ``cell_m`` from ``origin`` (§3.3 and §3.4: fitted so that the scene's
    longest bounding-box edge is the cube's edge)."""

    origin: tuple
    cell_m: float
    cells: int

    @classmethod
    def fit(cls, lo, hi, cells: int) -> "GridGeometry":
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        edge = float((hi - lo).max())
        pad = 1e-3 * max(edge, 1e-6)
        edge += 2 * pad
        centre = 0.5 * (lo + hi)
        origin = centre - 0.5 * edge
        return cls(tuple(float(x) for x in origin), edge / int(cells), int(cells))

    @property
    def n_cells(self) -> int:
        return self.cells ** 3

    def ijk(self, points) -> np.ndarray:
        """(N, 3) int64 cell coordinates (may lie outside [0, cells))."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        return np.floor((p - np.asarray(self.origin)) / self.cell_m).astype(np.int64)

    def flat(self, ijk) -> np.ndarray:
        ijk = np.asarray(ijk, np.int64)
        return (ijk[..., 0] * self.cells + ijk[..., 1]) * self.cells + ijk[..., 2]

    def cell_index(self, points) -> np.ndarray:
        """(N,) flat cell id of each point, -1 outside the grid."""
        ijk = self.ijk(points)
        inside = ((ijk >= 0) & (ijk < self.cells)).all(axis=1)
        return np.where(inside, self.flat(np.clip(ijk, 0, self.cells - 1)), -1)

    def unflat(self, ids) -> np.ndarray:
        ids = np.asarray(ids, np.int64)
        c = self.cells
        return np.stack([ids // (c * c), (ids // c) % c, ids % c], axis=-1)

    def cell_bounds(self, ids) -> tuple[np.ndarray, np.ndarray]:
        lo = np.asarray(self.origin) + self.unflat(ids) * self.cell_m
        return lo, lo + self.cell_m


# --------------------------------------------------------------------------------------- multiple-reference grid

@njit(cache=True)
def _overlapped_cells(p, r, origin, cell_m, c, i, out):
    """Cells (flat ids) whose box the sphere of record i overlaps (box distance < r); returns their count."""
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = min(max(int(np.floor((p[i, a] - r[i] - origin[a]) / cell_m)), 0), c - 1)
        hi[a] = min(max(int(np.floor((p[i, a] + r[i] - origin[a]) / cell_m)), 0), c - 1)
    k = 0
    r2 = r[i] * r[i]
    for x in range(lo[0], hi[0] + 1):
        bx = origin[0] + x * cell_m
        dx = max(bx - p[i, 0], 0.0, p[i, 0] - (bx + cell_m))
        for y in range(lo[1], hi[1] + 1):
            by = origin[1] + y * cell_m
            dy = max(by - p[i, 1], 0.0, p[i, 1] - (by + cell_m))
            for z in range(lo[2], hi[2] + 1):
                bz = origin[2] + z * cell_m
                dz = max(bz - p[i, 2], 0.0, p[i, 2] - (bz + cell_m))
                if dx * dx + dy * dy + dz * dz < r2:
                    out[k] = (x * c + y) * c + z
                    k += 1
    return k


@njit(cache=True)
def _build_refs(p, r, origin, cell_m, c):
    n = p.shape[0]
    counts = np.zeros(c * c * c + 1, np.int64)
    kmax = 1
    for i in range(n):
        e = int(2.0 * r[i] / cell_m) + 2
        kmax = max(kmax, e * e * e)
    buf = np.empty(kmax, np.int64)
    for i in range(n):
        k = _overlapped_cells(p, r, origin, cell_m, c, i, buf)
        for j in range(k):
            counts[buf[j] + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    refs = np.empty(start[-1], np.int32)
    for i in range(n):           # records in ascending order: each cell's list is sorted
        k = _overlapped_cells(p, r, origin, cell_m, c, i, buf)
        for j in range(k):
            refs[fill[buf[j]]] = i
            fill[buf[j]] += 1
    return start, refs


@dataclass
class MultiRefGrid:
    """§3.3: every record is referenced from each cell its sphere of validity (radius r) overlaps, so a lookup
    examines one cell. ``cell_start`` (c³ + 1) indexes ``refs`` (record ids, ascending within a cell)."""

    geometry: GridGeometry
    cell_start: np.ndarray   # (c³ + 1,) int64
    refs: np.ndarray         # (R,) int32

    @classmethod
    def build(cls, geometry: GridGeometry, positions, ranges) -> "MultiRefGrid":
        p = np.ascontiguousarray(positions, np.float64).reshape(-1, 3)
        r = np.ascontiguousarray(ranges, np.float64).reshape(-1)
        start, refs = _build_refs(p, r, np.asarray(geometry.origin, np.float64), float(geometry.cell_m),
                                  int(geometry.cells))
        return cls(geometry, start, refs)

    def refs_per_cell(self) -> np.ndarray:
        return np.diff(self.cell_start)

    def memory(self, ranges) -> dict:
        """§3.3's space bound |Q|(8(2r/c_l)³ + 23) + 4c³ (per-record r summed) against what the grid holds, in
        the paper's layout (4-byte cell index, 8-byte reference entries, 23-byte records) and in this one."""
        r = np.asarray(ranges, np.float64)
        n = len(r)
        c3 = self.geometry.n_cells
        bound_refs = float(((2.0 * r / self.geometry.cell_m) ** 3).sum())
        return {
            "records": n, "cells": c3, "cell_m": self.geometry.cell_m, "refs": int(len(self.refs)),
            "refs_bound": bound_refs,
            "bound_bytes": 8.0 * bound_refs + 23.0 * n + 4.0 * c3,
            "paper_layout_bytes": 8 * len(self.refs) + 23 * n + 4 * c3,
            # this implementation: int64 cell starts, int32 refs; records as float32 position, normal, range,
            # irradiance (the client's cache) and the AO weight
            "actual_bytes": int(self.cell_start.nbytes + self.refs.nbytes + n * (12 + 12 + 4 + 12 + 4)),
        }


def idw_weights(p, n, q, qn, r, mu: float) -> np.ndarray:
    """Eq. 1: W(p, q) = (max(0, r − |p − q|) · max(0, p_n · q_n))^μ, elementwise over pairs."""
    d = np.linalg.norm(p - q, axis=-1)
    base = np.maximum(0.0, r - d) * np.maximum(0.0, (n * qn).sum(axis=-1))
    return np.where(base > 0, base ** mu, 0.0)


@njit(cache=True)
def _idw_kernel(p, n, cells, cell_start, refs, q, qn, r, E, mu):
    m = p.shape[0]
    phi = np.zeros((m, 3))
    wsum = np.zeros(m)
    visited = np.zeros(m, np.int64)
    for i in range(m):
        c = cells[i]
        if c < 0:
            continue
        a, b = cell_start[c], cell_start[c + 1]
        visited[i] = b - a
        for k in range(a, b):
            j = refs[k]
            d0 = p[i, 0] - q[j, 0]
            d1 = p[i, 1] - q[j, 1]
            d2 = p[i, 2] - q[j, 2]
            dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            cosn = n[i, 0] * qn[j, 0] + n[i, 1] * qn[j, 1] + n[i, 2] * qn[j, 2]
            base = max(0.0, r[j] - dist) * max(0.0, cosn)
            if base <= 0.0:
                continue
            wgt = base if mu == 1.0 else base ** mu
            wsum[i] += wgt
            phi[i, 0] += wgt * E[j, 0]
            phi[i, 1] += wgt * E[j, 1]
            phi[i, 2] += wgt * E[j, 2]
        if wsum[i] > 0.0:
            phi[i, 0] /= wsum[i]
            phi[i, 1] /= wsum[i]
            phi[i, 2] /= wsum[i]
    return phi, wsum, visited


def idw(grid: MultiRefGrid, rec_pos, rec_nrm, rec_range, irradiance, p, n, mu: float = 1.0):
    """Eq. 2 through G: Φ(p) = Σ W q_e / Σ W over the records of p's cell (one cell per lookup, §3.3).

    Returns (Φ (M, 3) float32, weight sum (M,), records visited (M,)). Where the weight sum is 0 (no record in
    range, every normal facing away, or p outside the grid) eq. 2 is 0/0: Φ is 0 there and the caller falls
    back to the ambient function (§3.4-3.5).
    """
    p = np.ascontiguousarray(p, np.float64).reshape(-1, 3)
    n = np.ascontiguousarray(n, np.float64).reshape(-1, 3)
    cells = grid.geometry.cell_index(p)
    phi, wsum, visited = _idw_kernel(p, n, cells, grid.cell_start, grid.refs,
                                     np.ascontiguousarray(rec_pos, np.float64), np.ascontiguousarray(rec_nrm, np.float64),
                                     np.ascontiguousarray(rec_range, np.float64),
                                     np.ascontiguousarray(irradiance, np.float64), float(mu))
    return phi.astype(np.float32), wsum, visited


def idw_brute_force(rec_pos, rec_nrm, rec_range, irradiance, p, n, mu: float = 1.0):
    """Eq. 2 as written: the sum over every record of Q (no grid)."""
    p = np.asarray(p, np.float64).reshape(-1, 3)
    n = np.asarray(n, np.float64).reshape(-1, 3)
    w = idw_weights(p[:, None, :], n[:, None, :], np.asarray(rec_pos, np.float64)[None],
                    np.asarray(rec_nrm, np.float64)[None], np.asarray(rec_range, np.float64)[None], mu)
    wsum = w.sum(axis=1)
    num = w @ np.asarray(irradiance, np.float64)
    phi = np.where(wsum[:, None] > 0, num / np.where(wsum > 0, wsum, 1.0)[:, None], 0.0)
    return phi, wsum


# ---------------------------------------------------------------------------------------------- frustum clipping

def frustum_planes(pose, fov_deg: float, aspect: float, near_m: float, far_m: float) -> np.ndarray:
    """(6, 4) planes (n, d) with n · x + d >= 0 inside: near, far, left, right, bottom, top. ``fov_deg`` is
    horizontal, ``aspect`` = width / height."""
    f, r, u = pose.basis()
    eye = np.asarray(pose.position, np.float64)
    th = np.tan(np.radians(fov_deg) / 2.0)
    tv = th / aspect
    normals = [f, -f, th * f + r, th * f - r, tv * f + u, tv * f - u]
    normals = [v / np.linalg.norm(v) for v in normals]
    d = [-(f @ eye) - near_m, (f @ eye) + far_m] + [-(v @ eye) for v in normals[2:]]
    return np.column_stack([np.array(normals), np.array(d)])


def frustum_cells(geometry: GridGeometry, planes: np.ndarray, cell_ids) -> np.ndarray:
    """(K,) bool: which cells intersect the frustum, conservatively (a cell is out only when one plane has all
    of it outside: the positive-vertex test)."""
    lo, hi = geometry.cell_bounds(cell_ids)
    inside = np.ones(len(lo), bool)
    for nrm, d in zip(planes[:, :3], planes[:, 3]):
        pv = np.where(nrm > 0, hi, lo)
        inside &= pv @ nrm + d >= 0
    return inside


def frustum_cells_brute_force(geometry: GridGeometry, planes: np.ndarray, cell_ids) -> np.ndarray:
    """The same decision from all 8 corners of every cell, one plane and one corner at a time."""
    lo, hi = geometry.cell_bounds(cell_ids)
    out = np.ones(len(lo), bool)
    for k in range(len(lo)):
        for nrm, d in zip(planes[:, :3], planes[:, 3]):
            corners = [np.array([(hi if (b >> a) & 1 else lo)[k][a] for a in range(3)]) for b in range(8)]
            if all(float(c @ nrm + d) < 0 for c in corners):
                out[k] = False
                break
    return out


# ----------------------------------------------------------------------------------------------- ambient grid A

@dataclass
class AmbientGrid:
    """§3.4: a coarse cube of ``subdivisions``³ cells; per cell the AO-weighted mean irradiance A_e of the
    records inside (eq. 3), the principal normal A_n (PCA of their normals) and, filled at run time, the
    propagated values of empty cells (Algorithm 2)."""

    geometry: GridGeometry
    point_cell: np.ndarray   # (N,) flat cell of each record (-1 outside)
    weight: np.ndarray       # (N,) q_o
    normal: np.ndarray       # (s³, 3) principal normal A_n (0 where the cell has no record)
    has_normal: np.ndarray   # (s³,) bool

    @classmethod
    def build(cls, geometry: GridGeometry, positions, normals, ao) -> "AmbientGrid":
        cell = geometry.cell_index(positions)
        nrm = np.asarray(normals, np.float64).reshape(-1, 3)
        n_cells = geometry.n_cells
        ok = cell >= 0
        cov = np.zeros((n_cells, 3, 3))
        summed = np.zeros((n_cells, 3))
        for a in range(3):
            summed[:, a] = np.bincount(cell[ok], weights=nrm[ok, a], minlength=n_cells)
            for b in range(3):
                cov[:, a, b] = np.bincount(cell[ok], weights=nrm[ok, a] * nrm[ok, b], minlength=n_cells)
        has = np.bincount(cell[ok], minlength=n_cells) > 0
        principal = np.zeros((n_cells, 3))
        if has.any():
            _, vecs = np.linalg.eigh(cov[has])
            v = vecs[:, :, -1]                                   # eigenvector of the largest eigenvalue
            flip = np.einsum("ij,ij->i", v, summed[has]) < 0
            v[flip] *= -1.0
            principal[has] = v
        return cls(geometry, cell, np.asarray(ao, np.float64).reshape(-1), principal, has)

    def cell_values(self, irradiance) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 3: A_e = Σ q_o q_e / Σ q_o per cell; (A_e (s³, 3), defined (s³,))."""
        n_cells = self.geometry.n_cells
        ok = self.point_cell >= 0
        E = np.asarray(irradiance, np.float64)
        wsum = np.bincount(self.point_cell[ok], weights=self.weight[ok], minlength=n_cells)
        A = np.zeros((n_cells, 3))
        for ch in range(3):
            A[:, ch] = np.bincount(self.point_cell[ok], weights=self.weight[ok] * E[ok, ch], minlength=n_cells)
        defined = wsum > 0
        A[defined] /= wsum[defined, None]
        return A, defined

    def values(self, irradiance, iterations: int) -> tuple[np.ndarray, np.ndarray]:
        A, defined = self.cell_values(irradiance)
        return propagate(A, defined, self.normal, self.has_normal & defined, self.geometry.cells, iterations)

    def lookup(self, A, defined, points) -> tuple[np.ndarray, np.ndarray]:
        """F_a(A, p): trilinear interpolation between the centres of the 8 nearest cells (§3.5), over the
        defined ones only (renormalised). Returns (F_a (M, 3), found (M,)); found is False where none of the 8
        cells has a value (then F_a = 0)."""
        s = self.geometry.cells
        g = (np.asarray(points, np.float64).reshape(-1, 3) - np.asarray(self.geometry.origin)) \
            / self.geometry.cell_m - 0.5
        i0 = np.floor(g).astype(np.int64)
        f = g - i0
        num = np.zeros((len(g), 3))
        den = np.zeros(len(g))
        for b in range(8):
            o = np.array([(b >> 2) & 1, (b >> 1) & 1, b & 1])
            idx = i0 + o
            w = np.prod(np.where(o == 1, f, 1.0 - f), axis=1)
            inside = ((idx >= 0) & (idx < s)).all(axis=1)
            flat = self.geometry.flat(np.clip(idx, 0, s - 1))
            w = w * inside * defined[flat]
            num += w[:, None] * A[flat]
            den += w
        found = den > 0
        out = np.zeros_like(num)
        out[found] = num[found] / den[found, None]
        return out.astype(np.float32), found


def propagate(A, defined, normal, has_normal, cells: int, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Algorithm 2: fills empty cells from their non-empty face neighbours, ``iterations`` times.

    A source cell with a principal normal n sends its value across the faces whose axis component satisfies
    |n_axis| >= 1/√3, on the side of sgn(n_axis) (FilterNeighbours); a source without a normal (a cell filled by
    propagation) sends across all six faces (Fig. 4's caption). A_c counts the contributions one iteration
    brings to a cell, and the cell takes their mean; cells filled in an iteration are sources in the next.
    (The pseudo-code initialises A_c to 1 and divides every cell by it after every iteration, which would average
    each contribution with a zero and shrink filled cells again in later iterations; the text's "the propagated
    contributions are averaged" is what is implemented.)
    """
    s = int(cells)
    A = np.asarray(A, np.float64).reshape(s, s, s, 3).copy()
    defined = np.asarray(defined, bool).reshape(s, s, s).copy()
    n = np.asarray(normal, np.float64).reshape(s, s, s, 3)
    has_n = np.asarray(has_normal, bool).reshape(s, s, s).copy()
    thr = INV_SQRT3 - 1e-9
    for _ in range(int(iterations)):
        total = np.zeros_like(A)
        count = np.zeros(defined.shape)
        for axis in range(3):
            comp = n[..., axis]
            for sign in (1, -1):
                send = defined & (~has_n | ((np.abs(comp) >= thr) & (np.sign(comp) == sign)))
                src = [slice(None)] * 3
                dst = [slice(None)] * 3
                if sign > 0:
                    src[axis], dst[axis] = slice(0, s - 1), slice(1, s)
                else:
                    src[axis], dst[axis] = slice(1, s), slice(0, s - 1)
                m = send[tuple(src)]
                total[tuple(dst)] += np.where(m[..., None], A[tuple(src)], 0.0)
                count[tuple(dst)] += m
        new = (count > 0) & ~defined
        if not new.any():
            break
        A[new] = total[new] / count[new][:, None]
        defined |= new
    return A.reshape(-1, 3), defined.reshape(-1)
