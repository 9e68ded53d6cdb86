"""Seed 004 (Bugeja, Debattista, Spina: "An asynchronous method for cloud-based rendering", RAIL): remote
asynchronous indirect lighting for many clients.

Server (one instance shared by every client):
  prepare   §3.1 point set Q (light-traced dart sources, Poisson-disk dart throwing, AO area of effect), the grid
            geometries of G (§3.3) and A (§3.4). Q stays on the server; clients get it by transfer.
  request   decodes a client's request (camera + light changes, §4.1) and applies the scene changes; a change
            starts a new accumulation sequence (E₀ = E, §3.2).
  shade     §3.2 point-cloud shading: VPLs by light tracing, per point the sum of unoccluded VPL contributions,
            progressive mean. The server shades at ``pass_hz`` whatever the number of clients (§4.3: one
            estimate for everyone); a request runs the passes that fell due since the last one.
  clip      §4.1: cells of G whose points (by containment) are in the client's frustum and whose quantised
            irradiance changed since this client last received them; the first response is the full G.
  encode    cell id + irradiance triples (no indices), LZF (python-lzf), framed with lengths and a CRC-32;
            the initial full transfer always over TCP, updates over the run's protocol.
Client (one instance each):
  gbuffer, direct  the suite's kernels every frame (suite.core.gbuffer, suite.core.shading)
  apply     decodes a response (a damaged one is rejected whole and counted; the cache is kept), stage 1 of the
            two-stage smoothing (E'_c = w_c E_c + (1 − w_c) E_s) and eq. 6's interval estimate
  indirect  eq. 5's interpolation, IDW reconstruction (eq. 1-2) through the client's own G (rebuilt from the
            transferred records), optionally at reduced resolution with joint bilateral upsampling; the ambient
            function F_a·AO (§3.4-3.5, AO traced) where eq. 2 is 0/0 or on dynamic geometry.
  compose   direct + albedo · E / π.
On a tracer with a device path (Mitsuba llvm/cuda) the client frame stays on the device from the G-buffer to the
composed image, and the server's shading pass is one device kernel (device.py: the same values as the host path);
Embree runs the host path.
The client asks for the next update when the previous response has arrived (request/response, §4.1, §5.3).
"""
from __future__ import annotations

import math

import numpy as np

from suite.harness.method import Method

from . import wire
from .grid import AmbientGrid, GridGeometry, MultiRefGrid, frustum_cells, frustum_planes, idw
from .lighting import ProgressiveIrradiance, shade_points, trace_light_paths
from .pointset import ambient_occlusion, generate_point_set, point_spacing
from .smoothing import IntervalPredictor, interpolate
from .upsample import joint_bilateral_upsample

INV_PI = 1.0 / np.pi
# Request flags: bit 0 = send the full grid (nothing usable arrived yet), bit 1 = the previous response was
# rejected or never came: resend every cell in the frustum.
NEED_FULL, RESYNC = 1, 2
# grid_cells = 0: cells sized so that a record of mean range spans 2r/c_l = 3 cells (§3.3's example grid).
GRID_RANGE_RATIO = 3.0
MAX_GRID_CELLS = 160


def contained_cells(geometry: GridGeometry, positions) -> np.ndarray:
    """(C + 1,) start of each cell's points in Q's order (points are sorted by the cell containing them)."""
    cells = geometry.cell_index(positions)
    if len(cells) and (np.diff(cells) < 0).any():
        raise ValueError("points are not sorted by their cell")
    return np.concatenate([[0], np.cumsum(np.bincount(cells[cells >= 0], minlength=geometry.n_cells))]).astype(np.int64)


def select_cells(E, cell_start, occupied, geometry, pose, fov_deg, resolution, margin_m, sent, full):
    """§4.1: the cells of a response and the quantised irradiance. ``full``: every occupied cell. Otherwise the
    occupied cells that intersect the client's frustum (planes pushed out by ``margin_m``) and, when ``sent``
    (what this client last received) is given, only those with at least one changed value.
    Returns (cells, cells in view, scales per cell, codes per point)."""
    scales, codes = wire.quantise(E, cell_start)
    if full:
        return occupied, len(occupied), scales, codes
    w, h = resolution
    planes = frustum_planes(pose, fov_deg, w / h, 0.0, 1e30)
    planes[:, 3] += margin_m
    cells = occupied[frustum_cells(geometry, planes, occupied)]
    in_view = len(cells)
    if sent is not None:
        changed = np.zeros(geometry.n_cells, bool)
        owner = np.repeat(np.arange(geometry.n_cells), np.diff(cell_start))
        changed[owner[(codes != sent["codes"]).any(axis=1)]] = True
        changed |= scales != sent["scales"]
        cells = cells[changed[cells]]
    return cells, in_view, scales, codes


def remember_sent(state, cells, scales, codes, cell_start) -> None:
    """What the client holds after this response (the server's per-client copy for change detection)."""
    sel = np.concatenate([np.arange(cell_start[c], cell_start[c + 1]) for c in cells]) \
        if len(cells) else np.zeros(0, np.int64)
    state["codes"][sel] = codes[sel]
    state["scales"][cells] = scales[cells]


def encode_response(cells, scales, codes, cell_start, seq, use_lzf, full=None):
    """(raw body, framed payload): an update, or with ``full`` = (points, G geometry, A geometry) the initial
    transfer of G."""
    section = wire.encode_cells(cells, scales[cells], codes, cell_start)
    raw = wire.encode_full(full[0], full[1], full[2], section) if full is not None else section
    kind = wire.KIND_FULL if full is not None else wire.KIND_UPDATE
    return raw, wire.encode_frame(kind, seq, raw, compress=use_lzf)


class ClientGrid:
    """What a client holds after the initial transfer: Q's records, its own G and A, and the cache."""

    def __init__(self, raw: bytes):
        n, g, a, pos, nrm, rng, ao, off = wire.decode_full(raw)
        self.geometry = GridGeometry(tuple(float(x) for x in g[0]), float(g[1]), int(g[2]))
        self.ambient_geometry = GridGeometry(tuple(float(x) for x in a[0]), float(a[1]), int(a[2]))
        self.position, self.normal, self.range_m, self.ao = pos, nrm, rng, ao
        try:
            self.cell_start = contained_cells(self.geometry, pos)
        except ValueError as exc:
            raise wire.WireError(str(exc)) from None
        ids, scales, pts, codes, end = wire.decode_cells(raw, off, self.cell_start)
        if end != len(raw):
            raise wire.WireError("full transfer has trailing bytes")
        self.first_cells = (ids, scales, pts, codes)
        # G's references are rebuilt here from positions and ranges (same deterministic algorithm as the
        # server's), so only the records travel.
        self.grid = MultiRefGrid.build(self.geometry, pos, rng)
        self.ambient = AmbientGrid.build(self.ambient_geometry, pos, nrm, ao)

    def __len__(self) -> int:
        return len(self.position)


class Rail(Method):
    name = "rail"
    mode = "async"
    # Direct light on the client plus diffuse indirect light from the irradiance cloud: multi-bounce transport.
    light_transport = "global"
    # The client's direct term is suite.core.shading's Lambertian direct lighting, and seed 004 §3.1's point set
    # samples diffuse indirect lighting, whose irradiance lights every surface.
    flattens_materials = ("are shaded as Lambertian with their albedo: the client's direct lighting is Lambertian and "
                          "RAIL's irradiance records are diffuse (seed 004 §3.1)")
    outputs = {
        "cache_ready": "the client holds G (the initial transfer arrived intact)",
        "fallback_pixels": "pixels shaded with the ambient function F_a·AO (eq. 2 was 0/0, or dynamic geometry)",
        "zero_weight_pixels": "static-geometry pixels whose IDW weight sum was 0 (eq. 2 is 0/0)",
        "no_ambient_pixels": "fallback pixels where the ambient grid had no value either (indirect = 0)",
        "records_visited_mean": "G records examined per reconstructed pixel (one cell each)",
        "rejected_updates": "responses rejected so far (truncated or corrupt; the cache was kept)",
        "requests_sent": "requests sent so far",
        "update_cells": "cells applied to the cache in this frame (0 when no new response)",
        "interval_error_ms": "eq. 6: predicted minus recorded interval between cache updates (on update frames)",
        "update_interval_ms": "recorded interval τ between the last two cache updates (on update frames)",
        "predicted_interval_ms": "eq. 6's current estimate ΔT",
        "irradiance_pixels": "pixels at which IDW ran (fewer with irradiance_scale > 1)",
        "host_device_bytes": "bytes the reconstruction copied between host and device memory (device path: the "
                             "records' irradiance every frame, G after a full transfer, the fallback pixels; 0 on "
                             "the host path)",
    }
    update_outputs = {
        "points": "|Q|",
        "passes": "shading passes run in this update",
        "vpls": "VPLs of those passes",
        "pairs": "VPL·point pairs of those passes",
        "shadow_rays": "shadow rays of those passes",
        "restarted": "a scene change started a new accumulation sequence",
        "sequence_length": "terms in the current progressive mean",
        "light_changes": "light positions the request changed",
        "full": "the response is the initial full transfer of G",
        "cells_in_frustum": "occupied cells of G that intersect the client's frustum",
        "cells_sent": "cells in the response",
        "raw_bytes": "response body before LZF",
        "wire_bytes": "response as sent (header + LZF body)",
        "shade_ms": "wall time of the shading passes",
        "request_seq": "sequence number of the request answered",
    }

    # ------------------------------------------------------------------------------------------- offline data

    def prepare(self, scene, tracer):
        p = self.params
        lo, hi = scene.bounds()
        ambient_geometry = GridGeometry.fit(lo, hi, int(p["ambient_cells"]))
        spacing_m = point_spacing(scene, int(p["target_points"]), float(p["point_spacing_m"]))
        cells = int(p["grid_cells"])
        if cells <= 0:
            # §3.3's typical grid has 2r/c_l = 3 (r = 6, c_l = 4): c from the mean range of a record.
            r_mean = 0.5 * (float(p["range_min"]) + float(p["range_max"])) * spacing_m
            cells = int(np.clip(np.ceil(float((hi - lo).max()) / (2.0 * r_mean / GRID_RANGE_RATIO)), 1, MAX_GRID_CELLS))
        grid_geometry = GridGeometry.fit(lo, hi, cells)
        points = generate_point_set(
            scene, tracer, grid_geometry, target_points=int(p["target_points"]),
            spacing_m=spacing_m, dart_sources=int(p["dart_sources"]),
            darts_per_source=int(p["darts_per_source"]), source_bounces=int(p["vpl_bounces"]),
            ao_rays=int(p["ao_rays"]), range_min=float(p["range_min"]), range_max=float(p["range_max"]),
            seed=int(p["point_seed"]))
        grid = MultiRefGrid.build(grid_geometry, points.position, points.range_m)
        lights = scene.point_lights
        return {
            "points": points, "grid_geometry": grid_geometry, "ambient_geometry": ambient_geometry,
            "grid_memory": grid.memory(points.range_m),
            "light_positions": np.array([lt.position for lt in lights], np.float64).reshape(-1, 3),
            "light_intensities": np.array([lt.intensity for lt in lights], np.float64).reshape(-1, 3),
        }

    def reset(self) -> None:
        # server side
        self._acc = None
        self._lights = None
        self._pending_change = False
        self._last_pass_s = -math.inf
        self._last_pass_t = None
        self._sent: dict[int, dict] = {}
        # client side
        self._cg: ClientGrid | None = None
        self._device_grid = None           # (the ClientGrid, its DeviceGrid) on a tracer with a device path
        self._dynamic_device = None        # (key, Bool table of dynamic faces) on the device
        self._E_c = self._E_d = self._E_shown = None
        self._predictor = IntervalPredictor(float(self.params["w_d"]), float(self.params["delta_t0_ms"]))
        self._last_update_ms = None
        self._seq = 0
        self._outstanding = None          # (seq, sent at ms)
        self._flags = NEED_FULL
        self._sent_lights = None
        self._rejected = 0
        self._requests = 0

    # ----------------------------------------------------------------------------------------------- client

    @staticmethod
    def _now_ms(ctx) -> float:
        return 1e3 * ctx.group.start_s      # the client's own clock: this frame's start

    def client_input(self, ctx) -> None:
        now = self._now_ms(ctx)
        if not ctx.zero_latency and self._outstanding is not None:
            # Over TCP the response always comes; over UDP a lost request or response is given up after the
            # timeout and asked for again (with every cell in view).
            if ctx.protocol != "udp" or now - self._outstanding[1] < float(self.params["request_timeout_ms"]):
                return
            self._flags |= RESYNC
        scene = ctx.scene
        lights = scene.lights_at(ctx.t_s)
        if self._sent_lights is None:
            self._sent_lights = np.array([lt.position for lt in scene.point_lights], np.float64).reshape(-1, 3)
        changes = {i: lt.position for i, lt in enumerate(lights)
                   if not np.array_equal(np.asarray(lt.position, np.float64), self._sent_lights[i])}
        for i, pos in changes.items():
            self._sent_lights[i] = pos
        self._seq += 1
        payload = wire.encode_request(self._seq, ctx.t_s, scene.camera.pose_at(ctx.t_s), scene.camera.fov_deg,
                                      {i: np.asarray(p, np.float32) for i, p in changes.items()}, self._flags)
        ctx.send("request", payload, direction="up", protocol=ctx.protocol, after=[])
        self._outstanding = (self._seq, now)
        self._requests += 1

    def _apply(self, ctx, data) -> int:
        """Decodes a response into the cache; returns the cells applied. WireError leaves the cache as it was."""
        kind, seq, raw = wire.decode_frame(data)
        zl = ctx.zero_latency or not bool(self.params["smoothing"])
        if kind == wire.KIND_FULL:
            cg = ClientGrid(raw)
            ids, scales, pts, codes = cg.first_cells
            E = np.zeros((len(cg), 3))
            E[pts] = wire.dequantise(np.repeat(scales, np.diff(cg.cell_start)[ids]), codes)
            self._cg, self._E_c, self._E_d, self._E_shown = cg, E, E.copy(), E.copy()
            self._flags &= ~NEED_FULL
            n_cells = len(ids)
        elif kind == wire.KIND_UPDATE:
            if self._cg is None:
                raise wire.WireError("an update arrived before the full grid")
            cs = self._cg.cell_start
            ids, scales, pts, codes, end = wire.decode_cells(raw, 0, cs)
            if end != len(raw):
                raise wire.WireError("update has trailing bytes")
            E_s = wire.dequantise(np.repeat(scales, np.diff(cs)[ids]), codes)
            self._E_d = self._E_shown.copy()          # E_d: the value used in the previous frame (§4.2)
            w_c = 0.0 if zl else float(self.params["w_c"])
            self._E_c[pts] = w_c * self._E_c[pts] + (1.0 - w_c) * E_s      # stage 1
            n_cells = len(ids)
        else:
            raise wire.WireError(f"unexpected message kind {kind}")
        if self._outstanding is not None and seq >= self._outstanding[0]:
            self._outstanding = None
        self._flags &= ~RESYNC
        now = self._now_ms(ctx)
        if self._last_update_ms is not None:
            tau = now - self._last_update_ms
            err = self._predictor.observe(tau)
            ctx.record(interval_error_ms=err, update_interval_ms=tau)
        self._last_update_ms = now
        return n_cells

    def client_frame(self, ctx, update):
        from suite.core.gbuffer import has_device, render_gbuffer, render_gbuffer_device
        from suite.core.shading import direct_lighting

        p = self.params
        w, h = ctx.resolution
        # On a tracer with a device path (Mitsuba llvm/cuda) the frame stays on the device from the G-buffer to the
        # composed image (device.py); Embree runs the host path. Both count the same work.
        on_device = has_device(ctx.tracer)
        with ctx.stage("gbuffer", place="client") as st:
            render = render_gbuffer_device if on_device else render_gbuffer
            g = render(ctx.scene, ctx.tracer, ctx.t_s, resolution=(w, h), prev_t_s=ctx.prev_t_s)
            st.pixels = w * h
        with ctx.stage("direct", place="client") as st:
            direct = direct_lighting(ctx.scene, g, ctx.tracer, ctx.t_s, area_samples=int(p["area_samples"]),
                                     seed=ctx.seed)
            if not on_device:
                direct = np.asarray(direct, np.float32)
            st.pixels = w * h
        applied = 0
        if update is not None and update.is_new and "grid" in update.messages:
            with ctx.stage("apply", place="client") as st:
                data = update["grid"].data
                st.count(codec_bytes=len(data or b""))
                try:
                    had_grid = self._cg is not None
                    applied = self._apply(ctx, data)
                    if not had_grid:
                        st.count(points=len(self._cg.grid.refs))            # G rebuilt from the records
                except wire.WireError:
                    self._rejected += 1
                    self._flags |= RESYNC | (NEED_FULL if self._cg is None else 0)
                    self._outstanding = None
        irradiance = None
        info = {"fallback_pixels": 0, "zero_weight_pixels": 0, "no_ambient_pixels": 0, "records_visited_mean": 0.0,
                "irradiance_pixels": 0, "host_device_bytes": 0}
        if self._cg is not None:
            with ctx.stage("indirect", place="client") as st:
                irradiance, info = (self._reconstruct_device if on_device else self._reconstruct)(ctx, g)
                st.pixels = info["irradiance_pixels"]
                st.count(taps=int(info["records_visited_total"]))
        with ctx.stage("compose", place="client") as st:
            # final = direct + albedo · E / π (the diffuse indirect term), float32 on both paths
            if on_device:
                rgb = direct.rgb
                if irradiance is not None:
                    dr = g.device.dr
                    rgb = rgb + dr.select(g.valid, g.albedo * irradiance * dr.opaque(g.device.Float, INV_PI), 0.0)
                g.device.eval(rgb)
            else:
                rgb = direct if irradiance is None else direct + g.albedo * irradiance * INV_PI * g.valid[..., None]
            st.pixels = w * h
        if on_device:
            # The client shows the image from device memory; this read-back is the harness's (metrics, results).
            rgb = g.device.to_host(rgb, np.float32).reshape(h, w, 3)
        ctx.record(cache_ready=self._cg is not None, rejected_updates=self._rejected, requests_sent=self._requests,
                   update_cells=applied, predicted_interval_ms=self._predictor.delta_t_ms,
                   **{k: v for k, v in info.items() if k in self.outputs})
        return rgb.astype(np.float32)

    def _shown_irradiance(self, ctx) -> np.ndarray:
        """The records' irradiance this frame shows: E_c, or eq. 5's interpolation from E_d while smoothing."""
        zl = ctx.zero_latency or not bool(self.params["smoothing"])
        if zl or self._last_update_ms is None:
            self._E_shown = self._E_c.copy()
        else:                                           # stage 2, eq. 5
            t = self._now_ms(ctx) - self._last_update_ms
            self._E_shown = interpolate(self._E_d, self._E_c, t, self._predictor.delta_t_ms)
        return self._E_shown

    def _ambient(self, ctx, E, positions, normals) -> tuple[np.ndarray, int]:
        """F_a · AO (eq. 4) at the fallback pixels (float32 (M, 3)) and how many of them the ambient grid had no
        value for."""
        p, cg = self.params, self._cg
        A, defined = cg.ambient.values(E, int(p["ambient_iterations"]))
        fa, found = cg.ambient.lookup(A, defined, positions)
        ao_distance_m = float(cg.range_m.max()) if len(cg) else 1.0      # the records' largest reach
        ao = ambient_occlusion(positions, normals, ctx.tracer, int(p["client_ao_rays"]), ao_distance_m,
                               np.random.default_rng(ctx.seed))
        return fa * ao[:, None], int((~found).sum())

    def _reconstruct(self, ctx, g):
        """Irradiance (H, W, 3) at every visible pixel: IDW through G, the ambient function where it is 0/0."""
        p = self.params
        cg = self._cg
        E = self._shown_irradiance(ctx)
        scale = max(1, int(p["irradiance_scale"]))
        sub = (slice(None, None, scale), slice(None, None, scale))
        valid_lo = g.valid[sub]
        pos_lo = g.position[sub][valid_lo]
        nrm_lo = g.normal[sub][valid_lo]
        phi, wsum, visited = idw(cg.grid, cg.position, cg.normal, cg.range_m, E, pos_lo, nrm_lo, float(p["idw_mu"]))
        prim_lo = g.prim[sub][valid_lo]
        dynamic = self._dynamic_faces(ctx.scene)[prim_lo] if prim_lo.size else np.zeros(0, bool)
        zero = (wsum <= 0) & ~dynamic
        fallback = (wsum <= 0) | dynamic
        no_ambient = 0
        if fallback.any():
            phi[fallback], no_ambient = self._ambient(ctx, E, pos_lo[fallback], nrm_lo[fallback])
        lo_img = np.zeros(valid_lo.shape + (3,), np.float32)
        lo_img[valid_lo] = phi
        if scale > 1:
            full = joint_bilateral_upsample(lo_img, valid_lo, g.normal[sub], g.depth[sub], g.normal, g.depth,
                                            g.valid, scale)
        else:
            full = lo_img
        info = {"fallback_pixels": int(fallback.sum()), "zero_weight_pixels": int(zero.sum()),
                "no_ambient_pixels": no_ambient, "irradiance_pixels": int(valid_lo.sum()),
                "records_visited_mean": float(visited.mean()) if len(visited) else 0.0,
                "records_visited_total": int(visited.sum()), "host_device_bytes": 0}
        return full, info

    def _reconstruct_device(self, ctx, g):
        """:meth:`_reconstruct` on the device (device.py): the same values from a DeviceGBuffer, as a Vector3f.
        Host memory is reached for the records' irradiance (uploaded every frame), G after a full transfer, and
        the fallback pixels (F_a·AO on the host, scattered back); ``host_device_bytes`` counts them."""
        from . import device as rdev

        p, cg = self.params, self._cg
        dev = g.device
        dr = dev.dr
        bytes0 = dev.copied_bytes
        E = self._shown_irradiance(ctx)
        if self._device_grid is None or self._device_grid[0] is not cg or self._device_grid[1].dev is not dev:
            self._device_grid = (cg, rdev.DeviceGrid(dev, cg))
        grid = self._device_grid[1]
        scale = max(1, int(p["irradiance_scale"]))
        w, h = g.width, g.height
        if scale > 1:       # the samples at full-resolution pixels (i·scale, j·scale), as the host's [::scale]
            wl, hl = -(-w // scale), -(-h // scale)
            lo = dev.arange(wl * hl)
            src = (lo // wl) * (scale * w) + (lo % wl) * scale
            pos = dr.gather(dev.Point3d, g.position, src)
            nrm = dr.gather(dev.Vector3f, g.normal, src)
            valid_lo = dr.gather(dev.Bool, g.valid, src)
            prim_lo = dr.gather(dev.Int32, g.prim, src)
            depth_lo = dr.gather(dev.Float, g.depth, src)
            dev.eval(pos, nrm, valid_lo, prim_lo, depth_lo)
        else:
            pos, nrm, valid_lo, prim_lo = g.position, g.normal, g.valid, g.prim
        phi, wsum, visited = rdev.idw(grid, grid.irradiance(E), pos, dev.Vector3d(nrm), valid_lo,
                                      float(p["idw_mu"]))
        dynamic = valid_lo & dr.gather(dev.Bool, self._dynamic_table(dev, ctx.scene), dr.maximum(prim_lo, 0),
                                       valid_lo)
        empty = valid_lo & (wsum <= 0.0)
        fallback = empty | dynamic
        dev.eval(fallback, empty)
        n_pixels = int(dr.count(valid_lo)[0])
        n_fallback = int(dr.count(fallback)[0])
        n_zero = int(dr.count(empty & ~dynamic)[0])
        visited_total = dev.sum_u32(visited)
        lo_img = dev.Vector3f(phi)
        no_ambient = 0
        if n_fallback:
            idx = dr.compress(fallback)         # ascending: the host path's order (its AO rays draw in it)
            fa, no_ambient = self._ambient(ctx, E, dev.to_host(dr.gather(dev.Point3d, pos, idx), np.float64),
                                           dev.to_host(dr.gather(dev.Vector3f, nrm, idx), np.float32))
            dr.scatter(lo_img, dev.to_device(np.asarray(fa, np.float32), dev.Vector3f), idx)
            dev.eval(lo_img)
        if scale > 1:
            full = rdev.joint_bilateral_upsample(dev, lo_img, valid_lo, nrm, depth_lo, (wl, hl), g.normal, g.depth,
                                                 g.valid, (w, h), scale)
        else:
            full = lo_img
        info = {"fallback_pixels": n_fallback, "zero_weight_pixels": n_zero, "no_ambient_pixels": no_ambient,
                "irradiance_pixels": n_pixels,
                "records_visited_mean": visited_total / n_pixels if n_pixels else 0.0,
                "records_visited_total": visited_total,
                "host_device_bytes": dev.copied_bytes - bytes0}
        return full, info

    def _dynamic_table(self, dev, scene):
        """:meth:`_dynamic_faces` as a device Bool table (uploaded once per scene and device)."""
        key = (id(dev), scene.name, scene.num_faces)
        if self._dynamic_device is None or self._dynamic_device[0] != key:
            mask = self._dynamic_faces(scene)
            table = dev.to_device(mask if mask.size else np.zeros(1, bool), dev.Bool)
            self._dynamic_device = (key, table)
        return self._dynamic_device[1]

    @staticmethod
    def _dynamic_faces(scene) -> np.ndarray:
        mask = np.zeros(scene.num_faces, bool)
        for anim in scene.object_animations:
            mask |= scene.face_object == anim.object_id
        return mask

    # ----------------------------------------------------------------------------------------------- server

    def _server_state(self):
        if self._acc is None:
            prep = self.prepared
            pts = prep["points"]
            self._points = pts
            self._geometry = prep["grid_geometry"]
            self._cell_start = contained_cells(self._geometry, pts.position)
            self._occupied = np.flatnonzero(np.diff(self._cell_start) > 0)
            self._acc = ProgressiveIrradiance(len(pts))
            self._lights = prep["light_positions"].copy()
            self._intensities = prep["light_intensities"]
        return self._acc

    def server_update(self, ctx) -> None:
        p = self.params
        acc = self._server_state()
        with ctx.stage("request", place="server") as st:
            st.count(codec_bytes=sum(len(m.data or b"") for m in ctx.inbox))
            req = None
            n_changes = 0
            for m in ctx.inbox:
                if m.name != "request" or not m.complete:
                    continue
                try:
                    seq, t_s, pose, fov, changes, flags = wire.decode_request(m.data)
                except wire.WireError:
                    continue
                for li, pos in changes.items():             # scene changes sent by the client (§4.1, §4.3)
                    if 0 <= li < len(self._lights) and not np.array_equal(self._lights[li], pos):
                        self._lights[li] = pos
                        self._pending_change = True
                        n_changes += 1
                req = (seq, t_s, pose, fov, flags)
            if req is not None:
                ctx.scene.camera.add(req[1], req[2])        # the pose is known to the server from here on
        if req is None:
            return                                          # nothing decodable: the client will ask again
        seq, t_s, pose, fov, flags = req
        now_s = ctx.group.start_s
        if ctx.zero_latency:
            # the synchronous formulation (§5.4's zero-latency run): one pass per frame of scene time, shared by
            # the clients whose frames show that time
            due = int(self._last_pass_t != ctx.t_s)
        elif float(p["pass_hz"]) <= 0:
            due = 1
        else:
            due = min(int(p["max_passes_per_update"]),
                      1 if not math.isfinite(self._last_pass_s) else int((now_s - self._last_pass_s) * float(p["pass_hz"])))
        moved = self._last_pass_t is not None and bool(ctx.scene.moved_objects(self._last_pass_t, ctx.t_s))
        restarted = False
        stats = {"pairs": 0, "rays": 0, "vpls": 0}
        with ctx.stage("shade", place="server") as st:
            for k in range(max(0, due)):
                if self._pending_change or moved:
                    acc.restart()
                    restarted = True
                    self._pending_change = moved = False
                rng = np.random.default_rng([ctx.seed, k])
                vpls = trace_light_paths(ctx.scene, ctx.tracer, ctx.t_s, self._lights, self._intensities,
                                         int(p["vpls"]), int(p["vpl_bounces"]), rng,
                                         ctx.scene.area_light_triangles(ctx.t_s))
                E, c = shade_points(self._points.position, self._points.normal, vpls, ctx.tracer,
                                    float(p["vpl_clamp"]) * self._points.spacing_m)
                acc.add(E)
                stats["pairs"] += c["pairs"]
                stats["rays"] += c["rays"]
                stats["vpls"] += len(vpls)
            st.count(points=len(self._points) * max(0, due))
            if due > 0:
                self._last_pass_s = now_s
                self._last_pass_t = ctx.t_s
        shade_ms = ctx.stages[-1].wall_ms
        with ctx.stage("clip", place="server") as st:
            st.count(points=len(self._points) + len(self._occupied))   # quantise + change test, cell tests
            state = self._sent.get(ctx.client)
            full = state is None or bool(flags & NEED_FULL)
            margin = float(p["clip_margin"]) * float(self._points.range_m.max(initial=0.0))
            cells, in_view, scales, codes = select_cells(
                acc.E, self._cell_start, self._occupied, self._geometry, pose, fov, ctx.resolution, margin,
                None if (full or flags & RESYNC) else state, full)
            if state is None:
                state = self._sent[ctx.client] = {"codes": codes.copy(), "scales": scales.copy()}
            remember_sent(state, cells, scales, codes, self._cell_start)
        with ctx.stage("encode", place="server") as st:
            raw, payload = encode_response(cells, scales, codes, self._cell_start, seq, bool(p["lzf"]),
                                           (self._points, self._geometry, self.prepared["ambient_geometry"])
                                           if full else None)
            st.count(codec_bytes=len(raw))
        # The initial transfer of G travels over TCP whatever the run's protocol: a client rejects a damaged
        # message whole, and a ~100 kB grid over a lossy datagram link would almost never arrive intact.
        ctx.send("grid", payload, direction="down", protocol="tcp" if full else ctx.protocol)
        ctx.record(points=len(self._points), passes=max(0, due), vpls=stats["vpls"], pairs=stats["pairs"],
                   shadow_rays=stats["rays"], restarted=restarted, sequence_length=acc.n, light_changes=n_changes,
                   full=full, cells_in_frustum=in_view, cells_sent=len(cells), raw_bytes=len(raw),
                   wire_bytes=len(payload), shade_ms=shade_ms, request_seq=seq)
