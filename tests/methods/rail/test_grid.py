"""Seed 004 §3.3-3.5: the multiple-reference grid G, IDW (eq. 1-2), frustum clipping at cell granularity (§4.1)
and the ambient grid A (eq. 3, Algorithm 2, trilinear F_a)."""
import numpy as np
import pytest

from methods.rail.grid import (AmbientGrid, GridGeometry, MultiRefGrid, frustum_cells, frustum_cells_brute_force,
                               frustum_planes, idw, idw_brute_force, propagate)
from suite.core.scene.model import CameraPose


def _cloud(n=600, seed=0, extent=6.0, r=(0.4, 1.0)):
    rng = np.random.default_rng(seed)
    q = rng.random((n, 3)) * extent
    qn = rng.normal(size=(n, 3))
    qn /= np.linalg.norm(qn, axis=1, keepdims=True)
    rr = rng.uniform(*r, n)
    E = rng.random((n, 3)) * 5
    return q, qn, rr, E


def _gridded(cells: int, seed: int):
    """A random cloud in [0, 6]³, its grid G, and random query points in the same cube."""
    q, qn, rr, E = _cloud()
    geom = GridGeometry.fit(np.zeros(3), np.full(3, 6.0), cells)
    return q, qn, rr, E, geom, MultiRefGrid.build(geom, q, rr), np.random.default_rng(seed)


def test01_grid_lookup_references_exactly_the_records_whose_sphere_reaches_the_point():
    q, qn, rr, _, geom, grid, rng = _gridded(12, 1)
    p = rng.random((400, 3)) * 6
    cells = geom.cell_index(p)
    for k in range(len(p)):
        refs = set(grid.refs[grid.cell_start[cells[k]]:grid.cell_start[cells[k] + 1]].tolist())
        in_range = set(np.flatnonzero(np.linalg.norm(q - p[k], axis=1) < rr).tolist())
        assert in_range <= refs, "a record in range is missing from the point's cell"
    # every reference is a record whose sphere overlaps that cell (no cell lists a record that cannot reach it)
    owner = np.repeat(np.arange(geom.n_cells), np.diff(grid.cell_start))
    lo, hi = geom.cell_bounds(owner)
    d = np.linalg.norm(np.clip(q[grid.refs], lo, hi) - q[grid.refs], axis=1)
    assert (d < rr[grid.refs]).all()


def test02_idw_through_the_grid_equals_the_brute_force_sum_over_Q():
    q, qn, rr, E, geom, grid, rng = _gridded(10, 2)
    p = rng.random((500, 3)) * 6
    n = qn[rng.integers(0, len(q), 500)]
    for mu in (1.0, 0.5, 2.0):
        phi, wsum, visited = idw(grid, q, qn, rr, E, p, n, mu)
        ref, wref = idw_brute_force(q, qn, rr, E, p, n, mu)
        np.testing.assert_allclose(wsum, wref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(phi, ref, rtol=1e-5, atol=1e-6)
        assert (visited >= (wref > 0)).all()


def test03_zero_total_weight_gives_zero_not_nan():
    q, qn, rr, E = _cloud(n=50)
    geom = GridGeometry.fit(q.min(0), q.max(0), 6)
    grid = MultiRefGrid.build(geom, q, rr)
    p = np.array([[3.0, 3.0, 3.0], [100.0, 0.0, 0.0], q[0]])       # far from all, outside the grid, on a record
    n = np.array([[0, 0, 1.0], [0, 0, 1.0], -qn[0]])                 # the third faces away from its record
    q2, qn2 = q.copy(), qn.copy()
    q2[np.linalg.norm(q - p[0], axis=1) < 2.0] += 50.0               # nothing in range of the first point
    grid2 = MultiRefGrid.build(geom, q2, rr)
    phi, wsum, _ = idw(grid2, q2, qn2, rr, E, p[:2], n[:2])
    assert (wsum == 0).all() and np.isfinite(phi).all() and (phi == 0).all()
    qn3 = np.repeat(qn[:1], len(q), axis=0)                          # every normal equal: p faces away from all
    phi, wsum, _ = idw(grid, q, qn3, rr, E, p[2:], n[2:])
    assert wsum[0] == 0 and np.isfinite(phi).all()


def test04_memory_bound_and_actual_are_reported():
    q, qn, rr, _ = _cloud()
    geom = GridGeometry.fit(q.min(0), q.max(0), 16)
    mem = MultiRefGrid.build(geom, q, rr).memory(rr)
    expected = 8 * ((2 * rr / geom.cell_m) ** 3).sum() + 23 * len(q) + 4 * 16 ** 3
    assert mem["bound_bytes"] == pytest.approx(expected)
    assert mem["paper_layout_bytes"] == 8 * mem["refs"] + 23 * len(q) + 4 * 16 ** 3


def _pose(eye, target):
    return CameraPose(np.array(eye, float), np.array(target, float), np.array([0, 1.0, 0]))


def test05_frustum_clipping_equals_the_brute_force_corner_test_and_misses_no_visible_cell():
    geom = GridGeometry.fit(np.zeros(3), np.full(3, 10.0), 10)
    ids = np.arange(geom.n_cells)
    pose = _pose([5, 5, -2], [5, 4, 5])
    planes = frustum_planes(pose, 60.0, 16 / 9, 0.0, 1e30)
    fast = frustum_cells(geom, planes, ids)
    assert (fast == frustum_cells_brute_force(geom, planes, ids)).all()
    assert 0 < fast.sum() < len(ids)
    rng = np.random.default_rng(3)
    pts = rng.random((20000, 3)) * 10
    inside = (pts @ planes[:, :3].T + planes[:, 3] >= 0).all(axis=1)
    assert fast[geom.cell_index(pts[inside])].all(), "a cell with a point inside the frustum was clipped"


def test06_a_frustum_looking_away_from_the_grid_holds_no_cell():
    geom = GridGeometry.fit(np.zeros(3), np.full(3, 10.0), 8)
    planes = frustum_planes(_pose([5, 5, -1], [5, 5, -9]), 60.0, 16 / 9, 0.0, 1e30)
    assert not frustum_cells(geom, planes, np.arange(geom.n_cells)).any()


def test07_propagation_follows_algorithm_2_on_the_fig4_example():
    """Fig. 4: sources send only across the faces their principal normal faces (|n_axis| >= 1/√3); a cell
    that receives several contributions in one iteration averages them; cells filled by propagation have no
    normal and send in all directions in the next iteration."""
    s = 4
    flat = lambda i, j, k: (i * s + j) * s + k  # noqa: E731
    A = np.zeros((s ** 3, 3))
    defined = np.zeros(s ** 3, bool)
    normal = np.zeros((s ** 3, 3))
    a, b = flat(1, 1, 1), flat(1, 3, 1)
    A[a], A[b] = 1.0, 3.0
    defined[[a, b]] = True
    normal[a], normal[b] = [0, 1, 0], [0, -1, 0]
    A1, d1 = propagate(A, defined, normal, defined, s, 1)
    assert set(np.flatnonzero(d1)) == {a, b, flat(1, 2, 1)}
    assert A1[flat(1, 2, 1)] == pytest.approx([2.0, 2.0, 2.0])          # mean of the two contributions
    A2, d2 = propagate(A, defined, normal, defined, s, 2)
    for cell in (flat(0, 2, 1), flat(2, 2, 1), flat(1, 2, 0), flat(1, 2, 2)):
        assert d2[cell] and A2[cell] == pytest.approx([2.0, 2.0, 2.0])
    assert not d2[flat(1, 0, 1)], "the source's normal stops propagation on its back side"
    diag = normal.copy()
    diag[a] = [1 / np.sqrt(2), 1 / np.sqrt(2), 0]
    defined_a = defined.copy()
    defined_a[b] = False
    _, d = propagate(A, defined_a, diag, defined_a, s, 1)
    assert set(np.flatnonzero(d)) == {a, flat(2, 1, 1), flat(1, 2, 1)}
    _, dall = propagate(A, defined, normal, defined, s, 20)
    assert dall.all(), "enough iterations fill every empty cell"


def test08_ambient_grid_weights_by_ao_and_reports_regions_without_samples():
    geom = GridGeometry.fit(np.zeros(3), np.full(3, 4.0), 4)
    pos = np.array([[0.5, 0.5, 0.5], [0.6, 0.5, 0.5], [0.5, 0.6, 0.6]])
    nrm = np.array([[0, 1.0, 0], [0, 1.0, 0], [0, 0.9, 0.1]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ao = np.array([1.0, 0.5, 0.0])
    amb = AmbientGrid.build(geom, pos, nrm, ao)
    E = np.array([[1.0, 1, 1], [4.0, 4, 4], [100.0, 100, 100]])
    A, defined = amb.cell_values(E)
    c = geom.cell_index(pos[:1])[0]
    assert A[c] == pytest.approx([2.0, 2.0, 2.0])                        # eq. 3: (1·1 + 0.5·4) / 1.5
    assert np.dot(amb.normal[c], [0, 1, 0]) > 0.99                       # principal normal (PCA), sign kept
    assert defined.sum() == 1
    fa, found = amb.lookup(A, defined, np.array([[0.5, 0.5, 0.5], [3.5, 3.5, 3.5]]))
    assert found[0] and fa[0] == pytest.approx([2.0, 2.0, 2.0])
    assert not found[1] and (fa[1] == 0).all() and np.isfinite(fa).all()  # no sample anywhere near: 0, flagged
