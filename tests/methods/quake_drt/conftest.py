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


def _direct_setup(backend="embree", extra_lights=40, glossy_every=7):
    """(scene, tracer, shading points, lights, light table, rows) of the direct stage on the two-room scene: the
    jittered primary hits of a 32x24 frame, every ``glossy_every``-th point glossy (0: none)."""
    from methods.quake_drt import culling, direct, lights as lights_mod, primary
    from methods.quake_drt.rng import pixel_seeds

    scene, vis = testscenes.two_rooms(door_open=False, lights_in_b=2, extra_lights=extra_lights)
    scene = testscenes.with_visibility(scene, vis)
    tracer = make(backend, scene)
    w, h = 32, 24
    seeds = pixel_seeds(11, w, h).reshape(-1)
    o, d = primary.camera_rays(scene, 0.0, w, h, seeds, True)
    hits = tracer.intersect(o, d.astype(np.float32))
    s = primary.surface_from_hits(scene, 0.0, o, d, hits.prim, hits.u, hits.v, hits.t)
    idx = np.nonzero(s.valid)[0]
    lambert = np.ones(len(idx), bool)
    if glossy_every:
        lambert[::glossy_every] = False  # glossy points: no cos_x test (and the host path on a Dr.Jit backend)
    pts = direct.ShadingPoints(pixel=idx, throughput=np.ones((len(idx), 3)), p=s.p[idx], ng=s.ng_view[idx],
                               ns=s.ns_view[idx], wi=-s.d[idx], albedo=s.albedo[idx], material=s.material[idx],
                               prim=s.prim[idx], seed=seeds[idx], lambert=lambert)
    lights = lights_mod.build_lights(scene, 0.0)
    table = culling.build_table(vis, "scene", lights, scene.num_faces, 0.0254, True, scene.bounds())
    rows = culling.point_rows(table, vis, pts.prim, pts.p, pts.ng, "triangle", 0.0254, True)
    return scene, tracer, pts, lights, table, rows


@pytest.fixture
def direct_setup():
    return _direct_setup


@pytest.fixture
def calls_of(monkeypatch):
    """``calls_of(module, name)``: a list that grows by one at each call of ``module.name`` (so that a test of a device
    kernel knows the kernel ran, and does not compare the host path with itself)."""
    def watch(module, name):
        calls, original = [], getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, **k: calls.append(1) or original(*a, **k))
        return calls

    return watch
