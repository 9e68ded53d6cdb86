"""dabrovic_sponza: the OBJ from the scene search path with the project's sidecar (lights, materials, camera)."""
import hashlib
import shutil

import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene import list_scenes, load
from suite.core.scene.obj import loader as obj_loader
from suite.core.scene.search import find_scene_file

DESC = list_scenes().get("dabrovic_sponza", "unavailable: not listed")
pytestmark = pytest.mark.skipif(DESC.startswith("unavailable"), reason=DESC)
SHA256 = "67d1b2b4002b3bc38e9d718b80c63f197bef8709e1bbefce14a565a0830eb020"


@pytest.fixture(scope="module")
def sponza():
    return load("dabrovic_sponza")


@pytest.fixture(scope="module")
def tracer(sponza):
    from suite.core.trace import make

    return make("embree", sponza)


def test01_counts_materials_and_lights(sponza):
    c = sponza.obj.counts
    assert c["triangles_read"] == 66447 and c["triangles"] == 66446 and c["zero_area_triangles_dropped"] == 1
    assert c["objects"] == 33 and len(sponza.object_names) == 33
    assert c["faces_mapped_by_sidecar"] == 66447  # every object group has a colour from the sidecar
    assert sponza.obj.sha256 == SHA256 and sponza.obj.unsupported == {} and sponza.obj.missing_textures == []
    assert len(sponza.point_lights) == 5 and len(sponza.light_animations) == 5
    assert sponza.obj.defaults == []
    assert 3.5 <= sponza.camera.duration_s <= 4.5 and sponza.camera.fps == 30.0
    assert "CC BY-NC" in sponza.description


def _clearance(tracer, points, n_dirs=26):
    dirs = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                    np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = np.repeat(np.asarray(points, np.float64), len(dirs), axis=0)
    d = np.tile(dirs, (len(points), 1))
    hits = tracer.intersect(o.astype(np.float32), d.astype(np.float32))
    return hits.t.reshape(len(points), len(dirs)), hits.prim.reshape(len(points), len(dirs))


def test02_camera_stays_in_the_atrium_clear_of_geometry(sponza, tracer):
    cam = sponza.camera
    times = np.arange(0.0, cam.duration_s + 1e-9, 1.0 / cam.fps)
    eyes = np.array([cam.pose_at(t).position for t in times])
    # Inside the open court (x in [-10.5, 10.5], z in [-2.2, 2.2]) at eye height above its floor (y = 0.09).
    assert (np.abs(eyes[:, 0]) < 10.5).all() and (np.abs(eyes[:, 2]) < 2.2).all()
    assert np.allclose(eyes[:, 1], 1.8)
    t, _ = _clearance(tracer, eyes)
    assert t.min() > 0.8  # no wall, column or floor within 0.8 m of any frame's eye
    # Consecutive frames are not separated by geometry.
    seg = eyes[1:] - eyes[:-1]
    length = np.linalg.norm(seg, axis=1)
    moving = length > 0
    d = seg[moving] / length[moving, None]
    assert not tracer.occluded(eyes[:-1][moving].astype(np.float32), d.astype(np.float32), 0.0,
                               length[moving].astype(np.float32)).any()
    # A fast turn: 90 degrees of yaw within 0.3 s.
    fwd = np.array([cam.pose_at(t).basis()[0] for t in times])
    yaw = np.degrees(np.unwrap(np.arctan2(fwd[:, 0], fwd[:, 2])))
    step = int(round(0.3 * cam.fps))
    assert np.abs(yaw[step:] - yaw[:-step]).max() >= 89.0


def test03_lights_move_inside_the_building_then_hold(sponza, tracer):
    lo, hi = sponza.bounds()
    times = np.linspace(0.0, sponza.camera.duration_s, 41)
    pos = np.array([[lt.position for lt in sponza.lights_at(t)] for t in times])  # (T, L, 3)
    assert ((pos > lo) & (pos < hi)).all()
    t, prim = _clearance(tracer, pos.reshape(-1, 3))
    assert t.min() > 0.3
    # Not inside a closed solid: the surfaces around every light face it.
    ng = sponza.face_normals().astype(np.float64)[prim]
    dirs = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                    np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    facing = (prim < 0) | (np.einsum("lkc,kc->lk", ng, dirs) < 0)  # a miss: open sky above the court
    assert facing.mean(axis=1).min() > 0.5
    # Every light moves for the first 3.5 s (seed 004: light sources on a scripted path) and holds at the end.
    moved = np.linalg.norm(pos[times <= 3.5][-1] - pos[0], axis=1)
    assert (moved > 5.0).all()
    np.testing.assert_allclose(pos[times >= 3.5], np.broadcast_to(pos[times >= 3.5][:1], pos[times >= 3.5].shape))


def test04_same_file_by_path_gets_the_project_sidecar_by_hash(sponza):
    path = find_scene_file("dabrovic_sponza/sponza.obj")
    scene = load(str(path))
    assert scene.name == "dabrovic_sponza" and len(scene.point_lights) == 5


def test05_a_file_with_another_hash_is_an_error_naming_both(tmp_path, monkeypatch):
    folder = tmp_path / "dabrovic_sponza"
    folder.mkdir()
    copy = folder / "sponza.obj"
    shutil.copy(find_scene_file("dabrovic_sponza/sponza.obj"), copy)
    with open(copy, "a") as fh:
        fh.write("# edited\n")
    monkeypatch.setenv("SPLITBENCH_SCENE_PATH", str(tmp_path))
    obj_loader._scene_cache.clear()
    with pytest.raises(UserError) as info:
        load("dabrovic_sponza")
    msg = str(info.value)
    assert "dabrovic_sponza.toml" in msg and str(copy) in msg and SHA256 in msg
    assert hashlib.sha256(copy.read_bytes()).hexdigest() in msg


def test06_the_static_version_has_the_same_model_and_camera_and_holds_the_lights_where_they_start(sponza):
    """dabrovic_sponza_static: seed 002's static Sponza beside the moving-lights one (the same first frame)."""
    static = load("dabrovic_sponza_static")
    assert static.name == "dabrovic_sponza_static" and not static.light_animations and sponza.light_animations
    np.testing.assert_array_equal(static.positions, sponza.positions)
    np.testing.assert_array_equal(static.face_material, sponza.face_material)
    assert [(m.name, tuple(m.albedo)) for m in static.materials] == [(m.name, tuple(m.albedo))
                                                                      for m in sponza.materials]
    start = [(lt.position.tolist(), lt.intensity.tolist()) for lt in sponza.lights_at(0.0)]
    for t in np.linspace(0.0, sponza.camera.duration_s, 9):
        assert [(lt.position.tolist(), lt.intensity.tolist()) for lt in static.lights_at(t)] == start
        a, b = sponza.camera.pose_at(t), static.camera.pose_at(t)
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.target, b.target)
