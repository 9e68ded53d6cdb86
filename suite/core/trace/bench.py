"""Benchmarks of the rendering core: ``splitbench bench tracing`` and ``splitbench bench core``.

**Tracing overhead** (:func:`run`): the suite's ``occluded``/``intersect`` against a direct backend call on the
same rays, in the same process, interleaved, median of several repeats, so machine noise hits both alike. The
figure of merit is the ratio suite/raw rays per second (goal >= 0.90): the price of the shared interface
(argument checks, the frame shift, tmin/tmax handling, counters, the primitive id mapping, the alpha test).
On scenes with alpha-tested materials the suite makes more than one backend query per ray (``queries_per_ray``,
from the tracer's counters: the closest-hit queries of the alpha walk) where raw makes one and tests no alpha;
``ratio_at_queries_per_ray`` is the ratio against raw making as many queries per ray (``ratio * queries_per_ray``),
what the interface costs beyond the extra queries themselves. The goal is stated for ``ratio``.

Every ratio of medians comes with ``..._range``: the lowest and highest ratio of one repeat's two calls, which ran
next to each other (:func:`paired_range`). On a shared 2-core machine a single call moves by 10-15 %, so a ratio
whose range straddles its goal is not decided by the run, whichever side its median falls on.

"Raw" is the backend's own rate on rays that stay in its memory: numpy arrays for Embree (embreex's interface),
device-resident Dr.Jit arrays for Mitsuba. For Mitsuba the headline ratio is therefore the suite's device-resident
query (``tracer.device.occluded``/``intersect`` on Dr.Jit rays) against ``Scene.ray_test`` /
``ray_intersect_preliminary`` on the same rays in device memory; the numpy interface is reported beside it
(``numpy``: suite and raw fed from numpy, and their rate as a fraction of the device-resident raw rate), which is
what rays that travel between numpy and Dr.Jit cost.

**Core stages** (:func:`core`): per stage wall time, rays and pixels of one frame at a resolution (default 1080p) on
a backend: the G-buffer (camera rays, tracing, attribute interpolation; and fused, as methods run it), the raw
``ray_intersect`` of the same camera rays, the visibility pass (one shadow ray per pixel and point light) and the
raw ``ray_test`` of its rays, point-light shading, area-light shading, and the explicit host copies with their
bytes. On Embree every stage is the numpy/numba host path. Ratios: G-buffer / raw intersect (goal <= 2) and
visibility raw / pass (goal >= 0.9).
"""
from __future__ import annotations

import time

import numpy as np

from suite.core.gbuffer import camera_rays, render_gbuffer
from suite.core.trace import make
from suite.core.trace.base import as_rays
from suite.core.trace.robust import offset_ray_origin


# The goal for a pass's rays/s against the backend's raw rate on the same rays (tracing, method stages).
RAY_RATE_GOAL = 0.9

def shadow_rays(scene, resolution=(320, 180), t_s: float = 0.5):
    """Realistic shadow rays: from every visible pixel of the camera's view to every point light."""
    tracer = make("embree", scene)
    g = render_gbuffer(scene, tracer, t_s, resolution)
    p = offset_ray_origin(g.position[g.valid], g.geo_normal[g.valid], tracer.shift)
    lights = np.stack([lt.position for lt in scene.lights_at(t_s)]) if scene.point_lights else np.zeros((1, 3))
    to_light = lights[None, :, :] - p[:, None, :].astype(np.float64)
    dist = np.linalg.norm(to_light, axis=-1)
    dirs = (to_light / dist[..., None]).reshape(-1, 3).astype(np.float32)
    origins = np.broadcast_to(p[:, None, :], to_light.shape).reshape(-1, 3).astype(np.float32)
    return np.ascontiguousarray(origins), np.ascontiguousarray(dirs), (dist.reshape(-1) * 0.9999).astype(np.float32)


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def interleaved_times(pairs, repeats: int) -> dict:
    """Seconds of every call of each named function: one warm-up call each, then the functions in turn ``repeats``
    times, so that the i-th calls of any two of them ran next to each other (:func:`paired_range`)."""
    for _, fn in pairs:
        fn()
    times = {name: [] for name, _ in pairs}
    for _ in range(max(int(repeats), 1)):
        for name, fn in pairs:
            times[name].append(_median_time(fn, 1))
    return times


def interleaved(pairs, repeats: int) -> dict:
    """Median seconds of each named function, the functions run in turn ``repeats`` times (after one warm-up)."""
    return medians(interleaved_times(pairs, repeats))


def medians(times: dict) -> dict:
    """Median seconds per name of :func:`interleaved_times`'s calls."""
    return {name: float(np.median(t)) for name, t in times.items()}


def paired_range(num, den, scale: float = 1.0) -> list:
    """``[lowest, highest]`` of ``scale * num[i] / den[i]`` over paired repeats (the i-th entries ran next to each
    other, as :func:`interleaved_times` runs them): how far one repeat's ratio strays from the ratio of the medians
    on this machine. A goal inside the range is not decided by the run."""
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    if len(num) != len(den) or len(num) == 0:
        raise ValueError(f"paired_range needs paired repeats, got {len(num)} and {len(den)}")
    r = float(scale) * num / den
    return [float(r.min()), float(r.max())]


def run(scene, backend: str = "embree", max_rays: int = 500_000, repeats: int = 5,
        resolution=(640, 360)) -> dict:
    """Rays/s of suite vs raw backend for occluded and intersect queries on the same rays (see the module doc): up to
    ``max_rays`` shadow rays from the camera's view at ``resolution`` (enough that a query's fixed costs, a kernel
    launch and its Python side, do not dominate on small scenes)."""
    o, d, tmax = shadow_rays(scene, tuple(resolution))
    o, d, tmax = o[:max_rays], d[:max_rays], tmax[:max_rays]
    tracer = make(backend, scene)
    if not hasattr(tracer, "raw_occluded"):
        raise NotImplementedError(f"backend {backend} has no raw entry point")
    ro, rd, _, rlen = as_rays(o, d, 0.0, tmax, tracer.shift)  # raw backends take (N, 3)
    n = int(len(o))
    out = {"backend": backend, "scene": scene.name, "rays": n, "repeats": repeats}
    numpy_fns = {
        "occluded": (lambda: tracer.occluded(o, d, 0.0, tmax), lambda: tracer.raw_occluded(ro, rd, rlen)),
        # embreex writes hit distances into the lengths it is given: the raw closest-hit call takes a fresh copy
        # (as the suite's query does internally), or its later calls would trace shortened rays
        "intersect": (lambda: tracer.intersect(o, d, 0.0, tmax), lambda: tracer.raw_intersect(ro, rd, rlen.copy()))}
    def queries(fn) -> float:
        """Backend queries per ray the suite makes (1, plus the alpha walk's closest-hit queries)."""
        before = sum(tracer.counters.values())
        fn()
        return (sum(tracer.counters.values()) - before) / max(n, 1)

    dev = getattr(tracer, "device", None)
    if dev is None:
        out["interface"] = "numpy"
        for query, (suite_fn, raw_fn) in numpy_fns.items():
            times = interleaved_times([("suite", suite_fn), ("raw", raw_fn)], repeats)
            t = medians(times)
            q = queries(suite_fn)
            out[query] = {"suite_rays_per_s": n / t["suite"], "raw_rays_per_s": n / t["raw"],
                          "ratio": t["raw"] / t["suite"], "ratio_range": paired_range(times["raw"], times["suite"]),
                          "queries_per_ray": q, "ratio_at_queries_per_ray": q * t["raw"] / t["suite"]}
        return out
    # Device-resident rays: the suite's query takes world-space float32 origins (like the numpy interface) and does
    # its frame shift, length clipping, id mapping and counting on the device; raw gets the tracing-frame rays.
    out["interface"] = f"device ({dev.variant})"
    o_dev = dev.to_device(o, dev.Point3f)
    d_dev = dev.to_device(d, dev.Vector3f)
    tmax_dev = dev.to_device(tmax, dev.Float)
    ray = dev.raw_ray(dev.to_device(ro, dev.Point3f), dev.to_device(rd, dev.Vector3f), dev.to_device(rlen, dev.Float))
    dev.eval(o_dev, d_dev, tmax_dev)
    device_fns = {"occluded": (lambda: dev.occluded(o_dev, d_dev, 0.0, tmax_dev), lambda: dev.raw_occluded(ray)),
                  "intersect": (lambda: dev.intersect(o_dev, d_dev, 0.0, tmax_dev), lambda: dev.raw_intersect(ray))}
    for query in ("occluded", "intersect"):
        # Each pair interleaved on its own: a numpy-fed call leaves the allocator and the copy engine busy with its
        # large transfers, which the call timed right after it would absorb.
        times = interleaved_times([("suite", device_fns[query][0]), ("raw", device_fns[query][1])], repeats)
        t = medians(times)
        t.update(interleaved([("numpy_suite", numpy_fns[query][0]), ("numpy_raw", numpy_fns[query][1])], repeats))
        q = queries(device_fns[query][0])
        # device time alone (kernel history): what is left of the gap once the host's per-call costs are taken out
        k_suite, k_raw = dev.kernel_ms(device_fns[query][0], repeats), dev.kernel_ms(device_fns[query][1], repeats)
        out[query] = {"suite_rays_per_s": n / t["suite"], "raw_rays_per_s": n / t["raw"], "ratio": t["raw"] / t["suite"],
                      "ratio_range": paired_range(times["raw"], times["suite"]), "queries_per_ray": q,
                      "ratio_at_queries_per_ray": q * t["raw"] / t["suite"],
                      "suite_ms": 1e3 * t["suite"], "raw_ms": 1e3 * t["raw"],
                      "suite_kernel_ms": k_suite, "raw_kernel_ms": k_raw,
                      "kernel_ratio": k_raw / k_suite if k_suite > 0 else float("nan"),
                      "numpy": {"suite_rays_per_s": n / t["numpy_suite"], "raw_rays_per_s": n / t["numpy_raw"],
                                "ratio": t["numpy_raw"] / t["numpy_suite"],
                                "suite_of_device_raw": t["raw"] / t["numpy_suite"]}}
    return out


# ----------------------------------------------------------------------------------------------- core stages

def _timed(fn, repeats: int):
    """(median ms, last result) of ``fn`` after one warm-up call."""
    result = fn()
    times = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)), result


def core(scene, backend: str, resolution=(1920, 1080), t_s: float = 0.5, repeats: int = 7,
         area_samples: int = 4) -> dict:
    """Per-stage ms, rays and pixels of one frame on ``backend`` (see the module docstring)."""
    from suite.core import shading

    tracer = make(backend, scene)
    w, h = (int(x) for x in resolution)
    pixels = w * h
    lights = scene.lights_at(t_s)
    area = shading.AreaLights(scene, t_s)
    prev_t_s = max(t_s - 1.0 / scene.camera.fps, 0.0)
    dev = getattr(tracer, "device", None)
    stages: list[dict] = []

    def stage(name, ms, rays=0, nbytes=None, **extra):
        row = {"stage": name, "ms": ms, "pixels": pixels, "rays": int(rays)}
        if nbytes is not None:
            row["bytes"] = int(nbytes)
        row.update(extra)
        stages.append(row)
        return row

    def counted(fn):
        before = dict(tracer.counters)
        result = fn()
        return result, sum(tracer.counters[k] - before[k] for k in before)

    out = {"scene": scene.name, "backend": backend, "resolution": [w, h], "pixels": pixels, "lights": len(lights),
           "area_lights": len(area), "area_samples": area_samples, "repeats": repeats}
    if dev is None:
        out["path"] = "host (numpy/numba)"
        pose = scene.camera.pose_at(t_s)
        ms, (o64, d64) = _timed(lambda: camera_rays(pose, scene.camera.fov_deg, w, h, dtype=np.float64), repeats)
        stage("camera_rays", ms)
        o32, d32 = o64.astype(np.float32), d64.astype(np.float32)
        ms, _ = _timed(lambda: tracer.intersect(o32, d32), repeats)
        stage("trace", ms, pixels)
        g, rays = counted(lambda: render_gbuffer(scene, tracer, t_s, (w, h), prev_t_s))
        ro, rd, _, rlen = as_rays(o32, d32, 0.0, np.inf, tracer.shift)
        times = interleaved_times([("gbuffer", lambda: render_gbuffer(scene, tracer, t_s, (w, h), prev_t_s)),
                                   ("raw", lambda: tracer.raw_intersect(ro, rd, rlen.copy()))], repeats)
        t = medians(times)
        gb = stage("gbuffer", 1e3 * t["gbuffer"], rays)
        stage("raw_intersect", 1e3 * t["raw"], pixels)
        out["gbuffer_over_raw_intersect"] = t["gbuffer"] / t["raw"]
        out["gbuffer_over_raw_intersect_range"] = paired_range(times["gbuffer"], times["raw"])
        ms, vis = _timed(lambda: shading.point_light_visibility(g, lights, tracer), repeats)
        _, rays = counted(lambda: shading.point_light_visibility(g, lights, tracer))
        stage("visibility", ms, rays)
        min_d = shading.min_light_distance(scene)
        ms, _ = _timed(lambda: shading.shade_point_lights(g, lights, vis, min_distance=min_d), repeats)
        stage("shading", ms)
        if len(area):
            ms, _ = _timed(lambda: shading.area_light_radiance(g, area, tracer, area_samples, 0, min_d), repeats)
            _, rays = counted(lambda: shading.area_light_radiance(g, area, tracer, area_samples, 0, min_d))
            stage("area_lights", ms, rays)
        out["stages"] = stages
        return out

    from suite.core.device import gbuffer as dgb
    from suite.core.device import shading as dsh

    out["path"] = f"device ({dev.variant})"
    dgb.render_gbuffer(scene, tracer, t_s, (w, h), prev_t_s, stages=True)  # warm-up (kernel compilation)
    per_stage = []
    for _ in range(max(repeats, 1)):
        per_stage.append(dgb.render_gbuffer(scene, tracer, t_s, (w, h), prev_t_s, stages=True).stage_ms)
    for key, name in (("camera_rays_ms", "camera_rays"), ("trace_ms", "trace"), ("attributes_ms", "attributes")):
        stage(name, float(np.median([s[key] for s in per_stage])), pixels if name == "trace" else 0,
              note="evaluated separately")
    # raw: the same camera rays, held in device memory, through ray_intersect_preliminary; timed interleaved with
    # the fused G-buffer (ratios of one run, machine noise hits both alike)
    pose = scene.camera.pose_at(t_s)
    d64, _, _ = dgb.camera_rays(dev, pose, scene.camera.fov_deg, w, h)
    cam = (np.asarray(pose.position, np.float64).astype(np.float32).astype(np.float64) - tracer.shift).astype(np.float32)
    dr = dev.dr
    ray = dev.raw_ray(dev.Point3f(*[dr.full(dev.Float, float(x), pixels) for x in cam]), dev.Vector3f(d64),
                      dr.full(dev.Float, 1e37, pixels))
    def gbuffer():
        return dgb.render_gbuffer(scene, tracer, t_s, (w, h), prev_t_s)

    def raw_intersect():
        return dev.raw_intersect(ray)

    g = gbuffer()
    times = interleaved_times([("gbuffer", gbuffer), ("raw", raw_intersect)], repeats)
    t = medians(times)
    k_gb, k_raw = dev.kernel_ms(gbuffer, repeats), dev.kernel_ms(raw_intersect, repeats)
    gb = stage("gbuffer", 1e3 * t["gbuffer"], g.rays, note="fused: one kernel", kernel_ms=k_gb)
    stage("raw_intersect", 1e3 * t["raw"], pixels, note="the same camera rays, held in device memory", kernel_ms=k_raw)
    out["gbuffer_over_raw_intersect"] = gb["ms"] / (1e3 * t["raw"])
    out["gbuffer_over_raw_intersect_range"] = paired_range(times["gbuffer"], times["raw"])
    out["gbuffer_over_raw_intersect_kernels"] = k_gb / k_raw if k_raw > 0 else float("nan")
    vis, vis_rays = counted(lambda: dsh.point_light_visibility(g, lights, tracer))  # shadow rays + alpha walk
    if lights:
        rays_dev = dsh.shadow_rays(g, lights, tracer)

        def visibility():
            return dsh.point_light_visibility(g, lights, tracer)

        def raw_occluded():
            dev.eval(*[tracer.mscene.ray_test(r, coherent=False) for r, _ in rays_dev])

        times = interleaved_times([("pass", visibility), ("raw", raw_occluded)], repeats)
        t = medians(times)
        k_pass, k_raw = dev.kernel_ms(visibility, repeats), dev.kernel_ms(raw_occluded, repeats)
        stage("visibility", 1e3 * t["pass"], vis_rays, kernel_ms=k_pass)
        stage("raw_occluded", 1e3 * t["raw"], vis.rays, note="the pass's rays, held in device memory", kernel_ms=k_raw)
        out["visibility_raw_over_pass"] = t["raw"] / t["pass"]
        out["visibility_raw_over_pass_range"] = paired_range(times["raw"], times["pass"])
        out["visibility_raw_over_pass_kernels"] = k_raw / k_pass if k_pass > 0 else float("nan")
    else:
        ms, vis = _timed(lambda: dsh.point_light_visibility(g, lights, tracer), repeats)
        stage("visibility", ms, vis_rays)
    min_d = shading.min_light_distance(scene)
    ms, img = _timed(lambda: dsh.shade_point_lights(g, lights, vis, min_distance=min_d), repeats)
    stage("shading", ms)
    if len(area):
        dal = dsh.DeviceAreaLights(dev, area)
        ms, _ = _timed(lambda: dsh.area_light_radiance(g, dal, tracer, area_samples, 0, min_d), repeats)
        _, rays = counted(lambda: dsh.area_light_radiance(g, dal, tracer, area_samples, 0, min_d))
        stage("area_lights", ms, rays)
    # explicit host copies, with their bytes
    ms, (_, nbytes) = _timed(lambda: vis.to_host_bytes(with_bytes=True), repeats)
    stage("copy_visibility_to_host", ms, nbytes=nbytes)
    ms, (_, nbytes) = _timed(lambda: img.to_host(with_bytes=True), repeats)
    stage("copy_image_to_host", ms, nbytes=nbytes)
    ms, (_, nbytes) = _timed(lambda: g.to_host(with_bytes=True), repeats)
    stage("copy_gbuffer_to_host", ms, nbytes=nbytes)
    out["stages"] = stages
    out["device_counters"] = dict(dev.counters)
    return out
