"""Tracing backends: both backends see the same scene (parity), robust origins, counters, updates."""
import numpy as np
import pytest

from suite.errors import UserError
from suite.core.gbuffer import camera_rays
from suite.core.scene import list_scenes, load
from suite.core.trace import backend_params, make, offset_ray_origin

# Scenes whose data is not installed (OpenArena maps) are listed as "unavailable: <fix>"; they are skipped.
SCENES = [pytest.param(name, marks=pytest.mark.skip(reason=desc)) if desc.startswith("unavailable") else name
          for name, desc in sorted(list_scenes().items())]


def random_rays(scene, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds()
    origins = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return origins, dirs.astype(np.float32)


MITSUBA = backend_params("mitsuba-llvm", "mitsuba-cuda")


@pytest.mark.parametrize("mitsuba", MITSUBA)
@pytest.mark.parametrize("scene_name", SCENES)
def test01_backends_agree_on_hits_primitives_and_distances(scene_name, mitsuba):
    scene = load(scene_name)
    o1, d1 = random_rays(scene, 20000, seed=1)
    o2, d2 = camera_rays(scene.camera.pose_at(0.0), scene.camera.fov_deg, 96, 54)
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    he, hm = make("embree", scene).intersect(o, d), make(mitsuba, scene).intersect(o, d)
    assert np.mean(he.hit == hm.hit) >= 0.999
    assert np.mean(he.prim == hm.prim) >= 0.999
    same = he.hit & hm.hit & (he.prim == hm.prim)
    rel = np.abs(he.t[same] - hm.t[same]) / np.maximum(np.abs(he.t[same]), 1e-6)
    assert np.mean(rel <= 1e-4) >= 0.999


@pytest.mark.parametrize("mitsuba", MITSUBA)
@pytest.mark.parametrize("scene_name", ["living_room", "arena"])
def test02_backends_agree_on_occlusion_with_finite_tmax(scene_name, mitsuba):
    scene = load(scene_name)
    o, d = random_rays(scene, 20000, seed=2)
    tmax = np.random.default_rng(3).uniform(0.1, 5.0, len(o)).astype(np.float32)
    oe = make("embree", scene).occluded(o, d, 0.0, tmax)
    om = make(mitsuba, scene).occluded(o, d, 0.0, tmax)
    assert 0.05 < oe.mean() < 0.95  # a meaningful mix of blocked and free rays
    assert np.mean(oe == om) >= 0.999


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test03_tmin_skips_hits_before_it_and_reports_t_from_the_original_origin(backend, room_scene):
    tracer = make(backend, room_scene)
    o = np.array([[0, 1, 0]], np.float32)
    d = np.array([[1, 0, 0]], np.float32)
    # Block B spans x in [0.5, 1.8] but only up to y = 0.6; at y = 1 the ray reaches the wall at x = 3.
    assert tracer.intersect(o, d).t[0] == pytest.approx(3.0, rel=1e-5)
    o_low = np.array([[0, 0.3, 1.0]], np.float32)
    assert tracer.intersect(o_low, d).t[0] == pytest.approx(0.5, rel=1e-5)
    assert tracer.intersect(o_low, d, tmin=1.0).t[0] == pytest.approx(1.8, rel=1e-5)  # far side of block B
    assert tracer.intersect(o_low, d, tmin=2.0).t[0] == pytest.approx(3.0, rel=1e-5)
    assert tracer.occluded(o_low, d, 0.0, 0.4)[0] == np.False_
    assert tracer.occluded(o_low, d, 0.0, 0.6)[0] == np.True_


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test04_counters_count_every_ray(backend, room_scene):
    tracer = make(backend, room_scene)
    o = np.zeros((10, 3), np.float32)
    d = np.tile(np.float32([0, 1, 0]), (10, 1))
    tracer.intersect(o, d)
    tracer.occluded(o, d, 0, 1.0)
    tracer.occluded(o[:3], d[:3], 0, 1.0)
    assert tracer.counters == {"rays_intersect": 10, "rays_occluded": 13}


def test05_robust_offset_scales_with_coordinate_magnitude():
    from suite.core.trace.robust import OFFSET_ULPS

    n = np.array([[0, 1, 0]], np.float64)
    steps = []
    for magnitude in (100.0, 1e4):
        p = np.array([[magnitude, magnitude, magnitude]], np.float64)
        step = offset_ray_origin(p, n)[0, 1] - p[0, 1]
        assert step == pytest.approx(OFFSET_ULPS * float(np.spacing(np.float32(magnitude))), rel=1e-6)
        assert offset_ray_origin(p, -n)[0, 1] < p[0, 1]  # the other side moves the other way
        steps.append(step)
    assert steps[1] / steps[0] > 50  # not a fixed epsilon
    # Near the origin, where ULPs vanish, an absolute floor keeps the point off the surface.
    assert offset_ray_origin(np.zeros((1, 3)), n)[0, 1] > 1e-7
    # The offset is sized for coordinates in the tracer's frame: a point at the world origin traced in a
    # frame centred 20 units away gets the ULPs of 20.
    shifted = offset_ray_origin(np.zeros((1, 3)), n, frame_shift=[20.0, 0, 0])[0, 1]
    assert shifted == pytest.approx(OFFSET_ULPS * float(np.spacing(np.float32(20.0))), rel=1e-6)


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test06_update_moves_animated_objects(backend):
    scene = load("arena")
    anim = scene.object_animations[0]
    faces = np.nonzero(scene.face_object == anim.object_id)[0]
    tracer = make(backend, scene)

    def platform_probe(t):
        """A downward ray from 0.2 m above the centre of the platform's top at time t."""
        tri = scene.triangles(scene.positions_at(t))[faces].reshape(-1, 3)
        top = np.array([tri[:, 0].mean(), tri[:, 1].max() + 0.2, tri[:, 2].mean()], np.float32)
        return top[None], np.float32([[0, -1, 0]])

    t_rest, t_moved = float(anim.times_s[0]), float(anim.times_s[1])
    probe_rest, probe_moved = platform_probe(t_rest), platform_probe(t_moved)
    for t, hits_at_rest in ((t_rest, True), (t_moved, False), (t_rest, True)):
        tracer.update(t)
        hit_rest = scene.face_object[tracer.intersect(*probe_rest).prim[0]] == anim.object_id
        hit_moved = scene.face_object[tracer.intersect(*probe_moved).prim[0]] == anim.object_id
        assert hit_rest == hits_at_rest
        assert hit_moved == (not hits_at_rest)


def test07_unknown_backend_is_a_user_error(room_scene):
    with pytest.raises(UserError, match="unknown backend 'optix'"):
        make("optix", room_scene)


def test08_scalar_variant_is_a_slow_but_correct_last_resort(room_scene):
    """mitsuba-scalar traces one ray at a time; it must agree with the vectorised backends."""
    o = np.tile(np.float32([[0, 1, 0]]), (64, 1))
    rng = np.random.default_rng(4)
    d = rng.normal(size=(64, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = make("embree", room_scene)
    scalar = make("mitsuba-scalar", room_scene)
    try:
        hs, he = scalar.intersect(o, d), ref.intersect(o, d)
        np.testing.assert_array_equal(hs.prim, he.prim)
        np.testing.assert_allclose(hs.t, he.t, rtol=1e-5)
        np.testing.assert_array_equal(scalar.occluded(o, d, 0.0, 1.0), ref.occluded(o, d, 0.0, 1.0))
    finally:
        from suite.core.env import mitsuba

        mitsuba("llvm")  # the variant is process-global: restore the default for later tests


@pytest.mark.parametrize("scene_name", ["cornell", "dabrovic_sponza"])
def test09_compiled_surface_attributes_give_the_bits_of_the_numpy_reference(scene_name):
    """The G-buffer's per-hit pass (numba) against the whole-array numpy expressions it replaces: positions on the
    ray's plane intersection and barycentric, both normals, textured and flat albedo, emission; and the facing."""
    from suite.core import gbuffer as gb

    try:
        scene = load(scene_name)
    except UserError as exc:
        pytest.skip(f"scene data not available: {exc}")
    g, o64, d64, hits = gb.trace_primary(scene, make("embree", scene), 0.0, (48, 32))
    idx = np.nonzero(hits.prim >= 0)[0]
    assert 0 < len(idx)
    args = (scene, scene.positions_at(0.0), scene.normals_at(0.0), hits.prim[idx], hits.u[idx], hits.v[idx])
    for rays in ((o64[idx], d64[idx]), ()):
        for a, b in zip(gb.surface_attributes(*args, *rays), gb.surface_attributes_reference(*args, *rays)):
            assert a.dtype == b.dtype and np.array_equal(a, b)
    _, ng, ns, _, _ = gb.surface_attributes(*args, o64[idx], d64[idx])
    d = g.view_dir.reshape(-1, 3)[idx].astype(np.float64)
    flip = np.sign(np.einsum("ij,ij->i", ng, d))[:, None]
    flip[flip == 0] = 1.0
    ng_view = -flip * ng
    ns_view = np.where(np.einsum("ij,ij->i", ns, ng_view)[:, None] < 0, -ns, ns)
    out = gb.facing(ng, ns, g.view_dir.reshape(-1, 3)[idx])
    assert np.array_equal(out[0], ng_view.astype(np.float32)) and np.array_equal(out[1], ns_view.astype(np.float32))
    assert np.array_equal(out[2], flip[:, 0] < 0)


def test10_ray_arguments_take_the_bits_of_the_numpy_column_passes():
    """as_rays moves origins into the tracing frame and advances them by tmin (scalar or per ray) in one compiled
    pass for large row-major batches: the same float32 bits as numpy's column subtraction in the origins' own
    precision followed by ``o += d * tmin``."""
    from suite.core.trace.base import as_rays

    rng = np.random.default_rng(0)
    n = 20000  # above the compiled pass's threshold
    shift = np.array([12.3, -45.6, 7.89])
    d = rng.normal(size=(n, 3)).astype(np.float32)
    for dtype in (np.float32, np.float64):
        o = (rng.normal(size=(n, 3)) * 1000).astype(dtype)
        for tmin in (0.0, np.float32(0.25), (rng.random(n) * 50).astype(np.float32)):
            got, _, _, _ = as_rays(o, d, tmin, np.inf, shift)
            expected = np.empty((n, 3), np.float32)
            for c in range(3):
                np.subtract(o[:, c], shift[c], out=expected[:, c], casting="unsafe")
            if np.ndim(tmin) or tmin > 0:
                expected += d * np.broadcast_to(np.float32(tmin), (n,))[:, None]
            assert np.array_equal(got, expected)


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
@pytest.mark.parametrize("scene_name", ["cornell", "gallery"])
def test11_rays_made_in_the_tracing_frame_ahead_get_the_hits_of_intersect(backend, scene_name):
    """``intersect_local`` of the rays ``local_rays`` made (what a pipeline's worker makes while the backend traces
    other rays) answers as ``intersect`` does, alpha-tested walks (gallery) included, and counts the same rays."""
    from suite.core.pipeline import local_rays, trace_local

    scene = load(scene_name)
    tracer = make(backend, scene)
    o, d = random_rays(scene, 3000, 11)
    whole = tracer.intersect(o, d)
    counted = tracer.counters["rays_intersect"]
    tracer.reset_counters()
    query = local_rays(tracer, o, d)
    assert query is not None
    ahead = trace_local(tracer, query, o, d)
    assert tracer.counters["rays_intersect"] == counted
    for field in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(whole, field), getattr(ahead, field)), field
    assert (whole.prim >= 0).mean() > 0.5
