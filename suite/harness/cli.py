"""``splitbench`` command line (also ``python -m suite``). The surface is fixed by ../shared/design.md.

Errors a user can cause are one line on stderr (``splitbench: error: …``) with exit code 2, never a traceback.
``--json`` prints machine-readable results on stdout; progress bars go to stderr.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path

from suite.errors import UserError

PROG = "splitbench"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors and exit code 2 (argparse's own code, without the usage block)."""

    def error(self, message):
        raise UserError(message)


def _check_writable_dir(path, what: str = "--out") -> Path:
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise UserError(f"cannot write to {what} '{path}' ({exc.strerror or exc})") from None
    return path


def _print_json(obj) -> None:
    from suite.harness.results import _jsonable

    print(json.dumps(_jsonable(obj), indent=2, sort_keys=True))


def _parse_set_grid(items) -> dict[str, list]:
    """``--set key=value`` items as {key: [values...]}: a key given more than once spans a grid."""
    from suite.harness.registry import parse_set_value

    values: dict[str, list] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"malformed --set '{item}' (expected key=value)")
        grid = values.setdefault(key.strip(), [])
        parsed = parse_set_value(value.strip())
        if parsed not in grid:
            grid.append(parsed)
    return values


def _parse_sets(items) -> dict:
    return {key: vals[-1] for key, vals in _parse_set_grid(items).items()}


# ---------------------------------------------------------------------------------------------------- list

def cmd_list(args) -> int:
    from suite.harness import registry, runner

    methods = {}
    for name, spec in registry.discover().items():
        entry = {"description": spec.description, "params": spec.defaults, "doc": spec.docs,
                 "aliases": spec.config.get("aliases", {}), "variants": spec.variants,
                 "presets": sorted(spec.config.get("presets", {})), "path": str(spec.path)}
        try:
            entry["mode"] = spec.load().mode
        except Exception as exc:  # noqa: BLE001 - a broken method must not hide the others
            entry["mode"] = None
            entry["error"] = f"{type(exc).__name__}: {exc}"
        methods[name] = entry
    info = {"methods": methods, "scenes": _safe(_scenes), "backends": _safe(_backends),
            "backend_status": _safe(_backend_status), "net_profiles": _safe(runner.net_profiles)}
    if args.json:
        _print_json(info)
        return 0
    print("methods:")
    for name, m in methods.items():
        print(f"  {name:<20} {m.get('mode') or '?':<6} {m['description']}" + (f"  [{m['error']}]" if 'error' in m else ""))
    for title, key in (("scenes", "scenes"), ("backends", "backends"), ("net profiles", "net_profiles")):
        print(f"{title}:" + (" (on this machine)" if key == "backends" else ""))
        width = max([20, *(len(str(name)) for name in info[key])])  # one column of names, however long
        for name, desc in info[key].items():
            status = info["backend_status"].get(name) if key == "backends" else None
            if isinstance(status, dict):
                mark = "ok" if status["available"] else "unavailable"
                print(f"  {name:<{width}} [{mark}: {status['detail']}] {desc}")
            else:
                print(f"  {name:<{width}} {desc}")
    return 0


def _scenes():
    from suite.core.scene import list_scenes

    return list_scenes()


def _backends():
    from suite.core.trace import list_backends

    return list_backends()


def _backend_status():
    """Which backends work on this machine and what ``mitsuba`` (auto) resolves to."""
    from suite.core.trace import backend_status

    return backend_status()


def _safe(fn) -> dict:
    try:
        return dict(fn())
    except ImportError as exc:
        return {"(unavailable)": str(exc)}


# ----------------------------------------------------------------------------------------------------- run

def cmd_run(args) -> int:
    """One run, or a grid of runs when ``--set KEY=...`` repeats a key or ``--net``/``--protocol`` repeat; a grid
    goes through the executor (serial, local processes or Dask)."""
    import itertools

    from suite.harness import executor, runner

    options = {}
    if args.reference_spp is not None:
        options["reference_spp"] = args.reference_spp
    if args.clock is not None:
        options["clock"] = args.clock
    if args.server_net is not None:
        options["server_net"] = args.server_net
    if args.quality_clients is not None:
        options["quality_clients"] = args.quality_clients
    set_grid = _parse_set_grid(args.set)
    nets = list(dict.fromkeys(args.net or ["ideal"]))
    protocols = list(dict.fromkeys(args.protocol or ["tcp"]))
    client_counts = list(dict.fromkeys(args.clients or [1]))
    keys = list(set_grid)
    configs = []
    for net, protocol, clients, *values in itertools.product(nets, protocols, client_counts,
                                                             *(set_grid[k] for k in keys)):
        configs.append(runner.make_config(args.method, scene=args.scene, backend=args.backend,
                                          resolution=args.resolution, frames=args.frames, net=net,
                                          protocol=protocol, set_values=dict(zip(keys, values)), seed=args.seed,
                                          clients=clients, **options))
    out_dir = _check_writable_dir(args.out)
    if len(configs) == 1:
        outs = [runner.execute(configs[0], out_dir, force=args.force)]
    else:
        with executor.make_executor(args.executor, args.scheduler, args.workers) as ex:
            outcomes = executor.sweep(configs, out_dir, ex, desc=f"{args.method} grid", force=args.force)
        failed = [o for o in outcomes if o["error"]]
        if failed:
            raise UserError(f"{len(failed)} of {len(configs)} runs failed; first: {failed[0]['error']}")
        outs = [{"run_dir": o["run_dir"], "skipped": o["skipped"],
                 "summary": json.loads((Path(o["run_dir"]) / "summary.json").read_text())} for o in outcomes]
    if args.json:
        _print_json(outs[0] if len(outs) == 1 else outs)
    else:
        print("\n\n".join(format_summary(out) for out in outs))
    return 0


def _stat(summary, col, key="mean"):
    value = summary.get("stats", {}).get(col, {}).get(key)
    return float("nan") if value is None else value


def format_summary(out: dict) -> str:
    s = out["summary"]
    w, h = s["resolution"]
    lines = [f"results: {out['run_dir']}" + ("  (already complete: skipped)" if out["skipped"] else ""),
             f"{s['method']} [{s['variant']}, {s['mode']}]  scene {s['scene']}  {w}x{h}  {s['frames']} frames  "
             f"net {s['net']}/{s['protocol']}"
             + (f"  {s['clients']} clients" if s.get("clients", 1) > 1 else "")
             + (f"  server link {s['server_net']}" if s.get("server_net") else ""),
             f"  frame ms     mean {_stat(s, 'frame_ms'):8.2f}   p50 {_stat(s, 'frame_ms', 'p50'):8.2f}   "
             f"p95 {_stat(s, 'frame_ms', 'p95'):8.2f}   ({s['fps']:.1f} fps simulated)",
             f"  latency ms   mean {_stat(s, 'latency_ms'):8.2f}   p95 {_stat(s, 'latency_ms', 'p95'):8.2f}"
             + (f"   staleness mean {_stat(s, 'staleness_ms'):.2f}" if s["mode"] == "async" else ""),
             f"  bandwidth    {s['bandwidth_mbps']:.3f} Mbit/s  (down {s['bandwidth_down_mbps']:.3f}, "
             f"up {s['bandwidth_up_mbps']:.3f}; {s['bytes_down'] + s['bytes_up']} bytes)",
             f"  work         {s['rays']} rays   prepare {s['prepare_ms']:.1f} ms"
             + ("  (reused)" if s.get("prepare_reused") else "")]
    if s["mode"] == "async" and "staleness_ms" not in s.get("stats", {}):
        # No frame had an update in use (staleness is defined only then): the quality below is that of the
        # client's picture before any update arrived.
        lines.append(f"  note         no update reached the client in these {s['frames']} frames: it showed what it "
                     f"had before one (run more frames)")
    for label, prefix in (("vs reference", ""), ("vs zero-latency", "zl_")):
        ssim = _stat(s, f"{prefix}ssim")
        if prefix and not s.get("zero_latency_run"):
            lines.append(f"  {label:<16} identical (this run is its own zero-latency run)")
        elif not math.isnan(ssim):
            # PSNR has no finite value only when every compared frame was identical (infinite PSNR).
            psnr = _stat(s, f"{prefix}psnr_db")
            psnr_text = "inf" if math.isnan(psnr) else f"{psnr:.2f}"
            lines.append(f"  {label:<16} SSIM {ssim:.4f}   DSSIM {_stat(s, f'{prefix}dssim'):.4f}   "
                         f"PSNR {psnr_text} dB   FLIP {_stat(s, f'{prefix}flip'):.4f}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- reference, compare

def cmd_reference(args) -> int:
    from suite.harness import runner
    from suite.core.imageio import write_exr

    out = Path(args.out)
    if out.suffix.lower() != ".exr":
        raise UserError(f"--out '{out}' must end in .exr")
    if args.spp < 1:
        raise UserError(f"--spp must be >= 1, got {args.spp}")
    if args.frame < 0:
        raise UserError(f"--frame must be >= 0, got {args.frame}")
    _check_writable_dir(out.parent if str(out.parent) else ".", "--out directory")
    scene = runner.load_scene(args.scene)
    resolution = runner.parse_resolution(args.resolution) if args.resolution else list(scene.camera.resolution)
    t_s = scene.camera.frame_time_s(args.frame)
    img = runner.reference_image(scene, t_s, resolution, args.spp, args.max_depth)
    write_exr(out, img)
    info = {"out": str(out), "scene": args.scene, "t_s": t_s, "resolution": resolution, "spp": args.spp,
            "max_depth": args.max_depth}
    _print_json(info) if args.json else print(f"wrote {out} ({resolution[0]}x{resolution[1]}, {args.spp} spp, "
                                              f"t={t_s:.4f} s)")
    return 0


def cmd_compare(args) -> int:
    from suite.core.imageio import read_exr
    from suite.core.metrics import compare

    images = []
    for path in (args.ref, args.test):
        if not os.path.isfile(path):
            raise UserError(f"no such image '{path}'")
        images.append(read_exr(path))
    metrics = compare(images[0], images[1], exposure=args.exposure)
    if args.json:
        _print_json(metrics)
    else:
        for k, v in metrics.items():
            print(f"{k:<8} {v:.6g}")
    return 0


# ------------------------------------------------------------------------------------------------------ bench

def cmd_bench(args) -> int:
    if args.what == "tracing":
        return _bench_tracing(args.rest)
    if args.what == "core":
        return _bench_core(args.rest)
    if args.what == "clients":
        from suite.harness import bench_clients

        return int(bench_clients.main(list(args.rest)) or 0)
    bench = _method_bench(args.what)
    if hasattr(bench, "main"):
        return int(bench.main(list(args.rest)) or 0)
    _print_json(bench_document(bench.run(list(args.rest))))
    return 0


def bench_document(figures: dict) -> dict:
    """A benchmark's figures with the environment a run records in its config.json (package versions, host,
    git commit: :func:`suite.harness.results.environment`), so a stored or printed benchmark says where it ran."""
    from suite.harness import results

    return {**figures, **results.environment()}


def store_bench(name: str, results_root, parts: dict, schema_version: int):
    """Merges ``parts`` into the benchmark document ``<results>/bench/<name>.json`` (the parts of other runs kept,
    read as :func:`suite.harness.reporting.load_bench` reads it), stamped with ``schema_version`` and the
    environment (:func:`bench_document`), written atomically. Returns its path."""
    from suite.harness.reporting import load_bench

    doc = {**(load_bench(name, None, results_root) or {}), **parts, "schema_version": schema_version}
    return _store_bench(results_root, name, bench_document(doc))


def bench_parts(text: str, known, backend: str) -> list[str]:
    """A method bench's ``--parts`` list and ``--backend``, checked: each an error naming it when unknown."""
    from suite.harness import runner

    parts = [p.strip() for p in text.split(",") if p.strip()]
    unknown = sorted(set(parts) - set(known))
    if unknown or not parts:
        raise UserError(f"unknown benchmark part '{unknown[0] if unknown else text}' (choose from {', '.join(known)})")
    if backend not in runner.backend_names():
        raise UserError(f"unknown backend '{backend}' (choose from {', '.join(runner.backend_names())})")
    return parts


def bench_devices(text: str) -> list[str]:
    """A method bench's ``--device``: ``auto`` is every Dr.Jit backend that works here, ``''`` none, else a
    comma-separated list, each checked (a one-line error naming a backend that is not a Dr.Jit one or does not work
    on this machine)."""
    from suite.core.trace import backend_status, device_backends

    if text == "auto":
        return device_backends()
    names = [b.strip() for b in text.split(",") if b.strip()]
    status = backend_status()
    for b in names:
        if b not in ("mitsuba-llvm", "mitsuba-cuda"):
            raise UserError(f"--device: '{b}' is not a Dr.Jit backend (choose from auto, mitsuba-llvm, mitsuba-cuda)")
        if not status.get(b, {}).get("available"):
            raise UserError(f"--device: backend '{b}' does not work on this machine ({status.get(b, {}).get('detail')})")
    return names


_BENCH_DEVICES: dict = {}


def bench_device(scene, backend: str):
    """The Dr.Jit device of a ``backend`` tracer on ``scene``, made once per process (``.tracer`` is the tracer): what
    a method bench times its device kernels on beside the run's own backend."""
    from suite.core.trace import make

    key = (scene.name, backend)
    if key not in _BENCH_DEVICES:
        _BENCH_DEVICES[key] = make(backend, scene).device
    return _BENCH_DEVICES[key]


def device_columns(bench: str, backend: str, fn) -> dict:
    """``fn()``'s columns of a device kernel's timing on ``backend``; where it fails, a warning naming the kernel's
    bench and backend, and the error in a ``<backend>_error`` column instead (the host columns and the other
    devices' stay valid)."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - reported, stored and shown in the report; the bench goes on
        short = backend.replace("mitsuba-", "")
        message = f"{type(exc).__name__}: {exc}".splitlines()[0]
        print(f"{PROG}: warning: bench {bench}: the device kernel on {backend} failed: {message}", file=sys.stderr)
        return {f"{short}_error": message}


def device_rows(bench: str, backends, scene, fn) -> list:
    """One row per Dr.Jit backend of ``backends``: ``{"backend": name, **fn(name, tracer)}`` with a fresh tracer of
    that backend on ``scene``, or the backend's error (:func:`device_columns`): a method bench's stages timed again on
    each device beside its own backend."""
    from suite.core.trace import make

    return [{"backend": b, **device_columns(bench, b, lambda b=b: fn(b, make(b, scene)))} for b in backends]


def bench_scene(name: str, bench: str, preferred: str = "dabrovic_sponza", fallback: str = "living_room") -> str:
    """A method bench's ``--scene``: ``auto`` is ``preferred`` where its data is on this machine, else ``fallback``
    (with a note); any other name is kept."""
    from suite.harness.presets import scene_available

    if name != "auto":
        return name
    if scene_available(preferred):
        return preferred
    print(f"{PROG}: note: {preferred} is not available on this machine; bench {bench} uses {fallback}",
          file=sys.stderr)
    return fallback


def bench_names() -> list[str]:
    """``tracing``, ``core``, ``clients`` plus every method folder that ships a bench.py."""
    from suite.harness import registry

    return ["tracing", "core", "clients"] + [n for n, spec in registry.discover().items() if spec.has_module("bench")]


def _method_bench(name: str):
    """Imports ``methods/<name>/bench.py`` (:func:`suite.harness.registry.load_module`); it must define
    ``main(argv)`` or ``run(argv)``."""
    from suite.harness import registry

    spec = registry.discover().get(name)
    if spec is None or not spec.has_module("bench"):
        raise UserError(f"unknown benchmark '{name}' (choose from {', '.join(bench_names())})")
    module = spec.load_module("bench")
    if not hasattr(module, "main") and not hasattr(module, "run"):
        raise UserError(f"{spec.path / 'bench.py'} defines neither main(argv) nor run(argv)")
    return module


def _bench_selection(args, runner):
    """Scenes and backends of ``--scene``/``--backend`` (``all``: every available embedded scene, every backend that
    works on this machine; comma-separated lists allowed)."""
    from suite.core.trace import backend_status

    if args.backend == "all":
        backends = [b for b, st in backend_status().items() if st["available"] and b not in ("mitsuba", "mitsuba-scalar")]
    else:
        backends = [b.strip() for b in args.backend.split(",") if b.strip()]
    for b in backends:
        if b not in runner.backend_names():
            raise UserError(f"unknown backend '{b}' (choose from all, {', '.join(runner.backend_names())})")
    if args.scene == "all":
        from suite.core.scene import list_scenes

        scenes = [n for n, desc in list_scenes().items() if not str(desc).startswith("unavailable")
                  and not runner.is_map_spec(n)]
    else:
        scenes = [x.strip() for x in args.scene.split(",") if x.strip()]
    for name in scenes:
        if not os.path.isfile(name) and name not in runner.scene_names():
            raise UserError(f"unknown scene '{name}'")
    return scenes, backends


def _store_bench(out_root, name: str, doc: dict) -> Path:
    from suite.harness import results

    path = Path(out_root) / "bench" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    results.write_json(path, doc)
    return path


def _bench_tracing(argv) -> int:
    from suite.harness import runner

    p = _Parser(prog=f"{PROG} bench tracing", description="suite vs raw backend rays/s and their ratio")
    p.add_argument("--scene", default="cornell", help="embedded name or XML path, a comma-separated list, or 'all'")
    p.add_argument("--backend", default="embree", help="a backend, a comma-separated list, or 'all' (every backend "
                   "that works here)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--max-rays", type=int, default=500_000, help="shadow rays per call (at most the pixels of "
                   "--resolution times the scene's point lights)")
    p.add_argument("--resolution", default="640x360", help="the camera view the shadow rays leave from")
    p.add_argument("--out", default=None, help="results root: store the figures in <out>/bench/tracing.json")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        import importlib

        bench = importlib.import_module("suite.core.trace.bench")  # through sys.modules (tests substitute it)
    except ImportError as exc:
        raise UserError(f"the tracing benchmark is not available in this installation ({exc})") from None
    if args.repeats < 1:
        raise UserError("--repeats must be >= 1")
    if args.max_rays < 1:
        raise UserError("--max-rays must be >= 1")
    resolution = tuple(runner.parse_resolution(args.resolution))
    if args.backend != "all" and "," not in args.backend and args.backend not in runner.backend_names():
        raise UserError(f"unknown backend '{args.backend}' (choose from {', '.join(runner.backend_names())})")
    if args.scene != "all" and "," not in args.scene and not os.path.isfile(args.scene) \
            and args.scene not in runner.scene_names():
        raise UserError(f"unknown scene '{args.scene}'")
    scenes, backends = _bench_selection(args, runner)
    rows = []
    for name in scenes:
        scene = runner.load_scene(name)
        for backend in backends:
            row = bench.run(scene, backend, max_rays=args.max_rays, repeats=args.repeats, resolution=resolution)
            row.setdefault("backend", backend)
            rows.append(row)
    result = bench_document(rows[0] if len(rows) == 1 else {"results": rows, "goal": 0.9})
    if args.out:
        _store_bench(args.out, "tracing", result)
    if args.json:
        _print_json(result)
        return 0
    from suite.harness.reporting import range_text

    print(f"tracing benchmark: suite vs raw rays/s, median of {rows[0].get('repeats', '?')} (goal: suite/raw >= 0.90); raw = "
          "the backend's own rate on rays in its memory (Dr.Jit arrays for Mitsuba); (repeats lo-hi): the lowest and "
          "highest ratio of one repeat's two calls")
    print(f"  host {result['host']['node']} ({result['host']['platform']}), git {result['git']['commit'][:12]}")
    for r in rows:
        print(f"  {r['scene']} on {r['backend']} ({r.get('interface', 'numpy')}), {r['rays']:,} shadow rays")
        for query in ("occluded", "intersect"):
            q = r[query]
            walk = q.get("queries_per_ray", 1.0)
            print(f"    {query:9s}  suite {q['suite_rays_per_s']:>13,.0f} rays/s   raw {q['raw_rays_per_s']:>13,.0f} "
                  f"rays/s   ratio {q['ratio']:.3f}{range_text(q.get('ratio_range'))}"
                  + (f"   ({walk:.2f} backend queries per ray: the alpha walk)" if walk > 1.0005 else ""))
            if "kernel_ratio" in q:
                print(f"    {'':9s}  per call: suite {q['suite_ms']:.3f} ms, raw {q['raw_ms']:.3f} ms; device time "
                      f"alone (kernel history): suite {q['suite_kernel_ms']:.3f} ms, raw {q['raw_kernel_ms']:.3f} ms, "
                      f"ratio {q['kernel_ratio']:.3f}")
            if "numpy" in q:
                n = q["numpy"]
                print(f"    {'':9s}  numpy-fed: suite {n['suite_rays_per_s']:>13,.0f}   raw {n['raw_rays_per_s']:>13,.0f}"
                      f"   ratio {n['ratio']:.3f}   suite/device raw {n['suite_of_device_raw']:.3f}")
    if args.out:
        print(f"stored: {Path(args.out) / 'bench' / 'tracing.json'}")
    return 0


def _bench_core(argv) -> int:
    from suite.harness import runner

    p = _Parser(prog=f"{PROG} bench core", description="per-stage ms, rays and pixels of the rendering core")
    p.add_argument("--scene", default="living_room", help="embedded name or XML path, a comma-separated list, or 'all'")
    p.add_argument("--backend", default="all", help="a backend, a comma-separated list, or 'all' (default)")
    p.add_argument("--resolution", default="1920x1080")
    p.add_argument("--repeats", type=int, default=7,
                   help="median of this many calls per stage (ratios: interleaved calls of both sides)")
    p.add_argument("--area-samples", type=int, default=4)
    p.add_argument("--out", default="results", help="results root; the figures go to <out>/bench/core.json")
    p.add_argument("--no-store", action="store_true")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    from suite.core.trace import bench

    if args.repeats < 1:
        raise UserError("--repeats must be >= 1")
    resolution = runner.parse_resolution(args.resolution)
    scenes, backends = _bench_selection(args, runner)
    rows = []
    for name in scenes:
        scene = runner.load_scene(name)
        for backend in backends:
            rows.append(bench.core(scene, backend, resolution, repeats=args.repeats, area_samples=args.area_samples))
    result = bench_document({"results": rows, "goals": {"gbuffer_over_raw_intersect": "<= 2",
                                                        "visibility_raw_over_pass": ">= 0.9"}})
    path = None if args.no_store else _store_bench(args.out, "core", result)
    if args.json:
        _print_json(result)
        return 0
    print(format_core(rows))
    print(f"stored: {path}" if path else "not stored (--no-store)")
    return 0


def format_core(rows) -> str:
    from suite.harness.reporting import range_text

    lines = []
    for r in rows:
        w, h = r["resolution"]
        lines.append(f"{r['scene']} {w}x{h} on {r['backend']} [{r['path']}], {r['lights']} point lights, "
                     f"{r['area_lights']} area-light triangles, median of {r['repeats']}")
        lines.append(f"  {'stage':26s} {'ms':>9s} {'kernel ms':>10s} {'rays':>12s} {'pixels':>10s} {'bytes':>12s}")
        for st in r["stages"]:
            b = f"{st['bytes']:12,d}" if "bytes" in st else f"{'':12s}"
            k = f"{st['kernel_ms']:10.2f}" if "kernel_ms" in st else f"{'':10s}"
            lines.append(f"  {st['stage']:26s} {st['ms']:9.2f} {k} {st['rays']:12,d} {st['pixels']:10,d} {b}"
                         + (f"  ({st['note']})" if st.get("note") else ""))
        def kern(key, digits):
            return f"; device time alone (kernel ms): {r[key]:.{digits}f}" if key in r else ""

        lines.append(f"  G-buffer / raw intersect of the camera rays: {r['gbuffer_over_raw_intersect']:.2f}"
                     f"{range_text(r.get('gbuffer_over_raw_intersect_range'), 2)} (goal <= 2)"
                     + kern("gbuffer_over_raw_intersect_kernels", 2))
        if "visibility_raw_over_pass" in r:
            lines.append(f"  visibility pass: raw/pass {r['visibility_raw_over_pass']:.3f}"
                         f"{range_text(r.get('visibility_raw_over_pass_range'))} (goal >= 0.9)"
                         + kern("visibility_raw_over_pass_kernels", 3))
    return "\n".join(lines)


# -------------------------------------------------------------------------------------------------- reproduce

def cmd_reproduce(args) -> int:
    from suite.harness import executor, presets

    if args.matrix and args.preset not in presets.registry.SHARED_PRESETS:
        raise UserError(f"--matrix applies to the shared presets ({', '.join(presets.registry.SHARED_PRESETS)}), "
                        f"not '{args.preset}'")
    configs, problems, record = presets.expand(args.preset, methods=args.methods, matrix_file=args.matrix)
    results_dir = _check_writable_dir(args.out)
    report_dir = _check_writable_dir(args.report, "--report")
    for problem in problems:
        print(f"{PROG}: warning: {problem}", file=sys.stderr)
    for scene in record.get("skipped_scenes", []):
        print(f"{PROG}: note: scene '{scene}' is not available on this machine; its {args.preset} runs are "
              "skipped (recorded in the report; docs/scenes.md says where its data goes)", file=sys.stderr)
    # Which scenes this machine has (the report marks those it lacks) is recorded beside the runs.
    from suite import fileio

    fileio.write_text(Path(results_dir) / "scenes.json",
                      json.dumps({"scenes": runner_scenes()}, indent=2, sort_keys=True) + "\n")
    import time

    start_s = time.perf_counter()
    with executor.make_executor(args.executor, args.scheduler, args.workers) as ex:
        outcomes = executor.sweep(configs, results_dir, ex, desc=f"preset {args.preset}", force=args.force)
    # What ran, how long the sweep took and where (the README's budgets come from these records).
    record.update({"problems": problems, "executor": ex.name, "scheduler": args.scheduler,
                   "wall_s": time.perf_counter() - start_s, "host_cpus": os.cpu_count(),
                   # Summed per-run wall time (the sweep's CPU-bound work; divided over the workers in wall_s).
                   "runs_wall_s": sum(o.get("wall_s", 0.0) for o in outcomes if not o["skipped"]),
                   "done": sum(1 for o in outcomes if not o["error"] and not o["skipped"]),
                   "already_complete": sum(1 for o in outcomes if o["skipped"]),
                   "run_dirs": [Path(o["run_dir"]).name for o in outcomes if o["run_dir"]],
                   "failed": [{"method": o["config"]["method"], "scene": o["config"]["scene"],
                               "net": o["config"]["net"], "error": o["error"]} for o in outcomes if o["error"]]})
    (Path(results_dir) / "presets").mkdir(exist_ok=True)
    fileio.write_text(Path(results_dir) / "presets" / f"{args.preset}.json",
                      json.dumps(record, indent=2, sort_keys=True, default=str) + "\n")
    index = None
    if not args.no_report:
        from reports.build import build

        index = build(results_dir, report_dir)
    failed = [o for o in outcomes if o["error"]]
    if args.json:
        _print_json({"preset": args.preset, "results": str(results_dir), "report": str(index) if index else None,
                     "problems": problems,
                     "runs": [{k: o[k] for k in ("run_dir", "skipped", "error")} | {"method": o["config"]["method"]}
                              for o in outcomes]})
    else:
        done = sum(1 for o in outcomes if not o["error"] and not o["skipped"])
        skipped = sum(1 for o in outcomes if o["skipped"])
        print(f"preset {args.preset}: {done} runs done, {skipped} already complete, {len(failed)} failed")
        for o in failed:
            print(f"  FAILED {o['config']['method']} {o['config']['scene']} {o['config']['net']}: {o['error']}")
        print(f"report: {index}" if index else "report: not built (--no-report)")
    return 1 if failed or problems else 0


def runner_scenes() -> dict:
    from suite.core.scene import list_scenes

    return dict(list_scenes())


def cmd_report(args) -> int:
    from reports.build import build

    results_dir = Path(args.results)
    if not results_dir.is_dir():
        raise UserError(f"no results directory '{results_dir}'")
    out = _check_writable_dir(args.out)
    index = build(results_dir, out)
    _print_json({"report": str(index)}) if args.json else print(f"report: {index}")
    return 0


# ------------------------------------------------------------------------------------------------------ parser

def build_parser() -> argparse.ArgumentParser:
    from suite.harness.executor import EXECUTORS

    p = _Parser(prog=PROG, description="Offline benchmark suite for split/remote rendering pipelines.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    s = sub.add_parser("list", help="methods, scenes, backends, net profiles")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_list)

    s = sub.add_parser("run", help="run one method on one scene and network")
    s.add_argument("method")
    s.add_argument("--scene", default=None, help="embedded name, oa:<map>, a scene on the search path, or a path to a Mitsuba XML / OBJ / BSP / PK3 file (default: the method's [method] scene, else cornell)")
    s.add_argument("--backend", default="embree")
    s.add_argument("--resolution", default="160x90", help="WxH")
    s.add_argument("--frames", default=3, type=_int_arg("--frames"))
    s.add_argument("--net", action="append", default=None,
                   help="netsim profile or inline spec; 'ideal' = zero-latency (repeat for a grid)")
    s.add_argument("--protocol", action="append", default=None, choices=("tcp", "udp"), help="(repeat for a grid)")
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="method parameter (repeatable); "
                   "variant=paper|<name> picks a variant")
    s.add_argument("--seed", default=0, type=_int_arg("--seed"))
    s.add_argument("--clients", action="append", default=None, type=_int_arg("--clients"),
                   help="clients on the one server (default 1; repeat for a grid)")
    s.add_argument("--server-net", default=None,
                   help="profile of the server's link that all clients share (default: no shared bottleneck)")
    s.add_argument("--quality-clients", type=int, default=None,
                   help="how many clients are compared with the references (default 1; -1: all)")
    s.add_argument("--force", action="store_true", help="recompute even if a complete run with this key exists")
    s.add_argument("--out", default="results", help="results root")
    s.add_argument("--reference-spp", type=_int_arg("--reference-spp"), default=None,
                   help="spp of the path-traced reference (0 = no reference metrics; default 32)")
    s.add_argument("--clock", choices=("measured", "work"), default=None,
                   help="stage durations: measured wall time (default) or the work model")
    s.add_argument("--executor", default="serial", choices=EXECUTORS, help="for grids: serial, processes or dask")
    s.add_argument("--scheduler", default=None, help="for grids: Dask scheduler address tcp://host:port")
    s.add_argument("--workers", default=2, type=_int_arg("--workers"))
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("reference", help="render a Mitsuba path-traced reference (cached)")
    s.add_argument("--scene", required=True)
    s.add_argument("--resolution", default=None)
    s.add_argument("--spp", default=256, type=_int_arg("--spp"))
    s.add_argument("--frame", default=0, type=_int_arg("--frame"))
    s.add_argument("--max-depth", default=8, type=_int_arg("--max-depth"))
    s.add_argument("--out", required=True)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_reference)

    s = sub.add_parser("compare", help="ssim, dssim, psnr, nrmse, flip of TEST against REF")
    s.add_argument("ref")
    s.add_argument("test")
    s.add_argument("--exposure", default=1.0, type=float)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_compare)

    s = sub.add_parser("bench", help="benchmarks: tracing (suite vs raw backend rays/s), core (per-stage ms of the "
                       "rendering core), or METHOD (the method's bench.py)")
    s.add_argument("what", help="tracing [--scene S|all] [--backend B|all] [--out DIR] [--json], core [--scene S] "
                   "[--backend B|all] [--resolution WxH], or a method with a bench.py "
                   "(its own options; METHOD --help lists them)")
    s.add_argument("rest", nargs=argparse.REMAINDER)
    s.set_defaults(func=cmd_bench)

    s = sub.add_parser("reproduce", help="run a preset matrix, then build the report")
    s.add_argument("--preset", default="quick", choices=registry_presets(),
                   help="a method preset (smoke, quick, full) or the shared cross-method matrix (compare, "
                        "compare-full: suite/harness/compare.toml)")
    s.add_argument("--methods", default=None, help="comma-separated subset of methods")
    s.add_argument("--matrix", default=None, help="the shared matrix file of compare / compare-full (default "
                   "suite/harness/compare.toml)")
    s.add_argument("--out", default="results", help="results root")
    s.add_argument("--report", default="report", help="report directory")
    s.add_argument("--executor", default="serial", choices=EXECUTORS)
    s.add_argument("--scheduler", default=None, help="Dask scheduler address tcp://host:port (implies dask)")
    s.add_argument("--workers", default=2, type=_int_arg("--workers"))
    s.add_argument("--force", action="store_true", help="recompute runs that are already complete")
    s.add_argument("--no-report", action="store_true", help="do not build the report (a later `splitbench "
                   "report` builds it from everything stored)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_reproduce)

    s = sub.add_parser("report", help="build the HTML report from stored results")
    s.add_argument("results", nargs="?", default="results")
    s.add_argument("--out", default="report")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_report)

    try:
        import netsim.cli as netsim_cli
    except ImportError:
        netsim_cli = None
    if netsim_cli is not None and hasattr(netsim_cli, "register"):
        netsim_cli.register(sub)
    return p


def registry_presets() -> tuple:
    from suite.harness.registry import PRESETS

    return PRESETS


def _int_arg(name: str):
    def parse(text):
        try:
            return int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, got '{text}'") from None
    return parse


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return UserError.exit_code
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
