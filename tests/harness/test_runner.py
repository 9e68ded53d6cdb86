"""Runner and results store on the synthetic methods: files, atomicity, skipping, determinism, quality."""
import json

import numpy as np
import pandas as pd
import pytest

from suite.harness import results
from suite.errors import UserError


def _counters(run_dir):
    df = pd.read_parquet(run_dir / "frames.parquet")
    return df[["frame", "t_s", "rays", "pixels", "bytes_up", "bytes_down", "image_sha256", "dssim"]]


def test01_run_writes_config_frames_summary_and_images(fake_config, fake_core, tmp_path):
    cfg = fake_config(net="bw=8mbps,delay=5ms")
    out = fake_core.execute(cfg, tmp_path)
    run_dir = tmp_path / out["run_dir"].split("/")[-1]
    assert not out["skipped"] and results.is_complete(run_dir)
    doc = json.loads((run_dir / "config.json").read_text())
    assert doc["config"]["method"] == "synthetic_sync" and doc["schema_version"] == results.SCHEMA_VERSION
    assert {"packages", "host", "git", "backend", "seed"} <= set(doc)
    frames = pd.read_parquet(run_dir / "frames.parquet")
    assert list(frames["frame"]) == [0, 1, 2]
    # 16x8 pixels traced per frame; 64 bytes up and 4000 down per frame
    assert list(frames["rays"]) == [128] * 3
    assert list(frames["bytes_up"]) == [64] * 3 and list(frames["bytes_down"]) == [4000] * 3
    # frame time >= pose (5 ms) + frame transfer (4 ms at 8 Mbit/s + 5 ms) + the 0.5 ms modelled upload
    assert (frames["frame_ms"] >= 14.5).all()
    assert frames["critical_path"][0].startswith("pose>render>frame>upload")
    assert {"stage_render_ms", "stage_decode_ms", "net_frame_ms", "stage_upload_ms"} <= set(frames.columns)
    assert frames["dssim"].notna().all() and frames["zl_dssim"].notna().all()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["bytes_down"] == 12000 and summary["stats"]["frame_ms"]["p95"] >= 14.5
    names = sorted(p.name for p in (run_dir / "images").iterdir())
    assert names == sorted([f"frame_{i:04d}.exr" for i in range(3)] + [f"frame_{i:04d}.png" for i in range(3)]
                           + [f"{kind}_{i:04d}.png" for i in range(3)
                              for kind in ("reference", "direct_reference", "zero_latency")])
    # every quality frame is scored against both light transports, with both references' noise floors
    for prefix in ("", "direct_", "floor_", "direct_floor_", "zl_"):
        assert frames[f"{prefix}rel_mse"].notna().all(), prefix
    assert summary["light_transport"] == "direct"


def test02_rerun_of_a_complete_run_is_skipped(fake_config, fake_core, tmp_path):
    cfg = fake_config()
    first = fake_core.execute(cfg, tmp_path)
    second = fake_core.execute(cfg, tmp_path)
    assert second["skipped"] and second["run_dir"] == first["run_dir"]


def test03_identical_config_and_seed_give_identical_counters_bytes_and_images(fake_config, fake_core, tmp_path):
    cfg = fake_config(net="bw=8mbps,delay=5ms", seed=7)
    a = fake_core.execute(cfg, tmp_path / "a")
    b = fake_core.execute(cfg, tmp_path / "b")
    pd.testing.assert_frame_equal(_counters(results.Path(a["run_dir"])), _counters(results.Path(b["run_dir"])))
    c = fake_core.execute(fake_config(net="bw=8mbps,delay=5ms", seed=8), tmp_path / "c")
    assert list(_counters(results.Path(c["run_dir"]))["image_sha256"]) != \
        list(_counters(results.Path(a["run_dir"]))["image_sha256"])


def test03b_a_rehearsal_runs_once_per_process_and_configuration_and_changes_no_result(fake_config, fake_core,
                                                                                      tmp_path, monkeypatch):
    """The first frames of a configuration are rehearsed once per process before the timed run (measured clock
    only); the run after a rehearsal and a rerun without one give the same counters, bytes and images."""
    monkeypatch.setattr(fake_core, "_REHEARSED", set())
    calls = []
    simulate = fake_core.simulate
    monkeypatch.setattr(fake_core, "simulate", lambda *a, **k: calls.append(a[3]["frames"]) or simulate(*a, **k))
    cfg = fake_config(net="bw=8mbps,delay=5ms", seed=3, frames=5)
    a = fake_core.execute(cfg, tmp_path / "a")
    assert calls[0] == fake_core.REHEARSAL_FRAMES and "rehearsal" in a["summary"]["run_wall_s"]
    calls.clear()
    b = fake_core.execute(cfg, tmp_path / "b")
    assert calls and calls == [5] * len(calls)   # the run (and its zero-latency run): no second rehearsal
    pd.testing.assert_frame_equal(_counters(results.Path(a["run_dir"])), _counters(results.Path(b["run_dir"])))
    # another resolution is rehearsed; the work clock, which charges counted work only, is not
    assert fake_core.rehearse(None, None, None, fake_config(resolution="8x8", clock="work"), None) is False
    calls.clear()
    fake_core.execute(fake_config(resolution="8x8", frames=5), tmp_path / "c")
    assert calls[0] == fake_core.REHEARSAL_FRAMES


def test04_a_failing_run_leaves_nothing_that_looks_like_a_result(fake_config, fake_core, tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(fake_core, "write_png", boom)
    with pytest.raises(RuntimeError):
        fake_core.execute(fake_config(), tmp_path)
    assert results.complete_runs(tmp_path) == []
    # only the shared prepare() cache may remain: nothing that looks like a run
    assert [p.name for p in tmp_path.iterdir()] in ([], [fake_core.PREPARED_DIR])


def test05_async_method_uses_updates_and_records_staleness(fake_config, fake_core, tmp_path):
    cfg = fake_config("synthetic_async", net="bw=8mbps,delay=5ms", frames=6, clock="work")
    out = fake_core.execute(cfg, tmp_path)
    run_dir = results.Path(out["run_dir"])
    frames = pd.read_parquet(run_dir / "frames.parquet")
    updates = pd.read_parquet(run_dir / "updates.parquet")
    # 20000 bytes at 8 Mbit/s = 20 ms + 5 ms delay: the first update arrives after frame 1 (16.7 ms)
    assert frames["update_index"].iloc[0] == -1 and frames["update_index"].iloc[-1] >= 0
    assert frames["staleness_ms"].iloc[-1] >= 25.0
    assert len(updates) >= 2 and (updates["bytes_down"] == 20000).all()
    # the zero-latency run (lockstep) is a different image sequence than the delayed one
    assert (frames["zl_dssim"] > 0).any()
    assert json.loads((run_dir / "summary.json").read_text())["zero_latency_run"] is True


def test06_variant_and_set_values_reach_the_method(fake_config):
    assert fake_config(variant="paper")["params"]["gain"] == 2.0
    assert fake_config(set_values={"variant": "dim", "payload_bytes": 9})["params"] == \
        {"payload_bytes": 9, "gain": 0.5, "label": "plain", "work_ms": 0.0}


@pytest.mark.parametrize("kwargs, needle", [
    ({"resolution": "0x0"}, "resolution 0x0"),
    ({"resolution": "big"}, "malformed resolution 'big'"),
    ({"frames": -1}, "frame count must be >= 1"),
    ({"scene": "nowhere"}, "unknown scene 'nowhere'"),
    ({"net": "moon-link"}, "unknown network profile 'moon-link'"),
    ({"set_values": {"nope": 1}}, "unknown parameter 'nope'"),
    ({"set_values": {"payload_bytes": "many"}}, "parameter 'payload_bytes'"),
    ({"variant": "shiny"}, "no variant 'shiny'"),
    ({"backend": "abacus"}, "unknown backend 'abacus'"),
    ({"protocol": "sctp"}, "unknown protocol 'sctp'"),
])
def test07_bad_input_is_a_one_line_user_error_naming_it(fake_config, kwargs, needle):
    with pytest.raises(UserError, match=needle) as info:
        fake_config(**kwargs)
    assert "\n" not in str(info.value)


def test08_unknown_method_is_a_user_error(fake_core):
    with pytest.raises(UserError, match="unknown method 'teleport'"):
        fake_core.make_config("teleport", scene="toy", backend="fake")


def test09_quality_frames_cover_small_runs_and_thin_out_large_ones(fake_core):
    assert fake_core.quality_frames(5, 0) == [0, 1, 2, 3, 4]
    assert fake_core.quality_frames(64, 0) == list(range(0, 64, 4))
    assert fake_core.quality_frames(10, 3) == [0, 3, 6, 9]
    assert fake_core.quality_frames(10, -1) == []


def test10_runs_that_differ_only_in_the_network_share_one_zero_latency_run(fake_config, fake_core, tmp_path,
                                                                           monkeypatch):
    calls = []
    real = fake_core.simulate

    def counting(cls, scene, tracer, cfg, zero_latency, keep, **kw):
        calls.append(zero_latency)
        return real(cls, scene, tracer, cfg, zero_latency, keep, **kw)

    monkeypatch.setattr(fake_core, "simulate", counting)
    # the once-per-process rehearsal (a short ideal-network simulation) is not what is counted here, and whether it
    # runs depends on what this process ran before
    monkeypatch.setattr(fake_core, "rehearse", lambda *args, **kwargs: False)
    a = fake_core.execute(fake_config(net="bw=8mbps,delay=5ms"), tmp_path)
    b = fake_core.execute(fake_config(net="bw=80mbps,delay=1ms", protocol="udp"), tmp_path)
    assert calls == [False, True, False]  # the second run reuses the first one's zero-latency images
    za = pd.read_parquet(f"{a['run_dir']}/frames.parquet")["zl_dssim"]
    zb = pd.read_parquet(f"{b['run_dir']}/frames.parquet")["zl_dssim"]
    assert za.notna().all() and zb.notna().all()
    assert results.complete_runs(tmp_path) == sorted([results.Path(a["run_dir"]), results.Path(b["run_dir"])])
