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


def fake_reference_set(scene, t_s, resolution, spp, transport, max_depth, exposure, floor):
    """The fake reference of either transport (direct: 10 % darker), a small constant stderr and a fixed floor."""
    img = fake_reference(scene, t_s, resolution, spp, max_depth) * (0.9 if transport == "direct" else 1.0)
    floor_metrics = fake_compare(img, img + 0.01, 1.0) if floor else None
    return SimpleNamespace(image=img, stderr=np.full_like(img, 0.001), floor=floor_metrics)


def fake_compare(ref, test, exposure, ref_stderr=None):
    mse = float(np.mean((np.asarray(ref, np.float64) - test) ** 2))  # float64: a decoded corrupt image may hold huge values
    ssim = 1.0 / (1.0 + mse)
    return {"ssim": ssim, "dssim": (1 - ssim) / 2, "psnr_db": -10 * np.log10(max(mse, 1e-12)),
            "nrmse": float(np.sqrt(mse)), "flip": float(np.mean(np.abs(ref - test))), "rel_mse": mse}


def fake_write(path, img, exposure=1.0):
    with open(path, "wb") as f:
        np.save(f, np.asarray(img))


def copy_fake_method(root, name: str, config=None, as_name: str | None = None):
    """A copy of the synthetic method ``name`` under ``root`` (as ``as_name``); ``config(text) -> text`` rewrites
    its config.toml. Returns the copy's folder."""
    import shutil

    folder = Path(root) / (as_name or name)
    shutil.copytree(FAKE_METHODS / name, folder)
    if config is not None:
        cfg = folder / "config.toml"
        cfg.write_text(config(cfg.read_text()))
    return folder


def install_fake_core(setattr_):
    """Points the runner's hooks at the stand-ins with ``setattr_(obj, name, value)`` (monkeypatch.setattr in a
    test; plain setattr in a Dask worker process, tests/harness/dask_fake_core.py). Returns the runner."""
    from suite.harness import runner

    for name, value in (("load_scene", lambda spec: fake_scene()), ("scene_names", lambda: ["toy"]),
                        ("make_tracer", lambda backend, scene: FakeTracer()), ("backend_names", lambda: ["fake"]),
                        ("reference_image", fake_reference), ("reference_set", fake_reference_set),
                        ("compare_images", fake_compare), ("write_exr", fake_write), ("write_png", fake_write)):
        setattr_(runner, name, value)
    return runner


@pytest.fixture
def fake_method_copy():
    """:func:`copy_fake_method` for tests (this conftest is not importable by name under --import-mode=importlib)."""
    return copy_fake_method


@pytest.fixture
def fake_core(monkeypatch):
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(FAKE_METHODS))
    return install_fake_core(monkeypatch.setattr)


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
