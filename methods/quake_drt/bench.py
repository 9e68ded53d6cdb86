"""Benchmarks of seed 001's renderer: ``splitbench bench quake_drt`` (or ``python -m methods.quake_drt.bench``).

Parts (``--parts``, default all), printed and stored in ``<results>/bench/quake_drt.json`` (``--out``, default
``results``; a part that runs replaces its entry, the others are kept), so that the report shows them without
running anything:

``rays``
    Rays per second of the tracing stages against the backend's raw rate on the very same rays, medians of
    ``--repeats`` calls of stage and raw in turn (at least :data:`SHORT_STAGE_REPEATS` for the primary and secondary
    stages: a few tens of milliseconds each, whose ratio a single slow call moves; ``ratio_range``: the lowest and
    highest ratio of one repeat's stage and raw calls): the primary stage (G-buffer plus
    anti-aliased shading rays, attributes, overlays; on a Dr.Jit backend both are device kernels,
    methods/quake_drt/device_primary.py) against the raw closest-hit query on its two camera ray sets; the direct stage
    (light rows, subsampling, ray generation, shadow rays, accumulation) against the raw occlusion query on the rays it
    generated (captured from an untimed run; on a Dr.Jit backend the stage is the device kernel of
    methods/quake_drt/device_direct.py, and its rays are recorded per iteration of its loop over light samples, in the
    order it traces them; ``light_samples`` counts the samples it evaluated, of which only those above the point's
    horizon and in front of their emitter trace a ray, the rays raw traces); the secondary stage (mirror, glass and
    water chains to depth 5, all branches) against the raw closest-hit query on the continuation rays it traced
    (recorded in an untimed run; where the chains run on the device, methods/quake_drt/device_secondary.py, they record
    their rays there). On a Mitsuba llvm/cuda backend raw is the backend on those rays in device memory (uploaded once,
    outside the timed calls); the numpy-fed raw entry points are timed beside it (``raw_numpy_ms``, ``ratio_numpy``).
    The secondary stage needs specular surfaces in view: on a scene without them (the OpenArena benchmark levels have
    none) it is measured on :data:`SECONDARY_SCENE` at the same resolution, and its entry names the scene. Settings:
    the paper's pipeline with every culled light (``num_random_dl`` 0), so the direct stage has work. ``by_pixels``:
    each stage's ms and ratio at that size and at the ``--rays-larger`` sizes (a stage's fixed costs weigh less as the
    pixels grow). ``on_devices``: the same at ``--resolution`` on each Dr.Jit backend of ``--device`` beside
    ``--backend`` (what the device path, and a GPU where there is one, changes).
``asvgf``
    Milliseconds of each denoiser stage (Table 6.9: gradient, gradient a-trous, temporal, variance, a-trous) and of
    TAA at several resolutions, on frames the renderer made (the third frame of a paused camera, so the history
    is in use), with the filter taps each stage declares (its work counter, independent of the machine); beside
    them the temporal, variance and a-trous stages and TAA on each Dr.Jit device that works here (``--device``;
    methods/quake_drt/device.py and suite.core.device.denoise, the frame's copies to and from the device included,
    the histories on the device: ``llvm_temporal_ms``, ...);
    ``ms = a * megapixels`` fitted through the origin to the total (a positive rate whenever the times are, however
    noisy two sizes are) and the exponent of ms against pixels. Seed 001 Fig. 7.8 measures the same on a GPU.
``lights``
    The direct stage against the light count: every light of the map (no culling), the culled rows (all of their
    lights), and k = 1, 4, 16 random culled lights (uniform and power-proportional at k = 1), at one resolution;
    then k = 1 and all culled lights at several resolutions (cost against pixels).

Every part records its scene, backend and resolution; the document records where it ran (``packages``, ``host``,
``git``) as a run's config.json does. Times are wall times of this machine and backend; they compare parts of one
run with each other, not machines.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from methods.quake_drt import culling, direct
from methods.quake_drt import pipeline as pl
from suite.core.trace.recording import RecordingTracer

SCHEMA_VERSION = 1
PARTS = ("rays", "asvgf", "lights")
DEFAULT_SCENE = "oa:aggressor@pak1-maps"
FALLBACK_SCENE = "two_rooms"  # methods/quake_drt/testscenes.py, when the OpenArena data is missing
SECONDARY_SCENE = "gallery"  # embedded: a mirror and glass in view, for the secondary stage of a scene without them
SHORT_STAGE_REPEATS = 11  # the fewest repeats of the primary and secondary stages in part rays


def _median_ms(fn, repeats: int, device=None):
    """(median ms over ``repeats`` calls after one warm-up, last result). ``device``: a Dr.Jit device whose work each
    call waits for (its kernels run asynchronously; a stage that leaves its results on the device would otherwise
    be timed without them)."""
    result = fn()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        result = fn()
        if device is not None:
            device.sync()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), result


def _against_raw(stage, log, tracer, repeats: int, numpy_raw, records=()) -> dict:
    """``ms`` of ``stage`` and ``raw_ms`` of the backend alone on the stage's rays (``log``: ``("i" | "o", origins,
    directions, lengths)`` in the tracing frame; ``records``: ``("i" | "o", Ray3f)`` a device pass recorded), run in
    turn (medians). On a Dr.Jit backend raw is the backend on rays in device memory (``log`` uploaded once, here:
    :func:`suite.core.trace.recording.device_replay`), and the numpy-fed raw entry points (``numpy_raw``) are timed
    beside it as ``raw_numpy_ms``; elsewhere raw is ``numpy_raw``."""
    from suite.core.trace.bench import interleaved_times, medians, paired_range
    from suite.core.trace.recording import device_replay

    dev = getattr(tracer, "device", None)
    if dev is None:
        times = interleaved_times([("stage", stage), ("raw", numpy_raw)], repeats)
        t = medians(times)
        return {"ms": 1e3 * t["stage"], "raw_ms": 1e3 * t["raw"], "raw": "raw entry points",
                "time_ratio_range": paired_range(times["raw"], times["stage"])}
    _, replay = device_replay(dev, log, records)
    times = interleaved_times([("stage", stage), ("raw", replay), ("raw_numpy", numpy_raw)], repeats)
    t = medians(times)
    return {"ms": 1e3 * t["stage"], "raw_ms": 1e3 * t["raw"], "raw": "device-resident rays",
            "raw_numpy_ms": 1e3 * t["raw_numpy"], "time_ratio_range": paired_range(times["raw"], times["stage"])}


def _host_rays(dev, records) -> list:
    """``(origins, directions, lengths)`` float32 host copies of recorded device rays (``("i" | "o", Ray3f)``): what
    the numpy-fed raw entry points trace."""
    return [tuple(dev.to_host_all([ray.o, ray.d, ray.maxt], [np.float32] * 3)) for _, ray in records]


def _rates(entry: dict, rays: int, raw_rays: int) -> dict:
    """The entry's rays per second and its ratios to raw (and to the numpy-fed raw where it was timed);
    ``ratio_range``: the lowest and highest ratio of one repeat's stage and raw calls, which ran next to each other."""
    ms, raw_ms = entry["ms"], entry["raw_ms"]
    out = {k: v for k, v in entry.items() if k != "time_ratio_range"}
    out.update(rays=rays, rays_per_s=rays / (ms / 1e3), raw_rays=raw_rays, raw_rays_per_s=raw_rays / (raw_ms / 1e3),
               ratio=(rays / ms) / (raw_rays / raw_ms))
    if "time_ratio_range" in entry:
        out["ratio_range"] = [rays / raw_rays * r for r in entry["time_ratio_range"]]
    if "raw_numpy_ms" in entry:
        out["ratio_numpy"] = (rays / ms) / (raw_rays / entry["raw_numpy_ms"])
    return out


def load_scene(name: str):
    """A scene by name; ``two_rooms`` is the hand-made test scene with its box PVS."""
    if name == FALLBACK_SCENE:
        from methods.quake_drt import testscenes

        scene, vis = testscenes.two_rooms(door_open=False, lights_in_b=2, extra_lights=40)
        return testscenes.with_visibility(scene, vis)
    from suite.harness import runner

    return runner.load_scene(name)


class _Frame:
    """A pipeline on a scene at one resolution, with helpers to time its pieces."""

    def __init__(self, scene, tracer, resolution, t_s, **settings):
        self.scene, self.tracer = scene, tracer
        self.w, self.h = resolution
        self.t_s = t_s
        self.settings = pl.Settings.from_params(settings)
        self.prep = pl.prepare(scene, tracer, self.settings, t_s)
        self.pipe = pl.Pipeline(self.settings, self.prep, self.w, self.h)

    def seeds(self, i=0):
        from methods.quake_drt.rng import pixel_seeds

        return pixel_seeds(1000 + i, self.w, self.h).reshape(-1)

    def raw(self, i=0):
        return self.pipe.raw_frame(self.scene, self.tracer, self.t_s, None, self.seeds(i))

    def rays(self, fn) -> int:
        before = sum(self.tracer.counters.values())
        fn()
        return int(sum(self.tracer.counters.values()) - before)

    def direct(self, raw, capture=None, k=None, mode=None, cull=None):
        s = self.settings
        rows = culling.point_rows(self.prep.table, self.pipe._visibility(self.scene), raw.info["points"].prim,
                                  raw.info["points"].p, raw.info["points"].ng, s.pixel_cluster, s.cluster_probe_m,
                                  s.cull_lights if cull is None else cull)
        return direct.shade(raw.info["points"], raw.info["lights_obj"], self.prep.table, rows,
                            s.num_random_dl if k is None else k, mode or s.light_sampling, s.soft_shadows,
                            self.tracer, self.scene, pl._min_distance(self.scene), s.chunk_rays, capture=capture)


def bench_rays(scene, tracer, resolution, t_s: float, repeats: int, backend: str = "embree") -> dict:
    """Part ``rays`` (module docstring)."""
    from suite.core.trace.base import as_rays

    f = _Frame(scene, tracer, resolution, t_s, num_random_dl=0, denoiser=False, taa=False)
    from methods.quake_drt import primary

    seeds = f.seeds()  # made before the stage, as the pipeline makes them

    def prim():
        return primary.primary_stage(scene, tracer, t_s, None, (f.w, f.h), seeds, f.settings.antialiasing)

    from suite.core.gbuffer import camera_rays as pixel_centre_rays

    # The stage's two ray sets: the shading rays (jittered) and the G-buffer's pixel-centre rays.
    o, d = primary.camera_rays(scene, t_s, f.w, f.h, seeds, f.settings.antialiasing)
    oc, dc = pixel_centre_rays(scene.camera.pose_at(t_s), scene.camera.fov_deg, f.w, f.h, dtype=np.float64)
    sets = [as_rays(a.astype(np.float32), b.astype(np.float32), 0.0, np.inf, tracer.shift) for a, b in ((o, d), (oc, dc))]
    raw_rays = int(sum(len(r[1]) for r in sets))

    def raw_primary():
        for ro, rd, _, rlen in sets:
            tracer.raw_intersect(ro, rd, rlen.copy())  # embreex overwrites the lengths it is given

    short = max(repeats, SHORT_STAGE_REPEATS)
    timed = _against_raw(prim, [("i", ro, rd, rlen) for ro, rd, _, rlen in sets], tracer, short, raw_primary)
    out = {"primary": {**_rates(timed, f.rays(prim), raw_rays), "repeats": short}}
    raw = f.raw()
    captured = []
    _, direct_stats = f.direct(raw, capture=captured)  # its counters: the light samples
    # The stage's shadow rays as it traced them: host chunks (o, d, length), or on a Dr.Jit backend the device loop's
    # rays per iteration ("o", Ray3f), already in device memory (copied to numpy here for the numpy-fed raw only).
    records = [c for c in captured if len(c) == 2]
    chunks = [c for c in captured if len(c) == 3]
    chunks += _host_rays(getattr(tracer, "device", None), records)
    o_all = np.concatenate([c[0] for c in chunks]) if chunks else np.zeros((0, 3), np.float32)
    d_all = np.concatenate([c[1] for c in chunks]) if chunks else np.zeros((0, 3), np.float32)
    l_all = np.concatenate([c[2] for c in chunks]) if chunks else np.zeros(0, np.float32)
    dir_rays = f.rays(lambda: f.direct(raw))
    if len(o_all):
        log = [("o", *c) for c in captured if len(c) == 3]
        timed = _against_raw(lambda: f.direct(raw), log, tracer, repeats,
                             lambda: tracer.raw_occluded(o_all, d_all, l_all.copy()), records)
        out["direct"] = _rates(timed, dir_rays, int(len(o_all)))
    else:
        dir_ms, _ = _median_ms(lambda: f.direct(raw), repeats)
        out["direct"] = {"ms": dir_ms, "rays": dir_rays, "rays_per_s": dir_rays / (dir_ms / 1e3),
                         "raw_ms": float("nan"), "raw_rays": 0, "raw_rays_per_s": float("nan"), "ratio": float("nan")}
    out["direct"].update(repeats=repeats, shadow_rays=int(len(o_all)), light_samples=int(direct_stats.selected))
    out["secondary"] = bench_secondary(scene, tracer, resolution, t_s, short, backend)
    return {"scene": scene.name, "resolution": [f.w, f.h], "repeats": repeats, "settings": "paper pipeline, "
            "num_random_dl 0 (every culled light), antialiasing on", **out}


def _has_specular(scene) -> bool:
    return any(m.is_specular for m in scene.materials)


def bench_secondary(scene, tracer, resolution, t_s: float, repeats: int, backend: str = "embree") -> dict:
    """The ``secondary`` entry of part ``rays`` (module docstring): on ``scene`` when it has specular materials,
    else on :data:`SECONDARY_SCENE` with a tracer of ``backend`` (``tracer``'s)."""
    from methods.quake_drt import primary, secondary
    from suite.harness import runner

    if not _has_specular(scene):
        scene = runner.load_scene(SECONDARY_SCENE)
        tracer = runner.make_tracer(backend, scene)
    # No light culling: this stage does not read the PVS (and a scene without a BSP would compute one first).
    f = _Frame(scene, tracer, resolution, t_s, num_random_dl=0, denoiser=False, taa=False, pvs="none")
    s, seeds = f.settings, f.seeds()
    overlay = f.pipe._overlays(scene)
    skip = None if overlay is None else overlay > 0
    _, surf = primary.primary_stage(scene, tracer, t_s, None, (f.w, f.h), seeds, s.antialiasing,
                                    s.dof_aperture_m if s.dof else 0.0, s.dof_focal_m, overlay, s.overlay_alpha)

    def stage(tr=tracer, record=None):
        return secondary.secondary_stage(scene, tr, t_s, surf, seeds, s.max_depth, s.all_branches,
                                         s.glossy_reflections, s.glossy_cone_deg, skip, record)

    # The device as the stage finds it on the plain tracer: the same code path (the secondary stage asks only for
    # closest hits, directly or through walk_past; where its chains run on the device they record their rays there).
    recorder, records = RecordingTracer(tracer, device=True), []
    result = stage(recorder, records)
    log = list(recorder.log)  # the host queries; the device chains' rays are replayed from device memory
    recorder.log += [("i", *rays) for rays in _host_rays(getattr(tracer, "device", None), records)]  # numpy-fed raw
    raw_rays = recorder.rays
    entry = {"scene": scene.name, "repeats": repeats, "rays_per_depth": [int(n) for n in result.rays_per_depth],
             "specular_pixels": int(len(np.unique(result.points.pixel))) if len(result.points) else 0}
    if raw_rays == 0:
        return {**entry, "ms": _median_ms(stage, repeats)[0], "rays": 0, "rays_per_s": float("nan"),
                "raw_ms": float("nan"), "raw_rays": 0, "raw_rays_per_s": float("nan"), "ratio": float("nan")}

    timed = _against_raw(stage, log, tracer, repeats, recorder.replay, records)
    # backend queries: the continuation rays and any alpha walk past transparent texels
    return {**entry, **_rates(timed, f.rays(stage), raw_rays)}


def bench_asvgf(scene, tracer, resolutions, t_s: float, repeats: int, devices=()) -> dict:
    """Part ``asvgf`` (module docstring)."""
    from suite.harness.cli import bench_device, device_columns

    rows = []
    for res in resolutions:
        f = _Frame(scene, tracer, res, t_s, num_random_dl=1, denoiser=True, taa=True)
        p = f.pipe
        for i in range(2):  # two frames of a paused camera: the history is in use
            p.run_frame(scene, tracer, t_s, t_s if i else None, 500 + i)
        den = p.denoiser
        fwd = den.forward_project(scene, t_s)
        seeds = den.seeds_with_gradients(f.seeds(7), fwd)
        raw = p.raw_frame(scene, tracer, t_s, t_s, seeds, fwd)
        fwd = raw.info["fwd"]
        saved = dict(den.prev)
        times, taps = {}, {}

        def timed(name, fn):
            taps[name] = _Taps()
            fn(taps[name])  # the work counter of one call (the same for every call)
            times[name], result = _median_ms(lambda: fn(None), repeats, den.device)
            return result

        grad = timed("gradient", lambda st: den.gradient(raw.illum, fwd, st))
        lam = timed("gradient_atrous", lambda st: den.gradient_atrous(grad, st))
        alag = den.antilag(lam)
        color, moments, hist, _ = timed("temporal", lambda st: den.temporal(raw.illum, raw.guides, alag, st))
        var = timed("variance", lambda st: den.variance(raw.illum, moments, hist, raw.guides, st))
        filtered, _ = timed("atrous", lambda st: den.atrous(color, var, raw.guides, st))
        composed = raw.compose(filtered)
        taa_hist = p.taa.history

        def taa(st):
            p.taa.history = taa_hist
            return p.taa(composed, raw.g.motion, st)

        timed("taa", taa)
        # Stages 5-7 and TAA on each Dr.Jit device beside the host stages, on the same inputs: per call the frame's
        # inputs go up (as once per frame in a run) and the filtered colour and TAA output come back; the histories
        # are on the device already (uploaded once, before the timed calls, as a run keeps them there).
        on_device = {}
        own, own_prev_dev = den.device, den.prev_dev
        for backend in devices:
            short = backend.replace("mitsuba-", "")

            def columns():
                den.device = bench_device(scene, backend)
                den.prev_dev = None
                dtaa = p._device_taa(den.device)
                taa_history = {}

                def chain():
                    den._frame = den._frame_colour = None
                    t = [time.perf_counter()]

                    def done(result):  # each stage's kernels waited for before its clock stops
                        den.device.sync()
                        t.append(time.perf_counter())
                        return result

                    c_d, m_d, h_d, _ = done(den.temporal(raw.illum, raw.guides, alag))
                    v_d = done(den.variance(raw.illum, m_d, h_d, raw.guides))
                    done(den.atrous(c_d, v_d, raw.guides))
                    dtaa.history = taa_history["kept"]
                    done(dtaa(composed, raw.g.motion))
                    return np.diff(t) * 1e3

                dtaa.history = None
                dtaa(composed, raw.g.motion)  # the TAA history of this frame, kept on the device for the timed calls
                taa_history["kept"] = dtaa.history
                chain()  # compiles; uploads the history
                per = np.median([chain() for _ in range(max(1, repeats))], axis=0)
                return {f"{short}_{name}_ms": float(ms) for name, ms in zip(("temporal", "variance", "atrous", "taa"),
                                                                             per)}

            on_device.update(device_columns("quake_drt", backend, columns))
        p._taa_dev = None
        den.device, den.prev_dev = own, own_prev_dev
        den.prev = saved
        mp = res[0] * res[1] / 1e6
        total = sum(v for k, v in times.items() if k != "taa")
        rows.append({"resolution": list(res), "megapixels": mp, **{f"{k}_ms": v for k, v in times.items()},
                     **{f"{k}_taps": t.taps for k, t in taps.items()},
                     "denoiser_ms": total, "denoiser_taps": sum(t.taps for k, t in taps.items() if k != "taa"),
                     "denoiser_ms_per_mp": total / mp, "taa_ms_per_mp": times["taa"] / mp, **on_device})
    return {"scene": scene.name, "repeats": repeats, "rows": rows,
            "fit": fit_ms_per_mp([r["megapixels"] for r in rows], [r["denoiser_ms"] for r in rows]),
            "settings": "defaults (5 gradient and 5 a-trous passes, 3x3 kernel)"}


class _Taps:
    """A stand-in for a stage record that keeps the filter taps a denoiser stage declares."""

    def __init__(self):
        self.taps = 0

    def count(self, taps: int = 0, **_):
        self.taps += int(taps)


def fit_ms_per_mp(megapixels, ms) -> dict:
    """``ms = a * megapixels`` by least squares through the origin (every pass costs a fixed number of taps per
    pixel, so no fixed term is modelled; ``a`` is positive whenever the times are), its R², and the exponent of the
    log-log fit (1 = linear in the pixel count). Empty with fewer than two sizes or a non-positive time."""
    mp, t = np.asarray(megapixels, float), np.asarray(ms, float)
    if len(mp) < 2 or not (np.all(mp > 0) and np.all(t > 0)):
        return {}
    a = float((mp * t).sum() / (mp * mp).sum())
    ss = ((t - t.mean()) ** 2).sum()
    return {"ms_per_mp": a, "r2": float(1 - ((t - a * mp) ** 2).sum() / ss) if ss > 0 else 1.0,
            "exponent": float(np.polyfit(np.log(mp), np.log(t), 1)[0]) if np.ptp(mp) > 0 else float("nan")}


def bench_lights(scene, tracer, resolution, resolutions, t_s: float, repeats: int) -> dict:
    """Part ``lights`` (module docstring)."""
    f = _Frame(scene, tracer, resolution, t_s, num_random_dl=0, denoiser=False, taa=False)
    raw = f.raw()
    cases = [("all lights, no culling", dict(k=0, cull=False)), ("culled, all of the row", dict(k=0)),
             ("culled, k = 1", dict(k=1)), ("culled, k = 1, power", dict(k=1, mode="power")),
             ("culled, k = 4", dict(k=4)), ("culled, k = 16", dict(k=16))]
    rows = []
    for label, kw in cases:
        ms, (_, st) = _median_ms(lambda: f.direct(raw, **kw), repeats)
        rows.append({"case": label, "k": kw.get("k", 0), "culled": kw.get("cull", True),
                     "mode": kw.get("mode", "uniform"), "ms": ms, "shadow_rays": st.rays,
                     "lights_per_point": st.candidates / max(len(raw.info["points"]), 1),
                     "shaded_per_point": st.selected / max(len(raw.info["points"]), 1)})
    by_pixels = []
    for res in resolutions:
        g = _Frame(scene, tracer, res, t_s, num_random_dl=0, denoiser=False, taa=False)
        graw = g.raw()
        for k in (1, 0):
            ms, (_, st) = _median_ms(lambda: g.direct(graw, k=k), repeats)
            by_pixels.append({"resolution": list(res), "pixels": res[0] * res[1], "k": k, "ms": ms,
                              "shadow_rays": st.rays})
    return {"scene": scene.name, "resolution": list(resolution), "lights": len(f.prep.lights),
            "pvs_source": f.prep.table.source, "repeats": repeats, "rows": rows, "by_pixels": by_pixels}


# ---------------------------------------------------------------------------------------------------- store

def load(results_root) -> dict | None:
    from suite.harness.reporting import load_bench

    return load_bench("quake_drt", None, results_root)


def store(results_root, parts: dict) -> Path:
    from suite.harness.cli import store_bench

    return store_bench("quake_drt", results_root, parts, SCHEMA_VERSION)


# ------------------------------------------------------------------------------------------------------ CLI

def parser():
    from suite.harness.cli import _Parser

    ap = _Parser(prog="splitbench bench quake_drt", description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {', '.join(PARTS)}")
    ap.add_argument("--scene", default=None, help=f"default {DEFAULT_SCENE} ({FALLBACK_SCENE} without the "
                                                  "OpenArena data)")
    ap.add_argument("--backend", default="embree")
    ap.add_argument("--resolution", default="320x180", help="rays and lights resolution")
    ap.add_argument("--resolutions", default="160x90,320x180,640x360", help="asvgf and lights-by-pixels resolutions")
    ap.add_argument("--rays-larger", default="640x360", help="further sizes for part rays, comma-separated ('' for "
                    "none): its ratios by pixels")
    ap.add_argument("--device", default="auto", help="Dr.Jit backends to time the variance and a-trous stages on "
                    "beside the host filters, and part rays on beside --backend (auto: every one that works here; "
                    "'' for none)")
    ap.add_argument("--time", type=float, default=1.0, help="scene time of the benchmarked view, seconds")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="results", help="results root; the document goes to <out>/bench/")
    ap.add_argument("--no-store", action="store_true", help="print only")
    ap.add_argument("--json", action="store_true")
    return ap


def ratios_row(rays: dict) -> dict:
    """One row of part ``rays``'s ``by_pixels`` table: the resolution and each stage's ms and stage/raw ratio."""
    row = {"resolution": list(rays["resolution"])}
    for stage in ("primary", "secondary", "direct"):
        if stage in rays:
            row[f"{stage}_ms"], row[f"{stage}_ratio"] = rays[stage]["ms"], rays[stage]["ratio"]
            if "ratio_range" in rays[stage]:
                row[f"{stage}_ratio_range"] = rays[stage]["ratio_range"]
    return row


def rays_on_devices(scene, resolution, t_s: float, repeats: int, devices) -> list:
    """Part ``rays`` again on each Dr.Jit backend of ``devices`` beside the bench's own (a row each: the backend,
    its stages' ms and ratios to its device-resident raw and to its numpy-fed raw), so that the report shows what the
    device path changes, a GPU included. A backend that fails gives a row with its error."""
    from suite.harness.cli import device_rows

    def row(backend, tracer):
        r = bench_rays(scene, tracer, resolution, t_s, repeats, backend)
        out = ratios_row(r)
        for stage in ("primary", "secondary", "direct"):
            if stage in r and "ratio_numpy" in r[stage]:
                out[f"{stage}_ratio_numpy"] = r[stage]["ratio_numpy"]
        return out

    return device_rows("quake_drt", devices, scene, row)


def _resolutions(text: str):
    from suite.harness.runner import parse_resolution

    return [tuple(parse_resolution(r)) for r in text.split(",") if r.strip()]


def default_scene() -> str:
    from suite.core.scene import list_scenes

    return DEFAULT_SCENE if not list_scenes().get(DEFAULT_SCENE, "unavailable").startswith("unavailable") \
        else FALLBACK_SCENE


def run(args) -> dict:
    from suite.errors import UserError
    from suite.harness import runner
    from suite.harness.cli import bench_devices, bench_parts

    parts = bench_parts(args.parts, PARTS, args.backend)
    devices = bench_devices(args.device)
    if args.repeats < 1:
        raise UserError("--repeats must be >= 1")
    name = args.scene or default_scene()
    if name != FALLBACK_SCENE and not os.path.isfile(name) and name not in runner.scene_names():
        raise UserError(f"unknown scene '{name}'")
    scene = load_scene(name)
    tracer = runner.make_tracer(args.backend, scene)
    res = _resolutions(args.resolution)[0]
    many = _resolutions(args.resolutions)
    out = {}
    if "rays" in parts:
        out["rays"] = {"backend": args.backend, **bench_rays(scene, tracer, res, args.time, args.repeats,
                                                                  args.backend)}
        larger = [bench_rays(scene, tracer, r, args.time, args.repeats, args.backend)
                  for r in _resolutions(args.rays_larger)]
        out["rays"]["by_pixels"] = [ratios_row(r) for r in [out["rays"], *larger]]
        out["rays"]["on_devices"] = rays_on_devices(scene, res, args.time, args.repeats,
                                                    [b for b in devices if b != args.backend])
    if "asvgf" in parts:
        out["asvgf"] = {"backend": args.backend, "devices": devices,
                        **bench_asvgf(scene, tracer, many, args.time, args.repeats, devices)}
    if "lights" in parts:
        out["lights"] = {"backend": args.backend,
                         **bench_lights(scene, tracer, res, many, args.time, args.repeats)}
    return out


def format_results(out: dict) -> str:
    from suite.harness.reporting import range_text

    lines = []
    if "rays" in out:
        r = out["rays"]
        lines.append(f"rays/s, stage vs raw {r['backend']}: scene {r['scene']} {r['resolution'][0]}x"
                     f"{r['resolution'][1]}, medians")
        for stage in ("primary", "secondary", "direct"):
            s = r.get(stage)
            if s is None:
                continue
            where = f"   on {s['scene']}" if s.get("scene", r["scene"]) != r["scene"] else ""
            numpy_fed = f" (numpy-fed raw: {s['ratio_numpy']:.3f})" if "ratio_numpy" in s else ""
            samples = f", {s['light_samples']:,} light samples" if "light_samples" in s else ""
            lines.append(f"  {stage:9} {s['rays_per_s']:>13,.0f} rays/s ({s['ms']:.1f} ms, {s['rays']:,} rays"
                         f"{samples})   raw {s['raw_rays_per_s']:>13,.0f} rays/s ({s['raw_ms']:.1f} ms)   ratio "
                         f"{s['ratio']:.3f}{range_text(s.get('ratio_range'))}{numpy_fed}   median of "
                         f"{s.get('repeats', r['repeats'])}{where}")
        for row in r.get("by_pixels", [])[1:]:  # the first is the table above
            lines.append(f"  at {row['resolution'][0]}x{row['resolution'][1]}: "
                         + "   ".join(f"{st} {row[st + '_ratio']:.3f}" for st in ("primary", "secondary", "direct")
                                      if st + "_ratio" in row))
        for row in r.get("on_devices", []):
            short = row["backend"].replace("mitsuba-", "")
            if f"{short}_error" in row:
                lines.append(f"  on {row['backend']}: failed ({row[short + '_error']})")
                continue
            lines.append(f"  on {row['backend']}: " + "   ".join(
                f"{st} {row[st + '_ms']:.1f} ms, ratio {row[st + '_ratio']:.3f}"
                + (f" (numpy-fed {row[st + '_ratio_numpy']:.3f})" if st + "_ratio_numpy" in row else "")
                for st in ("primary", "secondary", "direct") if st + "_ratio" in row))
    if "asvgf" in out:
        r = out["asvgf"]
        lines.append(f"A-SVGF + TAA ms: scene {r['scene']}, median of {r['repeats']}")
        for row in r["rows"]:
            w, h = row["resolution"]
            devs = tuple(b.replace("mitsuba-", "") + "_" for b in r.get("devices", []))
            stages = "  ".join(f"{k[:-3]} {row[k]:.1f}" for k in row
                               if k.endswith("_ms") and k != "denoiser_ms" and not k.startswith(devs or ("\0",)))
            lines.append(f"  {w}x{h}: denoiser {row['denoiser_ms']:.1f} ms ({row['denoiser_ms_per_mp']:.0f} ms/MP), "
                         f"{stages}")
            for b in r.get("devices", []):
                short = b.replace("mitsuba-", "")
                if f"{short}_error" in row:
                    lines.append(f"    on {b}: failed ({row[short + '_error']})")
                    continue
                lines.append(f"    on {b}: " + "  ".join(f"{k} {row[f'{short}_{k}_ms']:.1f} (host {row[k + '_ms']:.1f})"
                                                     for k in ("temporal", "variance", "atrous", "taa")))
        if r["fit"]:
            lines.append(f"  fit: {r['fit']['ms_per_mp']:.0f} ms/MP (through the origin), "
                         f"R² {r['fit']['r2']:.4f}, exponent {r['fit']['exponent']:.2f}")
    if "lights" in out:
        r = out["lights"]
        lines.append(f"direct stage vs lights: scene {r['scene']} {r['resolution'][0]}x{r['resolution'][1]}, "
                     f"{r['lights']} lights, PVS {r['pvs_source']}")
        for row in r["rows"]:
            lines.append(f"  {row['case']:26} {row['ms']:9.1f} ms  {row['shadow_rays']:>10,} rays  "
                         f"{row['lights_per_point']:6.1f} lights/point  {row['shaded_per_point']:6.1f} shaded")
        for row in r["by_pixels"]:
            w, h = row["resolution"]
            lines.append(f"  {w}x{h} k={row['k']}: {row['ms']:.1f} ms, {row['shadow_rays']:,} rays")
    return "\n".join(lines)


def main(argv=None) -> int:
    import json

    args = parser().parse_args(argv)
    out = run(args)
    if not args.no_store:
        path = store(args.out, out)
        out_note = f"stored {path}"
    else:
        out_note = "not stored"
    if args.json:
        print(json.dumps(out, indent=1, default=float))
    else:
        print(format_results(out))
        print(out_note)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
