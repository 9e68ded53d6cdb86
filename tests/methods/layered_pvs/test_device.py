"""The layered SVGF (§4.4.1) and the pack stage (§4.1.3-§4.1.5) as Dr.Jit kernels (methods/layered_pvs/device.py)
on every Dr.Jit variant (llvm_ad_rgb here, cuda_ad_rgb where a GPU is usable): the SVGF gives the numba kernel's
values to rounding, the pack stage the host passes' texture, mask and block counts bit for bit, and the server
takes both on such a tracer."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from methods.layered_pvs import server as sv
from methods.layered_pvs.device import svgf_passes
from suite.core.trace import backend_params

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")
def _layers(seed, L=3, H=13, W=17):
    """Two or three surfaces per pixel a little apart, holes, slanted and turned normals (some facing away)."""
    rng = np.random.default_rng(seed)
    valid = np.zeros((L, H, W), bool)
    valid[0] = rng.random((H, W)) < 0.9
    for k in range(1, L):
        valid[k] = valid[k - 1] & (rng.random((H, W)) < 0.6)
    depth = np.where(valid, 2.0 + np.arange(L)[:, None, None] * 0.3 + rng.random((L, H, W)) * 0.05, 0.0)
    yy, xx = np.mgrid[0:H, 0:W]
    position = np.stack([xx * 0.02, yy * 0.02, np.zeros((H, W))], -1)[None] + \
        np.stack([np.zeros_like(depth), np.zeros_like(depth), depth], -1)
    normal = np.zeros((L, H, W, 3))
    normal[..., 2] = -1.0
    normal[..., 0] = rng.normal(0, 0.3, (L, H, W))
    normal[-1, ::3, ::2, 2] = 1.0
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    illum = np.where(valid[..., None], rng.random((L, H, W, 3)) * 2.0, 0.0)
    variance = np.where(valid, rng.random((L, H, W)) * 0.2, 0.0)
    return illum, variance, position, normal, valid, depth


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("sigma_n, iterations, layers", [(128.0, 3, 3), (12.5, 2, 2), (3.0, 5, 1)])
def test01_the_device_passes_give_the_numba_kernels_values(drjit_device, backend, sigma_n, iterations, layers,
                                                           at_parity):
    # 5 passes reach step 16, wider than the 17x13 grid: taps leave it
    illum, variance, position, normal, valid, depth = _layers(int(sigma_n), L=layers)
    illum = illum + np.where(valid[..., None], 0.0, 7.0)     # slots without a fragment come out 0 whatever they hold
    if layers == 3:  # fragments behind empty layers: a tap's search stops at the first empty layer
        valid[:, 0, :] = [[False], [False], [True]]
        position[2, 0], normal[2, 0], depth[2, 0] = position[0, 1], normal[0, 1], depth[0, 1]
        illum[2, 0] = illum[0, 1] + 0.5
    pix_angle = 2 * np.tan(np.radians(30.0)) / valid.shape[2]
    grids = [sv.pixel_major(a, np.float64) for a in (illum, variance, position, normal)] + \
        [sv.pixel_major(valid, np.bool_), sv.pixel_major(depth, np.float64)]
    want = sv._svgf_passes(*grids, pix_angle, iterations, sigma_n=sigma_n)
    got = svgf_passes(drjit_device(backend), *grids, pix_angle, iterations, sigma_n=sigma_n)
    assert got.shape == want.shape and got.dtype == np.float64
    # the device passes run in float32, the numba kernel in float64: float32 rounding (relative 1e-5 at most here)
    if backend == "mitsuba-llvm":
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    else:  # cuda's fused multiply-adds can tip a tap's choice between two nearly equidistant fragments
        at_parity(got, want, share=0.999, rtol=1e-4, atol=1e-6)
    v = sv.pixel_major(valid, np.bool_)
    assert (got[~v] == 0).all() and not np.allclose(got[v], grids[0][v], rtol=1e-3)


@pytest.mark.parametrize("backend", DRJIT)
def test02_denoise_fragments_on_a_device_counts_its_copies(drjit_device, backend):
    illum_g, _, position, normal, valid, depth = _layers(8, L=2)
    index = np.nonzero(valid)
    n = len(index[0])
    rng = np.random.default_rng(1)
    frag = SimpleNamespace(index=index, position=position[index], normal=normal[index])
    layers = SimpleNamespace(prim=np.zeros(valid.shape, np.int64), valid=valid, t=np.where(valid, depth, np.inf))
    view = SimpleNamespace(fov_deg=60.0, width=valid.shape[2])
    illum, m1 = illum_g[index], rng.random(n)
    m2 = m1 * m1 + rng.random(n) * 0.1
    dev = drjit_device(backend)
    want = sv.denoise_fragments(view, layers, frag, illum, m1, m2, spp=2, iterations=3)
    before = dev.counters["bytes_to_host"]
    got = sv.denoise_fragments(view, layers, frag, illum, m1, m2, spp=2, iterations=3, device=dev)
    assert dev.counters["bytes_to_host"] - before == valid.size * 3 * 4      # the filtered grid, once (float32)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)              # float32 passes against float64


# ------------------------------------------------------------------------------------------ packing on the device

def _host_pack(depth, valid, colour, tile, full_layers, order, relocation, fill, max_rounds=64):
    """The pack stage's host passes (methods/layered_pvs/packing.py), as the method runs them on Embree."""
    from methods.layered_pvs import packing

    slot_of = packing.relocate(depth, valid, tile, max_rounds) if relocation else packing.identity_slots(valid)
    slot_colour, occupied = packing.to_slots(colour, valid, slot_of)
    counts = np.maximum(packing.block_layer_counts(occupied, tile) - full_layers, 0)
    layout = packing.make_layout(counts, valid.shape[2], valid.shape[1], tile, full_layers, order)
    tex, mask = packing.pack(slot_colour, occupied, layout)
    if fill:
        tex = packing.colour_fill(tex, mask == 1, tile)
    return tex, mask, counts, int((slot_of[valid] != np.nonzero(valid)[0]).sum())


def _surfaces(seed, L=4, h=24, w=32):
    """Peeled layers of four surfaces (depths 1-4, each present in patches), so that a pixel's k-th fragment lies on
    different surfaces across a block and relocation has fragments to move; one 8x8 block empty, one block deeper
    than the layer budget would allow if every surface were present, colours random."""
    rng = np.random.default_rng(seed)
    present = rng.random((4, h // 4, w // 4)) < 0.55
    present = present.repeat(4, 1).repeat(4, 2) & (rng.random((4, h, w)) < 0.93)
    present[:, :8, :8] = False
    depth_of = (np.arange(1, 5)[:, None, None] + 0.2 * rng.random((4, h, w))).astype(np.float32)
    order = np.argsort(np.where(present, depth_of, np.inf), axis=0, kind="stable")
    sorted_depth = np.take_along_axis(np.where(present, depth_of, np.inf), order, axis=0)[:L]
    valid = np.isfinite(sorted_depth)
    colour = rng.integers(0, 256, (L, h, w, 3)).astype(np.uint8)
    return np.where(valid, sorted_depth, np.inf).astype(np.float32), valid, colour


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("order", ["block", "layer"])
@pytest.mark.parametrize("full_layers, relocation, fill", [(1, True, True), (0, True, True), (2, False, True),
                                                           (1, True, False)])
def test03_the_device_pack_stage_gives_the_host_passes_texture_mask_and_counts(drjit_device, backend, order,
                                                                               full_layers, relocation, fill):
    from methods.layered_pvs.device import pack_layers

    depth, valid, colour = _surfaces(7 + full_layers)
    want = _host_pack(depth, valid, colour, 8, full_layers, order, relocation, fill)
    tex, mask, counts, layout, relocated = pack_layers(drjit_device(backend), depth, valid, colour, 8, full_layers,
                                                       order, relocation, fill)
    assert tex.dtype == np.uint8 and mask.dtype == np.int8 and tex.shape == want[0].shape
    assert np.array_equal(counts, want[2]) and layout.tiles == int(want[2].sum())
    assert relocated == want[3] and (relocated > 0) == relocation          # relocation moved fragments here
    assert np.array_equal(mask, want[1])
    assert np.array_equal(tex, want[0])                                   # float32 sums in the host's order


@pytest.mark.parametrize("backend", DRJIT)
def test04_device_relocation_stops_after_max_rounds_as_the_host_pass_does(drjit_device, backend):
    from methods.layered_pvs.device import pack_layers

    # Fragments move a pixel further each round: 1, 2 and 3 rounds leave fewer moved than 64 (the host's counts
    # differ), and the device stops where the host pass does.
    depth, valid, colour = _surfaces(4)
    dev = drjit_device(backend)
    moved = []
    for rounds in (1, 2, 3, 64):
        want = _host_pack(depth, valid, colour, 8, 1, "block", True, True, max_rounds=rounds)
        got = pack_layers(dev, depth, valid, colour, 8, 1, "block", True, True, max_rounds=rounds)
        assert got[4] == want[3] and np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        moved.append(got[4])
    assert moved == sorted(set(moved))     # every further round moved more


@pytest.mark.parametrize("backend", DRJIT)
def test05_empty_layers_pack_on_the_device_as_on_the_host(drjit_device, backend):
    from methods.layered_pvs.device import pack_layers

    dev = drjit_device(backend)
    valid = np.zeros((3, 16, 16), bool)
    depth = np.full(valid.shape, np.inf, np.float32)
    colour = np.zeros(valid.shape + (3,), np.uint8)
    # Nothing at all and no full layer: an empty texture.
    tex, mask, counts, layout, relocated = pack_layers(dev, depth, valid, colour, 8, 0, "block")
    assert tex.shape == (0, 16, 3) and mask.shape == (0, 16) and not counts.any() and relocated == 0
    # One full layer, every tile of the others empty (test_packing test04): no tile.
    valid[0] = True
    depth[0] = 2.0
    colour[0] = 90
    want = _host_pack(depth, valid, colour, 8, 1, "layer", True, True)
    got = pack_layers(dev, depth, valid, colour, 8, 1, "layer")
    assert got[3].tiles == 0 and np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize("backend", DRJIT)
def test06_the_server_packs_on_the_device_of_a_drjit_tracer(backend, monkeypatch):
    from methods.layered_pvs import bench, device
    from suite.harness import runner

    scene = runner.load_scene("living_room")
    tracer = runner.make_tracer(backend, scene)
    calls, original = [], device.pack_layers

    def spy(dev, *args, **kwargs):
        out = original(dev, *args, **kwargs)
        calls.append((args, out))
        return out

    monkeypatch.setattr(device, "pack_layers", spy)
    params = {**bench.DEFAULT_PARAMS, "layers": 3}
    before = tracer.device.counters["bytes_to_host"]
    ctx, _, _, _ = bench.one_update(scene, tracer, params, (64, 36), 0.5, 0.6)
    assert len(calls) == 1
    (depth, valid, colour, tile, full_layers, order, relocation, fill), (tex, mask, counts, _, relocated) = calls[0]
    want = _host_pack(depth, valid, colour, tile, full_layers, order, relocation, fill)
    assert np.array_equal(tex, want[0]) and np.array_equal(mask, want[1]) and np.array_equal(counts, want[2])
    assert ctx.outputs["relocated_fragments"] == relocated == want[3]
    assert ctx.outputs["tiles"] == int(counts.sum()) and ctx.outputs["texture_rows"] == tex.shape[0]
    # The texture and mask came back for the codecs (with the block counts and the SVGF's grid), the layers' colours
    # went up: the update's record counts every copy.
    assert tracer.device.counters["bytes_to_host"] - before >= tex.nbytes + mask.nbytes + counts.size * 4
    assert ctx.outputs["host_device_bytes"] >= tex.nbytes + mask.nbytes + colour.nbytes + depth.size * 4


# ------------------------------------------------------------------------------------------ path tracing (§4.4)

def _fragments(scene_name, size=(64, 36), layers=2, t_s=0.5):
    from suite.harness import runner

    scene = runner.load_scene(scene_name)
    host = runner.make_tracer("embree", scene)
    host.update(t_s)
    view = sv.LayerView(scene.camera.pose_at(t_s), scene.camera.fov_deg, *size)
    o64, d64 = sv.view_rays(view)
    peeled = sv.peel(host, o64.astype(np.float32), d64.astype(np.float32), layers, shape=(size[1], size[0]))
    return scene, host, sv.fragments(scene, peeled, o64, d64, t_s)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["gallery", "arena", "cornell"])
def test07_device_paths_take_the_host_passes_samples(backend, scene_name):
    # gallery: two point lights and an emissive triangle (both light kinds, the choice written out), an alpha-tested
    # grate the bounces and shadow rays walk through, an albedo texture; arena: 73 point lights (the choice as loops
    # over a light table); cornell: an area light alone. Paths of up to 5 vertices, Russian roulette from the
    # third. The host passes run on the same tracer (its numpy-fed queries; test16 compares them across backends)
    # with the same seed: the same counter-based random numbers, so each path's contribution is the host's to
    # rounding (the device makes the bounce direction in float32), except for the rare path that a last-bit
    # difference sends past another edge; independent samples would differ by their whole noise.
    from methods.layered_pvs import device
    from suite.harness import runner

    scene, _, frag = _fragments(scene_name, size=(96, 54))
    tracer = runner.make_tracer(backend, scene)
    tracer.update(0.5)
    lights = sv.LightSampler(scene, 0.5)
    n, spp, depth, rr = len(frag.position), 8, 5, 3
    got = device.path_trace(tracer.device, frag, lights, spp, depth, rr, seed=1)
    want = np.zeros((n * spp, 3))
    for part in sv._path_parts(n * spp):
        sv._part_paths(tracer, scene, frag, 0.5, spp, depth, rr, lights, want, 1, *part)
    assert n > 5000 and np.all(want.mean(axis=0) > 0.01)
    scale = np.maximum(np.abs(got), np.abs(want)).max(axis=-1)
    lit = scale > 0
    rel = np.abs(got - want).max(axis=-1)[lit] / scale[lit]
    assert lit.mean() > 0.3
    assert (rel > 1e-3).mean() < 1e-3 and rel.mean() < 1e-3
    assert np.allclose(got.mean(axis=0), want.mean(axis=0), rtol=1e-4)
    other = device.path_trace(tracer.device, frag, lights, spp, depth, rr, seed=2)
    assert not np.allclose(other, got)


@pytest.mark.parametrize("backend", DRJIT)
def test08_device_paths_are_deterministic_and_count_their_rays(backend):
    from methods.layered_pvs import device
    from suite.harness import runner

    scene, _, frag = _fragments("gallery", size=(32, 18))
    tracer = runner.make_tracer(backend, scene)
    tracer.update(0.5)
    lights = sv.LightSampler(scene, 0.5)
    dev = tracer.device
    before = dict(tracer.counters)
    with device.recording({}) as records:
        first = device.path_trace(dev, frag, lights, 2, 5, 3, seed=7)
    record = records["path_trace"]
    counted = {k: tracer.counters[k] - before[k] for k in before}
    assert np.array_equal(first, device.path_trace(dev, frag, lights, 2, 5, 3, seed=7))
    assert not np.array_equal(first, device.path_trace(dev, frag, lights, 2, 5, 3, seed=8))
    assert first.shape == (2 * len(frag.position), 3) and np.isfinite(first).all() and (first >= 0).all()
    # three bounces, each a closest-hit query and a shadow query; the alpha walk adds closest-hit queries
    widths = {kind: sum(dev.dr.width(ray.d) for k, ray in record if k == kind) for kind in "io"}
    assert len(record) == 6 and widths["o"] == counted["rays_occluded"] > 0
    assert counted["rays_intersect"] >= widths["i"] > 0


@pytest.mark.parametrize("backend", DRJIT)
def test09_device_paths_without_bounces_or_lights_trace_nothing(backend):
    from methods.layered_pvs import device
    from suite.harness import runner

    scene, _, frag = _fragments("living_room", size=(16, 9), layers=1)
    tracer = runner.make_tracer(backend, scene)
    lights = sv.LightSampler(scene, 0.5)
    before = dict(tracer.counters)
    # max_depth 2 is direct light only (the primary fragment's, outside these paths)
    assert not device.path_trace(tracer.device, frag, lights, 2, 2, 3, seed=1).any()
    dark = SimpleNamespace(power=np.zeros(0))
    assert not device.path_trace(tracer.device, frag, dark, 2, 5, 3, seed=1).any()
    assert dict(tracer.counters) == before


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name, per_point", [("gallery", True), ("arena", True), ("arena", False)])
def test10_device_light_choice_and_sample_are_the_light_samplers(backend, scene_name, per_point, monkeypatch,
                                                                  at_parity):
    # gallery's three lights: the choice written out over broadcast scalars; arena's 73: loops over a light table;
    # with the per-point bound off (more lights than PER_POINT_LIGHTS), the power CDF's binary search.
    from methods.layered_pvs import device
    from suite.harness import runner

    scene = runner.load_scene(scene_name)
    if not per_point:
        monkeypatch.setattr(sv.LightSampler, "PER_POINT_LIGHTS", 8)
    lights = sv.LightSampler(scene, 0.5)
    dev = runner.make_tracer(backend, scene).device
    rng = np.random.default_rng(3)
    lo, hi = scene.positions.min(axis=0), scene.positions.max(axis=0)
    p = lo + (hi - lo) * rng.random((4000, 3))
    p[:40] = lights.centres[rng.integers(0, len(lights.centres), 40)]  # on a light: the clamped bound
    u, u2 = rng.random(4000), rng.random((4000, 2))
    want_j, want_pmf = lights.choose(p, u)
    _, _, want_w, want_ok = lights.sample(p, u, u2)
    lt = device.DeviceLights(dev, lights)
    assert lt.unrolled == (scene_name == "gallery")
    F64 = dev.Float64
    pd = dev.to_device(p, dev.Point3d)
    j, pmf = device._choose_light(dev, lt, pd, dev.to_device(u, F64))
    y, w, ok = device._light_sample(dev, lt, pd, j, pmf, j < lt.n_point, dev.to_device(u2[:, 0], F64),
                                    dev.to_device(u2[:, 1], F64))
    assert np.array_equal(dev.to_host(j), want_j)
    at_parity(dev.to_host(pmf), want_pmf, share=1.0, rtol=1e-12, atol=0.0)
    assert np.array_equal(dev.to_host(ok), want_ok)
    at_parity(dev.to_host(w)[want_ok], want_w[want_ok], share=1.0, rtol=1e-9, atol=0.0)


def _host_view(tracer):
    """``tracer`` seen as a host tracer (its numpy-fed queries): the host passes on the very same backend."""
    from suite.core.trace.recording import RecordingTracer

    return RecordingTracer(tracer)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name, offset", [("gallery", None), ("arena", None), ("arena", 1e4)])
def test11_the_device_pvs_is_the_host_passes_pvs(backend, scene_name, offset, at_parity):
    # Algorithm 1's seven views (two of them the same, as for a camera with no known motion) at 1.1x the FOV; the
    # gallery's grate is alpha-tested (its transparent texels let the views see through); arena also moved 1e4
    # away (the camera's origin rounded as the host rounds it, in the tracing frame).
    from suite.harness import runner

    scene = runner.load_scene(scene_name)
    if offset is not None:
        scene = scene.translated([offset, -offset, offset])
    tracer = runner.make_tracer(backend, scene)
    pose = scene.camera.pose_at(0.5)
    views = sv.predict_views([(0.4, scene.camera.pose_at(0.4)), (0.5, pose)], 0.2, 0.3) + [pose]
    before = dict(tracer.counters)
    got = sv.compute_pvs(tracer, views, scene.camera.fov_deg * 1.1, 96, 54)
    counted = tracer.counters["rays_intersect"] - before["rays_intersect"]
    host = _host_view(tracer)
    before = dict(tracer.counters)
    want = sv.compute_pvs(host, views, scene.camera.fov_deg * 1.1, 96, 54)
    assert 0 < len(want) < scene.num_faces
    if backend == "mitsuba-llvm":
        assert np.array_equal(got, want)
        assert counted == tracer.counters["rays_intersect"] - before["rays_intersect"]
    else:  # hits at the backends' parity: a triangle seen by a pixel or two may differ
        assert len(np.setxor1d(got, want)) <= 0.01 * len(want)


def _peeling_view(scene_name, backend):
    """(scene, tracer of ``backend``, its 80x45 layer view at 1.1x the FOV at t = 0.5); "far:" moves the scene 1e4
    away."""
    from suite.harness import runner

    scene = runner.load_scene(scene_name.removeprefix("far:"))
    if scene_name.startswith("far:"):
        scene = scene.translated([1e4, -1e4, 1e4])
    tracer = runner.make_tracer(backend, scene)
    return scene, tracer, sv.LayerView(scene.camera.pose_at(0.5), scene.camera.fov_deg * 1.1, 80, 45)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name, layers, keep_share, max_skips",
                         [("gallery", 4, None, 256), ("gallery", 6, 0.5, 256), ("arena", 3, 0.3, 2),
                          ("living_room", 8, 0.7, 1), ("far:living_room", 4, 0.8, 256)])
def test12_device_depth_peeling_gives_the_host_passes_layers(backend, scene_name, layers, keep_share, max_skips,
                                                             at_parity):
    # Every hit kept, or a random share of the triangles (many hits stepped over, up to max_skips queries per
    # layer: 1 and 2 stop rays short); more layers than the depth complexity of most pixels (empty layers); the
    # view at 1.1x the FOV, some pixels on the sky in arena; living_room moved 1e4 away ("far:"). The device's two
    # schedules (one kernel, a query per kernel) give the same layers and query counts.
    from methods.layered_pvs import device

    scene, tracer, view = _peeling_view(scene_name, backend)
    o64, d64 = sv.view_rays(view)
    keep = None if keep_share is None else np.random.default_rng(5).random(scene.num_faces) < keep_share
    args = (o64.astype(np.float32), d64.astype(np.float32), layers)
    before = tracer.counters["rays_intersect"]
    got = sv.peel(tracer, *args, max_skips=max_skips, shape=(45, 80), keep_mask=keep)
    counted = tracer.counters["rays_intersect"] - before
    before = tracer.counters["rays_intersect"]
    want = sv.peel(_host_view(tracer), *args, max_skips=max_skips, shape=(45, 80), keep_mask=keep)
    assert want.valid[0].any() and not want.valid[-1].all()
    counted_host = tracer.counters["rays_intersect"] - before
    # the other schedule (one query per kernel, compacted between queries: the benchmark's recording) as well
    before = tracer.counters["rays_intersect"]
    waves = sv.Layers(*(a.reshape((layers, 45, 80)) for a in device.peel(tracer.device, *args, keep, max_skips,
                                                                        wavefront=True)))
    counted_waves = tracer.counters["rays_intersect"] - before
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(got, name), getattr(waves, name)), name
    assert counted == counted_waves
    if backend == "mitsuba-llvm":
        for name in ("t", "prim", "u", "v"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
        assert counted == counted_host
    else:
        assert (got.prim == want.prim).mean() >= 0.99
        at_parity(got.t[got.valid & want.valid], want.t[got.valid & want.valid], share=0.99)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["arena", "cornell"])
def test13_device_direct_light_of_the_fragments_is_the_host_estimate(backend, scene_name, at_parity):
    # arena: 73 point lights, hard shadows (the normals rounded to float32 as the device G-buffer keeps them move a
    # few grazing shadow rays); cornell: an area light, sampled with other random numbers (within noise, paired
    # per fragment).
    from methods.layered_pvs import device
    from suite.harness import runner

    scene, _, frag = _fragments(scene_name, size=(64, 36))
    tracer = runner.make_tracer(backend, scene)
    tracer.update(0.5)
    got = tracer.device.to_host(device.direct_light(tracer.device, scene, frag, 0.5, 8, seed=4))
    want = sv.direct_illumination(scene, _host_view(tracer), frag, 0.5, 8, 5).astype(np.float64)
    assert got.shape == want.shape == (len(frag.position), 3) and want.mean() > 0.01
    if scene_name == "arena":
        at_parity(got, want, share=0.995, rtol=1e-5, atol=1e-6)
    else:
        diff = got - want
        se = diff.std(axis=0, ddof=1) / np.sqrt(len(diff))
        assert np.all(np.abs(diff.mean(axis=0)) < 5 * se), f"device {got.mean(axis=0)} vs host {want.mean(axis=0)}"


@pytest.mark.parametrize("backend", DRJIT)
def test14_device_moments_are_the_host_kernels(drjit_device, backend):
    from methods.layered_pvs import device, kernels

    dev = drjit_device(backend)
    rng = np.random.default_rng(6)
    n, spp = 500, 3
    sample, direct = rng.random((n * spp, 3)) * 2, rng.random((n, 3)).astype(np.float32)
    illum, m1, m2 = np.empty((n, 3), np.float32), np.empty(n), np.empty(n)
    kernels.jit()["_path_moments"](sample, direct.astype(np.float64), n, spp, illum, m1, m2)
    got = device.path_moments(dev, dev.to_device(sample, dev.Vector3d), dev.to_device(direct, dev.Vector3d), n, spp)
    assert np.array_equal(got[0], illum)
    for a, b in zip(got[1:], (m1, m2)):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)


@pytest.mark.parametrize("backend", DRJIT)
def test15_updates_made_on_the_device_are_deterministic_and_keep_the_hard_cases(backend):
    # The whole server update on a Dr.Jit tracer: a rerun gives the same bytes (counter-based random numbers keyed
    # by lane, seeded from the update's generator); a camera outside the room looking away gives an empty PVS, no
    # fragment and no tile, and a black client frame, as on Embree (tests/methods/layered_pvs/test_method.py test03);
    # a static camera's client frame shows the update.
    from methods.layered_pvs import bench
    from methods.layered_pvs.method import LayeredPVS
    from suite.core.scene.model import CameraPose
    from suite.harness import runner

    scene = runner.load_scene("living_room")
    tracer = runner.make_tracer(backend, scene)
    params = {**bench.DEFAULT_PARAMS, "layers": 3, "spp": 1, "max_depth": 4}
    res = (64, 36)

    def update(pose, seed=0):
        server = LayeredPVS(dict(params))
        ctx = bench.LocalContext(scene, tracer, 0.5, res, 0, pose, seed=seed)
        server.server_update(ctx)
        return ctx

    def show(ctx, pose):
        client = LayeredPVS(dict(params))
        cctx = bench.client_context(pose, scene.camera.fov_deg, 0.5, res)
        return client.client_frame(cctx, bench.delivered_update(ctx.sent["update"], 0, 0.5)), cctx.outputs

    pose = scene.camera.pose_at(0.5)
    first, again = update(pose), update(pose)
    assert first.sent["update"] == again.sent["update"] and first.outputs["host_device_bytes"] > 0
    assert first.sent["update"] != update(pose, seed=1).sent["update"]
    img, out = show(first, pose)
    assert out["rejected_updates"] == 0 and out["no_hit_pixels"] == 0 and img.mean() > 0
    lo, hi = scene.bounds()
    away = CameraPose(hi + 10.0, hi + 20.0, np.array([0.0, 1.0, 0.0]))
    empty = update(away)
    assert empty.outputs["pvs_triangles"] == 0 and empty.outputs["fragments"] == 0 and empty.outputs["tiles"] == 0
    img, out = show(empty, away)
    assert out["rejected_updates"] == 0 and (img == 0).all() and out["no_hit_pixels"] == res[0] * res[1]


@pytest.mark.parametrize("backend", DRJIT)
def test16_the_host_paths_trace_the_same_light_on_embree_and_on_mitsuba(backend):
    # The host path tracer with the same random numbers on embreex and on Mitsuba's numpy interface: the same rays,
    # so the same light but for the backends' parity (a shadow ray or two). arena's walls lie far from the tracing
    # frame's centre in world coordinates (x = 23 against 2 in the frame): an offset origin rounded to float32 in
    # world coordinates falls back onto its wall, where embreex reports a hit at t = 0 and Mitsuba none, which makes
    # the two estimates differ on about 0.5 % of the fragments (0.2–0.4 % of the mean light).
    from suite.core.trace.recording import RecordingTracer
    from suite.harness import runner

    scene, host, frag = _fragments("arena", size=(96, 54))
    tracer = runner.make_tracer(backend, scene)
    tracer.update(0.5)
    n = len(frag.position)
    embree = sv.path_trace(scene, host, frag, 0.5, 2, 3, 3, np.random.default_rng(0))[0]
    mitsuba = sv.path_trace(scene, RecordingTracer(tracer), frag, 0.5, 2, 3, 3, np.random.default_rng(0))[0]
    differ = np.abs(embree - mitsuba).max(axis=1) > 1e-6
    assert n > 5000 and embree.mean() > 0.1
    assert differ.sum() <= max(3, n // 2000), f"{differ.sum()} of {n} fragments differ"
    np.testing.assert_allclose(embree.mean(axis=0), mitsuba.mean(axis=0), rtol=2e-5)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["gallery", "arena", "atrium"])
def test17_device_fragments_are_the_host_passes_fragments(backend, scene_name, at_parity):
    # The same layers (peeled on Embree) made into fragments by the compiled host passes and on the device: gallery's
    # albedo texture, arena's moving platform at t = 0.5, atrium's emissive panels (front faces only). The device
    # keeps the positions and normals for the path tracer's G-buffer (no upload of its own), evaluated with the copies
    # (not computed again where the path tracer reads them).
    from methods.layered_pvs import device
    from suite.harness import runner

    t_s, size = 0.5, (96, 54)
    scene = runner.load_scene(scene_name)
    host = runner.make_tracer("embree", scene)
    host.update(t_s)
    view = sv.LayerView(scene.camera.pose_at(t_s), scene.camera.fov_deg * 1.1, *size)
    o64, d64 = sv.view_rays(view)
    layers = sv.peel(host, o64.astype(np.float32), d64.astype(np.float32), 3, shape=(size[1], size[0]))
    want = sv.fragments(scene, layers, o64, d64, t_s)
    tracer = runner.make_tracer(backend, scene)
    got = sv.fragments(scene, layers, o64, d64, t_s, device=tracer.device)
    assert len(want.position) > 4000 and got.device is not None and want.device is None
    assert all(np.array_equal(a, b) for a, b in zip(got.index, want.index))
    names = ("position", "geo_normal", "normal", "albedo", "emission", "view_dir")
    for name in names:
        assert getattr(got, name).dtype == getattr(want, name).dtype, name
    if backend == "mitsuba-llvm":
        for name in names:
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
    else:
        for name in names:
            at_parity(getattr(got, name), getattr(want, name), share=0.999, rtol=1e-6, atol=1e-6)
    if scene_name == "atrium":
        assert want.emission.any() and not want.emission.all()
    dr = tracer.device.dr
    assert all(twin.x.state == dr.VarState.Evaluated for twin in (got.device.position, got.device.geo_normal,
                                                                   got.device.normal))
    g = device.fragment_gbuffer(tracer.device, got)
    assert np.array_equal(tracer.device.to_host(g.position), got.position)
    empty = sv.Layers(*(np.full_like(a, -1 if a.dtype.kind == "i" else np.inf if name == "t" else 0)
                        for name, a in zip(("t", "prim", "u", "v"), (layers.t, layers.prim, layers.u, layers.v))))
    none = sv.fragments(scene, empty, o64, d64, t_s, device=tracer.device)
    assert len(none.position) == 0 and none.position.shape == (0, 3)


@pytest.mark.parametrize("backend", DRJIT)
def test18_device_fragments_keep_emission_on_front_faces_only(backend):
    # One of atrium's emissive panels (facing down) seen from above, through the ceiling, and from below: its
    # fragments emit only where the layer camera sees its front, on the host and on the device alike.
    from suite.core.scene.model import CameraPose
    from suite.harness import runner

    scene = runner.load_scene("atrium")
    host, tracer = runner.make_tracer("embree", scene), runner.make_tracer(backend, scene)
    host.update(0.5)
    panel = [i for i, m in enumerate(scene.materials) if m.is_emissive][0]
    tri = scene.positions[scene.faces[scene.face_material == panel]]
    centre = tri.reshape(-1, 3).mean(axis=0)
    normal = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
    normal /= np.linalg.norm(normal)
    emitting = {}
    for side in (-1.0, 1.0):  # behind the panel, in front of it
        view = sv.LayerView(CameraPose(centre + side * 2.0 * normal, centre, np.array([1.0, 0.0, 0.0])), 60.0, 48, 27)
        o64, d64 = sv.view_rays(view)
        layers = sv.peel(host, o64.astype(np.float32), d64.astype(np.float32), 4, shape=(27, 48))
        on_panel = (layers.valid & (scene.face_material[np.maximum(layers.prim, 0)] == panel))[layers.valid]
        want = sv.fragments(scene, layers, o64, d64, 0.5)
        got = sv.fragments(scene, layers, o64, d64, 0.5, device=tracer.device)
        assert on_panel.sum() > 50
        emitting[side] = [(f.emission[on_panel].max(axis=1) > 0).mean() for f in (want, got)]
    assert emitting[-1.0] == [0.0, 0.0] and emitting[1.0] == [1.0, 1.0]


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["gallery", "far:living_room"])
def test19_the_view_rays_made_on_the_device_give_the_host_layers_and_fragments(backend, scene_name, at_parity):
    # The layer view's pixel-centre rays made on the device (no upload) against the host's view_rays handed over:
    # the same layers, query counts and fragments, directions included; living_room also moved 1e4 away (the
    # camera's origin rounded as the host rounds it).
    scene, tracer, view = _peeling_view(scene_name, backend)
    o64, d64 = sv.view_rays(view)
    keep = np.random.default_rng(3).random(scene.num_faces) < 0.6
    counts = []
    layers = []
    for args, kw in (((o64.astype(np.float32), d64.astype(np.float32)), {}), ((None, None), {"view": view})):
        before = tracer.counters["rays_intersect"]
        layers.append(sv.peel(tracer, *args, 3, keep_mask=keep, shape=(45, 80), **kw))
        counts.append(tracer.counters["rays_intersect"] - before)
    handed, made = layers
    assert counts[1] > 0 and made.valid.any()
    want = sv.fragments(scene, made, o64, d64, 0.5, device=tracer.device)
    got = sv.fragments(scene, made, None, None, 0.5, device=tracer.device, view=view)
    names = ("position", "geo_normal", "normal", "albedo", "emission", "view_dir")
    if backend == "mitsuba-llvm":
        for name in ("t", "prim", "u", "v"):
            assert np.array_equal(getattr(handed, name), getattr(made, name)), name
        assert counts[0] == counts[1]
        for name in names:
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
    else:  # the device's division and square root round otherwise: rays at the backends' parity
        assert (handed.prim == made.prim).mean() >= 0.99
        for name in names:
            at_parity(getattr(got, name), getattr(want, name), share=0.999, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("backend", DRJIT)
def test20_a_new_camera_pose_reuses_the_server_kernels(backend):
    # The server's device passes read the per-update values (camera position, fragment count) from memory, so an
    # update from another pose launches the kernels the previous one compiled: literals there would compile the PVS,
    # peeling and fragment kernels for every pose (20-130 ms each on llvm_ad_rgb) and the moments' kernel for every
    # fragment count.
    import drjit as dr

    from suite.harness import runner

    scene = runner.load_scene("living_room")
    tracer = runner.make_tracer(backend, scene)
    keep = np.random.default_rng(4).random(scene.num_faces) < 0.8

    def update(t_s):
        pose = scene.camera.pose_at(t_s)
        view = sv.LayerView(pose, scene.camera.fov_deg * 1.1, 64, 36)
        sv.compute_pvs(tracer, [pose], view.fov_deg, 64, 36)
        layers = sv.peel(tracer, None, None, 3, keep_mask=keep, shape=(36, 64), view=view)
        frag = sv.fragments(scene, layers, None, None, t_s, device=tracer.device, view=view)
        sv.path_trace(scene, tracer, frag, t_s, 2, 4, 3, np.random.default_rng(0))
        return len(frag.position)

    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        hashes, sizes = [], []
        # three poses first: the direct light's recorded visibility kernel (Device.frozen) is recorded again in its
        # first calls, up to twice, as Dr.Jit's freeze turns inputs that changed from constants into values in memory
        for t_s in (0.5, 0.9, 1.3, 1.7, 2.1):
            dr.kernel_history()
            sizes.append(update(t_s))
            hashes.append({k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert min(sizes) > 0 and len(set(sizes)) > 1  # other poses, other fragment counts
    known = hashes[0] | hashes[1] | hashes[2]
    for later in hashes[3:]:
        assert later <= known, f"{len(later - known)} kernels compiled for a new pose"


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["gallery", "living_room", "far:living_room"])
def test21_the_denoiser_builds_its_tables_from_the_device_fragments(backend, scene_name, at_parity):
    # Fragments made on the device keep their positions and normals there: the layered SVGF builds its tables from
    # them (the spatial variance included) and uploads only the fragments' illumination, variance and depth. The
    # same filtered light as from the host grids, to rounding, with far fewer bytes going up; and, its passes in
    # float32, the float64 numba passes' light to float32 rounding, also with the scene 1e4 away from the origin
    # (positions relative to a fragment's keep the plane distances' precision).
    from methods.layered_pvs.server import denoise_fragments

    scene, tracer, view = _peeling_view(scene_name, backend)
    layers = sv.peel(tracer, None, None, 3, shape=(45, 80), view=view)
    frag = sv.fragments(scene, layers, None, None, 0.5, device=tracer.device, view=view)
    host_frag = dataclasses.replace(frag, device=None)
    rng = np.random.default_rng(2)
    n = len(frag.position)
    illum = rng.random((n, 3)) * np.where(rng.random((n, 1)) < 0.1, 8.0, 1.0)  # a few bright fragments
    m1 = illum @ np.array([0.2126, 0.7152, 0.0722])
    m2 = m1 * m1 + rng.random(n) * 0.05
    dev = tracer.device
    before = dev.counters["bytes_to_device"]
    want = denoise_fragments(view, layers, host_frag, illum, m1, m2, 2, 5, device=dev)
    grids_up = dev.counters["bytes_to_device"] - before
    before = dev.counters["bytes_to_device"]
    got = denoise_fragments(view, layers, frag, illum, m1, m2, 2, 5, device=dev)
    tables_up = dev.counters["bytes_to_device"] - before
    assert n > 2000 and got.shape == want.shape == (n, 3)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)   # both float32, positions relative to other points
    assert not np.array_equal(got, illum)                         # it filtered
    assert tables_up < grids_up / 3
    numba = denoise_fragments(view, layers, host_frag, illum, m1, m2, 2, 5)
    if backend == "mitsuba-llvm":
        np.testing.assert_allclose(got, numba, rtol=1e-4, atol=1e-6)
    else:  # cuda's fused multiply-adds can tip a tap's choice between two nearly equidistant fragments
        at_parity(got, numba, share=0.999, rtol=1e-4, atol=1e-6)
