"""Baseline: cloud-gaming video streaming, the foil every seed compares itself with.

The server renders the whole frame, encodes it as low-latency H.264 (or HEVC) and streams it; the client only
decodes and displays. Latency is input → render → encode → network → decode → display, one synchronous chain
per frame:

==========  ==================  =================================================================================
place       stage / message     what it does
==========  ==================  =================================================================================
up          ``pose``            the client's camera (the standard pose message, TCP)
server      ``server_receive``  decodes the pose; the server renders only poses it received
server      ``render``          the frame: ``renderer = "materials"`` (default), the suite's material kernel (direct
                                light from point and area lights, mirror / glass chains, glossy and alpha-tested
                                surfaces; suite.core.specular); ``renderer = "path"``, Mitsuba path tracing at
                                ``path_spp`` samples per pixel (:mod:`.pathtrace`)
server      ``denoise``         (path, ``path_denoise``) G-buffer and the shared a-trous filter (suite.core.denoise)
server      ``encode``          display transform to 8-bit sRGB, x264/x265 with zerolatency, no B-frames, slices
                                capped at the datagram size; under UDP, RTP-like datagrams (see :mod:`.video`)
down        ``video``           the encoded frame through netsim
client      ``decode``          reassembles the NAL units that arrived (UDP: a NAL unit with a lost fragment is
                                dropped), decodes, converts back to linear radiance for the metrics
==========  ==================  =================================================================================

The encode / send / decode part is :func:`suite.core.video.stream_frame` (shared with the streamed placement of
local renderers): under UDP a lost datagram damages the slices it carried, the damage propagates through
predicted frames until the next IDR frame or a full intra-refresh wave, and a frame the decoder makes no picture
from leaves the previous one on screen (frozen). Declared outputs count both.

The zero-latency run encodes and decodes too (the codec is part of the method) but over the ideal network.
"""
from __future__ import annotations

import numpy as np

from suite.errors import UserError
from suite.harness.method import Method

from suite.core import denoise, video

from methods.video_stream import pathtrace

RENDERERS = ("materials", "path")


class VideoStream(Method):
    name = "video_stream"
    mode = "sync"
    uses_network = True
    outputs = dict(video.STREAM_OUTPUTS)

    def __init__(self, params: dict):
        super().__init__(params)
        p = self.params
        self.stream_settings = video.StreamSettings.from_params(p)
        self.renderer = str(p.get("renderer", "materials"))
        if self.renderer not in RENDERERS:
            raise UserError(f"video_stream: unknown renderer '{self.renderer}' (choose from {', '.join(RENDERERS)})")
        # the material kernel is direct light with specular chains; the path tracer is global illumination
        self.light_transport = "global" if self.renderer == "path" else "direct"
        self.max_bounces = int(p.get("max_bounces", 2))
        self.area_samples = int(p.get("area_samples", 4))
        self.path_spp = int(p.get("path_spp", 4))
        self.path_max_depth = int(p.get("path_max_depth", 8))
        self.path_denoise = bool(p.get("path_denoise", True))
        self.atrous = denoise.AtrousSettings(iterations=int(p.get("path_atrous_iterations", 5)))
        if self.path_spp < 1 or self.path_max_depth < 1 or self.atrous.iterations < 0:
            raise UserError(f"path_spp and path_max_depth must be >= 1, path_atrous_iterations >= 0, got "
                            f"{self.path_spp}, {self.path_max_depth}, {self.atrous.iterations}")
        self.reset()

    def reset(self) -> None:
        self._stream: video.Stream | None = None

    def frame(self, ctx) -> np.ndarray:
        w, h = ctx.resolution
        pose_msg = ctx.send_pose(after=[])

        with ctx.stage("server_receive", place="server", after=["pose"]) as st:
            t_s, _ = ctx.receive_pose(pose_msg)
            st.bytes = pose_msg.size_bytes

        with ctx.stage("render", place="server") as st:
            if self.renderer == "path":
                traced = pathtrace.path_trace(ctx.scene, t_s, (w, h), self.path_spp, self.path_max_depth, ctx.seed)
                image = traced.noisy
                st.pixels = w * h * self.path_spp  # Mitsuba's rays are not the suite tracer's: samples count
            else:
                from suite.core.specular import render_materials

                image = render_materials(ctx.scene, ctx.tracer, t_s, (w, h), max_bounces=self.max_bounces,
                                         area_samples=self.area_samples, seed=ctx.seed).image
                st.pixels = w * h
        if self.renderer == "path" and self.path_denoise:
            with ctx.stage("denoise", place="server") as st:
                from suite.core.gbuffer import render_gbuffer

                g = render_gbuffer(ctx.scene, ctx.tracer, t_s, (w, h))
                image = pathtrace.denoise_frame(traced, g, self.atrous, getattr(ctx.tracer, "device", None))
                st.pixels = w * h
                st.count(taps=denoise.atrous_taps(w, h, self.atrous))

        if self._stream is None:
            fps = float(ctx.params.get("client_fps") or ctx.scene.camera.fps)
            self._stream = video.Stream(self.stream_settings, w, h, fps)
        return video.stream_frame(ctx, self._stream, image)
