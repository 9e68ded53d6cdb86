"""Quake III BSP reading on synthetic files: parsing, the scene built from them, and one-line rejection of
malformed or truncated files. Needs no OpenArena data (the search path is emptied); real maps are in
test_q3_maps.py."""
import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene.q3 import loader, paks
from suite.core.scene.q3.bsp import DTYPES, pack_bsp, parse_bsp, parse_entities, visdata_bytes

UNIT_M = 0.0254


def _records(name, rows):
    arr = np.zeros(len(rows), DTYPES[name])
    for i, row in enumerate(rows):
        for k, v in row.items():
            arr[i][k] = v
    return arr


def synthetic_lumps():
    """A 128 x 128 x 128 unit room cell: a floor quad (planar), a 3x3 Bezier bump (patch), one triangle (mesh),
    a billboard, and a sky quad; one cluster above the floor plane, solid below; a spawn point and a light."""
    floor = [(-64, -64, 0), (64, -64, 0), (64, 64, 0), (-64, 64, 0)]
    bump = [(x, y, 16.0 if (i, j) == (1, 1) else 0.0) for j, y in enumerate((-32, 0, 32))
            for i, x in enumerate((-32, 0, 32))]
    tri = [(-60, -60, 40), (-20, -60, 40), (-60, -20, 40)]
    flare = [(0, 0, 100)]
    sky = [(-64, -64, 128), (-64, 64, 128), (64, 64, 128), (64, -64, 128)]
    verts = floor + bump + tri + flare + sky
    normals = [(0, 0, 1)] * (4 + 9 + 3 + 1) + [(0, 0, -1)] * 4
    vertexes = _records("vertexes", [{"position": p, "normal": n, "texcoord": (p[0] / 64.0, p[1] / 64.0)}
                                     for p, n in zip(verts, normals)])
    meshverts = np.array([0, 2, 1, 0, 3, 2,  # floor, clockwise seen from above (Quake III's front winding)
                          0, 2, 1,  # the mesh triangle
                          0, 2, 1, 0, 3, 2], "<i4")  # sky
    faces = _records("faces", [
        {"shader": 0, "effect": -1, "type": 1, "vertex": 0, "n_vertexes": 4, "meshvert": 0, "n_meshverts": 6,
         "normal": (0, 0, 1)},
        {"shader": 0, "effect": -1, "type": 2, "vertex": 4, "n_vertexes": 9, "size": (3, 3), "normal": (0, 0, 1)},
        {"shader": 0, "effect": -1, "type": 3, "vertex": 13, "n_vertexes": 3, "meshvert": 6, "n_meshverts": 3},
        {"shader": 0, "effect": -1, "type": 4, "vertex": 16, "n_vertexes": 1},
        {"shader": 1, "effect": -1, "type": 1, "vertex": 17, "n_vertexes": 4, "meshvert": 9, "n_meshverts": 6,
         "normal": (0, 0, -1)},
    ])
    shaders = _records("shaders", [{"name": b"textures/test/floor", "contents": 1},
                                   {"name": b"textures/test/sky", "flags": 0x4, "contents": 1}])
    planes = _records("planes", [{"normal": (0, 0, 1), "dist": 0.0}])
    nodes = _records("nodes", [{"plane": 0, "children": (-1, -2), "mins": (-64, -64, -16), "maxs": (64, 64, 128)}])
    leafs = _records("leafs", [
        {"cluster": 0, "mins": (-64, -64, 0), "maxs": (64, 64, 128), "leafface": 0, "n_leaffaces": 4},
        {"cluster": -1, "mins": (-64, -64, -16), "maxs": (64, 64, 0)}])
    leaffaces = np.array([0, 1, 2, 4], "<i4")
    models = _records("models", [{"mins": (-64, -64, -16), "maxs": (64, 64, 128), "face": 0, "n_faces": 5}])
    entities = ('{\n"classname" "worldspawn"\n"message" "synthetic cell"\n}\n'
                '{\n"classname" "info_player_deathmatch"\n"origin" "0 -40 24"\n"angle" "90"\n}\n'
                '{\n"classname" "light"\n"origin" "0 0 64"\n"light" "300"\n"_color" "1 0.5 0.5"\n}\n')
    return {"entities": entities, "shaders": shaders, "planes": planes, "nodes": nodes, "leafs": leafs,
            "leaffaces": leaffaces, "models": models, "vertexes": vertexes, "meshverts": meshverts, "faces": faces,
            "visdata": visdata_bytes(np.ones((1, 1), bool))}


@pytest.fixture
def empty_search_path(monkeypatch, tmp_path):
    """No OpenArena archives anywhere: textures and shader scripts are missing."""
    monkeypatch.setenv("SPLITBENCH_OA_PATH", str(tmp_path / "no-paks"))
    monkeypatch.setenv("SPLITBENCH_SCENE_PATH", "")
    monkeypatch.setattr(paks, "DEFAULT_DIRS", ())
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))
    loader._scene_cache.clear()
    return tmp_path


# --- parsing ------------------------------------------------------------------------------------------

def test01_parse_synthetic_counts():
    b = parse_bsp(pack_bsp(synthetic_lumps()), "synthetic")
    assert b.face_type_counts() == {"planar": 2, "patch": 1, "mesh": 1, "billboard": 1}
    assert (len(b.vertexes), len(b.meshverts), len(b.leafs), b.n_clusters) == (21, 15, 2, 1)
    assert [e["classname"] for e in b.entities] == ["worldspawn", "info_player_deathmatch", "light"]
    assert b.shader_names == ["textures/test/floor", "textures/test/sky"]
    assert b.visdata.matrix().tolist() == [[True]]


def test02_entity_text():
    ents = parse_entities('{ "classname" "light" "light" "200" "light" "250" }\n{ "a" "b c" }')
    assert ents == [{"classname": "light", "light": "250"}, {"a": "b c"}]
    for bad in ('{ "a" "b" ', '"a" "b" }', '{ "a" }', '{ { "a" "b" } }', '{ "a" "b" } junk'):
        with pytest.raises(UserError):
            parse_entities(bad)


# --- malformed files: one clear line each ---------------------------------------------------------------

def _corrupt(edit):
    lumps = synthetic_lumps()
    edit(lumps)
    return pack_bsp(lumps)


def _set(lump, index, field, value):
    def edit(lumps):
        arr = lumps[lump].copy()
        arr[index][field] = value
        lumps[lump] = arr
    return edit


MALFORMED = {
    "bad magic": (lambda: b"VBSP" + pack_bsp(synthetic_lumps())[4:], "magic"),
    "bad version": (lambda: pack_bsp(synthetic_lumps(), version=47), "version 47"),
    "short header": (lambda: pack_bsp(synthetic_lumps())[:100], "shorter than the 144-byte header"),
    "truncated": (lambda: pack_bsp(synthetic_lumps())[:-40], "extends past the end of the file"),
    "record size": (lambda: _corrupt(lambda l: l.__setitem__("faces", l["faces"].tobytes()[:-4])),
                    "not a multiple of its 104-byte record"),
    "face vertexes": (lambda: _corrupt(_set("faces", 0, "n_vertexes", 400)), "face 0 refers to records"),
    "face shader": (lambda: _corrupt(_set("faces", 0, "shader", 9)), "face shader"),
    "meshvert": (lambda: _corrupt(lambda l: l.__setitem__("meshverts", np.array([0, 2, 9] + [0] * 12, "<i4"))),
                 "meshvert 9 is outside its 4 vertexes"),
    "meshvert count": (lambda: _corrupt(_set("faces", 0, "n_meshverts", 5)), "not a multiple of 3"),
    "patch size": (lambda: _corrupt(_set("faces", 1, "size", (2, 3))), "patch face 1 has a 2x3 control grid"),
    "leafface": (lambda: _corrupt(lambda l: l.__setitem__("leaffaces", np.array([0, 1, 2, 7], "<i4"))),
                 "leafface"),
    "leaf range": (lambda: _corrupt(_set("leafs", 0, "n_leaffaces", 9)), "leaf 0 refers to records"),
    "node child": (lambda: _corrupt(_set("nodes", 0, "children", (-1, -5))), "neither a node"),
    "node cycle": (lambda: _corrupt(_set("nodes", 0, "children", (0, -2))), "tree has a cycle"),
    "node plane": (lambda: _corrupt(_set("nodes", 0, "plane", 3)), "node plane"),
    "visdata size": (lambda: _corrupt(lambda l: l.__setitem__("visdata", np.array([5, 1], "<i4").tobytes() + b"\1")),
                     "visdata claims 5 clusters"),
    "cluster": (lambda: _corrupt(_set("leafs", 0, "cluster", 3)), "exceeds the 1 clusters"),
    "entities": (lambda: _corrupt(lambda l: l.__setitem__("entities", '{ "classname" "worldspawn" ')),
                 "entity lump"),
    "nan vertex": (lambda: _corrupt(_set("vertexes", 0, "position", (np.nan, 0, 0))), "NaN"),
    "no faces": (lambda: _corrupt(lambda l: l.__setitem__("faces", l["faces"][:0])), "no faces"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test03_malformed_files_are_rejected_with_one_line(case):
    make, phrase = MALFORMED[case]
    with pytest.raises(UserError) as err:
        parse_bsp(make(), "maps/bad.bsp")
    message = str(err.value)
    assert "\n" not in message and message.startswith("maps/bad.bsp: not a valid Quake III BSP")
    assert phrase in message


def test04_every_truncation_is_rejected():
    data = pack_bsp(synthetic_lumps())
    last_lump_end = max(int(np.frombuffer(data, "<i4", 2, 8 + 8 * i).sum()) for i in range(17))
    for cut in range(0, last_lump_end, 7):
        with pytest.raises(UserError):
            parse_bsp(data[:cut], "cut.bsp")


def test05_load_errors_are_one_line_user_errors(empty_search_path, tmp_path):
    bad = tmp_path / "bad.bsp"
    bad.write_bytes(pack_bsp(synthetic_lumps())[:300])
    for spec, phrase in ((str(bad), "extends past the end"), (str(tmp_path / "missing.bsp"), "cannot read BSP file"),
                         ("oa:aggressor", "SPLITBENCH_OA_PATH"), ("oa:", "names no map"),
                         (str(tmp_path / "x.pk3"), "does not exist")):
        with pytest.raises(UserError) as err:
            loader.load_q3(spec)
        assert phrase in str(err.value) and "\n" not in str(err.value)


# --- the scene built from a synthetic map --------------------------------------------------------------------

def test06_synthetic_scene(empty_search_path, tmp_path):
    from suite.core.scene import load

    path = tmp_path / "cell.bsp"
    path.write_bytes(pack_bsp(synthetic_lumps()))
    scene = load(str(path))
    c = scene.q3.counts
    # floor 2 + mesh 1 + patch 2 * 8 * 8 = 131 triangles; the billboard and the sky are skipped and counted.
    assert c["faces_skipped"]["billboard (type 4)"] == 1 and c["faces_skipped"]["sky"] == 1
    assert scene.num_faces == 2 + 1 + 128 and c["patch_triangles"] == 128
    # Missing texture: flat colour, counted by name.
    assert c["missing_textures"] == ["textures/test/floor"]
    assert np.allclose(scene.materials[0].albedo, 0.5)
    # Quake (x, y, z) -> (x, z, -y) * 0.0254: the floor is at y = 0, its triangles face +y (counter-clockwise).
    floor = np.nonzero(scene.q3.triangle_face == 0)[0]
    assert np.allclose(scene.face_normals()[floor], [0, 1, 0])
    assert np.allclose(scene.positions[:, 1].min(), 0.0) and np.isclose(scene.positions[:, 0].max(), 64 * UNIT_M)
    # Every triangle is wound counter-clockwise around its vertex normals.
    vn = scene.normals[scene.faces].sum(axis=1)
    assert (np.einsum("ij,ij->i", scene.face_normals(), vn) > 0).all()
    # The light entity: 300 * 7500 * pi / 63.75 * 0.0254^2 W/sr, colour normalised and decoded from sRGB.
    (light,) = scene.point_lights
    expected = 300 * 7500 * np.pi / 63.75 * UNIT_M ** 2
    assert np.allclose(light.position, np.array([0, 64, 0]) * UNIT_M)
    assert np.isclose(light.intensity[0], expected, rtol=1e-6) and light.intensity[1] < 0.25 * expected
    # Visibility: one cluster above the floor, solid below.
    vis = scene.visibility
    assert vis.cluster_of([[0, 0.5, 0], [0, -0.1, 0]]).tolist() == [0, -1]
    assert vis.triangle_cluster.tolist() == [0] * scene.num_faces
    assert vis.pvs(0).tolist() == [True] and vis.visible_triangles(0).all()
    # Camera: spawn point's floor + 50 units, looking along angle 90 (Quake +y = scene -z).
    pose = scene.camera.pose_at(0.0)
    assert np.isclose(pose.position[1], 50 * UNIT_M)
    assert np.allclose((pose.target - pose.position) / np.linalg.norm(pose.target - pose.position), [0, 0, -1])


def test07_cache_round_trip(empty_search_path, tmp_path):
    path = tmp_path / "cell.bsp"
    path.write_bytes(pack_bsp(synthetic_lumps()))
    cold = loader.load_q3(str(path))
    assert loader.last_load_stats["mode"] == "cold"
    loader._scene_cache.clear()
    warm = loader.load_q3(str(path))
    assert loader.last_load_stats["mode"] == "disk"
    for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object"):
        assert np.array_equal(getattr(cold, k), getattr(warm, k)), k
    assert np.array_equal(cold.visibility.triangle_cluster_ids, warm.visibility.triangle_cluster_ids)
    assert cold.q3.counts == warm.q3.counts
    assert [lt.intensity.tolist() for lt in cold.point_lights] == [lt.intensity.tolist() for lt in warm.point_lights]
    # Other options are another cache entry.
    loader.load_q3(str(path), patch_level=4)
    assert len(list(loader.cache_dir().glob("cell-*.npz"))) == 2


def test08_translated_scene_keeps_visibility(empty_search_path, tmp_path):
    path = tmp_path / "cell.bsp"
    path.write_bytes(pack_bsp(synthetic_lumps()))
    scene = loader.load_q3(str(path))
    moved = scene.translated((1e4, 0, -5e3))
    p = np.array([[0, 0.5, 0]])
    assert moved.visibility.cluster_of(p + [1e4, 0, -5e3]).tolist() == [0]
    smaller = scene.without_degenerate_faces(min_area=0.1)  # drops the small patch triangles (0.02 m^2)
    assert smaller.num_faces < scene.num_faces
    assert len(smaller.visibility.triangle_cluster) == smaller.num_faces == len(smaller.q3.triangle_face)
