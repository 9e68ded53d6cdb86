"""Bezier patch (face type 2) tessellation.

A patch is a ``width x height`` grid of control vertexes (both odd) made of ``(width-1)/2 x (height-1)/2``
biquadratic Bezier sub-patches, each on a 3x3 block of control points; neighbouring sub-patches share a row or
column of control points. Every sub-patch is sampled on a regular ``(level + 1) x (level + 1)`` grid of its
parameters (``level`` = ``DEFAULT_LEVEL`` = 8 segments per sub-patch edge, so 2 * 8 * 8 = 128 triangles per
sub-patch) and the samples of the whole patch form one vertex grid, so the vertexes on a seam between two
sub-patches are stored once.

Watertightness between separate patches as well: a point on a sub-patch edge depends only on the three control
points of that edge, and it is evaluated as ``b1 * Q1 + (b0 * Q0 + b2 * Q2)`` with Bernstein weights computed
from integers (``b0 = (L - k)^2 / L^2``, ``b1 = 2k(L - k) / L^2``, ``b2 = k^2 / L^2``). That expression is
symmetric in ``Q0``/``Q2`` and exact where the edge's weights are 0 and 1, so two patches that share an edge
(in either direction, as a row or a column) produce bit-identical vertexes along it.

Texture coordinates are interpolated with the same weights; normals are the analytic ``dP/du x dP/dv``,
oriented like the interpolated control normals, with the interpolated control normal where the derivative
vanishes (collapsed rows, e.g. the tip of a cone).
"""
from __future__ import annotations

import numpy as np

DEFAULT_LEVEL = 8


def _weights(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Bernstein weights (b0, b1, b2) and their derivatives at k / level, k = 0..level, shape (level+1, 3)."""
    k = np.arange(level + 1, dtype=np.float64)
    L = float(level)
    b = np.stack([(L - k) ** 2, 2.0 * k * (L - k), k ** 2], axis=1) / (L * L)
    db = np.stack([-2.0 * (L - k), 2.0 * (L - 2.0 * k), 2.0 * k], axis=1) / L
    return b, db


def _combine(w: np.ndarray, q0: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """``w1*q1 + (w0*q0 + w2*q2)``: symmetric under swapping (w0, q0) with (w2, q2). ``w`` (..., 3) broadcasts
    against the q's."""
    return w[..., 1:2] * q1 + (w[..., 0:1] * q0 + w[..., 2:3] * q2)


def tessellate_patch(control: np.ndarray, width: int, height: int, level: int = DEFAULT_LEVEL):
    """Tessellates one patch.

    ``control``: (width*height, C) float64 control attributes, row-major (``index = row * width + col``),
    columns ``[x, y, z, s, t, nx, ny, nz]``. Returns ``(vertexes (N, 8), triangles (T, 3) local indices)``; the
    vertex grid has ``(cols * level + 1) x (rows * level + 1)`` entries with ``cols = (width-1)/2`` and
    ``rows = (height-1)/2`` sub-patches.
    """
    ctrl = np.asarray(control, np.float64).reshape(height, width, -1)
    b, db = _weights(level)
    nu, nv = (width - 1) // 2, (height - 1) // 2
    gw, gh = nu * level + 1, nv * level + 1
    grid = np.zeros((gh, gw, ctrl.shape[2]))
    du = np.zeros((gh, gw, 3))
    dv = np.zeros((gh, gw, 3))
    for j in range(nv):  # sub-patch rows (v, along the control rows)
        for i in range(nu):  # sub-patch columns (u)
            c = ctrl[2 * j:2 * j + 3, 2 * i:2 * i + 3]  # (3 rows v, 3 cols u, C)
            # Inner sum over u for each of the three control rows: (3, level+1, C).
            rows = _combine(b[None, :, :], c[:, None, 0], c[:, None, 1], c[:, None, 2])
            rows_du = _combine(db[None, :, :], c[:, None, 0, :3], c[:, None, 1, :3], c[:, None, 2, :3])
            # Outer sum over v: (level+1 v, level+1 u, C).
            patch = _combine(b[:, None, :], rows[None, 0], rows[None, 1], rows[None, 2])
            pdu = _combine(b[:, None, :], rows_du[None, 0], rows_du[None, 1], rows_du[None, 2])
            pdv = _combine(db[:, None, :], rows[None, 0, :, :3], rows[None, 1, :, :3], rows[None, 2, :, :3])
            sl = (slice(j * level, j * level + level + 1), slice(i * level, i * level + level + 1))
            grid[sl] = patch
            du[sl] = pdu
            dv[sl] = pdv
    # The evaluation above runs the u sum first. On a seam between sub-patches both neighbours produce the same
    # bits (weights 1 and 0 on the shared control row/column), so overlapping writes agree.
    n_interp = grid[..., 5:8]
    n = np.cross(du, dv)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = length[..., 0] > 1e-9 * max(1.0, float(np.abs(ctrl[..., :3]).max()))
    n = np.where(ok[..., None], n / np.maximum(length, 1e-300), 0.0)
    flip = np.einsum("ijk,ijk->ij", n, n_interp) < 0
    n = np.where(flip[..., None], -n, n)
    ni_len = np.linalg.norm(n_interp, axis=-1, keepdims=True)
    n_interp = np.where(ni_len > 1e-12, n_interp / np.maximum(ni_len, 1e-300), 0.0)
    grid[..., 5:8] = np.where(ok[..., None], n, n_interp)
    # Two triangles per grid cell.
    idx = np.arange(gh * gw).reshape(gh, gw)
    a, bq, cq, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    tris = np.concatenate([np.stack([a, bq, cq], -1).reshape(-1, 3), np.stack([a, cq, d], -1).reshape(-1, 3)])
    return grid.reshape(-1, ctrl.shape[2]), tris


def tessellated_counts(width: int, height: int, level: int = DEFAULT_LEVEL) -> tuple[int, int]:
    """(vertexes, triangles) a patch tessellates into, before degenerate triangles are dropped."""
    nu, nv = (width - 1) // 2, (height - 1) // 2
    return (nu * level + 1) * (nv * level + 1), 2 * nu * nv * level * level
