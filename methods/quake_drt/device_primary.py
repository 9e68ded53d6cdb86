"""The primary stage's shading samples (seed 001 §4.1, §6.3; Table 2.1 "anti-aliasing") as one Dr.Jit kernel on the
run's Mitsuba variant: the device twin of :func:`methods.quake_drt.primary.camera_rays` (jittered pinhole rays) followed
by :func:`methods.quake_drt.primary.surface_from_hits`.

One lane per pixel: the pixel's jitter from its seed (the PCG twins of :mod:`methods.quake_drt.device_direct`), the
float64 direction through the jittered point in the operations of ``primary._camera``, the float32 ray, its closest
opaque hit (the alpha walk included), and the hit's surface through :func:`suite.core.device.gbuffer.hit_surface`, which
is the host's ``_hit_geometry`` and texel lookup operation for operation. On ``llvm_ad_rgb`` every field equals the host
pass's bit for bit (tests/methods/quake_drt/test_device_primary.py); the rays never leave device memory, and the
samples come back to the host once, as the stages after this one read them there (counted in the device's copy
counters and recorded by the pipeline as ``primary_device_bytes``); the kernel writes the vectors interleaved, in the
host's row layout.

Depth of field (the lens sample's ``cos``/``sin`` are numpy's) and transparent overlays (the walk records every layer
for the host's blend) keep the host path.
"""
from __future__ import annotations

import numpy as np

from methods.quake_drt.device_direct import _uniform
from methods.quake_drt.rng import DIM_JITTER_X, DIM_JITTER_Y
from suite.core.trace.base import MAX_RAY_LENGTH


# The fields that are 3-vectors (rows on the host).
VECTORS = ("d", "p", "ng", "ns", "ng_view", "ns_view", "albedo", "emission")


def available(tracer, jitter: bool, aperture_m: float, skip_faces, textures) -> bool:
    """Whether the device kernel serves this primary stage: a Dr.Jit tracer, jittered pinhole rays, no overlays, and
    textures the host's compiled pass takes too (else both would fall back to the numpy reference)."""
    return (getattr(tracer, "device", None) is not None and jitter and aperture_m <= 0.0 and skip_faces is None
            and textures is not None)


def shading_samples(scene, tracer, t_s: float, width: int, height: int, seeds: np.ndarray):
    """:class:`~methods.quake_drt.primary.Surface` of the jittered pinhole rays of every pixel, made and traced on the
    tracer's device; the same values as ``surface_from_hits(camera_rays(...), intersect(...))`` on the host."""
    from methods.quake_drt.primary import Surface

    dev = tracer.device
    tracer.update(t_s)
    pose = scene.camera.pose_at(t_s)
    basis = [float(x) for b in pose.basis() for x in np.asarray(b, np.float64)]
    cam64 = np.asarray(pose.position, np.float64)
    # The tracer's numpy interface subtracts the frame shift from the float64 origin and rounds once (base.as_rays).
    o_local = (cam64 - np.asarray(tracer.shift, np.float64)).astype(np.float32).astype(np.float64)
    tan_x = float(np.tan(np.radians(scene.camera.fov_deg) / 2.0))
    ops = dev.opaques([width, height, tan_x, width / height, *basis, *o_local, *cam64])
    seeds_d = dev.to_device(np.asarray(seeds, np.uint32).reshape(-1), dev.UInt32)
    out = dev.frozen("quake_drt.shading_samples", _kernel)(dev, ops, seeds_d, int(width), int(height))
    n = width * height
    traced = out.pop("traced", None)
    tracer.counters["rays_intersect"] += n if traced is None else dev.sum_u32(traced)
    names = [k for k in out if k not in VECTORS]
    h = dict(zip(names, dev.to_host_all([out[k] for k in names],
                                        [np.int64 if k in ("prim", "material") else np.float64 for k in names])))
    h.update({k: dev.rows_to_host(out[k], 3, np.float64) for k in VECTORS})
    return Surface(valid=h["prim"] >= 0, prim=h["prim"], u=h["u"], v=h["v"], p=h["p"], ng=h["ng"], ns=h["ns"],
                   ng_view=h["ng_view"], ns_view=h["ns_view"], albedo=h["albedo"], emission=h["emission"],
                   material=h["material"], o=np.broadcast_to(cam64, (n, 3)).copy(), d=h["d"], t=h["t"],
                   overlay_rgb=np.zeros((n, 3)), overlay_t=np.ones(n))


def _kernel(dev, ops, seeds, width: int, height: int) -> dict:
    """The samples' fields from the frame's scalars (:func:`shading_samples`), evaluated in one kernel."""
    from suite.core.device.gbuffer import hit_surface, row_col

    dr, F, F64 = dev.dr, dev.Float, dev.Float64
    w, h, tan_x, aspect = ops[0:4]
    fwd, right, up = ops[4:7], ops[7:10], ops[10:13]
    row, col = row_col(dev, dev.arange(width * height), width)  # the width read from memory: one kernel for all
    jx = _uniform(dev, seeds, DIM_JITTER_X) - 0.5
    jy = _uniform(dev, seeds, DIM_JITTER_Y) - 0.5
    # primary._camera: the float64 operations in its order (divisions by values in memory stay divisions)
    px = (2.0 * ((F64(col) + 0.5) + jx) / w - 1.0) * tan_x
    py = -(2.0 * ((F64(row) + 0.5) + jy) / h - 1.0) * tan_x / aspect
    d = [(fwd[c] + px * right[c]) + py * up[c] for c in range(3)]
    norm = dr.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])
    d64 = dev.Vector3d(d[0] / norm, d[1] / norm, d[2] / norm)
    o_local = dev.Point3f(F(ops[13]), F(ops[14]), F(ops[15]))
    ray_o = dev.Point3d(ops[16], ops[17], ops[18])
    t, prim, u, v, traced = dev.closest(o_local, dev.Vector3f(d64), dr.full(F, float(MAX_RAY_LENGTH), width * height))
    valid = prim >= 0
    hit = hit_surface(dev, prim, u, v, valid, ray_o, d64, d64, bary64=True)
    zero3, zero3d = dev.Vector3f(0.0, 0.0, 0.0), dev.Vector3d(0.0, 0.0, 0.0)
    tables = dev.tables
    emission = tables.front_emission(hit.mat, valid & hit.front)
    out = {"prim": prim, "u": u, "v": v, "t": dr.select(valid, F64(t), dr.inf), "d": d64,
           "p": dr.select(valid, dev.Vector3d(hit.position), zero3d), "ng": dr.select(valid, hit.ng_raw, zero3d),
           "ns": dr.select(valid, hit.ns_raw, zero3d), "ng_view": dr.select(valid, hit.ng, zero3d),
           "ns_view": dr.select(valid, hit.ns, zero3d), "albedo": dr.select(valid, hit.albedo, zero3),
           "emission": emission, "material": dr.select(valid, hit.mat, -1)}
    # the vectors interleaved here, as the host reads them: a separate interleaving kernel would read and write them
    # once more (about 8 % of the stage at 640x360 on llvm_ad_rgb)
    out.update({k: dev.interleaved(out[k]) for k in VECTORS})
    if traced is not None:
        out["traced"] = traced
    dr.eval(*out.values())
    return out
