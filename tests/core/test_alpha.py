"""Alpha testing in the tracers: transparent texels do not exist for camera rays or shadow rays, on both
backends, and every re-traced ray is counted."""
import numpy as np
import pytest

from suite.core.gbuffer import render_gbuffer
from suite.core.scene.builder import SceneBuilder
from suite.core.scene.model import CameraKey, Material
from suite.core.shading import point_light_visibility
from suite.core.trace import backend_params, make
from suite.core.trace.alpha import MAX_ALPHA_LAYERS

# Every backend; mitsuba-cuda is skipped with its reason where no GPU is usable.
BACKENDS = backend_params("embree", "mitsuba-llvm", "mitsuba-cuda")


def half_mask(size=16):
    """Left half (u < 0.5) transparent, right half opaque."""
    mask = np.zeros((size, size), np.float32)
    mask[:, size // 2:] = 1.0
    return mask


def screen_scene(layers=1, opacity=None, threshold=0.5):
    """A wall at z = -1 behind ``layers`` alpha-tested 2 x 2 m quads at z = 0, 0.1, ... (u along +x)."""
    b = SceneBuilder()
    wall = b.add_material("wall", albedo=0.5)
    screen = b.add_material("screen", albedo=0.8, opacity_texture=half_mask() if opacity is None else opacity,
                            alpha_threshold=threshold)
    b.add_quad(((0, 0, -1), (3, 0, 0), (0, 3, 0)), wall)
    for i in range(layers):
        b.add_quad(((0, 0, 0.1 * i), (1, 0, 0), (0, 1, 0)), screen)
    b.add_point_light("front", (0, 0, 3), 10.0)
    b.set_camera([CameraKey(0.0, (0, 0, 3), (0, 0, 0))], fov_deg=40, resolution=(32, 32))
    return b.build("screen")


def rays_toward(xs, z0=3.0):
    o = np.array([[x, 0.0, z0] for x in xs], np.float32)
    d = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (len(xs), 1))
    return o, d


@pytest.mark.parametrize("backend", BACKENDS)
def test01_camera_rays_pass_transparent_texels_and_stop_at_opaque_ones(backend):
    scene = screen_scene()
    tracer = make(backend, scene)
    o, d = rays_toward([-0.5, 0.5, -0.2, 0.2])
    hits = tracer.intersect(o, d)
    wall_faces, screen_faces = {0, 1}, {2, 3}
    assert set(hits.prim[[0, 2]]) <= wall_faces and set(hits.prim[[1, 3]]) <= screen_faces
    np.testing.assert_allclose(hits.t, [4.0, 3.0, 4.0, 3.0], rtol=1e-5)
    # 4 camera rays + 2 re-traced from past the transparent hits: the counters count the real rays.
    assert tracer.counters == {"rays_intersect": 6, "rays_occluded": 0}


@pytest.mark.parametrize("backend", BACKENDS)
def test02_shadow_rays_pass_transparent_texels(backend):
    scene = screen_scene()
    tracer = make(backend, scene)
    o, d = rays_toward([-0.5, 0.5, 2.5], z0=-0.99)  # from just in front of the wall toward +z
    d = -d
    occ = tracer.occluded(o, d, 0.0, 3.5)
    assert occ.tolist() == [False, True, False]
    # 3 shadow rays; the opaque faces (the wall behind them) block none of the 2 that the any-hit query found
    # blocked, so those walk the alpha-tested faces: 1 closest-hit query each, plus 1 re-trace past the transparent
    # hit.
    assert tracer.counters == {"rays_intersect": 3, "rays_occluded": 3}
    # A shadow ray that ends before the screen is never blocked by it, transparent or not.
    assert not tracer.occluded(o[1:2], d[1:2], 0.0, 0.5)[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test03_shadows_in_the_gbuffer_pass_through_the_holes(backend):
    """point_light_visibility (the compiled shadow-ray path) sees the light through the transparent half only."""
    scene = screen_scene()
    tracer = make(backend, scene)
    g = render_gbuffer(scene, tracer, 0.0, (32, 32))
    vis = point_light_visibility(g, scene.point_lights, tracer)[..., 0]
    on_wall = g.valid & (g.position[..., 2] < -0.5)
    seen_through = on_wall & (np.abs(g.position[..., 0]) < 0.9) & (np.abs(g.position[..., 1]) < 0.9)
    left, right = g.position[..., 0] < -0.1, g.position[..., 0] > 0.1
    assert (seen_through & left).sum() > 50 and not (on_wall & right & (np.abs(g.position[..., 0]) < 0.9)
                                                     & (np.abs(g.position[..., 1]) < 0.9)).any()
    assert vis[seen_through & left].all()  # the light shines through the holes it is seen through
    # The opaque half is visible to the camera and itself lit.
    assert vis[g.valid & (g.position[..., 2] > -0.5) & right].all()


@pytest.mark.parametrize("backend", BACKENDS)
def test04_many_layers_and_the_threshold(backend):
    scene = screen_scene(layers=5)
    tracer = make(backend, scene)
    o, d = rays_toward([-0.5])
    hits = tracer.intersect(o, d)
    assert hits.prim[0] in (0, 1) and tracer.counters["rays_intersect"] == 6  # 1 ray + 5 re-traces
    uniform = np.full((4, 4), 0.4, np.float32)
    assert make(backend, screen_scene(opacity=uniform, threshold=0.5)).intersect(o, d).prim[0] in (0, 1)
    assert make(backend, screen_scene(opacity=uniform, threshold=0.3)).intersect(o, d).prim[0] in (2, 3)
    assert MAX_ALPHA_LAYERS >= 16


def test05_scenes_without_alpha_tested_materials_pay_nothing():
    scene = screen_scene()
    assert scene.has_alpha_tested
    opaque = screen_scene(opacity=np.ones((2, 2), np.float32))
    opaque.materials[1] = Material("screen", [0.8] * 3)
    assert not opaque.has_alpha_tested and make("embree", opaque)._alpha is None
    tracer = make("embree", opaque)
    o, d = rays_toward([-0.5, 0.5])
    tracer.intersect(o, d)
    tracer.occluded(o, d, 0.0, 10.0)
    assert tracer.counters == {"rays_intersect": 2, "rays_occluded": 2}


def test06_gbuffer_carries_material_ids_and_kinds():
    from suite.core.scene import load

    scene = load("gallery")
    g = render_gbuffer(scene, make("embree", scene), 0.0, (96, 54))
    names = [m.name for m in scene.materials]
    assert ((g.material >= 0) == g.valid).all() and ((g.kind >= 0) == g.valid).all()
    for kind in ("diffuse", "mirror", "glass", "rough_conductor", "rough_plastic"):
        mask = g.kind_mask(kind)
        assert mask.any(), kind
        assert {scene.materials[m].shading_kind for m in np.unique(g.material[mask])} == {kind}
    assert (g.kind_mask("alpha") == g.kind_mask("diffuse")).all()  # the legacy kind shades as diffuse
    assert (g.material == names.index("grate")).any()
    # The existing diffuse scenes report only diffuse surfaces.
    cornell = load("cornell")
    assert set(np.unique(render_gbuffer(cornell, make("embree", cornell), 0.0, (16, 16)).kind)) <= {-1, 0}


@pytest.mark.parametrize("backend", BACKENDS)
def test07_opaque_and_alpha_groups_give_the_answer_of_the_whole_scene_walk(backend):
    """occluded in groups (an any-hit query against the opaque faces, then the walk of the open rays crossing the
    alpha-tested faces' box) blocks the same shadow rays as the walk of every blocked ray through the whole scene, on
    the host and on the device."""
    from suite.core.scene import load
    from suite.core.trace.bench import shadow_rays

    scene = load("gallery")
    o, d, tmax = shadow_rays(scene, (64, 36))
    grouped, whole = make(backend, scene), make(backend, scene)
    whole._groups = False  # no sub-scenes: the whole-scene walk
    blocked = grouped.occluded(o, d, 0.0, tmax)
    assert grouped._groups and 0 < blocked.sum() < len(blocked)
    assert np.array_equal(blocked, whole.occluded(o, d, 0.0, tmax))
    walked = grouped.counters["rays_intersect"]
    assert walked < whole.counters["rays_intersect"]  # fewer rays walk
    dev = getattr(grouped, "device", None)
    if dev is not None:
        args = (dev.to_device(o, dev.Point3f), dev.to_device(d, dev.Vector3f), 0.0, dev.to_device(tmax, dev.Float))
        for tracer in (grouped, whole):
            assert np.array_equal(np.array(tracer.device.occluded(*args), bool), blocked)
        if not dev.is_cuda:  # the groups' walk on the device (the GPU walks the whole scene, see occluded_rays)
            assert grouped.counters["rays_intersect"] == 2 * walked  # the same walk queries as the host's groups


@pytest.mark.parametrize("backend", BACKENDS)
def test07b_the_box_test_keeps_every_ray_that_meets_an_alpha_tested_face(backend):
    """The opaque-first order walks only rays whose segment crosses the alpha-tested faces' padded box: every ray the
    backend finds meeting one of those faces is among them (host and device tests), across random rays, rays along
    the axes (zero direction components) and segments that end just before or just past the faces."""
    from suite.core.scene import load
    from suite.core.trace.base import as_rays, box_candidates

    scene = load("gallery")
    tracer = make(backend, scene)
    _, alpha = tracer._alpha_groups()
    corners = tracer.local_positions(scene.positions)[scene.faces[alpha.faces]].reshape(-1, 3).astype(np.float64)
    lo, hi = corners.min(axis=0), corners.max(axis=0)  # the faces' own bounds (the box is padded beyond them)
    rng = np.random.default_rng(5)
    n = 20000
    centre, size = 0.5 * (lo + hi), np.maximum(hi - lo, 0.01)
    o = (centre + (rng.random((n, 3)) - 0.5) * 4.0 * np.maximum(size, 0.5)).astype(np.float32)
    target = centre + (rng.random((n, 3)) - 0.5) * 1.2 * size  # on the faces, near their edges and beyond
    d = target - o
    d[: n // 10, rng.integers(0, 3)] = 0.0  # some directions with a zero component
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    length = (np.linalg.norm(target - o, axis=1) * rng.uniform(0.98, 1.02, n)).astype(np.float32)
    world_o = (o.astype(np.float64) + tracer.shift).astype(np.float32)
    ro, rd, _, rlen = as_rays(world_o, d, 0.0, length, tracer.shift, tracer.soa_origins)
    meets = np.asarray(alpha.occluded(ro, rd, rlen.copy()), bool)
    cand = np.zeros(n, bool)
    cand[box_candidates(ro, rd, rlen, alpha.box, tracer.soa_origins)] = True
    assert meets.sum() > n // 10 and (~cand).sum() > 0
    assert not (meets & ~cand).any()
    dev = getattr(tracer, "device", None)
    if dev is not None:
        rows = ro.T if tracer.soa_origins else ro
        on_dev = np.array(dev.crosses_box(dev.to_device(rows, dev.Point3f), dev.to_device(rd, dev.Vector3f),
                                          dev.to_device(rlen, dev.Float), alpha.box), bool)
        assert not (meets & ~on_dev).any()


def test07c_gathered_rays_are_the_rows_of_fancy_indexing():
    from suite.core.trace.base import gather_rays

    rng = np.random.default_rng(2)
    o, d, length = rng.random((3, 50)).astype(np.float32), rng.random((50, 3)).astype(np.float32), \
        rng.random(50).astype(np.float32)
    idx = np.array([3, 0, 49, 7, 7])
    go, gd, gl = gather_rays(o, d, length, idx, soa=True)
    assert np.array_equal(go, o[:, idx]) and np.array_equal(gd, d[idx]) and np.array_equal(gl, length[idx])
    go, _, _ = gather_rays(np.ascontiguousarray(o.T), d, length, idx, soa=False)
    assert np.array_equal(go, o.T[idx])


def test07e_the_compiled_retrace_step_is_step_past_in_both_origin_layouts():
    """The re-trace rays start at alpha.step_past of the hit (its float64 steps), rounded to float32; rays with no
    length left end as misses; the re-traced hits come back as distances from the original origins."""
    from suite.core.trace.alpha import step_past
    from suite.core.trace.base import _retrace_jit

    setup, scatter = _retrace_jit()
    rng = np.random.default_rng(5)
    n = 64
    o = (rng.random((n, 3)) * 200 - 100).astype(np.float32)
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    t = (rng.random(n) * 50).astype(np.float32)
    length = (t + rng.random(n).astype(np.float32) * 5).astype(np.float32)
    length[::7] = t[::7]  # no length left past these hits
    todo = np.arange(0, n, 2)
    start = step_past(o[todo], d[todo], t[todo].astype(np.float64))
    keep = np.float64(1) * length[todo] - start > 0
    for soa in (False, True):
        tt, prim = t.copy(), np.arange(n, dtype=np.int32)
        u, v = np.full(n, 0.25, np.float32), np.full(n, 0.5, np.float32)
        idx, s = todo.copy(), np.empty(len(todo))
        o_next = np.empty((3, len(todo)) if soa else (len(todo), 3), np.float32)
        d_next, rem = np.empty((len(todo), 3), np.float32), np.empty(len(todo), np.float32)
        k = setup(np.ascontiguousarray(o.T) if soa else o, soa, d, length, tt, prim, u, v, idx, s, o_next, d_next, rem)
        assert k == keep.sum() and np.array_equal(idx[:k], todo[keep]) and np.array_equal(s[:k], start[keep])
        expected_o = (o[todo].astype(np.float64) + d[todo].astype(np.float64) * start[:, None]).astype(np.float32)
        assert np.array_equal(o_next[:, :k].T if soa else o_next[:k], expected_o[keep])
        assert np.array_equal(d_next[:k], d[todo][keep])
        assert np.array_equal(rem[:k], (length[todo].astype(np.float64) - start).astype(np.float32)[keep])
        gone = todo[~keep]
        assert np.all(np.isinf(tt[gone])) and np.all(prim[gone] == -1) and np.all(u[gone] == 0) and np.all(v[gone] == 0)
        p2 = np.where(np.arange(k) % 2 == 0, 9, -1).astype(np.int32)
        t2 = np.full(k, 1.5, np.float32)
        scatter(idx[:k], s[:k], t2, p2, t2, t2, tt, prim, u, v)
        hit = idx[:k][p2 >= 0]
        assert np.array_equal(tt[hit], (s[:k][p2 >= 0] + 1.5).astype(np.float32))
        assert np.all(np.isinf(tt[idx[:k][p2 < 0]])) and np.all(prim[idx[:k]] == p2)


def test08_the_compiled_alpha_test_gives_the_bits_of_the_numpy_reference():
    """AlphaTest.transparent (one numba pass per alpha-tested material) against the numpy opacity lookup and
    comparison: random hits on alpha-tested and other faces, misses, barycentrics outside the triangle (the texture
    repeats), float32 and float64 barycentrics, two thresholds."""
    from suite.core.trace.alpha import AlphaTest

    rng = np.random.default_rng(3)
    for threshold in (0.5, 0.3):
        scene = screen_scene(layers=2, opacity=rng.random((8, 8)).astype(np.float32), threshold=threshold)
        test = AlphaTest(scene)
        n = 4000
        prim = rng.integers(-1, scene.num_faces, n).astype(np.int32)
        u = (rng.random(n) * 3.0 - 1.0).astype(np.float32)
        v = (rng.random(n) * 3.0 - 1.0).astype(np.float32)
        for uu, vv in ((u, v), (u.astype(np.float64) / 3.0, v)):
            out = test.transparent(prim, uu, vv)
            assert np.array_equal(out, test.transparent_reference(prim, uu, vv)) and 0 < out.sum() < n


@pytest.mark.parametrize("backend", BACKENDS)
def test07d_the_box_test_on_axis_parallel_rays_and_segment_ends(backend):
    """Rays with zero direction components inside, on and outside a slab, and segments that stop short of the box, end
    in it or pass through it: the host test and, on a device, its twin."""
    from suite.core.trace.base import box_candidates

    box = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])  # a flat box: the z slab has zero width
    o = np.array([[-1, 0.5, 0], [-1, 0.5, 1e-3], [-1, 1.0, 0], [0.5, 0.5, 2], [0.5, 0.5, 2], [0.5, 0.5, 2],
                  [2, 2, 2]], np.float32)
    d = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1]], np.float32)
    length = np.array([5, 5, 5, 1.5, 2.0, 9.0, 9.0], np.float32)
    got = set(box_candidates(o, d, length, box, soa=False).tolist())
    # in the plane / off it / on the box's edge; stops short / ends on the box / passes through / misses it
    assert got == {0, 2, 4, 5}
    assert set(box_candidates(np.ascontiguousarray(o.T), d, length, box, soa=True).tolist()) == got
    assert set(box_candidates(o, d, length, box, soa=False, blocked=np.arange(7) == 4).tolist()) == got - {4}
    dev = getattr(make(backend, screen_scene()), "device", None)
    if dev is not None:
        on_dev = np.array(dev.crosses_box(dev.to_device(o, dev.Point3f), dev.to_device(d, dev.Vector3f),
                                          dev.to_device(length, dev.Float), box), bool)
        assert set(np.flatnonzero(on_dev).tolist()) == got
