"""RAIL's client on the Dr.Jit device path (methods/rail/device.py): the same frames as the host path, computed on
the run's Mitsuba variant (llvm_ad_rgb here, cuda_ad_rgb where a GPU is usable), with the frame kept on the device
from the G-buffer to the composed image."""
import copy

import numpy as np
import pandas as pd
import pytest

from suite.core.scene import load
from suite.core.scene.model import CameraPath
from suite.core.trace import backend_params, make
from suite.core.trace.recording import RecordingTracer
from suite.harness import registry, runner

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")
SMALL = {"target_points": 400, "dart_sources": 512, "darts_per_source": 16, "vpls": 16, "ao_rays": 8,
         "client_ao_rays": 2, "area_samples": 1}
SPARSE = {"target_points": 25, "range_min": 0.3, "range_max": 0.6}       # most pixels reach no record: F_a·AO
COUNTS = ["info_fallback_pixels", "info_zero_weight_pixels", "info_no_ambient_pixels", "info_irradiance_pixels",
          "info_records_visited_mean", "rays"]
_SCENES: dict = {}
_PREPARED: dict = {}


def _scene(name):
    """The scene; ``arena`` at one frame per second, so that frames 2 and 3 see its moving platform."""
    if name not in _SCENES:
        scene = load(name)
        if name == "arena":
            scene = copy.copy(scene)
            cam = scene.camera
            scene.camera = CameraPath(cam.keys, cam.fov_deg, cam.resolution, 1.0)
        _SCENES[name] = scene
    return _SCENES[name]


def _simulate(scene_name, backend, on_device: bool, frames=3, resolution=(48, 27), **params):
    """Frames of one client over lan-home; the host path runs on the same Mitsuba tracer with its device hidden."""
    scene = _scene(scene_name)
    params = {**SMALL, **params}
    cfg = runner.make_config("rail", scene=scene_name, resolution=f"{resolution[0]}x{resolution[1]}", frames=frames,
                             net="lan-home", clock="work", reference_spp=0, quality_every=-1, set_values=params)
    cls = registry.get("rail").load()
    tracer = make(backend, scene)
    key = (scene_name, backend, tuple(sorted(params.items())))
    if key not in _PREPARED:
        _PREPARED[key] = cls(cfg["params"]).prepare(scene, tracer)
    dev = tracer.device
    copied0 = dev.counters["bytes_to_host"]
    seq = runner.simulate(cls, scene, tracer if on_device else RecordingTracer(tracer), cfg, False,
                          keep=set(range(frames)), prepared=_PREPARED[key])
    frames_df = pd.DataFrame(seq.rows)
    images = [seq.images[(0, i)] for i in range(frames)]
    return frames_df, images, dev.counters["bytes_to_host"] - copied0


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name, params, exact", [
    ("living_room", {}, True),                                  # IDW at every pixel: the host's bits
    ("living_room", {"idw_mu": 2.0}, False),                    # eq. 1's power: the device's pow rounds apart
    ("living_room", {"irradiance_scale": 2}, False),            # §3.3's joint bilateral upsampling
    ("living_room", SPARSE, True),                              # the ambient fallback, scattered back
    ("arena", {}, True),                                        # a moving platform: dynamic pixels fall back
], ids=["idw", "mu2", "upsampled", "fallback", "dynamic"])
def test01_the_device_frames_are_the_host_frames(backend, scene_name, params, exact, at_parity):
    frames = 4 if scene_name == "arena" else 3
    host, host_images, _ = _simulate(scene_name, backend, False, frames, **params)
    dev, dev_images, _ = _simulate(scene_name, backend, True, frames, **params)
    assert host["info_cache_ready"].any()
    if scene_name == "arena" or params is SPARSE:
        assert (dev["info_fallback_pixels"] > 0).any()
    if backend != "mitsuba-llvm":  # cuda: the device G-buffer's hits at the backends' parity
        at_parity(dev[COUNTS].to_numpy(), host[COUNTS].to_numpy(), share=1.0, rtol=0.01, atol=2)
        for a, b in zip(host_images, dev_images):
            assert np.isfinite(b).all()
            at_parity(b, a)
        return
    pd.testing.assert_frame_equal(host[COUNTS], dev[COUNTS], check_exact=exact, rtol=1e-9)
    for a, b in zip(host_images, dev_images):
        assert np.isfinite(b).all()
        if exact:
            assert np.array_equal(a, b)
        else:
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5)
    assert (host["info_host_device_bytes"] == 0).all()
    ready = dev[dev["info_cache_ready"]]
    assert (ready["info_host_device_bytes"] > 0).all()          # the records' irradiance, every frame


@pytest.mark.parametrize("backend", DRJIT)
def test02_the_frame_stays_on_the_device_until_the_image_is_read_back(backend, monkeypatch):
    from methods.rail.method import Rail

    w, h, frames = 40, 24, 3
    copied = []                  # bytes each client frame copied to the host (the server shades on the device too)
    client_frame = Rail.client_frame

    def counted(self, ctx, update):
        c = ctx.tracer.device.counters
        before = c["bytes_to_host"]
        out = client_frame(self, ctx, update)
        copied.append(c["bytes_to_host"] - before)
        return out

    monkeypatch.setattr(Rail, "client_frame", counted)
    df, _, _ = _simulate("living_room", backend, True, frames=frames, resolution=(w, h))
    assert (df["info_fallback_pixels"] == 0).all() and df["info_cache_ready"].any()
    assert copied == [w * h * 3 * 4] * frames                   # one float32 RGB image per frame, nothing else


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("mu", [1.0, 2.0])
def test03_device_idw_equals_the_host_loop_inside_outside_and_on_the_edges_of_the_grid(backend, mu):
    from types import SimpleNamespace

    from methods.rail import device as rdev
    from methods.rail.grid import GridGeometry, MultiRefGrid, idw

    rng = np.random.default_rng(3)
    geometry = GridGeometry.fit(np.zeros(3), np.full(3, 4.0), 8)
    q = rng.uniform(0.0, 4.0, (300, 3))
    qn = rng.normal(size=(300, 3))
    qn /= np.linalg.norm(qn, axis=1, keepdims=True)
    r = rng.uniform(0.3, 1.2, 300)
    E = rng.random((300, 3))
    grid = MultiRefGrid.build(geometry, q, r)
    # points inside, outside on every side, exactly on cell and grid faces, and one pixel inactive
    p = np.concatenate([rng.uniform(-1.0, 5.0, (2000, 3)), [[0, 0, 0], [4, 4, 4], [4, 2, 2], [2, 2, 4], [0.5, 1, 2]]])
    n = rng.normal(size=p.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    active = np.ones(len(p), bool)
    active[-1] = False
    phi_h, w_h, v_h = idw(grid, q, qn, r, E, p[active], n[active], mu)
    dev = make(backend, load("cornell")).device
    cg = SimpleNamespace(geometry=geometry, grid=grid, position=q, normal=qn, range_m=r)
    dgrid = rdev.DeviceGrid(dev, cg)
    phi, wsum, visited = rdev.idw(dgrid, dgrid.irradiance(E), dev.to_device(p, dev.Point3d),
                                  dev.to_device(n, dev.Vector3d), dev.to_device(active, dev.Bool), mu)
    phi_d = dev.to_host(dev.Vector3f(phi), np.float32)
    w_d, v_d = dev.to_host(wsum), dev.to_host(visited)
    assert v_d[-1] == 0 and w_d[-1] == 0 and (phi_d[-1] == 0).all()
    assert np.array_equal(v_d[:-1], v_h)
    assert (w_h == 0).any() and (v_h == 0).any()                 # points outside G and without a record in range
    exact = mu == 1.0 and backend == "mitsuba-llvm"
    np.testing.assert_allclose(w_d[:-1], w_h, rtol=0 if exact else 1e-12, atol=0)
    np.testing.assert_allclose(phi_d[:-1], phi_h, rtol=0 if exact else 1e-6, atol=0)


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("scene_name", ["living_room", "gallery"])      # gallery: shadow rays through its grate
def test04_device_point_cloud_shading_gives_the_host_pass(backend, scene_name, at_parity):
    from methods.rail.lighting import shade_points, trace_light_paths

    scene = _scene(scene_name)
    tracer = make(backend, scene)
    prep = registry.get("rail").load()({**registry.get("rail").params(), **SMALL}).prepare(scene, tracer)
    pts = prep["points"]
    vpls = trace_light_paths(scene, tracer, 0.0, prep["light_positions"], prep["light_intensities"], 16, 3,
                             np.random.default_rng(0), scene.area_light_triangles(0.0))
    host_E, host_c = shade_points(pts.position, pts.normal, vpls, RecordingTracer(tracer), 0.5 * pts.spacing_m,
                                  batch=3 * len(pts))             # batches of 3 VPLs: E takes their sums in turn
    rays0 = tracer.counters["rays_occluded"]
    dev_E, dev_c = shade_points(pts.position, pts.normal, vpls, tracer, 0.5 * pts.spacing_m, batch=3 * len(pts))
    assert tracer.counters["rays_occluded"] - rays0 == dev_c["rays"] > 0
    assert (host_E > 0).any()
    if backend == "mitsuba-llvm":
        assert dev_c == host_c
        assert np.array_equal(dev_E, host_E)                        # the same rays, the same sums in the same order
    else:                                                           # cuda: visibility at the backends' parity
        assert abs(dev_c["rays"] - host_c["rays"]) <= 0.005 * host_c["rays"]
        at_parity(dev_E, host_E, share=0.99, rtol=1e-6, atol=1e-12)
