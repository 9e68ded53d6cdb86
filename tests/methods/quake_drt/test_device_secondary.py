"""The secondary stage's specular chains (seed 001 §4.1, §6.5) as a device wavefront
(methods/quake_drt/device_secondary.py): on llvm_ad_rgb, where the tests run it (frames take it on cuda_ad_rgb only),
its shading points (every field, in order), the emission the chains collect, the denoiser guides, the rays per depth
and the tracer's query counts are the host stage's bit for bit (at parity on cuda_ad_rgb): with all branches and with
one random branch, in one part and in two, with gold mirrors seen from either side, and when the chains end at
depth 1. Glossy cones and overlays keep the
host path."""
import numpy as np
import pytest

from methods.quake_drt import device_secondary, primary, secondary
from methods.quake_drt.direct import _FIELDS
from methods.quake_drt.rng import pixel_seeds
from suite.core.trace import backend_params, make
from suite.core.trace.recording import RecordingTracer

BACKENDS = backend_params("mitsuba-llvm", "mitsuba-cuda")


@pytest.fixture
def on_every_device(monkeypatch, calls_of):
    """The device chains on every Dr.Jit device (llvm too); returns the list of their calls."""
    monkeypatch.setattr(device_secondary, "DEVICES", ("llvm", "cuda"))
    return calls_of(device_secondary, "chains")


def _stage(scene, tracer, w, h, **kw):
    """(device result, host result, device counts, host counts) of the stage on one frame's samples."""
    seeds = pixel_seeds(5, w, h).reshape(-1)
    _, surf = primary.primary_stage(scene, tracer, 0.5, None, (w, h), seeds, True)
    out = []
    for tr in (tracer, RecordingTracer(tracer)):  # the recorder hides the device: the host stage
        before = dict(tracer.counters)
        res = secondary.secondary_stage(scene, tr, 0.5, surf, seeds, **kw)
        out.append((res, {c: v - before.get(c, 0) for c, v in tracer.counters.items()}))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def _agree(backend, got, want, at_parity):
    if backend == "mitsuba-llvm":
        for f in _FIELDS:
            a, b = getattr(got.points, f), getattr(want.points, f)
            assert a.dtype == b.dtype and np.array_equal(a, b), f
        for f in ("emission", "guide_pixel", "guide_p", "guide_n", "guide_depth"):
            assert np.array_equal(getattr(got, f), getattr(want, f)), f
    else:
        assert abs(len(got.points) - len(want.points)) <= 0.01 * len(want.points)
        at_parity(got.emission, want.emission)


def _gold_mirror(scene):
    """gallery with its mirror made of two-sided gold (a conductor whose Fresnel term is not 1, seen from both
    sides)."""
    import dataclasses

    mats = [dataclasses.replace(m, conductor_eta=np.array([0.143, 0.374, 1.442]),
                                conductor_k=np.array([3.983, 2.385, 1.603]), twosided=True)
            if m.kind == "mirror" else m for m in scene.materials]
    return dataclasses.replace(scene, materials=mats)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case,size,all_branches", [("gallery", (48, 27), True), ("gallery", (48, 27), False),
                                                    ("gallery", (224, 126), True), ("gold", (48, 27), True)],
                         ids=["one_part", "one_branch", "two_parts", "gold_twosided"])
def test01_the_device_chains_are_the_host_stages(backend, case, size, all_branches, on_every_device, at_parity):
    """gallery: mirrors, glass (both branches, or one picked by the chain's random number), an emitter seen in them
    and an alpha-tested grate; at 224x126 the chains come in two parts, whose points the host lists part by part;
    with a two-sided gold mirror the conductor Fresnel term weighs every reflection."""
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    if case == "gold":
        scene = _gold_mirror(scene)
    tracer = make(backend, scene)
    got, want, c_dev, c_host = _stage(scene, tracer, *size, max_depth=5, all_branches=all_branches)
    assert len(on_every_device) == 1
    assert len(want.points) > 0 and len(want.rays_per_depth) >= 3
    assert want.emission.any() or not all_branches  # the emitter seen through glass
    if size == (224, 126):
        assert want.rays_per_depth[0] >= 2 * secondary.PART_MIN_CHAINS  # so at least 2048 chains: two parts
    if case == "gold":
        assert 0.0 < want.points.throughput.min() and want.points.throughput.max() < 1.0
    _agree(backend, got, want, at_parity)
    if backend == "mitsuba-llvm":
        assert got.rays_per_depth == want.rays_per_depth and c_dev == c_host


def _mirror_back():
    """A two-sided gold mirror seen from its back (its normal faces away from the camera), reflecting a lit wall
    behind the camera; a one-sided twin beside it ends its chains there."""
    from suite.core.scene.builder import SceneBuilder
    from suite.core.scene.model import CameraKey

    b = SceneBuilder()
    gold = dict(conductor_eta=(0.143, 0.374, 1.442), conductor_k=(3.983, 2.385, 1.603))
    two = b.add_material("two_sided", albedo=(0.0, 0.0, 0.0), kind="mirror", twosided=True, **gold)
    one = b.add_material("one_sided", albedo=(0.0, 0.0, 0.0), kind="mirror", **gold)
    wall = b.add_material("wall", albedo=(0.7, 0.6, 0.5))
    b.add_quad(((-0.6, 0.0, 0.0), (0.0, 0.5, 0.0), (0.5, 0.0, 0.0)), two)  # front normal -z: away from the camera
    b.add_quad(((0.6, 0.0, 0.0), (0.0, 0.5, 0.0), (0.5, 0.0, 0.0)), one)
    b.add_quad(((0.0, 0.0, 8.0), (0.0, 6.0, 0.0), (6.0, 0.0, 0.0)), wall)  # behind the camera, facing the mirrors
    b.add_point_light("lamp", (0.0, 1.0, 6.0), intensity=20.0)
    b.set_camera([CameraKey(0.0, (0.0, 0.0, 5.0), (0.0, 0.0, 0.0))], fov_deg=30.0, resolution=(40, 30))
    return b.build("mirror_back")


@pytest.mark.parametrize("backend", BACKENDS)
def test02_a_two_sided_mirror_reflects_from_its_back(backend, on_every_device, at_parity):
    """The back of a two-sided mirror reflects (its Fresnel term of the cosine's magnitude; the reflected direction is
    the same about either side's normal) and the chains reach the wall behind the camera; the back of a one-sided one
    ends the chain (Mitsuba's one-sided conductor is black there)."""
    scene = _mirror_back()
    tracer = make(backend, scene)
    got, want, c_dev, c_host = _stage(scene, tracer, 48, 36, max_depth=5)
    assert len(on_every_device) == 1 and len(want.points) > 0
    column = want.points.pixel % 48
    assert column.max() < 24  # every shading point came through the two-sided mirror (the image's left half)
    _agree(backend, got, want, at_parity)
    if backend == "mitsuba-llvm":
        assert got.rays_per_depth == want.rays_per_depth and c_dev == c_host


@pytest.mark.parametrize("backend", BACKENDS)
def test03_chains_that_end_at_the_first_depth(backend, on_every_device, at_parity):
    """max_depth 1: the specular surfaces the first rays reach end their chains (no shading point, no next depth)."""
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    tracer = make(backend, scene)
    got, want, _, _ = _stage(scene, tracer, 48, 27, max_depth=1)
    assert len(want.rays_per_depth) == 1 and len(on_every_device) == 1
    _agree(backend, got, want, at_parity)


@pytest.mark.parametrize("backend", BACKENDS)
def test04_frames_take_the_device_chains_on_cuda_only_and_never_for_glossy_cones_or_overlays(backend, calls_of):
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    tracer = make(backend, scene)
    calls = calls_of(device_secondary, "chains")
    _stage(scene, tracer, 32, 18)
    assert len(calls) == (1 if backend == "mitsuba-cuda" else 0)
    assert not device_secondary.available(tracer, True, None)
    assert not device_secondary.available(tracer, False, np.zeros(scene.num_faces, bool))


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm"))
def test05_the_bench_replays_the_device_chains_rays(backend, monkeypatch, calls_of):
    """`splitbench bench quake_drt` part rays: where the chains run on the device they record their rays, so the raw
    replay traces the same rays as on the host path (and the numpy-fed raw gets them copied)."""
    from methods.quake_drt import bench
    from suite.harness import runner

    scene = runner.load_scene("gallery")
    host = bench.bench_secondary(scene, make("mitsuba-llvm", scene), (48, 27), 1.0, 1, "mitsuba-llvm")
    monkeypatch.setattr(device_secondary, "DEVICES", ("llvm",))
    calls = calls_of(device_secondary, "chains")
    dev = bench.bench_secondary(scene, make("mitsuba-llvm", scene), (48, 27), 1.0, 1, "mitsuba-llvm")
    assert calls and dev["raw"] == "device-resident rays"
    assert dev["raw_rays"] == host["raw_rays"] > 0 and dev["rays"] == host["rays"]
    assert dev["rays_per_depth"] == host["rays_per_depth"]
    assert dev["raw_ms"] > 0 and dev["raw_numpy_ms"] > 0
