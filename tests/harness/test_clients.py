"""Many clients on one server, and information that flows only as it would in the real system."""
import numpy as np
import pandas as pd
import pytest

from suite.harness import method as method_mod
from suite.harness import results
from suite.harness.clients import client_camera
from suite.harness.method import ClientCamera, ServerCamera, running_on
from suite.harness.timeline import SimulationError


def _run(fake_core, fake_config, tmp_path, **kw):
    kw.setdefault("net", "bw=100mbps,delay=5ms")
    kw.setdefault("frames", 8)
    kw.setdefault("clock", "work")
    kw.setdefault("reference_spp", 0)
    out = fake_core.execute(fake_config("synthetic_async", **kw), tmp_path)
    run_dir = results.Path(out["run_dir"])
    return out, pd.read_parquet(run_dir / "frames.parquet"), pd.read_parquet(run_dir / "updates.parquet")


def test01_three_clients_get_their_own_rows_paths_and_updates(fake_core, fake_config, tmp_path):
    out, frames, updates = _run(fake_core, fake_config, tmp_path, clients=3)
    assert sorted(frames["client"].unique()) == [0, 1, 2]
    assert frames.groupby("client").size().tolist() == [8, 8, 8]
    assert sorted(updates["client"].unique()) == [0, 1, 2]
    assert out["summary"]["clients"] == 3
    # each client shows updates made from its own poses: the images of the three clients differ
    last = frames[frames["frame"] == 7].set_index("client")["image_sha256"]
    assert last.nunique() == 3


def test02_the_server_sees_only_poses_that_arrived(fake_core, fake_config, tmp_path):
    _, frames, updates = _run(fake_core, fake_config, tmp_path, clients=3)
    for _, u in updates.iterrows():
        sent = frames[(frames["client"] == u["client"]) & (frames["frame"] == u["input_frame"])].iloc[0]
        # the update was made from the pose of the frame that sent it (its scene time), which arrived before
        # the update started: it is never the pose of a frame the client had not yet sent
        assert u["info_pose_t_s"] == pytest.approx(sent["t_s"])
        assert sent["start_s"] < u["start_s"]
    # what a client shows comes from an earlier pose than its own current one
    shown = frames.dropna(subset=["info_shown_pose_t_s"])
    assert len(shown) > 0 and (shown["info_shown_pose_t_s"] < shown["t_s"]).all()


def test03_a_narrow_shared_server_link_slows_every_client(fake_core, fake_config, tmp_path):
    # 3 clients, each update 20 kB; alone on 100 Mbit/s access links vs sharing a 2 Mbit/s server link
    _, wide, wide_u = _run(fake_core, fake_config, tmp_path / "wide", clients=3, frames=30)
    _, narrow, narrow_u = _run(fake_core, fake_config, tmp_path / "narrow", clients=3, frames=30,
                               server_net="bw=2mbps,delay=1ms")
    for c in range(3):
        assert narrow_u[narrow_u["client"] == c]["update_ms"].mean() > 3 * wide_u[wide_u["client"] == c][
            "update_ms"].mean()
    assert narrow["staleness_ms"].mean() > 2 * wide["staleness_ms"].mean()
    # a wide shared link changes nothing measurable
    _, wide2, wide2_u = _run(fake_core, fake_config, tmp_path / "wide2", clients=3, frames=30,
                             server_net="bw=10000mbps,delay=0ms")
    assert wide2_u["update_ms"].mean() == pytest.approx(wide_u["update_ms"].mean(), rel=0.05)


def test04_the_client_shows_what_it_decoded_from_delivered_bytes(fake_core, fake_config, tmp_path, monkeypatch):
    _, clean, _ = _run(fake_core, fake_config, tmp_path / "clean", clients=1)
    real = method_mod.deliver_bytes

    def corrupting(payload, size_bytes, lost_ranges):
        data = real(payload, size_bytes, lost_ranges)
        if data is None or len(data) < 4000:  # leave the 88-byte poses intact; corrupt the image updates
            return data
        return bytes(b ^ 0x5A for b in data[:64]) + data[64:]

    monkeypatch.setattr(method_mod, "deliver_bytes", corrupting)
    _, corrupt, _ = _run(fake_core, fake_config, tmp_path / "corrupt", clients=1)
    used = clean["update_index"] >= 0
    assert used.any()
    assert (clean.loc[used, "image_sha256"].values != corrupt.loc[used, "image_sha256"].values).all()
    assert (clean.loc[~used, "image_sha256"].values == corrupt.loc[~used, "image_sha256"].values).all()


def test05_server_code_cannot_read_a_clients_camera_path(fake_core):
    path = fake_core.load_scene("toy").camera
    client = ClientCamera(path, 0)
    server = ServerCamera(path, 0)
    assert np.allclose(client.pose_at(1.0).position, path.pose_at(1.0).position)
    with running_on("server"):
        with pytest.raises(SimulationError, match="server code read client 0's camera path"):
            client.pose_at(1.0)
        with pytest.raises(SimulationError, match="has received no pose"):
            server.pose_at(1.0)
        server.add(1.0, path.pose_at(1.0))
        assert np.allclose(server.pose_at(1.0).position, path.pose_at(1.0).position)


def test06_client_paths_are_distinct_deterministic_and_continuous(fake_core):
    path = fake_core.load_scene("toy").camera
    assert client_camera(path, 0, 4) is path
    paths = [client_camera(path, c, 4) for c in range(4)]
    at = [p.pose_at(1.0).position[0] for p in paths]
    assert len(set(np.round(at, 6))) == 4
    assert client_camera(path, 2, 4).pose_at(1.5).position.tolist() == paths[2].pose_at(1.5).position.tolist()
    # played back and forth: no jump where the path would wrap
    ts = np.linspace(0.0, 12.0, 1201)
    xs = np.array([paths[3].pose_at(t).position[0] for t in ts])
    assert np.abs(np.diff(xs)).max() < 0.02


def test07_prepare_is_shared_by_runs_that_differ_only_in_network_protocol_or_clients(fake_core, fake_config,
                                                                                   tmp_path):
    a, _, _ = _run(fake_core, fake_config, tmp_path, clients=1)
    b, _, _ = _run(fake_core, fake_config, tmp_path, clients=2, net="bw=50mbps,delay=20ms", protocol="udp")
    assert a["summary"]["prepare_reused"] is False and b["summary"]["prepare_reused"] is True
    assert a["summary"]["prepare_key"] == b["summary"]["prepare_key"]
    c, _, _ = _run(fake_core, fake_config, tmp_path, clients=1, seed=7)
    assert c["summary"]["prepare_reused"] is False
