"""Tracing overhead benchmark: the suite's ``occluded``/``intersect`` against a direct backend call.

Both sides trace the same rays in the same process, interleaved, and the median of several repeats is
kept, so machine noise hits both alike. The figure of merit is the ratio suite/raw rays per second
(goal >= 0.90): the price of the shared interface (argument checks, tmin handling, counters, id mapping).
"""
from __future__ import annotations

import time

import numpy as np

from suite.core.gbuffer import render_gbuffer
from suite.core.trace import make
from suite.core.trace.base import as_rays
from suite.core.trace.robust import offset_ray_origin


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


def run(scene, backend: str = "embree", max_rays: int = 500_000, repeats: int = 5) -> dict:
    """Rays/s of suite vs raw backend for occluded and intersect queries on the same rays."""
    o, d, tmax = shadow_rays(scene)
    o, d, tmax = o[:max_rays], d[:max_rays], tmax[:max_rays]
    tracer = make(backend, scene)
    if not hasattr(tracer, "raw_occluded"):
        raise NotImplementedError(f"backend {backend} has no raw entry point")
    ro, rd, _, rlen = as_rays(o, d, 0.0, tmax, tracer.shift)  # raw backends take (N, 3)
    # Warm up (JIT compilation for Dr.Jit, page faults for both), then interleave suite and raw.
    tracer.occluded(o, d, 0.0, tmax), tracer.raw_occluded(ro, rd, rlen)
    tracer.intersect(o, d, 0.0, tmax), tracer.raw_intersect(ro, rd, rlen)
    out = {"backend": backend, "scene": scene.name, "rays": int(len(o)), "repeats": repeats}
    for query, suite_fn, raw_fn in (
            ("occluded", lambda: tracer.occluded(o, d, 0.0, tmax), lambda: tracer.raw_occluded(ro, rd, rlen)),
            ("intersect", lambda: tracer.intersect(o, d, 0.0, tmax), lambda: tracer.raw_intersect(ro, rd, rlen))):
        suite_s, raw_s = [], []
        for _ in range(repeats):
            suite_s.append(_median_time(suite_fn, 1))
            raw_s.append(_median_time(raw_fn, 1))
        suite_rps = len(o) / float(np.median(suite_s))
        raw_rps = len(o) / float(np.median(raw_s))
        out[query] = {"suite_rays_per_s": suite_rps, "raw_rays_per_s": raw_rps, "ratio": suite_rps / raw_rps}
    return out
