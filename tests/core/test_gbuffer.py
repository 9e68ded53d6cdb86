"""G-buffer: pixel-centre primary rays equal Mitsuba's camera rays; attributes and motion vectors."""
import numpy as np
import pytest

from suite.core.gbuffer import camera_rays, project, render_gbuffer
from suite.errors import UserError
from suite.core.scene import load
from suite.core.scene.mitsuba_io import sensor_dict
from suite.core.trace import backend_params, make


def test01_camera_rays_match_mitsuba_perspective_sensor_at_pixel_centres():
    from suite.core.env import mitsuba

    mi = mitsuba("llvm")
    scene = load("living_room")
    width, height = 40, 24
    t = 1.3
    sensor = mi.load_dict(sensor_dict(mi, scene, t, (width, height), spp=1))
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    sx, sy = ((jj + 0.5) / width).reshape(-1), ((ii + 0.5) / height).reshape(-1)
    rays, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(sx, sy), mi.Point2f(0.5, 0.5))
    ref_o = np.array(rays.o).reshape(3, -1).T if np.array(rays.o).shape[0] == 3 else np.array(rays.o)
    ref_d = np.array(rays.d).reshape(3, -1).T if np.array(rays.d).shape[0] == 3 else np.array(rays.d)
    o, d = camera_rays(scene.camera.pose_at(t), scene.camera.fov_deg, width, height)
    # Mitsuba starts rays at the near clip plane; compare directions and the line through the origin.
    np.testing.assert_allclose(d, ref_d, atol=2e-5)
    np.testing.assert_allclose(np.cross(ref_o - o, d), 0.0, atol=1e-5)


def test02_project_inverts_camera_rays():
    scene = load("atrium")
    pose = scene.camera.pose_at(0.7)
    o, d = camera_rays(pose, scene.camera.fov_deg, 32, 18)
    xy, z = project(o + 3.0 * d, pose, scene.camera.fov_deg, 32, 18)
    jj, ii = np.meshgrid(np.arange(32) + 0.5, np.arange(18) + 0.5)
    np.testing.assert_allclose(xy[:, 0], jj.reshape(-1), atol=1e-4)
    np.testing.assert_allclose(xy[:, 1], ii.reshape(-1), atol=1e-4)
    assert (z > 0).all()


@pytest.mark.parametrize("backend", backend_params("embree", "mitsuba-llvm", "mitsuba-cuda"))
def test03_gbuffer_attributes_are_consistent(backend, room_scene):
    g = render_gbuffer(room_scene, make(backend, room_scene), 0.0)
    assert g.valid.all()  # a closed room: every pixel sees a surface
    p, eye = g.position.reshape(-1, 3), g.camera_position
    np.testing.assert_allclose(np.linalg.norm(p - eye, axis=1), g.depth.reshape(-1), rtol=1e-4)
    # Both normals are unit length and face the camera.
    for n in (g.normal, g.geo_normal):
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
        assert (np.einsum("hwc,hwc->hw", n, g.view_dir) < 0).all()
    albedos = {tuple(a) for a in np.unique(g.albedo.reshape(-1, 3).astype(np.float64).round(3), axis=0).tolist()}
    assert albedos == {(0.7, 0.5, 0.5), (0.3, 0.6, 0.4)}


def test04_background_pixels_are_marked_invalid(grazing_plane_scene):
    scene = grazing_plane_scene
    scene.camera.keys[0].target = np.array([0.0, 3.0, -10.0])  # look at the horizon: sky above
    g = render_gbuffer(scene, make("embree", scene), 0.0)
    assert 0 < g.valid.mean() < 1
    assert np.isinf(g.depth[~g.valid]).all() and (g.prim[~g.valid] == -1).all()
    assert (g.position[~g.valid] == 0).all()


def test05_motion_vectors_point_to_the_same_surface_in_the_previous_frame():
    scene = load("living_room")
    tracer = make("embree", scene)
    t_prev, t = 1.0, 1.0 + 1 / 30
    res = (80, 45)
    g = render_gbuffer(scene, tracer, t, res, prev_t_s=t_prev)
    g_prev = render_gbuffer(scene, tracer, t_prev, res)
    jj, ii = np.meshgrid(np.arange(res[0]) + 0.5, np.arange(res[1]) + 0.5)
    px = np.floor(jj + g.motion[..., 0]).astype(int)
    py = np.floor(ii + g.motion[..., 1]).astype(int)
    inside = (px >= 0) & (px < res[0]) & (py >= 0) & (py < res[1]) & g.valid
    assert np.abs(g.motion).max() > 0.5  # the camera moved
    same = g_prev.position[py[inside], px[inside]]
    dist = np.linalg.norm(same - g.position[inside], axis=-1)
    # Reprojected pixels land on (nearly) the same world point, except at disocclusions and edges.
    assert np.mean(dist < 0.1) > 0.95


def test06_bad_resolution_is_a_user_error(room_scene):
    with pytest.raises(UserError, match="0x0"):
        render_gbuffer(room_scene, make("embree", room_scene), 0.0, (0, 0))


@pytest.mark.parametrize("size", [(40, 24), (37, 19), (1, 1)])
def test07_compiled_camera_rays_give_the_bits_of_the_numpy_reference(size):
    from suite.core.gbuffer import camera_rays_reference

    scene = load("living_room")
    pose = scene.camera.pose_at(0.8)
    for dtype in (np.float64, np.float32):
        o, d = camera_rays(pose, scene.camera.fov_deg, *size, dtype=dtype)
        ref_o, ref_d = camera_rays_reference(pose, scene.camera.fov_deg, *size, dtype=dtype)
        assert o.dtype == d.dtype == np.dtype(dtype)
        assert np.array_equal(o, ref_o) and np.array_equal(d, ref_d)


@pytest.mark.parametrize("name", ["gallery", "arena"])
def test08_the_one_pass_gbuffer_gives_the_bits_of_the_numpy_composition(name):
    """trace_primary's per-pixel pass against whole-array numpy: surface_attributes_reference, normals turned toward
    the camera, front-facing emission, the albedo textures (gallery), and motion vectors of a moving camera and
    rigidly animated objects (arena) through project()."""
    from suite.core.gbuffer import camera_rays_reference, surface_attributes_reference, trace_primary

    scene = load(name)
    tracer = make("embree", scene)
    t = 2.0  # arena's platform is in view and moving
    prev = t - 1.0 / 30.0
    w, h = 64, 36
    g, _, _, hits = trace_primary(scene, tracer, t, (w, h), prev, device=False)
    o64, d64 = camera_rays_reference(scene.camera.pose_at(t), scene.camera.fov_deg, w, h, dtype=np.float64)
    dirs = d64.astype(np.float32)
    idx = np.nonzero(hits.prim >= 0)[0]
    assert len(idx) > 0
    p, ng, ns, alb, em = surface_attributes_reference(scene, scene.positions_at(t), scene.normals_at(t),
                                                      hits.prim[idx], hits.u[idx], hits.v[idx], o64[idx], d64[idx])
    flip = np.where(np.einsum("ij,ij->i", ng, dirs[idx].astype(np.float64)) < 0.0, -1.0, 1.0)[:, None]
    ng_view = -flip * ng
    ns_view = np.where(np.einsum("ij,ij->i", ns, ng_view)[:, None] < 0.0, -ns, ns)
    flat = lambda a: a.reshape(w * h, *a.shape[2:])  # noqa: E731
    assert np.array_equal(flat(g.position)[idx], p)
    assert np.array_equal(flat(g.geo_normal)[idx], ng_view.astype(np.float32))
    assert np.array_equal(flat(g.normal)[idx], ns_view.astype(np.float32))
    assert np.array_equal(flat(g.albedo)[idx], alb)
    assert np.array_equal(flat(g.emission)[idx], np.where(flip < 0.0, em, 0.0).astype(np.float32))
    assert np.array_equal(flat(g.depth)[idx], hits.t[idx])
    assert np.array_equal(flat(g.material)[idx], scene.face_material[hits.prim[idx]])
    miss = np.nonzero(hits.prim < 0)[0]
    assert np.isinf(flat(g.depth)[miss]).all() and (flat(g.material)[miss] == -1).all()
    assert not flat(g.position)[miss].any() and not flat(g.motion)[miss].any()
    # motion: where each point was at the previous time, projected into the previous frame, minus the pixel centre
    points = p.copy()
    obj = scene.face_object[hits.prim[idx]]
    moved = False
    for anim in scene.object_animations:
        sel = obj == anim.object_id
        m = anim.transform_at(prev) @ np.linalg.inv(anim.transform_at(t))
        moved |= bool(sel.any()) and not np.allclose(m, np.eye(4))
        points[sel] = p[sel] @ m[:3, :3].T + m[:3, 3]
    xy, _ = project(points, scene.camera.pose_at(prev), scene.camera.fov_deg, w, h)
    centres = np.stack([idx % w + 0.5, idx // w + 0.5], axis=-1)
    np.testing.assert_allclose(flat(g.motion)[idx], xy - centres, atol=1e-4)
    assert moved == (name == "arena")


@pytest.mark.parametrize("name", ["gallery", "arena"])
def test09_the_gbuffer_made_in_pipelined_row_chunks_is_the_one_made_whole(name, monkeypatch):
    """The host G-buffer traces row chunks while a worker makes the next chunk's rays and finishes the previous
    one's pixels: every field, motion vectors included (arena moves), equals the G-buffer made in one chunk."""
    from suite.core import gbuffer

    scene = load(name)
    tracer = make("embree", scene)
    size = (96, 61)
    assert len(gbuffer.row_chunks(61, 96)) == 1  # 5856 pixels: one chunk at the default size
    whole = render_gbuffer(scene, tracer, 0.5, size, 0.45)
    monkeypatch.setattr(gbuffer, "PIPELINE_MIN_PIXELS", 500)
    chunks = gbuffer.row_chunks(61, 96)
    assert len(chunks) == gbuffer.PIPELINE_CHUNKS and chunks[0][0] == 0 and chunks[-1][1] == 61
    heights = [b - a for a, b in chunks]  # a short first and last chunk: a short pipeline fill and drain
    assert heights[0] < max(heights) and heights[-1] < heights[0]
    assert all(a[1] == b[0] for a, b in zip(chunks[:-1], chunks[1:]))
    piped = render_gbuffer(scene, tracer, 0.5, size, 0.45)
    for field in ("position", "normal", "geo_normal", "albedo", "emission", "depth", "prim", "valid", "motion",
                  "view_dir", "material", "kind"):
        assert np.array_equal(getattr(whole, field), getattr(piped, field)), field


def _recording_steps(log, count, fail=None):
    """Pipeline steps that log (call, step, thread) and check the order the pipeline promises."""
    import threading

    def call(kind, k):
        def run():
            log.append((kind, k, threading.get_ident()))
            if (kind, k) == fail:
                raise ValueError(f"{kind} {k} failed")
        return run

    return [(call("make", k), call("trace", k), call("finish", k)) for k in range(count)]


def test10_the_pipeline_traces_in_order_on_the_callers_thread_after_each_make_and_before_each_finish():
    import threading

    from suite.core.pipeline import pipelined

    log = []
    pipelined(_recording_steps(log, 9))
    traces = [(k, t) for kind, k, t in log if kind == "trace"]
    assert [k for k, _ in traces] == list(range(9))
    assert {t for _, t in traces} == {threading.get_ident()}
    at = {(kind, k): i for i, (kind, k, _) in enumerate(log)}
    assert len(at) == 27  # every call once
    for k in range(9):
        assert at[("make", k)] < at[("trace", k)] < at[("finish", k)]


def test11_an_error_in_a_step_reaches_the_caller_and_the_pipeline_can_run_again():
    from suite.core.pipeline import pipelined

    for fail in (("make", 4), ("trace", 2), ("finish", 6), ("finish", 0)):
        log = []
        with pytest.raises(ValueError, match=f"{fail[0]} {fail[1]} failed"):
            pipelined(_recording_steps(log, 8, fail))
        assert not any(kind == "trace" and k > fail[1] for kind, k, _ in log if fail[0] != "finish")
    log = []
    pipelined(_recording_steps(log, 5))
    assert sorted(k for kind, k, _ in log if kind == "finish") == list(range(5))


def test12_a_pipeline_inside_a_step_of_another_runs_on_a_worker_of_its_own():
    from suite.core.pipeline import pipelined

    inner = []
    outer = _recording_steps([], 4)
    make, trace, finish = outer[1]

    def nested_finish():
        finish()
        pipelined(_recording_steps(inner, 5))

    outer[1] = (make, trace, nested_finish)
    pipelined(outer)
    assert sorted(k for kind, k, _ in inner if kind == "finish") == list(range(5))


def test13_serial_tracer_parts_query_one_at_a_time_and_leave_the_query_a_core():
    """Parts on threads of their own: queries run one at a time, and inside ``part()`` at most ``cores`` parts run
    their passes at once, a part's slot given up while its query waits for and holds the tracer (so three parts
    with one slot still overlap one part's passes with another's query)."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from suite.core.pipeline import SerialTracer

    state = {"passes": 0, "queries": 0, "max_passes": 0, "max_queries": 0, "overlap": 0}
    guard = threading.Lock()

    def enter(kind):
        with guard:
            state[kind] += 1
            state["max_" + kind] = max(state["max_" + kind], state[kind])
            if state["passes"] and state["queries"]:
                state["overlap"] += 1

    def leave(kind):
        with guard:
            state[kind] -= 1

    class Backend:
        def intersect(self, o, d):
            enter("queries")
            time.sleep(0.002)
            leave("queries")
            return len(d)

    serial = SerialTracer(Backend(), threading.Lock(), cores=1)

    def part(k):
        with serial.part():
            for _ in range(6):
                enter("passes")
                time.sleep(0.002)  # a compiled pass (the GIL released)
                leave("passes")
                assert serial.intersect(None, [k] * 3) == 3
        return k

    with ThreadPoolExecutor(3) as pool:
        assert sorted(pool.map(part, range(3))) == [0, 1, 2]
    assert state["max_queries"] == 1 and state["max_passes"] == 1
    assert state["overlap"] > 0
    assert serial.queried.is_set()
    with pytest.raises(AttributeError):
        serial.occluded_local  # noqa: B018  (the backend has no such query: not reached through unlocked)
