"""One benchmark run: config → scene, tracer, method → simulated frames → quality → results store.

``make_config`` validates user input into a full run config (every bad value is a UserError naming it) and
``execute`` runs it, or skips it when its results are already complete. The core is reached through the small
module-level hooks below (``load_scene``, ``make_tracer``, ``make_network``, ``reference_image``,
``compare_images``) so that the harness tests can run on synthetic scenes without the renderer.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite import fileio
from suite.core import scene as scene_mod
from suite.errors import UserError
from suite.harness import registry, results
from suite.harness.clients import client_camera
from suite.harness.method import (ClientCamera, Clock, Context, Method, ServerCamera, SimulationError, Update,  # noqa: F401
                                  delivered, running_on, scene_view)
from suite.harness.timeline import WORK_KINDS, Timeline, run_async, run_sync
from suite.progress import progress

DEFAULT_RESULTS_DIR = "results"
METRICS = ("ssim", "dssim", "psnr_db", "nrmse", "flip", "rel_mse")
# Metrics of an image against itself.
IDENTICAL = {"ssim": 1.0, "dssim": 0.0, "psnr_db": math.inf, "nrmse": 0.0, "flip": 0.0, "rel_mse": 0.0}
# Column prefixes of the quality metrics (docs/results.md): "" against the full-GI (path) reference, "direct_"
# against the direct-lighting reference, "floor_" / "direct_floor_" the noise floor of those references (the
# metric between two independent renders of the pose), "zl_" against the method's own zero-latency run.
QUALITY_PREFIXES = ("", "direct_", "floor_", "direct_floor_", "zl_")
RUN_DEFAULTS = {
    "scene": "cornell", "backend": "embree", "resolution": [160, 90], "frames": 3, "net": "ideal",
    "protocol": "tcp", "variant": "default", "seed": 0, "clock": "measured", "work_ns_per_ray": 50.0,
    "work_ns_per_pixel": 20.0, "quality_every": 0, "reference_spp": 32, "reference_max_depth": 8,
    "exposure": 1.0, "message_timeout_ms": 100.0, "clients": 1, "server_net": None, "quality_clients": 1,
    "work_ns_per_tap": 2.0, "work_ns_per_point": 50.0, "work_ns_per_codec_byte": 5.0,
    "reference_direct": True, "reference_floor": True,
}
# Settings that cannot change what a method computes offline: prepare() output is shared across them.
NOT_PREPARE_KEYS = ("net", "protocol", "clients", "server_net", "message_timeout_ms", "frames", "quality_every",
                    "quality_clients", "reference_spp", "reference_max_depth", "reference_direct", "reference_floor",
                    "exposure", "clock", "work_ns_per_ray", "work_ns_per_pixel", "work_ns_per_tap", "work_ns_per_point",
                    "work_ns_per_codec_byte")
MAX_CLIENTS = 256
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


def is_map_spec(spec: str) -> bool:
    """``oa:<map>`` (and ``oa:<map>@<pak>``): a map whose existence is checked when it is loaded."""
    from suite.core.scene.q3 import is_q3_spec

    return str(spec).lower().startswith("oa:") and is_q3_spec(spec)


def make_tracer(backend: str, scene):
    from suite.core.trace import make

    return make(backend, scene)


def backend_names() -> list[str]:
    from suite.core.trace import list_backends

    return list(list_backends())


def net_profiles() -> dict[str, str]:
    import netsim

    return dict(netsim.list_profiles())


def make_network(net: str, clients: int, server_net, seed: int):
    """The run's network: one access link per client (profile ``net``), all sharing the server's link
    (profile ``server_net``; None = no shared bottleneck). Bad specs are a UserError naming them."""
    import netsim

    try:
        return netsim.make_topology(access=net, server=server_net, clients=int(clients), seed=int(seed))
    except netsim.NetsimError as exc:
        raise UserError(str(exc)) from None


def reference_image(scene, t_s: float, resolution, spp: int, max_depth: int) -> np.ndarray:
    from suite.core.reference import path_reference

    return path_reference(scene, t_s, resolution=tuple(resolution), spp=spp, max_depth=max_depth)


def reference_set(scene, t_s: float, resolution, spp: int, transport: str, max_depth: int, exposure: float,
                  floor: bool):
    """One pose's reference for ``transport`` (``global`` | ``direct``) with ``.image``, ``.stderr`` and its noise
    floor ``.floor`` (a metrics dict, or None when ``floor`` is False)."""
    from suite.core.reference import reference_set as _reference_set

    return _reference_set(scene, t_s, tuple(resolution), spp, transport, max_depth, exposure=exposure, floor=floor)


def compare_images(ref, test, exposure: float, ref_stderr=None) -> dict:
    from suite.core.metrics import compare

    return compare(ref, test, exposure=exposure, ref_stderr=ref_stderr)


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
    """A scene is identified by the content of the files it loads from too (a scene file, an OpenArena map and
    its archives, an OBJ and its sidecar), so changed scene data makes a new run. Data that is missing gives ''
    here; the run itself then stops with the loader's error."""
    try:
        digest = scene_mod.source_digest(scene)
    except UserError:
        return ""
    return digest[:16]


def make_config(method: str, *, scene=None, backend=None, resolution=None, frames=None, net=None, protocol=None,
                variant=None, set_values: dict | None = None, seed=None, **options) -> dict:
    """Validates user input into a full run config (a plain dict, JSON-able, the run's identity)."""
    spec = registry.get(method)
    cfg = dict(RUN_DEFAULTS)
    if scene is None and spec.default_scene is not None:  # the method's own default: a scene it renders
        scene = spec.default_scene
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
        if cfg["scene"] not in names and not is_map_spec(cfg["scene"]):
            raise UserError(f"unknown scene '{cfg['scene']}' (choose from {', '.join(names)}, "
                            f"oa:<map> for an OpenArena map, or give a path to a Mitsuba XML, OBJ, BSP or PK3 file)")
    else:
        cfg["scene"] = os.path.abspath(cfg["scene"])
    cfg["scene_digest"] = _scene_identity(cfg["scene"])
    backends = backend_names()
    if cfg["backend"] not in backends:
        raise UserError(f"unknown backend '{cfg['backend']}' (choose from {', '.join(backends)})")
    try:
        cfg["clients"] = int(cfg["clients"])
    except (TypeError, ValueError):
        raise UserError(f"malformed client count '{cfg['clients']}'") from None
    if not 1 <= cfg["clients"] <= MAX_CLIENTS:
        raise UserError(f"client count must be 1..{MAX_CLIENTS}, got {cfg['clients']}")
    if cfg["server_net"] in ("", "none"):
        cfg["server_net"] = None
    try:
        cfg["quality_clients"] = int(cfg["quality_clients"])
    except (TypeError, ValueError):
        raise UserError(f"malformed quality_clients '{cfg['quality_clients']}'") from None
    if not math.isfinite(float(cfg["message_timeout_ms"])) or float(cfg["message_timeout_ms"]) <= 0:
        raise UserError(f"message_timeout_ms must be a finite time > 0, got {cfg['message_timeout_ms']}")
    # raises UserError for an unknown profile, a malformed spec or impossible settings
    make_network(cfg["net"], cfg["clients"], cfg["server_net"], 0)
    cfg["code_digest"] = results.code_digest(spec.name)
    return cfg


# ------------------------------------------------------------------------------------------------ simulation

@dataclass
class Sequence:
    """One frame sequence of a method: per-frame rows, images, and the timeline behind them."""

    rows: list = field(default_factory=list)
    images: dict = field(default_factory=dict)  # (client, frame index) → image, for the kept frames
    update_rows: list = field(default_factory=list)
    timeline: Timeline | None = None


def _image_digest(img: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(img, dtype=np.float32).tobytes()).hexdigest()[:16]


def _check_image(img, method: Method, index: int, resolution, client: int = 0) -> np.ndarray:
    w, h = resolution
    img = np.asarray(img)
    who = f"frame {index}" + (f" of client {client}" if client else "")
    if img.shape != (h, w, 3):
        raise UserError(f"method '{method.name}' returned an image of shape {img.shape} for {who}, "
                        f"expected {(h, w, 3)}")
    img = np.ascontiguousarray(img, dtype=np.float32)
    if not np.isfinite(img).all():
        raise UserError(f"method '{method.name}' returned a non-finite image for {who}")
    return img


def _group_columns(group, prefix_stage: str = "stage_") -> dict:
    cols = {}
    for ev in group.events.values():
        if ev.kind == "message":
            cols[f"net_{ev.name}_ms"] = 1e3 * ev.duration_s
        else:
            cols[f"{prefix_stage}{ev.name}_ms"] = 1e3 * ev.duration_s
    return cols


def _clock(cfg: dict) -> Clock:
    return Clock(cfg["clock"], cfg["work_ns_per_ray"], cfg["work_ns_per_pixel"], cfg["work_ns_per_tap"],
                 cfg["work_ns_per_point"], cfg["work_ns_per_codec_byte"])


def simulate(cls, scene, tracer, cfg: dict, zero_latency: bool, keep: set, prepared=None,
             desc: str | None = None, keep_clients=None) -> Sequence:
    """Runs one frame sequence of every client for real on the simulated clock.

    ``cls`` is the method class: the server gets one instance and every client its own, so that they share
    nothing but messages. ``keep``: frame indices whose images to keep (of the clients in ``keep_clients``,
    default all).
    """
    n_clients = int(cfg.get("clients", 1))
    keep_clients = set(range(n_clients)) if keep_clients is None else set(keep_clients)
    params = cfg["params"]
    if zero_latency:
        network = make_network("ideal", n_clients, None, cfg["seed"])
    else:
        network = make_network(cfg["net"], n_clients, cfg.get("server_net"), cfg["seed"])
    timeline = Timeline(network, message_timeout_s=cfg["message_timeout_ms"] / 1e3, clients=n_clients)
    clock = _clock(cfg)
    fps = float(params.get("client_fps") or scene.camera.fps)
    period_s = 1.0 / fps
    t0_s = scene.camera.frame_time_s(0)
    n = cfg["frames"]
    seq = Sequence(timeline=timeline)
    bar = progress(total=n * n_clients, desc=desc, unit="frame")

    server = cls(params)
    clients = [cls(params) for _ in range(n_clients)]
    for inst in [server, *clients]:
        inst.restore(prepared)
        inst.reset()
    paths = [client_camera(scene.camera, c, n_clients) for c in range(n_clients)]
    client_views = [scene_view(scene, ClientCamera(paths[c], c)) for c in range(n_clients)]
    server_views = [scene_view(scene, ServerCamera(paths[c], c)) for c in range(n_clients)]
    payloads: dict[int, bytes | None] = {}
    frame_info: dict[tuple, dict] = {}
    update_info: dict[tuple, dict] = {}
    prev_t = {}
    tracer_t = {"t": None}

    def set_scene_time(t_s):
        import greenlet

        greenlet.getcurrent().sb_t_s = t_s
        if hasattr(tracer, "update") and tracer_t["t"] != t_s:
            tracer.update(t_s)
            tracer_t["t"] = t_s

    # Loops interleave on the simulated clock; a resumed loop gets its scene time's geometry back (outside any
    # stage, so never timed).
    timeline.sched.on_resume = lambda g: set_scene_time(g.sb_t_s) if hasattr(g, "sb_t_s") else None

    def context(group, t_s, declared, **extra) -> Context:
        set_scene_time(t_s)
        c = group.client
        key = (group.loop, c)
        ctx = Context(group, scene=client_views[c], server_scene=server_views[c], tracer=tracer, t_s=t_s,
                      prev_t_s=prev_t.get(key), resolution=cfg["resolution"], seed=cfg["seed"], params=params,
                      zero_latency=zero_latency, protocol=cfg["protocol"], clock=clock, client=c,
                      clients=n_clients, outputs=declared, payloads=payloads, **extra)
        prev_t[key] = t_s
        return ctx

    def finish(ctx, img):
        c, i = ctx.client, ctx.index
        img = _check_image(img, cls, i, cfg["resolution"], c)
        frame_info[(c, i)] = _scalar_info(ctx.outputs)
        if i in keep and c in keep_clients:
            seq.images[(c, i)] = img
        bar.update(1)
        return _image_digest(img)

    def sync_frame(group):
        ctx = context(group, t0_s + group.index * period_s, cls.outputs)
        return finish(ctx, clients[group.client].frame(ctx))

    frame_ctx: dict[tuple, Context] = {}
    update_objects: dict[tuple, Update] = {}
    shown: dict[int, int] = {}

    def async_input(group):
        ctx = context(group, t0_s + group.index * period_s, cls.outputs)
        frame_ctx[(group.client, group.index)] = ctx
        clients[group.client].client_input(ctx)

    def async_update(group, inputs):
        _, frame_i, _ = inputs.newest
        ctx = context(group, t0_s + frame_i * period_s, cls.update_outputs,
                      inbox=[delivered(ev, payloads.get(ev.seq), fi, fs) for ev, fi, fs in inputs.messages])
        with running_on("server"):
            value = server.server_update(ctx)
        if value is not None:
            raise SimulationError(f"{cls.name}.server_update returned a value; what the client may use must "
                                  f"reach it as a message (ctx.send)")
        update_info[(group.client, group.index)] = _scalar_info(ctx.outputs)

    def async_frame(group, used):
        c = group.client
        ctx = frame_ctx.pop((c, group.index))
        update = None
        if used is not None:
            key = (c, used.index)
            if key not in update_objects:
                # The client gets the update as the bytes its messages delivered (losses zero-filled).
                msgs = {ev.name: delivered(ev, payloads.get(ev.seq)) for ev in used.group.events.values()
                        if ev.kind == "message" and ev.place == "down"}
                update_objects[key] = Update(used.index, t0_s + used.input_s, msgs)
            update = update_objects[key]
            update.is_new = shown.get(c) != used.index
            shown[c] = used.index
            ctx.update_index, ctx.update_t_s, ctx.update_is_new = used.index, update.input_t_s, update.is_new
        return finish(ctx, clients[c].client_frame(ctx, update))

    try:
        if cls.mode == "sync":
            frames = run_sync(timeline, n, period_s, sync_frame)
            updates = []
        else:
            update_fps = float(params.get("update_fps") or 0.0)
            frames, updates = run_async(timeline, n, period_s, async_update, async_frame, run_input=async_input,
                                        max_in_flight=int(params.get("max_in_flight") or 1),
                                        update_period_s=1.0 / update_fps if update_fps > 0 else 0.0,
                                        lockstep=zero_latency)
    finally:
        bar.close()

    for u in updates:
        row = {"client": u.client, "update": u.index, "start_s": u.start_s, "input_s": u.input_s,
               "input_frame": u.input_frame, "arrival_s": u.arrival_s, "update_ms": u.update_ms,
               "critical_path": ">".join(u.group.critical_path())}
        row.update(u.group.summary())
        row.update(_group_columns(u.group))
        row.update({f"info_{k}": v for k, v in update_info.get((u.client, u.index), {}).items()})
        seq.update_rows.append(row)

    by_client: dict[int, list] = {}
    for u in updates:
        by_client.setdefault(u.client, []).append(u)
    prev_start_s: dict[int, float] = {}
    for f in frames:
        g = f.group
        c = f.client
        row = {"client": c, "frame": f.index, "t_s": t0_s + f.index * period_s, "start_s": f.start_s,
               "display_s": f.display_s, "frame_ms": f.frame_ms, "latency_ms": f.latency_ms,
               "frame_interval_ms": f.frame_interval_ms, "staleness_ms": f.staleness_ms,
               "update_index": f.update_index}
        row.update(g.summary())
        row.update(_group_columns(g))
        display = g.display_event()
        row["critical_path"] = ">".join(g.critical_path(display))
        for name, ms in g.critical_path_ms(display).items():
            is_message = name in g.events and g.events[name].kind == "message"
            row[f"cp_{'net_' if is_message else ''}{name}_ms"] = ms
        if updates:
            # Async accounting: the server work of the update on screen, and the bytes of this client's updates
            # that arrived since its previous frame started (so the per-frame bytes sum to the delivered total).
            mine = by_client.get(c, [])
            if f.update_index >= 0:
                used = mine[f.update_index]
                row["server_ms"] = used.group.summary()["server_ms"]
                row.update(_group_columns(used.group))
            lo = prev_start_s.get(c, -math.inf)
            for u in mine:
                if lo < u.arrival_s <= f.start_s + 1e-9:
                    s = u.group.summary()
                    for key in ("bytes_down", "bytes_up", "lost_bytes", "retransmissions", "messages", "rays",
                                "work_taps", "work_points", "work_codec_bytes"):
                        row[key] += s[key]
        row["image_sha256"] = f.value
        row.update({f"info_{k}": v for k, v in frame_info.get((c, f.index), {}).items()})
        prev_start_s[c] = f.start_s
        seq.rows.append(row)
    return seq


def _scalar_info(info) -> dict:
    """Declared outputs made parquet-friendly scalars (lists are joined)."""
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
                   "network_ms", "bytes_down", "bytes_up", "rays", "pixels", "work_taps", "work_points",
                   "work_codec_bytes", *(f"{p}{m}" for p in QUALITY_PREFIXES for m in METRICS))


def run_location(cfg: dict, results_root) -> tuple[Path, str, dict]:
    env = results.environment()
    key = results.run_key(cfg, env)
    return Path(results_root) / results.run_dir_name(cfg, key), key, env


def prepared_data(cls, cfg: dict, scene, tracer, results_root: Path, env: dict) -> tuple:
    """The method's prepare() output, computed once per (method, params, scene, backend, resolution, seed, code)
    and shared by runs that differ only in network, protocol or client count.

    Cached as a pickle under ``<results>/.prepared/<key>.pkl``; returns (data, prepare_ms, reused, key). The
    prepare_ms of a reused result is the time the original computation took.
    """
    import pickle

    key = results.run_key({k: v for k, v in cfg.items() if k not in NOT_PREPARE_KEYS}, env)[:32]
    path = results_root / PREPARED_DIR / f"{key}.pkl"
    if path.is_file():
        with open(path, "rb") as fh:
            doc = pickle.load(fh)
        return doc["data"], doc["prepare_ms"], True, key
    method = cls(cfg["params"])
    # The server prepares offline; it has the scene but not the clients' camera paths.
    server_scene = scene_view(scene, ServerCamera(scene.camera, 0))
    t = time.perf_counter()
    data = method.prepare(server_scene, tracer)
    prepare_ms = 1e3 * (time.perf_counter() - t)
    path.parent.mkdir(parents=True, exist_ok=True)
    fileio.write_bytes(path, pickle.dumps({"data": data, "prepare_ms": prepare_ms}, protocol=pickle.HIGHEST_PROTOCOL))
    return data, prepare_ms, False, key


PREPARED_DIR = ".prepared"

# Frames of a rehearsal (:func:`rehearse`): two, so that the temporal stages (history, reprojection) run too.
REHEARSAL_FRAMES = 2
_REHEARSED: set = set()  # (process, method, parameters, scene, backend, resolution) rehearsed


def rehearse(cls, scene, tracer, cfg: dict, prepared) -> bool:
    """Runs the first :data:`REHEARSAL_FRAMES` frames of ``cfg`` once per process and (method, parameters, scene,
    backend, resolution), one client on the ideal network, keeping nothing (fresh method instances; rays are
    counted per stage, so the run's counters do not see it). A process's first frames otherwise hold one-time
    costs, imports, kernels compiled or loaded from numba's cache, thread pools, codec set-up, that a server or
    client running for longer would not pay per frame: without it, quake_drt on oa:aggressor at 160x90 took 3.8
    and 1.8 s for its first two frames against 62 ms after, and layered_pvs's first update on Dabrovic Sponza
    1.8 s against 0.4 s, holding back everything after it on the measured clock. Only with the measured clock (the
    work clock charges counted work only). Returns whether it ran."""
    if cfg["clock"] != "measured":
        return False
    key = (os.getpid(), cfg["method"], json.dumps(cfg["params"], sort_keys=True, default=str), cfg["scene"],
           cfg["backend"], tuple(cfg["resolution"]))
    if key in _REHEARSED:
        return False
    _REHEARSED.add(key)
    short = {**cfg, "frames": min(REHEARSAL_FRAMES, int(cfg["frames"])), "clients": 1, "net": "ideal",
             "server_net": None}
    simulate(cls, scene, tracer, short, zero_latency=True, keep=set(), prepared=prepared)
    return True


def execute(cfg: dict, results_root=DEFAULT_RESULTS_DIR, force: bool = False) -> dict:
    """Runs one validated config (from :func:`make_config`) into the results store.

    Returns ``{"run_dir", "skipped", "summary"}``; a complete run with the same key is skipped unless
    ``force``.
    """
    import pandas as pd

    run_dir, key, env = run_location(cfg, results_root)
    if results.is_complete(run_dir) and not force:
        return {"run_dir": str(run_dir), "skipped": True, "summary": results.load_run(run_dir)["summary"]}

    start_s = time.perf_counter()
    wall_s = {}
    spec = registry.get(cfg["method"])
    cls = spec.load()
    scene = load_scene(cfg["scene"])
    # What of the scene the method does not render: said now and stored with the run (or a UserError, before any
    # work, where the method would render none of the scene's light).
    facts = cls(cfg["params"])  # an instance for what the method declares; the runs make their own
    omitted = [str(x) for x in facts.omissions(scene)]
    for what in omitted:
        print(f"splitbench: warning: {cfg['method']} on {cfg['scene']}: {what}", file=sys.stderr)
    tracer = make_tracer(cfg["backend"], scene)
    n_clients = int(cfg.get("clients", 1))
    prepared, prepare_ms, prepare_reused, prepare_key = prepared_data(cls, cfg, scene, tracer, Path(results_root),
                                                                       env)

    q_frames = quality_frames(cfg["frames"], int(cfg["quality_every"]))
    q_clients = list(range(n_clients)) if int(cfg["quality_clients"]) < 0 else \
        list(range(min(n_clients, int(cfg["quality_clients"]))))
    keep_frames = saved_frames(q_frames or list(range(cfg["frames"])))
    keep = set(q_frames) | set(keep_frames)
    wall_s["setup"] = time.perf_counter() - start_s
    rehearse(cls, scene, tracer, cfg, prepared)
    wall_s["rehearsal"] = time.perf_counter() - start_s - sum(wall_s.values())
    main = simulate(cls, scene, tracer, cfg, zero_latency=cfg["net"] == "ideal" and not cfg.get("server_net"),
                    keep=keep, prepared=prepared, desc=f"{cls.name} {cfg['net']}",
                    keep_clients=set(q_clients) | {0})
    # The zero-latency run is the reference for the error that distribution adds; a method without messages
    # or a run on the ideal network would reproduce its own images, so it is skipped then.
    # A method may decide per parameters (a placement, a renderer): an instance attribute overrides the class's.
    wall_s["simulate"] = time.perf_counter() - start_s - sum(wall_s.values())
    needs_zl = facts.uses_network and (cfg["net"] != "ideal" or cfg.get("server_net"))
    zl = zero_latency_images(cls, scene, tracer, cfg, q_frames, q_clients, prepared, Path(results_root), env) \
        if needs_zl and q_frames and q_clients else None
    wall_s["zero_latency"] = time.perf_counter() - start_s - sum(wall_s.values())

    frames = pd.DataFrame(main.rows)
    for prefix in QUALITY_PREFIXES:
        for m in METRICS:
            frames[f"{prefix}{m}"] = np.nan
    row_of = {(int(c), int(i)): r for r, (c, i) in enumerate(zip(frames["client"], frames["frame"]))}
    references = {}
    spp = int(cfg["reference_spp"])
    transports = ("global", "direct") if cfg.get("reference_direct", True) else ("global",)
    for c, i in progress([(c, i) for c in q_clients for i in q_frames], desc="quality", unit="frame"):
        r = row_of[(c, i)]
        test = main.images[(c, i)]
        # The direct-lighting reference, like the noise floors, on at most SAVED_FRAMES poses (first, middle, last).
        for transport in (t for t in transports if t == "global" or i in keep_frames) if spp > 0 else ():
            # The reference sees the scene from this client's pose.
            ref = reference_set(scene_view(scene, client_camera(scene.camera, c, n_clients)),
                                float(frames.at[r, "t_s"]), cfg["resolution"], spp, transport,
                                int(cfg["reference_max_depth"]), cfg["exposure"],
                                # the noise floor on at most SAVED_FRAMES poses (first, middle, last): it costs a
                                # second render of each pose
                                bool(cfg.get("reference_floor", True)) and i in keep_frames)
            prefix = "" if transport == "global" else f"{transport}_"
            references[(transport, c, i)] = ref.image
            for m, v in compare_images(ref.image, test, cfg["exposure"], ref_stderr=ref.stderr).items():
                if m in METRICS:
                    frames.at[r, f"{prefix}{m}"] = float(v)
            for m, v in (ref.floor or {}).items():
                if m in METRICS:
                    frames.at[r, f"{prefix}floor_{m}"] = float(v)
        if zl is None:
            # This run is its own zero-latency run (ideal network, or a method without messages).
            for m, v in IDENTICAL.items():
                frames.at[r, f"zl_{m}"] = v
            continue
        for m, v in compare_images(zl[(c, i)], test, cfg["exposure"]).items():
            if m in METRICS:
                frames.at[r, f"zl_{m}"] = float(v)

    wall_s["quality"] = time.perf_counter() - start_s - sum(wall_s.values())
    timeline = main.timeline
    msgs = [e for e in timeline.events if e.kind == "message"]
    duration_s = max(frames["display_s"].max() - frames["start_s"].min(), 1e-12)
    bytes_down = sum(e.size_bytes for e in msgs if e.place == "down")
    bytes_up = sum(e.size_bytes for e in msgs if e.place == "up")
    summary = {
        "schema_version": results.SCHEMA_VERSION, "run_key": key, "method": cfg["method"],
        "variant": cfg["variant"], "mode": cls.mode, "light_transport": getattr(facts, "light_transport", "direct"),
        "scene": cfg["scene"], "net": cfg["net"],
        "server_net": cfg.get("server_net"), "clients": n_clients,
        "protocol": cfg["protocol"], "resolution": cfg["resolution"], "frames": cfg["frames"],
        "prepare_ms": prepare_ms, "prepare_reused": prepare_reused, "prepare_key": prepare_key,
        "simulated_s": duration_s, "fps": cfg["frames"] / duration_s,
        "bytes_down": bytes_down, "bytes_up": bytes_up,
        "bytes_down_per_client": bytes_down / n_clients, "bytes_up_per_client": bytes_up / n_clients,
        "bandwidth_mbps": 8e-6 * (bytes_down + bytes_up) / duration_s,
        "bandwidth_down_mbps": 8e-6 * bytes_down / duration_s, "bandwidth_up_mbps": 8e-6 * bytes_up / duration_s,
        "lost_bytes": sum(e.lost_bytes for e in msgs), "incomplete_messages": sum(not e.complete for e in msgs),
        "reordered_sends": timeline.reordered_sends, "updates": len(main.update_rows),
        "rays": int(frames["rays"].sum()), "quality_frames": q_frames, "quality_clients": q_clients,
        "saved_frames": keep_frames, "zero_latency_run": zl is not None, "omitted": omitted,
        "stats": results.summarize_frames(frames, SUMMARY_COLUMNS),
        # Host wall time of this run by phase (set-up incl. prepare, simulation, the zero-latency run, references
        # and metrics): what a sweep's budget is made of; measured, so it differs between reruns.
        "run_wall_s": {**{k: round(v, 3) for k, v in wall_s.items()},
                       "total": round(time.perf_counter() - start_s, 3)},
    }
    if main.update_rows:
        ups = pd.DataFrame(main.update_rows)
        summary["server_ms_per_update"] = float(ups["server_ms"].mean())
    config_doc = {"schema_version": results.SCHEMA_VERSION, "run_key": key, "config": cfg,
                  "method_str": str(cls(cfg["params"])), "method_mode": cls.mode, "seed": cfg["seed"],
                  "backend": {"name": cfg["backend"], **_describe(tracer)}, "network": _describe_net(cfg),
                  **env}

    with results.RunWriter(Path(results_root), run_dir.name) as w:
        w.write_json("config.json", config_doc)
        w.write_table("frames.parquet", frames)
        if main.update_rows:
            w.write_table("updates.parquet", pd.DataFrame(main.update_rows))
        w.write_table("events.parquet", pd.DataFrame([_event_row(e) for e in timeline.events]))
        for c in sorted({0, *q_clients}):
            tag = "" if c == 0 else f"client{c}_"
            for i in keep_frames:
                if (c, i) not in main.images:
                    continue
                write_exr(w.path(f"images/{tag}frame_{i:04d}.exr"), main.images[(c, i)])
                write_png(w.path(f"images/{tag}frame_{i:04d}.png"), main.images[(c, i)], cfg["exposure"])
                # The report's image columns: the references of both light transports and the zero-latency run.
                for transport, name in (("global", "reference"), ("direct", "direct_reference")):
                    if (transport, c, i) in references:
                        write_png(w.path(f"images/{tag}{name}_{i:04d}.png"), references[(transport, c, i)],
                                  cfg["exposure"])
                if zl is not None and (c, i) in zl:
                    write_png(w.path(f"images/{tag}zero_latency_{i:04d}.png"), zl[(c, i)], cfg["exposure"])
        final = w.commit(summary)
    return {"run_dir": str(final), "skipped": False, "summary": summary}


ZERO_LATENCY_DIR = ".zero-latency"


def zero_latency_images(cls, scene, tracer, cfg: dict, q_frames: list, q_clients: list, prepared,
                        results_root: Path, env: dict) -> dict:
    """The zero-latency run's images of the quality frames, shared by runs that differ only in the network.

    Without a network, net, protocol and the server's link cannot change the images, so the sequence is
    computed once per (method, params, scene, backend, resolution, frames, clients, seed, clock) and cached as
    .npy under ``<results>/.zero-latency/<key>/`` (exact float32; each file written atomically).
    """
    zl_cfg = {k: v for k, v in cfg.items() if k not in ("net", "protocol", "message_timeout_ms", "server_net",
                                                        "quality_clients")}
    folder = results_root / ZERO_LATENCY_DIR / results.run_key(zl_cfg, env)[:32]
    files = {(c, i): folder / (f"frame_{i:04d}.npy" if c == 0 else f"client{c}_frame_{i:04d}.npy")
             for c in q_clients for i in q_frames}
    if all(f.is_file() for f in files.values()):
        return {k: np.load(f) for k, f in files.items()}
    zl_cfg = dict(cfg, protocol="tcp")
    seq = simulate(cls, scene, tracer, zl_cfg, zero_latency=True, keep=set(q_frames), prepared=prepared,
                   desc=f"{cls.name} zero-latency", keep_clients=set(q_clients))
    folder.mkdir(parents=True, exist_ok=True)
    for k, f in files.items():
        buf = io.BytesIO()
        np.save(buf, seq.images[k])
        fileio.write_bytes(f, buf.getvalue())
    return seq.images


def _event_row(e) -> dict:
    return {"client": e.client, "loop": e.loop, "index": e.index, "name": e.name, "kind": e.kind, "place": e.place,
            "ready_s": e.ready_s, "start_s": e.start_s, "end_s": e.end_s, "binding": e.binding, "rays": e.rays,
            "pixels": e.pixels, "size_bytes": e.size_bytes, "delivered_bytes": e.delivered_bytes,
            "lost_bytes": e.lost_bytes, "retransmissions": e.retransmissions, "complete": e.complete,
            "protocol": e.protocol, "wall_ms": e.wall_ms,
            **{f"work_{k}": e.work.get(k, 0) for k in WORK_KINDS[1:]}}


def _describe(tracer) -> dict:
    describe = getattr(tracer, "describe", None)
    try:
        return dict(describe()) if callable(describe) else {}
    except Exception as exc:  # noqa: BLE001 - a description is informative only
        return {"describe_error": str(exc)}


def _describe_net(cfg: dict):
    return make_network(cfg["net"], cfg.get("clients", 1), cfg.get("server_net"), cfg["seed"]).describe()
