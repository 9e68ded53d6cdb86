"""The device-resident Dr.Jit path (suite.core.device): the same G-buffer, rays, bits and images as the host path on
the same backend, agreement with Embree, explicit host copies, and the Mitsuba tracer's shape resolution.

Every test runs on each Dr.Jit variant: llvm_ad_rgb here, cuda_ad_rgb where a GPU is usable (skipped with the
reason otherwise). On llvm_ad_rgb the device kernels perform the host path's operations in the same order and
precision, so the comparisons are exact; on cuda_ad_rgb (other rounding of division and square root, fused
multiply-adds) ids and bits agree at the backends' parity and images within float32 rounding.
"""
import numpy as np
import pytest

from suite.core import gbuffer as host_gbuffer
from suite.core import shading as host_shading
from suite.core.scene import list_scenes, load
from suite.core.trace import backend_params, make

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")
SCENES = [name for name, desc in sorted(list_scenes().items()) if not desc.startswith("unavailable")
          and not name.startswith("oa:")]
RES = (64, 36)


def exact(backend) -> bool:
    """Bit-exact comparisons with the numpy/numba host path hold on the CPU variant."""
    return backend == "mitsuba-llvm"


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name, offset", [(n, None) for n in SCENES] + [("living_room", 1e4)])
def test01_device_gbuffer_equals_the_host_gbuffer(backend, name, offset):
    """Every field, including motion vectors with object animation (arena) and textures and alpha (gallery)."""
    from suite.core.device import render_gbuffer

    scene = load(name)
    if offset:
        scene = scene.translated((offset, offset, offset))
    tracer = make(backend, scene)
    t_s, prev = 0.9, 0.8
    host = host_gbuffer.render_gbuffer(scene, tracer, t_s, RES, prev, device=False)
    before = tracer.counters["rays_intersect"]
    dg = render_gbuffer(scene, tracer, t_s, RES, prev)
    assert tracer.counters["rays_intersect"] - before == dg.rays >= RES[0] * RES[1]
    dev = dg.to_host()
    if exact(backend):
        for field in ("prim", "valid", "depth", "position", "normal", "geo_normal", "albedo", "emission", "material",
                      "kind", "view_dir"):
            assert np.array_equal(getattr(host, field), getattr(dev, field)), field
    else:
        assert np.mean(host.prim == dev.prim) >= 0.999
        same = host.prim == dev.prim
        np.testing.assert_allclose(dev.position[same], host.position[same], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dev.motion, host.motion, atol=1e-3)


@pytest.mark.parametrize("backend", DRJIT)
def test02_device_camera_rays_are_the_host_rays(backend):
    from suite.core.device import camera_rays

    scene = load("atrium")
    tracer = make(backend, scene)
    pose = scene.camera.pose_at(0.7)
    _, d64 = host_gbuffer.camera_rays(pose, scene.camera.fov_deg, 33, 19, dtype=np.float64)
    d_dev, _, _ = camera_rays(tracer.device, pose, scene.camera.fov_deg, 33, 19)
    got = tracer.device.to_host(d_dev)
    if exact(backend):
        assert np.array_equal(got, d64)
    np.testing.assert_allclose(got, d64, atol=1e-12)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name", ["living_room", "arena", "gallery", "atrium"])
def test03_device_visibility_bits_and_ray_counts_equal_the_host_path(backend, name):
    """The same shadow rays from the same G-buffer: identical bits (73 lights in 3 words on arena; alpha-tested
    shadows on gallery) and the same ray counters."""
    from suite.core.device import point_light_visibility, render_gbuffer

    scene = load(name)
    tracer = make(backend, scene)
    for t_s in (0.0, 0.9):
        g = host_gbuffer.render_gbuffer(scene, tracer, t_s, RES, device=False)
        lights = scene.lights_at(t_s)
        c0 = dict(tracer.counters)
        host = host_shading.point_light_visibility(g, lights, tracer)
        c1 = dict(tracer.counters)
        dg = render_gbuffer(scene, tracer, t_s, RES)
        c2 = dict(tracer.counters)
        vis = point_light_visibility(dg, lights, tracer)
        c3 = dict(tracer.counters)
        dev = vis.to_host()
        # both kernel shapes (lights written out, the CPU's default; a symbolic loop, the GPU's) give the same bits
        for unroll in (0, 32):
            assert np.array_equal(point_light_visibility(dg, lights, tracer, unroll=unroll).to_host(), dev)
        assert dev.shape == host.shape and host.any() and not host.all()
        if exact(backend):
            assert np.array_equal(dev, host)
            assert {k: c1[k] - c0[k] for k in c0} == {k: c3[k] - c2[k] for k in c0}
        else:
            assert np.mean(dev == host) >= 0.999


@pytest.mark.parametrize("backend", DRJIT)
def test04_device_shading_equals_the_host_shading(backend):
    from suite.core.device import point_light_visibility, render_gbuffer, shade_point_lights

    scene = load("living_room")
    tracer = make(backend, scene)
    g = host_gbuffer.render_gbuffer(scene, tracer, 0.5, RES, device=False)
    lights = scene.lights_at(0.5)
    vis = host_shading.point_light_visibility(g, lights, tracer)
    min_d = host_shading.min_light_distance(scene)
    dg = render_gbuffer(scene, tracer, 0.5, RES)
    dvis = point_light_visibility(dg, lights, tracer)
    for ambient in (None, 0.02):
        host = host_shading.shade_point_lights(g, lights, vis, ambient=ambient, min_distance=min_d)
        img, nbytes = shade_point_lights(dg, lights, dvis, ambient=ambient, min_distance=min_d).to_host(with_bytes=True)
        assert nbytes == RES[0] * RES[1] * 3 * 4
        if exact(backend):
            assert np.array_equal(img, host)
        np.testing.assert_allclose(img, host, rtol=1e-5, atol=1e-7)
        # shading from uploaded records in the byte layout of a received bitmap gives the same image
        from suite.core.device import DeviceVisibility

        packed = np.packbits(vis, axis=-1, bitorder="little").reshape(RES[1], -1)
        uploaded = DeviceVisibility.from_host_bytes(dg.device, packed, RES[0], RES[1], len(lights), 1)
        again = shade_point_lights(dg, lights, uploaded, ambient=ambient, min_distance=min_d).to_host()
        assert np.array_equal(again, img)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name", ["cornell", "gallery", "atrium"])
def test05_device_area_lights_take_the_host_estimators_samples(backend, name, at_parity):
    """The same counter-based random numbers (suite.core.rng) and the same operations: on the same G-buffer and
    backend the device image equals the host estimator's bit for bit on llvm_ad_rgb (at parity on cuda_ad_rgb), for
    seed and number of samples, with alpha-tested occluders (gallery) and many lights (atrium); another seed gives
    another image."""
    from suite.core.device import render_gbuffer

    scene = load(name)
    tracer = make(backend, scene)
    dg = render_gbuffer(scene, tracer, 0.0, (40, 40))
    g = dg.to_host()
    area = host_shading.AreaLights(scene, 0.0)
    images = []
    for seed, samples in ((0, 16), (5, 7)):  # a square number of samples and not
        host = host_shading.area_light_radiance(g, area, tracer, samples, seed=seed)
        dev = host_shading.area_light_radiance(dg, area, tracer, samples, seed=seed).to_host()
        assert host.max() > 0
        if exact(backend):
            assert np.array_equal(dev, host)
        else:
            at_parity(dev, host, share=0.99, rtol=1e-4, atol=1e-6)
        images.append(dev)
    assert not np.array_equal(images[0], images[1])


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name", ["gallery", "atrium"])
def test05b_embree_and_device_area_lights_agree_to_rounding_not_within_noise(backend, name):
    """Embree's host estimator and the device's take the same samples: the images differ only where the backends'
    barycentrics differ in the last bits (interpolated normals, texels) or a shadow ray grazes an occluder, so the
    mean relative difference is at rounding level and almost every pixel agrees to 1e-3 (independent random
    numbers at 16 samples differ by several per cent per pixel)."""
    from suite.core.device import render_gbuffer

    scene = load(name)
    area = host_shading.AreaLights(scene, 0.0)
    embree = make("embree", scene)
    host = host_shading.area_light_radiance(host_gbuffer.render_gbuffer(scene, embree, 0.0, (64, 36)), area, embree,
                                            16, seed=2).astype(np.float64)
    tracer = make(backend, scene)
    dev = host_shading.area_light_radiance(render_gbuffer(scene, tracer, 0.0, (64, 36)), area, tracer, 16,
                                           seed=2).to_host().astype(np.float64)
    lit = host.max(axis=-1) > 1e-4
    rel = (np.abs(dev - host).max(axis=-1) / np.maximum(host.max(axis=-1), 1e-12))[lit]
    assert lit.mean() > 0.3
    assert rel.mean() < 1e-4
    assert (rel > 1e-3).mean() < 0.005


@pytest.mark.parametrize("backend", DRJIT)
def test06_render_gbuffer_and_direct_lighting_dispatch_to_the_device_and_keep_the_twin(backend):
    scene = load("atrium")
    tracer = make(backend, scene)
    g = host_gbuffer.render_gbuffer(scene, tracer, 0.3, RES)
    assert g.device is not None and g.device.device is tracer.device
    with pytest.raises(ValueError):
        g.position[0, 0, 0] = 1.0  # read-only: the device twin cannot drift from it
    before = dict(tracer.device.counters)
    img = host_shading.direct_lighting(scene, g, tracer, 0.3, area_samples=4)
    assert isinstance(img, np.ndarray) and img.shape == (RES[1], RES[0], 3)
    assert tracer.device.counters["bytes_to_device"] - before["bytes_to_device"] < 100_000  # no G-buffer upload
    assert tracer.device.counters["bytes_to_host"] - before["bytes_to_host"] == img.nbytes
    # Embree keeps the host path and has no device
    emb = make("embree", scene)
    assert getattr(emb, "device", None) is None and host_gbuffer.render_gbuffer(scene, emb, 0.3, RES).device is None


@pytest.mark.parametrize("backend", DRJIT)
def test07_host_copies_are_explicit_and_counted(backend):
    from suite.core.device import render_gbuffer

    scene = load("living_room")
    tracer = make(backend, scene)
    dg = render_gbuffer(scene, tracer, 0.0, RES, prev_t_s=0.0)
    dev = tracer.device
    before = dict(dev.counters)
    g, nbytes = dg.to_host(with_bytes=True)
    n = RES[0] * RES[1]
    # position f64 x3, 5 float32 vectors x3, motion 2 floats, depth, prim, material, kind (int32) and valid (bool)
    assert nbytes == n * (24 + 5 * 12 + 8 + 4 * 4 + 1)
    assert dev.counters["bytes_to_host"] - before["bytes_to_host"] == nbytes
    part, part_bytes = dg.to_host(names=["prim"], with_bytes=True)
    assert part_bytes == n * 4 and part.position is None and np.array_equal(part.prim, g.prim)
    copy = dev.to_host(dg.depth, with_bytes=True)
    assert copy.nbytes == n * 4 and copy.array.dtype == np.float32


def _edge_tie(scene, a, b):
    """Per ray: hits ``a`` and ``b`` are different faces of one object that share an edge (two vertices)."""
    both = (a >= 0) & (b >= 0) & (a != b)
    fa, fb = scene.faces[np.maximum(a, 0)], scene.faces[np.maximum(b, 0)]
    shared = (fa[:, :, None] == fb[:, None, :]).any(axis=2).sum(axis=1)
    return both & (shared >= 2) & (scene.face_object[np.maximum(a, 0)] == scene.face_object[np.maximum(b, 0)])


@pytest.mark.parametrize("backend", DRJIT)
def test08_dynamic_geometry_hits_resolve_by_shape_not_shape_index(backend, monkeypatch):
    """On cuda_ad_rgb ``PreliminaryIntersection.shape_index`` is 0 whatever shape was hit, which gave hits on the
    moving platform the static mesh's faces. The tracer resolves the shape from ``pi.shape``; here every query
    returns shape_index = 0, as cuda_ad_rgb does, and the platform's faces must still come back (numpy and device
    paths), matching Embree face for face."""
    import drjit as dr

    from suite.core.device import render_gbuffer

    scene = load("arena")
    tracer = make(backend, scene)
    real = tracer.mscene

    class CudaLikeShapeIndex:
        def ray_intersect_preliminary(self, ray, *args, **kwargs):
            pi = real.ray_intersect_preliminary(ray, *args, **kwargs)
            pi.shape_index = dr.zeros(type(pi.shape_index), dr.width(pi.t))
            return pi

        def ray_test(self, ray, *args, **kwargs):
            return real.ray_test(ray, *args, **kwargs)

    monkeypatch.setattr(tracer, "query_scene", CudaLikeShapeIndex())
    anim = scene.object_animations[0]
    faces = np.nonzero(scene.face_object == anim.object_id)[0]
    t_rest = float(anim.times_s[0])
    tri = scene.triangles(scene.positions_at(t_rest))[faces].reshape(-1, 3)
    top = np.array([[tri[:, 0].mean(), tri[:, 1].max() + 0.2, tri[:, 2].mean()]], np.float32)
    tracer.update(t_rest)
    hit = tracer.intersect(top, np.float32([[0, -1, 0]])).prim[0]
    assert scene.face_object[hit] == anim.object_id
    embree = make("embree", scene)
    dev = tracer.device
    for t_s in (t_rest, float(anim.times_s[1])):
        # a grid of downward rays over the platform and its surroundings, on both paths and on Embree
        tri = scene.triangles(scene.positions_at(t_s))[faces].reshape(-1, 3)
        lo, hi = tri.min(axis=0) - 0.5, tri.max(axis=0) + 0.5
        xx, zz = np.meshgrid(np.linspace(lo[0], hi[0], 40), np.linspace(lo[2], hi[2], 40))
        o = np.stack([xx.ravel(), np.full(xx.size, hi[1] + 0.5), zz.ravel()], -1).astype(np.float32)
        d = np.tile(np.float32([[0, -1, 0]]), (len(o), 1))
        tracer.update(t_s), embree.update(t_s)
        ref = embree.intersect(o, d).prim
        on_platform = np.isin(ref, faces)
        assert on_platform.sum() > 100
        got_numpy = tracer.intersect(o, d).prim
        got_device = dev.to_host(dev.intersect(dev.to_device(o, dev.Point3f), dev.to_device(d, dev.Vector3f)).prim)
        for got in (got_numpy, got_device):
            # a ray through the diagonal two triangles share may hit either (OptiX breaks such ties unlike Embree):
            # the same face, or a face of the same object sharing that edge, is agreement
            agree = (got == ref) | _edge_tie(scene, got, ref)
            assert np.mean(agree[on_platform]) >= 0.99 and np.mean(agree) >= 0.99
            assert np.array_equal(scene.face_object[got[on_platform]], scene.face_object[ref[on_platform]])
        g = render_gbuffer(scene, tracer, t_s, (48, 27)).to_host(names=["prim"]).prim
        assert np.mean(g == host_gbuffer.render_gbuffer(scene, embree, t_s, (48, 27)).prim) >= 0.999


@pytest.mark.parametrize("backend", DRJIT)
def test09_device_queries_take_tmin_and_tmax_like_the_numpy_interface(backend, room_scene):
    tracer = make(backend, room_scene)
    dev = tracer.device
    o = np.array([[0, 0.3, 1.0]] * 4, np.float32)
    d = np.array([[1, 0, 0]] * 4, np.float32)
    o_d, d_d = dev.to_device(o, dev.Point3f), dev.to_device(d, dev.Vector3f)
    for tmin in (0.0, 1.0, 2.0):
        hits = dev.intersect(o_d, d_d, tmin)
        ref = tracer.intersect(o, d, tmin)
        np.testing.assert_allclose(dev.to_host(hits.t), ref.t, rtol=1e-6)
        assert np.array_equal(dev.to_host(hits.prim), ref.prim)
    tmax = np.float32([0.4, 0.6, 0.4, 0.6])
    blocked = dev.to_host(dev.occluded(o_d, d_d, 0.0, dev.to_device(tmax, dev.Float)))
    assert blocked.tolist() == [False, True, False, True]
    assert tracer.counters["rays_occluded"] == 4 and tracer.counters["rays_intersect"] == 3 * 4 + 3 * 4


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name", ["living_room", "arena", "gallery"])
def test10_device_path_agrees_with_embree(backend, name):
    """The two independent backends: primitive ids at the tracing parity (>= 99.9 %), visibility bits on >= 99.5 %
    of pixel-lights (the rest lie on shadow edges, where a one-ULP difference in the hit point decides)."""
    from suite.core.device import point_light_visibility, render_gbuffer

    scene = load(name)
    tracer, embree = make(backend, scene), make("embree", scene)
    g_e = host_gbuffer.render_gbuffer(scene, embree, 0.5, (96, 54))
    dg = render_gbuffer(scene, tracer, 0.5, (96, 54))
    assert np.mean(dg.to_host(names=["prim"]).prim == g_e.prim) >= 0.999
    lights = scene.lights_at(0.5)
    v_e = host_shading.point_light_visibility(g_e, lights, embree)
    v_d = point_light_visibility(dg, lights, tracer).to_host()
    assert np.mean(v_e == v_d) >= 0.995


@pytest.mark.parametrize("backend", DRJIT)
def test11_frame_scalars_read_from_one_copied_block_give_the_same_gbuffer(backend, monkeypatch):
    """Per-frame scalars (camera basis, positions, sizes) reach the kernels either as broadcast scalars (llvm) or as
    loads from one copied block (cuda, where each broadcast scalar is a launch): the same values, so the same
    G-buffer, bit for bit, motion vectors and moving objects included (arena)."""
    from suite.core.device import render_gbuffer

    scene = load("arena")
    tracer = make(backend, scene)
    dev = tracer.device
    fields = ("position", "normal", "depth", "prim", "motion")

    def render():
        before = dev.counters["copies_to_device"]
        g = render_gbuffer(scene, tracer, 0.9, RES, 0.8).to_host(names=list(fields))
        return g, dev.counters["copies_to_device"] - before

    render()  # the scene tables go to the device on first use
    plain, plain_copies = render()
    monkeypatch.setattr(dev, "is_cuda", not dev.is_cuda)  # the other way of passing the scalars
    other, other_copies = render()
    assert (other_copies > plain_copies) == dev.is_cuda  # the blocks are explicit, counted copies
    for name in fields:
        assert np.array_equal(getattr(plain, name), getattr(other, name)), name


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name", ["arena", "gallery"])
def test12_recorded_kernels_replay_later_frames_exactly_without_recording_again(backend, name):
    """The G-buffer and the visibility pass are recorded on their first calls (per resolution and light count) and
    replayed afterwards: frame after frame (a moving object and motion vectors on arena, alpha-tested surfaces on
    gallery, lights moved between frames) a replay gives what the same kernels give traced afresh, bit for bit, and
    no new recording is made."""
    import dataclasses

    from suite.core.device import render_gbuffer
    from suite.core.device.shading import point_light_visibility

    scene = load(name)
    tracer = make(backend, scene)
    dev = tracer.device
    fields = ["position", "normal", "geo_normal", "albedo", "depth", "prim", "motion", "emission"]

    def frame(t_s, lights, record):
        dev.record_kernels = record
        try:
            g = render_gbuffer(scene, tracer, t_s, RES, t_s - 0.05)
            vis = point_light_visibility(g, lights, tracer)
            return g.to_host(names=fields), dev.to_host(vis.data)
        finally:
            dev.record_kernels = True

    recordings = []
    for i, t_s in enumerate((0.3, 0.9, 1.7, 2.4, 3.1, 3.6)):
        lights = [dataclasses.replace(lt, position=lt.position + 0.05 * i) for lt in scene.lights_at(t_s)]
        (g, bits), (fresh, fresh_bits) = frame(t_s, lights, True), frame(t_s, lights, False)
        for f in fields:
            assert np.array_equal(getattr(g, f), getattr(fresh, f)), (t_s, f)
        assert np.array_equal(bits, fresh_bits), t_s
        recordings.append((dev._frozen["gbuffer"].n_recordings, dev._frozen["visibility"].n_recordings))
    # Dr.Jit records again when an input it took for a constant (the same value in its first calls: a camera at
    # rest, lights not yet moved) changes, and when its inputs first come from a replay; after that, frames replay
    assert recordings[-1] == recordings[-3] and max(recordings[-1]) <= 3, recordings
    render_gbuffer(scene, tracer, 0.3, (RES[0] // 2, RES[1] // 2), 0.25)  # another resolution: another recording
    assert dev._frozen["gbuffer"].n_recordings == recordings[-1][0] + 1


@pytest.mark.parametrize("backend", DRJIT)
def test13_grey_and_rgb_albedo_maps_read_alike_on_device_and_host(backend):
    """A single-channel albedo map is grey (its value in R, G and B) on both paths, beside three-channel ones, with
    texture coordinates far outside [0, 1] (the lookup repeats)."""
    import dataclasses

    from suite.core.device import render_gbuffer

    scene = load("living_room")
    rng = np.random.default_rng(3)
    mats = list(scene.materials)
    for i, channels in enumerate((1, 3, 1)):
        mats[i] = dataclasses.replace(mats[i], albedo_texture=rng.random((5 + 2 * i, 7, channels)).astype(np.float32))
    scene = dataclasses.replace(scene, materials=mats,
                                uvs=rng.uniform(-3.0, 3.0, (len(scene.positions), 2)).astype(np.float32))
    tracer = make(backend, scene)
    host = host_gbuffer.render_gbuffer(scene, tracer, 0.5, RES, device=False)
    dev = render_gbuffer(scene, tracer, 0.5, RES).to_host()
    grey = host.valid & np.isin(host.material, [0, 2])
    assert grey.sum() > 50 and np.array_equal(host.albedo[grey][:, 0], host.albedo[grey][:, 2])
    if exact(backend):
        assert np.array_equal(dev.albedo, host.albedo)
    else:
        same = dev.prim == host.prim
        np.testing.assert_allclose(dev.albedo[same], host.albedo[same], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", DRJIT)
def test14_area_lights_recording_their_rays_give_the_same_image(backend, at_parity):
    """A benchmark's recording runs the samples one after the other: the same image, and the recorded shadow rays
    are the ones the pass counts (gallery: the alpha walk adds closest-hit queries, not shadow rays)."""
    from suite.core.device import render_gbuffer
    from suite.core.device import shading as device_shading

    scene = load("gallery")
    tracer = make(backend, scene)
    dg = render_gbuffer(scene, tracer, 0.0, (48, 27))
    area = host_shading.AreaLights(scene, 0.0)
    plain = device_shading.area_light_radiance(dg, area, tracer, 4, seed=3).to_host()
    before = tracer.counters["rays_occluded"]
    rays = []
    recorded = device_shading.area_light_radiance(dg, area, tracer, 4, seed=3, record=rays).to_host()
    assert plain.max() > 0
    if backend == "mitsuba-llvm":
        assert np.array_equal(recorded, plain)
    else:  # a kernel per sample instead of one loop: the compiler may contract other multiply-adds
        at_parity(recorded, plain, share=1.0, rtol=1e-5, atol=1e-7)
    assert len(rays) == 4 and {kind for kind, _ in rays} == {"o"}
    widths = sum(tracer.device.dr.width(ray.d) for _, ray in rays)
    assert widths == tracer.counters["rays_occluded"] - before > 0


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("share", [0.0, 0.003, 0.3, 1.0])
def test15_where_any_gives_the_function_in_its_lanes_and_the_fallback_elsewhere(backend, share):
    """``where_any(mask, fn, *otherwise)`` equals ``select(mask, fn(mask), otherwise)`` lane for lane, whatever share
    of the lanes (none, a few scattered ones, many, all) the mask holds; the function reads the mask it is given."""
    scene = load("cornell")
    dev = make(backend, scene).device
    dr = dev.dr
    rng = np.random.default_rng(11)
    n = 1000
    mask_np = rng.random(n) < share
    x_np = rng.random(n).astype(np.float32)
    mask, x = dev.to_device(mask_np, dev.Bool), dev.to_device(x_np, dev.Float)

    def fn(m):
        return dr.select(m, x * 2.0 + 1.0, -5.0), dev.UInt32(m)

    y, count = dev.where_any(mask, fn, dr.full(dev.Float, 7.0, n), dr.zeros(dev.UInt32, n))
    dev.eval(y, count)
    assert np.array_equal(dev.to_host(y, np.float32), np.where(mask_np, x_np * np.float32(2) + np.float32(1), 7))
    assert np.array_equal(dev.to_host(count, np.int64), mask_np.astype(np.int64))


@pytest.mark.parametrize("backend", DRJIT)
def test16_vectors_interleaved_in_their_kernel_come_back_as_the_same_counted_rows(backend):
    """``interleaved`` (written by the kernel that computes the vector) and ``rows_to_host`` give the rows and the
    byte count ``to_host`` gives for the vector itself, float32 and float64, converted as asked."""
    scene = load("living_room")
    dev = make(backend, scene).device
    dr = dev.dr
    i = dev.Float64(dev.arange(1001))
    for vec, size in ((dev.Vector3d(i * 0.5, -i, i * i + 0.25), 8), (dev.Vector3f(dev.Float(i), 2.0, dev.Float(-i)), 4)):
        want = dev.to_host(vec)
        before = dev.counters["bytes_to_host"]
        got = dev.rows_to_host(dev.interleaved(vec), 3, np.float64)
        assert got.shape == (1001, 3) and got.dtype == np.float64 and np.array_equal(got, want)
        assert dev.counters["bytes_to_host"] - before == 1001 * 3 * size
        assert dr.width(dev.interleaved(vec)) == 3003


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("width, height", [(1, 5), (7, 3), (33, 19), (1920, 2), (16384, 3)])
def test18_camera_rays_take_row_and_column_of_every_pixel_exactly(backend, width, height):
    """The pixel's row comes from a float64 product with the width's reciprocal, not an integer division: exact at
    every width (the first and last pixel of each row included, up to the largest 32-bit index), so the directions
    are the host's."""
    from suite.core.device import camera_rays
    from suite.core.device.gbuffer import row_col

    scene = load("atrium")
    dev = make(backend, scene).device
    last = 2 ** 32 - 1
    big = np.unique(np.concatenate([[0, 1, last - 1, last], np.arange(last // width - 2, last // width + 1) * width,
                                    np.arange(last // width - 2, last // width + 1) * width - 1]))
    big = big[(big >= 0) & (big <= last)].astype(np.uint32)
    r, c = row_col(dev, dev.to_device(big, dev.UInt32), width)
    assert np.array_equal(dev.to_host(r), big // width) and np.array_equal(dev.to_host(c), big % width)
    pose = scene.camera.pose_at(0.7)
    d_dev, row, col = camera_rays(dev, pose, scene.camera.fov_deg, width, height)
    idx = np.arange(width * height)
    assert np.array_equal(dev.to_host(row), idx // width) and np.array_equal(dev.to_host(col), idx % width)
    if exact(backend):
        _, d64 = host_gbuffer.camera_rays(pose, scene.camera.fov_deg, width, height, dtype=np.float64)
        assert np.array_equal(dev.to_host(d_dev), d64)


@pytest.mark.parametrize("backend", DRJIT)
def test19_the_gbuffer_keeps_the_facing_and_derives_the_emission(backend):
    """On a scene with emitters the G-buffer kernel writes one byte of facing per pixel, not twelve of emission: the
    emission is an expression of the facing and the material (fused into the kernel that reads it) and equals the host
    G-buffer's (atrium's view sees its emitters); a scene without emitters keeps neither."""
    from suite.core.device import render_gbuffer

    scene = load("atrium")
    tracer = make(backend, scene)
    dr = tracer.device.dr
    g = render_gbuffer(scene, tracer, 0.9, RES, 0.8)
    assert g.front is not None and dr.width(g.front) == RES[0] * RES[1]
    assert g.front.state == dr.VarState.Evaluated and g.emission.state != dr.VarState.Evaluated
    host = host_gbuffer.render_gbuffer(scene, tracer, 0.9, RES, 0.8, device=False)
    emission = g.to_host(names=["emission"]).emission
    assert (host.emission.max(axis=-1) > 0).any()
    if exact(backend):
        assert np.array_equal(emission, host.emission)
    np.testing.assert_allclose(emission, host.emission, atol=1e-6)
    plain = load("living_room")
    g = render_gbuffer(plain, make(backend, plain), 0.9, RES)
    assert g.front is None and g.emission is None and not g.to_host(names=["emission"]).emission.any()
