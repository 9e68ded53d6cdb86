"""Seed 002's lossless codecs decode exactly; 'any' pixels may take either value; corrupt input is refused."""
import struct

import numpy as np
import pytest

from methods.layered_pvs import codecs as c


def _ternary(rng, shape, p_any=0.3):
    m = (rng.random(shape) < 0.4).astype(np.int8)
    m[rng.random(shape) < p_any] = c.ANY
    m[: shape[0] // 3] = 1      # a solid region, so that the quadtree has leaves above the pixel level
    return m


def test01_huffman_round_trips_every_byte_distribution():
    rng = np.random.default_rng(0)
    for data in (b"", b"a", b"aaaa", bytes(range(256)) * 3, rng.integers(0, 7, 5000).astype(np.uint8).tobytes(),
                 rng.geometric(0.05, 20000).clip(0, 255).astype(np.uint8).tobytes()):
        assert c.huffman_decode(c.huffman_encode(data)) == data


def test02_huffman_truncated_stream_is_refused():
    enc = c.huffman_encode(np.random.default_rng(1).integers(0, 200, 4000).astype(np.uint8).tobytes())
    with pytest.raises(c.CodecError):
        c.huffman_decode(enc[: len(enc) // 2])


@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (64, 64), (40, 96)])
def test03_quadtree_and_rle_masks_decode_exactly_where_not_any(shape):
    rng = np.random.default_rng(shape[0] * 31 + shape[1])
    m = _ternary(rng, shape)
    known = m != c.ANY
    q = c.quadtree_decode(c.quadtree_encode(m), shape)
    r = c.binary_rle_decode(c.binary_rle_encode(m), m.size).reshape(shape)
    assert (q[known] == m[known]).all()
    assert (r[known] == m[known]).all()
    assert set(np.unique(q)) <= {0, 1} and set(np.unique(r)) <= {0, 1}


def test04_any_pixels_make_both_masks_smaller():
    rng = np.random.default_rng(3)
    m = np.zeros((64, 64), np.int8)
    m[:, :20] = 1
    m[rng.random(m.shape) < 0.02] ^= 1
    with_any = m.copy()
    with_any[:, 40:] = c.ANY
    with_any[rng.random(m.shape) < 0.3] = c.ANY
    assert len(c.quadtree_encode(with_any)) < len(c.quadtree_encode(m))
    assert len(c.binary_rle_encode(with_any)) < len(c.binary_rle_encode(m))


def test05_byte_rle_round_trips_long_runs():
    v = np.concatenate([np.zeros(1000, np.uint8), np.arange(50, dtype=np.uint8), np.full(300, 7, np.uint8)])
    assert (c.byte_rle_decode(c.byte_rle_encode(v), len(v)) == v).all()
    with pytest.raises(c.CodecError):
        c.byte_rle_decode(c.byte_rle_encode(v), len(v) + 1)


def test06_quadtree_truncated_is_refused():
    enc = c.quadtree_encode(_ternary(np.random.default_rng(5), (32, 32), 0.0))
    with pytest.raises(c.CodecError):
        c.quadtree_decode(enc[:-3])


def _scene_like(rng, n_vert=200, n_tri=400):
    positions = rng.random((n_vert, 3)).astype(np.float32)
    faces = rng.integers(0, n_vert, (n_tri, 3)).astype(np.int64)
    return positions, faces


def test07_pvs_patch_chain_reconstructs_every_pvs():
    rng = np.random.default_rng(7)
    positions, faces = _scene_like(rng)
    server, client = c.PVSState(), c.PVSState()
    for step in range(6):
        ids = np.sort(rng.choice(len(faces), size=rng.integers(0, 150), replace=False))
        patch, server = c.pvs_patch_encode(server, ids, faces, positions)
        client = c.pvs_patch_decode(client, patch)
        assert np.array_equal(client.triangles, positions[faces[ids]]), step
        assert np.array_equal(client.tri_vidx, server.tri_vidx) and np.array_equal(client.table, server.table)


def test08_pvs_patch_sends_shared_vertices_once_and_small_changes_cheaply():
    rng = np.random.default_rng(8)
    positions, faces = _scene_like(rng, 100, 2000)
    ids = np.arange(1500)
    full, st = c.pvs_patch_encode(c.PVSState(), ids, faces, positions)
    # Each of the 100 vertices is sent once (12 bytes), the rest are references: far below 36 bytes per triangle.
    assert len(full) < 0.5 * 36 * len(ids)
    diff, _ = c.pvs_patch_encode(st, np.arange(10, 1510), faces, positions)
    assert len(diff) < 0.1 * len(full)


def test09_pvs_patch_against_wrong_state_is_refused():
    rng = np.random.default_rng(9)
    positions, faces = _scene_like(rng)
    _, st = c.pvs_patch_encode(c.PVSState(), np.arange(50), faces, positions)
    patch, _ = c.pvs_patch_encode(st, np.arange(20, 80), faces, positions)
    with pytest.raises(c.CodecError):
        c.pvs_patch_decode(c.PVSState(), patch)


@pytest.mark.parametrize("shape", [(0, 0), (0, 5), (1, 1), (1, 70), (70, 1), (33, 65), (64, 64), (129, 40)])
@pytest.mark.parametrize("p_any", [0.0, 0.3, 1.0])
def test10_compiled_quadtree_codec_gives_the_reference_bytes_and_masks(shape, p_any):
    """The compiled quadtree encoder and decoder against their whole-level numpy twins: the same bytes, the same masks,
    the same refusal of a payload cut short or announcing too few or too many bits."""
    rng = np.random.default_rng(shape[0] * 131 + shape[1] + int(10 * p_any))
    m = _ternary(rng, shape, p_any) if shape[0] else np.zeros(shape, np.int8)
    enc = c.quadtree_encode(m)
    assert enc == c.quadtree_encode_reference(m)
    dec = c.quadtree_decode(enc, shape)
    assert dec.dtype == np.uint8 and np.array_equal(dec, c.quadtree_decode_reference(enc, shape))
    h, w, n = struct.unpack_from("<HHI", enc)
    broken = [enc[:-1], enc[:9]] + [struct.pack("<HHI", h, w, n + dn) + enc[8:] + b"\0" for dn in (-1, 1, -n)]

    def outcome(decode, payload):
        try:
            return "mask", decode(payload).tobytes()
        except c.CodecError as e:
            return "error", str(e)

    outcomes = [outcome(c.quadtree_decode, payload) for payload in broken]
    assert outcomes == [outcome(c.quadtree_decode_reference, payload) for payload in broken]
    assert sum(kind == "error" for kind, _ in outcomes) >= 2
