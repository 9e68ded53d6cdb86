"""``splitbench bench layered_pvs`` stores its figures and images where the report reads them."""
import json

import pytest

from methods.layered_pvs import bench
from suite.core.trace import backend_params, device_backends


def test01_bench_stores_stage_ratios_codec_rates_client_cost_and_images(tmp_path):
    out = bench.run(["--scene", "living_room", "--resolutions", "32x18", "--layers", "2", "--codec-size", "64",
                     "--out", str(tmp_path)])
    row = out["server"][0]
    assert row["layers_rays"] > 0 and 0 < row["layers_ratio"] and row["render_ms_per_mpix"] > 0
    for st in ("pvs", "layers", "path_trace"):  # one update's ratio, lowest and highest, around the medians' ratio
        lo, hi = row[f"{st}_ratio_range"]
        assert lo * (1 - 1e-9) <= row[f"{st}_ratio"] <= hi * (1 + 1e-9)
    assert {r["codec"] for r in out["codecs"]} >= {"quadtree_mask", "rle_huffman_mask", "jpeg_q25_444", "pvs_patch"}
    doc = json.loads((tmp_path / "bench" / "layered_pvs.json").read_text())
    assert doc["images"] and all((tmp_path / "bench" / "layered_pvs" / n).is_file() for n in doc["images"])
    # the server rows again on each Dr.Jit backend that works here, each against its own device-resident raw
    assert [r["backend"] for r in doc["server_on_devices"]] == device_backends()
    for r in doc["server_on_devices"]:
        assert r["resolution"] == "32x18" and r["layers"] == 4 and r["raw"] == "backend on device-resident rays"
        assert all(r[f"{st}_rays"] > 0 and r[f"{st}_ratio"] > 0 for st in ("pvs", "layers", "path_trace"))
    # and the report shows them
    from methods.layered_pvs import report
    from suite.harness.reporting import SectionFiles

    html = "".join(report.bench_html(doc, SectionFiles(tmp_path / "report", "layered_pvs"), [], tmp_path))
    assert "svgf_host_ms" in html and ("on each Dr.Jit backend" in html) == bool(device_backends())


def test02_the_recorded_rays_are_the_ones_the_stage_traced():
    """Depth peeling writes each query's rays into buffers it reuses for the next query: the recording keeps copies,
    so replaying a recorded query gives the hits the stage got."""
    import numpy as np

    from methods.layered_pvs import server
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("living_room")
    tracer = make("embree", scene)
    answers = []

    class Answers:  # the tracer, keeping every answer it gave
        shift, soa_origins, scene, counters = tracer.shift, tracer.soa_origins, tracer.scene, tracer.counters

        def intersect(self, *a, **k):
            return tracer.intersect(*a, **k)

        def occluded(self, *a, **k):
            return tracer.occluded(*a, **k)

        def intersect_local(self, o, d, length):
            h = tracer.intersect_local(o, d, length)
            answers.append((h.prim.copy(), h.t.copy()))
            return h

        def occluded_local(self, o, d, length):
            return tracer.occluded_local(o, d, length)

    rec = bench.RecordingTracer(Answers())
    w, h = 48, 27
    o, d = server.view_rays(server.LayerView(scene.camera.pose_at(0.5), scene.camera.fov_deg, w, h))
    keep = np.random.default_rng(2).random(scene.num_faces) < 0.6  # hits stepped over: several queries per layer
    server.peel(rec, o.astype(np.float32), d.astype(np.float32), 3, keep_mask=keep, shape=(h, w))
    assert len(rec.log) == len(answers) > 3
    for (kind, ro, rd, rlen), (prim, t) in zip(rec.log, answers):
        again = tracer.intersect_local(ro.copy(), rd.copy(), rlen.copy())
        assert kind == "i" and np.array_equal(again.prim, prim) and np.array_equal(again.t, t)


def test03_the_report_states_how_many_rows_meet_the_ratio_goal_and_from_which_size():
    from methods.layered_pvs import report

    def row(res, pvs, layers, path):
        return {"resolution": res, "pvs_ratio": pvs, "layers_ratio": layers, "path_trace_ratio": path}

    rows = [row("160x90", 0.95, 0.80, 0.70), row("160x90", 0.91, 0.85, 0.92), row("480x270", 0.97, 0.91, 0.89),
            row("960x540", 0.99, 0.93, 0.93)]
    text = report.ratio_goal_text(rows)
    assert "pvs 0.910-0.990 of raw, 4 of 4 rows at >= 0.9;" in text
    assert "layers 0.800-0.930 of raw, 2 of 4 rows at >= 0.9 (every row from 480x270 up)" in text
    assert "path_trace 0.700-0.930 of raw, 2 of 4 rows at >= 0.9 (every row from 960x540 up)" in text
    rows[-1]["path_trace_ratio"] = 0.85
    assert "path_trace 0.700-0.920 of raw, 1 of 4 rows at >= 0.9 (not at the largest size)" in \
        report.ratio_goal_text(rows)
    assert report.ratio_goal_text([]) == ""
    # rows whose updates fell on both sides of the goal are counted
    rows[1]["layers_ratio_range"], rows[2]["layers_ratio_range"] = [0.83, 0.88], [0.86, 0.95]
    assert "layers 0.800-0.930 of raw, 2 of 4 rows at >= 0.9, 1 of 4 with updates on both sides of the goal" in \
        report.ratio_goal_text(rows)


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
@pytest.mark.parametrize("scene_name", ["living_room", "cornell"])
def test04_on_a_drjit_backend_each_stage_replays_every_ray_it_traced(backend, scene_name):
    """On a Dr.Jit backend the server traces on the device: the recording keeps the device passes' rays (PVS views,
    peeling, the fragments' shadow rays to point and area lights, the path bounces) and the numpy-fed queries, and
    each stage's replay holds as many rays as the stage counted (no alpha-tested surfaces here, whose walk adds
    queries the replay does not make); the bench's row takes them."""
    from methods.layered_pvs import device
    from suite.core.scene import load
    from suite.core.trace import make
    from suite.core.trace.recording import device_replay

    scene = load(scene_name)
    tracer = make(backend, scene)
    dev = tracer.device
    params = {**bench.DEFAULT_PARAMS, "layers": 2}
    with device.recording({}) as records:
        ctx, _, _, _ = bench.one_update(scene, bench.RecordingTracer(tracer, device=True), params, (32, 18), 0.5, 0.6)
    for stage in bench.SERVER_STAGES:
        rays, replay = device_replay(dev, ctx.stage_log[stage], records.get(stage, []))
        assert rays == ctx.stage_rays[stage] > 0, stage
        assert replay() > 0
    row = bench.server_rows(scene, tracer, params, [(32, 18)], [2], 0.5, repeats=1)[0]
    assert all(row[f"{st}_rays"] == ctx.stage_rays[st] and row[f"{st}_ratio"] > 0 for st in bench.SERVER_STAGES)
    assert row["raw"] == "backend on device-resident rays"
