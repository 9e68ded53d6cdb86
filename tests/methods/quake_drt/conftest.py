"""Shared helpers for the quake_drt tests: small scenes with a known PVS and a frame runner."""
import numpy as np
import pytest

from methods.quake_drt import pipeline as P
from methods.quake_drt import testscenes
from suite.core.trace import make


class Renderer:
    """A scene, its tracer and a pipeline with given settings, driven frame by frame without the harness."""

    def __init__(self, scene, vis=None, resolution=(48, 32), backend="embree", **settings):
        self.scene = testscenes.with_visibility(scene, vis) if vis is not None else scene
        self.tracer = make(backend, self.scene)
        base = dict(antialiasing=False, denoiser=False, taa=False)
        base.update(settings)
        self.settings = P.Settings.from_params(base)
        self.prep = P.prepare(self.scene, self.tracer, self.settings, 0.0)
        self.pipeline = P.Pipeline(self.settings, self.prep, *resolution)
        self.resolution = resolution

    def seeds(self, frame_seed):
        from methods.quake_drt.rng import pixel_seeds

        return pixel_seeds(frame_seed, *self.resolution).reshape(-1)

    def raw(self, frame_seed=1, t_s=0.0):
        """(image, RawFrame) of one undenoised frame."""
        raw = self.pipeline.raw_frame(self.scene, self.tracer, t_s, None, self.seeds(frame_seed))
        return raw.compose(None, self.settings.illumination), raw

    def raw_stack(self, n, first_seed=100):
        return np.stack([self.raw(first_seed + i)[0] for i in range(n)]).astype(np.float64)

    def run(self, frames):
        """Full frames with scene time advancing at 30 per second (the camera path of the test scenes holds still):
        (image, denoised, RawFrame, record) per frame."""
        out, prev = [], None
        for i in range(frames):
            t = i / 30.0
            out.append(self.pipeline.run_frame(self.scene, self.tracer, t, prev, 1000 + i))
            prev = t
        return out

    def frames(self, n, first_seed=0, t_s=0.0, each=None):
        """Runs ``n`` full frames of a paused camera; returns the list of displayed images."""
        out = []
        prev = None
        for i in range(n):
            img, den, raw, rec = self.pipeline.run_frame(self.scene, self.tracer, t_s, prev, first_seed + i)
            prev = t_s
            if each is not None:
                each(i, img, den, raw, rec)
            out.append(img)
        return out


@pytest.fixture
def renderer():
    return Renderer


@pytest.fixture
def two_rooms():
    return testscenes.two_rooms


SMALL_MAP = "oa:aggressor"


@pytest.fixture
def small_map():
    """The smallest OpenArena map's name; the test is skipped when the OpenArena data is not installed."""
    from suite.core.scene import list_scenes

    if list_scenes().get(SMALL_MAP, "unavailable").startswith("unavailable"):
        pytest.skip(f"{SMALL_MAP} needs the OpenArena data")
    return SMALL_MAP
