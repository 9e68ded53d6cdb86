"""Wavefront OBJ scenes: OBJ + MTL + textures through tinyobjloader, sidecars, strictness, the cache."""
import hashlib

import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene import load
from suite.core.scene.obj import ObjScene, load_obj
from suite.core.scene.obj import loader as obj_loader
from suite.core.scene.obj.samples import FLOOR_COOL, FLOOR_WARM, write_textured_room
from suite.core.scene.q3.textures import decode_srgb8


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A private scene cache; the in-process cache is emptied so every load goes to disk or converts."""
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))
    obj_loader._scene_cache.clear()
    yield tmp_path / "cache"
    obj_loader._scene_cache.clear()


@pytest.fixture
def room(tmp_path, cache):
    return write_textured_room(tmp_path / "room")


def mat(scene, name):
    return next(m for m in scene.materials if m.name == name)


def test01_textured_obj_loads_materials_textures_alpha_mask_and_emission(room):
    scene = load_obj(room)
    assert isinstance(scene, ObjScene)
    c = scene.obj.counts
    # 8 quads, two of them written as one polygon each (triangulated by tinyobjloader): 16 triangles.
    assert c["triangles"] == 16 and c["objects"] == 8 and c["mtl_materials"] == 6
    assert c["textured_materials"] == 2 and c["alpha_tested_materials"] == 1 and c["emissive_triangles"] == 2
    assert scene.object_names == ["floor", "back_wall", "left_wall", "right_wall", "ceiling", "front_wall", "grate",
                                  "lamp"]
    floor = mat(scene, "floor")
    # map_Kd: 8-bit sRGB decoded to linear, row 0 = the image's top row.
    assert floor.albedo_texture.shape == (64, 64, 3)
    np.testing.assert_allclose(floor.albedo_texture[0, 1], decode_srgb8(np.uint8(FLOOR_WARM)), rtol=1e-6)
    # The JPEG texture, named with a backslash in the MTL, is found and decoded too.
    assert mat(scene, "bricks").albedo_texture.shape == (64, 64, 3)
    grate = mat(scene, "grate")
    assert grate.opacity_texture.shape == (64, 64, 1) and grate.alpha_threshold == 0.5
    assert set(np.unique(grate.opacity_texture)) == {0.0, 1.0}
    np.testing.assert_allclose(mat(scene, "lamp").emission, [8, 8, 7])
    np.testing.assert_allclose(mat(scene, "plain").albedo, [0.6, 0.6, 0.55], rtol=1e-6)
    # Sidecar: one point light and a scripted camera.
    assert [lt.name for lt in scene.point_lights] == ["corner_lamp"]
    assert scene.camera.resolution == (160, 90) and scene.camera.duration_s == pytest.approx(2.0)


def test02_texture_coordinates_follow_the_obj_convention(room):
    """OBJ's v = 0 is the image's bottom row: the floor's front edge (v = 0) shows the texture's bottom half."""
    from suite.core.gbuffer import lookup_texture

    scene = load_obj(room)
    floor_faces = np.nonzero(scene.face_object == scene.object_names.index("floor"))[0]
    verts = np.unique(scene.faces[floor_faces])
    front = verts[scene.positions[verts, 2] > 2.9]  # z = +3 corners, written with vt v = 0
    back = verts[scene.positions[verts, 2] < -2.9]
    tex = mat(scene, "floor").albedo_texture
    uv_front = scene.uvs[front] * 0.98 + 0.01  # just inside the corners
    uv_back = scene.uvs[back] * 0.98 + 0.01
    cool, warm = decode_srgb8(np.uint8(FLOOR_COOL)), decode_srgb8(np.uint8(FLOOR_WARM))
    for uv, want, other in ((uv_front, cool, warm), (uv_back, warm, cool)):
        got = lookup_texture(tex, uv)
        # The checker darkens some tiles by 20 %: compare hues, not levels.
        hue = got / got.sum(axis=1, keepdims=True)
        assert np.abs(hue - want / want.sum()).max() < 0.02
        assert np.abs(hue - other / other.sum()).max() > 0.1


@pytest.mark.parametrize("backend", ["embree", "mitsuba-llvm"])
def test03_alpha_mask_lets_rays_through_transparent_texels(room, backend):
    from suite.core.trace import make

    scene = load_obj(room)
    tracer = make(backend, scene)
    grate = scene.object_names.index("grate")
    # The grate spans x in [-1, 1] at z = -1; texture u = (x + 1) / 2, bars where (64 u) % 16 < 4.
    x_bar, x_gap = -1 + 2 * (2 / 64), -1 + 2 * (10 / 64)
    o = np.float32([[x_bar, 1.3, 0.0], [x_gap, 1.3, 0.0]])
    d = np.float32([[0, 0, -1], [0, 0, -1]])
    hits = tracer.intersect(o, d)
    assert scene.face_object[hits.prim[0]] == grate and hits.t[0] == pytest.approx(1.0, rel=1e-5)
    assert scene.object_names[scene.face_object[hits.prim[1]]] == "back_wall"
    assert hits.t[1] == pytest.approx(3.0, rel=1e-5)
    assert list(tracer.occluded(o, d, 0.0, 2.0)) == [True, False]


def test04_emissive_material_is_a_one_sided_area_light(room):
    scene = load_obj(room)
    lights = scene.area_light_triangles(0.0)
    assert len(lights) == 2
    np.testing.assert_allclose(lights.radiance, [[8, 8, 7]] * 2)
    np.testing.assert_allclose(lights.normal, [[0, -1, 0]] * 2, atol=1e-6)  # emits down into the room
    assert lights.area.sum() == pytest.approx(1.0, rel=1e-6)


def test05_what_is_not_modelled_is_counted_and_reported_in_one_line(room, capsys):
    scene = load_obj(room)
    assert scene.obj.unsupported == {"Ks": 1, "Ns": 1, "map_bump": 1}
    assert scene.obj.missing_textures == ["tex/nothere.png"]
    assert mat(scene, "odd").albedo_texture is None  # falls back to Kd
    np.testing.assert_allclose(mat(scene, "odd").albedo, [0.3, 0.5, 0.3], rtol=1e-6)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "map_bump x1" in err[0] and "tex/nothere.png" in err[0]
    assert "map_bump x1" in scene.description
    with pytest.raises(UserError, match="not modelled: Ks x1, Ns x1, map_bump x1") as info:
        load_obj(room, strict=True)
    assert "\n" not in str(info.value)


GOOD = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n"


@pytest.mark.parametrize("text, message", [
    (GOOD[:-8], "line 5: malformed 'f' statement.*truncated"),         # cut inside the last face
    ("v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n", "line 3: malformed 'v' statement"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 nan\nf 1 2 3\n", "line 3: malformed 'v' statement"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n", "refers to vertex 7, the file has 3|out of bounds"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "zero value"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nhello world\nf 1 2 3\n", "line 4: unknown statement 'hello world'"),
    ("\x89PNG\r\n\x1a\n\x00\x00binary", "unknown statement|malformed"),
    ("# nothing but a comment\n", "no faces"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//4\n", "refers to normal 4, the file has 1|out of bounds"),
])
def test06_malformed_or_truncated_files_are_one_line_user_errors(tmp_path, cache, text, message):
    p = tmp_path / "bad.obj"
    p.write_bytes(text.encode("latin-1"))
    with pytest.raises(UserError, match=message) as info:
        load_obj(p)
    assert str(info.value).startswith(f"{p}: not a valid OBJ file: ")
    assert "\n" not in str(info.value)


def test07_comments_after_statements_and_unsupported_obj_statements(tmp_path, cache, capsys):
    p = tmp_path / "lines.obj"
    p.write_text("v 0 0 0 # origin\nv 1 0 0\nv 0 1 0\nf 1 2 3\nl 1 2\np 3\ncstype bspline\n")
    scene = load_obj(p)
    assert scene.num_faces == 1
    assert scene.obj.unsupported == {"l": 1, "p": 1, "cstype": 1}
    assert "l x1" in capsys.readouterr().err


def test08_mtl_problems(tmp_path, cache):
    p = tmp_path / "m.obj"
    p.write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n")
    (tmp_path / "m.mtl").write_text("Kd 1 0 0\nnewmtl a\n")
    with pytest.raises(UserError, match="'Kd' before any 'newmtl'"):
        load_obj(p)
    (tmp_path / "m.mtl").write_text("newmtl a\nKe 1 x 3\n")
    with pytest.raises(UserError, match="material 'a': malformed 'Ke'"):
        load_obj(p)
    (tmp_path / "m.mtl").unlink()
    scene = load_obj(p)  # a missing MTL is reported, its faces get the default material
    assert "missing MTL file m.mtl" in scene.obj.unsupported
    assert scene.materials[scene.face_material[0]].name == "default"


def test09_sidecar_checks(tmp_path, cache):
    obj = write_textured_room(tmp_path / "r", sidecar=False)
    side = obj.with_name("textured_room.splitbench.toml")
    sha = hashlib.sha256(obj.read_bytes()).hexdigest()
    side.write_text('[scene]\nsha256 = "' + "0" * 64 + '"\n')
    with pytest.raises(UserError) as info:
        load_obj(obj)
    assert str(side) in str(info.value) and str(obj) in str(info.value) and sha in str(info.value)
    side.write_text("[scene]\nunits = 2\n")
    with pytest.raises(UserError, match="unknown key 'units'"):
        load_obj(obj)
    side.write_text('[objects]\n"floor" = "nowhere"\n')
    with pytest.raises(UserError, match="no \\[materials.nowhere\\] table"):
        load_obj(obj)
    side.write_text(f"""[scene]
sha256 = "{sha}"
unit_m = 0.5
up = "z"
[materials.stone]
albedo = [0.2, 0.3, 0.4]
[materials.grate]
kind = "rough_plastic"
roughness = 0.3
[objects]
"*_wall" = "stone"
[[lights]]
name = "moving"
position = [0, 0, 1]
intensity = 2.0
keys = [{{ t = 0.0, position = [0, 0, 1] }}, {{ t = 2.0, position = [1, 0, 1] }}]
""")
    scene = load_obj(obj)
    # z up -> y up: (x, y, z) -> (x, z, -y), then half a metre per unit.
    lo, hi = scene.bounds()
    np.testing.assert_allclose(lo, [-1.5, -1.5, -1.5], atol=1e-6)
    np.testing.assert_allclose(hi, [1.5, 1.5, 0.0], atol=1e-6)  # the file's y in [0, 3] becomes z in [-1.5, 0]
    walls = [scene.object_names.index(n) for n in ("back_wall", "left_wall", "right_wall", "front_wall")]
    stone = [m.name for m in scene.materials].index("stone")
    assert (scene.face_material[np.isin(scene.face_object, walls)] == stone).all()
    grate = mat(scene, "grate")
    assert grate.kind == "rough_plastic" and grate.roughness == 0.3 and grate.opacity_texture is not None
    np.testing.assert_allclose(scene.lights_at(1.0)[0].position, [0.5, 0, 1])
    assert scene.obj.defaults == ["camera"]


def test10_cache_round_trip_is_exact_and_follows_dependencies(room, cache):
    cold = load_obj(room)
    assert obj_loader.last_load_stats["mode"] == "cold"
    obj_loader._scene_cache.clear()
    warm = load_obj(room)
    assert obj_loader.last_load_stats["mode"] == "disk"
    for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object"):
        np.testing.assert_array_equal(getattr(cold, k), getattr(warm, k))
    for a, b in zip(cold.materials, warm.materials):
        assert a.name == b.name and a.kind == b.kind
        np.testing.assert_array_equal(a.albedo, b.albedo)
        np.testing.assert_array_equal(a.emission, b.emission)
        for t in ("albedo_texture", "opacity_texture"):
            assert (getattr(a, t) is None) == (getattr(b, t) is None)
            if getattr(a, t) is not None:
                np.testing.assert_array_equal(getattr(a, t), getattr(b, t))
    assert warm.obj.counts == cold.obj.counts
    # A texture that changes, or one that was missing and appears, makes the cached entry stale.
    obj_loader._scene_cache.clear()
    from suite.core.scene.obj.samples import brick_texture, write_image

    write_image(room.parent / "tex" / "nothere.png", brick_texture())
    load_obj(room)
    assert obj_loader.last_load_stats["mode"] == "cold"
    assert mat(load_obj(room), "odd").albedo_texture is not None


def test11_load_routing_runner_and_defaults(tmp_path, cache):
    from suite.harness import runner

    obj = write_textured_room(tmp_path / "r", sidecar=False)
    scene = load(str(obj))
    assert isinstance(scene, ObjScene) and scene.name == "textured_room"
    cfg = runner.make_config("local_direct", scene=str(obj))
    assert cfg["scene"] == str(obj)
    # No sidecar: the camera looks at the scene from outside its bounding sphere; the emissive panel lights it, so
    # no default light is added.
    assert scene.obj.defaults == ["camera"] and scene.point_lights == []
    eye = scene.camera.pose_at(0.0).position
    lo, hi = scene.bounds()
    assert np.linalg.norm(eye - 0.5 * (lo + hi)) > 0.5 * np.linalg.norm(hi - lo)


def test12_a_sidecar_extends_a_project_sidecar_replacing_whole_tables(tmp_path, monkeypatch):
    from suite.core.scene.obj import sidecar as sc_mod

    monkeypatch.setattr(sc_mod, "DATA_DIR", tmp_path)
    base = tmp_path / "base.toml"
    base.write_text("""[scene]
name = "base"
title = "the base"
unit_m = 0.5
[materials.stone]
albedo = [0.2, 0.3, 0.4]
[objects]
"*" = "stone"
[[lights]]
name = "moving"
position = [0, 0, 1]
intensity = 2.0
keys = [{ t = 0.0, position = [0, 0, 1] }, { t = 2.0, position = [1, 0, 1] }]
[[lights]]
name = "second"
position = [0, 1, 0]
intensity = 1.0
[camera]
position = [0, 1, 2]
""")
    child = tmp_path / "child.toml"
    child.write_text("""[scene]
name = "child"
extends = "base"
title = "the base, lights still"
[[lights]]
name = "still"
position = [0, 0, 1]
intensity = 2.0
""")
    a, b = sc_mod.read_sidecar(base), sc_mod.read_sidecar(child)
    assert b.name == "child" and b.scene["title"] == "the base, lights still" and b.unit_m == 0.5
    assert b.materials == a.materials and b.objects == a.objects and b.camera == a.camera
    assert [lt["name"] for lt in b.lights] == ["still"] and "keys" not in b.lights[0]
    # the child's identity follows its base's text too
    before = b.text_sha256
    base.write_text(base.read_text().replace("0.2, 0.3, 0.4", "0.25, 0.3, 0.4"))
    assert sc_mod.read_sidecar(child).text_sha256 != before
    assert sorted(sc_mod.project_sidecars()) == ["base", "child"]
    for extends, message in (("nowhere", "extends 'nowhere', which is no other project sidecar"),
                             ("child", "extends 'child', which is no other project sidecar")):
        child.write_text(f'[scene]\nname = "child"\nextends = "{extends}"\n')
        with pytest.raises(UserError, match=message):
            sc_mod.read_sidecar(child)
    (tmp_path / "grandchild.toml").write_text('[scene]\nname = "grandchild"\nextends = "child"\n')
    child.write_text('[scene]\nname = "child"\nextends = "base"\n')
    with pytest.raises(UserError, match="extends 'child', which extends another sidecar \\(one level only\\)"):
        sc_mod.read_sidecar(tmp_path / "grandchild.toml")
