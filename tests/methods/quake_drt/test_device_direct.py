"""On a Dr.Jit backend the direct stage (seed 001 §4.1, §6.6, Algorithm 6.2) runs as one device kernel
(methods/quake_drt/device_direct.py): a lane per shading point, a loop over its light samples. Its illumination, its
work counts and the tracer's query counters are the host stage's, bit for bit on llvm_ad_rgb (at parity on
cuda_ad_rgb), for every subsampling mode with soft and hard shadows, for k past one 64-bit word of Floyd's duplicate
bits, for glossy points (shaded on the host), for shadows through alpha-tested texels and past overlays, and in the
hard cases: a light exactly on the floor, a cluster that sees no light, k larger than the row. Its recorded rays are
the rays it traces."""
import dataclasses
import types

import numpy as np
import pytest

from methods.quake_drt import device_direct, direct, testscenes
from suite.core.scene.model import PointLight
from suite.core.trace import backend_params
from suite.core.trace.recording import RecordingTracer

BACKENDS = backend_params("mitsuba-llvm", "mitsuba-cuda")


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


@pytest.fixture
def device_calls(calls_of):
    """The device direct passes run."""
    return calls_of(device_direct, "shade")


def _host_and_device(scene, tracer, pts, lights, table, rows, k, mode, soft, skip=None):
    """(host, device) results of the stage on the same tracer: (illumination, stats, tracer counters added)."""
    out = []
    for on_device in (False, True):
        before = dict(tracer.counters)
        il, st = direct.shade(pts, lights, table, rows, k, mode, soft, tracer, scene, 0.01, 4096, skip,
                              on_device=on_device)
        out.append((il, st, {c: v - before.get(c, 0) for c, v in tracer.counters.items()}))
    return out


def _agree(backend, got, want, at_parity):
    if backend == "mitsuba-llvm":
        assert _same(got, want)
    else:
        at_parity(got, want)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k,mode,soft", [(0, "uniform", True), (0, "uniform", False), (1, "uniform", True),
                                         (3, "uniform", True), (2, "power", True), (4, "irradiance", False)])
def test01_the_device_stage_gives_the_host_stages_illumination_counts_and_queries(backend, direct_setup, k, mode, soft,
                                                                                  device_calls, at_parity):
    scene, tracer, pts, lights, table, rows = direct_setup(backend)
    (il_h, st_h, c_h), (il_d, st_d, c_d) = _host_and_device(scene, tracer, pts, lights, table, rows, k, mode, soft)
    assert device_calls, "the device path did not run"
    _agree(backend, il_d, il_h, at_parity)
    assert st_h.rays > 0 and st_h.visible > 0 and (il_h > 0).any()
    if backend == "mitsuba-llvm":
        assert st_d == st_h and c_d == c_h


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [3, 65, 100, 1000])
def test02_floyds_duplicate_bits_span_several_words(backend, direct_setup, k, device_calls, at_parity):
    """Rows of more than 100 lights: k = 3 (weights n / k that a product with the reciprocal of k would round
    otherwise), k past 64 (two words of duplicate bits), and k above every row's count (all lights, weight 1)."""
    scene, tracer, pts, lights, table, rows = direct_setup(backend, extra_lights=150, glossy_every=0)
    counts = np.diff(table.row_offsets)[rows]
    assert counts.max() > 100
    (il_h, st_h, _), (il_d, st_d, _) = _host_and_device(scene, tracer, pts, lights, table, rows, k, "uniform", True)
    assert device_calls
    _agree(backend, il_d, il_h, at_parity)
    assert st_d.selected == st_h.selected == int(np.minimum(counts, k).sum())
    if backend == "mitsuba-llvm":
        assert st_d == st_h


def _overlay_scene():
    """A lit wall behind two overlay quads (faces that cast no shadow), the light in front of everything."""
    from suite.core.scene.builder import SceneBuilder
    from suite.core.scene.model import CameraKey
    from suite.core.scene.q3 import FLAGS

    b = SceneBuilder()
    wall = b.add_material("wall", albedo=(0.6, 0.6, 0.6))
    b.add_quad(((0, 0, -2.0), (3.0, 0, 0), (0, 3.0, 0)), wall)
    flags = [0, 0]
    for z, blend in ((1.0, "blend_blend"), (0.3, "blend_add")):
        m = b.add_material(f"overlay{z}", albedo=(0.4, 0.5, 0.6))
        b.add_quad(((0, 0, z), (0.6, 0, 0), (0, 0.6, 0)), m)
        flags += [FLAGS[blend]] * 2
    b.add_point_light("front", (0.0, 0.0, 3.0), intensity=20.0)
    b.add_area_light_quad("panel", (2.0, 2.0, 2.5), (0.5, 0.5), (0.0, 0.0, -1.0), radiance=8.0)
    flags += [0, 0]  # the panel's two triangles
    b.set_camera([CameraKey(0.0, (0.0, 0.0, 5.0), (0.0, 0.0, 0.0))], fov_deg=30.0, resolution=(40, 30))
    scene = b.build("overlays")
    scene.q3 = types.SimpleNamespace(face_flags=np.array(flags, np.int64), triangle_face=np.arange(len(flags)))
    return scene


def _hard_cases():
    """(name, scene, visibility, settings) of scenes whose frames the two paths render."""
    from suite.harness import runner

    on_floor, _ = testscenes.two_rooms(lights_in_b=0, area_light=False, camera="a")
    on_floor = dataclasses.replace(on_floor, point_lights=[PointLight("on_floor", (-2.0, 0.0, 0.5), [3.0] * 3)])
    on_floor_vis = testscenes.BoxVisibility([testscenes.ROOM_A, testscenes.ROOM_B], np.eye(2, dtype=bool), on_floor)
    dark, dark_vis = testscenes.two_rooms(door_open=False, lights_in_b=0, camera="b_away")
    rooms, rooms_vis = testscenes.two_rooms(door_open=False, lights_in_b=2, camera="a")
    return [("gallery: an alpha-tested grate, glossy and specular surfaces", runner.load_scene("gallery"), None,
             dict(pvs="none", num_random_dl=0)),
            ("overlays cast no shadow", _overlay_scene(), None, dict(pvs="none", num_random_dl=0, overlay_alpha=0.5)),
            ("a light exactly on the floor", on_floor, on_floor_vis, dict(num_random_dl=0)),
            ("a cluster that sees no light", dark, dark_vis, dict(num_random_dl=1)),
            ("k larger than the culled light count", rooms, rooms_vis, dict(num_random_dl=16, soft_shadows=False))]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", range(5), ids=lambda i: ["gallery", "overlays", "on_floor", "dark", "k_large"][i])
def test03_whole_frames_equal_the_host_pipelines(backend, case, renderer, device_calls, at_parity):
    """A raw frame on the Dr.Jit tracer (device G-buffer and direct stage) against the same frame with the device
    hidden (RecordingTracer: every stage on the host path), on the same backend."""
    name, scene, vis, settings = _hard_cases()[case]
    r = renderer(scene, vis, (40, 30), backend=backend, **settings)
    img_d, raw_d = r.raw(3)
    r.tracer = RecordingTracer(r.tracer)
    calls = len(device_calls)
    img_h, raw_h = r.raw(3)
    assert len(device_calls) == calls and calls > 0 or raw_d.info["shading_points"] == 0, name
    _agree(backend, img_d, img_h, at_parity)
    assert np.isfinite(img_d).all(), name
    keys = ("shading_points", "candidates", "selected", "shadow_rays", "shadow_rays_visible")
    if backend == "mitsuba-llvm":
        assert [raw_d.info[k] for k in keys] == [raw_h.info[k] for k in keys], name
    # the points go up (position and two normals, float64) and their illumination comes back, counted
    n_pts = raw_d.info["shading_points"]
    assert raw_h.info["direct_device_bytes"] == 0 and raw_d.info["direct_device_bytes"] >= n_pts * (72 + 24)
    if "overlays" in name:
        # the shadow rays crossed the overlays (the backend found them blocked) and the walk let them through
        assert raw_d.info["shadow_rays_visible"] == raw_d.info["shadow_rays"] > 0
    if "no light" in name:
        assert raw_d.info["shadow_rays"] == 0 and img_d.max() == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test04_the_recorded_rays_are_the_traced_rays(backend, direct_setup):
    """``capture`` on the device path: per loop iteration the rays that trace (the benchmark's raw replay); the
    backend's raw query on them finds as many unblocked as the stage lit."""
    scene, tracer, pts, lights, table, rows = direct_setup(backend, glossy_every=0)
    records = []
    il, st = direct.shade(pts, lights, table, rows, 0, "uniform", True, tracer, scene, 0.01, capture=records)
    dev = tracer.device
    assert records and all(kind == "o" for kind, _ in records)
    widths = [dev.dr.width(ray.d) for _, ray in records]
    assert sum(widths) == st.rays
    unblocked = sum(int(np.count_nonzero(~np.asarray(dev.raw_occluded(ray).numpy(), bool))) for _, ray in records)
    if backend == "mitsuba-llvm":
        assert unblocked == st.visible
    else:
        assert abs(unblocked - st.visible) <= 1e-3 * st.rays
    again, _ = direct.shade(pts, lights, table, rows, 0, "uniform", True, tracer, scene, 0.01)
    assert _same(il, again)  # recording changes nothing, and reruns give the same bits


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["uniform", "power"])
@pytest.mark.parametrize("k", [0, 1, 2, 70])
def test05_any_light_table_rows(backend, direct_setup, mode, k, device_calls, at_parity):
    """A made-up light table read at random rows: empty rows, a row of two dark lights (no power: the power choice
    finds no light and traces nothing), a bright and a dark light, every light, and random subsets of 1 to 150
    lights in shuffled order; a third of the lights dark."""
    scene, tracer, pts, lights, _, _ = direct_setup(backend, extra_lights=150, glossy_every=0)
    rng = np.random.default_rng(5)
    lights = dataclasses.replace(lights, rgb=lights.rgb.copy())
    dark = rng.random(len(lights)) < 1 / 3
    lights.rgb[dark] = 0.0
    (d0, d1), b0 = np.nonzero(dark)[0][:2], int(np.nonzero(~dark)[0][0])
    rows_lights = [[], [d0, d1], [b0, d0], list(range(len(lights)))]  # the dark row ends where a bright one starts
    rows_lights += [list(rng.permutation(len(lights))[:rng.integers(1, 151)]) for _ in range(12)]
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows_lights])]).astype(np.int64)
    table = types.SimpleNamespace(row_offsets=offsets, row_lights=np.concatenate(rows_lights).astype(np.int32),
                                  row_centre=None)
    rows = rng.integers(0, len(rows_lights), len(pts))
    rows[:8] = [0, 1, 2, 3, 0, 1, 2, 3]
    (il_h, st_h, c_h), (il_d, st_d, c_d) = _host_and_device(scene, tracer, pts, lights, table, rows, k, mode, True)
    assert device_calls
    _agree(backend, il_d, il_h, at_parity)
    assert st_h.rays > 0 and (il_h[rows <= 1] == 0).all()
    if backend == "mitsuba-llvm":
        assert st_d == st_h and c_d == c_h


@pytest.mark.parametrize("backend", BACKENDS)
def test06_a_table_whose_every_row_is_empty_lights_nothing(backend, direct_setup, device_calls):
    """Lights exist but no cluster sees one (oa_ctf2 from a spot outside its clusters): black, and no ray."""
    scene, tracer, pts, lights, _, _ = direct_setup(backend, glossy_every=0)
    table = types.SimpleNamespace(row_offsets=np.zeros(3, np.int64), row_lights=np.zeros(0, np.int32),
                                  row_centre=None)
    rows = np.arange(len(pts)) % 2
    for k, mode in ((0, "uniform"), (1, "uniform"), (2, "power")):
        il, st = direct.shade(pts, lights, table, rows, k, mode, True, tracer, scene, 0.01)
        assert (il == 0).all() and st.rays == st.visible == st.candidates == st.selected == 0
    assert device_calls


@pytest.mark.parametrize("backend", BACKENDS)
def test07_shadow_rays_walk_past_overlays_as_on_the_host(backend, renderer, device_calls, at_parity):
    """The overlays' shadow-ray walk (closest hits past faces that cast no shadow) makes the host walk's queries."""
    from methods.quake_drt.primary import overlay_faces

    scene = _overlay_scene()
    r = renderer(scene, None, (40, 30), backend=backend, pvs="none", num_random_dl=0, overlay_alpha=0.5)
    tracer = r.tracer
    r.tracer = RecordingTracer(tracer)  # the points of a host frame
    _, raw = r.raw(3)
    skip = overlay_faces(scene) > 0
    pts, table, rows = raw.info["points"], r.prep.table, raw.info["rows"]
    (il_h, st_h, c_h), (il_d, st_d, c_d) = _host_and_device(scene, tracer, pts, raw.info["lights_obj"], table, rows,
                                                            0, "uniform", True, skip)
    assert device_calls
    _agree(backend, il_d, il_h, at_parity)
    assert c_h["rays_intersect"] > 0  # the backend found rays blocked by overlays, and the walk passed them
    if backend == "mitsuba-llvm":
        assert st_d == st_h and c_d == c_h


@pytest.mark.parametrize("top", [40, 70_000])
def test08_the_points_run_grouped_by_light_row_in_pixel_order(top):
    """The kernel's lanes hold the points sorted by their light-table row (a packet then loops as often as each of its
    points and traces towards one light), points of one row in their own order; rows past 16 bits sort too. The
    illumination comes back in the points' order (test05: random rows)."""
    rows = np.random.default_rng(3).integers(0, top, 5000)
    order = device_direct.lane_order(rows)
    assert np.array_equal(np.sort(order), np.arange(len(rows)))
    assert (np.diff(rows[order]) >= 0).all()
    same = np.diff(rows[order]) == 0
    assert (np.diff(order)[same] > 0).all()
