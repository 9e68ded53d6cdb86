"""Seed 002: layered PVS streaming (CTU thesis, chapters 4-5).

Asynchronous (Fig. 4.1, §5.1): every client frame sends its pose (UPDATE_VIEWPOINT) and renders the newest
update it has decoded from its own newest pose; the server makes updates at ``update_fps`` from the newest pose
that arrived.

Server, per update (Fig. 4.2, Algorithm 3), one stage each:
  ``pvs``        Algorithm 1: id buffers from 7 predicted views at ``fov_enlarge`` x the client's FOV
  ``layers``     ray-traced depth peeling, primary hits restricted to the PVS (§4.1.2)
  ``path_trace`` every layer fragment path traced (§4.4: NEE, Russian roulette, ``spp`` samples)
  ``denoise``    SVGF's à-trous filter extended to layers (§4.4.1, ``denoise_iterations`` passes)
  ``pack``       fragment relocation (Algorithm 2), block counts, tile indices, packing (Fig. 4.7), colour
                 filling (§4.1.5)
  ``compress_*`` first layer as H.264 (``video_crf``), tiles as JPEG (``jpeg_quality``, 4:4:4), pixel mask
                 (binary quadtree or RLE + Huffman, with 'any' pixels §4.5.2), block counts and triangle-subset
                 masks (RLE + Huffman), PVS patch against the previous update (vertex references + Huffman)
then one message ``update`` (wire.py: header, parts with lengths and CRC-32). On a Mitsuba llvm/cuda tracer the
PVS views, the depth peeling, the path tracing (the fragments' direct light, their paths and the moments), the
SVGF and the pack stage run as Dr.Jit kernels (device.py); the fragments' surfaces and the codecs stay on the host.

Client, on a new update (Fig. 4.8): ``decode`` (parts), ``peel`` (depth peeling of its PVS from the update's
view, optionally with triangle subsets §4.5.1), ``relocate`` (fragments back to their layers); every frame
``render`` (Algorithm 4.1: PVS from the current pose, colour from the layer whose depth matches in the update's
view). An update that fails its checks (truncated, corrupt, or a PVS patch against a state the client does not
hold) is rejected: the client keeps showing its previous update and counts the rejection.

Differences from the thesis (also in config.toml [doc] and the report):
* The path tracer shades every material as Lambertian with its albedo (the thesis: Disney BRDF) and has no MIS
  (emitters are reached by next-event estimation only; emission is counted at the primary fragment).
* SVGF has no temporal accumulation (updates are ~180 ms apart); its variance is the larger of the sample and the
  3x3 spatial estimate.
* Client "rasterisation" is Embree ray casting of the PVS at pixel centres; the server's ID buffers of Algorithm 1
  are ray-cast as well.
* Every ``key_interval``-th update is a key (full PVS, IDR frame), so that a client that rejected an update
  recovers; the thesis streams patches over TCP only.
* The pixel mask covers the full layers too (relocation may move a fragment out of the first layer).
"""
from __future__ import annotations

import io
import math

import numpy as np

from suite.core import video
from suite.core.scene.model import CameraPose
from suite.errors import UserError
from suite.harness.method import Method

from methods.layered_pvs import client as cl
from methods.layered_pvs import codecs, packing, server, wire

PARTS = ("video", "jpeg", "mask", "blocks", "pvs", "subsets")


def jpeg_encode(rgb8: np.ndarray, quality: int) -> bytes:
    """JPEG with 4:4:4 chroma (no subsampling), as §6 configures it."""
    from PIL import Image

    if rgb8.size == 0:
        return b""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8)).save(buf, format="JPEG", quality=int(quality), subsampling=0,
                                                     optimize=False)
    return buf.getvalue()


def jpeg_decode(data: bytes, shape) -> np.ndarray:
    from PIL import Image

    if not data:
        return np.zeros(shape, np.uint8)
    try:
        img = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a corrupt part
        raise wire.WireError(f"JPEG part does not decode ({exc})") from None
    if img.shape != tuple(shape):
        raise wire.WireError(f"JPEG part is {img.shape[1]}x{img.shape[0]}, expected {shape[1]}x{shape[0]}")
    return img


class LayeredPVS(Method):
    name = "layered_pvs"
    mode = "async"
    # Layers are path traced on the server (§4.4: next-event estimation, Russian roulette): multi-bounce transport.
    light_transport = "global"
    # server.path_trace: every fragment and path vertex is Lambertian with its albedo
    flattens_materials = "are path-traced as Lambertian with their albedo"
    update_outputs = {
        **{f"bytes_{p}": f"bytes of the '{p}' part of the update" for p in PARTS},
        "bytes_header": "bytes of the header and part table",
        "mask_quadtree_bytes": "pixel mask as binary quadtree with 'any' pixels (whichever codec is sent)",
        "mask_rle_bytes": "pixel mask as RLE + Huffman with 'any' pixels (whichever codec is sent)",
        "mask_quadtree_noany_bytes": "pixel mask as binary quadtree with every 'any' pixel sent as 0",
        "subset_bytes": "triangle-subset masks (RLE + Huffman), whether or not they are sent",
        "pvs_triangles": "triangles in the PVS",
        "pvs_new_triangles": "triangles added since the previous update",
        "fragments": "layer fragments (all layers)",
        "fragments_per_pixel": "fragments per layer pixel",
        "layers_used": "deepest layer holding a fragment",
        "depth_overflow_pixels": "pixels whose every layer is filled (the layer budget may cut geometry)",
        "texture_rows": "rows of the packed texture (full layers + tile rows)",
        "tiles": "packed tiles",
        "relocated_fragments": "fragments moved by Algorithm 2",
        "host_device_bytes": "bytes the server's device kernels (PVS, depth peeling, path tracing, the layered SVGF "
                             "and the pack stage, on a Mitsuba llvm/cuda tracer) copied between host and device "
                             "memory; 0 on Embree",
        "key": "1 when the update carries a full PVS and an IDR video frame",
    }
    outputs = {
        **{f"bytes_{p}": f"bytes of the '{p}' part of the update on screen" for p in PARTS},
        "hole_pixels": "pixels without a colour (no PVS hit excluded): outside the update's view or no layer match",
        "no_hit_pixels": "pixels where the current view sees no PVS triangle (sky, or geometry the PVS missed)",
        "outside_pixels": "hit points outside the update's enlarged frustum",
        "unmatched_pixels": "hit points inside it whose depth matches no layer",
        "filled_pixels": "hole pixels filled (hole_fill variant)",
        "rejected_updates": "updates this client rejected so far (corrupt, truncated, or patch base missing)",
        "reject_reason": "why the last update was rejected ('' when it was not)",
        "client_rays": "rays the client cast (PVS peeling and the frame's primary rays)",
        "layer_mismatch_pixels": "layer pixels whose client-peeled fragment count differs from the mask's",
        "motion": "the client's own motion into this frame: forward | backward | sideways | fast_rotation | still "
                  "(the thesis's failure cases: backward motion and fast rotation, §6.3, §7)",
        "rotation_deg_s": "the client's view rotation rate into this frame (degrees per second)",
    }

    def __init__(self, params: dict):
        super().__init__(params)
        p = self.params
        if p.get("mask_codec", "quadtree") not in ("quadtree", "rle"):
            raise UserError(f"mask_codec must be quadtree or rle, got '{p.get('mask_codec')}'")
        if p.get("order", "block") not in packing.ORDERS:
            raise UserError(f"order must be block or layer, got '{p.get('order')}'")
        if int(p.get("layers", 4)) < 1 or int(p.get("layers", 4)) > 64:
            raise UserError(f"layers must be in 1..64, got {p.get('layers')}")
        if not 0 <= int(p.get("full_layers", 1)) <= int(p.get("layers", 4)):
            raise UserError("full_layers must be between 0 and layers")
        if float(p.get("update_fps", 5.5)) <= 0:
            raise UserError("update_fps must be > 0 (the corner offset of Algorithm 1 follows the update period)")
        if int(p.get("tile", 8)) not in (8, 16, 32):
            raise UserError(f"tile must be 8, 16 or 32 (JPEG blocks are 8x8), got {p.get('tile')}")
        self.reset()

    def prepare(self, scene, tracer):
        """Offline: which scene vertices share a position (the PVS patch references each position once)."""
        return {"canonical": _canonical_vertices(scene.positions)}

    def restore(self, prepared) -> None:
        super().restore(prepared)
        _warm_up()

    def reset(self) -> None:
        self._server: dict = {}      # client -> server-side state
        self._canonical = None       # scene vertex -> first vertex with the same position
        self._client: dict = {}      # this client's state (one client per instance)

    # ------------------------------------------------------------------------------------------ server

    def _server_state(self, c: int, ctx):
        st = self._server.get(c)
        if st is None:
            st = {"history": [], "pvs": codecs.PVSState(), "encoder": None, "count": 0}
            self._server[c] = st
        return st

    def _layer_view(self, ctx, pose) -> server.LayerView:
        w, h = ctx.resolution
        wl, hl, fov_l = server.layer_size(w, h, ctx.scene.camera.fov_deg, float(self.params["fov_enlarge"]),
                                          int(self.params["tile"]))
        return server.LayerView(pose, fov_l, wl, hl)

    def server_update(self, ctx) -> None:
        p = self.params
        c = ctx.client
        st = self._server_state(c, ctx)
        t_s, pose = ctx.latest_pose()
        st["history"] = (st["history"] + [(t_s, pose)])[-8:]
        scene, tracer = ctx.scene, ctx.tracer
        view = self._layer_view(ctx, pose)
        L, F, tile = int(p["layers"]), int(p["full_layers"]), int(p["tile"])
        period_s = 1.0 / float(p["update_fps"])
        key = st["count"] % max(int(p["key_interval"]), 1) == 0
        st["count"] += 1

        device = getattr(tracer, "device", None)
        copied0 = device.copied_bytes if device is not None else 0   # what the update's device kernels copy
        with ctx.stage("pvs", place="server") as sg:
            hist = st["history"]
            speed = 0.0
            if len(hist) >= 2 and hist[-1][0] > hist[-2][0]:
                speed = float(np.linalg.norm(np.asarray(hist[-1][1].position) - np.asarray(hist[-2][1].position))
                              / (hist[-1][0] - hist[-2][0]))
            corner = max(speed, float(p["corner_speed"]) * server.scene_extent(scene)) * period_s
            views = server.predict_views(hist, period_s, corner)
            pvs_ids = server.compute_pvs(tracer, views, view.fov_deg, view.width, view.height)
            sg.pixels = len(views) * view.width * view.height
        in_pvs = np.zeros(scene.num_faces, bool)
        in_pvs[pvs_ids] = True

        with ctx.stage("layers", place="server") as sg:
            if device is not None:  # the view's rays are made on the device, for the peeling and the fragments
                o64 = d64 = None
                layers = server.peel(tracer, None, None, L, keep_mask=in_pvs, shape=(view.height, view.width),
                                     view=view)
            else:
                o64, d64 = server.view_rays(view)
                layers = server.peel(tracer, o64.astype(np.float32), d64.astype(np.float32), L,
                                     keep_mask=in_pvs, shape=(view.height, view.width))
            sg.pixels = view.width * view.height

        with ctx.stage("path_trace", place="server") as sg:
            frag = server.fragments(scene, layers, o64, d64, ctx.t_s, device=device, view=view)
            illum, m1, m2 = server.path_trace(scene, tracer, frag, ctx.t_s, int(p["spp"]), int(p["max_depth"]),
                                              int(p["rr_depth"]), ctx.rng)
            sg.pixels = len(frag.position)

        shape = layers.prim.shape
        with ctx.stage("denoise", place="server") as sg:
            k, y, x = frag.index
            iters = int(p["denoise_iterations"])
            illum = server.denoise_fragments(view, layers, frag, illum, m1, m2, int(p["spp"]), iters,
                                             device=device)
            radiance = illum * frag.albedo + frag.emission
            colour = np.zeros(shape + (3,), np.uint8)
            colour[k, y, x] = video.to_video(radiance[None].astype(np.float32), float(p["exposure"]))[0]
            sg.count(taps=len(frag.position) * 25 * iters)

        with ctx.stage("pack", place="server") as sg:
            valid = layers.valid
            tex, mask, counts, layout, relocated = packing.pack_stage(
                layers.t, valid, colour, tile, F, p["order"], bool(p["relocation"]), bool(p["colour_fill"]),
                device=device)
            sg.pixels = tex.shape[0] * tex.shape[1]

        parts = {}
        full_rows = F * view.height
        with ctx.stage("compress_pvs", place="server") as sg:
            if self._canonical is None or len(self._canonical) != len(scene.positions):
                pre = self.prepared or {}
                canonical = pre.get("canonical")
                self._canonical = canonical if canonical is not None and len(canonical) == len(scene.positions) \
                    else _canonical_vertices(scene.positions)
            keys = _vertex_keys(scene, self._canonical, st["count"])
            positions = scene.positions_at(ctx.t_s)
            base_state = codecs.PVSState() if key else st["pvs"]
            parts["pvs"], new_state = codecs.pvs_patch_encode(base_state, pvs_ids, keys,
                                                              positions.astype(np.float32))
            st["pvs"] = new_state
            sg.count(codec_bytes=len(parts["pvs"]))
        with ctx.stage("compress_video", place="server") as sg:
            if F > 0:
                if st["encoder"] is None or key:
                    st["encoder"] = video.Encoder("h264", view.width, full_rows, float(p["update_fps"]), 0.0,
                                                  float(p["video_crf"]), 100000, False, p["video_preset"], 1 << 20)
                parts["video"] = st["encoder"].encode(tex[:full_rows]).data
            else:
                parts["video"] = b""
            sg.count(codec_bytes=full_rows * view.width * 3)
        with ctx.stage("compress_jpeg", place="server") as sg:
            parts["jpeg"] = jpeg_encode(tex[full_rows:], int(p["jpeg_quality"]))
            sg.count(codec_bytes=(tex.shape[0] - full_rows) * view.width * 3)
        with ctx.stage("compress_mask", place="server") as sg:
            qt = codecs.quadtree_encode(mask)
            sg.count(codec_bytes=mask.size)
        rle = codecs.binary_rle_encode(mask)
        qt_noany = codecs.quadtree_encode(np.where(mask == codecs.ANY, 0, mask))
        parts["mask"] = rle if p["mask_codec"] == "rle" else qt
        with ctx.stage("compress_other", place="server") as sg:
            parts["blocks"] = codecs.byte_rle_encode(counts.astype(np.uint8))
            pvs_rank = np.searchsorted(pvs_ids, np.maximum(layers.prim, 0))
            rows = server.Layers(layers.t, np.where(valid, pvs_rank, -1), layers.u, layers.v)
            subsets = cl.triangle_subsets(rows, len(pvs_ids))
            subset_bytes = codecs.binary_rle_encode(subsets.astype(np.uint8))
            if p["subset_peeling"]:
                parts["subsets"] = subset_bytes
            sg.count(codec_bytes=counts.size + subsets.size)

        flags = (wire.FLAG_KEY if key else 0) | (wire.FLAG_RELOCATED if p["relocation"] else 0) \
            | (wire.FLAG_LAYER_FIRST if p["order"] == "layer" else 0) \
            | (wire.FLAG_MASK_RLE if p["mask_codec"] == "rle" else 0) \
            | (wire.FLAG_SUBSETS if p["subset_peeling"] else 0)
        header = wire.Header(update=ctx.index, base=-1 if key else st.get("last_index", -1), flags=flags, layers=L,
                             full_layers=F, tile=tile, width=view.width, height=view.height, fov_deg=view.fov_deg,
                             pose=np.stack([pose.position, pose.target, pose.up]), exposure=float(p["exposure"]))
        payload = wire.encode(header, parts)
        st["last_index"] = ctx.index
        ctx.send("update", payload, direction="down")
        body = sum(len(v) for v in parts.values())
        ctx.record(**{f"bytes_{n}": len(parts.get(n, b"")) for n in PARTS}, bytes_header=len(payload) - body,
                   mask_quadtree_bytes=len(qt), mask_rle_bytes=len(rle), mask_quadtree_noany_bytes=len(qt_noany),
                   subset_bytes=len(subset_bytes), pvs_triangles=len(pvs_ids),
                   pvs_new_triangles=len(pvs_ids) - len(np.intersect1d(pvs_ids, base_state.tri_ids
                                                                       if base_state.tri_ids is not None
                                                                       else np.zeros(0, np.int64))),
                   fragments=int(valid.sum()), fragments_per_pixel=float(valid.sum()) / (view.width * view.height),
                   layers_used=int(valid.any(axis=(1, 2)).sum()),
                   depth_overflow_pixels=int(valid[-1].sum()), texture_rows=int(tex.shape[0]), tiles=layout.tiles,
                   relocated_fragments=relocated, key=int(key),
                   host_device_bytes=device.copied_bytes - copied0 if device is not None else 0)

    # ------------------------------------------------------------------------------------------ client

    def client_frame(self, ctx, update):
        p = self.params
        st = self._client
        st.setdefault("rejected", 0)
        st.setdefault("reason", "")
        rays = 0
        if update is not None and update.is_new and update.index != st.get("seen"):
            st["seen"] = update.index
            try:
                rays += self._apply_update(ctx, update)
                st["reason"] = ""
            except (wire.WireError, codecs.CodecError) as exc:
                st["rejected"] += 1
                st["reason"] = str(exc)
        w, h = ctx.resolution
        dec = st.get("decoded")
        with ctx.stage("render", place="client") as sg:
            sg.pixels = w * h
            if dec is None:
                img = np.zeros((h, w, 3), np.float32)
                stats = cl.FrameStats(w * h, 0, 0, 0, 0)
            else:
                cam = ctx.scene.camera
                rgb8, _, stats = cl.render_frame(dec, cam.pose_at(ctx.t_s), cam.fov_deg, w, h, float(p["depth_tol"]),
                                                 bool(p["hole_fill"]))
                img = video.from_video(rgb8, dec.exposure)
        sizes = st.get("sizes", {})
        motion, rot = _motion(ctx)
        ctx.record(motion=motion, rotation_deg_s=rot, **{f"bytes_{n}": sizes.get(n, 0) for n in PARTS},
                   hole_pixels=stats.outside + stats.unmatched - stats.filled, no_hit_pixels=stats.no_hit,
                   outside_pixels=stats.outside, unmatched_pixels=stats.unmatched, filled_pixels=stats.filled,
                   rejected_updates=st["rejected"], reject_reason=st["reason"], client_rays=rays + stats.rays,
                   layer_mismatch_pixels=st.get("mismatch", 0))
        return img

    def _apply_update(self, ctx, update) -> int:
        """Decodes, peels and relocates one update (Fig. 4.8); raises WireError / CodecError to reject it."""
        p = self.params
        st = self._client
        with ctx.stage("decode", place="client") as sg:
            msg = wire.decode(update["update"].data, update.index)
            hd = msg.header
            key = bool(hd.flags & wire.FLAG_KEY)
            prev = codecs.PVSState() if key else st.get("pvs")
            if prev is None or (not key and hd.base != st.get("applied", -2)):
                raise wire.WireError(f"update {hd.update}: PVS patch against update {hd.base}, the client holds "
                                     f"update {st.get('applied', 'none')}")
            pvs = codecs.pvs_patch_decode(prev, msg.parts["pvs"])
            full_rows = hd.full_layers * hd.height
            if hd.full_layers > 0:
                if key or st.get("decoder") is None:
                    st["decoder"] = video.Decoder("h264", hd.width, full_rows)
                frame = st["decoder"].decode(msg.parts.get("video", b""))
                if frame is None:
                    raise wire.WireError(f"update {hd.update}: part 'video' produced no picture")
                full = frame
            else:
                full = np.zeros((0, hd.width, 3), np.uint8)
            counts = codecs.byte_rle_decode(msg.parts["blocks"], (hd.height // hd.tile) * (hd.width // hd.tile))
            counts = counts.reshape(hd.height // hd.tile, hd.width // hd.tile).astype(np.int64)
            order = "layer" if hd.flags & wire.FLAG_LAYER_FIRST else "block"
            layout = packing.make_layout(counts, hd.width, hd.height, hd.tile, hd.full_layers, order)
            tiles = jpeg_decode(msg.parts.get("jpeg", b""), (layout.tile_rows * hd.tile, hd.width, 3))
            shape = (layout.texture_height, hd.width)
            if hd.flags & wire.FLAG_MASK_RLE:
                mask = codecs.binary_rle_decode(msg.parts["mask"], shape[0] * shape[1]).reshape(shape)
            else:
                mask = codecs.quadtree_decode(msg.parts["mask"], shape)
            subsets = None
            if hd.flags & wire.FLAG_SUBSETS:
                bits = codecs.binary_rle_decode(msg.parts["subsets"], hd.layers * len(pvs))
                subsets = bits.reshape(hd.layers, len(pvs)).astype(bool)
            tex = np.concatenate([full, tiles], axis=0)
            sg.count(codec_bytes=len(update["update"].data or b""))
        pose = CameraPose(hd.pose[0], hd.pose[1], hd.pose[2])
        view = server.LayerView(pose, hd.fov_deg, hd.width, hd.height)
        tris = pvs.triangles
        with ctx.stage("peel", place="client") as sg:
            layers, rays = cl.peel_client(tris, view, hd.layers, subsets if p["subset_peeling"] else None)
            sg.pixels = hd.width * hd.height * hd.layers
        with ctx.stage("relocate", place="client") as sg:
            n_pix = layers.counts
            slot_colour, slot_mask, stored = packing.unpack(tex, mask, layout, hd.layers)
            # A pixel whose client-peeled count exceeds the slots the mask marks keeps what the mask holds.
            st["mismatch"] = int((slot_mask.sum(axis=0) < n_pix).sum()) if hd.flags & wire.FLAG_RELOCATED else 0
            if hd.flags & wire.FLAG_RELOCATED:
                back, valid_back = packing.relocate_back(slot_colour, slot_mask, n_pix)
                texture, _ = packing.pack(back, valid_back & stored, layout)
            else:
                texture = tex
            sg.pixels = texture.shape[0] * texture.shape[1]
        e1 = tris[:, 1] - tris[:, 0]
        e2 = tris[:, 2] - tris[:, 0]
        nrm = np.cross(e1.astype(np.float64), e2.astype(np.float64))
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        st["decoded"] = cl.DecodedUpdate(hd.update, view, cl.Geometry(tris), nrm,
                                         np.where(layers.valid, layers.t, np.inf), n_pix, layout, texture,
                                         hd.exposure)
        st["pvs"] = pvs
        st["applied"] = hd.update
        st["sizes"] = {n: len(v) for n, v in msg.parts.items()}
        return rays


FAST_ROTATION_DEG_S = 60.0


def _motion(ctx) -> tuple[str, float]:
    """Classifies the client's own camera motion between its previous frame and this one."""
    if ctx.prev_t_s is None:
        return "still", 0.0
    cam = ctx.scene.camera
    a, b = cam.pose_at(ctx.prev_t_s), cam.pose_at(ctx.t_s)
    dt = max(ctx.t_s - ctx.prev_t_s, 1e-9)
    fa, fb = a.basis()[0], b.basis()[0]
    rot = math.degrees(math.acos(float(np.clip(np.dot(fa, fb), -1.0, 1.0)))) / dt
    v = (np.asarray(b.position, np.float64) - np.asarray(a.position, np.float64)) / dt
    speed = float(np.linalg.norm(v))
    if rot > FAST_ROTATION_DEG_S:
        return "fast_rotation", rot
    if speed < 1e-9:
        return "still", rot
    along = float(np.dot(v, fb)) / speed
    return ("forward" if along > 0.5 else "backward" if along < -0.5 else "sideways"), rot


def _warm_up() -> None:
    """Compiles the numba kernels (SVGF, Huffman coding, relocation, the path tracer's passes) before the first
    update, so that no update's stage time holds a compilation."""
    from methods.layered_pvs import kernels

    kernels.warm_up()
    one = np.ones((1, 1, 1), bool)
    server.svgf_layers(np.zeros((1, 1, 1, 3)), np.zeros((1, 1, 1)), np.zeros((1, 1, 1, 3)), np.zeros((1, 1, 1, 3)),
                       one, np.ones((1, 1, 1)), 0.01, iterations=1)
    codecs.huffman_decode(codecs.huffman_encode(b"ab"))
    packing.relocate(np.ones((2, 8, 8), np.float32), np.ones((2, 8, 8), bool), 8)


def _canonical_vertices(positions: np.ndarray) -> np.ndarray:
    """Scene vertex -> the first vertex at the same position: the PVS patch references a vertex once whatever
    mesh split it (texture seams, per-face normals), as §4.2's "same vertices in previous PVS"."""
    _, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


def _vertex_keys(scene, canonical: np.ndarray, update_count: int) -> np.ndarray:
    """(F, 3) vertex identities for the PVS patch: canonical scene vertices; vertices of animated objects get
    fresh ids at every update (they moved, so the client needs their new positions)."""
    keys = canonical[scene.faces]
    if scene.object_animations:
        moving = np.isin(scene.face_object, [a.object_id for a in scene.object_animations])
        keys = keys.copy()
        keys[moving] = scene.faces[moving].astype(np.int64) + len(scene.positions) * (update_count + 1)
    return keys
