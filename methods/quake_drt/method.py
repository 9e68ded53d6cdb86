"""Seed 001 (Bauer, TU Wien 2019/20, "Ray-traced Quake III"): Cook-style distribution ray tracing with PVS light
culling, light subsampling, A-SVGF and TAA, as a local renderer (no server, no network).

Per frame, all on the client (placement ``local``; :mod:`.pipeline` has the stage table):

* **primary** (§6.3, §6.4): G-buffer (position, normals, albedo, material, primitive, motion; the pixel's light
  row comes from the PVS cluster of the hit triangle or point, §4.3.1) and the shading sample of each pixel, with
  anti-aliasing jitter and depth of field when switched on; transparent overlays are blended along the ray in
  order (Algorithm 6.1, the three-surface limitation removed); alpha-tested surfaces are continued where their
  alpha is below the threshold (the tracers alpha-test). On a Dr.Jit backend the G-buffer and the jittered pinhole
  shading samples are device kernels (:mod:`.device_primary`, the host pass's bits on ``llvm_ad_rgb``).
* **secondary** (§6.5): mirrors, glass and water to depth ``max_depth`` (5); all branches (noise-free) or one
  random branch; optional glossy reflections. On ``cuda_ad_rgb`` the chains are a device wavefront
  (:mod:`.device_secondary`, the host pass's bits on ``llvm_ad_rgb``).
* **direct** (§6.6, Algorithm 6.2): for each shaded surface, the lights of its PVS row (Table 4.2; all lights
  with ``cull_lights`` off), ``num_random_dl`` of them chosen (0 = all; uniform with weight n/k, or proportional
  to power), one shadow ray each to a random point of an area light (soft shadows) or the point light. On a
  Dr.Jit backend one device kernel (:mod:`.device_direct`, the host stage's bits on ``llvm_ad_rgb``).
* **A-SVGF** (§6.10, Table 6.9): RNG, forward projection of gradient samples, gradient image, gradient a-trous,
  temporal accumulation with gradient-driven alpha, moments / variance, spatial a-trous (5 passes).
* **composition** (§6.11) and **TAA** (§6.12).

The switches of the thesis's console commands (Table 6.1) are parameters: ``cull_lights`` (rt_cullLights),
``num_random_dl`` (rt_numRandomDL), ``illumination`` (rt_illumination), ``antialiasing``, ``soft_shadows``,
``dof`` / ``dof_aperture_m`` / ``dof_focal_m`` (rt_dof, rt_aperture, rt_focallength), ``denoiser``, ``taa``;
``glossy_reflections`` is Table 2.1's fourth distribution effect. ``rt_accumulate`` (accumulate the paused game)
is the ground truth: with ``gt_frames`` = N > 0, every ``gt_every``-th frame (the last of each block of
``gt_every``) is also rendered N times with new seeds, with the denoiser, TAA and light subsampling off (every
light of the row: the same expectation as any k, far less noise), and the displayed image is compared with that
mean (declared outputs ``gt_*``). That work runs outside the timed stages and is cached, so the variants that
differ only in denoiser, TAA or subsampling share one ground truth.

Placement (``placement``; :meth:`QuakeDRT.place` maps a stage to where it runs):

* ``local`` (the thesis): every stage on the client; no messages.
* ``streamed`` (beyond the thesis, for comparison with the cloud-gaming baseline): the client sends its pose
  (``pose``, TCP); the server decodes it (``server_receive``) and runs every rendering stage above for that pose,
  keeping the denoiser's and TAA's histories of this client; the frame is encoded, sent and decoded exactly as the
  video-streaming baseline does (:func:`suite.core.video.stream_frame`: ``encode`` on the server, the ``video``
  message through netsim, ``decode`` on the client; UDP loss damages the picture until the next IDR frame). The
  outputs ``wire_bytes`` ... ``status`` describe the stream; the ground-truth outputs compare what the client
  shows (the decoded picture).
"""
from __future__ import annotations

import hashlib
import io

import numpy as np

from suite.errors import UserError
from suite.harness.method import Method

from methods.quake_drt import pipeline as pl
from suite.core import video

PLACEMENTS = ("local", "streamed")


class _SceneHere:
    """The scene as the code running now knows it (``ctx.scene``), looked up at every use: the pipeline's stages
    run on the server in the streamed placement, where the camera knows only the poses that arrived."""

    def __init__(self, ctx):
        self._ctx = ctx

    def __getattr__(self, name):
        return getattr(self._ctx.scene, name)


class QuakeDRT(Method):
    """Seed 001's renderer; parameters in config.toml ([doc] explains each)."""

    name = "quake_drt"
    mode = "sync"
    # The streamed placement sends messages; each instance says whether its own placement does (local: no
    # messages, so the zero-latency run would repeat the run and is skipped).
    uses_network = True
    outputs = {
        "pvs_source": "where the light culling's PVS came from: bsp (the map's), computed, scene, none (no culling)",
        "lights": "lights in the light array (point lights + area lights)",
        "shading_points": "surfaces the direct stage lit (primary diffuse hits + ends of specular chains)",
        "candidates_per_point": "mean lights in a shading point's row after culling (Table 4.2's count column)",
        "shaded_per_point": "mean lights chosen per shading point after subsampling (num_random_dl)",
        "shadow_rays": "shadow rays traced by the direct stage",
        "shadow_rays_visible": "of those, unoccluded",
        "points_unclustered": "shading points on triangles in no cluster (they read the all-lights row)",
        "secondary_rays": "reflection / refraction rays traced",
        "overlay_pixels": "pixels with transparent overlays blended in front",
        "gradient_samples": "A-SVGF gradient samples (forward-projected, visible)",
        "antilag_mean": "mean A-SVGF anti-lag lambda over valid pixels (1 = history discarded)",
        "hist_len_mean": "mean A-SVGF history length over valid pixels",
        "hist_len_max": "largest A-SVGF history length",
        "host_device_bytes": "bytes the A-SVGF (stages 5-7) and TAA copied between host and device memory (on a "
                             "Dr.Jit backend, where they run as device kernels and keep their histories there; 0 on "
                             "the host path)",
        "primary_device_bytes": "bytes the primary stage copied between host and device memory (on a Dr.Jit "
                                "backend, where the G-buffer and the jittered shading samples are device kernels: "
                                "both come back to the host; 0 on the host path)",
        "direct_device_bytes": "bytes the direct stage copied between host and device memory (on a Dr.Jit backend, "
                               "where it runs as a device kernel: the shading points and light table up, their "
                               "illumination back; 0 on the host path)",
        "audit_points": "shading points audited for culling errors",
        "audit_pairs": "(point, culled light) pairs the audit traced",
        "audit_missed": "culled pairs whose light actually reaches the point (unoccluded, facing): culling errors",
        "audit_missed_fraction": "audit_missed / audit_pairs",
        "audit_missed_energy": "share of the audited points' direct light that culling removed",
        "gt_frames": "frames accumulated for the ground truth of this frame (0: none)",
        "gt_ssim": "SSIM of the displayed image against the accumulated ground truth",
        "gt_psnr_db": "PSNR (dB) of the displayed image against the accumulated ground truth",
        "gt_nrmse": "NRMSE of the displayed image against the accumulated ground truth",
        "gt_ssim_raw": "SSIM of this frame's undenoised image against the ground truth",
        "gt_ssim_denoised": "SSIM of the denoised image before TAA against the ground truth (denoiser on)",
        "detail_near": "denoised / ground-truth mid-scale luminance contrast (3x3 minus 9x9 blur) on the nearer half "
                       "of the pixels",
        "detail_far": "the same on the farther half (below 1: shadow detail lost; seed 001 §7.5, Fig. 7.14)",
        **{k: f"(streamed) {v}" for k, v in video.STREAM_OUTPUTS.items()},
    }

    def __init__(self, params: dict):
        super().__init__(params)
        placement = str(self.params.get("placement", "local"))
        if placement not in PLACEMENTS:
            raise UserError(f"quake_drt: unknown placement '{placement}' (choose from {', '.join(PLACEMENTS)})")
        self.placement = placement
        self.uses_network = placement == "streamed"  # local: the zero-latency run would repeat this one
        self.settings = pl.Settings.from_params(self.params)
        self.stream_settings = video.StreamSettings.from_params(self.params) if self.uses_network else None
        self.pipeline: pl.Pipeline | None = None
        self._stream: video.Stream | None = None
        self._server_prev_t_s = None

    # ------------------------------------------------------------------------------------------ life cycle

    def prepare(self, scene, tracer):
        return pl.prepare(scene, tracer, self.settings, scene.camera.frame_time_s(0))

    def restore(self, prepared) -> None:
        self.prepared = prepared
        self.pipeline = None

    def reset(self) -> None:
        if self.pipeline is not None:
            self.pipeline.reset()
        self._stream = None
        self._server_prev_t_s = None

    def place(self, stage: str) -> str:
        """Where a rendering stage runs: the client (``local``) or the server (``streamed``)."""
        return "server" if self.placement == "streamed" else "client"

    # ----------------------------------------------------------------------------------------------- frame

    def frame(self, ctx) -> np.ndarray:
        w, h = ctx.resolution
        if self.pipeline is None or (self.pipeline.w, self.pipeline.h) != (w, h):
            self.pipeline = pl.Pipeline(self.settings, self.prepared, w, h)
        p = self.pipeline
        stage = lambda name: ctx.stage(name, place=self.place(name))  # noqa: E731
        if self.placement == "streamed":
            pose_msg = ctx.send_pose(after=[])
            with ctx.stage("server_receive", place="server", after=["pose"]) as st:
                t_s, _ = ctx.receive_pose(pose_msg)
                st.bytes = pose_msg.size_bytes
            # The server renders the pose it received; its motion vectors and histories go back to the previous
            # pose it received from this client.
            rendered, denoised, raw, record = p.run_frame(_SceneHere(ctx), ctx.tracer, t_s, self._server_prev_t_s,
                                                          ctx.seed, stage=stage)
            self._server_prev_t_s = t_s
            if self._stream is None:
                fps = float(ctx.params.get("client_fps") or ctx.scene.camera.fps)
                self._stream = video.Stream(self.stream_settings, w, h, fps)
            out = video.stream_frame(ctx, self._stream, rendered)
        else:
            out, denoised, raw, record = p.run_frame(ctx.scene, ctx.tracer, ctx.t_s, ctx.prev_t_s, ctx.seed,
                                                     stage=stage)
        # Everything below is measurement, not rendering: outside the stages, so neither timed nor counted.
        record.update(p.audit(ctx.scene, ctx.tracer, raw, ctx.seed))
        record.update(self._ground_truth(ctx, p, out, denoised, raw))
        pts = max(record.pop("shading_points"), 1)
        record["shading_points"] = pts
        record["candidates_per_point"] = record.pop("candidates") / pts
        record["shaded_per_point"] = record.pop("selected") / pts
        record["pvs_source"] = self.prepared.table.source
        ctx.record(**{k: v for k, v in record.items() if k in self.outputs})
        return out

    def _cached_ground_truth(self, ctx, p: pl.Pipeline) -> np.ndarray:
        """The accumulated ground truth of this view (:meth:`.pipeline.Pipeline.ground_truth`), cached under
        ``$SPLITBENCH_CACHE/quake_drt/ground_truth/`` (default ./cache): its key is the view, the scene's geometry,
        the lights at this time, the ground-truth settings, the frame count and the method's code, so the runs of
        the variants that differ only in denoiser, TAA or subsampling share one."""
        import json
        import os
        from pathlib import Path

        from suite import fileio
        from suite.harness import results

        scene = ctx.scene
        if getattr(self, "_digest_for", None) is not scene.faces:
            self._digest, self._digest_for = _scene_digest(scene), scene.faces
        pose = scene.camera.pose_at(ctx.t_s)
        gs = p.ground_truth_settings()
        lights = [(lt.name, lt.position.tolist(), lt.intensity.tolist()) for lt in scene.lights_at(ctx.t_s)]
        key_doc = {"scene": self._digest, "t_s": float(ctx.t_s), "resolution": [p.w, p.h],
                   "pose": [np.asarray(x, float).tolist() for x in (pose.position, pose.target, pose.up)],
                   "fov": float(scene.camera.fov_deg), "lights": lights, "frames": int(self.settings.gt_frames),
                   "settings": {k: v for k, v in vars(gs).items()
                                if k not in ("asvgf", "cull_audit_points", "gt_every", "chunk_rays")},
                   "code": results.code_digest("quake_drt"), "pvs": self.prepared.table.source}
        key = hashlib.sha256(json.dumps(key_doc, sort_keys=True, default=str).encode()).hexdigest()[:32]
        root = Path(os.environ.get("SPLITBENCH_CACHE") or os.path.join(os.getcwd(), "cache"))
        path = root / "quake_drt" / "ground_truth" / f"{key}.npy"
        if path.is_file():
            return np.load(path)
        gt = p.ground_truth(ctx.scene, ctx.tracer, ctx.t_s, self.settings.gt_frames)
        path.parent.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        np.save(buf, gt)
        fileio.write_bytes(path, buf.getvalue())
        return gt

    def _ground_truth(self, ctx, p: pl.Pipeline, out, denoised, raw) -> dict:
        s = self.settings
        if s.gt_frames <= 0 or (ctx.index + 1) % s.gt_every != 0:
            return {"gt_frames": 0}
        from suite.core.metrics import compare

        gt = self._cached_ground_truth(ctx, p)
        m = compare(gt, out)
        rec = {"gt_frames": s.gt_frames, "gt_ssim": float(m["ssim"]), "gt_psnr_db": float(m["psnr_db"]),
               "gt_nrmse": float(m["nrmse"]), "gt_ssim_raw": float(compare(gt, raw.compose())["ssim"])}
        if denoised is not None:
            rec["gt_ssim_denoised"] = float(compare(gt, denoised)["ssim"])
            rec.update(detail_ratios(denoised, gt, raw.guides))
        return rec


def _scene_digest(scene) -> str:
    """SHA-256 of what the renderer reads of a scene's geometry and materials (not its camera or lights)."""
    h = hashlib.sha256()
    for a in (scene.positions, scene.normals, scene.uvs, scene.faces, scene.face_material, scene.face_object):
        h.update(np.ascontiguousarray(a).tobytes())
    for m in scene.materials:
        h.update(repr((m.name, m.kind, m.albedo.tolist(), m.emission.tolist(), m.int_ior, m.ext_ior,
                       m.specular_reflectance.tolist(), m.specular_transmittance.tolist(), m.roughness,
                       m.twosided, m.alpha_threshold)).encode())
        for tex in (m.albedo_texture, m.opacity_texture):
            if tex is not None:
                h.update(np.ascontiguousarray(tex).tobytes())
    return h.hexdigest()


def detail_ratios(test: np.ndarray, gt: np.ndarray, guides) -> dict:
    """Mid-scale contrast of ``test`` over that of ``gt`` on the nearer and the farther half of the valid pixels
    (split at the median depth). Contrast is the band of luminance between a 3x3 and a 9x9 box blur: shadow edges
    and penumbrae a few pixels wide, not pixel noise (which the 3x3 blur removes). A denoiser that washes shadows
    out gives ratios below 1; the thesis sees the loss grow with distance (§7.5, Fig. 7.14)."""
    from scipy.ndimage import uniform_filter

    from suite.core.denoise import luminance

    def band(img):
        lum = luminance(img).astype(np.float64)
        return np.abs(uniform_filter(lum, 3, mode="nearest") - uniform_filter(lum, 9, mode="nearest"))

    valid = guides.valid
    if not valid.any():
        return {}
    bt, bg = band(test), band(gt)
    median = np.median(guides.depth[valid])
    out = {}
    for name, sel in (("detail_near", valid & (guides.depth <= median)), ("detail_far", valid & (guides.depth > median))):
        ref = bg[sel].sum()
        out[name] = float(bt[sel].sum() / ref) if ref > 0 else float("nan")
    return out
