"""H.264 / HEVC low-latency video: encoder, RTP-like packetisation, decoder.

Used by the video-streaming baseline, by streamed placements of local renderers and by any method that sends
an image as video.

The encoder is x264/x265 through PyAV with cloud-gaming settings: no B-frames, ``tune=zerolatency`` (no
lookahead, one packet per frame), a fixed IDR interval or periodic intra refresh, and either a target bitrate
(with a one-frame VBV buffer, so a frame never waits for later bandwidth) or a constant rate factor. Slices are
capped at the datagram size (``slice-max-size``), so a lost datagram damages part of a frame, not all of it.

Packetisation follows RTP's single-NAL-unit and fragmentation-unit modes (RFC 6184 §5.6, §5.8): NAL units are
packed into datagrams of at most ``mtu_bytes``; a NAL unit larger than that is split into fragments. The
receiver gets the datagrams that arrived (their boundaries are the transport's framing), keeps every NAL unit
whose bytes all arrived, drops the rest, and hands what it has to the decoder, which conceals missing slices
from its reference frame as a real client's decoder does.
"""
from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

import numpy as np

from suite.errors import UserError

CODECS = {"h264": ("libx264", "h264"), "hevc": ("libx265", "hevc")}
# Per-datagram header: frame index (u32), NAL index in the frame (u16), NAL units in the frame (u16), fragment
# index (u16), fragment count (u16). It lets the receiver put fragments back together and know what is missing.
_HEADER = struct.Struct("<IHHHH")
HEADER_BYTES = _HEADER.size


def check_codec(name: str) -> str:
    import av

    if name not in CODECS:
        raise UserError(f"unknown video codec '{name}' (choose from {', '.join(CODECS)})")
    encoder, _ = CODECS[name]
    if encoder not in av.codecs_available:
        raise UserError(f"video codec '{name}' needs {encoder}, which this PyAV build does not have")
    return name


@dataclass
class Encoded:
    data: bytes          # Annex-B bitstream of one frame
    keyframe: bool


class Encoder:
    """One stream's encoder (the server keeps one per client)."""

    def __init__(self, codec: str, width: int, height: int, fps: float, bitrate_mbps: float, crf: float,
                 keyint: int, intra_refresh: bool, preset: str, slice_bytes: int):
        import av

        self.width, self.height = width + (width & 1), height + (height & 1)  # 4:2:0 needs even sizes
        encoder, _ = CODECS[codec]
        ctx = av.CodecContext.create(encoder, "w")
        ctx.width, ctx.height, ctx.pix_fmt = self.width, self.height, "yuv420p"
        from fractions import Fraction

        rate = Fraction(fps).limit_denominator(1000)
        ctx.framerate, ctx.time_base = rate, 1 / rate
        # One thread: the bitstream of x264/x265 depends on the thread count, and bytes must not vary by machine.
        ctx.thread_count = 1
        gop = max(1, int(keyint))
        if codec == "h264":
            params = [f"keyint={gop}", f"min-keyint={gop}", "scenecut=0", "repeat-headers=1", "bframes=0",
                      f"slice-max-size={int(slice_bytes)}", "sliced-threads=0"]
            if intra_refresh:
                params.append("intra-refresh=1")
            opts = {"preset": preset, "tune": "zerolatency", "x264-params": ":".join(params)}
        else:
            params = [f"keyint={gop}", f"min-keyint={gop}", "scenecut=0", "repeat-headers=1", "bframes=0",
                      "frame-threads=1", "pools=none", "log-level=error", f"slice-max-size={int(slice_bytes)}"]
            opts = {"preset": preset, "tune": "zerolatency", "x265-params": ":".join(params)}
        if bitrate_mbps > 0:
            kbps = int(round(bitrate_mbps * 1000))
            ctx.bit_rate = kbps * 1000
            # A VBV buffer of one frame: no frame may exceed its share of the link (low-latency rate control).
            buf = max(1, int(round(kbps / fps)))
            key = "x264-params" if codec == "h264" else "x265-params"
            opts[key] += f":vbv-maxrate={kbps}:vbv-bufsize={buf}"
        else:
            opts["crf"] = f"{crf:g}"
        ctx.options = opts
        ctx.open()
        self.ctx = ctx
        self.index = 0

    def encode(self, rgb8: np.ndarray) -> Encoded:
        import av

        h, w, _ = rgb8.shape
        padded = np.zeros((self.height, self.width, 3), np.uint8)
        padded[:h, :w] = rgb8
        frame = av.VideoFrame.from_ndarray(padded, format="rgb24").reformat(format="yuv420p")
        frame.pts = self.index
        self.index += 1
        packets = self.ctx.encode(frame)
        data = b"".join(bytes(p) for p in packets)
        return Encoded(data, any(p.is_keyframe for p in packets))


class Decoder:
    """One client's decoder."""

    def __init__(self, codec: str, width: int, height: int):
        import av

        self.width, self.height = width, height
        self.ctx = av.CodecContext.create(CODECS[codec][1], "r")
        self.ctx.thread_count = 1

    def decode(self, data: bytes) -> np.ndarray | None:
        """The decoded RGB frame, or None when the decoder produced no picture from ``data``."""
        import av

        if not data:
            return None
        try:
            frames = self.ctx.decode(av.Packet(bytes(data)))
        except av.error.FFmpegError:
            return None  # a bitstream too damaged to decode: the client keeps the previous picture
        if not frames:
            return None
        rgb = frames[-1].to_ndarray(format="rgb24")
        return np.ascontiguousarray(rgb[: self.height, : self.width])


# ----------------------------------------------------------------------------------------- packetisation

def nal_units(data: bytes) -> list[bytes]:
    """Splits an Annex-B bitstream into NAL units, each with its start code."""
    starts = []
    i, n = 0, len(data)
    while i + 3 <= n:
        if data[i] == 0 and data[i + 1] == 0 and (data[i + 2] == 1 or (i + 4 <= n and data[i + 2] == 0
                                                                         and data[i + 3] == 1)):
            starts.append(i)
            i += 3 if data[i + 2] == 1 else 4
        else:
            i += 1
    if not starts:
        return [data] if data else []
    return [data[a:b] for a, b in zip(starts, starts[1:] + [n])]


@dataclass
class Packetised:
    message: bytes
    spans: list          # (start, end) of every datagram in ``message``
    nal_count: int


def packetise(frame_index: int, data: bytes, mtu_bytes: int) -> Packetised:
    """Datagrams of at most ``mtu_bytes``: one NAL unit each, or fragments of one (RFC 6184 §5.8)."""
    payload_max = mtu_bytes - HEADER_BYTES
    if payload_max < 16:
        raise UserError(f"mtu_bytes {mtu_bytes} leaves no room for payload (header {HEADER_BYTES} bytes)")
    parts, spans, offset = [], [], 0
    nals = nal_units(data)
    for k, nal in enumerate(nals):
        count = max(1, -(-len(nal) // payload_max))
        for f in range(count):
            chunk = nal[f * payload_max:(f + 1) * payload_max]
            datagram = _HEADER.pack(frame_index & 0xFFFFFFFF, k, len(nals), f, count) + chunk
            parts.append(datagram)
            spans.append((offset, offset + len(datagram)))
            offset += len(datagram)
    return Packetised(b"".join(parts), spans, len(nals))


def reassemble(frame_index: int, message: bytes, spans, lost_ranges) -> tuple[bytes, int, int]:
    """The NAL units of ``frame_index`` whose every fragment arrived, in order: (bitstream, NAL units kept,
    NAL units lost). When no datagram of the frame arrived the receiver cannot know how many were sent, and the
    frame counts as lost whole (lost = -1)."""
    lost = list(lost_ranges)
    fragments: dict[int, dict[int, bytes]] = {}
    counts: dict[int, int] = {}
    total = -1
    for a, b in spans:
        if b - a <= HEADER_BYTES or any(s < b and e > a for s, e in lost):
            continue
        idx, k, n_nals, f, count = _HEADER.unpack_from(message, a)
        if idx != (frame_index & 0xFFFFFFFF) or k >= n_nals or f >= count:
            continue
        total = n_nals
        counts[k] = count
        fragments.setdefault(k, {})[f] = message[a + HEADER_BYTES:b]
    out = [b"".join(parts[f] for f in range(counts[k])) for k, parts in sorted(fragments.items())
           if len(parts) == counts[k]]
    kept = len(out)
    return b"".join(out), kept, (total - kept if total >= 0 else -1)


# ---------------------------------------------------------------------------------------------- colour

def to_video(img: np.ndarray, exposure: float) -> np.ndarray:
    """Linear radiance → the suite's display transform (exposure, sRGB) → 8-bit RGB."""
    from suite.core.metrics import to_display

    return np.clip(np.rint(to_display(img, exposure) * 255.0), 0, 255).astype(np.uint8)


def from_video(rgb8: np.ndarray, exposure: float) -> np.ndarray:
    """8-bit sRGB → linear radiance (the inverse display transform), so metrics see what the viewer saw.

    8-bit input is looked up in a table of the 256 values (:func:`_from_video_table`: the same float64 transform per
    value, so the same float32 results as transforming every pixel, in a tenth of the time: every decoded frame of a
    streamed method goes through here); other input is transformed pixel by pixel."""
    rgb8 = np.asarray(rgb8)
    if rgb8.dtype == np.uint8:
        return _from_video_table(float(exposure))[rgb8]
    return _from_video_values(rgb8.astype(np.float64), float(exposure))


def _from_video_values(values: np.ndarray, exposure: float) -> np.ndarray:
    import colour

    linear = colour.cctf_decoding(values / 255.0, function="sRGB")
    return (np.asarray(linear) / exposure).astype(np.float32)


@functools.lru_cache(maxsize=32)
def _from_video_table(exposure: float) -> np.ndarray:
    """(256,) float32: :func:`from_video` of every 8-bit value at ``exposure``."""
    table = _from_video_values(np.arange(256, dtype=np.float64), exposure)
    table.flags.writeable = False
    return table


# ------------------------------------------------------------------------------------------- streaming

def nal_types(codec: str, bitstream: bytes) -> set[int]:
    """The NAL unit types in an Annex-B bitstream (H.264: 5 bits after the start code; HEVC: 6 bits)."""
    types = set()
    for nal in nal_units(bitstream):
        i = 3 if nal[2] == 1 else 4
        if len(nal) > i:
            types.add(nal[i] & 0x1F if codec == "h264" else (nal[i] >> 1) & 0x3F)
    return types


def has_idr(codec: str, bitstream: bytes) -> bool:
    # H.264 IDR slice: NAL type 5 (ITU-T H.264 Table 7-1); HEVC IDR_W_RADL / IDR_N_LP: 19, 20 (H.265 Table 7-1).
    idr = {5} if codec == "h264" else {19, 20}
    return bool(nal_types(codec, bitstream) & idr)


# The parameters of a video stream, with their defaults and one line each (a method's config.toml repeats the
# defaults it uses in [defaults] and these lines in [doc]).
STREAM_DEFAULTS = {"codec": "h264", "bitrate_mbps": 20.0, "crf": 23.0, "keyint": 60, "intra_refresh": False,
                   "preset": "veryfast", "mtu_bytes": 1200, "exposure": 1.0}

# Declared outputs (Method.outputs) of a frame sent as video by :func:`stream_frame`.
STREAM_OUTPUTS = {"wire_bytes": "bytes of the encoded frame on the wire (with datagram headers under UDP)",
                  "video_bytes": "bytes of the encoded bitstream of the frame",
                  "keyframe": "the encoder made an IDR frame",
                  "nal_lost": "NAL units of the frame that did not arrive whole (-1: nothing of the frame arrived)",
                  "status": "ok | damaged (decoded, but it or a reference lost data) | frozen (previous picture "
                            "shown)"}


@dataclass
class StreamSettings:
    """How a stream is encoded and sent (:data:`STREAM_DEFAULTS`)."""

    codec: str = "h264"
    bitrate_mbps: float = 20.0
    crf: float = 23.0
    keyint: int = 60
    intra_refresh: bool = False
    preset: str = "veryfast"
    mtu_bytes: int = 1200
    exposure: float = 1.0

    @classmethod
    def from_params(cls, p: dict) -> "StreamSettings":
        """The settings from a method's parameters; a bad value is a one-line UserError."""
        s = cls(**{k: type(v)(p.get(k, v)) for k, v in STREAM_DEFAULTS.items()})
        check_codec(s.codec)
        if s.bitrate_mbps < 0 or not 0 <= s.crf <= 51:
            raise UserError(f"bitrate_mbps must be >= 0 and crf in 0..51, got {s.bitrate_mbps}, {s.crf}")
        if s.keyint < 1:
            raise UserError(f"keyint must be >= 1, got {s.keyint}")
        if s.intra_refresh and s.codec != "h264":
            raise UserError("intra_refresh is an x264 option; use codec = \"h264\"")
        if s.exposure <= 0:
            raise UserError(f"exposure must be > 0, got {s.exposure}")
        if s.mtu_bytes - HEADER_BYTES < 16:
            raise UserError(f"mtu_bytes {s.mtu_bytes} leaves no room for payload (header {HEADER_BYTES} bytes)")
        return s


@dataclass
class Sent:
    """What the server's side of :class:`Stream` put on the wire for one frame."""

    payload: bytes               # the message: the bitstream (TCP) or the datagrams (UDP)
    encoded: Encoded
    spans: list | None           # datagram boundaries in ``payload`` (UDP), the transport's framing


class Stream:
    """One client's video stream: the server's encoder and the client's decoder with what the client knows about
    damage. A sync method keeps one per client (its server stages encode, its client stages decode).

    Under UDP a lost datagram damages the slices it carried; the decoder conceals them from its reference picture,
    and the damage propagates through predicted frames until the next IDR frame (``keyint``) or, with
    ``intra_refresh``, until a full refresh cycle of ``keyint`` frames has arrived intact. A frame from which the
    decoder produces no picture leaves the previous one on screen (frozen)."""

    def __init__(self, settings: StreamSettings, width: int, height: int, fps: float):
        s = self.s = settings
        self.w, self.h = int(width), int(height)
        self.encoder = Encoder(s.codec, self.w, self.h, fps, s.bitrate_mbps, s.crf, s.keyint, s.intra_refresh,
                               s.preset, s.mtu_bytes - HEADER_BYTES)
        self.decoder = Decoder(s.codec, self.w, self.h)
        from_video(to_video(np.zeros((1, 1, 3), np.float32), 1.0), 1.0)  # loads the colour transforms untimed
        self._last: np.ndarray | None = None
        self._damaged = False
        self._clean_run = 0

    def send_side(self, image: np.ndarray, frame_index: int, udp: bool) -> Sent:
        """Server: display transform, encode, and (UDP) packetise one frame of linear radiance."""
        encoded = self.encoder.encode(to_video(image, self.s.exposure))
        if udp:
            packets = packetise(frame_index, encoded.data, self.s.mtu_bytes)
            return Sent(packets.message, encoded, packets.spans)
        return Sent(encoded.data, encoded, None)

    def receive_side(self, frame_index: int, data: bytes | None, complete: bool, lost_ranges, spans):
        """Client: (linear radiance shown, bitstream bytes decoded, facts for :data:`STREAM_OUTPUTS` less the
        sender's) from the delivered bytes of one frame's message."""
        if spans is not None:
            bitstream, _, nal_lost = reassemble(frame_index, data or b"", spans, lost_ranges)
        else:
            # TCP delivers the whole frame or, past the timeout, nothing the client waited for
            bitstream, nal_lost = (data, 0) if complete else (b"", -1)
        rgb = self.decoder.decode(bitstream)
        if nal_lost != 0:
            self._damaged, self._clean_run = True, 0
        elif has_idr(self.s.codec, bitstream):
            self._damaged, self._clean_run = False, 0
        else:
            self._clean_run += 1
            if self.s.intra_refresh and self._clean_run >= self.s.keyint:
                self._damaged = False  # a whole refresh wave arrived intact
        if rgb is None:
            status = "frozen"
            rgb = self._last if self._last is not None else np.zeros((self.h, self.w, 3), np.uint8)
        else:
            status = "damaged" if self._damaged else "ok"
            self._last = rgb
        return from_video(rgb, self.s.exposure), len(bitstream), {"nal_lost": int(nal_lost), "status": status}


def stream_frame(ctx, stream: Stream, image: np.ndarray, after=None, name: str = "video") -> np.ndarray:
    """Sends one server-rendered frame to the client as video, in the harness's stages (the context ``ctx`` of a
    sync frame; duck-typed, see docs/method-contract.md): ``encode`` on the server (after ``after``), the message
    ``name`` down through the network, ``decode`` on the client when it has arrived. Records
    :data:`STREAM_OUTPUTS` and returns what the client shows (linear radiance)."""
    w, h = stream.w, stream.h
    with ctx.stage("encode", place="server", after=after) as st:
        sent = stream.send_side(image, ctx.index, ctx.protocol == "udp")
        st.bytes = len(sent.payload)
        st.count(codec_bytes=w * h * 3 // 2 + len(sent.encoded.data))
    msg = ctx.send(name, sent.payload if sent.payload else b"\0", direction="down")
    with ctx.stage("decode", place="client", after=[name]) as st:
        out, decoded_bytes, facts = stream.receive_side(ctx.index, msg.data, msg.complete, msg.lost_ranges,
                                                        sent.spans)
        st.count(codec_bytes=w * h * 3 // 2 + decoded_bytes)
        st.bytes = decoded_bytes
        st.pixels = w * h
    ctx.record(wire_bytes=len(sent.payload), video_bytes=len(sent.encoded.data),
               keyframe=bool(sent.encoded.keyframe), **facts)
    return out
