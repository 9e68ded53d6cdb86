"""The visibility pass (seed 000 Alg. 3B-2 steps 3-4): the column-wise core kernel traces exactly the rays of the
straightforward formulation, so its bitmap is bit-identical, near the origin, far from it, with background pixels
and in small chunks."""
import numpy as np
import pytest

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap.method import visibility_pass
from suite.core.shading import SHADOW_TMAX_SCALE, point_light_visibility
from suite.core.trace.robust import offset_ray_origin


def straightforward_visibility(g, lights, tracer):
    """The specification: per pixel and light, the offset origin, the unit direction and the distance to the
    light in float64 over (P, L, 3) arrays, the horizon test, one occluded query."""
    h, w = g.depth.shape
    vis = np.zeros((h * w, len(lights)), bool)
    idx = np.nonzero(g.valid.reshape(-1))[0]
    if len(lights) == 0 or len(idx) == 0:
        return vis.reshape(h, w, len(lights))
    ng = g.geo_normal.reshape(-1, 3)[idx].astype(np.float64)
    origin = offset_ray_origin(g.position.reshape(-1, 3)[idx], ng, getattr(tracer, "shift", None))
    light_pos = np.stack([lt.position for lt in lights]).astype(np.float64)
    to_light = light_pos[None, :, :] - origin[:, None, :]
    dist = np.linalg.norm(to_light, axis=-1)
    d = to_light / np.maximum(dist, 1e-30)[..., None]
    above = np.einsum("plc,pc->pl", d, ng) > 0
    sel = above.reshape(-1)
    o = np.broadcast_to(origin[:, None, :], d.shape).reshape(-1, 3)[sel]
    occ = tracer.occluded(o, d.reshape(-1, 3)[sel].astype(np.float32), 0.0,
                          (dist.reshape(-1)[sel] * SHADOW_TMAX_SCALE).astype(np.float32))
    flat = np.zeros(above.size, bool)
    flat[sel] = ~occ
    vis[idx] = flat.reshape(above.shape)
    return vis.reshape(h, w, len(lights))


def _scene_and_tracer(name, shift=None):
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load(name)
    if shift is not None:
        scene = scene.translated(shift)
    return scene, make("embree", scene)


@pytest.mark.parametrize("name, shift", [("living_room", None), ("living_room", (1e4, 1e4, 1e4)),
                                         ("atrium", None), ("arena", None)])
def test01_core_kernel_is_bit_identical_to_the_straightforward_formulation(name, shift):
    from suite.core.gbuffer import render_gbuffer

    scene, tracer = _scene_and_tracer(name, shift)
    for t_s in (0.0, 0.9):
        g = render_gbuffer(scene, tracer, t_s, resolution=(64, 36))
        lights = scene.lights_at(t_s)
        expected = straightforward_visibility(g, lights, tracer)
        assert expected.any() and not expected.all()
        assert np.array_equal(point_light_visibility(g, lights, tracer), expected)
        # chunks smaller than a row, and a chunk boundary inside the valid pixels
        assert np.array_equal(point_light_visibility(g, lights, tracer, chunk_rays=50), expected)


def test02_background_pixels_get_no_ray_and_no_bit():
    from suite.core.gbuffer import render_gbuffer

    scene, tracer = _scene_and_tracer("atrium")
    g = render_gbuffer(scene, tracer, 0.0, resolution=(64, 36))
    assert not g.valid.all()  # the atrium's open sky
    before = tracer.counters["rays_occluded"]
    vis = point_light_visibility(g, scene.lights_at(0.0), tracer)
    assert not vis[~g.valid].any()
    assert tracer.counters["rays_occluded"] - before <= int(g.valid.sum()) * len(scene.lights_at(0.0))


def test03_visibility_pass_packs_what_it_traced():
    from suite.core.gbuffer import render_gbuffer

    scene, tracer = _scene_and_tracer("living_room")
    g = render_gbuffer(scene, tracer, 0.0, resolution=(32, 18))
    lights = scene.lights_at(0.0)
    visibility, raw = visibility_pass(g, lights, tracer, "paper32")
    assert raw.nbytes == bm.bitmap_nbytes(32, 18, len(lights), "paper32")
    assert np.array_equal(bm.unpack(raw, 32, len(lights), "paper32"), visibility)


def test04_compiled_ray_origins_match_offset_ray_origin_bit_for_bit_across_magnitudes():
    from suite.core.trace.raygen import ShadowRays

    rng = np.random.default_rng(0)
    scales = np.array([0.0, 1e-30, 1e-8, 1e-3, 0.5, 1.0, 2.0, 3.0, 1e4, 1e7])
    p = (rng.standard_normal((len(scales) * 50, 3)) * np.repeat(scales, 50)[:, None])
    p[:3] = [[0.0, 0.0, 0.0], [2.0, -4.0, 1.0], [-0.0, 1e-40, 0.0]]  # zero, powers of two, a subnormal
    n = np.tile([0.0, 1.0, 0.0], (len(p), 1))
    n[::2] = rng.standard_normal((len(p[::2]), 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[:, 1] = np.abs(n[:, 1]) + 0.1  # every point faces the light above
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    light = np.array([0.0, 1e9, 0.0])
    pixels = np.arange(len(p), dtype=np.int64)
    for shift in (None, np.array([1e4, -3.0, 0.25])):
        for soa in (False, True):
            o, d, length, pixel = ShadowRays(p, n, pixels, shift, soa).toward(light, 1.0)
            assert len(d) == len(p) and np.array_equal(pixel, pixels)
            expected = offset_ray_origin(p, n, shift) - (0.0 if shift is None else shift)
            assert np.array_equal(o.T if soa else o, expected.astype(np.float32))


@pytest.mark.parametrize("n_pixels", [1, 3, 5])
def test05_tiny_pixel_sets_give_the_same_rays_in_both_layouts(n_pixels):
    """Layouts are chosen by flag, never guessed from array shapes (3 pixels look like a (3, N) array)."""
    from suite.core.trace.raygen import ShadowRays

    p = np.arange(3 * n_pixels, dtype=np.float64).reshape(n_pixels, 3)
    n = np.tile([0.0, 1.0, 0.0], (n_pixels, 1))
    pixels = np.arange(n_pixels)
    aos = ShadowRays(p, n, pixels, None, soa=False).toward([0.0, 100.0, 0.0], 1.0)
    soa = ShadowRays(p, n, pixels, None, soa=True).toward([0.0, 100.0, 0.0], 1.0)
    assert np.array_equal(aos[0], soa[0].T) and np.array_equal(aos[1], soa[1])
    np.testing.assert_allclose(aos[0], p, rtol=1e-6, atol=1e-6)


# --- the device path: the pass on a DeviceGBuffer (Mitsuba llvm_ad_rgb / cuda_ad_rgb) --------------------------------

from suite.core.trace import backend_params  # noqa: E402

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name, shift", [("living_room", None), ("living_room", (1e4, 1e4, 1e4)), ("arena", None),
                                         ("gallery", None)])
def test06_device_pass_is_bit_identical_to_the_straightforward_formulation(backend, name, shift):
    """The device kernel (rays generated inside the tracing kernel) against the specification traced through the
    numpy interface of the same backend, from the same G-buffer; also the packed bytes of every layout."""
    from suite.core.gbuffer import render_gbuffer_device
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load(name)
    if shift is not None:
        scene = scene.translated(shift)
    tracer = make(backend, scene)
    for t_s in (0.0, 0.9):
        dg = render_gbuffer_device(scene, tracer, t_s, (64, 36))
        g = dg.to_host()
        lights = scene.lights_at(t_s)
        expected = straightforward_visibility(g, lights, tracer)
        assert expected.any() and not expected.all()
        for layout in bm.LAYOUTS:
            if layout == "paper32" and len(lights) > bm.PAPER_MAX_LIGHTS:
                continue
            vis, raw = visibility_pass(dg, lights, tracer, layout)
            got = vis.to_host()
            host_raw, nbytes = raw.to_host(with_bytes=True)
            if backend == "mitsuba-llvm":
                assert np.array_equal(got, expected)
                assert np.array_equal(host_raw, bm.pack(expected, layout))
            else:
                assert np.mean(got == expected) >= 0.999
            assert np.array_equal(host_raw, bm.pack(got, layout)) and raw.nbytes == host_raw.nbytes
            assert nbytes >= host_raw.nbytes


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("lights_used", [0, 1, 7, 8, 9, 32, 33, 64, 73])
def test07_device_packing_matches_pack_for_every_layout_and_light_count(backend, lights_used):
    from suite.core.gbuffer import render_gbuffer_device
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("arena")
    tracer = make(backend, scene)
    dg = render_gbuffer_device(scene, tracer, 0.5, (20, 11))  # 220 pixels: bitmaps that end inside a word
    lights = scene.lights_at(0.5)[:lights_used]
    for layout in bm.LAYOUTS:
        if layout == "paper32" and lights_used > bm.PAPER_MAX_LIGHTS:
            continue
        vis, raw = visibility_pass(dg, lights, tracer, layout)
        got = vis.to_host()
        assert got.shape == (11, 20, lights_used)
        assert np.array_equal(raw.to_host(), bm.pack(got, layout))
        assert raw.nbytes == bm.bitmap_nbytes(20, 11, lights_used, layout)
