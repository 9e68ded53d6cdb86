"""Bezier patch tessellation: exact Bezier values, shared seam vertexes between sub-patches, bit-identical
edges between separate patches sharing control points (either direction, row or column), and the same on the
patches of real OpenArena maps when the archives are installed."""
import itertools

import numpy as np
import pytest

from suite.core.scene.q3.patches import DEFAULT_LEVEL, tessellate_patch, tessellated_counts


def _control(width, height, seed):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-500, 500, (height, width, 3))
    st = rng.uniform(-4, 4, (height, width, 2))
    nrm = rng.normal(size=(height, width, 3))
    return np.concatenate([pos, st, nrm], axis=2)


def _bezier(c, u, v):
    """Biquadratic Bezier of a (3, 3, C) block at (u, v): reference formula."""
    bu = np.array([(1 - u) ** 2, 2 * u * (1 - u), u ** 2])
    bv = np.array([(1 - v) ** 2, 2 * v * (1 - v), v ** 2])
    return np.einsum("i,j,jic->c", bu, bv, c)


def test01_counts_and_exact_values():
    ctrl = _control(5, 3, 0)
    grid, tris = tessellate_patch(ctrl.reshape(-1, 8), 5, 3, level=4)
    assert (len(grid), len(tris)) == tessellated_counts(5, 3, 4) == (9 * 5, 2 * 2 * 1 * 16)
    g = grid.reshape(5, 9, 8)
    for (i, j) in [(0, 0), (3, 2), (4, 4), (8, 1)]:  # column i (u), row j (v)
        sub, k = divmod(i, 4) if i < 8 else (1, 4)
        want = _bezier(ctrl[:, 2 * sub:2 * sub + 3], k / 4, j / 4)
        assert np.allclose(g[j, i, :5], want[:5], rtol=0, atol=1e-9)


def test02_sub_patch_seams_share_vertexes():
    """Neighbouring sub-patches index the same vertex along their seam: the grid has no duplicate rows."""
    ctrl = _control(7, 5, 1)
    grid, tris = tessellate_patch(ctrl.reshape(-1, 8), 7, 5)
    L = DEFAULT_LEVEL
    assert len(grid) == (3 * L + 1) * (2 * L + 1)
    # Each interior vertex (seams included) is used by 6 triangles: the mesh is closed inside.
    uses = np.bincount(tris.reshape(-1), minlength=len(grid)).reshape(2 * L + 1, 3 * L + 1)
    assert (uses[1:-1, 1:-1] == 6).all()
    # Every interior edge is shared by exactly two triangles (no cracks, no T-junctions).
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert set(counts.tolist()) <= {1, 2}
    assert (counts == 1).sum() == 2 * (3 * L + 2 * L)  # only the patch's outline is open


@pytest.mark.parametrize("flip", ["same", "reversed", "row_to_column", "reversed_column"])
def test03_separate_patches_sharing_an_edge_are_watertight(flip):
    """Patch B reuses patch A's last control column as its first column or row, possibly reversed; both
    produce bit-identical vertexes along it."""
    a = _control(3, 5, 2)
    b = _control(5, 3, 3) if "column" in flip else _control(3, 5, 3)
    edge = a[:, -1]  # A's last column (5 points)
    if flip == "same":
        b[:, 0] = edge
    elif flip == "reversed":
        b[:, 0] = edge[::-1]
    elif flip == "row_to_column":
        b[0, :] = edge
    else:
        b[-1, :] = edge[::-1]
    ga, _ = tessellate_patch(a.reshape(-1, 8), 3, 5)
    gb, _ = tessellate_patch(b.reshape(-1, 8), b.shape[1], b.shape[0])
    L = DEFAULT_LEVEL
    ga = ga.reshape(2 * L + 1, L + 1, 8)
    gb = gb.reshape(b.shape[0] // 2 * L + 1, b.shape[1] // 2 * L + 1, 8)
    ea = ga[:, -1, :3]
    eb = {"same": gb[:, 0], "reversed": gb[::-1, 0], "row_to_column": gb[0, :], "reversed_column": gb[-1, ::-1]}[flip]
    assert np.array_equal(ea, eb[:, :3])  # bit for bit, not just close


def test04_flat_patch_stays_in_its_plane():
    xs, ys = np.meshgrid([0.0, 10.0, 30.0], [0.0, 5.0, 20.0])
    ctrl = np.zeros((3, 3, 8))
    ctrl[..., 0], ctrl[..., 1] = xs, ys
    ctrl[..., 7] = 1.0
    grid, tris = tessellate_patch(ctrl.reshape(-1, 8), 3, 3)
    assert np.all(grid[:, 2] == 0) and np.allclose(grid[:, 5:8], [0, 0, 1])


# --- real maps -----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def oa_fs():
    from suite.core.scene.q3.loader import file_system
    from suite.core.scene.q3.paks import missing_data_message

    fs = file_system()
    if not fs or not fs.maps():
        pytest.skip(missing_data_message())
    return fs


def _patch_faces(bsp):
    f = bsp.faces
    return [(i, int(f["size"][i, 0]), int(f["size"][i, 1]), int(f["vertex"][i]))
            for i in np.nonzero(f["type"] == 2)[0]]


def _boundary_edges(ctrl):
    """The four boundary control polylines of a (H, W, C) grid, as (key, vertex indexes in the tessellated
    grid order) pairs."""
    return {"top": ctrl[0, :, :3], "bottom": ctrl[-1, :, :3], "left": ctrl[:, 0, :3], "right": ctrl[:, -1, :3]}


@pytest.mark.parametrize("map_name", ["kaos", "oa_ctf2", "oa_dm3"])
def test05_real_patch_seams_are_watertight(oa_fs, map_name):
    """Every pair of patch faces of a map whose boundaries share a control polyline (in either direction)
    produces the same vertexes along it, bit for bit."""
    from suite.core.scene.q3.bsp import parse_bsp

    entry = oa_fs.find(f"maps/{map_name}.bsp")
    if entry is None:
        pytest.skip(f"maps/{map_name}.bsp is not in the installed archives")
    bsp = parse_bsp(oa_fs.read("", entry), map_name)
    v = bsp.vertexes
    attrs = np.concatenate([v["position"], v["texcoord"], v["normal"]], axis=1).astype(np.float64)
    edges = {}
    grids = {}
    for face, w, h, first in _patch_faces(bsp):
        ctrl = attrs[first:first + w * h].reshape(h, w, 8)
        grid, _ = tessellate_patch(ctrl.reshape(-1, 8), w, h)
        L = DEFAULT_LEVEL
        g = grid.reshape((h - 1) // 2 * L + 1, (w - 1) // 2 * L + 1, 8)[..., :3]
        grids[face] = {"top": g[0], "bottom": g[-1], "left": g[:, 0], "right": g[:, -1]}
        for side, poly in _boundary_edges(ctrl).items():
            edges.setdefault(poly.tobytes(), []).append((face, side, False))
            edges.setdefault(poly[::-1].copy().tobytes(), []).append((face, side, True))
    shared = 0
    for users in edges.values():
        for (fa, sa, ra), (fb, sb, rb) in itertools.combinations(users, 2):
            if fa == fb:
                continue
            pa = grids[fa][sa][::-1] if ra else grids[fa][sa]
            pb = grids[fb][sb][::-1] if rb else grids[fb][sb]
            assert np.array_equal(pa, pb), (fa, sa, fb, sb)
            shared += 1
    print(f"{map_name}: {len(grids)} patches, {shared // 2} shared patch edges, all bit-identical")
