"""Framed slices: lossless round trip, corruption and truncation detected, UDP losses repaired by rows."""
import struct
import zlib

import numpy as np
import pytest

from methods.visibility_bitmap import wire
from suite.errors import UserError

H, W = 12, 10


def shadows(lights, t=0, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W]
    vis = np.stack([(xx + yy + l + t) % 5 > 1 for l in range(lights)], -1) if lights else np.zeros((H, W, 0), bool)
    return vis ^ (rng.random(vis.shape) < 0.02)


def needs(codec):
    """Skips the test when the codec's optional library is missing (python-lzo, lz4, zstandard, PyAV/libx264)."""
    from methods.visibility_bitmap.codecs import unavailable_reason

    reason = unavailable_reason(codec.split("+")[-1].split(":")[0])
    if reason:
        pytest.skip(f"codec {codec} unavailable: {reason}")


def pair(lights=3, layout="paper32", codec="none", rows_per_slice=None, repair="previous", keyframe_interval=0):
    needs(codec)
    enc = wire.FrameEncoder(W, H, lights, layout, codec, rows_per_slice, keyframe_interval)
    dec = wire.FrameDecoder(W, H, lights, layout, repair)
    return enc, dec


def test01_header_is_52_bytes_and_starts_with_magic():
    enc, _ = pair()
    msg = enc.encode(shadows(3), 0).message
    assert wire.HEADER_BYTES == 52 and msg[:4] == b"SBVB"
    assert len(msg) == 52 + H * W * 4


@pytest.mark.parametrize("codec", ["none", "lz4", "zstd", "delta+bitplane+zstd", "h264"])
@pytest.mark.parametrize("rows_per_slice", [None, 5])
@pytest.mark.parametrize("layout,lights", [("paper32", 3), ("words32", 33), ("packed8", 64), ("paper32", 0)])
def test02_lossless_transport_gives_the_exact_visibility_every_frame(codec, rows_per_slice, layout, lights):
    enc, dec = pair(lights, layout, codec, rows_per_slice, keyframe_interval=2)
    for t in range(3):
        vis = shadows(lights, t, seed=t)
        frame = enc.encode(vis, t)
        got = dec.decode(frame.message, t, frame.spans if rows_per_slice else None)
        assert got.status == "ok" and not got.problems
        assert np.array_equal(got.visibility, vis)


def test03_a_flipped_payload_byte_marks_the_frame_bad_and_it_is_not_shaded_from_garbage():
    enc, dec = pair(repair="lit")
    msg = bytearray(enc.encode(shadows(3), 0).message)
    msg[wire.HEADER_BYTES + 17] ^= 0x04
    got = dec.decode(bytes(msg), 0)
    assert got.bad and any("payload CRC" in p for p in got.problems)
    assert got.visibility.all()  # the "lit" repair, never the corrupted bits


def test04_a_truncated_message_is_detected():
    enc, dec = pair()
    msg = enc.encode(shadows(3), 0).message
    got = dec.decode(msg[:-7], 0)
    assert got.bad and any("truncated payload" in p for p in got.problems)
    got = dec.decode(msg[:30], 0)
    assert got.bad and any("truncated header" in p for p in got.problems)


def test05_a_flipped_header_byte_is_detected_by_the_header_crc():
    enc, dec = pair()
    msg = bytearray(enc.encode(shadows(3), 0).message)
    msg[13] ^= 0x01  # width
    got = dec.decode(bytes(msg), 0)
    assert got.bad and any("header CRC" in p for p in got.problems)


def test06_a_consistent_header_with_the_wrong_geometry_is_rejected():
    enc = wire.FrameEncoder(W, H, 4, "paper32", "none")
    _, dec = pair(lights=3)
    got = dec.decode(enc.encode(shadows(4), 0).message, 0)
    assert got.bad and any("geometry" in p for p in got.problems)


def test07_a_slice_of_another_frame_is_not_used():
    enc, dec = pair(repair="lit")
    msg = enc.encode(shadows(3), 5).message
    got = dec.decode(msg, 6)
    assert got.bad and any("frame 5" in p for p in got.problems)


def test08_lost_bytes_under_udp_miss_exactly_the_rows_of_the_slices_they_touch():
    enc, dec = pair(rows_per_slice=4, repair="lit")
    frame = enc.encode(shadows(3), 0)
    start, end = frame.spans[1]
    got = dec.decode(frame.message, 0, frame.spans, lost_ranges=[(start + 3, start + 4)])
    assert got.status == "repaired"
    assert got.rows_ok.tolist() == [True] * 4 + [False] * 4 + [True] * 4
    assert got.visibility[4:8].all() and np.array_equal(got.visibility[:4], shadows(3)[:4])


def test09_previous_repair_reuses_the_previous_frames_rows():
    enc, dec = pair(rows_per_slice=4, repair="previous")
    f0, f1 = shadows(3, 0, 1), shadows(3, 1, 2)
    dec.decode(enc.encode(f0, 0).message, 0)
    frame = enc.encode(f1, 1)
    got = dec.decode(frame.message, 1, frame.spans, lost_ranges=[frame.spans[2]])
    assert np.array_equal(got.visibility[8:], f0[8:]) and np.array_equal(got.visibility[:8], f1[:8])


def test10_previous_repair_without_a_previous_frame_falls_back_to_lit():
    enc, dec = pair(rows_per_slice=4, repair="previous")
    frame = enc.encode(shadows(3), 0)
    got = dec.decode(frame.message, 0, frame.spans, lost_ranges=[(0, len(frame.message))])
    assert got.bad and got.visibility.all()


def test11_temporal_codec_after_a_loss_repairs_the_slice_until_the_next_keyframe():
    enc, dec = pair(codec="delta+lz4", rows_per_slice=6, repair="lit", keyframe_interval=3)
    frames = [shadows(3, t, t) for t in range(4)]
    wf = [enc.encode(f, t) for t, f in enumerate(frames)]
    assert [f.keyframe for f in wf] == [True, False, False, True]
    dec.decode(wf[0].message, 0, wf[0].spans)
    lost = dec.decode(wf[1].message, 1, wf[1].spans, lost_ranges=[wf[1].spans[0]])
    assert lost.rows_ok.tolist() == [False] * 6 + [True] * 6
    after = dec.decode(wf[2].message, 2, wf[2].spans)  # arrived intact, but its delta reference is gone
    assert after.rows_ok.tolist() == [False] * 6 + [True] * 6
    assert any("temporal reference lost" in p for p in after.problems)
    key = dec.decode(wf[3].message, 3, wf[3].spans)
    assert key.status == "ok" and np.array_equal(key.visibility, frames[3])


def test12_unknown_repair_policy_is_a_user_error():
    with pytest.raises(UserError, match="unknown UDP repair"):
        wire.FrameDecoder(W, H, 3, "paper32", "zeros")


def test13_slices_cover_every_row_once():
    for height, rows in [(12, 5), (12, 4), (1, 8), (7, None), (7, 0)]:
        covered = [r for first, n in wire.slice_rows(height, rows) for r in range(first, first + n)]
        assert covered == list(range(height))


def test14_header_fields_round_trip():
    h = wire.SliceHeader(7, 640, 360, 33, "words32", 3, 5, 16, 8, 2, 45, 1234, 0xDEADBEEF)
    assert wire.parse_header(h.to_bytes()) == h
    body = h.to_bytes()
    assert struct.unpack_from("<I", body, 48)[0] == zlib.crc32(body[:48])
