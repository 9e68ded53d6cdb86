"""The streamed placement: the same renderer on the server for the pose the client sent, the frame sent as
low-latency video (suite.core.video) through the network and decoded on the client. Over a lossless network the
client shows the local image up to codec error; UDP loss damages frames until the next IDR frame."""
import glob

import pandas as pd
import pytest

from suite.errors import UserError
from suite.harness import registry, runner


def test01_streamed_puts_every_rendering_stage_on_the_server_and_uses_the_network():
    cls = registry.get("quake_drt").load()
    params = registry.get("quake_drt").params()
    streamed = cls({**params, "placement": "streamed"})
    assert streamed.uses_network is True and cls(params).uses_network is False
    assert {streamed.place(s) for s in ("primary", "direct", "asvgf_atrous", "taa")} == {"server"}
    with pytest.raises(UserError, match="keyint must be >= 1"):
        cls({**params, "placement": "streamed", "keyint": 0})
    with pytest.raises(UserError, match="unknown video codec 'vp9'"):
        cls({**params, "placement": "streamed", "codec": "vp9"})


def _execute(tmp_path, scene, variant, net="lan-home", protocol="tcp", frames=3, **sets):
    cfg = runner.make_config("quake_drt", scene=scene, resolution="48x27", frames=frames, net=net, protocol=protocol,
                             variant=variant, reference_spp=0, quality_every=1, clock="work",
                             set_values={"cull_audit_points": 0, **sets})
    out = runner.execute(cfg, tmp_path, force=True)
    return out["run_dir"], pd.read_parquet(f"{out['run_dir']}/frames.parquet")


def _image(run_dir, frame):
    from suite.core.imageio import read_exr

    return read_exr(glob.glob(f"{run_dir}/images/frame_{frame:04d}.exr")[0])


def test02_streamed_over_a_lossless_network_shows_the_local_image_up_to_codec_error(tmp_path, small_map):
    from suite.core.metrics import compare

    local_dir, local = _execute(tmp_path / "local", small_map, "default")
    stream_dir, streamed = _execute(tmp_path / "streamed", small_map, "streamed", crf=18.0, bitrate_mbps=0.0)
    assert (streamed["info_status"] == "ok").all() and (streamed["info_wire_bytes"] > 0).all()
    for i in range(3):
        a, b = _image(local_dir, i), _image(stream_dir, i)
        m = compare(a, b)
        assert 0 < m["dssim"] and m["psnr_db"] > 30.0, (i, m)  # codec error only: close, not identical
    # the latency chain: pose up, server render, encode, video down, decode on the client
    assert (streamed["net_pose_ms"] > 0).all() and (streamed["net_video_ms"] > 0).all()
    for col in ("stage_server_receive_ms", "stage_primary_ms", "stage_direct_ms", "stage_encode_ms",
                "stage_decode_ms"):
        assert col in streamed.columns
    assert (streamed["server_ms"] > 0).all() and "net_video_ms" not in local.columns
    ev = pd.read_parquet(f"{stream_dir}/events.parquet")
    place = dict(zip(ev["name"], ev["place"]))
    assert place["primary"] == place["asvgf_atrous"] == place["encode"] == "server" and place["decode"] == "client"
    # the rendering work is the local run's, moved to the server (same rays and taps per frame)
    assert list(streamed["rays"]) == list(local["rays"])


def test03_udp_loss_damages_streamed_frames_until_the_next_idr(tmp_path, small_map):
    _, f = _execute(tmp_path, small_map, "streamed", net="bw=50mbps,delay=5ms,loss=8%", protocol="udp", frames=8,
                    keyint=3, mtu_bytes=120)
    status, lost, key = f["info_status"], f["info_nal_lost"], f["info_keyframe"]
    assert (lost != 0).any(), "8 % loss over 8 frames of small datagrams must hit some"
    assert (status != "ok").sum() >= (lost != 0).sum()
    for i in range(len(f)):
        if lost[i] != 0:
            assert status[i] in ("damaged", "frozen")
        if status[i] == "ok" and i > 0 and status[i - 1] != "ok":
            assert key[i], "damage heals only at an IDR frame"
    # an undamaged frame is the lossless stream's frame (the zero-latency run); damage shows
    assert (f.loc[status == "ok", "zl_dssim"] == 0).all() and (f.loc[status != "ok", "zl_dssim"] > 0).any()
