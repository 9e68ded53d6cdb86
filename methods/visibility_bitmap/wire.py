"""The visibility bitmap on the wire: framed, checked slices of whole rows.

Seed 000 §4.3.1 sends the bare bitmap over TCP and the client "just awaits until (width * height * 4) bytes are
received": a corrupted or truncated transfer would be shaded from garbage, and seed 000 §5.2/§6.3 recommend UDP,
where datagrams get lost. Here every frame is sent as one or more **slices**, each a contiguous band of whole
bitmap rows with its own header:

======  =====  ===========================================================================
offset  type   field
======  =====  ===========================================================================
0       4s     magic ``b"SBVB"``
4       u8     format version (1)
5       u8     layout (0 paper32, 1 words32, 2 packed8; see :mod:`.bitmap`)
6       u8     codec base id (:data:`.codecs.BASE_IDS`)
7       u8     flags: bit 0 keyframe, bit 1 bit-plane transform, bit 2 temporal delta
8       u32    frame index
12      u32    width (pixels)
16      u32    height (pixels, whole frame)
20      u32    light count
24      u32    first row of this slice
28      u32    rows in this slice
32      u32    slice index
36      u32    slice count
40      u32    payload length (bytes)
44      u32    CRC-32 of the payload
48      u32    CRC-32 of bytes 0..47 (the header itself)
======  =====  ===========================================================================

All integers little-endian; the header is :data:`HEADER_BYTES` = 52 bytes. Every slice carries the whole frame's
geometry, so any slice alone can be decoded (losing the first datagram does not lose the frame).

TCP (seed 000's transport) sends one slice holding every row. UDP sends ``rows_per_slice`` rows per slice, each
slice encoded independently so that the loss of one slice never spoils another. The sender returns the byte
span of every slice in the message; the receiver maps lost byte ranges (from netsim) onto these spans, which
models datagrams that carry their slice number. A slice with any lost byte, a bad header CRC, a bad payload
CRC, a wrong geometry or a payload that does not decode is **missing**: its rows are repaired, never decoded.
Repair policies: ``previous`` (reuse the client's previous frame's bits for those rows; all lit when there is no
previous frame) or ``lit`` (treat every light as unobstructed in those rows).
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import codecs

MAGIC = b"SBVB"
VERSION = 1
_HEADER = struct.Struct("<4sBBBB10I")
HEADER_BYTES = _HEADER.size + 4
LAYOUT_IDS = {"paper32": 0, "words32": 1, "packed8": 2}
LAYOUT_NAMES = {v: k for k, v in LAYOUT_IDS.items()}
REPAIRS = ("previous", "lit")


@dataclass(frozen=True)
class SliceHeader:
    frame_index: int
    width: int
    height: int
    light_count: int
    layout: str
    codec_id: int
    flags: int
    first_row: int
    row_count: int
    slice_index: int
    slice_count: int
    payload_bytes: int
    payload_crc32: int

    @property
    def keyframe(self) -> bool:
        return bool(self.flags & codecs.FLAG_KEYFRAME)

    def to_bytes(self) -> bytes:
        body = _HEADER.pack(
            MAGIC, VERSION, LAYOUT_IDS[self.layout], self.codec_id, self.flags, self.frame_index, self.width,
            self.height, self.light_count, self.first_row, self.row_count, self.slice_index, self.slice_count,
            self.payload_bytes, self.payload_crc32,
        )
        return body + struct.pack("<I", zlib.crc32(body))


class BadSlice(ValueError):
    """A slice that fails a check; its rows must be repaired, not decoded."""


def parse_header(data: bytes) -> SliceHeader:
    """Parses and checks a slice header (magic, version, header CRC, known layout); raises :class:`BadSlice`."""
    if len(data) < HEADER_BYTES:
        raise BadSlice(f"truncated header: {len(data)} of {HEADER_BYTES} bytes")
    body = bytes(data[: _HEADER.size])
    (crc,) = struct.unpack_from("<I", data, _HEADER.size)
    if zlib.crc32(body) != crc:
        raise BadSlice("header CRC mismatch")
    magic, version, layout_id, codec_id, flags, *ints = _HEADER.unpack(body)
    if magic != MAGIC:
        raise BadSlice(f"bad magic {magic!r}")
    if version != VERSION:
        raise BadSlice(f"unsupported wire version {version}")
    if layout_id not in LAYOUT_NAMES:
        raise BadSlice(f"unknown layout id {layout_id}")
    (frame_index, width, height, light_count, first_row, row_count, slice_index, slice_count, payload_bytes,
     payload_crc32) = ints
    return SliceHeader(frame_index, width, height, light_count, LAYOUT_NAMES[layout_id], codec_id, flags,
                       first_row, row_count, slice_index, slice_count, payload_bytes, payload_crc32)


def slice_rows(height: int, rows_per_slice: int | None) -> list[tuple[int, int]]:
    """``[(first_row, row_count), ...]`` covering ``height`` rows; None or 0 → one slice (TCP)."""
    if not rows_per_slice or rows_per_slice >= height:
        return [(0, height)]
    if rows_per_slice < 0:
        raise UserError(f"rows per slice must be >= 0, got {rows_per_slice}")
    return [(r, min(rows_per_slice, height - r)) for r in range(0, height, rows_per_slice)]


@dataclass
class WireFrame:
    """One encoded frame: the message bytes and where each slice lies in it."""

    message: bytes
    spans: list[tuple[int, int]]  # (start, end) byte offsets of each slice in ``message``
    raw_bytes: int  # bitmap bytes before encoding (the paper's 8,294,400 at 1080p, paper32)
    keyframe: bool

    @property
    def nbytes(self) -> int:
        return len(self.message)


def _overlaps(span: tuple[int, int], lost: list[tuple[int, int]]) -> bool:
    start, end = span
    return any(a < end and b > start for a, b in lost)


class FrameEncoder:
    """Server side: ``(H, W, L)`` visibility → :class:`WireFrame` (seed 000 Alg. 3B-2 step 5, framed)."""

    def __init__(self, width: int, height: int, light_count: int, layout: str = "paper32",
                 codec: str = "none", rows_per_slice: int | None = None, keyframe_interval: int = 0):
        self.width, self.height, self.light_count, self.layout = width, height, light_count, layout
        self.bpp = bm.bytes_per_pixel(layout, light_count)
        self.spec = codecs.parse(codec)
        if keyframe_interval < 0:
            raise UserError(f"keyframe_interval must be >= 0, got {keyframe_interval}")
        self.keyframe_interval = keyframe_interval
        self.slices = slice_rows(height, rows_per_slice)
        self._encoders = [codecs.SliceEncoder(self.spec, n, width, self.bpp) for _, n in self.slices]
        self._frames_sent = 0

    def encode(self, visibility: np.ndarray, frame_index: int) -> WireFrame:
        if visibility.shape != (self.height, self.width, self.light_count):
            raise ValueError(f"visibility shape {visibility.shape} != {(self.height, self.width, self.light_count)}")
        raw = bm.pack(visibility, self.layout)
        return self.encode_bitmap(raw, frame_index)

    def encode_bitmap(self, raw: np.ndarray, frame_index: int) -> WireFrame:
        keyframe = self._frames_sent == 0 or (
            self.keyframe_interval > 0 and self._frames_sent % self.keyframe_interval == 0
        )
        self._frames_sent += 1
        flags = self.spec.flags | (codecs.FLAG_KEYFRAME if keyframe else 0)
        parts, spans, offset = [], [], 0
        for index, ((first, count), enc) in enumerate(zip(self.slices, self._encoders)):
            payload = enc.encode(raw[first : first + count], keyframe)
            header = SliceHeader(
                frame_index, self.width, self.height, self.light_count, self.layout,
                codecs.BASE_IDS[self.spec.base], flags, first, count, index, len(self.slices),
                len(payload), zlib.crc32(payload),
            )
            part = header.to_bytes() + payload
            parts.append(part)
            spans.append((offset, offset + len(part)))
            offset += len(part)
        return WireFrame(b"".join(parts), spans, int(raw.nbytes), keyframe)


@dataclass
class ReceivedFrame:
    """What the client shades from: never garbage. ``rows_ok[r]`` is False where row ``r`` was repaired."""

    frame_index: int
    bitmap: np.ndarray  # (H, W * bpp) uint8, repaired rows included
    visibility: np.ndarray  # (H, W, L) bool
    rows_ok: np.ndarray  # (H,) bool
    problems: list[str] = field(default_factory=list)

    @property
    def rows_missing(self) -> int:
        return int((~self.rows_ok).sum())

    @property
    def bad(self) -> bool:
        """True when no row of this frame arrived intact (the whole frame was repaired)."""
        return not bool(self.rows_ok.any()) and self.rows_ok.size > 0

    @property
    def status(self) -> str:
        return "ok" if self.rows_ok.all() else ("bad" if self.bad else "repaired")


class FrameDecoder:
    """Client side: message (+ lost byte ranges) → :class:`ReceivedFrame`, repairing what is missing."""

    def __init__(self, width: int, height: int, light_count: int, layout: str = "paper32",
                 repair: str = "previous"):
        if repair not in REPAIRS:
            raise UserError(f"unknown UDP repair '{repair}' (choose from {', '.join(REPAIRS)})")
        self.width, self.height, self.light_count, self.layout = width, height, light_count, layout
        self.bpp = bm.bytes_per_pixel(layout, light_count)
        self.repair = repair
        self._lit_row = bm.all_lit_row(width, light_count, layout)
        self._previous: np.ndarray | None = None
        # Per slice (first_row, row_count): its decoder and the last frame index it decoded.
        self._decoders: dict[tuple[int, int], tuple[codecs.CodecSpec, codecs.SliceDecoder, int]] = {}

    def _check(self, h: SliceHeader, payload: bytes) -> None:
        expect = (self.width, self.height, self.light_count, self.layout)
        if (h.width, h.height, h.light_count, h.layout) != expect:
            raise BadSlice(f"slice geometry {(h.width, h.height, h.light_count, h.layout)} != expected {expect}")
        if h.row_count == 0 or h.first_row + h.row_count > self.height:
            raise BadSlice(f"slice rows {h.first_row}+{h.row_count} outside 0..{self.height}")
        if len(payload) != h.payload_bytes:
            raise BadSlice(f"truncated payload: {len(payload)} of {h.payload_bytes} bytes")
        if zlib.crc32(payload) != h.payload_crc32:
            raise BadSlice("payload CRC mismatch")

    def _decode_slice(self, h: SliceHeader, payload: bytes) -> np.ndarray | None:
        try:
            spec = codecs.from_wire(h.codec_id, h.flags)
        except ValueError as exc:
            raise BadSlice(str(exc)) from None
        key = (h.first_row, h.row_count)
        entry = self._decoders.get(key)
        if entry is None or entry[0] != spec:
            entry = (spec, codecs.SliceDecoder(spec, h.row_count, self.width, self.bpp), -2)
        spec, decoder, last_index = entry
        if spec.temporal and not h.keyframe and h.frame_index != last_index + 1:
            decoder.lose()  # the reference frame of this slice never arrived
        try:
            rows = decoder.decode(payload, h.keyframe)
        except Exception as exc:  # noqa: BLE001 - any decoder failure means the slice cannot be trusted
            decoder.lose()
            self._decoders[key] = (spec, decoder, h.frame_index)
            raise BadSlice(f"payload does not decode: {exc}") from None
        self._decoders[key] = (spec, decoder, h.frame_index)
        return rows

    def decode(self, message: bytes, frame_index: int, spans: list[tuple[int, int]] | None = None,
               lost_ranges: list[tuple[int, int]] | tuple = ()) -> ReceivedFrame:
        """Decodes one frame's message.

        ``spans``: slice byte spans from the sender (UDP datagram framing); None parses the message as a TCP
        byte stream, slice after slice, until a header fails. ``lost_ranges``: ``[(start, end), ...]`` bytes
        of ``message`` that never arrived. ``frame_index``: the frame the client expects; slices of another
        frame are ignored.
        """
        out = np.empty((self.height, self.width * self.bpp), dtype=np.uint8)
        rows_ok = np.zeros(self.height, dtype=bool)
        problems: list[str] = []
        lost = list(lost_ranges)
        message = memoryview(message)  # slices below must not copy a megabyte-sized frame
        if spans is None:
            spans, offset = [], 0
            while offset < len(message):
                try:
                    h = parse_header(message[offset : offset + HEADER_BYTES])
                except BadSlice as exc:
                    problems.append(f"at byte {offset}: {exc}")
                    break
                spans.append((offset, offset + HEADER_BYTES + h.payload_bytes))
                offset = spans[-1][1]
        for span in spans:
            if _overlaps(span, lost):
                problems.append(f"slice at bytes {span[0]}..{span[1]} lost")
                continue
            part = message[span[0] : span[1]]
            try:
                h = parse_header(part)
                payload = part[HEADER_BYTES:]
                self._check(h, payload)
                if h.frame_index != frame_index:
                    raise BadSlice(f"slice of frame {h.frame_index}, expected {frame_index}")
                rows = self._decode_slice(h, payload)
            except BadSlice as exc:
                problems.append(f"slice at bytes {span[0]}..{span[1]}: {exc}")
                continue
            if rows is None:
                problems.append(f"rows {h.first_row}..{h.first_row + h.row_count}: temporal reference lost")
                continue
            out[h.first_row : h.first_row + h.row_count] = rows
            rows_ok[h.first_row : h.first_row + h.row_count] = True
        missing = ~rows_ok
        if missing.any():
            if self.repair == "previous" and self._previous is not None:
                out[missing] = self._previous[missing]
            else:
                out[missing] = self._lit_row
        # Slices whose rows were repaired lose their temporal reference (the server cannot know).
        for (first, count), (spec, dec, idx) in list(self._decoders.items()):
            if not rows_ok[first : first + count].all():
                dec.lose()
        self._previous = out  # never written again: the next frame decodes into a fresh array
        visibility = bm.unpack(out, self.width, self.light_count, self.layout)
        return ReceivedFrame(frame_index, out, visibility, rows_ok, problems)
