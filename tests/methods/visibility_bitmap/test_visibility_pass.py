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
    """The specification: per pixel and light, the offset origin (float64) rounded once into the tracing frame, and
    from it the unit direction and the distance to the light's tracing-frame position in float32 over (P, L, 3)
    arrays, the horizon test against the geometric normal, one occluded query."""
    h, w = g.depth.shape
    vis = np.zeros((h * w, len(lights)), bool)
    idx = np.nonzero(g.valid.reshape(-1))[0]
    if len(lights) == 0 or len(idx) == 0:
        return vis.reshape(h, w, len(lights))
    shift = np.zeros(3) if getattr(tracer, "shift", None) is None else np.asarray(tracer.shift, np.float64)
    ng = g.geo_normal.reshape(-1, 3)[idx].astype(np.float32)
    origin = offset_ray_origin(g.position.reshape(-1, 3)[idx], ng.astype(np.float64), getattr(tracer, "shift", None))
    o_local = (origin - shift).astype(np.float32)
    light_local = (np.stack([lt.position for lt in lights]).astype(np.float64) - shift).astype(np.float32)
    t = light_local[None, :, :] - o_local[:, None, :]
    dist = np.sqrt(t[..., 0] * t[..., 0] + (t[..., 1] * t[..., 1] + t[..., 2] * t[..., 2]))
    d = t / np.maximum(dist, np.float32(1e-30))[..., None]
    cos = (d[..., 0] * ng[:, None, 0] + d[..., 1] * ng[:, None, 1]) + d[..., 2] * ng[:, None, 2]
    above = cos > 0
    assert d.dtype == dist.dtype == cos.dtype == np.float32
    sel = above.reshape(-1)
    o = np.broadcast_to(origin[:, None, :], d.shape).reshape(-1, 3)[sel]
    occ = tracer.occluded(o, d.reshape(-1, 3)[sel], 0.0, dist.reshape(-1)[sel] * np.float32(SHADOW_TMAX_SCALE))
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


def _float32_segments(p, n, light, shift):
    """The rays of the specification (straightforward_visibility) from points ``p`` to one light: (origin, direction,
    length) in the tracing frame, float32, of the points above the light's horizon."""
    shift = np.zeros(3) if shift is None else np.asarray(shift, np.float64)
    o = (offset_ray_origin(p, n, shift) - shift).astype(np.float32)
    t = (np.asarray(light, np.float64) - shift).astype(np.float32) - o
    dist = np.sqrt(t[:, 0] * t[:, 0] + (t[:, 1] * t[:, 1] + t[:, 2] * t[:, 2]))
    d = t / np.maximum(dist, np.float32(1e-30))[:, None]
    n32 = n.astype(np.float32)
    above = (d[:, 0] * n32[:, 0] + d[:, 1] * n32[:, 1]) + d[:, 2] * n32[:, 2] > 0
    return o[above], d[above], (dist * np.float32(SHADOW_TMAX_SCALE))[above], np.flatnonzero(above)


def test08_compiled_shadow_rays_are_float32_segments_from_the_rounded_origin_to_the_rounded_light():
    """Direction and length are computed in float32 from the origin as the backend traces it (offset in float64,
    rounded once into the tracing frame) to the light's rounded tracing-frame position: the traced segment in the
    precision it is traced in, the same bits in both layouts, near the origin and far from it."""
    from suite.core.trace.raygen import ShadowRays

    rng = np.random.default_rng(3)
    p = rng.uniform(-20.0, 20.0, (4000, 3))
    n = rng.standard_normal((4000, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    pixels = np.arange(len(p), dtype=np.int64)
    for shift in (None, np.array([1e4, -3.0, 0.25])):
        for light in ([0.3, 7.7, -1.1], [123.456, -0.001, 5e3]):
            world = np.asarray(light) + (0.0 if shift is None else shift)
            o, d, length, idx = _float32_segments(p + (0.0 if shift is None else shift), n, world, shift)
            assert 0 < len(idx) < len(p)  # lights below some horizons
            for soa in (False, True):
                go, gd, glen, gpix = ShadowRays(p + (0.0 if shift is None else shift), n, pixels, shift,
                                                soa).toward(world, SHADOW_TMAX_SCALE)
                assert np.array_equal(gpix, idx)
                assert np.array_equal(go.T if soa else go, o)
                assert np.array_equal(gd, d) and np.array_equal(glen, length)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name, shift", [("living_room", (1e4, 1e4, 1e4)), ("arena", None)])
def test09_device_shadow_rays_equal_the_compiled_host_rays(backend, name, shift):
    """The rays the device pass traces (:func:`suite.core.device.shading.shadow_rays`, compacted per light) are the
    host's :class:`~suite.core.trace.raygen.ShadowRays`, bit for bit on llvm_ad_rgb."""
    from suite.core.device.shading import shadow_rays
    from suite.core.gbuffer import render_gbuffer_device
    from suite.core.scene import load
    from suite.core.trace import make
    from suite.core.trace.raygen import ShadowRays

    scene = load(name)
    if shift is not None:
        scene = scene.translated(shift)
    tracer = make(backend, scene)
    dg = render_gbuffer_device(scene, tracer, 0.5, (64, 36))
    g = dg.to_host()
    dev = tracer.device
    lights = scene.lights_at(0.5)
    pixels = np.flatnonzero(g.valid.reshape(-1))
    host = ShadowRays(g.position.reshape(-1, 3).astype(np.float64), g.geo_normal.reshape(-1, 3).astype(np.float64),
                      pixels, tracer.shift)
    for light, (ray, idx) in zip(lights, shadow_rays(dg, lights, tracer)):
        o, d, length, pixel = host.toward(light.position, SHADOW_TMAX_SCALE)
        got = [dev.to_host(ray.o), dev.to_host(ray.d), dev.to_host(ray.maxt)]
        got_pixel = dev.to_host(idx)
        assert len(pixel) > 0
        if backend == "mitsuba-llvm":
            assert np.array_equal(got_pixel, pixel)
            assert np.array_equal(got[0], o) and np.array_equal(got[1], d) and np.array_equal(got[2], length)
        else:  # fused multiply-adds on cuda can tip a grazing pixel's horizon test: compare the common pixels
            common, at_got, at_host = np.intersect1d(got_pixel, pixel, return_indices=True)
            assert len(common) >= 0.999 * max(len(pixel), len(got_pixel))
            np.testing.assert_allclose(got[1][at_got], d[at_host], atol=1e-6)
