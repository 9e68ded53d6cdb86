"""The server's compiled passes (methods/layered_pvs/kernels.py) give the bits of their numpy references: depth
peeling restricted to a PVS (``keep_mask`` against the ``keep`` callable of ``peel_reference``) and the path
tracer's wavefront (``path_trace`` against ``path_trace_reference``, same seed, same random numbers)."""
import numpy as np
import pytest

from methods.layered_pvs import server
from suite.core.gbuffer import camera_rays
from suite.core.scene import load
from suite.core.trace import make


@pytest.mark.parametrize("name", ["gallery", "atrium"])
def test01_peeling_and_path_tracing_equal_their_references(name):
    scene = load(name)
    tracer = make("embree", scene)
    w, h, t_s = 48, 27, 0.5
    o64, d64 = camera_rays(scene.camera.pose_at(t_s), scene.camera.fov_deg, w, h, dtype=np.float64)
    in_pvs = np.random.default_rng(1).random(scene.num_faces) < 0.7  # a PVS that leaves faces out
    args = (tracer.intersect, o64.astype(np.float32), d64.astype(np.float32), 3)
    fast = server.peel(*args, keep_mask=in_pvs, shape=(h, w))
    ref = server.peel_reference(*args, keep=lambda prim: in_pvs[prim], shape=(h, w))
    for field in ("prim", "t", "u", "v"):
        if hasattr(ref, field):
            assert np.array_equal(getattr(fast, field), getattr(ref, field), equal_nan=True), field
    assert (fast.prim[1] >= 0).any() and (fast.prim[0] < 0).any()  # a second layer; holes where the PVS ends
    frag = server.fragments(scene, fast, o64, d64, t_s)
    out = server.path_trace(scene, tracer, frag, t_s, 2, 4, 3, np.random.default_rng(7))
    expected = server.path_trace_reference(scene, tracer, frag, t_s, 2, 4, 3, np.random.default_rng(7))
    for a, b in zip(out, expected):
        assert np.array_equal(a, b)
    assert np.isfinite(out[0]).all() and out[0].max() > 0.0
