"""One benchmark run: config → scene, tracer, method → simulated frames → quality → results store.

``make_config`` validates user input into a full run config (every bad value is a UserError naming it) and
``execute`` runs it, or skips it when its results are already complete. The core is reached through the small
module-level hooks below (``load_scene``, ``make_tracer``, ``make_link``, ``reference_image``,
``compare_images``) so that the harness tests can run on synthetic scenes without the renderer.
"""
from __future__ import annotations

import hashlib
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.harness import registry, results
from suite.errors import UserError
from suite.harness.method import Clock, Context, Method
from suite.progress import progress
from suite.harness.timeline import IdealLink, Timeline, run_async, run_sync

DEFAULT_RESULTS_DIR = "results"
METRICS = ("ssim", "dssim", "psnr_db", "nrmse", "flip")
# Metrics of an image against itself.
IDENTICAL = {"ssim": 1.0, "dssim": 0.0, "psnr_db": math.inf, "nrmse": 0.0, "flip": 0.0}
RUN_DEFAULTS = {
    "scene": "cornell", "backend": "embree", "resolution": [160, 90], "frames": 3, "net": "ideal",
    "protocol": "tcp", "variant": "default", "seed": 0, "clock": "measured", "work_ns_per_ray": 50.0,
    "work_ns_per_pixel": 20.0, "quality_every": 0, "reference_spp": 32, "reference_max_depth": 8,
    "exposure": 1.0, "message_timeout_ms": 100.0,
}
# With quality_every = 0, at most this many frames per run are compared against the references.
AUTO_QUALITY_FRAMES = 16
# At most this many frames per run are saved as EXR + PNG.
SAVED_FRAMES = 3


# ------------------------------------------------------------------------------------------------------ hooks

def load_scene(spec):
    from suite.core.scene import load

    return load(spec)


def scene_names() -> list[str]:
    from suite.core.scene import list_scenes

    return list(list_scenes())


def make_tracer(backend: str, scene):
    from suite.core.trace import make

    return make(backend, scene)


def backend_names() -> list[str]:
    from suite.core.trace import list_backends

    return list(list_backends())


def _netsim():
    try:
        import netsim
    except ImportError:
        return None
    return netsim if hasattr(netsim, "make_network") else None


_INLINE = re.compile(r"^\s*bw=([0-9.]+)\s*mbps\s*,\s*delay=([0-9.]+)\s*ms\s*$", re.IGNORECASE)


def make_link(net: str, direction: str, seed: int):
    """A link for one direction: netsim when installed, else the ideal-link fallback (delay + size/bandwidth)."""
    ns = _netsim()
    if ns is not None:
        # One netsim instance per direction, each its own FIFO; distinct seeds keep their loss streams apart.
        return ns.make_network(net, seed=int(seed) * 2 + (0 if direction == "down" else 1))
    if net == "ideal":
        return IdealLink()
    m = _INLINE.match(net)
    if m:
        return IdealLink(bandwidth_mbps=float(m.group(1)), delay_ms=float(m.group(2)))
    raise UserError(f"unknown network profile '{net}' (netsim is not installed: use 'ideal' or "
                    f"'bw=<N>mbps,delay=<D>ms')")


def net_profiles() -> dict[str, str]:
    ns = _netsim()
    if ns is not None:
        return dict(ns.list_profiles())
    return {"ideal": "zero delay, infinite bandwidth, no loss (fallback link; netsim not installed)"}


def reference_image(scene, t_s: float, resolution, spp: int, max_depth: int) -> np.ndarray:
    from suite.core.reference import path_reference

    return path_reference(scene, t_s, resolution=tuple(resolution), spp=spp, max_depth=max_depth)


def compare_images(ref, test, exposure: float) -> dict:
    from suite.core.metrics import compare

    return compare(ref, test, exposure=exposure)


def write_exr(path, img) -> None:
    from suite.core.imageio import write_exr as _write

    _write(path, img)


def write_png(path, img, exposure: float) -> None:
    from suite.core.imageio import write_png as _write

    _write(path, img, exposure=exposure)


# ----------------------------------------------------------------------------------------------------- config

def parse_resolution(value) -> list[int]:
    if isinstance(value, (list, tuple)) and len(value) == 2:
        w, h = value
    else:
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(value))
        if not m:
            raise UserError(f"malformed resolution '{value}' (expected WxH, e.g. 160x90)")
        w, h = m.groups()
    w, h = int(w), int(h)
    if w < 1 or h < 1 or w > 16384 or h > 16384:
        raise UserError(f"resolution {w}x{h} is out of range (each side 1..16384)")
    return [w, h]


def _scene_identity(scene: str) -> str:
    """A scene file is identified by its content too, so an edited file makes a new run."""
    if os.path.isfile(scene):
        return hashlib.sha256(Path(scene).read_bytes()).hexdigest()[:16]
    return ""


def make_config(method: str, *, scene=None, backend=None, resolution=None, frames=None, net=None, protocol=None,
                variant=None, set_values: dict | None = None, seed=None, **options) -> dict:
    """Validates user input into a full run config (a plain dict, JSON-able, the run's identity)."""
    spec = registry.get(method)
    cfg = dict(RUN_DEFAULTS)
    given = {"scene": scene, "backend": backend, "resolution": resolution, "frames": frames, "net": net,
             "protocol": protocol, "variant": variant, "seed": seed, **options}
    unknown = set(given) - set(RUN_DEFAULTS)
    if unknown:
        raise UserError(f"unknown run option '{sorted(unknown)[0]}'")
    cfg.update({k: v for k, v in given.items() if v is not None})
    set_values = dict(set_values or {})
    if "variant" in set_values:  # --set variant=paper picks the paper settings / a named variant
        cfg["variant"] = str(set_values.pop("variant"))
    cfg["method"] = spec.name
    cfg["params"] = spec.params(cfg["variant"], set_values)
    cfg["resolution"] = parse_resolution(cfg["resolution"])
    try:
        cfg["frames"] = int(cfg["frames"])
    except (TypeError, ValueError):
        raise UserError(f"malformed frame count '{cfg['frames']}'") from None
    if cfg["frames"] < 1:
        raise UserError(f"frame count must be >= 1, got {cfg['frames']}")
    if cfg["protocol"] not in ("tcp", "udp"):
        raise UserError(f"unknown protocol '{cfg['protocol']}' (choose tcp or udp)")
    if cfg["clock"] not in ("measured", "work"):
        raise UserError(f"unknown clock '{cfg['clock']}' (choose measured or work)")
    try:
        cfg["seed"] = int(cfg["seed"])
    except (TypeError, ValueError):
        raise UserError(f"malformed seed '{cfg['seed']}'") from None
    if int(cfg["reference_spp"]) < 0:
        raise UserError(f"reference spp must be >= 0, got {cfg['reference_spp']}")
    cfg["scene"] = str(cfg["scene"])
    if not os.path.isfile(cfg["scene"]):
        names = scene_names()
        if cfg["scene"] not in names:
            raise UserError(f"unknown scene '{cfg['scene']}' (choose from {', '.join(names)}, "
                            f"or give a path to a Mitsuba XML file)")
    else:
        cfg["scene"] = os.path.abspath(cfg["scene"])
    cfg["scene_digest"] = _scene_identity(cfg["scene"])
    backends = backend_names()
    if cfg["backend"] not in backends:
        raise UserError(f"unknown backend '{cfg['backend']}' (choose from {', '.join(backends)})")
    make_link(cfg["net"], "down", 0)  # raises UserError for an unknown profile or malformed spec
    return cfg


# ------------------------------------------------------------------------------------------------ simulation

@dataclass
class Sequence:
    """One frame sequence of a method: per-frame rows, images, and the timeline behind them."""

    rows: list = field(default_factory=list)
    images: dict = field(default_factory=dict)  # frame index → image, for the kept frames
    update_rows: list = field(default_factory=list)
    timeline: Timeline | None = None


def _image_digest(img: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(img, dtype=np.float32).tobytes()).hexdigest()[:16]


def _check_image(img, method: Method, index: int, resolution) -> np.ndarray:
    w, h = resolution
    img = np.asarray(img)
    if img.shape != (h, w, 3):
        raise UserError(f"method '{method.name}' returned an image of shape {img.shape} for frame {index}, "
                        f"expected {(h, w, 3)}")
    img = np.ascontiguousarray(img, dtype=np.float32)
    if not np.isfinite(img).all():
        raise UserError(f"method '{method.name}' returned a non-finite image for frame {index}")
    return img


def _group_columns(group, prefix_stage: str = "stage_") -> dict:
    cols = {}
    for ev in group.events.values():
        if ev.kind == "message":
            cols[f"net_{ev.name}_ms"] = 1e3 * ev.duration_s
        else:
            cols[f"{prefix_stage}{ev.name}_ms"] = 1e3 * ev.duration_s
    return cols


def simulate(method: Method, scene, tracer, cfg: dict, zero_latency: bool, keep: set,
             desc: str | None = None) -> Sequence:
    """Runs one frame sequence for real on the simulated clock. ``keep``: frame indices whose images to keep."""
    net = "ideal" if zero_latency else cfg["net"]
    links = {d: (IdealLink() if zero_latency else make_link(net, d, cfg["seed"])) for d in ("down", "up")}
    timeline = Timeline(links, message_timeout_s=cfg["message_timeout_ms"] / 1e3)
    clock = Clock(cfg["clock"], cfg["work_ns_per_ray"], cfg["work_ns_per_pixel"])
    params = cfg["params"]
    fps = float(params.get("client_fps") or scene.camera.fps)
    period_s = 1.0 / fps
    t0_s = scene.camera.frame_time_s(0)
    n = cfg["frames"]
    seq = Sequence(timeline=timeline)
    bar = progress(total=n, desc=desc, unit="frame")
    method.reset()
    state = {"prev_frame_t": None, "prev_update_t": None, "used": None}
    frame_info: dict[int, dict] = {}

    def context(group, t_s, prev_t_s, **extra) -> Context:
        if hasattr(tracer, "update"):
            tracer.update(t_s)
        return Context(group, scene=scene, tracer=tracer, t_s=t_s, prev_t_s=prev_t_s, resolution=cfg["resolution"],
                       seed=cfg["seed"], params=params, zero_latency=zero_latency, protocol=cfg["protocol"],
                       clock=clock, **extra)

    def finish(index, img):
        img = _check_image(img, method, index, cfg["resolution"])
        # Method-specific per-frame facts (e.g. codec bytes, repaired rows) become `info_<key>` columns.
        frame_info[index] = _scalar_info(getattr(method, "frame_info", None))
        if index in keep:
            seq.images[index] = img
        bar.update(1)
        return _image_digest(img)

    def sync_frame(group):
        i = group.index
        t_s = t0_s + i * period_s
        ctx = context(group, t_s, state["prev_frame_t"])
        state["prev_frame_t"] = t_s
        return finish(i, method.frame(ctx))

    def async_update(group, input_s):
        t_s = t0_s + input_s
        ctx = context(group, t_s, state["prev_update_t"])
        state["prev_update_t"] = t_s
        return method.server_update(ctx)

    def async_frame(group, used):
        i = group.index
        t_s = t0_s + i * period_s
        is_new = used is not None and used.index != state["used"]
        state["used"] = used.index if used is not None else None
        ctx = context(group, t_s, state["prev_frame_t"], update_index=used.index if used else -1,
                      update_t_s=(t0_s + used.input_s) if used else None, update_is_new=is_new)
        state["prev_frame_t"] = t_s
        return finish(i, method.client_frame(ctx, used.value if used else None))

    try:
        if method.mode == "sync":
            frames = run_sync(timeline, n, period_s, sync_frame)
            updates = []
        else:
            update_fps = float(params.get("update_fps") or 0.0)
            frames, updates = run_async(timeline, n, period_s, async_update, async_frame,
                                        max_in_flight=int(params.get("max_in_flight") or 1),
                                        update_period_s=1.0 / update_fps if update_fps > 0 else 0.0,
                                        lockstep=zero_latency)
    finally:
        bar.close()

    for u in updates:
        row = {"update": u.index, "start_s": u.start_s, "input_s": u.input_s, "arrival_s": u.arrival_s,
               "update_ms": u.update_ms, "critical_path": ">".join(u.group.critical_path())}
        row.update(u.group.summary())
        row.update(_group_columns(u.group))
        seq.update_rows.append(row)

    prev_start_s = -math.inf
    for f in frames:
        g = f.group
        row = {"frame": f.index, "t_s": t0_s + f.index * period_s, "start_s": f.start_s, "display_s": f.display_s,
               "frame_ms": f.frame_ms, "latency_ms": f.latency_ms, "frame_interval_ms": f.frame_interval_ms,
               "staleness_ms": f.staleness_ms, "update_index": f.update_index}
        row.update(g.summary())
        row.update(_group_columns(g))
        row["critical_path"] = ">".join(g.critical_path())
        for name, ms in g.critical_path_ms().items():
            is_message = name in g.events and g.events[name].kind == "message"
            row[f"cp_{'net_' if is_message else ''}{name}_ms"] = ms
        if updates:
            # Async accounting: the server work of the update on screen, and the bytes of the updates that
            # arrived since the previous frame started (so the per-frame bytes sum to the delivered total).
            if f.update_index >= 0:
                used = updates[f.update_index]
                row["server_ms"] = used.group.summary()["server_ms"]
                row.update(_group_columns(used.group))
            for u in updates:
                if prev_start_s < u.arrival_s <= f.start_s + 1e-9:
                    s = u.group.summary()
                    for key in ("bytes_down", "bytes_up", "lost_bytes", "retransmissions", "messages", "rays"):
                        row[key] += s[key]
        row["image_sha256"] = f.value
        row.update({f"info_{k}": v for k, v in frame_info.get(f.index, {}).items()})
        prev_start_s = f.start_s
        seq.rows.append(row)
    return seq


def _scalar_info(info) -> dict:
    """A method's ``frame_info`` dict with values made parquet-friendly scalars (lists are joined)."""
    if not isinstance(info, dict):
        return {}
    out = {}
    for key, value in info.items():
        if isinstance(value, (list, tuple)):
            value = "; ".join(str(v) for v in value)
        elif isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, (bool, int, float, str)) or value is None:
            out[str(key)] = value
    return out


def quality_frames(n_frames: int, quality_every: int) -> list[int]:
    if quality_every < 0:
        return []
    k = quality_every or max(1, math.ceil(n_frames / AUTO_QUALITY_FRAMES))
    return list(range(0, n_frames, k))


def saved_frames(candidates: list[int]) -> list[int]:
    if len(candidates) <= SAVED_FRAMES:
        return list(candidates)
    return sorted({candidates[0], candidates[len(candidates) // 2], candidates[-1]})


# ------------------------------------------------------------------------------------------------------- run

SUMMARY_COLUMNS = ("frame_ms", "latency_ms", "frame_interval_ms", "staleness_ms", "client_ms", "server_ms",
                   "network_ms", "bytes_down", "bytes_up", "rays", "pixels", *METRICS,
                   *(f"zl_{m}" for m in METRICS))


def run_location(cfg: dict, results_root) -> tuple[Path, str, dict]:
    env = results.environment()
    key = results.run_key(cfg, env)
    return Path(results_root) / results.run_dir_name(cfg, key), key, env


def execute(cfg: dict, results_root=DEFAULT_RESULTS_DIR, force: bool = False) -> dict:
    """Runs one validated config (from :func:`make_config`) into the results store.

    Returns ``{"run_dir", "skipped", "summary"}``; a complete run with the same key is skipped.
    """
    import pandas as pd

    run_dir, key, env = run_location(cfg, results_root)
    if results.is_complete(run_dir) and not force:
        return {"run_dir": str(run_dir), "skipped": True, "summary": results.load_run(run_dir)["summary"]}

    spec = registry.get(cfg["method"])
    cls = spec.load()
    scene = load_scene(cfg["scene"])
    tracer = make_tracer(cfg["backend"], scene)
    method = cls(cfg["params"])

    t = time.perf_counter()
    method.prepare(scene, tracer)
    prepare_ms = 1e3 * (time.perf_counter() - t)

    q_frames = quality_frames(cfg["frames"], int(cfg["quality_every"]))
    keep_frames = saved_frames(q_frames or list(range(cfg["frames"])))
    keep = set(q_frames) | set(keep_frames)
    main = simulate(method, scene, tracer, cfg, zero_latency=cfg["net"] == "ideal", keep=keep,
                    desc=f"{method.name} {cfg['net']}")
    # The zero-latency run is the reference for the error that distribution adds; a method without messages
    # or a run on the ideal network would reproduce its own images, so it is skipped then.
    needs_zl = method.uses_network and cfg["net"] != "ideal"
    zl = zero_latency_images(method, scene, tracer, cfg, q_frames, Path(results_root), env) \
        if needs_zl and q_frames else None

    frames = pd.DataFrame(main.rows)
    for m in METRICS:
        frames[m] = np.nan
        frames[f"zl_{m}"] = np.nan
    references = {}
    spp = int(cfg["reference_spp"])
    for i in progress(q_frames, desc="quality", unit="frame"):
        test = main.images[i]
        if spp > 0:
            ref = reference_image(scene, float(frames.at[i, "t_s"]), cfg["resolution"], spp,
                                  int(cfg["reference_max_depth"]))
            references[i] = ref
            for m, v in compare_images(ref, test, cfg["exposure"]).items():
                if m in METRICS:
                    frames.at[i, m] = float(v)
        if zl is None:
            # This run is its own zero-latency run (ideal network, or a method without messages).
            for m, v in IDENTICAL.items():
                frames.at[i, f"zl_{m}"] = v
            continue
        for m, v in compare_images(zl[i], test, cfg["exposure"]).items():
            if m in METRICS:
                frames.at[i, f"zl_{m}"] = float(v)

    timeline = main.timeline
    msgs = [e for e in timeline.events if e.kind == "message"]
    duration_s = max(frames["display_s"].max() - frames["start_s"].min(), 1e-12)
    bytes_down = sum(e.size_bytes for e in msgs if e.place == "down")
    bytes_up = sum(e.size_bytes for e in msgs if e.place == "up")
    summary = {
        "schema_version": results.SCHEMA_VERSION, "run_key": key, "method": cfg["method"],
        "variant": cfg["variant"], "mode": cls.mode, "scene": cfg["scene"], "net": cfg["net"],
        "protocol": cfg["protocol"], "resolution": cfg["resolution"], "frames": cfg["frames"],
        "prepare_ms": prepare_ms, "simulated_s": duration_s, "fps": cfg["frames"] / duration_s,
        "bytes_down": bytes_down, "bytes_up": bytes_up,
        "bandwidth_mbps": 8e-6 * (bytes_down + bytes_up) / duration_s,
        "bandwidth_down_mbps": 8e-6 * bytes_down / duration_s, "bandwidth_up_mbps": 8e-6 * bytes_up / duration_s,
        "lost_bytes": sum(e.lost_bytes for e in msgs), "incomplete_messages": sum(not e.complete for e in msgs),
        "reordered_sends": timeline.reordered_sends, "updates": len(main.update_rows),
        "rays": int(frames["rays"].sum()), "quality_frames": q_frames, "saved_frames": keep_frames,
        "zero_latency_run": zl is not None,
        "stats": results.summarize_frames(frames, SUMMARY_COLUMNS),
    }
    config_doc = {"schema_version": results.SCHEMA_VERSION, "run_key": key, "config": cfg,
                  "method_str": str(method), "method_mode": cls.mode, "seed": cfg["seed"],
                  "backend": {"name": cfg["backend"], **_describe(tracer)}, "network": _describe_net(cfg),
                  **env}

    with results.RunWriter(Path(results_root), run_dir.name) as w:
        w.write_json("config.json", config_doc)
        w.write_table("frames.parquet", frames)
        if main.update_rows:
            w.write_table("updates.parquet", pd.DataFrame(main.update_rows))
        w.write_table("events.parquet", pd.DataFrame([_event_row(e) for e in timeline.events]))
        for i in keep_frames:
            write_exr(w.path(f"images/frame_{i:04d}.exr"), main.images[i])
            write_png(w.path(f"images/frame_{i:04d}.png"), main.images[i], cfg["exposure"])
            if i in references:
                write_png(w.path(f"images/reference_{i:04d}.png"), references[i], cfg["exposure"])
        final = w.commit(summary)
    return {"run_dir": str(final), "skipped": False, "summary": summary}


ZERO_LATENCY_DIR = ".zero-latency"


def zero_latency_images(method, scene, tracer, cfg: dict, q_frames: list, results_root: Path, env: dict) -> dict:
    """The zero-latency run's images of the quality frames, shared by runs that differ only in the network.

    Without a network, net and protocol cannot change the images, so the sequence is computed once per
    (method, params, scene, backend, resolution, frames, seed, clock) and cached as .npy under
    ``<results>/.zero-latency/<key>/`` (exact float32; each file written atomically).
    """
    zl_cfg = {k: v for k, v in cfg.items() if k not in ("net", "protocol", "message_timeout_ms")}
    folder = results_root / ZERO_LATENCY_DIR / results.run_key(zl_cfg, env)[:32]
    files = {i: folder / f"frame_{i:04d}.npy" for i in q_frames}
    if all(f.is_file() for f in files.values()):
        return {i: np.load(f) for i, f in files.items()}
    zl_cfg = dict(cfg, protocol="tcp")
    seq = simulate(method, scene, tracer, zl_cfg, zero_latency=True, keep=set(q_frames),
                   desc=f"{method.name} zero-latency")
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in files.items():
        tmp = f.with_name(f".{f.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, seq.images[i])
        os.replace(tmp, f)
    return seq.images


def _event_row(e) -> dict:
    return {"loop": e.loop, "index": e.index, "name": e.name, "kind": e.kind, "place": e.place,
            "ready_s": e.ready_s, "start_s": e.start_s, "end_s": e.end_s, "binding": e.binding, "rays": e.rays,
            "pixels": e.pixels, "size_bytes": e.size_bytes, "delivered_bytes": e.delivered_bytes,
            "lost_bytes": e.lost_bytes, "retransmissions": e.retransmissions, "complete": e.complete,
            "protocol": e.protocol, "wall_ms": e.wall_ms}


def _describe(tracer) -> dict:
    describe = getattr(tracer, "describe", None)
    try:
        return dict(describe()) if callable(describe) else {}
    except Exception as exc:  # noqa: BLE001 - a description is informative only
        return {"describe_error": str(exc)}


def _describe_net(cfg: dict):
    link = make_link(cfg["net"], "down", cfg["seed"])
    describe = getattr(link, "describe", None)
    return describe() if callable(describe) else cfg["net"]
