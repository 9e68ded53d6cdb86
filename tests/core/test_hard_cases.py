"""Numerically hard cases: grazing light, far-from-origin scenes, lights on surfaces, closed occluders,
degenerate triangles. Each runs on both backends."""
import numpy as np
import pytest

from suite.core.gbuffer import render_gbuffer
from suite.core.scene import load
from suite.core.scene.model import PointLight
from suite.core.shading import direct_lighting, point_light_visibility, shade_point_lights
from suite.core.trace import backend_params, make

# Every backend; mitsuba-cuda is skipped with its reason where no GPU is usable.
BACKENDS = backend_params("embree", "mitsuba-llvm", "mitsuba-cuda")


@pytest.mark.parametrize("backend", BACKENDS)
def test01_grazing_light_at_85_degrees_leaves_no_shadow_acne(backend, grazing_plane_scene):
    scene = grazing_plane_scene
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (96, 64))
    vis = point_light_visibility(g, scene.point_lights, tracer)
    assert g.valid.mean() > 0.5
    # Nothing but the plane itself could shadow it: every visible plane pixel must be lit.
    assert vis[g.valid].all(), f"{(~vis[g.valid]).sum()} acne pixels"


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scene_name", ["living_room", "arena"])
def test02_scene_moved_1e4_units_away_gives_the_same_visibility(backend, scene_name):
    scene = load(scene_name)
    far = scene.translated([1e4, 1e4, 1e4])
    res, t_s = scene.camera.resolution, 0.5
    vis = []
    for s in (scene, far):
        tracer = make(backend, s)
        g = render_gbuffer(s, tracer, t_s, res)
        vis.append((point_light_visibility(g, s.lights_at(t_s), tracer), g.valid))
    (v0, valid0), (v1, valid1) = vis
    assert np.mean(valid0 == valid1) >= 0.995
    per_pixel_agree = (v0 == v1).all(axis=-1)
    assert np.mean(per_pixel_agree) >= 0.995


@pytest.mark.parametrize("backend", BACKENDS)
def test03_light_exactly_on_a_surface_gives_finite_results(backend, room_scene):
    scene = room_scene
    # Put a light exactly on the floor (y = 0) in the middle of the view.
    scene.point_lights = [PointLight("on_floor", [0.0, 0.0, 1.0], [3.0, 3.0, 3.0])]
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (64, 48))
    rgb = direct_lighting(scene, g, tracer, 0.0)
    assert np.isfinite(rgb).all()
    assert (rgb >= 0).all()
    assert rgb.max() > 0  # the walls around it are lit


@pytest.mark.parametrize("backend", BACKENDS)
def test04_shading_point_inside_a_closed_occluder_is_dark_and_finite(backend, room_scene):
    scene = room_scene
    # The camera sits inside block A (closed box [-1.5,-0.5]x[0,1.2]x[-1,0]); all lights are outside.
    scene.camera.keys[0].position = np.array([-1.0, 0.6, -0.5])
    scene.camera.keys[0].target = np.array([-1.0, 0.6, -2.0])
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (32, 24))
    assert g.valid.all()
    vis = point_light_visibility(g, scene.point_lights, tracer)
    assert not vis.any()
    rgb = shade_point_lights(g, scene.point_lights, vis)
    assert np.isfinite(rgb).all() and (rgb == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test05_degenerate_triangles_are_ignored_without_nan(backend, room_scene):
    scene = room_scene
    n_before = scene.num_faces
    # Append zero-area triangles: a repeated vertex, and three collinear vertices, across the view.
    base = len(scene.positions)
    extra = np.array([[-2, 1, 0], [2, 1, 0], [0, 1, 0]], np.float32)
    scene.positions = np.concatenate([scene.positions, extra])
    scene.normals = np.concatenate([scene.normals, np.tile(np.float32([0, 0, 1]), (3, 1))])
    scene.uvs = np.concatenate([scene.uvs, np.zeros((3, 2), np.float32)])
    scene.faces = np.concatenate([scene.faces, [[base, base + 1, base + 2], [base, base, base + 1]]]).astype(np.int32)
    scene.face_material = np.concatenate([scene.face_material, [0, 0]]).astype(np.int32)
    scene.face_object = np.concatenate([scene.face_object, [0, 0]]).astype(np.int32)
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (48, 32))
    rgb = direct_lighting(scene, g, tracer, 0.0)
    assert np.isfinite(rgb).all() and np.isfinite(g.normal).all()
    assert not np.isin(g.prim, [n_before, n_before + 1]).any()
    assert scene.without_degenerate_faces().num_faces == n_before


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("offset", [0.0, 1e4])
def test06_offset_origins_do_not_self_intersect_even_at_grazing_angles(backend, offset):
    """Shadow rays leaving every visible surface point into its hemisphere are not blocked within 1 mm
    any more often than with a 4x larger offset (what remains is genuine contact geometry)."""
    import suite.core.trace.robust as robust

    scene = load("atrium").translated([offset] * 3) if offset else load("atrium")
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.5, (120, 68))
    p, n = g.position[g.valid], g.geo_normal[g.valid]
    rng = np.random.default_rng(0)
    d = rng.normal(size=p.shape)
    d = np.where(np.einsum("ij,ij->i", d, n)[:, None] < 0, -d, d)
    d = d - 0.97 * np.einsum("ij,ij->i", d, n)[:, None] * n  # 1.7 to 90 degrees above the plane
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    def blocked(ulps):
        old = robust.OFFSET_ULPS
        robust.OFFSET_ULPS = ulps
        try:
            return tracer.occluded(robust.offset_ray_origin(p, n, tracer.shift), d, 0.0, np.float32(1e-3)).mean()
        finally:
            robust.OFFSET_ULPS = old

    assert blocked(robust.OFFSET_ULPS) <= blocked(4 * robust.OFFSET_ULPS) + 2e-4
    assert blocked(robust.OFFSET_ULPS) < 2e-3


def test07_many_lights_visibility_matches_one_light_at_a_time():
    """arena has >= 60 lights; batching lights into chunks must not change any bit."""
    scene = load("arena")
    tracer = make("embree", scene)
    g = render_gbuffer(scene, tracer, 0.0, (40, 24))
    lights = scene.lights_at(0.0)
    assert len(lights) >= 60
    batched = point_light_visibility(g, lights, tracer, chunk_rays=3000)
    single = np.stack([point_light_visibility(g, [lt], tracer)[..., 0] for lt in lights], axis=-1)
    np.testing.assert_array_equal(batched, single)
    assert 0 < batched.mean() < 0.5  # walls occlude most lights from most pixels


@pytest.mark.parametrize("backend", BACKENDS)
def test08_very_far_point_lights_give_finite_results(backend, grazing_plane_scene):
    # Shadow rays are made in float32 in the tracing frame (docs/core.md). A light 1e15 m above the floor lights
    # it; one 1e20 m away overflows the float32 squared distance: its rays are not traced and its bits are 0, which
    # its float64 contribution (below 1e-40 of its intensity) is anyway. Host and device passes agree on both.
    from suite.core.device import point_light_visibility as device_visibility
    from suite.core.gbuffer import render_gbuffer_device

    scene = grazing_plane_scene
    scene.point_lights = [PointLight("far", [0.0, 1e15, 0.0], [1e30] * 3),
                          PointLight("beyond", [0.0, 1e20, 0.0], [1e30] * 3)]
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (48, 32))
    vis = point_light_visibility(g, scene.point_lights, tracer)
    assert g.valid.mean() > 0.5
    assert vis[g.valid, 0].all() and not vis[..., 1].any()
    rgb = shade_point_lights(g, scene.point_lights, vis)
    assert np.isfinite(rgb).all() and rgb[g.valid].min() > 0
    if getattr(tracer, "device", None) is not None:
        dg = render_gbuffer_device(scene, tracer, 0.0, (48, 32))
        dvis = device_visibility(dg, scene.point_lights, tracer).to_host()
        assert not dvis[..., 1].any()
        assert np.mean(dvis == vis) >= (1.0 if backend == "mitsuba-llvm" else 0.999)
