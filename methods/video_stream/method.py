"""Baseline: cloud-gaming video streaming, the foil every seed compares itself with.

The server renders the whole frame, encodes it as low-latency H.264 (or HEVC) and streams it; the client only
decodes and displays. Latency is input → render → encode → network → decode → display, one synchronous chain
per frame:

==========  ==================  =================================================================================
place       stage / message     what it does
==========  ==================  =================================================================================
up          ``pose``            the client's camera (the standard pose message, TCP)
server      ``server_receive``  decodes the pose; the server renders only poses it received
server      ``render``          the frame: the suite's material kernel (direct light from point and area lights,
                                mirror / glass chains, glossy and alpha-tested surfaces; suite.core.specular)
server      ``encode``          display transform to 8-bit sRGB, x264/x265 with zerolatency, no B-frames, slices
                                capped at the datagram size; under UDP, RTP-like datagrams (see :mod:`.video`)
down        ``video``           the encoded frame through netsim
client      ``decode``          reassembles the NAL units that arrived (UDP: a NAL unit with a lost fragment is
                                dropped), decodes, converts back to linear radiance for the metrics
==========  ==================  =================================================================================

Under UDP a lost datagram damages the slices it carried; the decoder conceals them from its reference picture,
and the damage propagates through predicted frames until the next IDR frame (``keyint``) or, with
``intra_refresh``, until a full refresh cycle of ``keyint`` frames has arrived intact. A frame from which the
decoder produces no picture leaves the previous one on screen (frozen). Declared outputs count both.

The zero-latency run encodes and decodes too (the codec is part of the method) but over the ideal network.
"""
from __future__ import annotations

import numpy as np

from suite.errors import UserError
from suite.harness.method import Method

from suite.core import video

STATUSES = ("ok", "damaged", "frozen")


def _nal_types(codec: str, bitstream: bytes) -> set[int]:
    types = set()
    for nal in video.nal_units(bitstream):
        i = 3 if nal[2] == 1 else 4
        if len(nal) > i:
            types.add(nal[i] & 0x1F if codec == "h264" else (nal[i] >> 1) & 0x3F)
    return types


def _has_idr(codec: str, bitstream: bytes) -> bool:
    # H.264 IDR slice: NAL type 5 (ITU-T H.264 Table 7-1); HEVC IDR_W_RADL / IDR_N_LP: 19, 20 (H.265 Table 7-1).
    idr = {5} if codec == "h264" else {19, 20}
    return bool(_nal_types(codec, bitstream) & idr)


class VideoStream(Method):
    name = "video_stream"
    mode = "sync"
    uses_network = True
    outputs = {"wire_bytes": "bytes of the encoded frame on the wire (with datagram headers under UDP)",
               "video_bytes": "bytes of the encoded bitstream of the frame",
               "keyframe": "the encoder made an IDR frame",
               "nal_lost": "NAL units of the frame that did not arrive whole (-1: nothing of the frame arrived)",
               "status": "ok | damaged (decoded, but it or a reference lost data) | frozen (previous picture shown)"}

    def __init__(self, params: dict):
        super().__init__(params)
        p = self.params
        self.codec = video.check_codec(str(p.get("codec", "h264")))
        self.bitrate_mbps = float(p.get("bitrate_mbps", 20.0))
        self.crf = float(p.get("crf", 23.0))
        if self.bitrate_mbps < 0 or not 0 <= self.crf <= 51:
            raise UserError(f"bitrate_mbps must be >= 0 and crf in 0..51, got {self.bitrate_mbps}, {self.crf}")
        self.keyint = int(p.get("keyint", 60))
        if self.keyint < 1:
            raise UserError(f"keyint must be >= 1, got {self.keyint}")
        self.intra_refresh = bool(p.get("intra_refresh", False))
        if self.intra_refresh and self.codec != "h264":
            raise UserError("intra_refresh is an x264 option; use codec = \"h264\"")
        self.preset = str(p.get("preset", "veryfast"))
        self.mtu_bytes = int(p.get("mtu_bytes", 1200))
        self.max_bounces = int(p.get("max_bounces", 2))
        self.area_samples = int(p.get("area_samples", 4))
        self.exposure = float(p.get("exposure", 1.0))
        if self.exposure <= 0:
            raise UserError(f"exposure must be > 0, got {self.exposure}")
        self.reset()

    def reset(self) -> None:
        self._encoder: video.Encoder | None = None
        self._decoder: video.Decoder | None = None
        self._last: np.ndarray | None = None
        self._damaged = False
        self._clean_run = 0

    def _fps(self, ctx) -> float:
        return float(ctx.params.get("client_fps") or ctx.scene.camera.fps)

    def frame(self, ctx) -> np.ndarray:
        w, h = ctx.resolution
        udp = ctx.protocol == "udp"
        fps = self._fps(ctx)
        pose_msg = ctx.send_pose(after=[])

        with ctx.stage("server_receive", place="server", after=["pose"]) as st:
            t_s, _ = ctx.receive_pose(pose_msg)
            st.bytes = pose_msg.size_bytes

        with ctx.stage("render", place="server") as st:
            from suite.core.specular import render_materials

            image = render_materials(ctx.scene, ctx.tracer, t_s, (w, h), max_bounces=self.max_bounces,
                                     area_samples=self.area_samples, seed=ctx.seed).image
            st.pixels = w * h

        if self._encoder is None:
            self._encoder = video.Encoder(self.codec, w, h, fps, self.bitrate_mbps, self.crf, self.keyint,
                                          self.intra_refresh, self.preset, self.mtu_bytes - video.HEADER_BYTES)
            self._decoder = video.Decoder(self.codec, w, h)
        with ctx.stage("encode", place="server") as st:
            encoded = self._encoder.encode(video.to_video(image, self.exposure))
            packets = video.packetise(ctx.index, encoded.data, self.mtu_bytes) if udp else None
            payload = packets.message if udp else encoded.data
            st.bytes = len(payload)
            st.count(codec_bytes=w * h * 3 // 2 + len(encoded.data))
        msg = ctx.send("video", payload if payload else b"\0", direction="down")

        with ctx.stage("decode", place="client", after=["video"]) as st:
            data = msg.data
            if udp:
                bitstream, _, nal_lost = video.reassemble(ctx.index, data, packets.spans, msg.lost_ranges)
            else:
                # TCP delivers the whole frame or, past the timeout, nothing the client waited for
                bitstream, nal_lost = (data, 0) if msg.complete else (b"", -1)
            rgb = self._decoder.decode(bitstream)
            st.count(codec_bytes=w * h * 3 // 2 + len(bitstream))
            st.bytes = len(bitstream)
            if nal_lost != 0:
                self._damaged, self._clean_run = True, 0
            elif _has_idr(self.codec, bitstream):
                self._damaged, self._clean_run = False, 0
            else:
                self._clean_run += 1
                if self.intra_refresh and self._clean_run >= self.keyint:
                    self._damaged = False  # a whole refresh wave arrived intact
            if rgb is None:
                status = "frozen"
                rgb = self._last if self._last is not None else np.zeros((h, w, 3), np.uint8)
            else:
                status = "damaged" if self._damaged else "ok"
                self._last = rgb
            out = video.from_video(rgb, self.exposure)
            st.pixels = w * h

        ctx.record(wire_bytes=len(payload), video_bytes=len(encoded.data), keyframe=bool(encoded.keyframe),
                   nal_lost=int(nal_lost), status=status)
        return out
