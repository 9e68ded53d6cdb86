"""One frame of seed 001's renderer, stage by stage (chapter 6), independent of the harness.

:class:`Pipeline` holds what lives across frames (the light array and its culling table, the denoiser's and
TAA's histories) and runs a frame as a sequence of stages, each inside ``stage(name)`` (the harness's
``ctx.stage`` in :mod:`.method`; a no-op in tests and benchmarks):

==========================  =====================================================================================
stage                       what (thesis)
==========================  =====================================================================================
``asvgf_rng_forward``       per-pixel seeds; A-SVGF forward projection of gradient samples (Table 6.9 rows 1-2)
``primary``                 G-buffer and shading samples: AA jitter, depth of field, transparent overlays (§6.3-6.4);
                            each surface's light-table row from its (merged) cluster (Table 6.4, §4.3.1)
``secondary``               mirror / glass / water chains to ``max_depth`` (§6.5), rows of the surfaces they reach;
                            skipped without such pixels
``direct``                  culled rows (§4.3), subsampling (``rt_numRandomDL``), shadow rays, Alg. 6.2 (§6.6)
``asvgf_gradient``          gradient image of the forward-projected samples (Table 6.9 row 3)
``asvgf_gradient_atrous``   dense gradient and anti-lag lambda (row 4)
``asvgf_temporal``          temporal accumulation with gradient-driven alpha (row 5)
``asvgf_variance``          luminance moments and variance
``asvgf_atrous``            spatial a-trous, 5 passes (row 6)
``composition``             illumination x albedo + emission, overlays blended on top (§6.11)
``taa``                     temporal anti-aliasing (§6.12, row 7)
==========================  =====================================================================================

Denoiser stages run only with ``denoiser`` on, ``taa`` only with ``taa`` on. :func:`Pipeline.raw_frame` renders
the undenoised image of one seed; the accumulated ground truth (§7.2: "the accumulation of 1500 frames of the
paused game with the same configuration") averages ``gt_frames`` of them (:meth:`Pipeline.ground_truth`).
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numba
import numpy as np

from methods.quake_drt import asvgf as asvgf_mod
from methods.quake_drt import culling, direct, lights as lights_mod, primary, rng, secondary
from methods.quake_drt.taa import TAA
from suite.errors import UserError


GT_SEED = 0x5EED0000  # frame seeds of the accumulated ground truth: GT_SEED, GT_SEED + 1, ...


@dataclass
class Settings:
    """The method's parameters (config.toml [defaults] documents each)."""

    cull_lights: bool = True
    num_random_dl: int = 1
    light_sampling: str = "uniform"
    area_light_unit: str = "polygon"
    pvs: str = "auto"
    pvs_symmetric: bool = True
    pixel_cluster: str = "triangle"
    cluster_probe_m: float = 0.0254
    illumination: bool = True
    antialiasing: bool = True
    soft_shadows: bool = True
    dof: bool = False
    dof_aperture_m: float = 0.02
    dof_focal_m: float = 3.0
    glossy_reflections: bool = False
    glossy_cone_deg: float = 5.0
    max_depth: int = 5
    all_branches: bool = True
    transparency: str = "blend"
    overlay_alpha: float = 0.5
    denoiser: bool = True
    taa: bool = True
    taa_alpha: float = 0.1
    taa_clamp_sigma: float = 1.0
    asvgf: asvgf_mod.ASVGFSettings = field(default_factory=asvgf_mod.ASVGFSettings)
    spp: int = 1
    cull_audit_points: int = 256
    gt_frames: int = 0
    gt_every: int = 8
    chunk_rays: int = direct.DEFAULT_CHUNK_RAYS

    @classmethod
    def from_params(cls, p: dict) -> "Settings":
        a = asvgf_mod.ASVGFSettings(
            antilag=bool(p.get("asvgf_antilag", True)),
            gradient_iterations=int(p.get("asvgf_gradient_iterations", 5)),
            gradient_sigma=float(p.get("asvgf_gradient_sigma", 4.0)),
            history_cap=int(p.get("asvgf_history_cap", 256)),
            alpha_color=float(p.get("asvgf_alpha_color", 0.075)),
            alpha_moments=float(p.get("asvgf_alpha_moments", 0.1)),
            depth_tolerance=float(p.get("asvgf_depth_tolerance", 2.0)),
            atrous_iterations=int(p.get("asvgf_atrous_iterations", 5)),
            atrous_radius=int(p.get("asvgf_atrous_radius", 1)),
            phi_color=float(p.get("asvgf_phi_color", 10.0)),
            phi_normal=float(p.get("asvgf_phi_normal", 128.0)),
            phi_depth=float(p.get("asvgf_phi_depth", 1.0)),
            feedback_tap=int(p.get("asvgf_feedback_tap", 0)))
        keys = {f for f in cls.__dataclass_fields__ if f != "asvgf"}
        s = cls(asvgf=a, **{k: p[k] for k in keys if k in p})
        s.validate()
        return s

    def validate(self) -> None:
        checks = [
            (self.num_random_dl >= 0, f"num_random_dl must be >= 0 (0 = all lights), got {self.num_random_dl}"),
            (self.light_sampling in direct.MODES, f"light_sampling must be one of {direct.MODES}"),
            (self.area_light_unit in lights_mod.UNITS, f"area_light_unit must be one of {lights_mod.UNITS}"),
            (self.pvs in culling.PVS_SOURCES, f"pvs must be one of {culling.PVS_SOURCES}"),
            (self.pixel_cluster in culling.PIXEL_CLUSTER_RULES,
             f"pixel_cluster must be one of {culling.PIXEL_CLUSTER_RULES}"),
            (self.cluster_probe_m > 0, "cluster_probe_m must be > 0"),
            (self.dof_aperture_m >= 0 and self.dof_focal_m > 0, "dof_aperture_m must be >= 0, dof_focal_m > 0"),
            (0.0 <= self.glossy_cone_deg < 90.0, "glossy_cone_deg must be in [0, 90)"),
            (self.max_depth >= 0, "max_depth must be >= 0"),
            (self.transparency in primary.TRANSPARENCY_MODES,
             f"transparency must be one of {primary.TRANSPARENCY_MODES}"),
            (0.0 <= self.overlay_alpha <= 1.0, "overlay_alpha must be in [0, 1]"),
            (0.0 < self.taa_alpha <= 1.0, "taa_alpha must be in (0, 1]"),
            (self.taa_clamp_sigma >= 0, "taa_clamp_sigma must be >= 0"),
            (self.cull_audit_points >= 0 and self.gt_frames >= 0 and self.gt_every >= 1,
             "cull_audit_points and gt_frames must be >= 0, gt_every >= 1"),
            (self.chunk_rays >= 1024, "chunk_rays must be >= 1024"),
            (self.spp >= 1, "spp must be >= 1"),
            (self.spp == 1 or not self.denoiser,
             "spp > 1 (traditional samples per pixel) needs denoiser = false: A-SVGF shades one sample per pixel"),
            (self.asvgf.history_cap >= 1 and self.asvgf.atrous_iterations >= 0
             and self.asvgf.gradient_iterations >= 0 and self.asvgf.atrous_radius in (1, 2),
             "asvgf_history_cap >= 1, iterations >= 0, asvgf_atrous_radius 1 or 2"),
            (0.0 < self.asvgf.alpha_color <= 1.0 and 0.0 < self.asvgf.alpha_moments <= 1.0,
             "asvgf_alpha_color and asvgf_alpha_moments must be in (0, 1]"),
        ]
        for ok, message in checks:
            if not ok:
                raise UserError(message)


@dataclass
class Prepared:
    """What ``Method.prepare`` computes once: the light array, its clusters and the visibility table."""

    lights: lights_mod.LightList
    table: culling.CullTable
    visibility: object | None  # a computed visibility (the scene's own is read from the scene)


class _NoStage:
    pixels = 0
    bytes = 0

    def count(self, **work):
        pass


@contextmanager
def no_stage(name):
    yield _NoStage()


def prepare(scene, tracer, settings: Settings, t_s: float) -> Prepared:
    lights = lights_mod.build_lights(scene, t_s, settings.area_light_unit)
    vis, source = culling.resolve_visibility(scene, tracer, settings.pvs)
    table = culling.build_table(vis, source, lights, scene.num_faces, settings.cluster_probe_m,
                                settings.pvs_symmetric, scene.bounds())
    own = getattr(scene, "visibility", None)
    return Prepared(lights, table, None if vis is own else vis)


@dataclass
class RawFrame:
    """The undenoised frame and what produced it."""

    g: object
    surface: primary.Surface
    seeds: np.ndarray
    illum: np.ndarray  # (H, W, 3) demodulated direct illumination
    albedo: np.ndarray  # (H, W, 3) effective albedo (sum over the pixel's shading points of weight x albedo)
    emission: np.ndarray  # (H, W, 3) emission along the primary and secondary rays
    guides: asvgf_mod.Guides
    info: dict

    def compose(self, illum=None, illumination: bool = True) -> np.ndarray:
        """Composition (§6.11): illumination x albedo + emission, overlays blended on top."""
        il = self.illum if illum is None else illum
        rgb = (il * self.albedo if illumination else self.albedo) + self.emission
        h, w = rgb.shape[:2]
        s = self.surface
        rgb = s.overlay_rgb.reshape(h, w, 3) + s.overlay_t.reshape(h, w, 1) * rgb
        return rgb.astype(np.float32)


class Pipeline:
    """Seed 001's renderer for one resolution (module docstring)."""

    def __init__(self, settings: Settings, prep: Prepared, width: int, height: int):
        self.s = settings
        self.prep = prep
        self.w, self.h = int(width), int(height)
        self.denoiser = asvgf_mod.ASVGF(settings.asvgf, self.w, self.h)
        self.taa = TAA(settings.taa_alpha, settings.taa_clamp_sigma)
        self._taa_dev = None  # the TAA on a tracer's Dr.Jit device (_device_taa)
        self._overlay_cache = {}

    def reset(self) -> None:
        self.denoiser.reset()
        self.taa.reset()
        self._taa_dev = None

    # -- helpers ----------------------------------------------------------------------------------------------

    def _overlays(self, scene):
        key = id(scene.faces)
        if key not in self._overlay_cache:
            self._overlay_cache[key] = primary.overlay_faces(scene, self.s.transparency)
        return self._overlay_cache[key]

    def _visibility(self, scene):
        return self.prep.visibility if self.prep.visibility is not None else getattr(scene, "visibility", None)

    def _primary_points(self, scene, s: primary.Surface, seeds) -> direct.ShadingPoints:
        spec = np.array([m.is_specular for m in scene.materials], bool)
        rows = np.nonzero(s.valid & ~spec[np.maximum(s.material, 0)])[0]
        at = lambda a: np.take(a, rows, axis=0)  # noqa: E731 (about 4x faster than a[rows] on (N, 3) rows)
        wi = -at(s.d)
        mat = at(s.material)
        return direct.ShadingPoints(pixel=rows, throughput=np.ones((len(rows), 3)), p=at(s.p), ng=at(s.ng_view),
                                    ns=secondary.bsdf_normal(scene, mat, at(s.ns_view), at(s.ns), wi), wi=wi,
                                    albedo=at(s.albedo), material=mat, prim=at(s.prim),
                                    seed=at(np.asarray(seeds, np.uint32)), lambert=secondary.lambert_mask(scene, mat))

    # -- the undenoised frame ---------------------------------------------------------------------------------

    def raw_frame(self, scene, tracer, t_s: float, prev_t_s, seeds: np.ndarray, fwd=None, stage=no_stage,
                  lights=None, suffix: str = "") -> RawFrame:
        """Primary, secondary and direct stages for per-pixel ``seeds``; ``fwd``: gradient samples to re-shade.
        ``suffix`` is appended to the stage names (the extra samples of ``spp`` > 1)."""
        s, w, h = self.s, self.w, self.h
        named = stage
        stage = lambda name: named(name + suffix)  # noqa: E731
        n = w * h
        info = {}
        overlay = self._overlays(scene)
        skip = None if overlay is None else overlay > 0
        table = self.prep.table
        vis = self._visibility(scene)

        def rows_of(p: direct.ShadingPoints) -> np.ndarray:
            # The light-table row of each surface: its (merged) cluster, the G-buffer's cluster of Table 6.4.
            return culling.point_rows(table, vis, p.prim, p.p, p.ng, s.pixel_cluster, s.cluster_probe_m,
                                      s.cull_lights)

        dev = getattr(tracer, "device", None)
        with stage("primary") as st:
            copied0 = dev.copied_bytes if dev is not None else 0
            g, surf = primary.primary_stage(scene, tracer, t_s, prev_t_s, (w, h), seeds, s.antialiasing,
                                            s.dof_aperture_m if s.dof else 0.0, s.dof_focal_m, overlay,
                                            s.overlay_alpha)
            if fwd is not None and len(fwd):
                fwd = fwd.subset(asvgf_mod.ASVGF.visible(fwd, g))
                primary.forwarded_surface(scene, t_s, surf, fwd.cur, fwd.prim, fwd.u, fwd.v)
            prim_pts = self._primary_points(scene, surf, seeds)
            prim_rows = rows_of(prim_pts)
            st.pixels = n
        # on a Dr.Jit backend the G-buffer and the jittered shading samples are device kernels whose results come
        # back to the host for the stages after this one (methods/quake_drt/device_primary.py)
        info["primary_device_bytes"] = (dev.copied_bytes - copied0) if dev is not None else 0
        info["overlay_pixels"] = surf.n_overlay_pixels
        info["fwd"] = fwd
        spec = np.array([m.is_specular for m in scene.materials], bool)
        sec = None
        if (surf.valid & spec[np.maximum(surf.material, 0)]).any() and s.max_depth > 0:
            with stage("secondary") as st:
                sec = secondary.secondary_stage(scene, tracer, t_s, surf, seeds, s.max_depth, s.all_branches,
                                                s.glossy_reflections, s.glossy_cone_deg, skip)
                sec_rows = rows_of(sec.points)
                st.pixels = len(sec.guide_pixel)  # one guide per pixel that has a shading point: no np.unique
        info["secondary_rays"] = sec.rays if sec is not None else 0
        lights = lights if lights is not None else lights_mod.refresh(self.prep.lights, scene, t_s)
        with stage("direct") as st:
            pts = direct.ShadingPoints.concat([prim_pts, sec.points if sec is not None else None])
            rows = np.concatenate([prim_rows, sec_rows]) if sec is not None else prim_rows
            copied0 = dev.copied_bytes if dev is not None else 0
            if s.illumination:
                # on a Dr.Jit backend a device kernel (methods/quake_drt/device_direct.py): the points go up, their
                # illumination comes back (counted in direct_device_bytes)
                il, stats = direct.shade(pts, lights, table, rows, s.num_random_dl, s.light_sampling,
                                         s.soft_shadows, tracer, scene, _min_distance(scene), s.chunk_rays, skip)
            else:
                il, stats = np.zeros((len(pts), 3)), direct.DirectStats()
            illum, albedo = demodulate(pts, il, n)
            guides = self._guides(g, surf, sec, scene, t_s)  # the filters' guides, from what this frame traced
            st.pixels = n
        emission = surf.emission.copy()
        if sec is not None:
            emission += sec.emission
        info.update(direct_device_bytes=(dev.copied_bytes - copied0) if dev is not None else 0, lights=len(lights),
                    shading_points=len(pts), candidates=stats.candidates, selected=stats.selected,
                    shadow_rays=stats.rays, shadow_rays_visible=stats.visible,
                    points_unclustered=int((rows == table.all_row).sum()) if s.cull_lights and table.n_clusters else 0,
                    rows=rows, points=pts, lights_obj=lights)
        return RawFrame(g, surf, np.asarray(seeds, np.uint32), illum.reshape(h, w, 3), albedo.reshape(h, w, 3),
                        emission.reshape(h, w, 3), guides, info)

    def _guides(self, g, surf, sec, scene, t_s) -> asvgf_mod.Guides:
        fdepth = g.depth.astype(np.float64).copy()
        fnormal = g.normal.astype(np.float64).copy()
        if sec is not None and len(sec.guide_pixel):
            fdepth.reshape(-1)[sec.guide_pixel] = sec.guide_depth
            fnormal.reshape(-1, 3)[sec.guide_pixel] = sec.guide_n
        valid = g.valid
        depth = np.where(valid, g.depth, 0.0)
        cam = np.asarray(scene.camera.pose_at(t_s).position, np.float64)
        return asvgf_mod.Guides(valid=valid, point=g.position.astype(np.float64), depth=depth,
                                normal=g.normal.astype(np.float32), motion=g.motion.astype(np.float32),
                                filter_depth=np.where(valid, fdepth, 0.0), filter_normal=fnormal, camera=cam)

    # -- a full frame -----------------------------------------------------------------------------------------

    def run_frame(self, scene, tracer, t_s: float, prev_t_s, frame_seed: int, stage=no_stage):
        """(displayed image, denoised image before TAA or None, raw frame, record of per-frame facts)."""
        s, w, h = self.s, self.w, self.h
        den = self.denoiser
        den.device = getattr(tracer, "device", None)  # a Dr.Jit backend's: the filters run there
        den.copied_bytes = 0
        with stage("asvgf_rng_forward") as st:
            seeds = rng.pixel_seeds(frame_seed, w, h).reshape(-1)
            fwd = None
            if s.denoiser:
                fwd = den.forward_project(scene, t_s)
                seeds = den.seeds_with_gradients(seeds, fwd)
            st.pixels = w * h
        raw = self.raw_frame(scene, tracer, t_s, prev_t_s, seeds, fwd, stage)
        fwd = raw.info.pop("fwd")
        record = {k: v for k, v in raw.info.items() if k not in ("rows", "points", "lights_obj")}
        extra = []
        for i in range(1, s.spp):
            # Traditional samples (§7.3.1, Fig. 7.11): the whole frame again with other seeds, averaged.
            more = rng.pixel_seeds(int(rng.pcg_np(np.uint32((frame_seed + 0x2545F491 * i) & 0xFFFFFFFF))), w, h)
            extra.append(self.raw_frame(scene, tracer, t_s, prev_t_s, more.reshape(-1), None, stage,
                                        suffix=f"_s{i + 1}"))
            for key in ("shadow_rays", "shadow_rays_visible", "candidates", "selected", "shading_points",
                        "secondary_rays", "primary_device_bytes", "direct_device_bytes"):
                record[key] += extra[-1].info[key]
        denoised = None
        if s.denoiser:
            with stage("asvgf_gradient") as st:
                grad = den.gradient(raw.illum, fwd, st)
            with stage("asvgf_gradient_atrous") as st:
                lam = den.gradient_atrous(grad, st)
                alag = den.antilag(lam)
            with stage("asvgf_temporal") as st:
                color, moments, hist, _ = den.temporal(raw.illum, raw.guides, alag, st)
            with stage("asvgf_variance") as st:
                var = den.variance(raw.illum, moments, hist, raw.guides, st)
            with stage("asvgf_atrous") as st:
                filtered, fed_back = den.atrous(color, var, raw.guides, st)
                den.end_frame(raw.surface, raw.seeds, raw.illum, fed_back if fed_back is not None else color,
                              moments, hist, raw.guides)
            valid = raw.guides.valid
            hist_mean, hist_max = den.stats(hist, valid)
            record.update(gradient_samples=int(len(fwd)) if fwd is not None else 0,
                          antilag_mean=den.stats(alag, valid)[0], hist_len_mean=hist_mean, hist_len_max=hist_max)
            with stage("composition") as st:
                denoised = raw.compose(filtered, s.illumination)
                st.pixels = w * h
            out = denoised
        else:
            with stage("composition") as st:
                out = raw.compose(None, s.illumination)
                if extra:
                    out = (out + sum(x.compose(None, s.illumination) for x in extra)) / (1 + len(extra))
                st.pixels = w * h
        if s.taa:
            with stage("taa") as st:
                if den.device is not None:  # the history stays on the device
                    out = den.counted_copies(lambda: self._device_taa(den.device)(out, raw.g.motion))
                    st.count(taps=w * h * (9 + 9 + 16))
                else:
                    out = self.taa(out, raw.g.motion, st)
        if s.denoiser or s.taa:
            record["host_device_bytes"] = den.copied_bytes
        return out, denoised, raw, record

    def _device_taa(self, device):
        """The TAA whose history lives on ``device`` (methods/quake_drt/device.py), made on first use; it takes over
        the host TAA's history."""
        from methods.quake_drt.device import DeviceTAA

        if self._taa_dev is None or self._taa_dev.dev is not device:
            t = self.taa
            self._taa_dev = DeviceTAA(device, t.alpha, t.clamp_sigma, t.firefly_sigma)
            if t.history is not None:
                self._taa_dev.set_history(t.history)
        return self._taa_dev

    # -- ground truth and audit (outside the timed stages) ----------------------------------------------------

    def ground_truth_settings(self) -> Settings:
        """The ground truth's configuration: this one with the denoiser, TAA and light subsampling off. Every light
        of the row per frame has the same expectation as any k (the estimator is unbiased) and far less noise, so
        the N accumulated frames converge much further; culling stays on where there is a PVS (exact where the
        PVS is conservative, which the culling audit checks), since it too only saves rays."""
        import dataclasses

        return dataclasses.replace(self.s, num_random_dl=0, denoiser=False, taa=False, spp=1,
                                   cull_lights=self.s.cull_lights or self.prep.table.n_clusters > 0)

    def ground_truth(self, scene, tracer, t_s: float, frames: int) -> np.ndarray:
        """The mean of ``frames`` undenoised frames of the paused scene (§7.2's accumulated ground truth) in the
        :meth:`ground_truth_settings`; frame i uses the seeds of frame seed ``GT_SEED + i`` whatever the run's
        seed, so one ground truth serves every run of the same view and configuration."""
        gt = Pipeline(self.ground_truth_settings(), self.prep, self.w, self.h)
        acc = np.zeros((self.h, self.w, 3))
        for i in range(frames):
            seeds = rng.pixel_seeds(GT_SEED + i, self.w, self.h).reshape(-1)
            acc += gt.raw_frame(scene, tracer, t_s, None, seeds).compose(None, self.s.illumination)
        return (acc / max(frames, 1)).astype(np.float32)

    def audit(self, scene, tracer, raw: RawFrame, sample_seed: int) -> dict:
        """How often culling drops a light that contributes: for ``cull_audit_points`` random shading points,
        one shadow ray to each light their row does not hold. Returns the counts (module :mod:`.culling`)."""
        s = self.s
        pts, rows, lights = raw.info["points"], raw.info["rows"], raw.info["lights_obj"]
        table = self.prep.table
        empty = {"audit_points": 0, "audit_pairs": 0, "audit_missed": 0, "audit_missed_fraction": 0.0,
                 "audit_missed_energy": 0.0}
        if not s.cull_lights or s.cull_audit_points == 0 or len(pts) == 0 or table.n_clusters == 0 \
                or not s.illumination:
            return empty
        pick = np.random.default_rng(sample_seed).choice(len(pts), min(s.cull_audit_points, len(pts)), replace=False)
        sub = pts.subset(np.sort(pick))
        sub_rows = rows[np.sort(pick)]
        offs, lids = culling.culled_lights(table, sub_rows, len(lights))
        culled = culling.CullTable(table.source, 0, table.symmetric, table.light_cluster_offsets,
                                   table.light_cluster_ids, table.light_unclustered, offs, lids,
                                   table.tri_row, table.all_row)
        ident = np.arange(len(sub), dtype=np.int64)
        md = _min_distance(scene)
        skip = self._overlays(scene)
        skip = None if skip is None else skip > 0
        missed_il, st = direct.shade(sub, lights, culled, ident, 0, "uniform", s.soft_shadows, tracer, scene, md,
                                     s.chunk_rays, skip)
        kept_il, _ = direct.shade(sub, lights, table, sub_rows, 0, "uniform", s.soft_shadows, tracer, scene, md,
                                  s.chunk_rays, skip)
        m = missed_il.sum(axis=1)
        total = m.sum() + kept_il.sum()
        return {"audit_points": int(len(sub)), "audit_pairs": int(len(lids)), "audit_missed": int(st.visible),
                "audit_missed_fraction": float(st.visible / max(len(lids), 1)),
                "audit_missed_energy": float(m.sum() / total) if total > 0 else 0.0}


def _min_distance(scene) -> float:
    from suite.core.shading import min_light_distance

    return min_light_distance(scene)


def demodulate_reference(pts: direct.ShadingPoints, il: np.ndarray, n: int):
    """(illumination, albedo) per pixel of ``n`` from the shading points' illumination ``il``: radiance and albedo
    (the point's throughput times its albedo, 1 for glossy points) summed per pixel in point order
    (``np.bincount``), the illumination their ratio where the albedo exceeds 1e-6, else the radiance over an albedo
    of 1 (or the albedo itself where there is no radiance)."""
    weight = pts.throughput * np.where(pts.lambert[:, None], pts.albedo, 1.0)
    radiance = np.zeros((n, 3))
    albedo = np.zeros((n, 3))
    for c in range(3):
        radiance[:, c] = np.bincount(pts.pixel, weights=weight[:, c] * il[:, c], minlength=n)
        albedo[:, c] = np.bincount(pts.pixel, weights=weight[:, c], minlength=n)
    ok = albedo > 1e-6
    illum = np.where(ok, radiance / np.where(ok, albedo, 1.0), radiance)
    return illum, np.where(ok, albedo, np.where(radiance > 0, 1.0, albedo))


def demodulate(pts: direct.ShadingPoints, il: np.ndarray, n: int):
    """:func:`demodulate_reference` in one compiled pass (the same sums in the same order: its bits)."""
    pixel = np.ascontiguousarray(pts.pixel, np.int64)
    if len(pixel) and (pixel.min() < 0 or pixel.max() >= n):
        raise ValueError(f"shading points of pixels outside the {n}-pixel frame")
    illum, albedo = np.empty((n, 3)), np.empty((n, 3))
    _demodulate_kernel(pixel, np.ascontiguousarray(pts.throughput, np.float64),
                       np.ascontiguousarray(pts.lambert, np.bool_), np.ascontiguousarray(pts.albedo, np.float64),
                       np.ascontiguousarray(il, np.float64), illum, albedo)
    return illum, albedo


@numba.njit(cache=True, nogil=True)
def _demodulate_kernel(pixel, throughput, lambert, point_albedo, il, illum, albedo):
    radiance = np.zeros(illum.shape)
    albedo[:] = 0.0
    for i in range(pixel.shape[0]):
        p = pixel[i]
        for c in range(3):
            w = throughput[i, c] * (point_albedo[i, c] if lambert[i] else 1.0)
            radiance[p, c] += w * il[i, c]
            albedo[p, c] += w
    for p in range(illum.shape[0]):
        for c in range(3):
            a, r = albedo[p, c], radiance[p, c]
            if a > 1e-6:
                illum[p, c] = r / a
            else:
                illum[p, c] = r
                albedo[p, c] = 1.0 if r > 0 else a
