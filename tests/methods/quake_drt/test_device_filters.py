"""On a Dr.Jit backend the A-SVGF's stages 3-7 (Table 6.9: gradient image, gradient à-trous and anti-lag, temporal
accumulation, variance, à-trous) and TAA run as device kernels (methods/quake_drt/device.py,
suite.core.device.denoise) with their histories on the device: the frames are the host stages' frames (to
rounding), a light switched off is picked up by the device's gradients as by the host's, and the copies are
counted."""
import numpy as np
import pandas as pd
import pytest

from suite.core.scene import load
from suite.core.trace import backend_params, make
from suite.core.trace.recording import RecordingTracer
from suite.harness import registry, runner

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")


def _frames(scene, backend, on_device: bool, frames=4, resolution=(48, 27), **params):
    cfg = runner.make_config("quake_drt", scene=scene.name, resolution=f"{resolution[0]}x{resolution[1]}",
                             frames=frames, clock="work", reference_spp=0, quality_every=-1,
                             set_values={"gt_frames": 0, "cull_audit_points": 0, **params})
    cls = registry.get("quake_drt").load()
    tracer = make(backend, scene)
    prepared = cls(cfg["params"]).prepare(scene, tracer)
    seq = runner.simulate(cls, scene, tracer if on_device else RecordingTracer(tracer), cfg, False,
                          keep=set(range(frames)), prepared=prepared)
    return pd.DataFrame(seq.rows), [seq.images[(0, i)] for i in range(frames)]


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("params", [{}, {"asvgf_history_cap": 2}], ids=["defaults", "history_cap_2"])
def test01_device_filters_give_the_host_filters_frames(backend, params, at_parity):
    scene = load("gallery")
    host, host_images = _frames(scene, backend, False, **params)
    dev, dev_images = _frames(scene, backend, True, **params)
    assert (host["info_host_device_bytes"] == 0).all()
    w, h = 48, 27
    # per frame at least the colour and variance up and the filtered colour down
    assert (dev["info_host_device_bytes"] >= w * h * (12 + 4 + 12)).all()
    np.testing.assert_allclose(dev["info_hist_len_max"], host["info_hist_len_max"], rtol=1e-5)
    assert host["info_hist_len_max"].max() == min(4, params.get("asvgf_history_cap", 256))
    for a, b in zip(host_images, dev_images):
        assert np.isfinite(b).all()
        if backend == "mitsuba-llvm":
            np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)
        else:  # cuda: fused multiply-adds in the filters' float sums
            at_parity(b, a, share=0.999)


@pytest.mark.parametrize("backend", DRJIT)
def test02_device_taa_gives_the_host_taa_with_its_history_on_the_device(drjit_device, backend):
    from methods.quake_drt.device import DeviceTAA
    from methods.quake_drt.taa import TAA

    rng = np.random.default_rng(5)
    h, w = 23, 31
    host, dev = TAA(0.1, 1.0), DeviceTAA(drjit_device(backend), 0.1, 1.0, 3.0)
    for frame in range(4):
        c = rng.gamma(1.0, 1.0, (h, w, 3)).astype(np.float32)
        c[4, 7] = 50.0                                          # a firefly
        motion = rng.normal(0.0, 3.0, (h, w, 2)).astype(np.float32)
        motion[:3] = 40.0                                       # history outside the image
        a, b = host(c, motion), dev(c, motion)
        assert b.dtype == np.float32 and b.shape == a.shape
        # the history's float32 sum: within 1e-6 here; fused multiply-adds on cuda round it otherwise
        tol = (1e-6, 1e-7) if backend == "mitsuba-llvm" else (1e-5, 1e-6)
        np.testing.assert_allclose(b, a, rtol=tol[0], atol=tol[1])
    assert not np.allclose(a, c)                                # the history was blended in


@pytest.mark.parametrize("backend", DRJIT)
def test03_a_light_switched_off_is_picked_up_by_the_device_gradients_as_by_the_hosts(renderer, two_rooms, backend,
                                                                                    at_parity):
    from methods.quake_drt.testscenes import switch_off

    t_off = 10
    scene, vis = two_rooms(door_open=False, lights_in_b=1, camera="a", resolution=(64, 40))
    runs = {}
    for on_device in (False, True):
        r = renderer(scene, vis, (64, 40), backend=backend, num_random_dl=1, denoiser=True, taa=True)
        if not on_device:
            r.tracer = RecordingTracer(r.tracer)                 # hides the device: the host stages
        switch_off(r.scene, "a_ceiling", t_off)
        runs[on_device] = r.run(t_off + 3)
    for (a, _, _, rec_a), (b, _, _, rec_b) in zip(runs[False], runs[True]):
        if backend == "mitsuba-llvm":
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5)
        else:  # cuda: fused multiply-adds in the filters' float sums
            at_parity(b, a, share=0.999, rtol=1e-3, atol=1e-4)
        assert rec_b["antilag_mean"] == pytest.approx(rec_a["antilag_mean"], rel=1e-3, abs=1e-6)
    assert runs[True][t_off][3]["antilag_mean"] > 0.2 and runs[True][t_off - 1][3]["antilag_mean"] < 1e-5
    assert runs[True][t_off][3]["host_device_bytes"] > 0 and runs[False][t_off][3]["host_device_bytes"] == 0
