"""Benchmarks of seed 004 (RAIL): ``splitbench bench rail`` (or ``python -m methods.rail.bench``).

Parts (``--parts``, default all), printed and stored in ``<results>/bench/rail.json`` (``--out``, default
``results``; a part that runs replaces its entry, the others are kept) so that the report shows them without
running anything:

``shading``
    One point-cloud shading pass (§3.2: light tracing + VPL·point shadow rays) against |Q| and against the
    number of light paths: ms per pass, VPL·point pairs per second, shadow rays per second, and the backend's
    raw rate on the very rays the pass traced (Embree: ``raw_occluded``), so the ratio shows what the pair
    generation and the suite's query cost on top of the backend.
``reconstruction``
    IDW through G (eq. 1-2, §3.3) against pixels (G-buffers of the camera path at 3 resolutions) and |Q|: ms per
    megapixel and records visited per pixel (the cell's list length) of the host loop (what Embree runs), and
    beside it the device path's (``device.py``) on every Dr.Jit backend that works here (``--device``): wall ms
    per megapixel, the device time alone, and the speed-up over the host loop; grid memory: §3.3's bound against
    what G holds (paper layout and this implementation).
``figures``
    Images for the report: one frame's direct light (the client's kernels), indirect light (final − direct: the
    IDW reconstruction times albedo/π) and final image, and seed 004's Fig. 10 as a sequence: frames of an
    asynchronous run over dsl-3m and of the zero-latency run while the lights move, and their grey |difference| ×2
    (written as PNGs under ``<results>/bench/rail/``).
``serving``
    One request's server work besides shading (§4.1: frustum clip, change test, encoding, LZF) on camera-path
    poses, and the amortisation model of §5.3 it implies for c clients: ideal t, actual r_p(c) + t with
    r_p(c) = c · (clip + encode), sequential c · t, speed-up.

Defaults (``dabrovic_sponza`` when available, else ``living_room``; Embree) run in about a minute on the 2-core
machine. Times are wall times on this machine and backend; they compare parts of one run with each other.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from suite.core.trace.recording import RecordingTracer

SCHEMA_VERSION = 1
PARTS = ("shading", "reconstruction", "serving", "figures")
FIGURE_FRAMES = (24, 36, 48, 60)


def store(results_root, parts: dict) -> Path:
    """Merges ``parts`` into ``<results>/bench/rail.json`` (with the environment a run records) atomically."""
    from suite.harness.cli import store_bench

    return store_bench("rail", results_root, parts, SCHEMA_VERSION)


def _params(**overrides) -> dict:
    from suite.harness import registry

    return {**registry.get("rail").params(), **overrides}


_PREPARED: dict = {}


def _prepare(scene, tracer, **overrides):
    """prepare() of the method for these parameters (once per process) and its ms."""
    from methods.rail.method import Rail

    key = (scene.name, tuple(sorted(overrides.items())))
    if key not in _PREPARED:
        t0 = time.perf_counter()
        prep = Rail(_params(**overrides)).prepare(scene, tracer)
        _PREPARED[key] = (prep, 1e3 * (time.perf_counter() - t0))
    return _PREPARED[key]


def _one_pass(scene, tracer, prep, n_paths: int, seed: int = 0, clamp: float = 0.5):
    from methods.rail.lighting import shade_points, trace_light_paths

    pts = prep["points"]
    rng = np.random.default_rng(seed)
    vpls = trace_light_paths(scene, tracer, 0.0, prep["light_positions"], prep["light_intensities"], n_paths,
                             3, rng, scene.area_light_triangles(0.0))
    _, counters = shade_points(pts.position, pts.normal, vpls, tracer, clamp * pts.spacing_m)
    return len(vpls), counters


def _raw_rate(recorder, repeats: int) -> float | None:
    """Rays/s of the backend's raw entry points on the rays ``recorder`` (a RecordingTracer) kept; None without
    them. On a Dr.Jit device (where the pass itself runs on the device, methods/rail/device.py) the rays are copied
    to the device once and the raw rate is that of rays in its memory (``Device.raw_occluded``)."""
    if not hasattr(recorder.tracer, "raw_occluded") or not recorder.log:
        return None
    dev = getattr(recorder.tracer, "device", None)
    if dev is not None:
        up = lambda a, t: dev.to_device(np.ascontiguousarray(a), t)  # noqa: E731
        rays = [dev.raw_ray(up(o, dev.Point3f), up(d, dev.Vector3f), up(length, dev.Float))
                for kind, o, d, length in recorder.log if kind == "o"]

        def replay():
            for ray in rays:
                dev.raw_occluded(ray)
    else:
        replay = recorder.replay
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        replay()
        times.append(time.perf_counter() - t0)
    return recorder.rays / float(np.median(times))


def bench_shading(scene, tracer, targets, paths, repeats: int) -> dict:
    rows = []
    base_paths = paths[len(paths) // 2]
    for target in targets:
        prep, prep_ms = _prepare(scene, tracer, target_points=int(target))
        for n_paths in (paths if target == targets[len(targets) // 2] else [base_paths]):
            times, counters, n_vpl = [], None, 0
            rec = RecordingTracer(tracer)
            for r in range(repeats):
                t0 = time.perf_counter()
                n_vpl, counters = _one_pass(scene, rec if r == 0 else tracer, prep, int(n_paths), seed=r)
                times.append(time.perf_counter() - t0)
            t = float(np.median(times))
            raw = _raw_rate(rec, repeats)
            rows.append({"target_points": int(target), "points": len(prep["points"]), "light_paths": int(n_paths),
                         "vpls": int(n_vpl), "pass_ms": 1e3 * t, "pairs": counters["pairs"],
                         "shadow_rays": counters["rays"], "pairs_per_s": counters["pairs"] / t,
                         "shadow_rays_per_s": counters["rays"] / t, "raw_rays_per_s": raw,
                         "pass_over_raw": (counters["rays"] / t) / raw if raw else None, "prepare_ms": prep_ms})
            print(f"  shading |Q|={rows[-1]['points']:6d} paths={n_paths:3d} vpls={n_vpl:4d}: "
                  f"{rows[-1]['pass_ms']:8.1f} ms, {rows[-1]['pairs_per_s'] / 1e6:6.2f} M pairs/s, "
                  f"{rows[-1]['shadow_rays_per_s'] / 1e6:6.2f} M rays/s"
                  + (f" (raw {raw / 1e6:.2f} M/s)" if raw else ""))
    return {"scene": scene.name, "backend": tracer.name if hasattr(tracer, "name") else "", "rows": rows}


def _gbuffer_samples(scene, tracer, resolution):
    from suite.core.gbuffer import render_gbuffer

    t = scene.camera.frame_time_s(0) + 0.5 * scene.camera.duration_s
    g = render_gbuffer(scene, tracer, t, resolution=resolution)
    return g.position[g.valid], g.normal[g.valid], int(g.valid.sum())


def _device_idw(scene, backend, grid_geometry, grid, pts, E, resolution, mu: float, repeats: int) -> dict:
    """The device path's IDW (methods/rail/device.py) on ``backend``'s own G-buffer of the same view: wall ms of a
    call (the per-frame upload of the records' irradiance included) and the device time alone (Dr.Jit's kernel
    history)."""
    from types import SimpleNamespace

    from methods.rail import device as rdev
    from suite.core.gbuffer import render_gbuffer_device
    from suite.harness.cli import bench_device

    dev = bench_device(scene, backend)
    tracer = dev.tracer
    t = scene.camera.frame_time_s(0) + 0.5 * scene.camera.duration_s
    g = render_gbuffer_device(scene, tracer, t, tuple(resolution))
    cg = SimpleNamespace(geometry=grid_geometry, grid=grid, position=pts.position, normal=pts.normal,
                         range_m=pts.range_m)
    dgrid = rdev.DeviceGrid(dev, cg)
    nrm = dev.Vector3d(g.normal)
    dev.eval(nrm)

    def call():
        out = rdev.idw(dgrid, dgrid.irradiance(E), g.position, nrm, g.valid, mu)
        dev.sync()
        return out

    call()                                                                  # compile / warm
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return {"ms": 1e3 * float(np.median(times)), "kernel_ms": dev.kernel_ms(call, repeats),
            "pixels": int(dev.dr.count(g.valid)[0])}


def bench_reconstruction(scene, tracer, targets, resolutions, repeats: int, devices=()) -> dict:
    """Host IDW (``grid.idw``, numba, one thread) on ``tracer``'s G-buffers, and beside it the device path's IDW on
    each backend of ``devices`` (its own G-buffer of the same view; the same records and irradiance)."""
    from methods.rail.grid import MultiRefGrid, idw
    from suite.harness.cli import device_columns

    rows, memory = [], []
    mu = float(_params()["idw_mu"])
    for target in targets:
        prep, _ = _prepare(scene, tracer, target_points=int(target))
        pts = prep["points"]
        grid = MultiRefGrid.build(prep["grid_geometry"], pts.position, pts.range_m)
        E = np.ones((len(pts), 3))
        memory.append({"target_points": int(target), **prep["grid_memory"]})
        for res in (resolutions if target == targets[len(targets) // 2] else [resolutions[len(resolutions) // 2]]):
            p, n, valid = _gbuffer_samples(scene, tracer, res)
            idw(grid, pts.position, pts.normal, pts.range_m, E, p[:16], n[:16], mu)     # compile / warm
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                _, wsum, visited = idw(grid, pts.position, pts.normal, pts.range_m, E, p, n, mu)
                times.append(time.perf_counter() - t0)
            t = float(np.median(times))
            row = {"target_points": int(target), "points": len(pts), "resolution": f"{res[0]}x{res[1]}",
                   "pixels": valid, "idw_ms": 1e3 * t, "ms_per_megapixel": 1e3 * t / max(valid, 1) * 1e6,
                   "records_visited_per_pixel": float(visited.mean()),
                   "zero_weight_share": float((wsum <= 0).mean())}
            line = (f"  idw |Q|={len(pts):6d} {res[0]}x{res[1]}: host {row['ms_per_megapixel']:8.1f} ms/MP, "
                    f"{row['records_visited_per_pixel']:.1f} records/pixel")
            for backend in devices:
                short = backend.replace("mitsuba-", "")

                def columns():
                    d = _device_idw(scene, backend, prep["grid_geometry"], grid, pts, E, res, mu, repeats)
                    mp = max(d["pixels"], 1) / 1e6
                    return {f"{short}_idw_ms": d["ms"], f"{short}_ms_per_megapixel": d["ms"] / mp,
                            f"{short}_kernel_ms_per_megapixel": d["kernel_ms"] / mp,
                            f"{short}_speedup": row["ms_per_megapixel"] / (d["ms"] / mp)}

                row.update(device_columns("rail", backend, columns))
                if f"{short}_ms_per_megapixel" in row:
                    line += (f", {short} {row[f'{short}_ms_per_megapixel']:8.1f} ms/MP (device "
                             f"{row[f'{short}_kernel_ms_per_megapixel']:.1f})")
            rows.append(row)
            print(line)
    return {"scene": scene.name, "rows": rows, "memory": memory, "devices": list(devices)}


def bench_serving(scene, tracer, clients, repeats: int) -> dict:
    from methods.rail import wire
    from methods.rail.method import contained_cells, encode_response, remember_sent, select_cells

    prep, _ = _prepare(scene, tracer)
    pts, geom = prep["points"], prep["grid_geometry"]
    start = contained_cells(geom, pts.position)
    occupied = np.flatnonzero(np.diff(start) > 0)
    cam = scene.camera
    poses = [cam.pose_at(cam.frame_time_s(0) + k * cam.duration_s / 8) for k in range(8)]
    t_pass = []
    for r in range(repeats):
        t0 = time.perf_counter()
        _one_pass(scene, tracer, prep, int(_params()["vpls"]), seed=r)
        t_pass.append(time.perf_counter() - t0)
    t_ms = 1e3 * float(np.median(t_pass))
    rng = np.random.default_rng(0)
    E0 = rng.random((len(pts), 3))
    times, sizes = [], []
    for pose in poses:
        E1 = E0 * rng.uniform(0.8, 1.2, (len(pts), 1))
        scales0, codes0 = wire.quantise(E0, start)
        sent = {"codes": codes0, "scales": scales0}
        t0 = time.perf_counter()
        cells, _, scales, codes = select_cells(E1, start, occupied, geom, pose, cam.fov_deg, cam.resolution,
                                               float(pts.range_m.max()), sent, False)
        remember_sent(sent, cells, scales, codes, start)
        raw, payload = encode_response(cells, scales, codes, start, 1, True)
        times.append(time.perf_counter() - t0)
        sizes.append((len(raw), len(payload)))
    serve_ms = 1e3 * float(np.median(times))
    rows = [{"clients": int(c), "ideal_ms": t_ms, "actual_ms": t_ms + c * serve_ms, "sequential_ms": c * t_ms,
             "speedup": c * t_ms / (t_ms + c * serve_ms)} for c in clients]
    print(f"  serving: pass {t_ms:.1f} ms, clip+encode {serve_ms:.2f} ms per request")
    return {"scene": scene.name, "points": len(pts), "pass_ms": t_ms, "serve_ms": serve_ms,
            "raw_bytes_mean": float(np.mean([s[0] for s in sizes])),
            "wire_bytes_mean": float(np.mean([s[1] for s in sizes])), "rows": rows}


def bench_figures(scene, tracer, results_root, frames: int = 61, resolution=(160, 90), net: str = "dsl-3m") -> dict:
    from suite.core.gbuffer import render_gbuffer
    from suite.core.imageio import write_png
    from suite.core.shading import direct_lighting
    from suite.harness import registry, runner

    cfg = runner.make_config("rail", scene=scene.name, resolution=f"{resolution[0]}x{resolution[1]}",
                             frames=frames, net=net, reference_spp=0, quality_every=-1, clock="work")
    cls = registry.get("rail").load()
    prepared, _ = _prepare(scene, tracer)
    keep = set(range(frames))
    seqs = {zl: runner.simulate(cls, scene, tracer, cfg, zl, keep=keep, prepared=prepared) for zl in (False, True)}
    t0, dt = scene.camera.frame_time_s(0), 1.0 / scene.camera.fps
    folder = Path(results_root) / "bench" / "rail"
    folder.mkdir(parents=True, exist_ok=True)
    last = frames - 1
    t = t0 + last * dt
    tracer.update(t)
    g = render_gbuffer(scene, tracer, t, resolution=resolution)
    direct = direct_lighting(scene, g, tracer, t, area_samples=int(cfg["params"]["area_samples"]), seed=0)
    final = seqs[False].images[(0, last)]
    comp = np.concatenate([direct, np.maximum(final - direct, 0.0), final], axis=1)
    pick = [i for i in FIGURE_FRAMES if i < frames]
    rows = [np.concatenate([seqs[zl].images[(0, i)] for i in pick], axis=1) for zl in (False, True)]
    diff = np.abs(rows[0] - rows[1]).mean(axis=-1, keepdims=True)        # only indirect light differs
    rows.append(np.repeat(2.0 * diff, 3, axis=-1))
    paths = {"components": folder / "components.png", "trailing": folder / "trailing.png"}
    write_png(paths["components"], np.repeat(np.repeat(comp, 2, 0), 2, 1))
    write_png(paths["trailing"], np.repeat(np.repeat(np.concatenate(rows, axis=0), 2, 0), 2, 1))
    ssim_note = []
    from suite.core.metrics import compare

    for i in pick:
        m = compare(seqs[True].images[(0, i)], seqs[False].images[(0, i)])
        ssim_note.append({"frame": i, "t_s": t0 + i * dt, "ssim": m["ssim"], "psnr_db": m["psnr_db"]})
    print(f"  figures: {paths['components']}, {paths['trailing']}")
    # paths relative to the results root, so that the document stays valid wherever the results are copied
    return {"scene": scene.name, "components": "bench/rail/components.png", "trailing": "bench/rail/trailing.png",
            "frames": pick, "quality": ssim_note,
            "setting": f"{scene.name}, {resolution[0]}x{resolution[1]}, {net}/tcp, default variant, frames {pick}"}


def run(args) -> dict:
    from suite.core.scene import load
    from suite.core.trace import make

    from suite.harness.cli import bench_devices, bench_scene

    devices = bench_devices(args.device)
    scene = load(bench_scene(args.scene, "rail"))
    tracer = make(args.backend, scene)
    targets = [int(x) for x in args.points.split(",")]
    paths = [int(x) for x in args.paths.split(",")]
    out = {}
    if "shading" in args.parts:
        out["shading"] = {**bench_shading(scene, tracer, targets, paths, args.repeats), "backend": args.backend}
    if "reconstruction" in args.parts:
        from suite.harness.runner import parse_resolution

        res = [tuple(parse_resolution(r)) for r in args.resolutions.split(",")]
        out["reconstruction"] = {**bench_reconstruction(scene, tracer, targets, res, args.repeats, devices),
                                 "backend": args.backend}
    if "serving" in args.parts:
        out["serving"] = {**bench_serving(scene, tracer, [int(c) for c in args.clients.split(",")], args.repeats),
                          "backend": args.backend}
    if "figures" in args.parts:
        out["figures"] = {**bench_figures(scene, tracer, args.out), "backend": args.backend}
    return out


def main(argv=None) -> int:
    from suite.harness.cli import bench_parts

    ap = argparse.ArgumentParser(prog="splitbench bench rail", description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--scene", default="auto", help="scene (auto: dabrovic_sponza when available)")
    ap.add_argument("--backend", default="embree")
    ap.add_argument("--points", default="2000,6000,14000", help="target_points values (|Q| sweep)")
    ap.add_argument("--paths", default="16,32,64", help="light paths per pass (VPL sweep)")
    ap.add_argument("--resolutions", default="160x90,320x180,640x360")
    ap.add_argument("--clients", default="1,2,4,8,16,24,32")
    ap.add_argument("--device", default="auto", help="Dr.Jit backends to time the device IDW on beside the host "
                    "loop (auto: every one that works here; '' for none)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default="results")
    ap.add_argument("--no-store", action="store_true")
    args = ap.parse_args(argv)
    args.parts = bench_parts(args.parts, PARTS, args.backend)
    out = run(args)
    if not args.no_store:
        print(f"stored: {store(args.out, out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
