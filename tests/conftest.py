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
