"""Computed visibility: a cell grid whose PVS is sampled by rays, for scenes without a BSP."""
import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene import load
from suite.core.scene.cellvis import (CellVisibility, computed_visibility, dilate_pvs, false_negative_rate,
                                      triangle_cells, visibility_for)
from suite.core.scene.model import CameraKey, CameraPath, Material, PointLight, Scene

QUICK = dict(rays_per_pair=16, points_per_cell=64, show_progress=False)


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def quad(corners, normal):
    """Two triangles wound counter-clockwise around ``normal``."""
    c = np.asarray(corners, np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if np.dot(np.cross(c[1] - c[0], c[2] - c[0]), normal) < 0:
        faces = faces[:, ::-1]
    return c, np.tile(np.asarray(normal, np.float64), (4, 1)), faces


def two_rooms(door_closed: bool) -> Scene:
    """Two 4 x 3 x 4 m rooms side by side (x in [0, 4] and [4, 8]) in one closed box, joined by a doorway in the
    wall x = 4 (z in [1.5, 2.5], up to 2.2 m), optionally shut by a door panel."""
    X, Y, Z = 8.0, 3.0, 4.0
    parts = [  # (name, quad)
        ("floor", quad([[0, 0, 0], [X, 0, 0], [X, 0, Z], [0, 0, Z]], [0, 1, 0])),
        ("ceiling", quad([[0, Y, 0], [X, Y, 0], [X, Y, Z], [0, Y, Z]], [0, -1, 0])),
        ("wall_z0", quad([[0, 0, 0], [X, 0, 0], [X, Y, 0], [0, Y, 0]], [0, 0, 1])),
        ("wall_z4", quad([[0, 0, Z], [X, 0, Z], [X, Y, Z], [0, Y, Z]], [0, 0, -1])),
        ("wall_a_end", quad([[0, 0, 0], [0, Y, 0], [0, Y, Z], [0, 0, Z]], [1, 0, 0])),
        ("wall_b_end", quad([[X, 0, 0], [X, Y, 0], [X, Y, Z], [X, 0, Z]], [-1, 0, 0])),
        ("divider_1", quad([[4, 0, 0], [4, Y, 0], [4, Y, 1.5], [4, 0, 1.5]], [1, 0, 0])),
        ("divider_2", quad([[4, 0, 2.5], [4, Y, 2.5], [4, Y, Z], [4, 0, Z]], [1, 0, 0])),
        ("lintel", quad([[4, 2.2, 1.5], [4, Y, 1.5], [4, Y, 2.5], [4, 2.2, 2.5]], [1, 0, 0])),
    ]
    if door_closed:
        parts.append(("door", quad([[4, 0, 1.5], [4, 2.2, 1.5], [4, 2.2, 2.5], [4, 0, 2.5]], [1, 0, 0])))
    pos, nrm, faces, obj = [], [], [], []
    for i, (_, (p, n, f)) in enumerate(parts):
        faces.append(f + sum(len(x) for x in pos))
        pos.append(p), nrm.append(n), obj.append(np.full(len(f), i))
    cam = CameraPath([CameraKey(0.0, [1, 1.6, 2], [7, 1.6, 2])])
    F = sum(len(f) for f in faces)
    return Scene("two_rooms_" + ("closed" if door_closed else "open"), np.concatenate(pos), np.concatenate(nrm),
                 np.zeros((sum(len(p) for p in pos), 2)), np.concatenate(faces), np.zeros(F, np.int32),
                 np.concatenate(obj), [n for n, _ in parts], [Material("grey", [0.5] * 3)],
                 [PointLight("l", [2, 2.5, 2], [1, 1, 1])], cam)


def room_cells(vis, room):
    """Cells lying entirely inside room 'a' (x in [0, 4]) or 'b' (x in [4, 8])."""
    lo, hi = vis.leaf_bounds
    sel = (hi[:, 0] <= 4.0 + 1e-9) if room == "a" else (lo[:, 0] >= 4.0 - 1e-9)
    return np.nonzero(sel)[0]


def test01_closed_door_rooms_do_not_see_each_other():
    scene = two_rooms(door_closed=True)
    vis = computed_visibility(scene, "embree", cell_size_m=1.0, **QUICK)
    assert tuple(vis.dims) == (8, 3, 4) and np.allclose(vis.origin, 0.0)
    a, b = room_cells(vis, "a"), room_cells(vis, "b")
    assert len(a) == len(b) == 48
    m = vis.pvs_matrix()
    assert not m[np.ix_(a, b)].any() and not m[np.ix_(b, a)].any()
    assert m[np.ix_(a, a)].mean() > 0.9  # an empty room sees itself
    far_wall = scene.face_object == scene.object_names.index("wall_b_end")
    for c in a:
        assert not vis.visible_triangles(c)[far_wall].any()


def test02_open_door_rooms_see_each_other():
    scene = two_rooms(door_closed=False)
    vis = computed_visibility(scene, "embree", cell_size_m=1.0, **QUICK)
    m = vis.pvs_matrix()
    a, b = room_cells(vis, "a"), room_cells(vis, "b")
    assert m[np.ix_(a, b)].mean() > 0.3
    in_front = vis.cluster_of([[3.5, 1.0, 2.0]])[0]
    behind = vis.cluster_of([[4.5, 1.0, 2.0]])[0]
    assert m[in_front, behind] and m[behind, in_front]
    far_wall = scene.face_object == scene.object_names.index("wall_b_end")
    assert vis.visible_triangles(in_front)[far_wall].all()
    # Against 256 segments per pair on 1500 random pairs, few visible pairs are missed.
    fn = false_negative_rate(vis, scene, "embree", pairs=1500, dense_rays=256)
    assert fn["dense_visible"] > 500 and fn["false_negative_rate"] < 0.05
    # Dilation by one cell only adds pairs.
    dil = dilate_pvs(m, vis.dims, 1)
    assert (dil >= m).all() and dil.sum() > m.sum()


def test03_interface_matches_q3_visibility():
    from suite.core.scene.q3.visibility import Q3Visibility

    public = {n for n in dir(Q3Visibility) if not n.startswith("_")} - {"to_q3", "to_scene", "leaf_of_q3",
                                                                          "planes_normal", "planes_dist", "node_plane",
                                                                          "node_children", "leaf_area", "leaf_mins_q3",
                                                                          "leaf_maxs_q3", "unit_m", "from_arrays",
                                                                          "to_arrays", "ARRAYS", "offset"}
    assert public <= set(dir(CellVisibility))
    scene = two_rooms(door_closed=False)
    vis = computed_visibility(scene, "embree", cell_size_m=1.0, **QUICK)
    assert list(vis.cluster_of([[-1, 1, 1], [0.5, 0.5, 0.5], [7.9, 2.9, 3.9]])) == [-1, 0, vis.n_clusters - 1]
    assert not vis.pvs(-1).any() and vis.symmetry()["one_way_ordered_pairs"] == 0
    assert vis.symmetry()["diagonal_all_set"]
    # Every triangle is in the cells its surface crosses: the 8 m floor lies in the 32 bottom-row cells.
    floor = np.nonzero(scene.face_object == 0)[0]
    cells = set(np.concatenate([vis.clusters_of_triangle(i) for i in floor]).tolist())
    assert len(cells) == 32 and all(vis.cell_index([c])[0, 1] == 0 for c in cells)
    assert (vis.triangle_cluster >= 0).all()
    moved = vis.translated([10, 0, 0])
    assert moved.cluster_of([[10.5, 0.5, 0.5]])[0] == 0
    keep = np.ones(scene.num_faces, bool)
    keep[:2] = False
    assert vis.subset_triangles(keep).num_triangles == scene.num_faces - 2
    with pytest.raises(UserError, match="out of range"):
        vis.pvs(vis.n_clusters)


def test04_deterministic_and_cached(cache):
    scene = two_rooms(door_closed=False)
    v1 = computed_visibility(scene, "embree", cell_size_m=1.0, seed=3, **QUICK)
    assert v1.stats["cached"] is False and len(list((cache / "visibility").glob("*.npz"))) == 1
    v2 = computed_visibility(scene, "embree", cell_size_m=1.0, seed=3, use_cache=False, **QUICK)
    np.testing.assert_array_equal(v1.pvs_rows, v2.pvs_rows)
    v3 = computed_visibility(scene, "embree", cell_size_m=1.0, seed=3, **QUICK)
    assert v3.stats["cached"] is True
    for k in CellVisibility.ARRAYS:
        np.testing.assert_array_equal(getattr(v1, k), getattr(v3, k))
    computed_visibility(scene, "embree", cell_size_m=1.0, seed=4, **QUICK)
    assert len(list((cache / "visibility").glob("*.npz"))) == 2


def test05_triangle_box_overlap_is_exact():
    # A diagonal triangle in the plane x + y + z = 1.5 crosses the unit cube [0, 1]^3 (the plane cuts it) but not
    # the cube [1, 2] x [1, 2] x [0, 1], which its bounding box overlaps.
    tri = np.array([[[1.5, 0, 0], [0, 1.5, 0], [0, 0, 1.5]]])
    rows, cells = triangle_cells(tri, np.zeros(3), 1.0, np.array([2, 2, 2]))
    got = {tuple(np.unravel_index(c, (2, 2, 2))) for c in cells}
    assert (0, 0, 0) in got and (1, 1, 0) not in got and (1, 0, 0) in got


@pytest.mark.parametrize("spec", ["living_room", "cornell"])
def test06_runs_on_embedded_and_mitsuba_scenes(spec):
    scene = load(spec)
    vis = computed_visibility(scene, "embree", max_cells=64, **QUICK)
    assert vis.n_clusters <= 64 and vis.stats["triangles_without_cell"] == 0
    lo, hi = scene.bounds()
    c = vis.cluster_of([0.5 * (lo + hi)])[0]
    assert c >= 0 and vis.visible_triangles(c).any()


def test07_alpha_tested_grates_let_visibility_through(tmp_path, monkeypatch):
    """In the textured OBJ room a grate (alpha mask) stands at z = -1: the cells behind it stay visible."""
    from suite.core.scene.obj.samples import write_textured_room

    scene = load(str(write_textured_room(tmp_path / "room")))
    vis = computed_visibility(scene, "mitsuba-llvm", cell_size_m=1.0, **QUICK)
    front = vis.cluster_of([[0.0, 1.3, -0.5]])[0]
    behind = vis.cluster_of([[0.0, 1.3, -1.5]])[0]
    assert vis.pvs(front)[behind]


def test08_visibility_for_prefers_the_scene_own():
    import dataclasses

    own = object()
    scene = two_rooms(door_closed=True)

    @dataclasses.dataclass(eq=False)
    class WithVis(Scene):
        visibility: object = None

    assert visibility_for(WithVis(**{f.name: getattr(scene, f.name) for f in dataclasses.fields(Scene)},
                                  visibility=own)) is own
    assert isinstance(visibility_for(scene, "embree", cell_size_m=2.0, **QUICK), CellVisibility)


def test09_parameter_checks():
    scene = two_rooms(door_closed=True)
    with pytest.raises(UserError, match="rays_per_pair"):
        computed_visibility(scene, "embree", rays_per_pair=0)
    with pytest.raises(UserError, match="at most 65536 cells"):
        computed_visibility(scene, "embree", cell_size_m=0.01)
