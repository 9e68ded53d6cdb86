"""Primary-visibility buffer (G-buffer) from pixel-centre primary rays.

Tracing one ray through each pixel centre gives the same visible surface as rasterisation sampled at pixel
centres, on either backend. The camera model is Mitsuba's ``perspective`` sensor with ``fov_axis='x'``, so
pixel (row i, column j) looks along ``forward + (2 s_x - 1) tan(fov/2) right - (2 s_y - 1) tan(fov/2)/aspect up``
with ``s = ((j + 0.5)/W, (i + 0.5)/H)``; :func:`project` is its inverse.

The tracer skips transparent texels of alpha-tested materials (:mod:`suite.core.trace.alpha`), so a pixel shows
what lies behind them. Each pixel carries its material index and shading kind (``material``, ``kind``,
:meth:`GBuffer.kind_mask`) so that methods can branch on mirrors, glass and glossy surfaces.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError


@dataclass
class GBuffer:
    position: np.ndarray  # (H, W, 3) float64 world position (0 for background); float64 keeps far-from-origin
    #                      scenes as precise as scenes at the origin for secondary rays
    normal: np.ndarray  # (H, W, 3) shading normal, on the camera's side of the surface
    geo_normal: np.ndarray  # (H, W, 3) geometric normal, on the camera's side
    albedo: np.ndarray  # (H, W, 3) diffuse reflectance
    emission: np.ndarray  # (H, W, 3) emitted radiance toward the camera (area lights seen directly)
    depth: np.ndarray  # (H, W) distance along the primary ray, inf for background
    prim: np.ndarray  # (H, W) int32 global face index, -1 for background
    valid: np.ndarray  # (H, W) bool, a surface was hit
    motion: np.ndarray  # (H, W, 2) float32 (dx, dy) in pixels: previous-frame position = current + motion
    view_dir: np.ndarray  # (H, W, 3) unit primary-ray directions
    camera_position: np.ndarray  # (3,)
    material: np.ndarray | None = None  # (H, W) int32 index into scene.materials, -1 for background
    kind: np.ndarray | None = None  # (H, W) int8 shading kind (suite.core.scene.model.KIND_CODES), -1 background
    # The DeviceGBuffer this one was copied from (Mitsuba tracers; then the arrays are read-only, so the two cannot
    # drift apart): shading on the same tracer uses it instead of uploading the host arrays again.
    device: object | None = field(default=None, repr=False, compare=False)

    def kind_mask(self, kind: str) -> np.ndarray:
        """(H, W) bool: pixels whose visible surface has shading kind ``kind`` ("diffuse", "mirror", "glass",
        "rough_conductor", "rough_plastic"; the legacy "alpha" is "diffuse")."""
        from suite.core.scene.model import KIND_CODES

        code = KIND_CODES.get("diffuse" if kind == "alpha" else kind)
        if code is None:
            raise UserError(f"unknown material kind '{kind}' (choose from {', '.join(KIND_CODES)})")
        if self.kind is None:
            raise UserError("this G-buffer carries no material kinds")
        return self.kind == code

    @property
    def resolution(self) -> tuple[int, int]:
        return int(self.depth.shape[1]), int(self.depth.shape[0])

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f).nbytes for f in ("position", "normal", "albedo", "depth", "prim", "motion"))


def check_resolution(resolution) -> tuple[int, int]:
    try:
        width, height = (int(x) for x in resolution)
    except (TypeError, ValueError):
        raise UserError(f"resolution {resolution!r} is not WIDTHxHEIGHT") from None
    if width <= 0 or height <= 0:
        raise UserError(f"resolution {width}x{height} must be positive in both dimensions")
    return width, height


def camera_rays(pose, fov_deg: float, width: int, height: int, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre rays, row-major from the top-left pixel: origins (N,3) and unit directions (N,3)."""
    forward, right, up = pose.basis()
    tan_x = np.tan(np.radians(fov_deg) / 2.0)
    aspect = width / height
    sx = (np.arange(width) + 0.5) / width
    sy = (np.arange(height) + 0.5) / height
    px = (2.0 * sx - 1.0) * tan_x
    py = -(2.0 * sy - 1.0) * tan_x / aspect
    d = forward[None, None, :] + px[None, :, None] * right[None, None, :] + py[:, None, None] * up[None, None, :]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    dirs = d.reshape(-1, 3).astype(dtype)
    origins = np.broadcast_to(np.asarray(pose.position, dtype), dirs.shape).copy()
    return origins, dirs


def project(points: np.ndarray, pose, fov_deg: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """World points → continuous pixel coordinates (x, y) (pixel centres at j+0.5, i+0.5) and view depth z.

    Points behind the camera get z <= 0; their pixel coordinates are meaningless.
    """
    forward, right, up = pose.basis()
    rel = np.asarray(points, np.float64) - np.asarray(pose.position, np.float64)
    lx, ly, lz = rel @ right, rel @ up, rel @ forward
    tan_x = np.tan(np.radians(fov_deg) / 2.0)
    aspect = width / height
    safe_z = np.where(np.abs(lz) > 1e-12, lz, 1e-12)
    x = 0.5 * (1.0 + lx / (safe_z * tan_x)) * width
    y = 0.5 * (1.0 - ly * aspect / (safe_z * tan_x)) * height
    return np.stack([x, y], axis=-1), lz


def lookup_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, repeating lookup with Mitsuba's ``bitmap`` conventions (row 0 at v = 0, texel centres at +0.5).

    ``texture`` is (H, W, C); returns (N, C) float32."""
    h, w = texture.shape[:2]
    x = uv[:, 0] * w - 0.5
    y = uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0i, y0i = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1i, y1i = (x0i + 1) % w, (y0i + 1) % h
    t00, t10 = texture[y0i, x0i], texture[y0i, x1i]
    t01, t11 = texture[y1i, x0i], texture[y1i, x1i]
    return ((1 - fx) * (1 - fy) * t00 + fx * (1 - fy) * t10 + (1 - fx) * fy * t01 + fx * fy * t11).astype(np.float32)


_compiled = None  # the numba versions of the per-hit passes below, compiled on first use


def _attributes(positions, normals, faces, w0, w1, w2, ray_o, ray_d, use_ray, p, ng, ns):
    """Per hit: float64 position (barycentric, or the ray's intersection with the triangle's plane), unit geometric
    normal and interpolated shading normal. Dot products sum as ``np.einsum("ij,ij->i")`` does: (x + z) + y."""
    for i in range(len(w0)):
        f0, f1, f2 = faces[i, 0], faces[i, 1], faces[i, 2]
        t0x, t0y, t0z = np.float64(positions[f0, 0]), np.float64(positions[f0, 1]), np.float64(positions[f0, 2])
        t1x, t1y, t1z = np.float64(positions[f1, 0]), np.float64(positions[f1, 1]), np.float64(positions[f1, 2])
        t2x, t2y, t2z = np.float64(positions[f2, 0]), np.float64(positions[f2, 1]), np.float64(positions[f2, 2])
        e1x, e1y, e1z = t1x - t0x, t1y - t0y, t1z - t0z
        e2x, e2y, e2z = t2x - t0x, t2y - t0y, t2z - t0z
        gx, gy, gz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        glen = max(np.sqrt((gx * gx + gy * gy) + gz * gz), 1e-30)
        gx, gy, gz = gx / glen, gy / glen, gz / glen
        a, b, c = w0[i], w1[i], w2[i]
        px = (t0x * a + t1x * b) + t2x * c
        py = (t0y * a + t1y * b) + t2y * c
        pz = (t0z * a + t1z * b) + t2z * c
        if use_ray:
            denom = (ray_d[i, 0] * gx + ray_d[i, 2] * gz) + ray_d[i, 1] * gy
            if abs(denom) > 1e-12:
                t_plane = ((t0x - ray_o[i, 0]) * gx + (t0z - ray_o[i, 2]) * gz) + (t0y - ray_o[i, 1]) * gy
                t_plane = t_plane / denom
                px = ray_o[i, 0] + t_plane * ray_d[i, 0]
                py = ray_o[i, 1] + t_plane * ray_d[i, 1]
                pz = ray_o[i, 2] + t_plane * ray_d[i, 2]
        nx = (np.float64(normals[f0, 0]) * a + np.float64(normals[f1, 0]) * b) + np.float64(normals[f2, 0]) * c
        ny = (np.float64(normals[f0, 1]) * a + np.float64(normals[f1, 1]) * b) + np.float64(normals[f2, 1]) * c
        nz = (np.float64(normals[f0, 2]) * a + np.float64(normals[f1, 2]) * b) + np.float64(normals[f2, 2]) * c
        nlen = np.sqrt((nx * nx + ny * ny) + nz * nz)
        if nlen > 1e-12:
            nsafe = max(nlen, 1e-30)
            nx, ny, nz = nx / nsafe, ny / nsafe, nz / nsafe
        else:
            nx, ny, nz = gx, gy, gz
        p[i, 0], p[i, 1], p[i, 2] = px, py, pz
        ng[i, 0], ng[i, 1], ng[i, 2] = gx, gy, gz
        ns[i, 0], ns[i, 1], ns[i, 2] = nx, ny, nz


def _facing(ng, ns, dirs, ng_view, ns_view, front):
    """Per hit: normals turned toward the viewer (np.sign of n . d, 0 counted as +1) and whether ``ng`` faced it."""
    for i in range(len(ng)):
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        s = (ng[i, 0] * dx + ng[i, 2] * dz) + ng[i, 1] * dy
        flip = -1.0 if s < 0.0 else 1.0
        front[i] = flip < 0.0
        vx, vy, vz = -flip * ng[i, 0], -flip * ng[i, 1], -flip * ng[i, 2]
        ng_view[i, 0], ng_view[i, 1], ng_view[i, 2] = vx, vy, vz
        back = ((ns[i, 0] * vx + ns[i, 2] * vz) + ns[i, 1] * vy) < 0.0
        for k in range(3):
            ns_view[i, k] = -ns[i, k] if back else ns[i, k]


def _scatter(dst, idx, src):
    """``dst[idx] = src`` for (N, 3) rows, cast to ``dst``'s type as numpy's assignment casts."""
    for i in range(len(idx)):
        for k in range(3):
            dst[idx[i], k] = src[i, k]


def _motion(motion, idx, lx, ly, lz, tan_x, aspect, width, height):
    """``motion[idx] = float32(project(...) - pixel centres)`` of row-major pixel indices ``idx``, from the view-space
    coordinates ``lx, ly, lz`` of the points (:func:`project`'s expressions in their order)."""
    for i in range(len(idx)):
        z = lz[i] if abs(lz[i]) > 1e-12 else 1e-12
        x = 0.5 * (1.0 + lx[i] / (z * tan_x)) * width
        y = 0.5 * (1.0 - ly[i] * aspect / (z * tan_x)) * height
        motion[idx[i], 0] = np.float32(x - (np.float64(idx[i] % width) + 0.5))
        motion[idx[i], 1] = np.float32(y - (np.float64(idx[i] // width) + 0.5))


def _motion_vectors(motion, idx, points, pose, fov_deg: float, width: int, height: int) -> None:
    """``motion[idx]``: where float64 world ``points`` project in the frame of ``pose`` minus their pixel centres
    (:func:`project`: its matrix products, then one compiled pass)."""
    forward, right, up = pose.basis()
    rel = np.asarray(points, np.float64) - np.asarray(pose.position, np.float64)
    tan_x = np.tan(np.radians(fov_deg) / 2.0)
    _kernels()[3](motion, idx, rel @ right, rel @ up, rel @ forward, float(tan_x), width / height, int(width),
                  int(height))


def _scatter_rows(dst, idx, src) -> None:
    """``dst[idx] = src`` for (N, 3) rows in one compiled pass (numpy's fancy-index assignment of rows is slow)."""
    _kernels()[2](dst, idx, np.ascontiguousarray(src))


def _kernels():
    """:func:`_attributes`, :func:`_facing`, :func:`_scatter` and :func:`_motion` compiled (numba, one pass over the hits, compiled on first use):
    every float64 operation in the order of the numpy expressions of :func:`surface_attributes_reference` and of
    the Dr.Jit G-buffer, so the three give the same bits."""
    global _compiled
    if _compiled is None:
        import numba

        jit = numba.njit(cache=True, nogil=True, error_model="numpy")
        _compiled = (jit(_attributes), jit(_facing), jit(_scatter), jit(_motion))
    return _compiled


def surface_attributes(scene, positions, normals, prim, u, v, ray_o=None, ray_d=None):
    """Interpolated position, geometric and shading normals, albedo and emission for hit records.

    With float64 rays (``ray_o``, ``ray_d``) the position is the exact intersection of the ray with the hit
    triangle's plane, computed in float64: the tracers' float32 distance carries an error that grows with the
    distance from the origin, which would shift shadow edges in scenes far from the origin.

    Position and normals come from one compiled pass over the hits (:func:`_kernels`), with the bits of
    :func:`surface_attributes_reference`.
    """
    faces = np.ascontiguousarray(scene.faces[prim])
    n = len(faces)
    w0 = np.asarray(1.0 - u - v).astype(np.float64)  # in the barycentrics' own precision, then float64
    w1, w2 = np.asarray(u, np.float64), np.asarray(v, np.float64)
    p, ng, ns = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    use_ray = ray_o is not None
    ro = np.ascontiguousarray(ray_o, np.float64) if use_ray else np.zeros((1, 3))
    rd = np.ascontiguousarray(ray_d, np.float64) if use_ray else np.zeros((1, 3))
    _kernels()[0](np.ascontiguousarray(positions), np.ascontiguousarray(normals), faces, w0, w1, w2, ro, rd, use_ray,
                  p, ng, ns)
    albedo, emission = _materials(scene, faces, prim, w0, w1, w2)
    return p, ng, ns, albedo, emission


def _materials(scene, faces, prim, w0, w1, w2):
    """(albedo, emission) float32 of hits on faces ``faces`` (indices ``prim``) at barycentrics w0, w1, w2."""
    mat = scene.face_material[prim]
    albedo = scene.face_albedo()[prim].astype(np.float32)
    for mid, m in enumerate(scene.materials):
        if m.albedo_texture is not None:
            sel = mat == mid
            if sel.any():
                w = np.stack([w0[sel], w1[sel], w2[sel]], axis=-1)[..., None]
                uv = (scene.uvs[faces[sel]].astype(np.float64) * w).sum(axis=1)
                albedo[sel] = lookup_texture(m.albedo_texture, uv)
    emission_table = np.stack([m.emission for m in scene.materials]).astype(np.float32)
    return albedo, emission_table[mat]


def surface_attributes_reference(scene, positions, normals, prim, u, v, ray_o=None, ray_d=None):
    """:func:`surface_attributes` as whole-array numpy expressions (the reference its compiled pass is tested
    against)."""
    faces = scene.faces[prim]
    w = np.stack([1.0 - u - v, u, v], axis=-1).astype(np.float64)[..., None]
    tri = positions[faces].astype(np.float64)
    ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ng /= np.maximum(np.linalg.norm(ng, axis=-1, keepdims=True), 1e-30)
    p = (tri * w).sum(axis=1)
    if ray_o is not None:
        denom = np.einsum("ij,ij->i", ray_d, ng)
        ok = np.abs(denom) > 1e-12
        t_plane = np.einsum("ij,ij->i", tri[:, 0] - ray_o, ng) / np.where(ok, denom, 1.0)
        p = np.where(ok[:, None], ray_o + t_plane[:, None] * ray_d, p)
    ns = (normals[faces].astype(np.float64) * w).sum(axis=1)
    ns_len = np.linalg.norm(ns, axis=-1, keepdims=True)
    ns = np.where(ns_len > 1e-12, ns / np.maximum(ns_len, 1e-30), ng)
    albedo, emission = _materials(scene, faces, prim, w[:, 0, 0], w[:, 1, 0], w[:, 2, 0])
    return p, ng, ns, albedo, emission


def facing(ng, ns, dirs):
    """Both normals turned toward the viewer (surfaces are shaded on the side they are seen from):
    (ng_view float32, ns_view float32, front_facing bool: the geometric normal already faced the camera)."""
    n = len(ng)
    ng_view, ns_view, front = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, bool)
    _kernels()[1](np.ascontiguousarray(ng, np.float64), np.ascontiguousarray(ns, np.float64),
                  np.ascontiguousarray(dirs), ng_view, ns_view, front)
    return ng_view, ns_view, front


def has_device(tracer) -> bool:
    """True when the tracer has a Dr.Jit device path (Mitsuba ``llvm_ad_rgb`` / ``cuda_ad_rgb``)."""
    return getattr(tracer, "device", None) is not None


def render_gbuffer(scene, tracer, t_s: float, resolution=None, prev_t_s: float | None = None,
                   device: bool | None = None) -> GBuffer:
    """Traces pixel-centre primary rays for the camera pose at ``t_s``.

    ``motion`` maps each pixel to where its surface point was in the frame at ``prev_t_s`` (camera motion and
    rigid object motion); it is zero when ``prev_t_s`` is None.

    A tracer with a device path (Mitsuba ``llvm_ad_rgb`` / ``cuda_ad_rgb``) computes it with the Dr.Jit kernels of
    :mod:`suite.core.device` and copies it to the host (the same values; ``g.device`` keeps the device copy);
    ``device=False`` forces the numpy path, which Embree always takes. :func:`render_gbuffer_device` returns the
    device G-buffer without copying it.
    """
    if device is not False and has_device(tracer):
        return render_gbuffer_device(scene, tracer, t_s, resolution, prev_t_s).to_host_twin()
    return trace_primary(scene, tracer, t_s, resolution, prev_t_s, device=False)[0]


def render_gbuffer_device(scene, tracer, t_s: float, resolution=None, prev_t_s: float | None = None):
    """The G-buffer as a :class:`suite.core.device.DeviceGBuffer` (Dr.Jit arrays that stay on the tracer's device).
    A tracer without a device path is a UserError."""
    if not has_device(tracer):
        raise UserError(f"backend '{getattr(tracer, 'name', type(tracer).__name__)}' has no device path "
                        "(use a mitsuba backend with the llvm or cuda variant)")
    from suite.core.device.gbuffer import render_gbuffer as device_gbuffer

    return device_gbuffer(scene, tracer, t_s, resolution, prev_t_s)


def trace_primary(scene, tracer, t_s: float, resolution=None, prev_t_s: float | None = None,
                  device: bool | None = None):
    """:func:`render_gbuffer` plus what it was made from: ``(g, origins, dirs, hits)`` with float64 pixel-centre
    rays (N, 3) in row-major pixel order and the tracer's :class:`~suite.core.trace.base.Hits` for them."""
    width, height = check_resolution(resolution or scene.camera.resolution)
    if device is not False and has_device(tracer):
        from suite.core.device.gbuffer import render_gbuffer as device_gbuffer

        dg = device_gbuffer(scene, tracer, t_s, (width, height), prev_t_s, keep_hits=True)
        o64, d64 = camera_rays(scene.camera.pose_at(t_s), scene.camera.fov_deg, width, height, dtype=np.float64)
        return dg.to_host_twin(), o64, d64, dg.hits_to_host()
    tracer.update(t_s)
    pose = scene.camera.pose_at(t_s)
    # float64 rays give exact surface positions below; the tracers take their float32 rounding.
    o64, d64 = camera_rays(pose, scene.camera.fov_deg, width, height, dtype=np.float64)
    dirs = d64.astype(np.float32)
    hits = tracer.intersect(o64.astype(np.float32), dirs)
    n = width * height
    valid = hits.prim >= 0
    position = np.zeros((n, 3), np.float64)
    normal = np.zeros((n, 3), np.float32)
    geo = np.zeros((n, 3), np.float32)
    albedo = np.zeros((n, 3), np.float32)
    emission = np.zeros((n, 3), np.float32)
    idx = np.nonzero(valid)[0]
    if len(idx):
        positions = scene.positions_at(t_s)
        normals = scene.normals_at(t_s)
        p, ng, ns, alb, em = surface_attributes(scene, positions, normals, hits.prim[idx], hits.u[idx], hits.v[idx],
                                                o64[idx], d64[idx])
        ng_view, ns_view, front_facing = facing(ng, ns, dirs[idx])
        for dst, src in ((position, p), (geo, ng_view), (normal, ns_view), (albedo, alb)):
            _scatter_rows(dst, idx, src)
        # Area emitters emit on the side their normal points to (Mitsuba's `area` is one-sided).
        emission[idx] = np.where(front_facing[:, None], em, 0.0)
    motion = np.zeros((n, 2), np.float32)
    if prev_t_s is not None and len(idx):
        prev_points = p
        if scene.object_animations:
            prev_points = _points_at_previous_time(scene, hits.prim[idx], prev_points, t_s, prev_t_s)
        _motion_vectors(motion, idx, prev_points, scene.camera.pose_at(prev_t_s), scene.camera.fov_deg, width, height)
    depth = np.where(valid, hits.t, np.inf).astype(np.float32)
    material = np.full(n, -1, np.int32)
    kind = np.full(n, -1, np.int8)
    if len(idx):
        material[idx] = scene.face_material[hits.prim[idx]]
        kind[idx] = scene.face_kind_codes()[hits.prim[idx]]
    hw = (height, width)
    g = GBuffer(position=position.reshape(*hw, 3), normal=normal.reshape(*hw, 3), geo_normal=geo.reshape(*hw, 3),
                albedo=albedo.reshape(*hw, 3), emission=emission.reshape(*hw, 3), depth=depth.reshape(hw),
                prim=hits.prim.reshape(hw), valid=valid.reshape(hw), motion=motion.reshape(*hw, 2),
                view_dir=dirs.reshape(*hw, 3), camera_position=np.asarray(pose.position, np.float32),
                material=material.reshape(hw), kind=kind.reshape(hw))
    return g, o64, d64, hits


def _points_at_previous_time(scene, prim, points, t_s, prev_t_s):
    obj = scene.face_object[prim]
    out = points.copy()
    for anim in scene.object_animations:
        sel = obj == anim.object_id
        if sel.any():
            m = anim.transform_at(prev_t_s) @ np.linalg.inv(anim.transform_at(t_s))
            out[sel] = points[sel] @ m[:3, :3].T + m[:3, 3]
    return out
