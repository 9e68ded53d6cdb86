import os

import pytest

# Keep caches of a test session away from the user's cache.
os.environ.setdefault("SPLITBENCH_CACHE", os.path.join(os.path.dirname(__file__), "..", "build", "test-cache"))

# Scene files the project does not ship (docs/scenes.md, "Scene search path"): the shared scenes folder beside the
# checkout, when it exists, is added to the search path, so that dabrovic_sponza is available to the tests.
_SHARED_SCENES = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "scenes"))
if os.path.isdir(_SHARED_SCENES):
    _path = [p for p in os.environ.get("SPLITBENCH_SCENE_PATH", "").split(os.pathsep) if p]
    if _SHARED_SCENES not in _path:
        os.environ["SPLITBENCH_SCENE_PATH"] = os.pathsep.join(_path + [_SHARED_SCENES])


@pytest.fixture(autouse=True)
def _quiet_progress(monkeypatch):
    monkeypatch.setenv("SPLITBENCH_PROGRESS", "0")


_DRJIT_DEVICES: dict = {}


@pytest.fixture
def drjit_device():
    """``drjit_device(backend)``: the Dr.Jit device of a ``backend`` tracer (on the small cornell scene, made once per
    session), for tests of device kernels that take their data as arrays."""
    def get(backend):
        if backend not in _DRJIT_DEVICES:
            from suite.core.scene import load
            from suite.core.trace import make

            _DRJIT_DEVICES[backend] = make(backend, load("cornell")).device
        return _DRJIT_DEVICES[backend]

    return get


@pytest.fixture
def at_parity():
    """``at_parity(got, want, share=0.995, rtol=1e-4, atol=1e-5)``: asserts that at least ``share`` of the elements of
    ``got`` are close to ``want``. How a device kernel on cuda_ad_rgb (other rounding of division and square root,
    fused multiply-adds) is compared with the host path, where its rays can hit other triangles at the backends'
    parity (tests/core/test_device.py); on llvm_ad_rgb the tests compare exactly or to rounding."""
    import numpy as np

    def check(got, want, share=0.995, rtol=1e-4, atol=1e-5):
        got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
        assert got.shape == want.shape
        close = np.isclose(got, want, rtol=rtol, atol=atol)
        assert close.mean() >= share, f"{close.mean():.4f} of the values agree (want >= {share})"

    return check
