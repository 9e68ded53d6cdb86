"""``splitbench bench clients``: how cost grows with the number of clients on one server.

For C in (1, 2, 4, 8, 16, 24, 32) it simulates one method (default: visibility_bitmap, small frames) with C
clients, each on its own access link, all sharing the server's link, and reports per C: the server's busy time
per client frame, bytes per client, the mean client frame time, and the harness's own overhead (wall time of
the simulation minus the stages' measured wall time) per client frame, which must stay flat: the harness is
linear in C. The document goes to ``<results>/bench/clients.json`` with the environment of the run.
"""
from __future__ import annotations

import argparse
import time

from suite.errors import UserError

CLIENT_COUNTS = (1, 2, 4, 8, 16, 24, 32)


def measure(method: str, scene_name: str, backend: str, resolution: str, frames: int, net: str, server_net,
            counts=CLIENT_COUNTS, progress=True) -> list[dict]:
    from suite.harness import registry, runner

    rows = []
    cls = registry.get(method).load()
    scene = runner.load_scene(scene_name)
    tracer = runner.make_tracer(backend, scene)
    # The first count runs twice and its first pass is dropped: it pays the process's one-time compilation
    # (numba kernels, Dr.Jit), which is no cost of the clients.
    for k, c in enumerate([counts[0], *counts]):
        cfg = runner.make_config(method, scene=scene_name, backend=backend, resolution=resolution, frames=frames,
                                 net=net, clients=c, server_net=server_net, reference_spp=0)
        inst = cls(cfg["params"])
        prepared = inst.prepare(runner.scene_view(scene, runner.ServerCamera(scene.camera, 0)), tracer)
        t = time.perf_counter()
        seq = runner.simulate(cls, scene, tracer, cfg, zero_latency=False, keep=set(), prepared=prepared,
                              desc=f"{c} clients" if progress else None)
        wall_ms = 1e3 * (time.perf_counter() - t)
        events = seq.timeline.events
        stage_wall_ms = sum(e.wall_ms for e in events if e.kind == "stage")
        client_frames = c * frames
        server_ms = sum(1e3 * e.duration_s for e in events if e.kind != "message" and e.place == "server")
        msgs = [e for e in events if e.kind == "message"]
        frame_ms = [r["frame_ms"] for r in seq.rows]
        if k == 0:
            continue
        rows.append({
            "clients": c, "client_frames": client_frames,
            "server_ms_per_client_frame": server_ms / client_frames,
            "bytes_down_per_client": sum(e.size_bytes for e in msgs if e.place == "down") / c,
            "bytes_up_per_client": sum(e.size_bytes for e in msgs if e.place == "up") / c,
            "frame_ms_mean": sum(frame_ms) / len(frame_ms),
            "simulation_wall_ms": wall_ms, "stage_wall_ms": stage_wall_ms,
            "harness_overhead_ms_per_client_frame": (wall_ms - stage_wall_ms) / client_frames,
        })
    return rows


def main(argv) -> int:
    from suite.harness import results
    from suite.harness.cli import _print_json

    p = argparse.ArgumentParser(prog="splitbench bench clients", description=__doc__.splitlines()[0])
    p.add_argument("--method", default="visibility_bitmap")
    p.add_argument("--scene", default="living_room")
    p.add_argument("--backend", default="embree")
    p.add_argument("--resolution", default="32x18")
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--net", default="lan-home")
    p.add_argument("--server-net", default="bw=1000mbps,delay=1ms")
    p.add_argument("--clients", default=",".join(map(str, CLIENT_COUNTS)), help="comma-separated counts")
    p.add_argument("--out", default="results")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        counts = [int(x) for x in args.clients.split(",")]
    except ValueError:
        raise UserError(f"malformed --clients '{args.clients}' (comma-separated integers)") from None
    rows = measure(args.method, args.scene, args.backend, args.resolution, args.frames, args.net,
                   args.server_net or None, counts)
    doc = {"bench": "clients", "method": args.method, "scene": args.scene, "backend": args.backend,
           "resolution": args.resolution, "frames": args.frames, "net": args.net, "server_net": args.server_net,
           "rows": rows, **results.environment()}
    path = results.Path(args.out) / "bench" / "clients.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    results.write_json(path, doc)
    if args.json:
        _print_json(doc)
    else:
        print(f"{'C':>3} {'server ms/frame':>16} {'bytes down/client':>18} {'frame ms':>9} {'overhead ms/frame':>18}")
        for r in rows:
            print(f"{r['clients']:>3} {r['server_ms_per_client_frame']:>16.2f} {r['bytes_down_per_client']:>18.0f} "
                  f"{r['frame_ms_mean']:>9.1f} {r['harness_overhead_ms_per_client_frame']:>18.3f}")
        print(f"stored: {path}")
    return 0
