"""The pipeline end to end: bit-identical to Algorithm 3A when lossless, Figure 7's schedule, repairs under loss."""
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import transfer
from methods.visibility_bitmap.method import VisibilityBitmap, decode_inputs, encode_inputs
from suite.errors import UserError
from suite.harness.method import ClientCamera, Clock, Context, ServerCamera, scene_view
from suite.harness.timeline import Timeline

CONFIG = Path(__file__).resolve().parents[3] / "methods" / "visibility_bitmap" / "config.toml"
RES = (48, 27)
FRAMES = 2


def needs(codec):
    """Skips the test when the codec's optional library is missing."""
    from methods.visibility_bitmap.codecs import unavailable_reason

    reason = unavailable_reason(codec.split("+")[-1].split(":")[0])
    if reason:
        pytest.skip(f"codec {codec} unavailable: {reason}")


@pytest.fixture(scope="module")
def living_room():
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("living_room")
    return scene, make("embree", scene)


@dataclass
class Delivery:
    arrival_s: float
    delivered_bytes: int
    lost_ranges: list = field(default_factory=list)
    retransmissions: int = 0
    complete: bool = True


class IdealLink:
    """Test double of a link: arrival = send + delay + size / bandwidth, no loss (exact, hand-computable)."""

    def __init__(self, bandwidth_mbps: float = math.inf, delay_ms: float = 0.0):
        self.bandwidth_mbps, self.delay_ms = float(bandwidth_mbps), float(delay_ms)

    def send(self, size_bytes, direction="down", protocol="tcp", at_s=0.0, deadline_s=None):
        transfer_s = 0.0 if math.isinf(self.bandwidth_mbps) else size_bytes * 8.0 / (self.bandwidth_mbps * 1e6)
        return Delivery(at_s + self.delay_ms / 1e3 + transfer_s, int(size_bytes))


class Links:
    """A one-client network of two test-double links, in the shape of a netsim topology."""

    def __init__(self, down, up):
        self.links = {"down": down, "up": up}

    def send(self, size_bytes, client=0, direction="down", protocol="tcp", at_s=0.0, deadline_s=None):
        return self.links[direction].send(size_bytes, direction, protocol, at_s, deadline_s)


class LossyLink(IdealLink):
    """An ideal link that drops the given byte ranges of every message of ``lose_sizes_over`` bytes or more."""

    def __init__(self, lost_fraction_ranges, delay_ms=1.0, lose_sizes_over=1000, never_arrives=False):
        super().__init__(bandwidth_mbps=1000.0, delay_ms=delay_ms)
        self.ranges, self.threshold, self.never = lost_fraction_ranges, lose_sizes_over, never_arrives

    def send(self, size_bytes, direction="down", protocol="tcp", at_s=0.0, deadline_s=None):
        d = super().send(size_bytes, direction, protocol, at_s)
        if size_bytes < self.threshold:
            return d
        if self.never:
            return Delivery(arrival_s=math.inf, delivered_bytes=0, complete=False)
        lost = [(int(a * size_bytes), int(b * size_bytes)) for a, b in self.ranges]
        return Delivery(d.arrival_s, size_bytes - sum(b - a for a, b in lost), lost, 0, not lost)


def run(method, scene, tracer, zero_latency, protocol="tcp", link=None, frames=FRAMES, up_link=None):
    """A minimal sync driver on the harness's Timeline and Context: returns images and contexts per frame.

    Stage durations come from the work clock (rays and pixels), so schedules are the same on every machine.
    """
    link = link or IdealLink(bandwidth_mbps=100.0, delay_ms=2.0)
    timeline = Timeline(Links(link, up_link or IdealLink(100.0, 2.0)))
    method.reset()
    images, contexts, prev_t = [], [], None
    client_scene = scene_view(scene, ClientCamera(scene.camera, 0))
    server_scene = scene_view(scene, ServerCamera(scene.camera, 0))
    for i in range(frames):
        t_s = scene.camera.frame_time_s(i)
        group = timeline.group("frame", i, i / 30.0)
        ctx = Context(group, scene=client_scene, server_scene=server_scene, tracer=tracer, t_s=t_s, prev_t_s=prev_t,
                      resolution=RES, seed=0, params=method.params, zero_latency=zero_latency, protocol=protocol,
                      clock=Clock("work"), outputs=VisibilityBitmap.outputs)
        images.append(method.frame(ctx))
        contexts.append((ctx, group, dict(ctx.outputs)))
        prev_t = t_s
    return images, contexts


@pytest.fixture(scope="module")
def standalone(living_room):
    scene, tracer = living_room
    method = VisibilityBitmap({})
    method.restore(method.prepare(scene, tracer))
    return run(method, scene, tracer, zero_latency=True)[0]


@pytest.mark.parametrize("codec,layout", [("none", "paper32"), ("lzo", "paper32"), ("lz4", "packed8"),
                                          ("zstd", "words32"), ("delta+bitplane+zstd", "packed8"),
                                          ("h264", "packed8")])
@pytest.mark.parametrize("protocol", ["tcp", "udp"])
def test01_lossless_transport_gives_an_image_bit_identical_to_standalone_3a(living_room, standalone, codec,
                                                                              layout, protocol):
    from methods.visibility_bitmap.codecs import unavailable_reason

    if unavailable_reason(codec.split("+")[-1]):
        pytest.skip(unavailable_reason(codec.split("+")[-1]))
    scene, tracer = living_room
    method = VisibilityBitmap({"codec": codec, "layout": layout, "udp_slice_rows": 4})
    method.restore(method.prepare(scene, tracer))
    images, contexts = run(method, scene, tracer, zero_latency=False, protocol=protocol)
    for distributed, alone, (_, _, info) in zip(images, standalone, contexts):
        assert info["status"] == "ok"
        assert distributed.tobytes() == alone.tobytes()


def test02_client_gbuffer_overlaps_the_server_as_in_figure_7(living_room):
    scene, tracer = living_room
    method = VisibilityBitmap({})
    method.restore(method.prepare(scene, tracer))
    # An instant up-link: the server starts at once, so the overlap does not hinge on the link's delay.
    _, contexts = run(method, scene, tracer, zero_latency=False, frames=1, up_link=IdealLink())
    ev = contexts[0][1].events
    assert ev["client_gbuffer"].start_s == contexts[0][1].start_s  # does not wait for the server
    assert ev["server_receive"].start_s >= ev["inputs"].end_s
    assert ev["server_gbuffer"].start_s < ev["client_gbuffer"].end_s  # the two places run at once
    assert ev["receive_bitmap"].start_s >= ev["bitmap"].end_s
    assert ev["shading"].start_s >= max(ev["cpu_to_gpu"].end_s, ev["client_gbuffer"].end_s)
    order = ["inputs", "server_receive", "server_gbuffer", "visibility", "gpu_to_cpu", "encode", "bitmap",
             "receive_bitmap", "cpu_to_gpu", "shading", "output"]
    assert [ev[a].end_s <= ev[b].start_s + 1e-12 for a, b in zip(order, order[1:])] == [True] * (len(order) - 1)


def test03_memory_transfers_are_modelled_from_raw_bitmap_bytes_and_bandwidth(living_room):
    scene, tracer = living_room
    needs("zstd")
    method = VisibilityBitmap({"codec": "zstd", "gpu_to_cpu_mb_per_s": 100.0, "cpu_to_gpu_mb_per_s": 400.0})
    method.restore(method.prepare(scene, tracer))
    _, contexts = run(method, scene, tracer, zero_latency=False, frames=1)
    ev = contexts[0][1].events
    raw = bm.bitmap_nbytes(*RES, 3, "paper32")
    assert contexts[0][2]["raw_bytes"] == raw and contexts[0][2]["wire_bytes"] < raw
    assert ev["gpu_to_cpu"].kind == "modelled" and ev["cpu_to_gpu"].kind == "modelled"
    assert 1e3 * ev["gpu_to_cpu"].duration_s == pytest.approx(transfer.transfer_ms(raw, 100e6))
    assert 1e3 * ev["cpu_to_gpu"].duration_s == pytest.approx(transfer.transfer_ms(raw, 400e6))


def test04_udp_loss_repairs_only_the_lost_rows_with_lit(living_room, standalone):
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import min_light_distance, point_light_visibility, shade_point_lights

    scene, tracer = living_room
    method = VisibilityBitmap({"udp_repair": "lit", "udp_slice_rows": 3})
    method.restore(method.prepare(scene, tracer))
    images, contexts = run(method, scene, tracer, zero_latency=False, protocol="udp",
                           link=LossyLink([(0.40, 0.45)]), frames=1)
    info = contexts[0][2]
    assert info["status"] == "repaired" and 0 < info["rows_repaired"] < RES[1]
    events = contexts[0][1].events
    assert events["bitmap"].protocol == "udp" and events["inputs"].protocol == "tcp"  # the camera never gets lost
    t_s = scene.camera.frame_time_s(0)
    g = render_gbuffer(scene, tracer, t_s, resolution=RES)
    lights = scene.lights_at(t_s)
    vis = point_light_visibility(g, lights, tracer)
    bad_rows = np.nonzero((images[0] != standalone[0]).any(axis=(1, 2)))[0]
    vis[bad_rows] = True
    expected = shade_point_lights(g, lights, vis, min_distance=min_light_distance(scene))
    assert len(bad_rows) <= info["rows_repaired"]
    assert images[0].tobytes() == expected.tobytes()


def test05_a_bitmap_that_never_arrives_marks_the_frame_bad_and_reuses_the_previous_frame(living_room):
    scene, tracer = living_room
    method = VisibilityBitmap({"udp_repair": "previous"})
    method.restore(method.prepare(scene, tracer))
    good, _ = run(method, scene, tracer, zero_latency=False, frames=1)
    method2 = VisibilityBitmap({"udp_repair": "lit"})
    method2.restore(method2.prepare(scene, tracer))
    images, contexts = run(method2, scene, tracer, zero_latency=False, link=LossyLink([], never_arrives=True),
                           frames=1)
    assert contexts[0][2]["status"] == "bad" and contexts[0][2]["rows_repaired"] == RES[1]
    assert np.isfinite(images[0]).all() and images[0].sum() >= good[0].sum()  # all lit: never darker


def test06_ambient_term_lifts_only_pixels_where_every_light_is_shadowed(living_room, standalone):
    scene, tracer = living_room
    method = VisibilityBitmap({"ambient": True, "ambient_radiance": 0.5})
    method.restore(method.prepare(scene, tracer))
    images, _ = run(method, scene, tracer, zero_latency=True, frames=1)
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import point_light_visibility

    g = render_gbuffer(scene, tracer, scene.camera.frame_time_s(0), resolution=RES)
    dark = g.valid & ~point_light_visibility(g, scene.lights_at(0.0), tracer).any(axis=-1)
    assert dark.any() and (~dark & g.valid).any()
    diff = images[0] - standalone[0]
    assert np.allclose(diff[dark], 0.5 * g.albedo[dark], atol=1e-5)  # seed 000 §5.1: L_ambient * rho
    assert not diff[~dark].any()


def test07_scene_moved_1e4_away_gives_the_same_bitmap_within_half_a_percent_of_pixels(living_room):
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import point_light_visibility
    from suite.core.trace import make

    scene, tracer = living_room
    far = scene.translated((1e4, 1e4, 1e4))
    res = (96, 54)
    bitmaps = []
    for s, tr in ((scene, tracer), (far, make("embree", far))):
        g = render_gbuffer(s, tr, 0.0, resolution=res)
        bitmaps.append(bm.pack(point_light_visibility(g, s.lights_at(0.0), tr), "paper32").reshape(res[1], res[0], 4))
    differing = (bitmaps[0] != bitmaps[1]).any(axis=-1).mean()
    assert differing <= 0.005, f"{100 * differing:.2f} % of pixels differ"


def test08_paper32_refuses_a_scene_with_more_than_32_lights(living_room):
    from dataclasses import replace

    from suite.core.scene import PointLight

    scene, tracer = living_room
    many = replace(scene, point_lights=[PointLight(f"l{i}", (0.0, 2.0, 0.1 * i), (1.0, 1.0, 1.0)) for i in range(33)])
    with pytest.raises(UserError, match="at most 32 lights"):
        VisibilityBitmap({"layout": "paper32"}).prepare(many, tracer)
    VisibilityBitmap({"layout": "words32"}).prepare(many, tracer)


def test09_inputs_carry_the_pose_and_the_resolution_only_on_the_first_frame(living_room):
    scene, _ = living_room
    pose = scene.camera.pose_at(0.5)
    first, later = encode_inputs(0.5, pose, (640, 360)), encode_inputs(0.5, pose, None)
    assert len(first) == len(later) + 8
    t_s, p, res = decode_inputs(first)
    assert t_s == 0.5 and res == (640, 360) and np.array_equal(p[0], pose.position)
    assert decode_inputs(later)[2] is None


@pytest.mark.parametrize("params,message", [({"codec": "gzip"}, "unknown codec"), ({"layout": "rgb"}, "layout"),
                                            ({"udp_repair": "zero"}, "udp_repair"),
                                            ({"cpu_to_gpu_mb_per_s": 0.0}, "> 0"),
                                            ({"udp_slice_rows": 0}, "udp_slice_rows")])
def test10_bad_parameters_are_one_line_user_errors(params, message):
    with pytest.raises(UserError, match=message):
        VisibilityBitmap(params)


def test11_config_documents_every_parameter_and_every_variant_constructs():
    config = tomllib.loads(CONFIG.read_text())
    defaults = config["defaults"]
    assert set(config["doc"]) == set(defaults)
    from methods.visibility_bitmap.codecs import unavailable_reason

    for name, overrides in [("paper", config["paper"]), *config["variants"].items()]:
        assert set(overrides) <= set(defaults), name
        params = {**defaults, **overrides}
        base = str(params.get("codec", "none")).split("+")[-1].split(":")[0]
        if unavailable_reason(base):  # an optional codec this machine lacks: refused by name, in one line
            with pytest.raises(UserError, match=f"codec '{base}' is unavailable"):
                VisibilityBitmap(params)
        else:
            VisibilityBitmap(params)


def test12_registry_finds_the_method_class():
    from suite.harness import registry

    assert registry.get("visibility_bitmap").load() is not None


def plane_scene(light_position):
    """A 20 m floor seen from above at an angle and a back wall at z = -10 facing it, one light.

    Nothing stands between the floor and a light above it or on the wall, so every floor pixel must be lit.
    """
    from suite.core.scene import CameraKey
    from suite.core.scene.builder import SceneBuilder

    b = SceneBuilder()
    grey = b.add_material("grey", albedo=(0.7, 0.7, 0.7))
    b.add_quad(((0.0, 0.0, 0.0), (10.0, 0.0, 0.0), (0.0, 0.0, -10.0)), grey)
    b.add_quad(((0.0, 2.0, -10.0), (10.0, 0.0, 0.0), (0.0, 2.0, 0.0)), grey)
    b.add_point_light("lamp", light_position, 10.0)
    b.set_camera([CameraKey(0.0, (0.0, 2.0, 3.0), (0.0, 0.0, -4.0))], fov_deg=60.0, resolution=RES)
    return b.build("plane")


@pytest.mark.parametrize("light_position", [(0.0, 0.02, -9.0), (3.0, 1.0, -10.0)],
                         ids=["grazing_the_floor", "on_the_wall_surface"])
def test13_an_unoccluded_floor_has_no_acne_and_a_finite_lit_image(light_position):
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import point_light_visibility
    from suite.core.trace import make

    scene = plane_scene(light_position)
    tracer = make("embree", scene)
    g = render_gbuffer(scene, tracer, 0.0, resolution=RES)
    floor = g.valid & (g.normal[..., 1] > 0.99)
    vis = point_light_visibility(g, scene.lights_at(0.0), tracer)
    assert floor.sum() > 0.3 * floor.size
    assert vis[floor].all(), f"{int((~vis[floor]).sum())} floor pixels shadow themselves"
    needs("lz4")
    method = VisibilityBitmap({"codec": "lz4"})
    method.restore(method.prepare(scene, tracer))
    images, _ = run(method, scene, tracer, zero_latency=False, frames=1)
    assert np.isfinite(images[0]).all() and (images[0][floor].max(axis=-1) > 0).all()


def test14_without_ambient_the_image_is_the_cores_direct_lighting(living_room):
    # living_room has point lights only, so direct_lighting (proven against Mitsuba's `direct` integrator in
    # tests/core/test_direct_lighting.py) is exactly seed 000 §3.1's shading: the distributed image must equal it.
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import direct_lighting

    scene, tracer = living_room
    needs("zstd")
    method = VisibilityBitmap({"codec": "zstd", "layout": "packed8"})
    method.restore(method.prepare(scene, tracer))
    images, _ = run(method, scene, tracer, zero_latency=False, frames=1)
    t_s = scene.camera.frame_time_s(0)
    g = render_gbuffer(scene, tracer, t_s, resolution=RES)
    assert images[0].tobytes() == direct_lighting(scene, g, tracer, t_s).tobytes()


@pytest.mark.slow
def test15_distributed_image_agrees_with_mitsuba_direct_within_its_noise(living_room):
    """Same statistics as tests/core/test_direct_lighting.py: |z| > 5 on < 0.5 % of non-edge pixels, no bias."""
    from scipy import ndimage

    from suite.core.gbuffer import render_gbuffer
    from suite.core.reference import render_with_stderr
    from suite.core.scene.mitsuba_io import to_mitsuba_dict
    from suite.core.shading import point_light_visibility

    scene, tracer = living_room
    res, t_s = (64, 36), scene.camera.frame_time_s(0)
    needs("lz4")
    method = VisibilityBitmap({"codec": "lz4", "layout": "packed8"})
    method.restore(method.prepare(scene, tracer))
    timeline = Timeline(Links(IdealLink(100.0, 2.0), IdealLink(100.0, 2.0)))
    ctx = Context(timeline.group("frame", 0, 0.0), scene=scene_view(scene, ClientCamera(scene.camera, 0)),
                  server_scene=scene_view(scene, ServerCamera(scene.camera, 0)), tracer=tracer, t_s=t_s,
                  prev_t_s=None, resolution=res, seed=0, params=method.params, zero_latency=False,
                  clock=Clock("work"), outputs=VisibilityBitmap.outputs)
    ours = method.frame(ctx)
    ref, se_ref = render_with_stderr(to_mitsuba_dict(scene, t_s, res, integrator={"type": "direct"}),
                                     spp=2048, passes=16, seed=7)
    g = render_gbuffer(scene, tracer, t_s, res)
    vis = point_light_visibility(g, scene.lights_at(t_s), tracer)
    keys = [np.where(g.valid, g.prim, -1).astype(float), *np.moveaxis(g.normal.round(3), -1, 0),
            *np.moveaxis(g.albedo.round(3), -1, 0), *np.moveaxis(vis.astype(float), -1, 0)]
    edge = ~g.valid
    for k in keys:  # pixel-centre sampling and Mitsuba's box filter legitimately differ across edges
        edge |= (ndimage.maximum_filter(k, 3, mode="nearest") - ndimage.minimum_filter(k, 3, mode="nearest")) > 1e-6
    keep = ~edge
    diff = (ours - ref)[keep]
    se = np.sqrt(se_ref[keep] ** 2 + (0.01 * ref[keep]) ** 2)
    z = np.where(se > 0, diff / np.maximum(se, 1e-12), np.where(np.abs(diff) < 1e-6, 0.0, np.inf))
    assert keep.mean() > 0.3
    assert np.mean(np.abs(z) > 5) < 0.005
    assert abs(diff.sum() / np.sqrt((se_ref[keep] ** 2).sum())) < 5


@pytest.mark.parametrize("layout,bytes_per_pixel", [("paper32", 4), ("packed8", 0)])
def test16_a_scene_without_point_lights_sends_what_the_layout_says_and_matches_standalone(layout, bytes_per_pixel):
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("cornell")  # an area light only: seed 000 traces point lights, so L = 0
    tracer = make("embree", scene)
    needs("lz4")
    method = VisibilityBitmap({"layout": layout, "codec": "lz4"})
    method.restore(method.prepare(scene, tracer))
    alone, _ = run(method, scene, tracer, zero_latency=True, frames=1)
    images, contexts = run(method, scene, tracer, zero_latency=False, frames=1)
    assert contexts[0][2]["raw_bytes"] == RES[0] * RES[1] * bytes_per_pixel
    assert images[0].tobytes() == alone[0].tobytes()


# --- the device path (Mitsuba llvm_ad_rgb / cuda_ad_rgb: G-buffer, visibility, packing and shading on the device) --

from suite.core.trace import backend_params  # noqa: E402

DRJIT = backend_params("mitsuba-llvm", "mitsuba-cuda")


def host_algorithm_3a(scene, tracer, t_s, prev_t_s, ambient=None):
    """Algorithm 3A through the numpy/numba host path on the same tracer (what the method computed before it ran on
    the device)."""
    from suite.core.gbuffer import render_gbuffer
    from suite.core.shading import min_light_distance, point_light_visibility, shade_point_lights

    g = render_gbuffer(scene, tracer, t_s, RES, prev_t_s, device=False)
    lights = scene.lights_at(t_s)
    return shade_point_lights(g, lights, point_light_visibility(g, lights, tracer), ambient=ambient,
                              min_distance=min_light_distance(scene))


@pytest.mark.parametrize("backend", DRJIT)
@pytest.mark.parametrize("name, codec, layout", [("living_room", "none", "paper32"), ("living_room", "lz4", "packed8"),
                                                 ("arena", "zstd", "words32"), ("arena", "none", "packed8")])
def test17_device_path_is_bit_identical_to_standalone_and_to_the_host_path(backend, name, codec, layout):
    from suite.core.scene import load
    from suite.core.trace import make

    needs(codec)
    scene = load(name)
    tracer = make(backend, scene)
    method = VisibilityBitmap({"codec": codec, "layout": layout, "udp_slice_rows": 4})
    method.restore(method.prepare(scene, tracer))
    alone, alone_ctx = run(method, scene, tracer, zero_latency=True)
    images, contexts = run(method, scene, tracer, zero_latency=False, protocol="udp")
    for i, (distributed, standalone, (_, group, info)) in enumerate(zip(images, alone, contexts)):
        assert info["status"] == "ok" and distributed.tobytes() == standalone.tobytes()
        assert info["raw_bytes"] == bm.bitmap_nbytes(*RES, len(scene.lights_at(0.0)), layout)
        prev = scene.camera.frame_time_s(i - 1) if i else None
        host = host_algorithm_3a(scene, tracer, scene.camera.frame_time_s(i), prev)
        if backend == "mitsuba-llvm":
            assert standalone.tobytes() == host.tobytes()  # the CPU results did not change
        else:
            np.testing.assert_allclose(standalone, host, rtol=1e-4, atol=1e-6)
    # the output pass is the explicit read-back of the shaded image, with its bytes
    assert alone_ctx[0][1].events["output"].size_bytes == RES[0] * RES[1] * 3 * 4


@pytest.mark.parametrize("backend", DRJIT)
def test18_device_path_ambient_and_repairs_match_the_host_path(backend):
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("living_room")
    tracer = make(backend, scene)
    method = VisibilityBitmap({"ambient": True, "ambient_radiance": 0.05, "layout": "packed8"})
    method.restore(method.prepare(scene, tracer))
    alone, _ = run(method, scene, tracer, zero_latency=True, frames=1)
    host = host_algorithm_3a(scene, tracer, scene.camera.frame_time_s(0), None, ambient=0.05)
    np.testing.assert_allclose(alone[0], host, rtol=1e-5, atol=1e-7)
    lossy = VisibilityBitmap({"layout": "packed8", "udp_slice_rows": 4, "udp_repair": "lit"})
    lossy.restore(lossy.prepare(scene, tracer))
    images, contexts = run(lossy, scene, tracer, zero_latency=False, protocol="udp", frames=1,
                           link=LossyLink([(0.0, 0.3)]))
    info = contexts[0][2]
    assert info["status"] == "repaired" and 0 < info["rows_repaired"] < RES[1]
    assert np.isfinite(images[0]).all() and images[0].mean() > 0


# --- what of a scene the method leaves out (seed 000 §3.1: point lights only) ------------------------------------

def test19_a_scene_lit_only_by_area_lights_is_refused_by_name_with_no_result(tmp_path, capsys):
    from suite.harness import cli

    code = cli.main(["run", "visibility_bitmap", "--scene", "cornell", "--resolution", "32x18", "--frames", "1",
                     "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "cornell" in err and "no point lights" in err and "area lights" in err
    assert not any(tmp_path.rglob("summary.json"))


def test20_emissive_triangles_beside_point_lights_are_warned_and_stored_as_omitted(tmp_path, capsys):
    from suite.core.scene import load
    from suite.harness import runner

    assert VisibilityBitmap({}).omissions(load("living_room")) == []  # point lights only: nothing left out
    cfg = runner.make_config("visibility_bitmap", scene="atrium", resolution="32x18", frames=1, reference_spp=0)
    summary = runner.execute(cfg, tmp_path)["summary"]
    area = len(load("atrium").emissive_faces())
    assert area > 0 and summary["omitted"] and f"{area} emissive triangles" in summary["omitted"][0]
    assert f"warning: visibility_bitmap on atrium: its {area} emissive" in capsys.readouterr().err
