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
