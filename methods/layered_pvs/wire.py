"""The UPDATE_SCENE message (seed 002 §5.1) on the wire: a header with the update's view, then named parts, each
with its length and CRC-32, so that a truncated or corrupt part is detected and named on the client.

Layout (little-endian)::

    magic "LPVS" | version u8 | flags u8 | update u32 | base i32 | layers u8 | full_layers u8 | tile u8 |
    width u16 | height u16 | fov_deg f64 | position, target, up 9 x f64 | exposure f32 | parts u8 |
    parts x (id u8, length u32, crc32 u32) | header crc32 u32 | part payloads in table order
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

MAGIC = b"LPVS"
VERSION = 1
PART_IDS = {"video": 1, "jpeg": 2, "mask": 3, "blocks": 4, "pvs": 5, "subsets": 6}
PART_NAMES = {v: k for k, v in PART_IDS.items()}

FLAG_KEY = 0x01            # full PVS (no base) and an IDR video frame
FLAG_RELOCATED = 0x02      # fragments were relocated (Algorithm 2): the client relocates them back
FLAG_LAYER_FIRST = 0x04    # tile order: layer-first (else block-first)
FLAG_MASK_RLE = 0x08       # pixel mask as RLE + Huffman (else binary quadtree)
FLAG_SUBSETS = 0x10        # triangle-subset masks present (§4.5.1)

_HEAD = struct.Struct("<4sBBIiBBBHHd9dfB")
_PART = struct.Struct("<BII")


class WireError(ValueError):
    """An update the client cannot use; the message names the update and the part."""


@dataclass
class Header:
    update: int
    base: int
    flags: int
    layers: int
    full_layers: int
    tile: int
    width: int
    height: int
    fov_deg: float
    pose: np.ndarray            # (3, 3): position, target, up
    exposure: float


@dataclass
class Message:
    header: Header
    parts: dict = field(default_factory=dict)     # name -> bytes


def encode(header: Header, parts: dict) -> bytes:
    table, body = [], []
    for name, data in parts.items():
        data = bytes(data)
        table.append(_PART.pack(PART_IDS[name], len(data), zlib.crc32(data)))
        body.append(data)
    head = _HEAD.pack(MAGIC, VERSION, header.flags, header.update, header.base, header.layers, header.full_layers,
                      header.tile, header.width, header.height, header.fov_deg,
                      *np.asarray(header.pose, np.float64).ravel(), header.exposure, len(table)) + b"".join(table)
    return head + struct.pack("<I", zlib.crc32(head)) + b"".join(body)


def decode(data: bytes | None, expected_update: int | None = None) -> Message:
    """Parses and checks a delivered update; raises :class:`WireError` naming what is wrong."""
    tag = f"update {expected_update}" if expected_update is not None else "update"
    if not data or len(data) < _HEAD.size + 4:
        raise WireError(f"{tag}: truncated header ({0 if not data else len(data)} bytes)")
    v = _HEAD.unpack_from(data)
    if v[0] != MAGIC or v[1] != VERSION:
        raise WireError(f"{tag}: bad magic or version (corrupt header)")
    n_parts = v[-1]
    end = _HEAD.size + n_parts * _PART.size
    if len(data) < end + 4:
        raise WireError(f"{tag}: truncated part table")
    (crc,) = struct.unpack_from("<I", data, end)
    if crc != zlib.crc32(data[:end]):
        raise WireError(f"{tag}: header checksum mismatch (corrupt header)")
    header = Header(update=v[3], base=v[4], flags=v[2], layers=v[5], full_layers=v[6], tile=v[7], width=v[8],
                    height=v[9], fov_deg=v[10], pose=np.asarray(v[11:20], np.float64).reshape(3, 3),
                    exposure=float(v[20]))
    tag = f"update {header.update}"
    pos = end + 4
    parts = {}
    for i in range(n_parts):
        pid, length, pcrc = _PART.unpack_from(data, _HEAD.size + i * _PART.size)
        name = PART_NAMES.get(pid, f"#{pid}")
        chunk = data[pos:pos + length]
        if len(chunk) < length:
            raise WireError(f"{tag}: part '{name}' truncated ({len(chunk)} of {length} bytes)")
        if zlib.crc32(chunk) != pcrc:
            raise WireError(f"{tag}: part '{name}' checksum mismatch (corrupt)")
        parts[name] = chunk
        pos += length
    return Message(header, parts)


def part_sizes(data: bytes | None) -> dict:
    """Part lengths from the (checked) part table, without checking the payloads; {} when the header is bad."""
    try:
        if not data or len(data) < _HEAD.size + 4:
            return {}
        v = _HEAD.unpack_from(data)
        end = _HEAD.size + v[-1] * _PART.size
        if len(data) < end + 4 or struct.unpack_from("<I", data, end)[0] != zlib.crc32(data[:end]):
            return {}
        return {PART_NAMES.get(p, f"#{p}"): n for p, n, _ in
                (_PART.unpack_from(data, _HEAD.size + i * _PART.size) for i in range(v[-1]))}
    except struct.error:
        return {}
