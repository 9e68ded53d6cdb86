"""The compiled passes of the primary and direct stages give the bits of their references: camera rays and
shading samples (primary.py) against whole-array numpy, the one-pass shadow-ray generation of direct.py against
its two-pass reference (``_select`` then ``_rays`` on ``offset_ray_origin``), the accumulation against
``np.bincount``, and the direct stage's image against the chunking."""
import dataclasses

import numpy as np
import pytest

from methods.quake_drt import direct, primary, testscenes
from methods.quake_drt.rng import pixel_seeds
from suite.core.shading import SHADOW_TMAX_SCALE
from suite.core.trace import backend_params, make
from suite.core.trace.robust import offset_ray_origin

SURFACE_FIELDS = ("valid", "prim", "u", "v", "p", "ng", "ns", "ng_view", "ns_view", "albedo", "emission", "material",
                  "o", "d", "t", "overlay_rgb", "overlay_t")


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def _textured(scene, channels=(3, 1, 3), seed=0):
    """``scene`` with random albedo textures (of the given channel counts, odd sizes) on its first materials and
    texture coordinates far outside [0, 1] (the lookup repeats), so that every branch of the lookup runs."""
    rng = np.random.default_rng(seed)
    mats = list(scene.materials)
    for i, c in enumerate(channels[:len(mats)]):
        tex = rng.random((5 + 3 * i, 7 + 2 * i, c)).astype(np.float32)
        mats[i] = dataclasses.replace(mats[i], albedo_texture=tex)
    uvs = rng.uniform(-3.0, 3.0, (len(scene.positions), 2)).astype(np.float32)
    return dataclasses.replace(scene, materials=mats, uvs=uvs)


def _scenes(small_map=None):
    scene, _ = testscenes.two_rooms(door_open=False, lights_in_b=1)  # the door is material 1
    out = [scene, _textured(scene)]
    if small_map is not None:
        from suite.harness import runner

        out.append(runner.load_scene(small_map))
    return out


@pytest.mark.parametrize("jitter", [False, True])
def test01_camera_rays_compiled_equal_numpy(jitter):
    scene, _ = testscenes.two_rooms()
    for w, h in ((37, 23), (64, 48), (1, 1)):
        seeds = pixel_seeds(5, w, h).reshape(-1)
        o, d = primary.camera_rays(scene, 0.0, w, h, seeds, jitter)
        ro, rd = primary.camera_rays_reference(scene, 0.0, w, h, seeds, jitter)
        assert _same(o, ro) and _same(d, rd)


def _random_hits(scene, n, seed):
    """Hits on random faces at random barycentrics (some misses), of random rays through the hit points."""
    rng = np.random.default_rng(seed)
    prim = rng.integers(0, len(scene.faces), n).astype(np.int32)
    prim[rng.random(n) < 0.1] = -1
    u = rng.random(n).astype(np.float32)
    v = (rng.random(n) * (1.0 - u)).astype(np.float32)
    o = rng.normal(0.0, 3.0, (n, 3))
    d = rng.normal(0.0, 1.0, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.where(prim >= 0, rng.uniform(0.1, 10.0, n), np.inf).astype(np.float32)
    u[prim < 0], v[prim < 0] = 0.0, 0.0
    return o, d, prim, u, v, t


def test02_surface_pass_equals_the_reference_on_traced_and_random_hits():
    for scene in _scenes():
        tracer = make("embree", scene)
        w, h = 40, 30
        o, d = primary.camera_rays(scene, 0.0, w, h, pixel_seeds(3, w, h).reshape(-1), True)
        hits = tracer.intersect(o, d.astype(np.float32))
        cases = [(o, d, hits.prim, hits.u, hits.v, hits.t), _random_hits(scene, 4000, 1)]
        for case, (co, cd, prim, u, v, t) in enumerate(cases):
            s = primary.surface_from_hits(scene, 0.0, co, cd, prim, u, v, t)
            ref = primary.surface_from_hits_reference(scene, 0.0, co, cd, prim, u, v, t)
            for f in SURFACE_FIELDS:
                assert _same(getattr(s, f), getattr(ref, f)), f
            if case == 1 and scene.materials[1].albedo_texture is not None:  # both channel counts are read
                one = s.albedo[s.material == 1]
                three = s.albedo[s.material == 0]
                assert len(one) and (one[:, 0] == one[:, 2]).all()
                assert len(three) and (three[:, 0] != three[:, 2]).any() and len(np.unique(three[:, 0])) > 10


def test03_surface_pass_on_an_openarena_map(small_map):
    from suite.harness import runner

    scene = runner.load_scene(small_map)
    tracer = make("embree", scene)
    w, h = 96, 54
    o, d = primary.camera_rays(scene, 1.0, w, h, pixel_seeds(9, w, h).reshape(-1), True)
    hits = tracer.intersect(o, d.astype(np.float32))
    s = primary.surface_from_hits(scene, 1.0, o, d, hits.prim, hits.u, hits.v, hits.t)
    ref = primary.surface_from_hits_reference(scene, 1.0, o, d, hits.prim, hits.u, hits.v, hits.t)
    for f in SURFACE_FIELDS:
        assert _same(getattr(s, f), getattr(ref, f)), f


def test04_textures_the_pass_does_not_take_go_to_the_reference():
    scene, _ = testscenes.two_rooms()
    rgba = _textured(scene, channels=(4,))
    assert primary._texture_table(rgba) is None
    o, d, prim, u, v, t = _random_hits(rgba, 500, 2)
    rgb = dataclasses.replace(rgba, materials=[dataclasses.replace(m, albedo_texture=None) for m in rgba.materials])
    s = primary.surface_from_hits(rgb, 0.0, o, d, prim, u, v, t)
    ref = primary.surface_from_hits_reference(rgb, 0.0, o, d, prim, u, v, t)
    assert all(_same(getattr(s, f), getattr(ref, f)) for f in SURFACE_FIELDS)


def _jittered_samples(scene, tracer, w, h, seed):
    """(pixel seeds, surface_from_hits of the jittered camera rays traced whole) at time 0."""
    seeds = pixel_seeds(seed, w, h).reshape(-1)
    o, d = primary.camera_rays(scene, 0.0, w, h, seeds, True)
    hits = tracer.intersect(o, d.astype(np.float32))
    return seeds, primary.surface_from_hits(scene, 0.0, o, d, hits.prim, hits.u, hits.v, hits.t)


@pytest.mark.parametrize("k,mode,soft", [(0, "uniform", True), (0, "uniform", False), (1, "uniform", True),
                                         (3, "uniform", True), (2, "power", True), (4, "irradiance", False)])
def test05_one_pass_ray_generation_equals_select_then_rays(k, mode, soft, direct_setup):
    scene, tracer, pts, lights, table, rows = direct_setup()
    mode_code = direct.MODES.index(mode)
    cdf = {"uniform": np.zeros(len(table.row_lights)),
           "power": direct.row_power_cdf(table.row_offsets, table.row_lights, lights.power),
           "irradiance": direct.row_irradiance_cdf(table, lights)}[mode]
    shift = np.asarray(tracer.shift, np.float64)
    counts = np.diff(table.row_offsets)[rows]
    widest = int((counts if k == 0 else np.minimum(counts, k)).max())
    per_point = counts if k == 0 else np.minimum(counts, k)
    cap = max(widest, int(per_point.sum()) // 5)  # several chunks
    seeds = np.ascontiguousarray(pts.seed, np.uint32)
    light_args = (lights.kind, lights.position, lights.rgb, lights.area, lights.tri_offsets,
                  np.ascontiguousarray(lights.tri_p0), lights.tri_e1, lights.tri_e2, lights.tri_normal, lights.tri_cdf,
                  lights.rep_tri, soft, shift, 0.01, float(SHADOW_TMAX_SCALE))
    pt_args = (pts.ng, pts.ns, pts.lambert, seeds)
    origin = offset_ray_origin(pts.p, pts.ng, shift)

    def outputs():
        return (np.empty((cap, 3), np.float32), np.empty((cap, 3), np.float32), np.empty(cap, np.float32),
                np.empty((cap, 3)), np.empty(cap, np.int32))

    i_ref = i_new = 0
    chunks = 0
    while i_ref < len(rows):
        s_point, s_light, s_dim = (np.empty(cap, np.int64) for _ in range(3))
        s_weight = np.empty(cap)
        samples, i_ref, cand_ref, sel_ref = direct._select(i_ref, rows, table.row_offsets, table.row_lights, cdf, k,
                                                           mode_code, seeds, np.empty(widest, np.int64), s_point,
                                                           s_light, s_weight, s_dim)
        ref = outputs()
        n_ref = direct._rays(samples, s_point, s_light, s_weight, s_dim, origin, *pt_args, *light_args, *ref,
                             np.empty(cap, np.int32))
        new = outputs()
        scratch = (np.empty(widest, np.int64), np.empty(widest, np.int64), np.empty(widest),
                   np.empty(widest, np.int64))
        n_new, i_new, cand, sel = direct._generate(i_new, cap, rows, table.row_offsets, table.row_lights, cdf, k,
                                                   mode_code, *scratch, pts.p, *pt_args, *light_args, *new)
        assert (n_new, i_new, cand, sel) == (n_ref, i_ref, cand_ref, sel_ref)
        assert n_new > 0
        for a, b in zip(new, ref):
            assert _same(a[:n_new], b[:n_ref])
        chunks += 1
    assert chunks > 2


def test06_accumulation_equals_bincount():
    rng = np.random.default_rng(4)
    n_pts, n_rays = 300, 20000
    pt = np.sort(rng.integers(0, n_pts, n_rays)).astype(np.int32)
    w = rng.random((n_rays, 3)) * 10.0 ** rng.uniform(-6, 3, (n_rays, 1))
    occ = rng.random(n_rays) < 0.4
    out = np.zeros((n_pts, 3))
    visible = direct._accumulate(n_rays, occ, w, pt, out)
    lit = np.nonzero(~occ)[0]
    ref = np.zeros((n_pts, 3))
    for c in range(3):
        ref[:, c] += np.bincount(pt[lit], weights=w[lit, c], minlength=n_pts)
    assert visible == len(lit)
    assert _same(out, ref)


def test07_the_direct_stage_does_not_depend_on_its_chunking(monkeypatch, direct_setup):
    scene, tracer, pts, lights, table, rows = direct_setup()
    pts = dataclasses.replace(pts, lambert=np.ones(len(pts), bool))
    md = 0.01
    whole, st_whole = direct.shade(pts, lights, table, rows, 0, "uniform", True, tracer, scene, md, 1 << 24)
    monkeypatch.setattr(direct, "PIPELINE_FIRST_SAMPLES", 64)
    monkeypatch.setattr(direct, "PIPELINE_MAX_SAMPLES", 2048)
    chunked, st_chunked = direct.shade(pts, lights, table, rows, 0, "uniform", True, tracer, scene, md, 1 << 24)
    small, st_small = direct.shade(pts, lights, table, rows, 0, "uniform", True, tracer, scene, md, 1024)
    assert _same(whole, chunked) and _same(whole, small)
    assert st_whole == st_chunked == st_small
    assert st_whole.rays > 4096


def test08_pipelined_shading_samples_equal_the_whole_image_passes(monkeypatch):
    """The primary stage's jittered shading rays are made, traced and shaded in row chunks, pipelined: the samples
    equal surface_from_hits of the whole image's rays and hits, textured scenes included."""
    from suite.core import gbuffer

    monkeypatch.setattr(gbuffer, "PIPELINE_MIN_PIXELS", 300)
    for scene in _scenes():
        tracer = make("embree", scene)
        w, h = 64, 40
        seeds, whole = _jittered_samples(scene, tracer, w, h, 9)
        assert len(gbuffer.row_chunks(h, w)) > 1
        _, piped = primary.primary_stage(scene, tracer, 0.0, None, (w, h), seeds, jitter=True)
        for field in SURFACE_FIELDS:
            assert _same(getattr(whole, field), getattr(piped, field)), field


def test09_per_pixel_demodulation_equals_bincount():
    """Radiance and albedo summed per pixel in point order and their ratio (or the fallbacks for an albedo under
    1e-6): the compiled pass gives the bits of the np.bincount reference, with glossy points (albedo 1), several
    points per pixel, pixels without points and black points."""
    from methods.quake_drt import pipeline

    rng = np.random.default_rng(12)
    m, n = 5000, 900
    albedo = rng.random((m, 3))
    albedo[::11] = 0.0                          # black surfaces: the albedo fallback
    pts = direct.ShadingPoints(pixel=rng.integers(0, n - 50, m), throughput=rng.random((m, 3)) * 2,
                               p=np.zeros((m, 3)), ng=np.zeros((m, 3)), ns=np.zeros((m, 3)), wi=np.zeros((m, 3)),
                               albedo=albedo, material=np.zeros(m, np.int64), prim=np.zeros(m, np.int64),
                               seed=np.zeros(m, np.uint32), lambert=rng.random(m) < 0.8)
    il = rng.random((m, 3)) * 3
    il[::13] = 0.0
    pts.pixel[:3], pts.lambert[:3], pts.throughput[:3] = n - 1, False, 1e-8  # radiance under a near-zero albedo
    got = pipeline.demodulate(pts, il, n)
    ref = pipeline.demodulate_reference(pts, il, n)
    assert all(_same(a, b) for a, b in zip(got, ref))
    assert (ref[1][n - 50:-1] == 0).all() and (ref[1][-1] == 1.0).all()  # empty pixels; albedo 1 under light
    empty = pts.subset(slice(0, 0))
    assert all(_same(a, b) for a, b in zip(pipeline.demodulate(empty, il[:0], 4),
                                           pipeline.demodulate_reference(empty, il[:0], 4)))


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
def test10_on_a_drjit_tracer_the_primary_stage_takes_the_device_gbuffer_with_the_host_pipelines_bits(backend,
                                                                                                    monkeypatch):
    """A Mitsuba llvm/cuda tracer's primary stage traces its jittered shading rays whole and takes the device
    G-buffer (suite.core.device) instead of the host pipeline of row chunks: the same G-buffer and samples as that
    pipeline on the same backend (its queries through a wrapper that hides the device)."""
    from suite.core import gbuffer
    from suite.core.device import gbuffer as device_gbuffer
    from suite.core.trace.recording import RecordingTracer

    monkeypatch.setattr(gbuffer, "PIPELINE_MIN_PIXELS", 300)
    calls = []
    original = device_gbuffer.render_gbuffer
    monkeypatch.setattr(device_gbuffer, "render_gbuffer", lambda *a, **k: calls.append(1) or original(*a, **k))
    for scene in _scenes():
        tracer = make(backend, scene)
        w, h = 64, 40
        seeds = pixel_seeds(9, w, h).reshape(-1)
        g_dev, s_dev = primary.primary_stage(scene, tracer, 0.0, None, (w, h), seeds, jitter=True)
        g_host, s_host = primary.primary_stage(scene, RecordingTracer(tracer), 0.0, None, (w, h), seeds, jitter=True)
        for field in SURFACE_FIELDS:
            assert _same(getattr(s_dev, field), getattr(s_host, field)), field
        for field in ("position", "normal", "geo_normal", "albedo", "depth", "prim", "valid"):
            assert _same(getattr(g_dev, field), getattr(g_host, field)), field
    assert len(calls) == len(_scenes())


def test11_row_assignment_and_shading_point_joins_equal_numpys():
    """``primary.put_rows`` (whole rows through a void view) is ``dst[rows] = src`` for 1-D and (N, k) arrays, other
    source dtypes and strided sources; ``ShadingPoints.concat`` of one part with points is that part, of several
    their fields joined in order."""
    rng = np.random.default_rng(11)
    rows = np.sort(rng.choice(500, 70, replace=False))
    cases = [(rng.random(500), rng.random(70)), (rng.random((500, 3)), rng.random((70, 3))),
             (rng.integers(0, 9, (500, 3)), rng.integers(0, 9, (70, 3))),
             (rng.random((500, 3)), rng.random((70, 3)).astype(np.float32)),
             (rng.random((500, 3)), rng.random((70, 6))[:, ::2]), (np.zeros(500, bool), rng.random(70) < 0.5)]
    for dst, src in cases:
        want = dst.copy()
        want[rows] = src
        primary.put_rows(dst, rows, src)
        assert np.array_equal(dst, want)
    one = direct.ShadingPoints.empty()
    one = dataclasses.replace(one, pixel=np.arange(4), throughput=rng.random((4, 3)), p=rng.random((4, 3)),
                              ng=rng.random((4, 3)), ns=rng.random((4, 3)), wi=rng.random((4, 3)),
                              albedo=rng.random((4, 3)), material=np.arange(4), prim=np.arange(4),
                              seed=np.arange(4, dtype=np.uint32), lambert=np.ones(4, bool))
    assert direct.ShadingPoints.concat([one, None, direct.ShadingPoints.empty()]) is one
    two = direct.ShadingPoints.concat([one, one])
    assert len(two) == 8 and np.array_equal(two.p, np.concatenate([one.p, one.p]))
    assert len(direct.ShadingPoints.concat([None, direct.ShadingPoints.empty()])) == 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test12_barycentric_points_are_the_bits_of_the_weighted_sum(dtype):
    """The forward projection's points (``primary.barycentric_points``) without (N, 3, 3) temporaries: the bits of
    numpy's ``(tri * w).sum(axis=1)``, which adds the three weighted corners in order, for float32 and float64
    barycentrics."""
    from methods.quake_drt.primary import barycentric_points

    rng = np.random.default_rng(5)
    tri = rng.normal(size=(4097, 3, 3)) * 1e3
    u, v = (rng.random(4097) * 0.5).astype(dtype), (rng.random(4097) * 0.5).astype(dtype)
    want = (tri * np.stack([1.0 - u - v, u, v], axis=-1)[..., None]).sum(axis=1)
    got = barycentric_points(tri, u, v)
    assert got.dtype == np.float64 and np.array_equal(got, want)
