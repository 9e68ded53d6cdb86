"""Mitsuba scenes in and out: supported plugins load, unsupported ones are named, export round-trips."""
import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene import load
from suite.core.scene.mitsuba_io import load_mitsuba, to_mitsuba_dict


def mi():
    from suite.core.env import mitsuba

    return mitsuba("llvm")


def minimal_scene(**shapes):
    d = {"type": "scene", "sensor": {"type": "perspective", "fov": 45.0,
                                     "to_world": mi().ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                                     "film": {"type": "hdrfilm", "width": 32, "height": 24}}}
    d.update(shapes)
    return d


def test01_cornell_box_loads_with_its_materials_area_light_and_camera():
    scene = load_mitsuba(mi().cornell_box(), name="cornell")
    assert scene.num_faces == 36
    assert len(scene.emissive_faces()) == 2
    assert scene.camera.resolution == (256, 256)
    assert scene.camera.fov_deg == pytest.approx(39.3077, rel=1e-4)
    np.testing.assert_allclose(scene.camera.pose_at(0.0).position, [0, 0, 3.9], atol=1e-5)
    assert {"light", "floor", "small-box"} <= set(scene.object_names)


def test02_sphere_is_tessellated_to_the_stated_resolution():
    d = minimal_scene(ball={"type": "sphere", "center": [0, 0, 0], "radius": 2.0})
    coarse = load_mitsuba(d, sphere_resolution=8)
    fine = load_mitsuba(d, sphere_resolution=32)
    assert fine.num_faces > 10 * coarse.num_faces / 2
    np.testing.assert_allclose(np.linalg.norm(fine.positions, axis=1), 2.0, rtol=1e-5)
    # Triangles are wound outward: face normals point away from the centre.
    centroids = fine.triangles().mean(axis=1)
    assert (np.einsum("ij,ij->i", fine.face_normals(), centroids) > 0).all()


def test03_point_lights_keep_position_and_intensity():
    d = minimal_scene(floor={"type": "rectangle"},
                      lamp={"type": "point", "position": [1, 2, 3], "intensity": {"type": "rgb", "value": [4, 5, 6]}})
    scene = load_mitsuba(d)
    assert len(scene.point_lights) == 1
    np.testing.assert_allclose(scene.point_lights[0].position, [1, 2, 3])
    np.testing.assert_allclose(scene.point_lights[0].intensity, [4, 5, 6])


@pytest.mark.parametrize("shape, expected", [
    ({"type": "rectangle", "bsdf": {"type": "thindielectric"}}, "unsupported BSDF plugin 'thindielectric'"),
    ({"type": "disk"}, "unsupported shape plugin 'disk'"),
    ({"type": "rectangle", "bsdf": {"type": "roughdielectric"}}, "unsupported BSDF plugin 'roughdielectric'"),
])
def test04_unsupported_plugins_are_named_in_a_one_line_error(shape, expected):
    with pytest.raises(UserError, match=expected) as info:
        load_mitsuba(minimal_scene(thing=shape))
    assert "'thing'" in str(info.value)
    assert "\n" not in str(info.value)


def test05_unsupported_emitters_are_named():
    d = minimal_scene(floor={"type": "rectangle"}, sun={"type": "directional", "direction": [0, -1, 0]})
    with pytest.raises(UserError, match="unsupported emitter plugin"):
        load_mitsuba(d)


def test06_missing_and_malformed_files_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load(str(tmp_path / "nope.xml"))
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='rectangle'>")
    with pytest.raises(UserError, match="could not load"):
        load(str(bad))
    with pytest.raises(UserError, match="unknown scene 'kitchen'"):
        load("kitchen")


def test07_xml_scene_loads_from_a_file(tmp_path):
    xml = tmp_path / "s.xml"
    xml.write_text("""<scene version="3.0.0">
      <sensor type="perspective"><float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/></film></sensor>
      <shape type="cube" id="box"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf></shape>
      <emitter type="point"><point name="position" x="0" y="3" z="0"/><rgb name="intensity" value="10, 10, 10"/></emitter>
    </scene>""")
    scene = load(str(xml))
    assert scene.num_faces == 12 and scene.camera.resolution == (40, 30)
    np.testing.assert_allclose(scene.materials[0].albedo, [0.2, 0.4, 0.6], rtol=1e-5)


def test08_export_renders_the_same_image_as_the_original_dict():
    m = mi()
    original = m.cornell_box()
    original["sensor"]["film"].update(width=32, height=32, rfilter={"type": "box"})
    scene = load_mitsuba(original, name="cornell")
    a = np.array(m.render(m.load_dict(original), spp=256, seed=1))
    b = np.array(m.render(m.load_dict(to_mitsuba_dict(scene, 0.0, (32, 32))), spp=256, seed=1))
    assert abs(a.mean() - b.mean()) < 0.01 * a.mean()
    assert np.abs(a - b).mean() < 0.05 * a.mean()


def test09_export_places_animated_objects_at_the_requested_time():
    scene = load("arena")
    anim = scene.object_animations[0]
    m = mi()
    for t in (0.0, 2.0):
        d = to_mitsuba_dict(scene, t, (16, 16))
        mesh_positions = np.concatenate([np.array(v.vertex_positions_buffer()).reshape(-1, 3)
                                         for k, v in d.items() if k.startswith("mesh_")])
        moved = scene.positions_at(t)[scene.faces[scene.face_object == anim.object_id]].reshape(-1, 3)
        # Every vertex of the platform at time t appears in the exported meshes.
        dists = np.min(np.linalg.norm(mesh_positions[None, :, :] - moved[:8, None, :], axis=-1), axis=1)
        assert dists.max() < 1e-5


# --- materials beyond diffuse ---------------------------------------------------------------------

def rgb(values):
    return {"type": "rgb", "value": [float(x) for x in values]}


def bitmap(array, **kw):
    return {"type": "bitmap", "data": mi().TensorXf(np.ascontiguousarray(array, np.float32)), "raw": True, **kw}


def load_bsdf(bsdf):
    """The material of a rectangle with ``bsdf`` (a fresh dict each time: Mitsuba consumes bitmap tensors)."""
    scene = load_mitsuba(minimal_scene(thing={"type": "rectangle", "bsdf": bsdf}))
    assert len(scene.materials) == 1
    return scene.materials[0]


@pytest.mark.parametrize("bsdf, expected", [
    ({"type": "conductor"}, dict(kind="mirror", conductor_eta=[0, 0, 0], conductor_k=[1, 1, 1], twosided=False)),
    ({"type": "conductor", "eta": rgb([0.2, 0.9, 1.3]), "k": 2.5, "specular_reflectance": rgb([0.9, 0.8, 0.7])},
     dict(kind="mirror", conductor_eta=[0.2, 0.9, 1.3], conductor_k=[2.5] * 3, specular_reflectance=[0.9, 0.8, 0.7])),
    ({"type": "twosided", "bsdf": {"type": "conductor"}}, dict(kind="mirror", twosided=True)),
    ({"type": "roughconductor"}, dict(kind="rough_conductor", roughness=0.1, distribution="beckmann")),
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}, dict(kind="rough_conductor", roughness=0.3,
                                                                           distribution="ggx")),
    ({"type": "dielectric", "int_ior": 1.33, "ext_ior": 1.0}, dict(kind="glass", eta=1.33)),
    ({"type": "dielectric", "int_ior": "water", "specular_transmittance": rgb([0.9, 1.0, 0.95])},
     dict(kind="glass", eta=1.3330 / 1.000277, specular_transmittance=[0.9, 1.0, 0.95])),
    ({"type": "roughplastic"}, dict(kind="rough_plastic", roughness=0.1, distribution="beckmann",
                                    eta=1.49 / 1.000277, albedo=[0.5] * 3, nonlinear=False)),
    ({"type": "twosided", "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.25, "int_ior": 1.6,
                                   "ext_ior": 1.0, "nonlinear": True, "diffuse_reflectance": rgb([0.2, 0.3, 0.4])}},
     dict(kind="rough_plastic", roughness=0.25, distribution="ggx", eta=1.6, nonlinear=True, twosided=True,
          albedo=[0.2, 0.3, 0.4])),
])
def test10_each_material_plugin_loads_with_its_parameters(bsdf, expected):
    mat = load_bsdf(bsdf)
    for field, value in expected.items():
        got = getattr(mat, field)
        if isinstance(value, (list, float)):
            np.testing.assert_allclose(got, value, rtol=1e-5, err_msg=field)
        else:
            assert got == value, field
    assert mat.opacity_texture is None


def test11_conductor_presets_are_read_back_from_mitsuba():
    gold = load_bsdf({"type": "conductor", "material": "Au"})
    assert gold.kind == "mirror" and gold.conductor_eta[2] > gold.conductor_eta[0] and gold.conductor_k.min() > 1


def test12_mask_loads_its_opacity_bitmap_around_any_material():
    opacity = np.zeros((4, 8, 1), np.float32)
    opacity[:, 4:] = 1.0
    mat = load_bsdf({"type": "mask", "opacity": bitmap(opacity), "bsdf": {"type": "diffuse",
                                                                           "reflectance": rgb([0.3, 0.6, 0.2])}})
    assert mat.kind == "diffuse" and mat.is_alpha_tested and mat.alpha_threshold == 0.5
    np.testing.assert_array_equal(mat.opacity_texture, opacity)
    np.testing.assert_allclose(mat.albedo, [0.3, 0.6, 0.2])
    glossy = load_bsdf({"type": "mask", "opacity": bitmap(opacity),
                        "bsdf": {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.2}}})
    assert glossy.kind == "rough_conductor" and glossy.twosided and glossy.is_alpha_tested


def test13_png_bitmaps_are_linearised_like_mitsuba_does(tmp_path):
    """Mitsuba keeps 8-bit texels as integers and converts them at lookup (sRGB unless raw); read back, they
    must be the linear values Mitsuba renders with, not 0..255."""
    from suite.core.imageio import write_png

    path = str(tmp_path / "grey.png")
    write_png(path, np.full((2, 2, 3), 0.2158, np.float32))  # stored as sRGB 128
    srgb = load_bsdf({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": path}})
    raw = load_bsdf({"type": "diffuse", "reflectance": {"type": "bitmap", "filename": path, "raw": True}})
    np.testing.assert_allclose(srgb.albedo_texture, 0.21586, atol=1e-4)
    np.testing.assert_allclose(raw.albedo_texture, 128 / 255, atol=1e-6)


def test14_xml_with_references_loads_every_material(tmp_path):
    xml = tmp_path / "s.xml"
    xml.write_text("""<scene version="3.0.0">
      <bsdf type="twosided" id="brass"><bsdf type="roughconductor"><string name="distribution" value="ggx"/>
        <float name="alpha" value="0.2"/></bsdf></bsdf>
      <bsdf type="dielectric" id="water"><string name="int_ior" value="water"/></bsdf>
      <sensor type="perspective"><float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/></film></sensor>
      <shape type="cube" id="box"><ref id="brass"/></shape>
      <shape type="sphere" id="drop"><ref id="water" name="bsdf"/><float name="radius" value="0.3"/></shape>
      <shape type="rectangle" id="lamp"><bsdf type="conductor"/>
        <emitter type="area"><rgb name="radiance" value="2, 2, 2"/></emitter></shape>
    </scene>""")
    scene = load(str(xml))
    kinds = {scene.object_names[o]: scene.materials[m].kind for o, m in zip(scene.face_object, scene.face_material)}
    assert kinds == {"box": "rough_conductor", "drop": "glass", "lamp": "mirror"}
    assert len(scene.emissive_faces()) == 2


@pytest.mark.parametrize("thing, message", [
    ({"type": "rectangle", "bsdf": {"type": "thindielectric"}}, "unsupported BSDF plugin 'thindielectric'"),
    ({"type": "rectangle", "bsdf": {"type": "roughdielectric"}}, "unsupported BSDF plugin 'roughdielectric'"),
    ({"type": "rectangle", "bsdf": {"type": "plastic"}}, "unsupported BSDF plugin 'plastic'"),
    ({"type": "rectangle", "bsdf": {"type": "bumpmap", "bsdf": {"type": "diffuse"},
                                    "arbitrary": {"type": "bitmap", "data": None}}}, "unsupported BSDF plugin 'bumpmap'"),
    ({"type": "rectangle", "bsdf": {"type": "twosided", "a": {"type": "diffuse"}, "b": {"type": "conductor"}}},
     "different front and back"),
    ({"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": {"type": "dielectric"}}}, "twosided must wrap"),
    ({"type": "rectangle", "bsdf": {"type": "mask", "opacity": 0.5, "bsdf": {"type": "diffuse"}}},
     "'opacity' must be a bitmap"),
    ({"type": "rectangle", "bsdf": {"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.3}},
     "roughconductor parameter 'alpha_u'"),
    ({"type": "rectangle", "bsdf": {"type": "roughconductor", "alpha": {"type": "bitmap", "data": None}}},
     "unsupported texture plugin 'bitmap' for 'alpha'"),
    ({"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard"}}},
     "unsupported texture plugin 'checkerboard' for 'reflectance'"),
    ({"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "data": None,
                                                                       "filter_type": "nearest"}}},
     "bitmap parameter 'filter_type' 'nearest'"),
    ({"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "data": None,
                                                                       "wrap_mode": "clamp"}}},
     "bitmap parameter 'wrap_mode' 'clamp'"),
    ({"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "data": None,
                                                                       "to_uv": "scale"}}},
     "bitmap parameter 'to_uv'"),
    ({"type": "rectangle", "interior": {"type": "homogeneous"}}, "participating media are not modelled"),
    ({"type": "rectangle", "exterior": {"type": "homogeneous"}}, "participating media are not modelled"),
    ({"type": "rectangle", "flip_normals": True}, "rectangle parameter 'flip_normals'"),
    ({"type": "rectangle", "emitter": {"type": "area", "radiance": {"type": "bitmap", "data": None}}},
     "unsupported texture plugin 'bitmap' for 'radiance'"),
    ({"type": "rectangle", "emitter": {"type": "area", "radiance": {"type": "d65"}}},
     "unsupported texture plugin 'd65' for 'radiance'"),
    ({"type": "cylinder"}, "unsupported shape plugin 'cylinder'"),
    ({"type": "rectangle", "bsdf": {"type": "null"}}, "unsupported BSDF plugin 'null'"),
    ({"type": "rectangle", "bsdf": {"type": "blendbsdf", "weight": 0.5, "a": {"type": "diffuse"},
                                    "b": {"type": "conductor"}}}, "unsupported BSDF plugin 'blendbsdf'"),
    ({"type": "rectangle", "bsdf": {"type": "mask", "opacity": {"type": "bitmap", "data": None},
                                    "bsdf": {"type": "mask", "opacity": {"type": "bitmap", "data": None},
                                             "bsdf": {"type": "diffuse"}}}}, "a mask inside a mask"),
    ({"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute",
                                                                       "name": "vertex_color"}}},
     "unsupported texture plugin 'mesh_attribute'"),
    ({"type": "rectangle", "sensor": {"type": "irradiancemeter", "film": {"type": "hdrfilm", "width": 1,
                                                                          "height": 1}}},
     "'irradiancemeter' as rectangle parameter 'sensor'"),
])
def test15_anything_not_modelled_is_rejected_naming_it(thing, message):
    m = mi()

    def fill(d):  # bitmaps need fresh tensors; transforms need Mitsuba objects
        for k, v in list(d.items()):
            if isinstance(v, dict):
                fill(v)
            elif k == "data" and v is None:
                d[k] = m.TensorXf(np.ones((2, 2, 3), np.float32))
            elif k == "to_uv":
                d[k] = m.ScalarTransform4f().scale([2.0, 2.0, 1.0])
        return d

    with pytest.raises(UserError, match=message) as info:
        load_mitsuba(minimal_scene(thing=fill(thing)))
    assert "'thing'" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("extra, message", [
    (dict(env={"type": "constant"}), "unsupported emitter plugin 'constant'"),
    (dict(sun={"type": "spot"}), "unsupported emitter plugin 'spot'"),
    (dict(fog={"type": "homogeneous"}), "participating media are not modelled"),
    (dict(cam2={"type": "orthographic"}), "sensor plugin 'orthographic' is not supported"),
])
def test16_unsupported_top_level_objects_are_rejected_naming_them(extra, message):
    with pytest.raises(UserError, match=message) as info:
        load_mitsuba(minimal_scene(floor={"type": "rectangle"}, **extra))
    assert f"'{next(iter(extra))}'" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("sensor, message", [
    ({"type": "thinlens", "aperture_radius": 0.1}, "sensor plugin 'thinlens'"),
    ({"principal_point_offset_x": 0.2}, "principal_point_offset_x"),
    ({"film": {"type": "hdrfilm", "width": 32, "height": 24, "crop_width": 16, "crop_height": 12}}, "cropped film"),
    ({"film": {"type": "specfilm", "width": 32, "height": 24}}, "film plugin 'specfilm'"),
    ({"srf": {"type": "d65"}}, "'d65' as perspective parameter 'srf'"),
])
def test17_sensor_settings_that_change_the_camera_are_rejected(sensor, message):
    d = minimal_scene(floor={"type": "rectangle"})
    d["sensor"].update(sensor)
    with pytest.raises(UserError, match=message):
        load_mitsuba(d)


def test18_export_and_load_round_trip_keeps_every_material():
    """model -> to_mitsuba_dict -> load: the gallery's materials come back (float32 rounding aside)."""
    import dataclasses

    scene = load("gallery")
    back = load_mitsuba(to_mitsuba_dict(scene, 0.0, (32, 18)))
    # to_mitsuba_dict writes one mesh 'mesh_<i>' per (object, material) group, in np.unique order.
    groups = np.unique(np.stack([scene.face_object, scene.face_material], axis=1), axis=0)
    pairs = {}
    for obj, mat in zip(back.face_object, back.face_material):
        group = int(back.object_names[obj].split("_")[1])
        pairs.setdefault(int(groups[group][1]), int(mat))
    assert len(pairs) == len(scene.materials)
    for i, j in pairs.items():
        a, b = scene.materials[i], back.materials[j]
        assert (a.shading_kind, a.twosided if a.kind != "diffuse" else False) == (b.shading_kind, b.twosided), a.name
        textured = ("albedo_texture",) if a.albedo_texture is not None else ("albedo",)
        fields = {"diffuse": textured,
                  "mirror": ("specular_reflectance", "conductor_eta", "conductor_k"),
                  "glass": ("eta", "specular_reflectance", "specular_transmittance"),
                  "rough_conductor": ("roughness", "distribution", "conductor_eta", "conductor_k",
                                      "specular_reflectance"),
                  "rough_plastic": textured + ("roughness", "distribution", "eta", "nonlinear",
                                    "specular_reflectance")}[a.shading_kind]
        for f in fields + ("emission", "opacity_texture", "alpha_threshold"):
            x, y = getattr(a, f), getattr(b, f)
            if isinstance(x, str) or isinstance(x, bool) or x is None:
                assert x == y, (a.name, f)
            else:
                np.testing.assert_allclose(y, x, rtol=2e-6, atol=1e-6, err_msg=f"{a.name}.{f}")
    assert {f.name for f in dataclasses.fields(type(scene.materials[0]))} >= {"opacity_texture", "roughness"}


def test19_built_objects_in_a_dict_are_checked_too():
    """A dict may carry BSDFs Mitsuba already built; they are read through what Mitsuba exposes."""
    m = mi()
    with pytest.raises(UserError, match="unsupported BSDF plugin 'thindielectric'") as info:
        load_mitsuba(minimal_scene(thing={"type": "rectangle", "bsdf": m.load_dict({"type": "thindielectric"})}))
    assert "'thing'" in str(info.value)
    with pytest.raises(UserError, match="different front and back"):
        load_mitsuba(minimal_scene(thing={"type": "rectangle", "bsdf": m.load_dict(
            {"type": "twosided", "a": {"type": "diffuse"}, "b": {"type": "conductor"}})}))
    built = m.load_dict({"type": "twosided", "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}})
    mat = load_mitsuba(minimal_scene(thing={"type": "rectangle", "bsdf": built})).materials[0]
    assert (mat.kind, mat.distribution, mat.twosided) == ("rough_conductor", "ggx", True)
    assert mat.roughness == pytest.approx(0.3)


def test20_rendering_settings_are_accepted_and_not_used():
    d = minimal_scene(floor={"type": "rectangle"})
    d["integrator"] = {"type": "volpath", "max_depth": 12}
    d["sensor"]["sampler"] = {"type": "stratified", "sample_count": 16}
    d["sensor"]["film"]["rfilter"] = {"type": "gaussian"}
    assert load_mitsuba(d).num_faces == 2
