"""Harness tests run on a synthetic scene, tracer, reference and metrics, so they need no renderer.

``fake_core`` points the runner's hooks at numpy stand-ins and adds tests/harness/fake_methods to the method
search path (methods `synthetic_sync` and `synthetic_async`).
"""
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

FAKE_METHODS = Path(__file__).parent / "fake_methods"


class FakeTracer:
    def __init__(self):
        self.counters = {"rays_intersect": 0, "rays_occluded": 0}
        self.updates = []

    def trace(self, n):
        self.counters["rays_intersect"] += int(n)

    def update(self, t_s):
        self.updates.append(t_s)

    def describe(self):
        return {"variant": "fake"}


def fake_scene():
    from suite.core.scene.model import CameraKey, CameraPath

    # The camera moves along x by 1 unit per second over 4 s, so a pose says when it was sampled.
    camera = CameraPath([CameraKey(0.0, [0.0, 0.0, 5.0], [0.0, 0.0, 0.0]), CameraKey(4.0, [4.0, 0.0, 5.0], [4.0, 0.0, 0.0])],
                        fov_deg=45.0, resolution=(16, 8), fps=30.0)
    return SimpleNamespace(camera=camera, is_dynamic=False)


def fake_reference(scene, t_s, resolution, spp, max_depth):
    w, h = resolution
    x = np.linspace(0.0, 1.0, w, dtype=np.float32)
    return np.broadcast_to((x * (1.0 + t_s))[None, :, None], (h, w, 3)).astype(np.float32).copy()


def fake_compare(ref, test, exposure):
    mse = float(np.mean((ref - test) ** 2))
    ssim = 1.0 / (1.0 + mse)
    return {"ssim": ssim, "dssim": (1 - ssim) / 2, "psnr_db": -10 * np.log10(max(mse, 1e-12)),
            "nrmse": float(np.sqrt(mse)), "flip": float(np.mean(np.abs(ref - test)))}


def fake_write(path, img, exposure=1.0):
    with open(path, "wb") as f:
        np.save(f, np.asarray(img))


@pytest.fixture
def fake_core(monkeypatch):
    from suite.harness import runner

    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(FAKE_METHODS))
    monkeypatch.setattr(runner, "load_scene", lambda spec: fake_scene())
    monkeypatch.setattr(runner, "scene_names", lambda: ["toy"])
    monkeypatch.setattr(runner, "make_tracer", lambda backend, scene: FakeTracer())
    monkeypatch.setattr(runner, "backend_names", lambda: ["fake"])
    monkeypatch.setattr(runner, "reference_image", fake_reference)
    monkeypatch.setattr(runner, "compare_images", fake_compare)
    monkeypatch.setattr(runner, "write_exr", fake_write)
    monkeypatch.setattr(runner, "write_png", fake_write)
    return runner


@pytest.fixture
def fake_config(fake_core):
    def make(method="synthetic_sync", **kw):
        kw.setdefault("scene", "toy")
        kw.setdefault("backend", "fake")
        kw.setdefault("resolution", "16x8")
        kw.setdefault("frames", 3)
        kw.setdefault("reference_spp", 4)
        return fake_core.make_config(method, **kw)
    return make
