"""Seed 004 §4.1 on the wire: requests, the full transfer, cell updates (id + irradiance triples, no indices),
LZF, and frames that a truncated or corrupt message cannot pass."""
import numpy as np
import pytest

from methods.rail import wire
from suite.core.scene.model import CameraPose


def _cells(n_cells=20, seed=0):
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 6, n_cells)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    E = rng.random((int(start[-1]), 3)) * 7.0
    return start, E


def test01_lzf_frames_round_trip_and_shrink_repetitive_bodies():
    raw = bytes(range(256)) * 40
    framed = wire.encode_frame(wire.KIND_UPDATE, 7, raw, compress=True)
    assert len(framed) < len(raw)
    assert wire.decode_frame(framed) == (wire.KIND_UPDATE, 7, raw)
    plain = wire.encode_frame(wire.KIND_UPDATE, 7, raw, compress=False)
    assert len(plain) == len(raw) + wire.HEADER.size and wire.decode_frame(plain)[2] == raw
    noise = np.random.default_rng(0).integers(0, 256, 500, np.uint8).tobytes()   # incompressible: sent raw
    assert wire.decode_frame(wire.encode_frame(wire.KIND_UPDATE, 1, noise))[2] == noise


@pytest.mark.parametrize("damage", ["truncate_body", "truncate_header", "flip_body", "zero_range", "empty"])
def test02_a_damaged_frame_is_rejected_whole(damage):
    framed = bytearray(wire.encode_frame(wire.KIND_UPDATE, 3, b"irradiance" * 100))
    if damage == "truncate_body":
        framed = framed[:-5]
    elif damage == "truncate_header":
        framed = framed[:10]
    elif damage == "flip_body":
        framed[-3] ^= 0x40
    elif damage == "zero_range":
        framed[wire.HEADER.size + 2:wire.HEADER.size + 12] = bytes(10)   # what a lost UDP range looks like
    else:
        framed = b""
    with pytest.raises(wire.WireError):
        wire.decode_frame(bytes(framed))


def test03_cells_round_trip_without_point_indices():
    start, E = _cells()
    scales, codes = wire.quantise(E, start)
    ids = np.flatnonzero(np.diff(start) > 0)[::2]
    body = wire.encode_cells(ids, scales[ids], codes, start)
    k = np.diff(start)[ids]
    assert len(body) == 4 + (6 * len(ids) + 3 * k.sum())   # cell id + scale + 3 bytes per point, nothing else
    got_ids, got_scales, pts, got_codes, end = wire.decode_cells(body, 0, start)
    assert end == len(body) and (got_ids == ids).all() and (got_scales == scales[ids]).all()
    assert (pts == np.concatenate([np.arange(start[c], start[c + 1]) for c in ids])).all()
    assert (got_codes == codes[pts]).all()
    back = wire.dequantise(np.repeat(got_scales, k), got_codes)
    rel = np.abs(back - E[pts]) / np.repeat(scales[ids].astype(float), k)[:, None]
    assert rel.max() < 0.02                                  # 8-bit gamma codes relative to the cell's scale
    with pytest.raises(wire.WireError):
        wire.decode_cells(body[:-1], 0, start)


def test04_requests_carry_camera_flags_and_light_changes():
    pose = CameraPose(np.array([1.0, 2, 3]), np.array([0.0, 2, 0]), np.array([0, 1.0, 0]))
    data = wire.encode_request(5, 0.25, pose, 75.0, {2: np.array([1.0, 2.0, 3.5], np.float32)}, flags=3)
    seq, t_s, got, fov, changes, flags = wire.decode_request(data)
    assert (seq, t_s, fov, flags) == (5, 0.25, 75.0, 3)
    assert np.allclose(got.position, pose.position) and list(changes) == [2]
    assert np.allclose(changes[2], [1.0, 2.0, 3.5])
    with pytest.raises(wire.WireError):
        wire.decode_request(data[:-4])


def test05_octahedral_normals_round_trip():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(1000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    back = wire.octahedral_decode(wire.octahedral_encode(n))
    assert np.abs(back - n).max() < 1e-5
