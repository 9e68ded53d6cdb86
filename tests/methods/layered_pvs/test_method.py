"""The layered-PVS pipeline end to end, server update -> bytes -> client frame, on a small living_room: a static
camera reproduces the server's view, corrupt or truncated updates are rejected without a crash, the hard cases of
the issue behave as documented, and reruns give identical bytes."""
import json

import numpy as np
import pytest

from suite.core.scene.model import CameraPose
from methods.layered_pvs import client as cl
from methods.layered_pvs.bench import LocalContext, client_context, delivered_update
from methods.layered_pvs import server as sv
from methods.layered_pvs.method import LayeredPVS

RES = (64, 36)
FAST = {"update_fps": 5.5, "client_fps": 60.0, "max_in_flight": 1, "layers": 4, "full_layers": 1, "tile": 8,
        "order": "block", "fov_enlarge": 1.1, "corner_speed": 0.02, "spp": 1, "max_depth": 3, "rr_depth": 3,
        "denoise_iterations": 1, "relocation": True, "colour_fill": True, "video_crf": 25.0,
        "video_preset": "veryfast", "jpeg_quality": 25, "mask_codec": "quadtree", "subset_peeling": False,
        "key_interval": 10, "depth_tol": 0.01, "hole_fill": False, "exposure": 1.0}


@pytest.fixture(scope="module")
def world():
    from suite.harness import runner

    scene = runner.load_scene("living_room")
    return scene, runner.make_tracer("embree", scene)


def _update(world, method, pose, index=0, t_s=0.0):
    scene, tracer = world
    ctx = LocalContext(scene, tracer, t_s, RES, index, pose)
    method.server_update(ctx)
    return ctx


def _show(world, method, payload, pose, index=0, t_s=0.0, new=True):
    scene, _ = world
    ctx = client_context(pose, scene.camera.fov_deg, t_s, RES, index)
    img = method.client_frame(ctx, None if payload is None else delivered_update(payload, index, t_s, new))
    return img, ctx.outputs


def test01_static_camera_reproduces_the_server_view(world):
    scene, _ = world
    pose = scene.camera.pose_at(0.5)
    server, client = LayeredPVS(dict(FAST)), LayeredPVS(dict(FAST))
    up = _update(world, server, pose)
    assert up.outputs["host_device_bytes"] == 0         # Embree: the server's passes stay on the host
    img, out = _show(world, client, up.sent["update"], pose)
    assert out["rejected_updates"] == 0 and out["hole_pixels"] == 0 and out["unmatched_pixels"] == 0
    assert out["no_hit_pixels"] == 0       # a closed room: every pixel sees the PVS
    # The client frame is the centre crop of the decoded first layer (same pixel density, aligned centres).
    dec = client._client["decoded"]
    w, h = RES
    x0, y0 = (dec.view.width - w) // 2, (dec.view.height - h) // 2
    from suite.core import video

    crop = video.from_video(dec.texture[y0:y0 + h, x0:x0 + w], 1.0)
    assert np.mean(np.isclose(img, crop, rtol=1e-6, atol=1e-7).all(axis=-1)) > 0.97
    assert img.mean() > 0.0


def test02_corrupt_and_truncated_updates_are_rejected_and_the_previous_update_stays(world):
    scene, _ = world
    pose = scene.camera.pose_at(0.5)
    server, client = LayeredPVS(dict(FAST)), LayeredPVS(dict(FAST))
    first = _update(world, server, pose, 0).sent["update"]
    good, _ = _show(world, client, first, pose, 0)
    second = bytearray(_update(world, server, pose, 1, 0.1).sent["update"])
    second[len(second) // 2] ^= 0xFF
    img, out = _show(world, client, bytes(second), pose, 1)
    assert out["rejected_updates"] == 1 and "checksum mismatch" in out["reject_reason"]
    assert np.array_equal(img, good)
    img, out = _show(world, client, first[:100], pose, 2)
    assert out["rejected_updates"] == 2 and "truncated" in out["reject_reason"]
    assert np.array_equal(img, good)
    # A patch whose base the client never applied (it rejected update 1) is refused until the next key update.
    third = _update(world, server, pose, 2, 0.2).sent["update"]
    _, out = _show(world, client, third, pose, 3)
    assert out["rejected_updates"] == 3 and "patch against update 1" in out["reject_reason"]


def test03_camera_inside_a_wall_or_facing_the_sky_gives_an_empty_pvs_and_black_frames(world):
    scene, _ = world
    lo, hi = scene.bounds()
    outside = CameraPose(hi + 10.0, hi + 20.0, np.array([0.0, 1.0, 0.0]))     # looking away from the scene
    server, client = LayeredPVS(dict(FAST)), LayeredPVS(dict(FAST))
    up = _update(world, server, outside)
    assert up.outputs["pvs_triangles"] == 0 and up.outputs["fragments"] == 0 and up.outputs["tiles"] == 0
    img, out = _show(world, client, up.sent["update"], outside)
    assert out["rejected_updates"] == 0 and (img == 0).all() and out["no_hit_pixels"] == RES[0] * RES[1]


def test04_depth_beyond_the_layer_budget_and_empty_tile_layers(world):
    scene, _ = world
    pose = scene.camera.pose_at(0.5)
    one = LayeredPVS({**FAST, "layers": 1})
    up = _update(world, one, pose)
    # One layer: every tiled layer is empty (no tile, no JPEG bytes) and deeper geometry is cut.
    assert up.outputs["tiles"] == 0 and up.outputs["bytes_jpeg"] == 0
    assert up.outputs["depth_overflow_pixels"] > 0
    moved = CameraPose(pose.position + np.array([0.6, 0.0, 0.0]), pose.target + np.array([0.6, 0.0, 0.0]), pose.up)
    client = LayeredPVS({**FAST, "layers": 1})
    _, out = _show(world, client, up.sent["update"], moved)
    assert out["unmatched_pixels"] > 0          # disocclusions the single layer cannot fill: holes, counted


def test05_an_update_shown_after_the_client_moved_far_counts_holes_and_hole_fill_fills_them(world):
    scene, _ = world
    pose = scene.camera.pose_at(0.5)
    server = LayeredPVS(dict(FAST))
    payload = _update(world, server, pose).sent["update"]
    far = scene.camera.pose_at(scene.camera.duration_s)
    _, out = _show(world, LayeredPVS(dict(FAST)), payload, far)
    assert out["rejected_updates"] == 0
    holes = out["outside_pixels"] + out["unmatched_pixels"]
    assert holes > 0
    _, out_f = _show(world, LayeredPVS({**FAST, "hole_fill": True}), payload, far)
    assert out_f["filled_pixels"] > 0 and out_f["hole_pixels"] < holes


def test06_an_edge_on_triangle_gives_no_fragment_and_no_error():
    tri = np.array([[[0.0, -1.0, 5.0], [0.0, 1.0, 5.0], [0.0, 0.0, 9.0]]], np.float32)   # in the plane x = 0
    view = sv.LayerView(CameraPose(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])),
                        60.0, 16, 8)
    layers, _ = cl.peel_client(tri, view, 2)
    assert layers.valid.sum() <= 2 * 8        # at most the one column that grazes it


def test07_subset_peeling_gives_the_same_layers_as_full_peeling(world):
    scene, tracer = world
    pose = scene.camera.pose_at(0.5)
    wl, hl, fov = sv.layer_size(*RES, scene.camera.fov_deg, 1.1, 8)
    view = sv.LayerView(pose, fov, wl, hl)
    ids = sv.compute_pvs(tracer, [pose], fov, wl, hl)
    tris = scene.positions[scene.faces[ids]]
    full, _ = cl.peel_client(tris, view, 4)
    subsets = cl.triangle_subsets(full, len(ids))
    sub, _ = cl.peel_client(tris, view, 4, subsets)
    assert np.array_equal(full.prim, sub.prim) and np.allclose(full.t, sub.t)


def test08_reruns_give_identical_update_bytes(world):
    scene, _ = world
    pose = scene.camera.pose_at(0.5)
    a = _update(world, LayeredPVS(dict(FAST)), pose).sent["update"]
    b = _update(world, LayeredPVS(dict(FAST)), pose).sent["update"]
    assert a == b


def test09_bad_parameters_are_one_line_errors():
    from suite.errors import UserError

    with pytest.raises(UserError, match="mask_codec"):
        LayeredPVS({**FAST, "mask_codec": "zip"})
    with pytest.raises(UserError, match="full_layers"):
        LayeredPVS({**FAST, "full_layers": 9})


def test10_a_run_whose_updates_arrive_corrupt_completes_and_counts_rejections(tmp_path, monkeypatch):
    import pandas as pd

    import suite.harness.method as hm
    from suite.harness import runner

    real = hm.deliver_bytes

    def corrupt(payload, size, lost):
        data = real(payload, size, lost)
        if data is not None and len(data) > 1000:      # updates (poses are 88 bytes): flip one byte mid-payload
            data = bytearray(data)
            data[len(data) // 2] ^= 0x5A
            data = bytes(data)
        return data

    monkeypatch.setattr(hm, "deliver_bytes", corrupt)
    cfg = runner.make_config("layered_pvs", scene="living_room", resolution="32x18", frames=12, net="wan-50m",
                             protocol="tcp", reference_spp=4, clock="work",
                             set_values={"layers": 2, "spp": 1, "max_depth": 2, "denoise_iterations": 1})
    out = runner.execute(cfg, tmp_path)
    f = pd.read_parquet(f"{out['run_dir']}/frames.parquet")
    shown = f[f["update_index"] >= 0]
    assert len(shown) > 0 and shown["staleness_ms"].notna().all() and f["dssim"].notna().any()
    assert {"info_bytes_jpeg", "info_bytes_video", "info_bytes_mask", "info_bytes_pvs"} <= set(f.columns)
    assert shown["info_rejected_updates"].min() >= 1
    assert shown["info_reject_reason"].str.contains("checksum mismatch").all()
    # The report section reads the stored run and states its claims (quadtree against RLE is measured on any run).
    from pathlib import Path

    from methods.layered_pvs import report

    run_dir = Path(out["run_dir"])
    html = report.section(f.assign(run=run_dir.name, method="layered_pvs", resolution="32x18",
                                   scene="living_room"), [run_dir], out_dir=tmp_path / "report")
    assert "002.quadtree_vs_rle" in html and "002.dssim_static" in html
    # Every declared claim has a row: those whose runs are not in the results say what they need.
    stored = json.loads((tmp_path / "report" / "layered_pvs" / "claims.json").read_text())
    assert sorted(c["id"] for c in stored) == sorted(report.CLAIMS.expected)
    latency = next(c for c in stored if c["id"] == "002.latency")
    assert latency["kind"] == "not measurable here" and "not in these results" in latency["explanation"]


def test11_the_pvs_is_the_union_of_its_views_and_a_repeated_view_is_traced_once(world):
    """Algorithm 1's PVS: every triangle some view sees. The views of a camera with no known motion repeat the
    current one; repeating a view adds no triangle and no ray."""
    scene, tracer = world
    wl, hl, fov = sv.layer_size(*RES, scene.camera.fov_deg, 1.1, 8)
    a, b = scene.camera.pose_at(0.3), scene.camera.pose_at(0.7)
    each = [set(sv.compute_pvs(tracer, [p], fov, wl, hl).tolist()) for p in (a, b)]
    before = dict(tracer.counters)
    both = sv.compute_pvs(tracer, [a, b, a, a, b], fov, wl, hl)
    traced = sum(tracer.counters.values()) - sum(before.values())
    assert set(both.tolist()) == each[0] | each[1] and np.all(np.diff(both) > 0)
    assert traced == 2 * wl * hl
