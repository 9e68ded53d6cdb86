"""Codec measurements on real visibility bitmaps, for the report's codec table.

``python -m methods.visibility_bitmap.bench --scene living_room --resolution 640x360 --frames 10`` renders the
server's bitmaps along the scene's camera path (G-buffer + one shadow ray per pixel and light, seed 000
Alg. 3B-2) and encodes/decodes the sequence with every codec, printing ratio, mean encode/decode ms per frame
and whether the round trip was bit-exact. Times are wall times on this machine (one run, one process, the same
bitmaps for every codec), so they compare codecs with each other, not machines.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from methods.visibility_bitmap import bitmap as bm
from methods.visibility_bitmap import codecs

DEFAULT_CODECS = ("none", "lzo", "lz4", "zstd", "zstd:9", "bitplane+lz4", "bitplane+zstd", "delta+lz4", "delta+zstd",
                  "delta+bitplane+zstd", "h264", "bitplane+h264")


def render_bitmaps(scene, tracer, resolution, frames: int, light_limit: int | None = None) -> list[np.ndarray]:
    """``(H, W, L)`` bool visibility of the first ``frames`` frames of the camera path."""
    from suite.gbuffer import render_gbuffer
    from suite.shading import point_light_visibility

    out = []
    for i in range(frames):
        t_s = scene.camera.frame_time_s(i)
        g = render_gbuffer(scene, tracer, t_s, resolution=resolution)
        lights = scene.lights_at(t_s)[:light_limit]
        out.append(point_light_visibility(g, lights, tracer))
    return out


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

    The bitmap goes through netsim on ``bw=800mbps,delay=2.5ms,loss=P`` (lan-home's link with loss), under
    UDP. Only images and bytes are reported here: frame times of lossy UDP runs belong to the harness.
    """
    import netsim

    from methods.visibility_bitmap.method import VisibilityBitmap
    from suite.method import Clock, Context
    from suite.metrics import compare
    from suite.timeline import IdealLink, Timeline

    def sequence(method, zero_latency, link):
        timeline = Timeline({"down": link, "up": IdealLink(800.0, 2.5)})
        method.reset()
        images, infos, prev_t = [], [], None
        for i in range(frames):
            t_s = scene.camera.frame_time_s(i)
            ctx = Context(timeline.group("frame", i, i / scene.camera.fps), scene=scene, tracer=tracer, t_s=t_s,
                          prev_t_s=prev_t, resolution=resolution, seed=seed, params=method.params,
                          zero_latency=zero_latency, protocol="udp", clock=Clock("work"))
            images.append(method.frame(ctx))
            infos.append(dict(method.frame_info))
            prev_t = t_s
        return images, infos

    base = dict(params or {})
    reference = VisibilityBitmap(base)
    reference.prepare(scene, tracer)
    alone, _ = sequence(reference, True, IdealLink())
    rows = []
    for loss in loss_rates:
        for repair in repairs:
            method = VisibilityBitmap({**base, "udp_repair": repair})
            method.prepare(scene, tracer)
            link = netsim.make_network(f"bw=800mbps,delay=2.5ms,loss={100 * loss:g}%", seed=seed)
            images, infos = sequence(method, False, link)
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


def main(argv=None) -> None:
    from suite.scene import load
    from suite.trace import make

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="living_room")
    ap.add_argument("--resolution", default="640x360")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--lights", type=int, default=None, help="use only the first N lights")
    ap.add_argument("--layouts", default="paper32,packed8")
    ap.add_argument("--codecs", default=",".join(DEFAULT_CODECS))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--loss", default="", help="comma-separated UDP loss rates (e.g. 0,0.01): run the loss sweep "
                                               "instead of the codec table")
    ap.add_argument("--codec", default="lz4", help="loss sweep: wire codec")
    ap.add_argument("--slice-rows", type=int, default=8, help="loss sweep: udp_slice_rows")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.resolution.lower().split("x"))
    scene = load(args.scene)
    tracer = make("embree", scene)
    if args.loss:
        rows = loss_sweep(scene, tracer, (w, h), args.frames, [float(x) for x in args.loss.split(",")],
                          params={"layout": "packed8", "codec": args.codec, "udp_slice_rows": args.slice_rows})
        if args.json:
            print(json.dumps(rows, indent=1))
            return
        print(f"{args.scene} {w}x{h}, {args.frames} frames, UDP, codec {args.codec}, {args.slice_rows} rows per slice")
        print(f"{'loss':>6} {'repair':9} {'rows repaired':>13} {'bad':>4} {'SSIM':>7} {'PSNR dB':>8} {'FLIP':>7}")
        for r in rows:
            print(f"{r['loss']:6.3f} {r['repair']:9} {100 * r['rows_repaired_fraction']:12.2f}% {r['bad_frames']:4d} "
                  f"{r['ssim']:7.4f} {r['psnr_db']:8.2f} {r['flip']:7.4f}")
        return
    vis = render_bitmaps(scene, tracer, (w, h), args.frames, args.lights)
    rows = []
    for layout in args.layouts.split(","):
        if layout == "paper32" and vis[0].shape[-1] > bm.PAPER_MAX_LIGHTS:
            continue
        rows += codec_table(vis, layout, args.codecs.split(","), repeats=args.repeats)
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print(f"{args.scene} {w}x{h}, {vis[0].shape[-1]} lights, {args.frames} frames "
          f"(lit fraction {np.mean([v.mean() for v in vis]):.3f})")
    print(f"{'layout':8} {'codec':22} {'raw B/frame':>12} {'wire B/frame':>13} {'ratio':>9} {'enc ms':>8} "
          f"{'dec ms':>8}  exact")
    for r in rows:
        if not r["available"]:
            print(f"{r['layout']:8} {r['codec']:22} unavailable: {r['reason']}")
            continue
        print(f"{r['layout']:8} {r['codec']:22} {r['raw_bytes'] / r['frames']:12.0f} {r['bytes_per_frame']:13.0f} "
              f"{r['ratio']:9.1f} {r['encode_ms']:8.2f} {r['decode_ms']:8.2f}  {r['bit_exact']}")


if __name__ == "__main__":
    main()
