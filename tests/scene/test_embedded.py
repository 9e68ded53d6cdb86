"""The embedded default scenes and the builder that makes them.

Geometry checks use a small numpy ray/triangle intersector (Moeller-Trumbore), so they need no tracing
backend. The cornell scene goes through the Mitsuba loader and is tested only where that loader exists.
"""
import importlib.util

import numpy as np
import pytest

from suite.errors import UserError
from suite.core.scene.builder import CameraScript, SceneBuilder
from suite.core.scene.embedded import ARENA_GRID, ARENA_ROOM_HALF_M, EMBEDDED, arena_corridors, arena_room_centers

BUILT_IN_CODE = ("living_room", "atrium", "arena", "gallery")
SAMPLE_DT_S = 1.0 / 120.0


@pytest.fixture(scope="module")
def scenes():
    return {name: EMBEDDED[name]() for name in BUILT_IN_CODE}


# --- helpers --------------------------------------------------------------------------------------

def first_hit_t(scene, origins, dirs, t_s=0.0):
    """Nearest hit distance per ray (inf on a miss), brute force over all faces."""
    tri = scene.triangles(scene.positions_at(t_s)).astype(np.float64)
    p0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.full(len(origins), np.inf)
    for i, (o, d) in enumerate(zip(np.asarray(origins, np.float64), np.asarray(dirs, np.float64))):
        pvec = np.cross(d, e2)
        det = np.einsum("fk,fk->f", e1, pvec)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = o - p0
        u = np.einsum("fk,fk->f", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        v = (qvec @ d) * inv
        t = np.einsum("fk,fk->f", e2, qvec) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
        if hit.any():
            out[i] = t[hit].min()
    return out


def overlapping_coplanar_face_pairs(scene):
    """(i, j) pairs of distinct faces on one plane whose interiors overlap (sampled at 7 interior points).
    Such faces make the nearest hit ambiguous, so two tracing backends could report different primitives."""
    tri = scene.triangles().astype(np.float64)
    n = scene.face_normals().astype(np.float64)
    n *= np.where(n[np.arange(len(n)), np.abs(n).argmax(axis=1)] < 0, -1.0, 1.0)[:, None]
    keys = np.concatenate([np.round(n, 4), np.round(np.einsum("fk,fk->f", n, tri[:, 0]), 3)[:, None]], axis=1)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    weights = np.array([[1 / 3, 1 / 3, 1 / 3], [0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8],
                        [0.45, 0.45, 0.1], [0.1, 0.45, 0.45], [0.45, 0.1, 0.45]])
    pairs = []
    for g in np.unique(group):
        idx = np.nonzero(group.reshape(-1) == g)[0]
        if len(idx) < 2:
            continue
        points = np.einsum("sv,fvk->fsk", weights, tri[idx]).reshape(-1, 3)  # (G*7, 3)
        owner = np.repeat(idx, len(weights))
        a, e1, e2 = tri[idx, 0], tri[idx, 1] - tri[idx, 0], tri[idx, 2] - tri[idx, 0]
        rel = points[:, None, :] - a[None]  # (P, G, 3)
        d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
        r1, r2 = (rel * e1).sum(2), (rel * e2).sum(2)
        den = d11 * d22 - d12 * d12
        u = (d22 * r1 - d12 * r2) / den
        v = (d11 * r2 - d12 * r1) / den
        inside = (u > 1e-4) & (v > 1e-4) & (u + v < 1 - 1e-4) & (owner[:, None] != idx[None])
        for p_i, t_i in zip(*np.nonzero(inside)):
            pairs.append((int(owner[p_i]), int(idx[t_i])))
    return sorted(set(pairs))


def path_samples(camera):
    times = np.arange(0.0, camera.duration_s + 1e-9, SAMPLE_DT_S) + camera.keys[0].t_s
    poses = [camera.pose_at(t) for t in times]
    positions = np.array([p.position for p in poses])
    forwards = np.array([p.basis()[0] for p in poses])
    return times, positions, forwards


def yaw_deg(forwards):
    return np.degrees(np.unwrap(np.arctan2(-forwards[:, 0], -forwards[:, 2])))


# --- determinism and counts -----------------------------------------------------------------------

@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_two_builds_of_a_scene_are_identical(scenes, name):
    a, b = scenes[name], EMBEDDED[name]()
    for field in ("positions", "normals", "uvs", "faces", "face_material", "face_object"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert [m.name for m in a.materials] == [m.name for m in b.materials]
    assert all(np.array_equal(x.position, y.position) and np.array_equal(x.intensity, y.intensity)
               for x, y in zip(a.point_lights, b.point_lights))
    assert [(k.t_s, tuple(k.position), tuple(k.target)) for k in a.camera.keys] == \
           [(k.t_s, tuple(k.position), tuple(k.target)) for k in b.camera.keys]


def test_living_room_has_exactly_three_point_lights_and_no_area_lights(scenes):
    scene = scenes["living_room"]
    assert len(scene.point_lights) == 3
    assert len(scene.emissive_faces()) == 0


def test_living_room_walls_are_pink(scenes):
    wall = next(m for m in scenes["living_room"].materials if m.name == "pink_wall")
    assert wall.albedo[0] > wall.albedo[2] > wall.albedo[1]


def test_arena_has_at_least_sixty_point_lights(scenes):
    assert len(scenes["arena"].point_lights) >= 60


def test_atrium_has_both_area_and_point_lights(scenes):
    scene = scenes["atrium"]
    assert len(scene.point_lights) > 0
    assert len(scene.emissive_faces()) > 0


@pytest.mark.parametrize("name,max_faces", [("living_room", 5000), ("atrium", 20000), ("arena", 30000)])
def test_triangle_count_stays_moderate(scenes, name, max_faces):
    assert 0 < scenes[name].num_faces < max_faces


def test_atrium_court_is_open_to_the_sky(scenes):
    scene = scenes["atrium"]
    up = np.array([[0.0, 1.0, 0.0]])
    assert np.isinf(first_hit_t(scene, np.array([[0.0, 1.7, 0.0]]), up))[0]
    # ...while the ground-floor gallery has a ceiling (the upper gallery's floor slab).
    assert np.isfinite(first_hit_t(scene, np.array([[0.0, 1.7, 4.4]]), up))[0]


# --- geometry validity ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_face_normals_agree_with_stored_vertex_normals(scenes, name):
    scene = scenes[name]
    face_n = scene.face_normals().astype(np.float64)
    vert_n = scene.normals[scene.faces].astype(np.float64)
    dots = np.einsum("fk,fvk->fv", face_n, vert_n)
    assert (dots > 0).all(), f"{int((dots <= 0).any(axis=1).sum())} faces are wound against their normals"


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_no_degenerate_faces_and_finite_bounds(scenes, name):
    scene = scenes[name]
    assert scene.face_areas().min() > 1e-8
    lo, hi = scene.bounds()
    assert np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()
    assert np.isfinite(scene.normals).all()
    np.testing.assert_allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_no_two_coplanar_faces_overlap(scenes, name):
    pairs = overlapping_coplanar_face_pairs(scenes[name])
    assert not pairs, f"{len(pairs)} overlapping coplanar face pairs, e.g. {pairs[:3]}"


def test_overlap_check_finds_two_boxes_sharing_a_face():
    b = SceneBuilder()
    m = b.add_material("m", albedo=0.5)
    b.add_box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), m)
    b.add_box((1.0, 0.0, 0.0), (2.0, 1.0, 1.0), m)
    b.set_camera(CameraScript((0.0, 0.5, 5.0)).keys)
    assert len(overlapping_coplanar_face_pairs(b.build("two_boxes"))) > 0


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_uvs_lie_in_the_unit_square(scenes, name):
    uvs = scenes[name].uvs
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_lights_lie_inside_the_scene_and_are_positive(scenes, name):
    scene = scenes[name]
    lo, hi = scene.bounds()
    for t_s in (0.0, scene.camera.duration_s / 3, scene.camera.duration_s):
        for light in scene.lights_at(t_s):
            assert (light.position > lo).all() and (light.position < hi).all(), light.name
            assert (light.intensity > 0).all(), light.name


# --- camera paths ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_camera_path_lasts_about_four_seconds_at_30_fps(scenes, name):
    cam = scenes[name].camera
    assert 3.5 <= cam.duration_s <= 4.5
    assert cam.fps == 30.0
    assert tuple(cam.resolution) == (320, 180)


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_camera_path_contains_a_fast_rotation(scenes, name):
    _, _, forwards = path_samples(scenes[name].camera)
    yaw = yaw_deg(forwards)
    window = int(round(0.3 / SAMPLE_DT_S))
    fastest_deg = np.abs(yaw[window:] - yaw[:-window]).max()
    assert fastest_deg >= 80.0, f"largest yaw change in 0.3 s is only {fastest_deg:.1f} deg"


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_camera_path_contains_a_walk_and_a_backward_move(scenes, name):
    _, positions, forwards = path_samples(scenes[name].camera)
    velocity = np.diff(positions, axis=0) / SAMPLE_DT_S
    along_view_m_s = np.einsum("tk,tk->t", velocity, forwards[:-1])
    backward_s = (along_view_m_s < -0.5).sum() * SAMPLE_DT_S
    forward_s = (along_view_m_s > 0.5).sum() * SAMPLE_DT_S
    assert backward_s >= 0.5, f"camera moves backward for only {backward_s:.2f} s"
    assert forward_s >= 0.5, f"camera walks forward for only {forward_s:.2f} s"


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_camera_keyframes_lie_inside_the_scene_bounds(scenes, name):
    scene = scenes[name]
    lo, hi = scene.bounds()
    for key in scene.camera.keys:
        assert (key.position > lo).all() and (key.position < hi).all(), f"key at t={key.t_s} s is outside"


@pytest.mark.parametrize("name", BUILT_IN_CODE)
def test_camera_never_starts_inside_or_against_geometry(scenes, name):
    # A camera inside a wall or furniture would see a surface at (nearly) zero distance in some direction.
    scene = scenes[name]
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    for key in scene.camera.keys:
        t = first_hit_t(scene, np.repeat(key.position[None], len(dirs), 0), dirs, key.t_s)
        assert t.min() > 0.25, f"key at t={key.t_s} s is {t.min():.3f} m from a surface"


# --- arena: rooms, corridors, dynamics ------------------------------------------------------------

def test_arena_has_at_least_six_rooms_joined_into_one_level():
    centers = arena_room_centers()
    assert len(centers) >= 6
    # Every room is reachable through corridors.
    nx = ARENA_GRID[0]
    links = {(a[0] + nx * a[1], b[0] + nx * b[1]) for a, b, _ in arena_corridors()}
    reached, frontier = {0}, [0]
    while frontier:
        r = frontier.pop()
        for a, b in links:
            for x, y in ((a, b), (b, a)):
                if x == r and y not in reached:
                    reached.add(y)
                    frontier.append(y)
    assert reached == set(range(len(centers)))


def test_arena_walls_occlude_every_room_from_every_other(scenes):
    scene = scenes["arena"]
    centers = arena_room_centers() + np.array([0.0, 1.7, 0.0])
    pairs = [(i, j) for i in range(len(centers)) for j in range(i + 1, len(centers))]
    origins = np.array([centers[i] for i, _ in pairs])
    delta = np.array([centers[j] - centers[i] for i, j in pairs])
    dist = np.linalg.norm(delta, axis=1)
    t = first_hit_t(scene, origins, delta / dist[:, None])
    blocked = t < dist - 1e-3
    assert blocked.all(), f"rooms see each other: {[p for p, b in zip(pairs, blocked) if not b]}"


def test_arena_corridors_let_adjacent_rooms_see_through_their_doors(scenes):
    scene = scenes["arena"]
    centers = arena_room_centers()
    nx = ARENA_GRID[0]
    origins, dirs, dists = [], [], []
    for a, b, offset in arena_corridors():
        ca, cb = centers[a[0] + nx * a[1]], centers[b[0] + nx * b[1]]
        axis = 0 if a[1] == b[1] else 2
        start, end = ca.copy(), cb.copy()
        start[2 - axis] += offset
        end[2 - axis] += offset
        start[axis] += ARENA_ROOM_HALF_M - 1.0  # 1 m inside room a, in front of its door
        end[axis] -= ARENA_ROOM_HALF_M - 1.0
        start[1] = end[1] = 1.5
        d = end - start
        origins.append(start)
        dirs.append(d / np.linalg.norm(d))
        dists.append(np.linalg.norm(d))
    t = first_hit_t(scene, np.array(origins), np.array(dirs))
    assert (t > np.array(dists)).all(), "a corridor is blocked"


def test_arena_has_one_moving_object_and_one_moving_light(scenes):
    scene = scenes["arena"]
    assert scene.is_dynamic
    assert len(scene.object_animations) == 1 and len(scene.light_animations) == 1
    moving = scene.object_animations[0].object_id
    assert scene.object_names[moving] == "moving_platform"
    moved = np.linalg.norm(scene.positions_at(2.0) - scene.positions_at(0.0), axis=1)
    vert_object = np.full(len(scene.positions), -1)
    vert_object[scene.faces.reshape(-1)] = np.repeat(scene.face_object, 3)
    assert (moved[vert_object == moving] > 1.0).all()
    assert (moved[vert_object != moving] == 0).all()
    light = scene.light_animations[0].light_index
    assert scene.point_lights[light].name == "moving_light"
    assert np.linalg.norm(scene.lights_at(2.0)[light].position - scene.lights_at(0.0)[light].position) > 1.0


def test_other_embedded_scenes_are_static(scenes):
    assert not scenes["living_room"].is_dynamic
    assert not scenes["atrium"].is_dynamic
    assert not scenes["gallery"].is_dynamic


def test_gallery_has_one_of_each_material_kind_and_both_light_types(scenes):
    scene = scenes["gallery"]
    used = {scene.materials[m].kind for m in np.unique(scene.face_material)}
    assert used == {"diffuse", "mirror", "glass", "rough_conductor", "rough_plastic"}
    assert any(m.is_alpha_tested for m in scene.materials) and scene.has_alpha_tested
    assert len(scene.point_lights) == 2 and len(scene.area_light_triangles()) == 2


# --- builder --------------------------------------------------------------------------------------

def _one_box_scene(**box_kwargs):
    b = SceneBuilder()
    m = b.add_material("m", albedo=0.5)
    b.add_box((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0), m, **box_kwargs)
    b.set_camera(CameraScript((0.0, 0.0, 10.0)).keys)
    return b.build("box")


def test_box_faces_point_outward_and_inward_box_faces_point_in():
    for inward, sign in ((False, 1.0), (True, -1.0)):
        scene = _one_box_scene(inward=inward)
        centres = scene.triangles().mean(axis=1)
        assert (np.einsum("fk,fk->f", scene.face_normals(), centres) * sign > 0).all()
        assert scene.num_faces == 12


def test_box_open_faces_are_left_out():
    scene = _one_box_scene(open_faces=("-y", "+z"))
    assert scene.num_faces == 8
    assert not (scene.face_normals()[:, 1] < -0.99).any()


def test_cylinder_side_normals_point_away_from_the_axis():
    b = SceneBuilder()
    m = b.add_material("m", albedo=0.5)
    b.add_cylinder((2.0, 0.0, 3.0), 0.5, 2.0, 12, m)
    b.set_camera(CameraScript((0.0, 1.0, 10.0)).keys)
    scene = b.build("cyl")
    radial = scene.positions - np.array([2.0, 0.0, 3.0])
    radial[:, 1] = 0
    side = np.abs(scene.normals[:, 1]) < 0.5
    assert side.any() and (np.einsum("vk,vk->v", radial[side], scene.normals[side]) > 0).all()
    assert (np.einsum("fk,fvk->fv", scene.face_normals(), scene.normals[scene.faces]) > 0).all()


def test_area_light_quad_faces_the_stated_direction():
    b = SceneBuilder()
    b.add_area_light_quad("panel", (0.0, 3.0, 0.0), (1.0, 0.5), (0.0, -1.0, 0.0), radiance=10.0)
    b.set_camera(CameraScript((0.0, 1.0, 5.0)).keys)
    scene = b.build("panel")
    np.testing.assert_allclose(scene.face_normals(), [[0.0, -1.0, 0.0]] * 2, atol=1e-6)
    assert scene.face_areas().sum() == pytest.approx(0.5)
    assert len(scene.emissive_faces()) == 2


def test_builder_rejects_a_triangle_wound_against_its_normals():
    b = SceneBuilder()
    m = b.add_material("m", albedo=0.5)
    with pytest.raises(UserError, match="wound against"):
        b.add_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, -1]] * 3, [[0, 0]] * 3, [[0, 1, 2]], m)


def test_builder_rejects_duplicate_names_and_an_unanimatable_static_object():
    b = SceneBuilder()
    b.add_material("m", albedo=0.5)
    with pytest.raises(UserError, match="defined twice"):
        b.add_material("m", albedo=0.2)
    with pytest.raises(UserError, match="static"):
        b.add_object_animation(0, [0.0, 1.0], [[0, 0, 0], [1, 0, 0]])


def test_camera_script_turn_reaches_the_requested_yaw_at_the_requested_time():
    cam = CameraScript((0.0, 1.0, 0.0), yaw_deg=0.0)
    cam.turn(90.0, 0.3)
    assert cam.keys[-1].t_s == pytest.approx(0.3)
    np.testing.assert_allclose(cam.keys[-1].target - cam.keys[-1].position, [-1.0, 0.0, 0.0], atol=1e-12)


# --- cornell (through the Mitsuba loader) ---------------------------------------------------------

@pytest.mark.skipif(importlib.util.find_spec("suite.core.scene.mitsuba_io") is None,
                    reason="the Mitsuba loader is not available")
def test_cornell_loads_with_a_gentle_path_around_the_original_sensor():
    scene = EMBEDDED["cornell"]()
    assert scene.name == "cornell"
    assert len(scene.emissive_faces()) > 0
    cam = scene.camera
    assert tuple(cam.resolution) == (256, 256) and cam.fov_deg == pytest.approx(39.3077)
    pose = cam.pose_at(0.0)
    np.testing.assert_allclose(pose.position, [0.0, 0.0, 3.9])
    np.testing.assert_allclose(pose.target, [0.0, 0.0, 0.0])
    _, positions, forwards = path_samples(cam)
    assert np.abs(np.diff(yaw_deg(forwards))).max() / SAMPLE_DT_S < 60.0  # gentle: under 60 deg/s
    assert np.linalg.norm(positions - [0.0, 0.0, 3.9], axis=1).max() < 1.0
