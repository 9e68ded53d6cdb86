"""Seed 000: hybrid rendering with a server-traced visibility bitmap (Algorithms 3A, 3B-1, 3B-2).

Per client frame (synchronous, seed 000 Figure 7):

==========  ==================  =================================================================================
place       stage / message     what it does
==========  ==================  =================================================================================
up          ``inputs``          camera position/target/up and scene time; the resolution on the first frame
                                (seed 000 §4.3, §4.3.1, Alg. 3B-1 step 1); always TCP
client      ``client_gbuffer``  the client's G-buffer; no dependency, so it overlaps the server's work (Fig. 7)
server      ``server_receive``  parses the inputs (Alg. 3B-2 step 1)
server      ``server_gbuffer``  the server's own G-buffer of the same view (Alg. 3B-2 step 2)
server      ``visibility``      one shadow ray per pixel and light; bit i set when light i is unobstructed,
                                packed into the bitmap layout (Alg. 3B-2 steps 3-4, §3.2)
server      ``gpu_to_cpu``      modelled read-back of the raw bitmap (§4.4.3; Fig. 10: 13.24 ms at 1080p)
server      ``encode``          codec + framing (header with CRCs; UDP: slices of rows) (§4.5.3)
down        ``bitmap``          the framed bitmap through netsim (Alg. 3B-2 step 5 / 3B-1 step 3)
client      ``receive_bitmap``  checks headers and CRCs, decodes, repairs missing rows (never shades garbage)
client      ``cpu_to_gpu``      modelled upload of the raw bitmap (§4.4.3; Fig. 10: 4.14 ms at 1080p)
client      ``shading``         Lambertian point lights with the bitmap as k_shadow (§3.1, Alg. 3B-1 step 4),
                                optional ambient term where all k_shadow = 0 (§5.1, Fig. 9)
client      ``output``          copies the shaded image to the output (Fig. 10's output pass)
==========  ==================  =================================================================================

On a Mitsuba backend with a device path (``mitsuba-llvm``, ``mitsuba-cuda``; :mod:`suite.core.device`) both
G-buffers, the visibility pass, the packing and the shading run as Dr.Jit kernels and their data stays on the device:
the packed bitmap is read back at the end of ``visibility`` (the encoder needs it in host memory), the client uploads
the received bitmap as it is in ``shading``, and ``output`` is the read-back of the image (its bytes recorded). The
bits and images are those of the host path (Embree keeps it).

Seed 000 shades point lights on Lambertian surfaces only (§3.1, Algorithm 3A). Emissive triangles show their own
radiance where seen but light nothing, and other materials are shaded as Lambertian with their albedo: a scene with
either says so (:meth:`VisibilityBitmap.omissions`: a warning and the summary's ``omitted``), and a scene lit by
emissive triangles alone (cornell) is refused.

The zero-latency run is the paper's standalone mode (§4.5.1, Algorithm 3A): G-buffer, visibility and shading
on one machine, with no network, memory-transfer, packing or codec passes. With a lossless transport and any
codec here (all are lossless) the distributed image is bit-identical to it.

Parameters (``config.toml`` [defaults]; ``--set key=value``):

``layout`` (str, ``"paper32"``)
    Bitmap layout: ``paper32`` (one uint32 per pixel, ≤ 32 lights, the paper's), ``words32`` (⌈L/32⌉ uint32 per
    pixel; lifts the §6.2 limit), ``packed8`` (⌈L/8⌉ bytes per pixel: only what the scene needs).
``codec`` (str, ``"none"``)
    Wire codec ``[delta+][bitplane+]BASE`` with BASE one of ``none``, ``lzo``, ``lz4``, ``zstd[:LEVEL]``,
    ``h264`` (lossless libx264); see :mod:`.codecs`. Encoding runs on the server, decoding on the client.
``keyframe_interval`` (int, ``30``)
    Temporal codecs (``delta+``, ``h264``) send a keyframe every this many frames (0: only the first). Under
    UDP it bounds how long a lost slice stays unrecoverable.
``udp_slice_rows`` (int, ``8``)
    Under ``--protocol udp``: bitmap rows per independently decodable slice. A lost datagram costs the slices
    it touches. Under TCP the frame is one slice.
``udp_repair`` (str, ``"previous"``)
    What the client shows for rows it did not receive intact: ``previous`` (reuse the previous frame's bits for
    those rows; all lit before any frame arrived) or ``lit`` (every light unobstructed). Also applies to a TCP
    frame that fails its CRC or does not arrive before the message timeout.
``ambient`` (bool, ``false``) and ``ambient_radiance`` (float, ``0.02``)
    Seed 000 §5.1 / Figure 9: add ``ambient_radiance · ρ`` where every k_shadow = 0. The paper tunes the value
    per scene; the default suits the embedded scenes' light intensities.
``gpu_to_cpu_mb_per_s`` (float, ``626.5``) and ``cpu_to_gpu_mb_per_s`` (float, ``2003.5``)
    Effective bandwidths (1 MB = 1e6 bytes) of the modelled memory transfers. The defaults are what seed 000
    Figure 10 implies (8,294,400 bytes in 13.24 ms and 4.14 ms); the ``pcie3`` variant uses the nominal
    PCIe 3.0 ×16 rate, 15,754 MB/s. See :mod:`.transfer`.
``transfer_latency_ms`` (float, ``0.0``)
    Fixed cost added to each modelled memory transfer.

Per-frame facts beyond the harness's columns are the declared :attr:`VisibilityBitmap.outputs` (raw and wire
bytes, keyframe, rows repaired, frame status, problems found); the results store keeps them as ``info_<key>``
columns.

The report section "Seed 000 — visibility bitmap" (:mod:`.report`) reads the runs of ``[presets.quick]`` /
``[presets.full]`` and the figures stored by ``splitbench bench visibility_bitmap`` (:mod:`.bench`: visibility
pass against raw occluded-ray throughput, server work against pixels × lights, bytes and codecs against
resolution and light count).
"""
from __future__ import annotations

import struct

import numpy as np

from suite.core.scene.model import CameraPose
from suite.errors import UserError
from suite.harness.method import Method

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import codecs, transfer, wire

# Inputs message (up): scene time, then camera position, target, up as float64 (seed 000 §4.3.1 sends three
# float3; doubles keep the server's view bit-identical to the client's), then the resolution on the first frame.
_INPUTS = struct.Struct("<d9d")
_RESOLUTION = struct.Struct("<II")


def encode_inputs(t_s: float, pose, resolution: tuple[int, int] | None) -> bytes:
    body = _INPUTS.pack(float(t_s), *np.asarray(pose.position, np.float64), *np.asarray(pose.target, np.float64),
                        *np.asarray(pose.up, np.float64))
    return body + (_RESOLUTION.pack(*resolution) if resolution is not None else b"")


def decode_inputs(data: bytes) -> tuple[float, np.ndarray, tuple[int, int] | None]:
    values = _INPUTS.unpack_from(data)
    resolution = _RESOLUTION.unpack_from(data, _INPUTS.size) if len(data) >= _INPUTS.size + _RESOLUTION.size else None
    return values[0], np.asarray(values[1:], np.float64).reshape(3, 3), resolution


def visibility_pass(g, lights, tracer, layout: str):
    """The server's visibility pass (seed 000 Alg. 3B-2 steps 3-4, §4.4.2): one shadow ray per pixel and light
    from the G-buffer position, then bit i of the pixel's record = light i unobstructed.

    Host G-buffer: returns the ``(H, W, L)`` bool visibility and the packed bitmap (:func:`.bitmap.pack`).
    Device G-buffer (:class:`suite.core.device.DeviceGBuffer`, Mitsuba llvm/cuda): the rays are generated, traced
    and their bits accumulated in one Dr.Jit kernel per 32 lights and packed on the device; returns the
    :class:`suite.core.device.DeviceVisibility` and the :class:`.bitmap.DeviceBitmap` (``to_host()`` is the
    read-back). The bits are the same on both paths. This is exactly what the ``visibility`` stage times, and what
    ``splitbench bench visibility_bitmap`` compares with the backend's raw occluded-ray throughput.
    """
    from suite.core.device.gbuffer import DeviceGBuffer
    from suite.core.shading import point_light_visibility

    visibility = point_light_visibility(g, lights, tracer)
    if isinstance(g, DeviceGBuffer):
        return visibility, bm.pack_device(visibility, layout)
    return visibility, bm.pack(visibility, layout)


def _gbuffer(scene, tracer, t_s, resolution, prev_t_s):
    """The G-buffer a stage works on: on the tracer's device when it has one (Mitsuba llvm/cuda; nothing is copied
    to the host), else the host G-buffer (Embree)."""
    from suite.core.gbuffer import has_device, render_gbuffer, render_gbuffer_device

    if has_device(tracer):
        return render_gbuffer_device(scene, tracer, t_s, resolution, prev_t_s)
    return render_gbuffer(scene, tracer, t_s, resolution=resolution, prev_t_s=prev_t_s)


def _to_output(rgb, st) -> np.ndarray:
    """The output pass: the shaded image copied to the output buffer (on the device path the read-back to host
    memory, whose bytes the stage records)."""
    if isinstance(rgb, np.ndarray):
        return np.array(rgb, dtype=np.float32, copy=True)
    out, nbytes = rgb.to_host(with_bytes=True)
    st.bytes = nbytes
    return out


class VisibilityBitmap(Method):
    """Seed 000's pipeline; parameters are documented in the module docstring and config.toml."""

    name = "visibility_bitmap"
    mode = "sync"
    uses_network = True
    # Algorithm 3A's Lambertian(n, m, wPos, l): no reflections, refractions or highlights
    flattens_materials = "are shaded as Lambertian with their albedo, as seed 000 shades every surface (Algorithm 3A)"
    outputs = {"raw_bytes": "bitmap bytes before the codec (W x H x bytes per pixel of the layout)",
               "wire_bytes": "framed, encoded bytes sent (0 in the standalone run)",
               "keyframe": "the frame was encoded without reference to earlier frames",
               "rows_repaired": "bitmap rows the client did not receive intact and repaired",
               "status": "ok | repaired | lost: what the client made of the frame",
               "problems": "what the client's checks found (lost slices, CRC failures), joined"}

    def __init__(self, params: dict):
        super().__init__(params)
        p = self.params
        self.layout = bm.check_layout(str(p.get("layout", "paper32")))
        self.codec = str(codecs.parse(str(p.get("codec", "none"))))
        self.keyframe_interval = int(p.get("keyframe_interval", 30))
        if self.keyframe_interval < 0:
            raise UserError(f"keyframe_interval must be >= 0, got {self.keyframe_interval}")
        self.udp_slice_rows = int(p.get("udp_slice_rows", 8))
        if self.udp_slice_rows < 1:
            raise UserError(f"udp_slice_rows must be >= 1, got {self.udp_slice_rows}")
        self.udp_repair = str(p.get("udp_repair", "previous"))
        if self.udp_repair not in wire.REPAIRS:
            raise UserError(f"unknown udp_repair '{self.udp_repair}' (choose from {', '.join(wire.REPAIRS)})")
        self.ambient = bool(p.get("ambient", False))
        self.ambient_radiance = float(p.get("ambient_radiance", 0.02))
        if self.ambient_radiance < 0:
            raise UserError(f"ambient_radiance must be >= 0, got {self.ambient_radiance}")
        self.gpu_to_cpu_bytes_per_s = transfer.bandwidth_from_mb_per_s(
            p.get("gpu_to_cpu_mb_per_s", transfer.PAPER_GPU_TO_CPU_BYTES_PER_S / 1e6), "gpu_to_cpu_mb_per_s")
        self.cpu_to_gpu_bytes_per_s = transfer.bandwidth_from_mb_per_s(
            p.get("cpu_to_gpu_mb_per_s", transfer.PAPER_CPU_TO_GPU_BYTES_PER_S / 1e6), "cpu_to_gpu_mb_per_s")
        self.transfer_latency_ms = float(p.get("transfer_latency_ms", 0.0))
        transfer.transfer_ms(0, 1.0, self.transfer_latency_ms)  # validates the latency
        self.light_count = 0
        self.reset()

    # ------------------------------------------------------------------------------------------ life cycle

    def omissions(self, scene) -> list[str]:
        # Seed 000 §3.1 shades point lights only: one bit per pixel and point light. Emissive surfaces still show
        # their own radiance where seen (the G-buffer's emission) but light nothing, so a scene lit by them alone
        # is refused and one lit by both says what is left out.
        area = len(scene.emissive_faces())
        if not scene.point_lights:
            raise UserError(f"visibility_bitmap: scene '{scene.name}' has no point lights"
                            + (f" (only area lights: {area} emissive triangles)" if area else "")
                            + "; seed 000's bitmap has one bit per point light (§3.1) and would render no light")
        lights = [f"its {area} emissive triangles light nothing: seed 000 shades point lights only (§3.1), so area "
                  f"lights show only their own emission"] if area else []
        return lights + super().omissions(scene)

    def prepare(self, scene, tracer) -> dict:
        light_count = len(scene.lights_at(scene.camera.frame_time_s(0)))
        bm.bytes_per_pixel(self.layout, light_count)  # paper32 with > 32 lights is a UserError here
        return {"light_count": light_count}

    def restore(self, prepared) -> None:
        self.prepared = prepared
        self.light_count = int(prepared["light_count"]) if prepared else 0

    def reset(self) -> None:
        self._encoder: wire.FrameEncoder | None = None
        self._decoder: wire.FrameDecoder | None = None
        self._encoder_key = None
        self._server_resolution: tuple[int, int] | None = None
        self._frames_in_sequence = 0

    def _ambient(self):
        return self.ambient_radiance if self.ambient else None

    def _shade(self, scene, g, lights, visibility):
        from suite.core.shading import min_light_distance, shade_point_lights

        # seed 000 §3.1: E = Σ_i I_i/π · ρ · max(n·L_i, 0) · k_shadow,i with distance falloff (Mitsuba units);
        # §5.1 / Fig. 9: + L_ambient · ρ where all k_shadow = 0.
        return shade_point_lights(g, lights, visibility, ambient=self._ambient(),
                                  min_distance=min_light_distance(scene))

    # ---------------------------------------------------------------------------------------------- frame

    def frame(self, ctx) -> np.ndarray:
        return self._standalone(ctx) if ctx.zero_latency else self._distributed(ctx)

    def _standalone(self, ctx) -> np.ndarray:
        """Algorithm 3A (seed 000 §3.1, §4.5.1 standalone mode): everything on one machine, no wire."""
        from suite.core.shading import point_light_visibility

        w, h = ctx.resolution
        lights = ctx.scene.lights_at(ctx.t_s)
        # On a tracer with a device path (Mitsuba llvm/cuda) everything up to the output pass stays on the device.
        with ctx.stage("gbuffer", place="client", after=[]) as st:
            g = _gbuffer(ctx.scene, ctx.tracer, ctx.t_s, (w, h), ctx.prev_t_s)
            st.pixels = w * h
        with ctx.stage("visibility", place="client") as st:
            visibility = point_light_visibility(g, lights, ctx.tracer)
            st.pixels = w * h
        with ctx.stage("shading", place="client") as st:
            rgb = self._shade(ctx.scene, g, lights, visibility)
            st.pixels = w * h
        with ctx.stage("output", place="client") as st:
            out = _to_output(rgb, st)
            st.pixels = w * h
        raw_bytes = bm.bitmap_nbytes(w, h, len(lights), self.layout)
        ctx.record(raw_bytes=raw_bytes, wire_bytes=0, keyframe=True, rows_repaired=0, status="ok", problems=[])
        self._frames_in_sequence += 1
        return out

    def _distributed(self, ctx) -> np.ndarray:
        """Algorithms 3B-1 (client) and 3B-2 (server), scheduled as in seed 000 Figure 7."""
        w, h = ctx.resolution
        scene, tracer = ctx.scene, ctx.tracer  # the client's view; server stages use ctx.scene (the server's)
        first = self._frames_in_sequence == 0

        # Client, Alg. 3B-1 step 1: send the camera (and the window size on the first frame, §4.3.1). Inputs
        # always travel over TCP, also in UDP runs: a lost camera update would desynchronise the two scenes
        # (§3.2 requires them in sync), and at under 100 bytes reliability costs nothing measurable.
        pose = scene.camera.pose_at(ctx.t_s)
        inputs = ctx.send("inputs", encode_inputs(ctx.t_s, pose, (w, h) if first else None), direction="up",
                          protocol="tcp", after=[])

        # Client, step 2: its G-buffer does not wait for the server (Figure 7).
        with ctx.stage("client_gbuffer", place="client", after=[]) as st:
            g_client = _gbuffer(scene, tracer, ctx.t_s, (w, h), ctx.prev_t_s)
            st.pixels = w * h

        # Server, Alg. 3B-2 step 1: the inputs synchronise its copy of the scene; the camera it renders is the
        # one it decoded (its scene view has no other).
        with ctx.stage("server_receive", place="server", after=["inputs"]) as st:
            t_s, server_pose, resolution = decode_inputs(inputs.data)
            if resolution is not None:
                self._server_resolution = resolution
            if self._server_resolution is None:
                raise RuntimeError("server has no resolution: the first frame's inputs carry it")
            sw, sh = self._server_resolution
            ctx.scene.camera.add(t_s, CameraPose(*server_pose))
            st.bytes = inputs.size_bytes
        lights = scene.lights_at(t_s)
        light_count = len(lights)

        # Server, step 2: its own G-buffer (the redundant one of §3.2).
        with ctx.stage("server_gbuffer", place="server") as st:
            g_server = _gbuffer(ctx.scene, tracer, t_s, (sw, sh), None)
            st.pixels = sw * sh

        # Server, steps 3-4: one shadow ray per pixel and light, bit i = light i unobstructed (§3.2). On the device
        # path the packed bitmap is read back to host memory at the end of the stage (the encoder needs it there);
        # the read-back the paper measured is the modelled stage that follows.
        with ctx.stage("visibility", place="server") as st:
            visibility, raw = visibility_pass(g_server, lights, tracer, self.layout)
            if not isinstance(raw, np.ndarray):
                raw = raw.to_host()
            st.pixels = sw * sh
            st.bytes = raw.nbytes

        # Server, pre-step 5: VRAM → RAM read-back (§4.4.3), modelled from bytes and bandwidth.
        ctx.modelled_stage("gpu_to_cpu", place="server",
                           duration_ms=transfer.transfer_ms(raw.nbytes, self.gpu_to_cpu_bytes_per_s,
                                                            self.transfer_latency_ms))

        # Server, step 5: encode and frame; under UDP as independent slices of rows.
        udp = ctx.protocol == "udp"
        key = (sw, sh, light_count, udp)
        if self._encoder is None or self._encoder_key != key:
            self._encoder = wire.FrameEncoder(sw, sh, light_count, self.layout, self.codec,
                                              self.udp_slice_rows if udp else None, self.keyframe_interval)
            self._decoder = wire.FrameDecoder(w, h, light_count, self.layout, self.udp_repair)
            self._encoder_key = key
        with ctx.stage("encode", place="server") as st:
            frame = self._encoder.encode_bitmap(raw, ctx.index)
            st.bytes = frame.nbytes
        msg = ctx.send("bitmap", frame.message, direction="down")

        # Client, step 3: receive; headers and CRCs decide what may be shaded, missing rows are repaired.
        lost = list(msg.lost_ranges)
        if not msg.complete and not lost:
            lost = [(0, frame.nbytes)]  # never arrived before the timeout
        with ctx.stage("receive_bitmap", place="client", after=["bitmap"]) as st:
            # The client decodes what was delivered (lost bytes zero-filled); under UDP each slice is one
            # datagram, so the slice boundaries are the transport's framing.
            received = self._decoder.decode(msg.data, ctx.index, frame.spans if udp else None, lost)
            st.bytes = frame.nbytes
            st.pixels = w * h

        # Client, pre-step 4: RAM → VRAM upload (§4.4.3), modelled.
        ctx.modelled_stage("cpu_to_gpu", place="client",
                           duration_ms=transfer.transfer_ms(received.bitmap.nbytes, self.cpu_to_gpu_bytes_per_s,
                                                            self.transfer_latency_ms))

        # Client, step 4: shading from its own G-buffer and the received k_shadow bits.
        # On the device path the received records are uploaded as they are (no unpacking) and shaded there.
        with ctx.stage("shading", place="client", after=["cpu_to_gpu", "client_gbuffer"]) as st:
            from suite.core.device import DeviceGBuffer, DeviceVisibility

            if isinstance(g_client, DeviceGBuffer):
                vis_dev = DeviceVisibility.from_host_bytes(g_client.device, received.bitmap, w, h, light_count,
                                                           bm.bytes_per_pixel(self.layout, light_count))
                rgb = self._shade(scene, g_client, lights, vis_dev)
            else:
                rgb = self._shade(scene, g_client, lights, received.visibility)
            st.pixels = w * h
        with ctx.stage("output", place="client") as st:
            out = _to_output(rgb, st)
            st.pixels = w * h

        ctx.record(raw_bytes=int(raw.nbytes), wire_bytes=frame.nbytes, keyframe=frame.keyframe,
                   rows_repaired=received.rows_missing, status=received.status, problems=list(received.problems))
        self._frames_in_sequence += 1
        return out
