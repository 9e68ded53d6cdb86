"""On a Dr.Jit backend the primary stage's jittered shading samples (seed 001 §4.1, §6.3; Table 2.1 anti-aliasing) are
one device kernel (methods/quake_drt/device_primary.py): the pixel's jitter, the float64 ray, its closest hit with the
alpha walk, and the hit's surface. Every field of the samples and the tracer's query counters are the host pass's
(camera_rays, intersect, surface_from_hits), bit for bit on llvm_ad_rgb (at parity on cuda_ad_rgb): on a textured
scene with an alpha-tested grate, on moving geometry at two times, and where rays miss everything. Depth of field
and transparent overlays keep the host path; the pipeline records what the stage copied to the host."""
import numpy as np
import pytest

from methods.quake_drt import device_primary, primary
from methods.quake_drt.rng import pixel_seeds
from suite.core.trace import backend_params, make
from suite.core.trace.recording import RecordingTracer

BACKENDS = backend_params("mitsuba-llvm", "mitsuba-cuda")
FIELDS = ("valid", "prim", "u", "v", "p", "ng", "ns", "ng_view", "ns_view", "albedo", "emission", "material", "o",
          "d", "t", "overlay_rgb", "overlay_t")


def _host_samples(scene, tracer, t_s, w, h, seeds):
    tracer.update(t_s)
    o, d = primary.camera_rays(scene, t_s, w, h, seeds, True)
    hits = tracer.intersect(o, d.astype(np.float32))
    return primary.surface_from_hits(scene, t_s, o, d, hits.prim, hits.u, hits.v, hits.t)


def _counted(tracer, fn):
    before = dict(tracer.counters)
    out = fn()
    return out, {c: v - before.get(c, 0) for c, v in tracer.counters.items()}


def _agree(backend, got, want, at_parity):
    for f in FIELDS:
        a, b = getattr(got, f), getattr(want, f)
        assert a.dtype == b.dtype and a.shape == b.shape, f
        if backend == "mitsuba-llvm":
            assert np.array_equal(a, b), f
        elif a.dtype.kind == "f":
            at_parity(np.where(np.isfinite(a), a, 0.0), np.where(np.isfinite(b), b, 0.0))
        else:
            assert (a == b).mean() >= 0.995, f


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name,t_s", [("gallery", 0.0), ("arena", 0.0), ("arena", 1.5), ("cornell", 0.5)])
def test01_the_device_samples_are_the_host_passes_fields_and_queries(backend, name, t_s, at_parity):
    """gallery: a texture and an alpha-tested grate (the walk's extra queries counted alike); arena: its platform
    moves, so the device reads the vertices at t_s."""
    from suite.harness import runner

    scene = runner.load_scene(name)
    tracer = make(backend, scene)
    w, h = 64, 40
    seeds = pixel_seeds(7, w, h).reshape(-1)
    got, c_dev = _counted(tracer, lambda: device_primary.shading_samples(scene, tracer, t_s, w, h, seeds))
    want, c_host = _counted(tracer, lambda: _host_samples(scene, tracer, t_s, w, h, seeds))
    assert got.valid.any() and (got.t[got.valid] > 0).all()
    _agree(backend, got, want, at_parity)
    if backend == "mitsuba-llvm":
        assert c_dev == c_host
    if name == "gallery":
        assert c_dev["rays_intersect"] > w * h  # the alpha walk re-traced rays through transparent texels


@pytest.mark.parametrize("backend", BACKENDS)
def test02_rays_that_miss_everything_get_the_background_values(backend, at_parity):
    """A camera looking away from the scene: every sample invalid, prim and material -1, t infinite, zero vectors."""
    import dataclasses

    from suite.core.scene.model import CameraKey
    from suite.harness import runner

    scene = runner.load_scene("cornell")
    key = scene.camera.keys[0]
    back = key.position - key.target  # far behind the camera, looking further away from the box
    camera = dataclasses.replace(scene.camera, keys=[CameraKey(0.0, key.position + 100.0 * back,
                                                               key.position + 101.0 * back, key.up)])
    scene = dataclasses.replace(scene, camera=camera)
    tracer = make(backend, scene)
    seeds = pixel_seeds(3, 16, 9).reshape(-1)
    got = device_primary.shading_samples(scene, tracer, 0.0, 16, 9, seeds)
    assert not got.valid.any() and (got.prim == -1).all() and (got.material == -1).all()
    assert np.isinf(got.t).all() and not got.p.any() and not got.ns_view.any() and not got.albedo.any()
    _agree(backend, got, _host_samples(scene, tracer, 0.0, 16, 9, seeds), at_parity)


@pytest.fixture
def device_calls(calls_of):
    """The device sample kernels run."""
    return calls_of(device_primary, "shading_samples")


@pytest.mark.parametrize("backend", BACKENDS)
def test03_the_primary_stage_takes_the_kernel_for_jittered_pinhole_rays_only(backend, device_calls,
                                                                            at_parity):
    """The stage's samples and G-buffer on the Dr.Jit tracer equal the host path's (the device hidden); with depth of
    field the lens sample stays on the host, and so do the samples of a tracer without a device."""
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    tracer = make(backend, scene)
    seeds = pixel_seeds(11, 48, 27).reshape(-1)
    g_d, s_d = primary.primary_stage(scene, tracer, 0.5, 0.25, (48, 27), seeds, True)
    assert len(device_calls) == 1
    g_h, s_h = primary.primary_stage(scene, RecordingTracer(tracer), 0.5, 0.25, (48, 27), seeds, True)
    assert len(device_calls) == 1
    _agree(backend, s_d, s_h, at_parity)
    for f in ("position", "normal", "albedo", "depth", "prim", "motion"):
        if backend == "mitsuba-llvm":
            assert np.array_equal(getattr(g_d, f), getattr(g_h, f)), f
    primary.primary_stage(scene, tracer, 0.5, 0.25, (48, 27), seeds, True, aperture_m=0.05, focal_m=3.0)
    primary.primary_stage(scene, tracer, 0.5, 0.25, (48, 27), seeds, False)
    assert len(device_calls) == 1


@pytest.mark.parametrize("backend", BACKENDS)
def test04_a_frame_records_the_bytes_its_primary_stage_copied(backend, renderer, two_rooms):
    """On the Dr.Jit tracer the G-buffer and the samples come back to the host (at least the samples' float64
    position, four normals and direction per pixel); the host path copies nothing."""
    scene, vis = two_rooms(door_open=True, lights_in_b=1)
    r = renderer(scene, vis, (32, 24), backend=backend, antialiasing=True)
    _, raw_d = r.raw(2)
    r.tracer = RecordingTracer(r.tracer)
    _, raw_h = r.raw(2)
    assert raw_h.info["primary_device_bytes"] == 0
    assert raw_d.info["primary_device_bytes"] >= 32 * 24 * 6 * 24
