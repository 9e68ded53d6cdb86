"""The video baseline's codec path: packetisation round trips, losses damage slices until the next IDR frame,
and a lossless transport shows exactly what the zero-latency run shows."""
import numpy as np
import pandas as pd
import pytest

from suite.core import video
from methods.video_stream.method import VideoStream
from suite.errors import UserError


def _frames(n, w=96, h=64):
    x = np.linspace(0, 1, w)[None, :, None]
    return [np.clip((x + 0.02 * i) * np.ones((h, w, 3)), 0, 1).astype(np.float32) for i in range(n)]


def _encoder(w=96, h=64, keyint=4, **kw):
    kw.setdefault("bitrate_mbps", 0.0)
    return video.Encoder("h264", w, h, 30.0, kw["bitrate_mbps"], 23.0, keyint, False, "veryfast", 300)


def test01_packetise_then_reassemble_gives_the_bitstream_back():
    enc = _encoder()
    data = enc.encode(video.to_video(_frames(1)[0], 1.0)).data
    p = video.packetise(7, data, mtu_bytes=200)
    assert all(b - a <= 200 for a, b in p.spans) and p.spans[-1][1] == len(p.message)
    out, kept, lost = video.reassemble(7, p.message, p.spans, [])
    assert out == data and kept == p.nal_count and lost == 0
    # another frame's datagrams are ignored
    assert video.reassemble(8, p.message, p.spans, [])[1] == 0


def test02_a_lost_fragment_drops_its_whole_nal_unit():
    data = _encoder().encode(video.to_video(_frames(1)[0], 1.0)).data
    p = video.packetise(0, data, mtu_bytes=64)
    big = [k for k, nal in enumerate(video.nal_units(data)) if len(nal) > 64 - video.HEADER_BYTES][0]
    a, b = p.spans[sum(1 for nal in video.nal_units(data)[:big]
                       for _ in range(max(1, -(-len(nal) // (64 - video.HEADER_BYTES)))))]
    out, kept, lost = video.reassemble(0, p.message, p.spans, [(a + 2, a + 3)])
    assert lost == 1 and kept == p.nal_count - 1 and len(out) < len(data)
    # nothing arrived: the receiver cannot count what was sent
    assert video.reassemble(0, p.message, p.spans, [(0, len(p.message))]) == (b"", 0, -1)


def test03_encode_decode_is_deterministic_and_close_to_the_input():
    a, b = _encoder(), _encoder()
    dec = video.Decoder("h264", 96, 64)
    for img in _frames(3):
        x, y = a.encode(video.to_video(img, 1.0)), b.encode(video.to_video(img, 1.0))
        assert x.data == y.data
        rgb = dec.decode(x.data)
        assert rgb.shape == (64, 96, 3)
        assert np.abs(rgb.astype(int) - video.to_video(img, 1.0).astype(int)).mean() < 3.0


def test04_idr_frames_come_every_keyint_frames():
    enc = _encoder(keyint=3)
    flags = [video.has_idr("h264", enc.encode(video.to_video(img, 1.0)).data) for img in _frames(7)]
    assert flags == [True, False, False, True, False, False, True]


def test05_bad_parameters_are_one_line_errors():
    with pytest.raises(UserError, match="unknown video codec 'vp9'"):
        VideoStream({"codec": "vp9"})
    with pytest.raises(UserError, match="keyint must be >= 1"):
        VideoStream({"keyint": 0})
    with pytest.raises(UserError, match="intra_refresh is an x264 option"):
        VideoStream({"codec": "hevc", "intra_refresh": True})


def _run(tmp_path, net, protocol, frames=8, **params):
    from suite.harness import runner

    cfg = runner.make_config("video_stream", scene="living_room", resolution="64x36", frames=frames, net=net,
                             protocol=protocol, set_values=params, reference_spp=0, clock="work")
    out = runner.execute(cfg, tmp_path)
    return pd.read_parquet(f"{out['run_dir']}/frames.parquet")


def test06_lossless_tcp_shows_what_the_zero_latency_run_shows(tmp_path):
    frames = _run(tmp_path, "lan-home", "tcp", frames=3)
    assert (frames["info_status"] == "ok").all()
    assert (frames["zl_dssim"].dropna() == 0).all()


def test07_udp_loss_damages_frames_until_the_next_idr(tmp_path):
    frames = _run(tmp_path, "bw=50mbps,delay=5ms,loss=5%", "udp", frames=12, keyint=4, mtu_bytes=200)
    status, lost, key = frames["info_status"], frames["info_nal_lost"], frames["info_keyframe"]
    assert (lost != 0).any(), "5 % loss over 12 frames must hit some datagram"
    for i in range(len(frames)):
        if lost[i] != 0:
            assert status[i] in ("damaged", "frozen")
        if status[i] == "ok" and i > 0 and status[i - 1] != "ok":
            assert key[i], "damage heals only at an IDR frame"


@pytest.mark.parametrize("exposure", [1.0, 0.37, 2.5])
def test08_decoded_8bit_frames_become_the_linear_radiance_of_the_display_transform(exposure):
    """from_video looks 8-bit values up in a table: every value gives the bits of the sRGB decoding of that value,
    in any frame shape, and input that is not 8-bit is transformed pixel by pixel."""
    import colour

    values = np.arange(256, dtype=np.uint8)
    direct = (np.asarray(colour.cctf_decoding(values.astype(np.float64) / 255.0, function="sRGB"))
              / exposure).astype(np.float32)
    assert np.array_equal(video.from_video(values, exposure), direct)
    frame = np.random.default_rng(9).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    out = video.from_video(frame, exposure)
    assert out.dtype == np.float32 and out.shape == frame.shape and np.array_equal(out, direct[frame])
    assert np.array_equal(video.from_video(frame.astype(np.uint16), exposure), out)  # pixel by pixel: the same
    assert video.from_video(np.array([[[255, 0, 128]]], np.uint8), exposure)[0, 0, 0] == np.float32(1.0 / exposure)
