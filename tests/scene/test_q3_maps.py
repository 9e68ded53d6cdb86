"""Real OpenArena maps (Debian's openarena-* packages; scripts/setup.sh installs them as root). Skipped with the
fix named when the archives are not installed.

Checks: parse counts against the independent reader bsp_tool, point -> cluster lookups against leaf bounds,
PVS rows against bsp_tool's, clusters of triangles against the leaf face lists, the loaded scenes' counts,
the on-disk cache, camera paths inside the level, rejection of truncated / corrupted real files, spec
resolution, and one rendered view."""
import collections
import math
import time
import zipfile

import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene.q3 import list_q3_scenes, loader, paks
from suite.core.scene.q3.bsp import parse_bsp
from suite.core.scene.q3.camera import check_path, ray_hits

# (map, archive): both versions of aggressor (0.8.8 overrides 0.8.1), kaos (0.8.1 only), oa_ctf2 (0.8.8).
VERSIONS = [("aggressor", "pak1-maps.pk3"), ("aggressor", "pak6-patch088.pk3"), ("kaos", "pak1-maps.pk3"),
            ("oa_ctf2", "pak6-patch088.pk3")]
# What the files hold (cross-checked against bsp_tool in test01).
EXPECTED = {"oa:aggressor@pak1-maps": {"light_entities": 84, "clusters": 330, "spots": 47},
            "oa:aggressor": {"light_entities": 0, "clusters": 402, "spots": 0},
            "oa:kaos": {"light_entities": 30, "clusters": 931, "spots": 0},
            "oa:oa_ctf2": {"light_entities": 48, "clusters": 300, "spots": 0}}


@pytest.fixture(scope="module")
def fs():
    fs = loader.file_system()
    if not fs or not fs.maps():
        pytest.skip(paks.missing_data_message())
    return fs


def _bytes(fs, name, pak):
    versions = [e for e in fs.versions(f"maps/{name}.bsp") if e.pak.endswith(pak)]
    if not versions:
        pytest.skip(f"maps/{name}.bsp is not in {pak}")
    return fs.read("", versions[-1])


@pytest.fixture(scope="module")
def scenes(fs, tmp_path_factory):
    cache = tmp_path_factory.mktemp("q3cache")
    mp = pytest.MonkeyPatch()
    mp.setenv("SPLITBENCH_CACHE", str(cache))
    loader._scene_cache.clear()
    out, times = {}, {}
    try:
        for spec in EXPECTED:
            t0 = time.perf_counter()
            out[spec] = loader.load_q3(spec)
            times[spec] = (time.perf_counter() - t0, loader.last_load_stats["mode"])
        yield out, times, cache
    finally:
        mp.undo()
        loader._scene_cache.clear()


# --- against bsp_tool ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name,pak", VERSIONS, ids=[f"{m}@{p[:-4]}" for m, p in VERSIONS])
def test01_parse_counts_match_bsp_tool(fs, name, pak):
    bsp_tool = pytest.importorskip("bsp_tool")
    from bsp_tool.branches.id_software import quake3

    data = _bytes(fs, name, pak)
    ours = parse_bsp(data, name)
    ref = bsp_tool.IdTechBsp.from_bytes(quake3, f"{name}.bsp", data)
    assert ref.loading_errors == {}
    types = collections.Counter(int(f.type.value) for f in ref.FACES)
    assert dict(collections.Counter(ours.faces["type"].tolist())) == dict(types)
    pairs = {"vertexes": ref.VERTICES, "meshverts": ref.INDICES, "leafs": ref.LEAVES, "leaffaces": ref.LEAF_FACES,
             "nodes": ref.NODES, "planes": ref.PLANES, "models": ref.MODELS, "shaders": ref.TEXTURES,
             "brushes": ref.BRUSHES, "brushsides": ref.BRUSH_SIDES, "faces": ref.FACES}
    assert {k: len(getattr(ours, k)) for k in pairs} == {k: len(v) for k, v in pairs.items()}
    assert len(ours.entities) == len(ref.ENTITIES)
    assert [e.get("classname") for e in ours.entities] == [e.get("classname") for e in ref.ENTITIES]
    assert ours.lump_bytes["visdata"] == ref.headers["VISIBILITY"].length
    assert ours.n_clusters == len(ref.VISIBILITY)
    assert all(bytes(ours.visdata.rows[i]) == bytes(ref.VISIBILITY[i]) for i in range(ours.n_clusters))
    assert ours.leafs["cluster"].tolist() == [leaf.cluster for leaf in ref.LEAVES]
    assert ours.shader_names == [t.name.split(b"\0", 1)[0].decode("latin-1") for t in ref.TEXTURES]
    assert np.allclose(ours.vertexes["position"][::97], [list(v.position) for v in ref.VERTICES[::97]])
    patch = ours.faces["type"] == 2
    assert ours.faces["size"][patch].tolist() == [[int(f.patch.x), int(f.patch.y)] for f in ref.FACES
                                                   if int(f.type.value) == 2]
    print(f"{name}@{pak}: faces {ours.face_type_counts()}, vertexes {len(ours.vertexes)}, meshverts "
          f"{len(ours.meshverts)}, leafs {len(ours.leafs)}, clusters {ours.n_clusters}, entities "
          f"{len(ours.entities)}, visdata {ours.lump_bytes['visdata']} bytes")


# --- visibility --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", list(EXPECTED))
def test02_point_to_cluster_agrees_with_leaf_bounds(scenes, spec):
    """Random points inside the boxes of leaves with a cluster: when the BSP tree puts a point in a leaf with a
    cluster, that leaf's box holds it (leaf boxes are conservative and may overlap, so the tree can pick a
    neighbour). Boxes of solid leaves are not checked: q3map2 does not bound them tightly. The vectorised
    lookup equals a one-point-at-a-time CM_PointLeafnum."""
    vis = scenes[0][spec].visibility
    rng = np.random.default_rng(7)
    leaves = np.nonzero(vis.leaf_cluster >= 0)[0]
    pick = rng.choice(leaves, 20000)
    lo, hi = vis.leaf_mins_q3[pick], vis.leaf_maxs_q3[pick]
    q = lo + rng.random((len(pick), 3)) * (hi - lo)
    found = vis.leaf_of(vis.to_scene(q))
    inside = ((q >= vis.leaf_mins_q3[found] - 1.0) & (q <= vis.leaf_maxs_q3[found] + 1.0)).all(axis=1)
    open_leaf = vis.leaf_cluster[found] >= 0
    same_leaf = np.mean(found == pick)
    same_cluster = np.mean(vis.leaf_cluster[found] == vis.leaf_cluster[pick])
    print(f"{spec}: {np.mean(inside[open_leaf]):.4%} of points in open leaves inside the found leaf's box, "
          f"{same_leaf:.2%} in the sampled leaf, {same_cluster:.2%} in its cluster, "
          f"{np.mean(~open_leaf):.2%} in solid leaves ({np.mean(inside[~open_leaf]):.2%} inside their boxes)")
    assert inside[open_leaf].all()
    assert same_cluster >= 0.5

    def point_leaf(p):  # CM_PointLeafnum, one point at a time
        num = 0
        while num >= 0:
            plane = vis.node_plane[num]
            d = float(np.dot(p, vis.planes_normal[plane]) - vis.planes_dist[plane])
            num = vis.node_children[num, 0 if d >= 0 else 1]
        return -1 - num

    assert [point_leaf(p) for p in q[:300]] == found[:300].tolist()
    # The centre of a convex leaf's box is usually inside the leaf (not always: a slanted leaf's box is larger).
    centre = 0.5 * (vis.leaf_mins_q3[leaves] + vis.leaf_maxs_q3[leaves])
    centre_in_leaf = np.mean(vis.leaf_of(vis.to_scene(centre)) == leaves)
    print(f"{spec}: {centre_in_leaf:.1%} of open leaves contain their box centre")
    assert centre_in_leaf >= 0.5


@pytest.mark.parametrize("spec", list(EXPECTED))
def test03_pvs_and_triangle_clusters(scenes, spec):
    scene = scenes[0][spec]
    vis = scene.visibility
    sym = vis.symmetry()
    print(f"{spec}: PVS of {sym['clusters']} clusters, {sym['visible_ordered_pairs']} visible ordered pairs, "
          f"{sym['one_way_ordered_pairs']} one-way ({sym['one_way_fraction']:.2%}); not assumed symmetric")
    assert sym["diagonal_all_set"]
    m = vis.pvs_matrix()
    assert all(np.array_equal(vis.pvs(c), m[c]) for c in range(0, vis.n_clusters, 37))
    # Every triangle is in a cluster; its merged cluster is one of its clusters.
    counts = np.diff(vis.triangle_cluster_offsets)
    assert (counts > 0).all() and len(counts) == scene.num_faces
    owner = np.repeat(np.arange(scene.num_faces), counts)
    member = np.zeros(scene.num_faces, bool)
    np.logical_or.at(member, owner, vis.triangle_cluster_ids == vis.triangle_cluster[owner])
    assert member.all()
    # World triangles' clusters come from their face's leaves (leaffaces lists).
    from suite.core.scene.q3.bsp import gather_ranges

    data = loader.resolve(spec)[2]
    bsp = parse_bsp(data, spec)
    leafs = bsp.leafs[bsp.leafs["cluster"] >= 0]
    pair_face = gather_ranges(bsp.leaffaces, leafs["leafface"], leafs["n_leaffaces"])
    pair_cluster = np.repeat(leafs["cluster"], leafs["n_leaffaces"])
    allowed = set(zip(pair_face.tolist(), pair_cluster.tolist()))
    face = scene.q3.triangle_face
    world = scene.q3.face_model[face] == 0
    pairs = set(zip(face[owner][world[owner]].tolist(), vis.triangle_cluster_ids[world[owner]].tolist()))
    assert pairs <= allowed
    # From a cluster, its own triangles are potentially visible.
    c = int(vis.triangle_cluster[0])
    assert vis.visible_triangles(c)[vis.triangle_cluster == c].all()
    print(f"{spec}: {np.mean(counts > 1):.1%} of triangles are in more than one cluster (max {counts.max()})")


# --- scenes ------------------------------------------------------------------------------------------------------

def test04_scene_counts(scenes):
    loaded, times, _ = scenes
    for spec, scene in loaded.items():
        c = scene.q3.counts
        want = EXPECTED[spec]
        assert c["light_entities"] == want["light_entities"] and c["clusters"] == want["clusters"], spec
        assert c["lights_by_kind"]["spot"] == want["spots"]
        assert scene.visibility.n_clusters == want["clusters"]
        assert c["triangles"] == scene.num_faces and len(scene.emissive_faces()) == c["surface_light_triangles"]
        assert c["missing_textures"] == [], (spec, c["missing_textures"])
        assert c["degenerate_triangles_dropped"] < 0.05 * scene.num_faces
        kinds = collections.Counter(lt["kind"] for lt in scene.q3.lights)
        assert len(scene.point_lights) == sum(kinds.values())
        print(f"{spec}: {scene.num_faces} triangles (patches {c['patch_triangles']}), faces {c['faces_by_type']}, "
              f"skipped {({k: v for k, v in c['faces_skipped'].items() if v})}, {c['light_entities']} light "
              f"entities ({dict(kinds)}), {c['surface_light_triangles']} surface-light triangles, "
              f"{c['clusters']} clusters; load {times[spec][0]:.2f} s ({times[spec][1]})")


def test05_cached_load_is_fast_and_identical(scenes):
    loaded, times, cache = scenes
    mp = pytest.MonkeyPatch()
    mp.setenv("SPLITBENCH_CACHE", str(cache))
    try:
        for spec, cold in loaded.items():
            loader._scene_cache.clear()
            t0 = time.perf_counter()
            warm = loader.load_q3(spec)
            dt = time.perf_counter() - t0
            assert loader.last_load_stats["mode"] == "disk"
            for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object"):
                assert np.array_equal(getattr(cold, k), getattr(warm, k)), (spec, k)
            for a, b in zip(cold.materials, warm.materials):
                assert a.name == b.name and a.kind == b.kind and np.array_equal(a.emission, b.emission)
                assert (a.albedo_texture is None) == (b.albedo_texture is None)
                if a.albedo_texture is not None:
                    assert np.array_equal(a.albedo_texture, b.albedo_texture), (spec, a.name)
                assert (a.opacity_texture is None) == (b.opacity_texture is None)
            assert np.array_equal(cold.visibility.triangle_cluster, warm.visibility.triangle_cluster)
            print(f"{spec}: cold {times[spec][0]:.2f} s, cached {dt:.2f} s")
            assert times[spec][0] < 15.0 and dt < 2.0
    finally:
        mp.undo()


def _yaw(key):
    d = key.target - key.position
    return math.degrees(math.atan2(-d[0], -d[2]))


@pytest.mark.parametrize("spec", list(EXPECTED))
def test06_camera_paths_stay_inside_the_level(scenes, spec):
    scene = scenes[0][spec]
    cam = scene.camera
    tris = scene.triangles().astype(np.float64)
    r = check_path(cam, scene.visibility, tris)
    assert r["frames_in_solid"] == 0 and r["segments_crossing_geometry"] == 0, spec
    dirs = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                    float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    clearance = min(ray_hits(tris, np.repeat(k.position[None], len(dirs), 0), dirs, 50.0).min() for k in cam.keys)
    assert clearance >= 0.4
    assert 3.5 <= cam.duration_s <= 4.5
    # A fast turn (>= 80 deg within 0.35 s) and a backward move (moving against the view direction).
    keys = cam.keys
    def turn(a, b):
        return abs(((_yaw(b) - _yaw(a) + 180.0) % 360.0) - 180.0)

    fast = any(turn(a, b) >= 80 for i, a in enumerate(keys) for b in keys[i + 1:] if b.t_s - a.t_s <= 0.35 + 1e-9)
    backward = any(np.dot(b.position - a.position, a.target - a.position) < -0.5 for a, b in zip(keys, keys[1:]))
    assert fast and backward
    print(f"{spec}: {r['frames']} frames, clusters visited {r['clusters_visited']}, clearance {clearance:.2f} m")


def test07_render_one_view(scenes):
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import direct_lighting
    from suite.core.trace import make

    scene = scenes[0]["oa:aggressor@pak1-maps"]
    tracer = make("embree", scene)
    g = render_gbuffer(scene, tracer, 0.0, (160, 90))
    rgb = direct_lighting(scene, g, tracer, 0.0, area_samples=4)
    assert g.valid.mean() > 0.95
    assert g.albedo[g.valid].std(axis=0).min() > 0.02  # textured, not flat
    mean = float(rgb[g.valid].mean())
    assert 0.01 < mean < 2.0 and np.isfinite(rgb).all()


# --- errors, specs, override order ---------------------------------------------------------------------------------

def test08_truncated_and_corrupted_real_files(fs):
    data = _bytes(fs, "aggressor", "pak1-maps.pk3")
    for cut in (0, 100, 143, 144, len(data) // 3, len(data) - 1):
        with pytest.raises(UserError) as err:
            parse_bsp(data[:cut], "maps/aggressor.bsp")
        assert "\n" not in str(err.value) and str(err.value).startswith("maps/aggressor.bsp: not a valid")
    bad = bytearray(data)
    bad[8 + 13 * 8:8 + 13 * 8 + 4] = np.int32(len(data) - 10).tobytes()  # faces lump offset near the end
    with pytest.raises(UserError, match="lump 'faces'"):
        parse_bsp(bytes(bad), "x")
    bad = bytearray(data)
    faces_off = int(np.frombuffer(data, "<i4", 1, 8 + 13 * 8)[0])
    bad[faces_off + 12:faces_off + 16] = np.int32(10 ** 7).tobytes()  # face 0's first vertex
    with pytest.raises(UserError, match="face 0 refers to records"):
        parse_bsp(bytes(bad), "x")


def test09_specs_and_override_order(fs, tmp_path, monkeypatch):
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))
    name, map_name, data, source, _ = loader.resolve("oa:aggressor")
    assert source == "pak6-patch088.pk3:maps/aggressor.bsp"  # the later archive overrides pak1-maps
    assert loader.resolve("oa:AGGRESSOR@pak1-maps")[3] == "pak1-maps.pk3:maps/aggressor.bsp"
    with pytest.raises(UserError, match="unknown OpenArena map 'nosuchmap'"):
        loader.resolve("oa:nosuchmap")
    with pytest.raises(UserError, match="it is in: pak1-maps.pk3, pak6-patch088.pk3"):
        loader.resolve("oa:aggressor@pak9")
    pk3 = next(e.pak for e in fs.versions("maps/kaos.bsp"))
    with pytest.raises(UserError, match="pick one with"):
        loader.resolve(pk3)
    assert loader.resolve(pk3 + ":kaos")[1] == "kaos"
    bsp_path = tmp_path / "aggressor.bsp"
    bsp_path.write_bytes(data)
    scene = loader.load_q3(str(bsp_path))
    assert scene.q3.counts["clusters"] == 402 and scene.q3.counts["missing_textures"] == []
    # A single-map archive of our own, added with the highest priority.
    one = tmp_path / "zz-one.pk3"
    with zipfile.ZipFile(one, "w") as z:
        z.writestr("maps/aggressor.bsp", _bytes(fs, "aggressor", "pak1-maps.pk3"))
    assert loader.resolve(str(one))[3] == "zz-one.pk3:maps/aggressor.bsp"
    assert loader.file_system((str(one),)).find("maps/aggressor.bsp").pak.endswith("zz-one.pk3")


def test10_listing_and_missing_data(fs, monkeypatch, tmp_path):
    from suite.core.scene import list_scenes

    listed = list_q3_scenes()
    assert set(EXPECTED) <= set(listed) and not any(d.startswith("unavailable") for d in listed.values())
    assert set(listed) <= set(list_scenes())
    monkeypatch.setenv("SPLITBENCH_OA_PATH", str(tmp_path))
    monkeypatch.setattr(paks, "DEFAULT_DIRS", ())
    missing = list_q3_scenes()
    assert set(missing) == set(listed)
    assert all(d.startswith("unavailable: OpenArena maps not found") and "SPLITBENCH_OA_PATH" in d
               for d in missing.values())
    with pytest.raises(UserError) as err:
        loader.load_q3("oa:kaos")
    assert "apt-get download" in str(err.value) and "\n" not in str(err.value)


def test11_every_map_file_in_the_archives_parses(fs):
    """All BSP files of all archives (overridden versions included) pass validation; face types seen."""
    seen = collections.Counter()
    files = 0
    for name in fs.maps():
        for entry in fs.versions(f"maps/{name}.bsp"):
            bsp = parse_bsp(fs.read("", entry), f"{entry.pak}:{entry.name}")
            seen.update(bsp.face_type_counts())
            files += 1
    print(f"{files} BSP files of {len(fs.maps())} maps; faces by type over all: {dict(seen)}")
    assert files >= len(fs.maps()) >= 50 and set(seen) == {"planar", "patch", "mesh", "billboard"}
