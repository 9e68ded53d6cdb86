"""On a Dr.Jit backend the A-SVGF's spatial variance and à-trous passes (Table 6.9 stages 6 and 7) run as the
device kernels of suite.core.device.denoise: the frames are the host filters' frames (to rounding), and the
copies the filters make are counted."""
import numpy as np
import pandas as pd
import pytest

from suite.core.scene import load
from suite.core.trace import backend_params, make
from suite.core.trace.recording import RecordingTracer
from suite.harness import registry, runner

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")


def _frames(scene, backend, on_device: bool, frames=4, resolution=(48, 27)):
    cfg = runner.make_config("quake_drt", scene=scene.name, resolution=f"{resolution[0]}x{resolution[1]}",
                             frames=frames, clock="work", reference_spp=0, quality_every=-1,
                             set_values={"gt_frames": 0, "cull_audit_points": 0})
    cls = registry.get("quake_drt").load()
    tracer = make(backend, scene)
    prepared = cls(cfg["params"]).prepare(scene, tracer)
    seq = runner.simulate(cls, scene, tracer if on_device else RecordingTracer(tracer), cfg, False,
                          keep=set(range(frames)), prepared=prepared)
    return pd.DataFrame(seq.rows), [seq.images[(0, i)] for i in range(frames)]


@pytest.mark.parametrize("backend", DRJIT)
def test01_device_filters_give_the_host_filters_frames(backend):
    scene = load("gallery")
    host, host_images = _frames(scene, backend, False)
    dev, dev_images = _frames(scene, backend, True)
    assert (host["info_host_device_bytes"] == 0).all()
    w, h = 48, 27
    # per frame at least the colour and variance up and the filtered colour down
    assert (dev["info_host_device_bytes"] >= w * h * (12 + 4 + 12)).all()
    assert list(host["info_hist_len_max"]) == list(dev["info_hist_len_max"])
    for a, b in zip(host_images, dev_images):
        assert np.isfinite(b).all()
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)
