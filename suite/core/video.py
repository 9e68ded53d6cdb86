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
    """8-bit sRGB → linear radiance (the inverse display transform), so metrics see what the viewer saw."""
    import colour

    linear = colour.cctf_decoding(rgb8.astype(np.float64) / 255.0, function="sRGB")
    return (np.asarray(linear) / float(exposure)).astype(np.float32)
