"""``splitbench bench layered_pvs``: server stages against the backend's raw ray rate, codec throughput, client
reprojection cost, how they grow with pixels and layers, and the report's images (layers, packed texture, client
frame, difference). Stores ``<results>/bench/layered_pvs.json`` and PNGs in ``<results>/bench/layered_pvs/``.

``<stage>_ratio`` is the time the backend alone takes for the stage's own rays over the stage's time (1 = the stage
is pure tracing; below it, the share of shading, sampling and bookkeeping), and ``<stage>_ratio_range`` the lowest
and highest such ratio of one update and the replay timed right after it (how far this machine's noise moves one
measurement). The rays are recorded in one update
(:class:`RecordingTracer`, outside every timed run); the stages are then timed in ``--repeats`` further updates with
the plain tracer (the same rays: the update is deterministic), interleaved with the replay of each stage's rays on
the backend's raw entry points (``raw_intersect`` / ``raw_occluded`` on rays already in its frame and layout, each
call timed on fresh copies made just before it, so its rays are in the cache as the stage's are; a backend without
them replays through the suite's queries, and the row says so); medians of the repeats. On a Dr.Jit backend
"raw" is the backend on rays in device memory: the PVS views, the depth peeling and the path tracer's bounces run
as device kernels there and are recorded on the device, the other queries (uploaded once, outside the timed calls)
join them, and every stage replays on ``ray_intersect_preliminary`` / ``ray_test`` of Dr.Jit arrays.

One update is made outside the harness with :class:`LocalContext` (stages timed with ``perf_counter``).

``svgf_host_ms`` and ``svgf_<device>_ms``: the layered SVGF (§4.4.1) on the recorded update's own inputs, the numba
kernel and the Dr.Jit kernel (methods/layered_pvs/device.py, copies included) on each Dr.Jit backend that works here
(``--device``), medians of the row's repeats. ``pack_host_ms`` and ``pack_<device>_ms`` likewise for the pack stage
(relocation, packing, colour filling: ``packing.pack_stage``), the numba passes against the Dr.Jit kernels.

``server_on_devices``: the server rows again, at the middle ``--resolutions`` size and 4 layers (``--device-layers``),
on each Dr.Jit backend of ``--device`` beside ``--backend``: what the device path (and a GPU, where there is one)
changes, each backend against its own raw.

The default sizes (:data:`DEFAULT_RESOLUTIONS`) run from 160x90 to 960x540, half the thesis's 1920x1080 in each
direction: the ratios grow with the pixels, as each query's and each pass's fixed costs spread over more rays.
"""
from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from suite import fileio
from suite.core.trace.bench import paired_range
from suite.core.trace.recording import RecordingTracer, device_replay
from suite.errors import UserError
from suite.harness.method import wait_for_device

DEFAULT_RESOLUTIONS = ("160x90", "480x270", "960x540")
# Rows of at most SMALL_ROW_PIXELS take at least SMALL_ROW_REPEATS updates: their stages last tens of milliseconds,
# and a median of three of those moves with one slow update.
SMALL_ROW_PIXELS, SMALL_ROW_REPEATS = 160 * 90, 7
DEFAULT_PARAMS = {"update_fps": 5.5, "client_fps": 60.0, "max_in_flight": 1, "layers": 4, "full_layers": 1,
                  "tile": 8, "order": "block", "fov_enlarge": 1.1, "corner_speed": 0.02, "spp": 2, "max_depth": 4,
                  "rr_depth": 3, "denoise_iterations": 5, "relocation": True, "colour_fill": True,
                  "video_crf": 25.0, "video_preset": "veryfast", "jpeg_quality": 25, "mask_codec": "quadtree",
                  "subset_peeling": False, "key_interval": 10, "depth_tol": 0.01, "hole_fill": False,
                  "exposure": 1.0}
SERVER_STAGES = ("pvs", "layers", "path_trace")


class LocalContext:
    """The parts of the harness Context the method uses, without the timeline: stages timed by perf_counter."""

    def __init__(self, scene, tracer, t_s, resolution, index=0, pose=None, seed=0):
        self.scene, self.tracer, self.t_s, self.index = scene, tracer, t_s, index
        self.client, self.resolution, self.rng = 0, tuple(resolution), np.random.default_rng(seed)
        self._pose = pose
        self.prev_t_s = None
        self.sent, self.outputs, self.stage_ms, self.stage_rays, self.stage_log = {}, {}, {}, {}, {}

    @contextmanager
    def stage(self, name, place, after=None):
        rec = SimpleNamespace(pixels=0, count=lambda **kw: None)
        c = getattr(self.tracer, "counters", {})
        r0 = sum(c.values()) if c else 0
        log = getattr(self.tracer, "log", None)
        l0 = len(log) if log is not None else 0
        t0 = time.perf_counter()
        yield rec
        wait_for_device(self.tracer)  # as the harness's stages: the stage's kernels are part of its time
        self.stage_ms[name] = 1e3 * (time.perf_counter() - t0)
        if log is not None:
            self.stage_log[name] = log[l0:]
        self.stage_rays[name] = (sum(c.values()) if c else 0) - r0

    def latest_pose(self):
        return self.t_s, self._pose

    def send(self, name, payload, direction="down"):
        self.sent[name] = bytes(payload)

    def record(self, **kw):
        self.outputs.update(kw)


def client_context(pose, fov_deg, t_s, resolution, index=0):
    cam = SimpleNamespace(pose_at=lambda t: pose, fov_deg=fov_deg)
    return LocalContext(SimpleNamespace(camera=cam), None, t_s, resolution, index)


def delivered_update(payload: bytes, index: int, t_s: float, new: bool = True):
    from suite.harness.method import Delivered, Update

    return Update(index, t_s, {"update": Delivered("update", payload, len(payload), [], True, 0.0, 0.0)}, new)


def one_update(scene, tracer, params, resolution, t_s, later_s):
    """Server update at ``t_s``, then the client's frame at ``later_s``; returns contexts, client and image."""
    from methods.layered_pvs.method import LayeredPVS

    srv, cli = LayeredPVS(params), LayeredPVS(params)
    srv.restore(srv.prepare(scene, tracer))
    ctx = LocalContext(scene, tracer, t_s, resolution, 0, scene.camera.pose_at(t_s))
    srv.server_update(ctx)
    cctx = client_context(scene.camera.pose_at(later_s), scene.camera.fov_deg, later_s, resolution)
    t0 = time.perf_counter()
    img = cli.client_frame(cctx, delivered_update(ctx.sent["update"], 0, t_s))
    cctx.stage_ms["first_frame_total"] = 1e3 * (time.perf_counter() - t0)
    return ctx, cctx, cli, img


def _replay(tracer, log):
    """(rays, replay function) for a stage's recorded rays: the backend's raw entry points where it has them (embreex
    overwrites the lengths it is given: each call gets fresh copies, made outside the timed call), else the
    suite's queries on rays already in the tracing frame; and whether the replay is raw."""
    rays = int(sum(len(d) for _, _, d, _ in log))
    raw = hasattr(tracer, "raw_intersect") and hasattr(tracer, "raw_occluded")
    if raw:
        calls = [(tracer.raw_intersect if kind == "i" else tracer.raw_occluded, o, d, length)
                 for kind, o, d, length in log]
    else:
        shift = np.zeros(3) if getattr(tracer, "shift", None) is None else tracer.shift
        calls = [(lambda o, d, length, k=kind: (tracer.intersect if k == "i" else tracer.occluded)(
            o.astype(np.float64) + shift, d, 0.0, length), o, d, length) for kind, o, d, length in log]

    def replay() -> float:
        # Each call is timed on fresh copies of its rays made just before it, outside the timed call: the rays are
        # in the cache as the stage's are (its worker has just made them), not read cold from memory.
        elapsed = 0.0
        for fn, o, d, length in calls:
            o, d, length = o.copy(), d.copy(), length.copy()
            t0 = time.perf_counter()
            fn(o, d, length)
            elapsed += time.perf_counter() - t0
        return elapsed

    return rays, replay, raw


@contextmanager
def _kept_inputs(module, name: str):
    """Keeps the data arguments of the update's call of ``module.name`` (the layered SVGF,
    ``server.denoise_fragments``; the pack stage, ``packing.pack_stage``) in the yielded dict."""
    kept, original = {}, getattr(module, name)

    def keep(*args, **kwargs):
        kept["args"] = args  # the data; the method names its device by keyword
        return original(*args, **kwargs)

    setattr(module, name, keep)
    try:
        yield kept
    finally:
        setattr(module, name, original)


def _device_ms(column: str, fn, args, devices, scene, repeats: int) -> dict:
    """``fn(*args, device=...)`` on the recorded update's inputs: host ms (``<column>_host_ms``) and, per Dr.Jit
    device, the device kernels' ms, copies included (``<column>_<llvm|cuda>_ms``); medians of ``repeats`` calls
    after a warm-up."""
    from suite.harness.cli import bench_device, device_columns

    def timed(name, backend):
        device = bench_device(scene, backend) if backend else None
        fn(*args, device=device)
        times = []
        for _ in range(max(int(repeats), 1)):
            t0 = time.perf_counter()
            fn(*args, device=device)
            times.append(1e3 * (time.perf_counter() - t0))
        return {f"{column}_{name}_ms": float(np.median(times))}

    out = timed("host", None)
    for b in devices:
        out.update(device_columns("layered_pvs", b, lambda b=b: timed(b.replace("mitsuba-", ""), b)))
    return out


def server_rows(scene, tracer, params, resolutions, layer_counts, t_s, repeats: int = 3, devices=()):
    from methods.layered_pvs import device as layered_device
    from methods.layered_pvs import packing, server

    rows = []
    for res in resolutions:
        for L in layer_counts:
            p = {**params, "layers": L}
            # The recording takes the code paths the timed updates take: on a Dr.Jit tracer the PVS, the layers and
            # the paths are traced on the device (their rays recorded there), the other queries through the recorder.
            dev = getattr(tracer, "device", None)
            rec = RecordingTracer(tracer, device=dev is not None)
            with _kept_inputs(server, "denoise_fragments") as svgf_inputs, \
                    _kept_inputs(packing, "pack_stage") as pack_inputs, layered_device.recording({}) as device_rays:
                ctx, _, _, _ = one_update(scene, rec, p, res, t_s, t_s + 0.1)  # records the rays (and warms up)
            if dev is None:
                replays = {stage: _replay(tracer, ctx.stage_log[stage]) for stage in SERVER_STAGES}
            else:  # raw on a Dr.Jit backend: rays in device memory (numpy-fed raw calls convert every ray)
                replays = {stage: (*device_replay(dev, ctx.stage_log[stage], device_rays.get(stage, [])), True)
                           for stage in SERVER_STAGES}
            stage_ms = {stage: [] for stage in SERVER_STAGES}
            raw_ms = {stage: [] for stage in SERVER_STAGES}
            reps = max(int(repeats), 1)
            if res[0] * res[1] <= SMALL_ROW_PIXELS:
                reps = max(reps, SMALL_ROW_REPEATS)
            for _ in range(reps):  # interleaved: machine noise hits both alike
                ctx, cctx, cli, _ = one_update(scene, tracer, p, res, t_s, t_s + 0.1)
                for stage in SERVER_STAGES:
                    stage_ms[stage].append(ctx.stage_ms[stage])
                    raw_ms[stage].append(1e3 * replays[stage][1]())
            per_stage = {}
            for stage in SERVER_STAGES:
                n = replays[stage][0]
                per_stage[f"{stage}_rays"] = n
                per_stage[f"{stage}_ratio"] = float(np.median(raw_ms[stage]) / np.median(stage_ms[stage])) \
                    if n else float("nan")
                if n:  # one update's ratio, lowest and highest: the stage and its replay ran next to each other
                    per_stage[f"{stage}_ratio_range"] = paired_range(raw_ms[stage], stage_ms[stage])
                ctx.stage_ms[stage] = float(np.median(stage_ms[stage]))
            n_rays = sum(per_stage[f"{s}_rays"] for s in SERVER_STAGES)
            rows.append({"resolution": f"{res[0]}x{res[1]}", "layers": L, "rays": n_rays, "repeats": reps,
                         "raw": ("backend on device-resident rays" if dev is not None else "backend raw entry points")
                         if replays["pvs"][2] else "suite queries (no raw entry)",
                         **per_stage, **{f"{k}_ms": round(v, 2) for k, v in ctx.stage_ms.items()},
                         "client_decode_ms": cctx.stage_ms.get("decode"), "client_peel_ms": cctx.stage_ms.get("peel"),
                         "client_render_ms": cctx.stage_ms.get("render"),
                         "render_ms_per_mpix": cctx.stage_ms.get("render") / (res[0] * res[1] / 1e6),
                         "update_bytes": len(ctx.sent["update"]),
                         **(_device_ms("svgf", server.denoise_fragments, svgf_inputs["args"], devices, scene, reps)
                            if "args" in svgf_inputs else {}),
                         **(_device_ms("pack", packing.pack_stage, pack_inputs["args"], devices, scene, reps)
                            if "args" in pack_inputs else {})})
    return rows


def server_on_devices(scene, params, resolution, layers: int, t_s, repeats: int, devices) -> list:
    """:func:`server_rows` at one size on each Dr.Jit backend of ``devices``, a row each with its ``backend``; a
    backend that fails gives a row with its error."""
    from suite.harness.cli import device_rows

    return device_rows("layered_pvs", devices, scene,
                       lambda _, tracer: server_rows(scene, tracer, params, [resolution], [layers], t_s, repeats)[0])


def codec_rows(size: int = 512, seed: int = 0):
    from methods.layered_pvs import codecs
    from methods.layered_pvs.method import jpeg_decode, jpeg_encode

    rng = np.random.default_rng(seed)
    mask = (rng.random((size, size)) < 0.1).astype(np.int8)
    mask[:, :size // 2] = 1
    mask[rng.random(mask.shape) < 0.2] = codecs.ANY
    img = (rng.random((size // 2, size, 3)) * 40 + np.linspace(0, 200, size)[None, :, None]).astype(np.uint8)
    n_tri = 60 * size
    positions = rng.random((n_tri // 2, 3)).astype(np.float32)
    faces = rng.integers(0, n_tri // 2, (n_tri, 3)).astype(np.int64)
    cases = {
        "huffman": (lambda: codecs.huffman_encode(img.tobytes()), codecs.huffman_decode, img.nbytes),
        "quadtree_mask": (lambda: codecs.quadtree_encode(mask), codecs.quadtree_decode, mask.size),
        "rle_huffman_mask": (lambda: codecs.binary_rle_encode(mask), codecs.binary_rle_decode, mask.size),
        "jpeg_q25_444": (lambda: jpeg_encode(img, 25), lambda b: jpeg_decode(b, img.shape), img.nbytes),
        "pvs_patch": (lambda: codecs.pvs_patch_encode(codecs.PVSState(), np.arange(n_tri), faces, positions)[0],
                      lambda b: codecs.pvs_patch_decode(codecs.PVSState(), b), n_tri * 36),
    }
    rows = []
    for name, (enc, dec, raw) in cases.items():
        t0 = time.perf_counter()
        data = enc()
        t1 = time.perf_counter()
        dec(data)
        t2 = time.perf_counter()
        rows.append({"codec": name, "input_bytes": raw, "output_bytes": len(data),
                     "encode_MB_per_s": raw / 1e6 / (t1 - t0), "decode_MB_per_s": raw / 1e6 / (t2 - t1)})
    return rows


def write_images(out_dir: Path, ctx, cli, img, reference) -> list:
    from PIL import Image

    from suite.core import video
    from methods.layered_pvs import packing

    dec = cli._client["decoded"]
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    L = dec.depth.shape[0]
    h, w = dec.view.height, dec.view.width
    yy, xx = np.mgrid[0:h, 0:w]
    strips = []
    for k in range(min(L, 3)):
        tx, ty, st = packing.slot_texel(dec.layout, xx, yy, np.full_like(xx, k))
        layer = np.where((st & (k < dec.counts))[..., None], dec.texture[ty, tx], 0).astype(np.uint8)
        strips.append(layer)
    Image.fromarray(np.concatenate(strips, axis=1)).save(out_dir / "layers.png")
    Image.fromarray(dec.texture).save(out_dir / "packed_texture.png")
    Image.fromarray(video.to_video(img, 1.0)).save(out_dir / "client_frame.png")
    diff = np.abs(video.to_video(img, 1.0).astype(np.int16) - video.to_video(reference, 1.0).astype(np.int16))
    Image.fromarray(np.clip(diff * 4, 0, 255).astype(np.uint8)).save(out_dir / "difference_x4.png")
    names += ["layers.png", "packed_texture.png", "client_frame.png", "difference_x4.png"]
    return names


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="splitbench bench layered_pvs")
    ap.add_argument("--scene", default="auto", help="scene (auto: dabrovic_sponza, the thesis's Sponza stand-in, "
                    "when available, else living_room)")
    ap.add_argument("--backend", default="embree")
    ap.add_argument("--resolutions", default=",".join(DEFAULT_RESOLUTIONS))
    ap.add_argument("--layers", default="2,4,8")
    ap.add_argument("--codec-size", type=int, default=512, help="side of the codec benchmark's mask (pixels)")
    ap.add_argument("--repeats", type=int, default=3, help="timed updates per row (median; at least "
                    f"{SMALL_ROW_REPEATS} for rows of up to {SMALL_ROW_PIXELS} pixels), after one recording")
    ap.add_argument("--device", default="auto", help="Dr.Jit backends to time the layered SVGF and pack stage on "
                    "beside the numba kernels, and the server stages on beside --backend (auto: every one that works "
                    "here; '' for none)")
    ap.add_argument("--device-layers", type=int, default=4, help="layers of the server rows on the --device backends")
    ap.add_argument("--out", default="results")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise UserError("--repeats must be >= 1")
    from suite.harness import runner

    try:
        res = [tuple(int(x) for x in r.split("x")) for r in args.resolutions.split(",")]
        layer_counts = [int(x) for x in args.layers.split(",")]
    except ValueError:
        raise UserError(f"bad --resolutions '{args.resolutions}' or --layers '{args.layers}'") from None
    from suite.harness.cli import bench_devices, bench_scene

    devices = bench_devices(args.device)
    args.scene = bench_scene(args.scene, "layered_pvs")
    scene = runner.load_scene(args.scene)
    tracer = runner.make_tracer(args.backend, scene)
    from methods.layered_pvs.method import _warm_up

    _warm_up()
    t_s = 0.5 * scene.camera.duration_s
    out = {"scene": args.scene, "backend": args.backend, "params": DEFAULT_PARAMS, "devices": devices,
           "server": server_rows(scene, tracer, DEFAULT_PARAMS, res, layer_counts, t_s, args.repeats, devices),
           "server_on_devices": server_on_devices(scene, DEFAULT_PARAMS, res[len(res) // 2], args.device_layers,
                                                  t_s, args.repeats, [b for b in devices if b != args.backend]),
           "codecs": codec_rows(args.codec_size)}
    # Images at the largest resolution: the client 0.15 s after the update, against the update rendered there.
    big = res[-1]
    ctx, _, cli, img = one_update(scene, tracer, DEFAULT_PARAMS, big, t_s, t_s + 0.15)
    ctx2, _, _, ref = one_update(scene, tracer, DEFAULT_PARAMS, big, t_s + 0.15, t_s + 0.15)
    bench_dir = Path(args.out) / "bench"
    out["images"] = write_images(bench_dir / "layered_pvs", ctx, cli, img, ref)
    out["client"] = [{"resolution": r["resolution"], "layers": r["layers"], "render_ms_per_mpix":
                      r["render_ms_per_mpix"], "peel_ms": r["client_peel_ms"]} for r in out["server"]]
    from suite.harness.cli import bench_document

    doc = bench_document(out)
    fileio.write_text(bench_dir / "layered_pvs.json", json.dumps(doc, indent=1, default=float) + "\n")
    return out
