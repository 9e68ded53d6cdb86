"""RAIL's messages (seed 004 §4.1) as bytes: requests (camera + scene changes), the initial full transfer of G,
and irradiance updates (cell id + irradiance triples, no indices), LZF-compressed, in a frame with lengths and a
CRC-32 so that a truncated or corrupt message is rejected as a whole (:class:`WireError`).

Frame: ``RAIL`` magic, version, kind, flags (bit 0: body is LZF), sequence number, raw length, body length,
CRC-32 of the body, then the body. A request's sequence number is echoed by its response.

Irradiance section (the paper's record stores irradiance in 3 bytes): ``uint32`` cell count, then per cell its
``uint32`` id, a ``float16`` scale (the cell's largest channel value, rounded up) and, for the points the cell
contains in the deterministic order of Q, one 8-bit triple each: code = round(255 (E / scale)^(1/2.2)).
"""
from __future__ import annotations

import struct
import zlib

import numpy as np

try:
    import lzf
except ImportError:  # pragma: no cover - python-lzf is a dependency (pyproject.toml)
    lzf = None

from suite.harness.method import decode_pose, encode_pose

MAGIC = b"RAIL"
VERSION = 1
KIND_FULL, KIND_UPDATE, KIND_REQUEST = 1, 2, 3
FLAG_LZF = 1
HEADER = struct.Struct("<4sBBHIIII")
GAMMA = 2.2
_FULL_HEAD = struct.Struct("<I3ddI3ddI")
_CHANGE = np.dtype([("light", "<u2"), ("position", "<f4", (3,))])
_POSE_BYTES = 88


class WireError(ValueError):
    """A message that cannot be decoded (truncated, corrupt, wrong kind): the receiver rejects it whole."""


# ------------------------------------------------------------------------------------------------------- frames

def lzf_available() -> bool:
    return lzf is not None


def encode_frame(kind: int, seq: int, raw: bytes, compress: bool = True) -> bytes:
    body, flags = raw, 0
    if compress and raw:
        if lzf is None:
            raise RuntimeError("python-lzf is not installed (pip install python-lzf)")
        packed = lzf.compress(raw)
        if packed is not None and len(packed) < len(raw):  # None: LZF would not make it smaller
            body, flags = packed, FLAG_LZF
    return HEADER.pack(MAGIC, VERSION, kind, flags, seq & 0xFFFFFFFF, len(raw), len(body),
                       zlib.crc32(body)) + body


def decode_frame(data: bytes | None, expect_kind: int | None = None) -> tuple[int, int, bytes]:
    """(kind, seq, raw body); :class:`WireError` for anything but an intact frame."""
    if data is None or len(data) < HEADER.size:
        raise WireError(f"message of {0 if data is None else len(data)} bytes is shorter than the "
                        f"{HEADER.size}-byte header")
    magic, version, kind, flags, seq, raw_len, body_len, crc = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise WireError("bad magic or version")
    if expect_kind is not None and kind != expect_kind:
        raise WireError(f"message kind {kind}, expected {expect_kind}")
    body = bytes(data[HEADER.size:])
    if len(body) != body_len:
        raise WireError(f"body of {len(body)} bytes, header says {body_len} (truncated)")
    if zlib.crc32(body) != crc:
        raise WireError("CRC-32 mismatch (corrupt body)")
    if flags & FLAG_LZF:
        try:
            raw = lzf.decompress(body, raw_len)
        except Exception as exc:  # the LZF stream itself is damaged
            raise WireError(f"LZF: {exc}") from None
        if raw is None or len(raw) != raw_len:
            raise WireError("LZF body does not decompress to the stated length")
    else:
        raw = body
        if len(raw) != raw_len:
            raise WireError("raw length mismatch")
    return kind, seq, bytes(raw)


# ----------------------------------------------------------------------------------------------------- requests

def encode_request(seq: int, t_s: float, pose, fov_deg: float, changes: dict, flags: int = 0) -> bytes:
    """Camera (the suite's standard pose record), request flags and scene changes: {light index: position}."""
    ch = np.zeros(len(changes), _CHANGE)
    for k, (li, pos) in enumerate(sorted(changes.items())):
        ch[k] = (li, pos)
    raw = encode_pose(t_s, pose, fov_deg) + struct.pack("<BH", flags, len(ch)) + ch.tobytes()
    return encode_frame(KIND_REQUEST, seq, raw, compress=False)


def decode_request(data: bytes):
    """(seq, t_s, pose, fov_deg, {light: position}, flags)."""
    _, seq, raw = decode_frame(data, KIND_REQUEST)
    if len(raw) < _POSE_BYTES + 3:
        raise WireError("request too short")
    t_s, pose, fov = decode_pose(raw[:_POSE_BYTES])
    flags, n = struct.unpack_from("<BH", raw, _POSE_BYTES)
    body = raw[_POSE_BYTES + 3:]
    if len(body) != n * _CHANGE.itemsize:
        raise WireError("request change list has the wrong length")
    ch = np.frombuffer(body, _CHANGE)
    return seq, t_s, pose, fov, {int(c["light"]): np.asarray(c["position"], np.float64) for c in ch}, int(flags)


# ------------------------------------------------------------------------------------------ irradiance encoding

def quantise(E: np.ndarray, cell_start: np.ndarray):
    """Per-cell float16 scales and 8-bit codes (points sorted by cell; ``cell_start`` (C + 1) indexes them).
    Returns (scales (C,) float16, codes (N, 3) uint8)."""
    E = np.maximum(np.asarray(E, np.float64), 0.0)
    per_point = E.max(axis=1)
    counts = np.diff(cell_start)
    owner = np.repeat(np.arange(len(counts)), counts)
    cell_max = np.zeros(len(counts))
    np.maximum.at(cell_max, owner, per_point)
    scale = cell_max.astype(np.float16)
    low = scale.astype(np.float64) < cell_max
    scale[low] = np.nextafter(scale[low], np.float16(np.inf))
    s = scale.astype(np.float64)[owner]
    codes = np.where(s[:, None] > 0, np.round(255.0 * (E / np.where(s > 0, s, 1.0)[:, None]) ** (1.0 / GAMMA)), 0)
    return scale, np.clip(codes, 0, 255).astype(np.uint8)


def dequantise(scale, codes) -> np.ndarray:
    return (np.asarray(scale, np.float64)[:, None] * (np.asarray(codes, np.float64) / 255.0) ** GAMMA)


def encode_cells(cell_ids, scales, codes, cell_start) -> bytes:
    """§4.1 response body: per cell its id, scale and the irradiance triples of its points (no indices)."""
    cell_ids = np.asarray(cell_ids, np.int64)
    k = (cell_start[cell_ids + 1] - cell_start[cell_ids]).astype(np.int64)
    seg = 6 + 3 * k
    off = 4 + np.concatenate([[0], np.cumsum(seg)[:-1]]).astype(np.int64)
    buf = np.zeros(4 + int(seg.sum()), np.uint8)
    buf[:4] = np.frombuffer(struct.pack("<I", len(cell_ids)), np.uint8)
    if len(cell_ids):
        buf[off[:, None] + np.arange(4)] = cell_ids.astype("<u4").view(np.uint8).reshape(-1, 4)
        buf[off[:, None] + 4 + np.arange(2)] = np.asarray(scales, np.float16).astype("<f2").view(np.uint8).reshape(-1, 2)
        pts = np.concatenate([np.arange(cell_start[c], cell_start[c + 1]) for c in cell_ids])
        first = np.repeat(off + 6, 3 * k)
        within = np.arange(int(3 * k.sum())) - np.repeat(np.cumsum(3 * k) - 3 * k, 3 * k)
        buf[first + within] = codes[pts].reshape(-1)
    return buf.tobytes()


def decode_cells(raw: bytes, offset: int, cell_start: np.ndarray):
    """(cell ids, scales, points (P,), codes (P, 3), end offset); WireError on any inconsistency."""
    n_cells = len(cell_start) - 1
    if len(raw) < offset + 4:
        raise WireError("irradiance section truncated")
    (n,) = struct.unpack_from("<I", raw, offset)
    pos = offset + 4
    ids = np.zeros(n, np.int64)
    scales = np.zeros(n, np.float16)
    starts = np.zeros(n, np.int64)
    for i in range(n):
        if pos + 6 > len(raw):
            raise WireError("irradiance section truncated")
        cid, = struct.unpack_from("<I", raw, pos)
        if cid >= n_cells:
            raise WireError(f"cell id {cid} outside the grid of {n_cells} cells")
        ids[i] = cid
        scales[i] = np.frombuffer(raw, "<f2", 1, pos + 4)[0]
        starts[i] = pos + 6
        pos += 6 + 3 * int(cell_start[cid + 1] - cell_start[cid])
    if pos > len(raw):
        raise WireError("irradiance section truncated")
    if not np.isfinite(scales.astype(np.float64)).all() or (scales.astype(np.float64) < 0).any():
        raise WireError("invalid irradiance scale")
    k = (cell_start[ids + 1] - cell_start[ids]).astype(np.int64)
    pts = np.concatenate([np.arange(cell_start[c], cell_start[c + 1]) for c in ids]) if n else np.zeros(0, np.int64)
    arr = np.frombuffer(raw, np.uint8)
    src = np.repeat(starts, 3 * k) + (np.arange(int(3 * k.sum())) - np.repeat(np.cumsum(3 * k) - 3 * k, 3 * k))
    codes = arr[src].reshape(-1, 3)
    return ids, scales, pts, codes, pos


# --------------------------------------------------------------------------------------------- full transfer

def octahedral_encode(n: np.ndarray) -> np.ndarray:
    """Unit normals to 2 float32 each (the paper's 8-byte normals)."""
    n = np.asarray(n, np.float64)
    p = n[:, :2] / np.abs(n).sum(axis=1, keepdims=True)
    neg = n[:, 2] < 0
    folded = (1.0 - np.abs(p[:, ::-1])) * np.where(p >= 0, 1.0, -1.0)
    return np.where(neg[:, None], folded, p).astype(np.float32)


def octahedral_decode(e: np.ndarray) -> np.ndarray:
    e = np.asarray(e, np.float64)
    z = 1.0 - np.abs(e).sum(axis=1)
    xy = np.where((z < 0)[:, None], (1.0 - np.abs(e[:, ::-1])) * np.where(e >= 0, 1.0, -1.0), e)
    n = np.column_stack([xy, z])
    return (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)


def encode_full(points, grid_geometry, ambient_geometry, irradiance_section: bytes) -> bytes:
    """Body of the initial transfer of G (§4.1): grid geometries, the records as structure of arrays
    (position, normal, range, AO weight) and every cell's irradiance."""
    n = len(points)
    head = _FULL_HEAD.pack(n, *grid_geometry.origin, grid_geometry.cell_m, grid_geometry.cells,
                           *ambient_geometry.origin, ambient_geometry.cell_m, ambient_geometry.cells)
    return b"".join([head, np.asarray(points.position, "<f4").tobytes(),
                     octahedral_encode(points.normal).astype("<f4").tobytes(),
                     np.asarray(points.range_m, "<f2").tobytes(),
                     np.round(np.clip(points.ao, 0, 1) * 255).astype(np.uint8).tobytes(), irradiance_section])


def decode_full(raw: bytes):
    """(n, grid (origin, cell_m, cells), ambient (origin, cell_m, cells), position, normal, range, ao, offset of
    the irradiance section)."""
    if len(raw) < _FULL_HEAD.size:
        raise WireError("full transfer truncated")
    v = _FULL_HEAD.unpack_from(raw)
    n = v[0]
    sizes = [12 * n, 8 * n, 2 * n, n]
    end = _FULL_HEAD.size + sum(sizes)
    if len(raw) < end or v[5] <= 0 or v[10] <= 0 or not (0 < v[4] and 0 < v[9]):
        raise WireError("full transfer truncated or invalid")
    off = _FULL_HEAD.size
    pos = np.frombuffer(raw, "<f4", 3 * n, off).reshape(n, 3).copy()
    off += sizes[0]
    nrm = octahedral_decode(np.frombuffer(raw, "<f4", 2 * n, off).reshape(n, 2))
    off += sizes[1]
    rng = np.frombuffer(raw, "<f2", n, off).astype(np.float32)
    off += sizes[2]
    ao = np.frombuffer(raw, np.uint8, n, off).astype(np.float32) / 255.0
    off += sizes[3]
    return n, (v[1:4], v[4], v[5]), (v[6:9], v[9], v[10]), pos, nrm, rng, ao, off
