"""Benchmarks of seed 000's visibility bitmap: ``splitbench bench visibility_bitmap`` (or ``python -m
methods.visibility_bitmap.bench``).

Parts (``--parts``, default all), each printed and stored in ``<results>/bench/visibility_bitmap.json`` (``--out``,
default ``results``; a part that runs replaces its entry, the others are kept) so that the report can show them
without running anything:

``throughput``
    The visibility pass (:func:`.method.visibility_pass`: ray generation from the G-buffer, the suite's
    ``occluded`` query, the scatter into the mask, the packing) against the raw backend on the very rays the pass
    traced, in one process, interleaved, median of ``--repeats``. Embree: ``tracer.raw_occluded`` on the rays
    recorded from one untimed pass. Mitsuba llvm/cuda: the device pass (plus the read-back of the packed bitmap
    the stage does) against ``ray_test`` on the same rays held in device memory, the backend's own rate; the
    numpy-fed rate of those rays is reported beside it. Figure of merit: the ratio of rays per second, stage / raw
    (goal >= 0.90).
``linearity``
    Server work against pixels x lights (seed 000 §3.2: one shadow ray per pixel and light): the visibility pass
    and the whole server frame (G-buffer + visibility pass) at 3 resolutions x 3 light counts (the first N
    lights of a many-light scene), median of ``--repeats``; least-squares fit ``ms = a * (pixels * lights) + b``,
    slope ``a`` in ns per pixel-light and R².
``codecs``
    Bytes per frame and codec ratio, encode/decode ms, bit-exactness on real bitmaps of the camera path, at
    640x360 ... 1920x1080 (the paper's 8,294,400-byte raw bitmap is the 1920x1080 paper32 row).
``lights``
    Bytes per frame against light count (the first N lights of ``--lights-scene``), per layout.

Each part records its scene and backend; the document records where it ran as a run's config.json does
(``packages``, ``host``, ``git``). Times are wall times on this machine and its backend; they compare parts of
one run with each other, not machines. ``--loss`` keeps the former UDP loss sweep (printed, not stored).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import codecs
from suite.core.trace.bench import interleaved_times, paired_range
from suite.core.trace.recording import RecordingTracer
from suite.harness.reporting import range_text

DEFAULT_CODECS = ("none", "lzo", "lz4", "zstd", "zstd:9", "bitplane+lz4", "bitplane+zstd", "delta+lz4", "delta+zstd",
                  "delta+bitplane+zstd", "h264", "bitplane+h264")


def render_bitmaps(scene, tracer, resolution, frames: int, light_limit: int | None = None) -> list[np.ndarray]:
    """``(H, W, L)`` bool visibility of the first ``frames`` frames of the camera path."""
    from suite.core.shading import point_light_visibility

    out = []
    for i in range(frames):
        t_s = scene.camera.frame_time_s(i)
        g = _server_gbuffer(scene, tracer, t_s, resolution)
        lights = scene.lights_at(t_s)[:light_limit]
        vis = point_light_visibility(g, lights, tracer)
        out.append(vis if isinstance(vis, np.ndarray) else vis.to_host())
    return out


def _server_gbuffer(scene, tracer, t_s, resolution):
    """The G-buffer the method's server stage makes: on the device for Mitsuba llvm/cuda, else on the host."""
    from suite.core.gbuffer import has_device, render_gbuffer, render_gbuffer_device

    if has_device(tracer):
        return render_gbuffer_device(scene, tracer, t_s, tuple(resolution))
    return render_gbuffer(scene, tracer, t_s, resolution=tuple(resolution))


def codec_table(visibility: list[np.ndarray], layout: str, codec_specs=DEFAULT_CODECS,
                keyframe_interval: int = 30, repeats: int = 3) -> list[dict]:
    """One row per codec: ratio, encoded bytes per frame, encode/decode ms per frame, bit_exact, availability.

    Each codec runs the sequence ``repeats`` times; the ms are the fastest repeat (the least disturbed by other
    processes on a shared machine). Bytes do not vary between repeats.
    """
    light_count = visibility[0].shape[-1]
    width = visibility[0].shape[1]
    frames = [bm.pack(v, layout) for v in visibility]
    rows = []
    for spec in codec_specs:
        runs = [codecs.measure(spec, frames, width, bm.bytes_per_pixel(layout, light_count), keyframe_interval)
                for _ in range(max(repeats, 1))]
        m = runs[0]
        if m.available:
            m.encode_ms = min(r.encode_ms for r in runs)
            m.decode_ms = min(r.decode_ms for r in runs)
            m.bit_exact = all(r.bit_exact for r in runs)
        row = m.as_dict()
        row.update(layout=layout, lights=light_count, frames=len(frames),
                   bytes_per_frame=m.encoded_bytes / len(frames) if m.available else None)
        rows.append(row)
    return rows


def loss_sweep(scene, tracer, resolution, frames: int, loss_rates, repairs=("previous", "lit"),
               params: dict | None = None, seed: int = 0) -> list[dict]:
    """UDP loss against image quality: per loss rate and repair policy, the rows repaired and the metrics of
    the distributed frames against the standalone (Algorithm 3A) frames of the same poses.

    The bitmap goes through a netsim topology whose client link is ``bw=800mbps,delay=2.5ms,loss=P``
    (lan-home's link with loss), under UDP. Only images and bytes are reported here: frame times of lossy UDP runs belong to the harness.
    """
    import netsim

    from methods.visibility_bitmap.method import VisibilityBitmap
    from suite.core.metrics import compare
    from suite.harness.method import ClientCamera, Clock, Context, ServerCamera, scene_view
    from suite.harness.timeline import Timeline

    def sequence(method, zero_latency, spec):
        timeline = Timeline(netsim.make_topology(access=spec, seed=seed))
        method.reset()
        client_scene = scene_view(scene, ClientCamera(scene.camera, 0))
        server_scene = scene_view(scene, ServerCamera(scene.camera, 0))
        images, infos, prev_t = [], [], None
        for i in range(frames):
            t_s = scene.camera.frame_time_s(i)
            ctx = Context(timeline.group("frame", i, i / scene.camera.fps), scene=client_scene,
                          server_scene=server_scene, tracer=tracer, t_s=t_s, prev_t_s=prev_t, resolution=resolution,
                          seed=seed, params=method.params, zero_latency=zero_latency, protocol="udp",
                          clock=Clock("work"), outputs=VisibilityBitmap.outputs)
            images.append(method.frame(ctx))
            infos.append(dict(ctx.outputs))
            prev_t = t_s
        return images, infos

    base = dict(params or {})
    reference = VisibilityBitmap(base)
    reference.restore(reference.prepare(scene, tracer))
    alone, _ = sequence(reference, True, "ideal")
    rows = []
    for loss in loss_rates:
        for repair in repairs:
            method = VisibilityBitmap({**base, "udp_repair": repair})
            method.restore(method.prepare(scene, tracer))
            # lan-home's link with loss, both ways (the inputs go over TCP: loss only delays them)
            images, infos = sequence(method, False, f"bw=800mbps,delay=2.5ms,loss={100 * loss:g}%")
            metrics = [compare(a, b) for a, b in zip(alone, images)]
            rows.append({
                "loss": loss, "repair": repair, "frames": frames,
                "rows_repaired_fraction": float(np.mean([i["rows_repaired"] for i in infos]) / resolution[1]),
                "bad_frames": sum(i["status"] == "bad" for i in infos),
                "wire_bytes_per_frame": float(np.mean([i["wire_bytes"] for i in infos])),
                "ssim": float(np.mean([m["ssim"] for m in metrics])),
                "psnr_db": float(np.mean([min(m["psnr_db"], 99.0) for m in metrics])),
                "flip": float(np.mean([m["flip"] for m in metrics])),
            })
    return rows


# ------------------------------------------------------------------------------------------------ throughput

def throughput(scene, tracer, resolution=(640, 360), t_s: float = 0.5, layout: str = "paper32",
               repeats: int = 7) -> dict:
    """Rays/s of the method's visibility pass against the raw backend on the same rays (goal: ratio >= 0.90).

    Embree (host path): the pass from a host G-buffer against ``tracer.raw_occluded`` on the recorded numpy rays.
    Mitsuba llvm/cuda (device path): the pass from a device G-buffer (ray generation, traversal and bits in one
    kernel per 32 lights, packing, and the read-back of the packed bitmap the stage does) against Mitsuba's
    ``ray_test`` on the same rays held in device memory (``raw``: the backend's own rate), and, for reference,
    against the same rays fed from numpy (``numpy_raw``). ``ratio_range``: the lowest and highest ratio of one
    repeat, whose stage and raw calls ran next to each other.
    """
    from methods.visibility_bitmap.method import visibility_pass
    from suite.core.gbuffer import has_device, render_gbuffer

    if has_device(tracer):
        return _throughput_device(scene, tracer, resolution, t_s, layout, repeats)
    if not hasattr(tracer, "raw_occluded"):
        raise NotImplementedError(f"backend {getattr(tracer, 'name', '?')} has no raw entry point")
    g = render_gbuffer(scene, tracer, t_s, resolution=tuple(resolution))
    lights = scene.lights_at(t_s)
    recorder = RecordingTracer(tracer)
    visibility_pass(g, lights, recorder, layout)
    rays = recorder.rays

    def stage():
        visibility_pass(g, lights, tracer, layout)

    # interleaved after one warm-up call each (page faults, caches): machine noise hits both alike
    times = interleaved_times([("stage", stage), ("raw", recorder.replay)], repeats)
    stage_s, raw_s = times["stage"], times["raw"]
    stage_rps = rays / float(np.median(stage_s))
    raw_rps = rays / float(np.median(raw_s))
    return {"scene": scene.name, "resolution": list(resolution), "lights": len(lights), "layout": layout,
            "rays": rays, "repeats": repeats, "path": "host", "raw": "numpy rays",
            "stage_ms": 1e3 * float(np.median(stage_s)),
            "raw_ms": 1e3 * float(np.median(raw_s)), "stage_rays_per_s": stage_rps, "raw_rays_per_s": raw_rps,
            "ratio": stage_rps / raw_rps, "ratio_range": paired_range(raw_s, stage_s), "goal": 0.90}


def _throughput_device(scene, tracer, resolution, t_s, layout, repeats) -> dict:
    from methods.visibility_bitmap.method import visibility_pass
    from suite.core.device.shading import shadow_rays
    from suite.core.gbuffer import render_gbuffer_device

    dev = tracer.device
    g = render_gbuffer_device(scene, tracer, t_s, tuple(resolution))
    lights = scene.lights_at(t_s)
    rays_dev = shadow_rays(g, lights, tracer)
    rays = int(sum(dev.dr.width(r.d) for r, _ in rays_dev))
    host_rays = [(dev.to_host(r.o, np.float32), dev.to_host(r.d, np.float32), dev.to_host(r.maxt, np.float32))
                 for r, _ in rays_dev]

    def stage():
        _, raw = visibility_pass(g, lights, tracer, layout)
        raw.to_host()  # the stage reads the packed bitmap back for the encoder

    def raw():
        out = [tracer.mscene.ray_test(r, coherent=False) for r, _ in rays_dev]
        dev.eval(*out)

    def numpy_raw():
        for o, d, length in host_rays:
            tracer.raw_occluded(o, d, length)

    # interleaved after one warm-up call each (kernel compilation, allocations): machine noise hits all alike
    times = interleaved_times([("stage", stage), ("raw", raw), ("numpy_raw", numpy_raw)], repeats)
    stage_s, raw_s, np_s = times["stage"], times["raw"], times["numpy_raw"]
    stage_rps = rays / float(np.median(stage_s))
    raw_rps = rays / float(np.median(raw_s))
    np_rps = rays / float(np.median(np_s))
    return {"scene": scene.name, "resolution": list(resolution), "lights": len(lights), "layout": layout,
            "rays": rays, "repeats": repeats, "path": f"device ({dev.variant})",
            "stage_ms": 1e3 * float(np.median(stage_s)), "raw_ms": 1e3 * float(np.median(raw_s)),
            "stage_rays_per_s": stage_rps, "raw_rays_per_s": raw_rps, "ratio": stage_rps / raw_rps,
            "ratio_range": paired_range(raw_s, stage_s), "raw": "device-resident rays",
            "numpy_raw_ms": 1e3 * float(np.median(np_s)),
            "numpy_raw_rays_per_s": np_rps, "numpy_raw_ratio": np_rps / raw_rps, "goal": 0.90}


# ------------------------------------------------------------------------------------------------ linearity

def fit_line(x, y) -> dict:
    """Least squares ``y = slope * x + intercept`` and its coefficient of determination R²."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    slope, intercept = np.polyfit(x, y, 1)
    residual = y - (slope * x + intercept)
    total = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - float((residual ** 2).sum()) / total if total > 0 else float("nan")
    return {"slope": float(slope), "intercept": float(intercept), "r2": r2}


def linearity(scene, tracer, resolutions, light_counts, t_s: float = 0.5, layout: str = "packed8",
              repeats: int = 3) -> dict:
    """Server work (G-buffer + visibility pass) at every resolution x light count; linear fits in pixels x lights.

    ``ms = a * (pixels * lights) + b``: ``a`` is reported in ns per pixel-light. The visibility pass is the work
    the claim is about (one ray per pixel and light); the whole server frame adds the G-buffer, which grows with
    pixels only, so its fit is reported beside it.
    """
    from methods.visibility_bitmap.method import visibility_pass

    all_lights = scene.lights_at(t_s)
    if max(light_counts) > len(all_lights):
        raise ValueError(f"scene {scene.name} has {len(all_lights)} lights, fewer than {max(light_counts)}")
    points = []
    for w, h in resolutions:
        for n in light_counts:
            lights = all_lights[:n]
            gbuffer_s, visibility_s, rays = [], [], 0
            for _ in range(max(repeats, 1)):
                t0 = time.perf_counter()
                g = _server_gbuffer(scene, tracer, t_s, (w, h))
                t1 = time.perf_counter()
                before = tracer.counters["rays_occluded"]
                _, raw = visibility_pass(g, lights, tracer, layout)
                if not isinstance(raw, np.ndarray):
                    raw.to_host()  # as the method's stage does
                t2 = time.perf_counter()
                rays = tracer.counters["rays_occluded"] - before
                gbuffer_s.append(t1 - t0)
                visibility_s.append(t2 - t1)
            points.append({"resolution": [w, h], "pixels": w * h, "lights": n, "pixel_lights": w * h * n,
                           "rays": int(rays), "gbuffer_ms": 1e3 * float(np.median(gbuffer_s)),
                           "visibility_ms": 1e3 * float(np.median(visibility_s)),
                           "server_ms": 1e3 * float(np.median(np.add(gbuffer_s, visibility_s)))})
    x = [p["pixel_lights"] for p in points]
    fits = {}
    for key in ("visibility_ms", "server_ms"):
        f = fit_line(x, [p[key] for p in points])
        fits[key] = {"ns_per_pixel_light": 1e6 * f["slope"], "intercept_ms": f["intercept"], "r2": f["r2"]}
    return {"scene": scene.name, "layout": layout, "repeats": repeats, "points": points, "fit": fits}


# --------------------------------------------------------------------------------------------- bytes, codecs

def codecs_by_resolution(scene, tracer, resolutions, frames: int, codec_specs, layouts=("paper32", "packed8"),
                         repeats: int = 1) -> list[dict]:
    """The codec table at each resolution, on the first ``frames`` bitmaps of the camera path."""
    rows = []
    for w, h in resolutions:
        vis = render_bitmaps(scene, tracer, (w, h), frames)
        for layout in layouts:
            if layout == "paper32" and vis[0].shape[-1] > bm.PAPER_MAX_LIGHTS:
                continue
            for row in codec_table(vis, layout, codec_specs, repeats=repeats):
                rows.append({"scene": scene.name, "resolution": [w, h], "pixels": w * h, **row})
    return rows


def bytes_by_lights(scene, tracer, resolution, light_counts, frames: int, codec_specs,
                    layouts=bm.LAYOUTS) -> list[dict]:
    """Bytes per frame against light count (the first N lights of ``scene``), per layout and codec."""
    rows = []
    for n in light_counts:
        vis = render_bitmaps(scene, tracer, tuple(resolution), frames, light_limit=n)
        for layout in layouts:
            if layout == "paper32" and n > bm.PAPER_MAX_LIGHTS:
                continue
            for row in codec_table(vis, layout, codec_specs, repeats=1):
                rows.append({"scene": scene.name, "resolution": list(resolution), "light_count": n,
                             "raw_bytes_per_frame": bm.bitmap_nbytes(*resolution, n, layout),
                             **{k: row[k] for k in ("codec", "layout", "available", "reason", "bytes_per_frame",
                                                    "ratio", "bit_exact") if k in row}})
    return rows


# ------------------------------------------------------------------------------------------------- storage

BENCH_NAME = "visibility_bitmap"  # results/bench/<name>.json
SCHEMA_VERSION = 1


def load(results_root) -> dict | None:
    """The stored benchmark document under ``results_root``, or None (read-only; used by the report)."""
    from suite.harness.reporting import load_bench

    return load_bench(BENCH_NAME, None, results_root)


def store(results_root, parts: dict) -> Path:
    """Merges ``parts`` into the stored document and returns its path. The document records the environment a
    run records in its config.json (package versions, host, git commit; :func:`suite.harness.cli.bench_document`)
    and is written atomically."""
    from suite.harness.cli import store_bench

    return store_bench(BENCH_NAME, results_root, parts, SCHEMA_VERSION)


# ---------------------------------------------------------------------------------------------------- CLI

PARTS = ("throughput", "linearity", "codecs", "lights")
TABLE_CODECS = ("none", "lzo", "lz4", "zstd", "bitplane+zstd", "delta+bitplane+zstd", "h264")


def _resolutions(text: str) -> list[tuple[int, int]]:
    from suite.harness.runner import parse_resolution

    return [tuple(parse_resolution(r)) for r in text.split(",") if r.strip()]


def _ints(text: str) -> list[int]:
    from suite.errors import UserError

    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"expected comma-separated integers, got '{text}'") from None
    if not values or min(values) < 1:
        raise UserError(f"expected integers >= 1, got '{text}'")
    return values


def parser() -> argparse.ArgumentParser:
    from suite.harness.cli import _Parser

    ap = _Parser(prog="splitbench bench visibility_bitmap", description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {', '.join(PARTS)}")
    ap.add_argument("--scene", default="living_room", help="throughput and codecs scene")
    ap.add_argument("--backend", default="embree")
    ap.add_argument("--resolution", default="640x360", help="throughput resolution")
    ap.add_argument("--repeats", type=int, default=7, help="throughput repeats (median)")
    ap.add_argument("--lights-scene", default="arena", help="linearity and light-count scene (many lights)")
    ap.add_argument("--linearity-resolutions", default="320x180,480x270,640x360")
    ap.add_argument("--linearity-lights", default="8,24,72")
    ap.add_argument("--linearity-repeats", type=int, default=3)
    ap.add_argument("--codec-resolutions", default="640x360,1280x720,1920x1080")
    ap.add_argument("--codecs", default=",".join(TABLE_CODECS))
    ap.add_argument("--frames", type=int, default=3, help="codec and light-count sequences: frames of the path")
    ap.add_argument("--light-counts", default="1,3,8,32,33,73")
    ap.add_argument("--lights-resolution", default="640x360")
    ap.add_argument("--out", default="results", help="results root; the document goes to <out>/bench/")
    ap.add_argument("--no-store", action="store_true", help="print only")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--loss", default="", help="comma-separated UDP loss rates (e.g. 0,0.01): run the UDP loss "
                                               "sweep instead (printed, not stored)")
    ap.add_argument("--codec", default="lz4", help="loss sweep: wire codec")
    ap.add_argument("--slice-rows", type=int, default=8, help="loss sweep: udp_slice_rows")
    return ap


def run(args) -> dict:
    """Runs the chosen parts; returns ``{part: result}``."""
    from suite.harness import runner
    from suite.errors import UserError

    from suite.harness.cli import bench_parts

    parts = bench_parts(args.parts, PARTS, args.backend)
    for name in (args.scene, args.lights_scene):
        if not os.path.isfile(name) and name not in runner.scene_names():
            raise UserError(f"unknown scene '{name}'")
    if args.repeats < 1 or args.linearity_repeats < 1 or args.frames < 1:
        raise UserError("--repeats, --linearity-repeats and --frames must be >= 1")
    out = {}
    cache = {}

    def scene_and_tracer(name):
        if name not in cache:
            scene = runner.load_scene(name)
            cache[name] = (scene, runner.make_tracer(args.backend, scene))
        return cache[name]

    if "throughput" in parts:
        scene, tracer = scene_and_tracer(args.scene)
        out["throughput"] = {"backend": args.backend,
                             **throughput(scene, tracer, _resolutions(args.resolution)[0], repeats=args.repeats)}
    if "linearity" in parts:
        scene, tracer = scene_and_tracer(args.lights_scene)
        out["linearity"] = {"backend": args.backend,
                            **linearity(scene, tracer, _resolutions(args.linearity_resolutions),
                                        _ints(args.linearity_lights), repeats=args.linearity_repeats)}
    if "codecs" in parts:
        scene, tracer = scene_and_tracer(args.scene)
        out["codecs"] = [dict(row, backend=args.backend) for row in codecs_by_resolution(
            scene, tracer, _resolutions(args.codec_resolutions), args.frames, args.codecs.split(","))]
    if "lights" in parts:
        scene, tracer = scene_and_tracer(args.lights_scene)
        counts = [n for n in _ints(args.light_counts) if n <= len(scene.lights_at(0.0))]
        out["lights"] = [dict(row, backend=args.backend) for row in bytes_by_lights(
            scene, tracer, _resolutions(args.lights_resolution)[0], counts, args.frames,
            ("none", "lz4", "bitplane+zstd"))]
    return out


def format_results(out: dict) -> str:
    lines = []
    if "throughput" in out:
        r = out["throughput"]
        w, h = r["resolution"]
        lines += [f"visibility pass vs raw {r['backend']} occluded: scene {r['scene']} {w}x{h}, {r['lights']} lights, "
                  f"{r['rays']:,} shadow rays, median of {r['repeats']}; {r.get('path', 'host')} path, raw = "
                  f"{r.get('raw', 'numpy rays')}",
                  f"  stage {r['stage_rays_per_s']:>13,.0f} rays/s ({r['stage_ms']:.1f} ms)   "
                  f"raw {r['raw_rays_per_s']:>13,.0f} rays/s ({r['raw_ms']:.1f} ms)   "
                  f"ratio {r['ratio']:.3f}{range_text(r.get('ratio_range'))}  (goal >= {r['goal']:.2f})"]
        if "numpy_raw_rays_per_s" in r:
            lines.append(f"  raw fed from numpy {r['numpy_raw_rays_per_s']:>13,.0f} rays/s ({r['numpy_raw_ms']:.1f} ms), "
                         f"{r['numpy_raw_ratio']:.3f} of the device-resident rate")
    if "linearity" in out:
        r = out["linearity"]
        lines.append(f"server work vs pixels x lights: scene {r['scene']}, median of {r['repeats']}")
        lines.append(f"  {'resolution':>10} {'lights':>6} {'pixel-lights':>13} {'rays':>11} {'G-buffer ms':>12} "
                     f"{'visibility ms':>14} {'server ms':>10}")
        for p in r["points"]:
            w, h = p["resolution"]
            lines.append(f"  {f'{w}x{h}':>10} {p['lights']:6d} {p['pixel_lights']:13,d} {p['rays']:11,d} "
                         f"{p['gbuffer_ms']:12.1f} {p['visibility_ms']:14.1f} {p['server_ms']:10.1f}")
        for key, f in r["fit"].items():
            lines.append(f"  fit {key:<14} = {f['ns_per_pixel_light']:.2f} ns x pixels x lights + "
                         f"{f['intercept_ms']:.1f} ms   R² {f['r2']:.4f}")
    if "codecs" in out:
        lines.append("codecs on the camera path's bitmaps (bytes per frame, ms per frame):")
        lines.append(f"  {'resolution':>10} {'layout':8} {'codec':20} {'wire B/frame':>13} {'ratio':>8} "
                     f"{'enc ms':>8} {'dec ms':>8}  exact")
        for r in out["codecs"]:
            w, h = r["resolution"]
            if not r["available"]:
                lines.append(f"  {f'{w}x{h}':>10} {r['layout']:8} {r['codec']:20} unavailable: {r['reason']}")
                continue
            lines.append(f"  {f'{w}x{h}':>10} {r['layout']:8} {r['codec']:20} {r['bytes_per_frame']:13,.0f} "
                         f"{r['ratio']:8.1f} {r['encode_ms']:8.2f} {r['decode_ms']:8.2f}  {r['bit_exact']}")
    if "lights" in out:
        lines.append("bytes per frame vs light count:")
        for r in out["lights"]:
            if r.get("available", True):
                lines.append(f"  {r['light_count']:4d} lights {r['layout']:8} {r['codec']:15} raw "
                             f"{r['raw_bytes_per_frame']:>10,d}  wire {r['bytes_per_frame']:>12,.0f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.loss:
        return _loss_main(args)
    out = run(args)
    if not args.no_store:
        path = store(args.out, out)
        out_note = f"stored: {path}"
    else:
        out_note = "not stored (--no-store)"
    if args.json:
        from suite.harness.cli import _print_json

        _print_json(out)
    else:
        print(format_results(out))
        print(out_note)
    return 0


def _loss_main(args) -> int:
    from suite.harness import runner

    w, h = _resolutions(args.resolution)[0]
    scene = runner.load_scene(args.scene)
    tracer = runner.make_tracer(args.backend, scene)
    rows = loss_sweep(scene, tracer, (w, h), args.frames, [float(x) for x in args.loss.split(",")],
                      params={"layout": "packed8", "codec": args.codec, "udp_slice_rows": args.slice_rows})
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{args.scene} {w}x{h}, {args.frames} frames, UDP, codec {args.codec}, {args.slice_rows} rows per slice")
    print(f"{'loss':>6} {'repair':9} {'rows repaired':>13} {'bad':>4} {'SSIM':>7} {'PSNR dB':>8} {'FLIP':>7}")
    for r in rows:
        print(f"{r['loss']:6.3f} {r['repair']:9} {100 * r['rows_repaired_fraction']:12.2f}% {r['bad_frames']:4d} "
              f"{r['ssim']:7.4f} {r['psnr_db']:8.2f} {r['flip']:7.4f}")
    return 0


if __name__ == "__main__":
    import sys

    from suite.errors import UserError

    try:
        sys.exit(main())
    except UserError as exc:
        print(f"splitbench: error: {exc}", file=sys.stderr)
        sys.exit(UserError.exit_code)
