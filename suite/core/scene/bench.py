"""Scene loading and computed-visibility benchmark: ``python -m suite.core.scene.bench [options]``.

Reports, for ``dabrovic_sponza`` (when it is on the scene search path) and a generated OBJ of ``--triangles``
triangles (default 1 M), the load time cold (conversion, an empty cache) and cached (from the on-disk cache, a
new in-process cache), median of ``--repeats``, in this process after the imports. With ``--visibility`` it
also computes the cell PVS of Sponza (default parameters, no cache) and measures its false-negative rate
against dense sampling (:func:`suite.core.scene.cellvis.false_negative_rate`) and the fraction of the camera
path's pixels whose triangle the PVS of the eye's cell misses.

``run(...)`` returns the same numbers as a dict (``--json`` prints it).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _load_times(spec: str, repeats: int) -> dict:
    from suite.core.scene.obj import loader

    cold, cached = [], []
    scene = None
    for _ in range(repeats):
        with tempfile.TemporaryDirectory(prefix="splitbench-scene-bench-") as tmp:
            old = os.environ.get("SPLITBENCH_CACHE")
            os.environ["SPLITBENCH_CACHE"] = tmp
            try:
                loader._scene_cache.clear()
                t0 = time.perf_counter()
                scene = loader.load_obj(spec)
                cold.append(time.perf_counter() - t0)
                loader._scene_cache.clear()
                t0 = time.perf_counter()
                loader.load_obj(spec)
                cached.append(time.perf_counter() - t0)
                assert loader.last_load_stats["mode"] == "disk"
                cache_bytes = sum(p.stat().st_size for p in Path(tmp).rglob("*.npz"))
            finally:
                loader._scene_cache.clear()
                if old is None:
                    os.environ.pop("SPLITBENCH_CACHE", None)
                else:
                    os.environ["SPLITBENCH_CACHE"] = old
    return {"spec": spec, "triangles": scene.num_faces, "vertices": int(len(scene.positions)),
            "file_bytes": Path(scene.obj.source).stat().st_size, "cache_bytes": cache_bytes,
            "cold_s": statistics.median(cold), "cached_s": statistics.median(cached), "repeats": repeats,
            "cold_all_s": cold, "cached_all_s": cached}


def view_false_negative_rate(vis, scene, tracer, frames: int = 17, resolution=(160, 90)) -> dict:
    """Fraction of the camera path's pixels (``frames`` frames) whose visible triangle is not in the PVS of the
    eye's cell: what a PVS-culled renderer would lose."""
    import numpy as np

    from suite.core.gbuffer import camera_rays

    missed = total = 0
    for t in np.linspace(scene.camera.keys[0].t_s, scene.camera.keys[-1].t_s, frames):
        pose = scene.camera.pose_at(t)
        o, d = camera_rays(pose, scene.camera.fov_deg, *resolution)
        hits = tracer.intersect(o, d)
        ok = hits.prim >= 0
        pvs_tris = vis.visible_triangles(vis.cluster_of(pose.position[None])[0])
        missed += int((~pvs_tris[hits.prim[ok]]).sum())
        total += int(ok.sum())
    return {"frames": frames, "pixels": total, "missed": missed, "rate": missed / max(total, 1)}


def run(triangles: int = 1_000_000, repeats: int = 3, visibility: bool = False, backend: str = "embree") -> dict:
    from suite.core.scene import list_scenes
    from suite.core.scene.obj import reader
    from suite.core.scene.obj.samples import write_grid_obj

    reader._ARRAYS_OK = reader._self_test() if reader._ARRAYS_OK is None else reader._ARRAYS_OK  # warm the import
    out = {"host": {"cpus": os.cpu_count(), "platform": sys.platform}, "loads": []}
    desc = list_scenes().get("dabrovic_sponza", "unavailable")
    if desc.startswith("unavailable"):
        out["dabrovic_sponza"] = desc
    else:
        out["loads"].append(_load_times("dabrovic_sponza", repeats))
    with tempfile.TemporaryDirectory(prefix="splitbench-grid-") as tmp:
        t0 = time.perf_counter()
        path = write_grid_obj(Path(tmp) / f"grid_{triangles}.obj", triangles)
        out["grid_write_s"] = time.perf_counter() - t0
        out["loads"].append(_load_times(str(path), repeats))
    if visibility and not desc.startswith("unavailable"):
        from suite.core.scene import load
        from suite.core.scene.cellvis import computed_visibility, false_negative_rate
        from suite.core.trace import make

        scene = load("dabrovic_sponza")
        tracer = make(backend, scene)
        vis = computed_visibility(scene, tracer, use_cache=False)
        out["visibility"] = {"params": vis.params, "stats": vis.stats,
                             "pvs_fraction": float(vis.pvs_matrix().mean()),
                             "dense": false_negative_rate(vis, scene, tracer, pairs=4000, dense_rays=512),
                             "camera_path_pixels": view_false_negative_rate(vis, scene, tracer)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m suite.core.scene.bench", description=__doc__.splitlines()[0])
    p.add_argument("--triangles", type=int, default=1_000_000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--visibility", action="store_true", help="also compute and evaluate Sponza's cell PVS")
    p.add_argument("--backend", default="embree")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    res = run(args.triangles, args.repeats, args.visibility, args.backend)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    if "dabrovic_sponza" in res:
        print(f"dabrovic_sponza: {res['dabrovic_sponza']}")
    for r in res["loads"]:
        print(f"{Path(r['spec']).name}: {r['triangles']:,} triangles, {r['file_bytes'] / 1e6:.1f} MB; load cold "
              f"{r['cold_s']:.2f} s, cached {r['cached_s']:.3f} s (median of {r['repeats']}; cache file "
              f"{r['cache_bytes'] / 1e6:.1f} MB)")
    v = res.get("visibility")
    if v:
        s, d, c = v["stats"], v["dense"], v["camera_path_pixels"]
        print(f"cell PVS: {s['cells']} cells {s['dims']} of {v['params']['cell_size_m']:.2f} m, {s['pairs']:,} pairs, "
              f"{s['rays']:,} rays in {s['trace_s']:.1f} s ({s['rays_per_s']:,} rays/s), total {s['total_s']:.1f} s; "
              f"PVS holds {v['pvs_fraction']:.1%} of cell pairs")
        print(f"  false negatives vs {d['dense_rays']} segments per pair on {d['pairs']} pairs: {d['false_negatives']} of "
              f"{d['dense_visible']} visible pairs ({d['false_negative_rate']:.1%}); camera-path pixels missed: "
              f"{c['missed']} of {c['pixels']} ({c['rate']:.3%})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
