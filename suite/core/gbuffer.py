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

from dataclasses import dataclass, field, fields

import numpy as np

from suite.errors import UserError
from suite.core.pipeline import local_rays, pipelined, trace_local
from suite.core.trace.base import Hits


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

    def detach(self) -> "GBuffer":
        """Makes the arrays writable, in place: a device twin's read-only arrays become host copies and the link to
        the device G-buffer goes (once changed, the two would no longer agree). Returns this G-buffer."""
        if self.device is not None:
            for f in fields(self):
                a = getattr(self, f.name)
                if isinstance(a, np.ndarray) and not a.flags.writeable:
                    setattr(self, f.name, a.copy())
            self.device = None
        return self

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
    """Pixel-centre rays, row-major from the top-left pixel: origins (N,3) and unit directions (N,3).

    One compiled pass (:func:`_camera`) with the bits of :func:`camera_rays_reference` (and of the Dr.Jit
    ``suite.core.device.gbuffer.camera_rays``)."""
    forward, right, up = (np.asarray(v, np.float64) for v in pose.basis())
    tan_x = float(np.tan(np.radians(fov_deg) / 2.0))
    dirs = np.empty((height * width, 3), dtype)
    _kernels()[3](forward, right, up, tan_x, width / height, int(width), int(height), 0, int(height), dirs)
    origins = np.empty_like(dirs)
    for c in range(3):  # column by column: numpy's broadcast of a 3-vector over rows is several times slower
        origins[:, c] = pose.position[c]
    return origins, dirs


def _camera(forward, right, up, tan_x, aspect, width, height, row0, row1, out):
    """Unit pixel-centre directions of the rows ``row0:row1`` of the image (``out`` holds the whole image), the
    float64 operations of :func:`camera_rays_reference` in their order (numpy's norm sums the squares as
    (x + y) + z), then cast to ``out``'s type."""
    for i in range(row0, row1):
        sy = (np.float64(i) + 0.5) / height
        py = -(2.0 * sy - 1.0) * tan_x / aspect
        for j in range(width):
            sx = (np.float64(j) + 0.5) / width
            px = (2.0 * sx - 1.0) * tan_x
            dx = (forward[0] + px * right[0]) + py * up[0]
            dy = (forward[1] + px * right[1]) + py * up[1]
            dz = (forward[2] + px * right[2]) + py * up[2]
            norm = np.sqrt((dx * dx + dy * dy) + dz * dz)
            k = i * width + j
            out[k, 0] = dx / norm
            out[k, 1] = dy / norm
            out[k, 2] = dz / norm


def camera_rays_reference(pose, fov_deg: float, width: int, height: int, dtype=np.float32):
    """:func:`camera_rays` as whole-array numpy expressions (the reference its compiled pass is tested against)."""
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
_hit_geometry_jit = None  # the compiled _hit_geometry, which the compiled passes call (bound before they compile)
_texel_jit = None  # the compiled _texel, likewise


def _hit_geometry(positions, normals, f0, f1, f2, a, b, c, use_ray, rox, roy, roz, rdx, rdy, rdz):
    """One hit: float64 position (barycentric, or the ray's intersection with the triangle's plane), unit geometric
    normal and interpolated shading normal, as 9 floats. Dot products sum as ``np.einsum("ij,ij->i")`` does:
    (x + z) + y."""
    t0x, t0y, t0z = np.float64(positions[f0, 0]), np.float64(positions[f0, 1]), np.float64(positions[f0, 2])
    t1x, t1y, t1z = np.float64(positions[f1, 0]), np.float64(positions[f1, 1]), np.float64(positions[f1, 2])
    t2x, t2y, t2z = np.float64(positions[f2, 0]), np.float64(positions[f2, 1]), np.float64(positions[f2, 2])
    e1x, e1y, e1z = t1x - t0x, t1y - t0y, t1z - t0z
    e2x, e2y, e2z = t2x - t0x, t2y - t0y, t2z - t0z
    gx, gy, gz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    glen = max(np.sqrt((gx * gx + gy * gy) + gz * gz), 1e-30)
    gx, gy, gz = gx / glen, gy / glen, gz / glen
    px = (t0x * a + t1x * b) + t2x * c
    py = (t0y * a + t1y * b) + t2y * c
    pz = (t0z * a + t1z * b) + t2z * c
    if use_ray:
        denom = (rdx * gx + rdz * gz) + rdy * gy
        if abs(denom) > 1e-12:
            t_plane = ((t0x - rox) * gx + (t0z - roz) * gz) + (t0y - roy) * gy
            t_plane = t_plane / denom
            px = rox + t_plane * rdx
            py = roy + t_plane * rdy
            pz = roz + t_plane * rdz
    nx = (np.float64(normals[f0, 0]) * a + np.float64(normals[f1, 0]) * b) + np.float64(normals[f2, 0]) * c
    ny = (np.float64(normals[f0, 1]) * a + np.float64(normals[f1, 1]) * b) + np.float64(normals[f2, 1]) * c
    nz = (np.float64(normals[f0, 2]) * a + np.float64(normals[f1, 2]) * b) + np.float64(normals[f2, 2]) * c
    nlen = np.sqrt((nx * nx + ny * ny) + nz * nz)
    if nlen > 1e-12:
        nsafe = max(nlen, 1e-30)
        nx, ny, nz = nx / nsafe, ny / nsafe, nz / nsafe
    else:
        nx, ny, nz = gx, gy, gz
    return px, py, pz, gx, gy, gz, nx, ny, nz


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


def _texel(uvs, f0, f1, f2, a, b1, b2, slot, tex_shape, tex_data):
    """The albedo texture ``slot`` of :func:`texture_table` at a hit on the face with vertices f0, f1, f2 and float64
    barycentrics a, b1, b2, as float32 RGB: UVs interpolated as :func:`_materials_reference` does, then
    :func:`lookup_texture` (bilinear, repeating) operation for operation."""
    uvx = (np.float64(uvs[f0, 0]) * a + np.float64(uvs[f1, 0]) * b1) + np.float64(uvs[f2, 0]) * b2
    uvy = (np.float64(uvs[f0, 1]) * a + np.float64(uvs[f1, 1]) * b1) + np.float64(uvs[f2, 1]) * b2
    h, w, c, off = tex_shape[slot, 0], tex_shape[slot, 1], tex_shape[slot, 2], tex_shape[slot, 3]
    x = uvx * w - 0.5
    y = uvy * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    # Repeating texel indices (numpy's floor modulo; numba's integer % floors too): an integer division only where
    # the texel lies outside the first repeat, and the neighbour wraps by comparison (the same indices).
    x0i, y0i = np.int64(x0), np.int64(y0)
    if x0i < 0 or x0i >= w:
        x0i %= w
    if y0i < 0 or y0i >= h:
        y0i %= h
    x1i = x0i + 1 if x0i + 1 < w else 0
    y1i = y0i + 1 if y0i + 1 < h else 0
    # The bilinear weights and the four texels' offsets once for the three channels (the products in
    # lookup_texture's order: ((1 - fx) * (1 - fy)) * t00, ...); the channels as a tuple (an array here would be a
    # heap allocation per hit), one channel repeated for a single-channel texture.
    w00, w10, w01, w11 = (1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy
    i00, i10 = off + (y0i * w + x0i) * c, off + (y0i * w + x1i) * c
    i01, i11 = off + (y1i * w + x0i) * c, off + (y1i * w + x1i) * c
    c1, c2 = (1, 2) if c > 1 else (0, 0)
    f64 = np.float64
    return (np.float32(((w00 * f64(tex_data[i00]) + w10 * f64(tex_data[i10])) + w01 * f64(tex_data[i01]))
                      + w11 * f64(tex_data[i11])),
            np.float32(((w00 * f64(tex_data[i00 + c1]) + w10 * f64(tex_data[i10 + c1])) + w01 * f64(tex_data[i01 + c1]))
                       + w11 * f64(tex_data[i11 + c1])),
            np.float32(((w00 * f64(tex_data[i00 + c2]) + w10 * f64(tex_data[i10 + c2])) + w01 * f64(tex_data[i01 + c2]))
                       + w11 * f64(tex_data[i11 + c2])))


def _surface(positions, normals, faces, prim, u, v, one, w0, ray_o, ray_d, use_ray, face_material, albedo_table,
             emission_table, uvs, tex_slot, tex_shape, tex_data, p, ng, ns, albedo, emission):
    """:func:`surface_attributes` per hit in one pass: barycentrics ``(one - u) - v`` in the hits' own precision
    (``one`` carries it; or ``w0`` where given), then float64; :func:`_hit_geometry`; the material's constant albedo
    or its texture at the hit (:func:`_texel`), and its emission. The bits of :func:`surface_attributes_reference`."""
    given = w0.shape[0] > 0
    for i in range(prim.shape[0]):
        f = prim[i]
        a = w0[i] if given else np.float64((one - u[i]) - v[i])
        b1, b2 = np.float64(u[i]), np.float64(v[i])
        r = _hit_geometry_jit(positions, normals, faces[f, 0], faces[f, 1], faces[f, 2], a, b1, b2,
                              use_ray, ray_o[i, 0] if use_ray else 0.0, ray_o[i, 1] if use_ray else 0.0,
                              ray_o[i, 2] if use_ray else 0.0, ray_d[i, 0] if use_ray else 0.0,
                              ray_d[i, 1] if use_ray else 0.0, ray_d[i, 2] if use_ray else 0.0)
        for k in range(3):
            p[i, k] = r[k]
            ng[i, k] = r[3 + k]
            ns[i, k] = r[6 + k]
        m = face_material[f]
        for k in range(3):
            albedo[i, k] = albedo_table[m, k]
            emission[i, k] = emission_table[m, k]
        slot = tex_slot[m]
        if slot >= 0:
            rgb = _texel_jit(uvs, faces[f, 0], faces[f, 1], faces[f, 2], a, b1, b2, slot, tex_shape, tex_data)
            albedo[i, 0], albedo[i, 1], albedo[i, 2] = rgb[0], rgb[1], rgb[2]


def _pixels(positions, normals, faces, prim, u, v, t, cam, d64, dirs, face_material, face_kind, face_object,
            albedo_table, emission_table, uvs, tex_slot, tex_shape, tex_data, motion_on, prev_xform, prev_cam,
            prev_basis, tan_x, aspect, width, height, first, position, geo, normal, albedo, emission, depth, material,
            kind, motion):
    """The whole per-pixel G-buffer in one pass over the pixels (:func:`trace_primary`): for a hit, the attributes of
    :func:`surface_attributes` (barycentrics ``1 - u - v`` in float32, then float64; the position on the camera
    ray's plane intersection), the facing of :func:`facing`, constant albedo, front-facing emission, depth,
    material, kind, and motion (the previous-time point through its object's ``prev_xform`` (3 x 4 rows per
    object; none when nothing is animated), projected as :func:`project` computes it, plain (x + y) + z dot
    products as on the device); background values for a miss. Albedo textures (``texture_table``) are looked up as
    :func:`lookup_texture` does: float64 UVs interpolated as :func:`_materials_reference` does, bilinear and repeating,
    rounded to float32. The arrays hold the pixels from ``first`` on (row-major in a ``width`` x ``height`` image).
    """
    for i in range(prim.shape[0]):
        f = prim[i]
        if f < 0:
            for k in range(3):
                position[i, k] = 0.0
                geo[i, k] = 0.0
                normal[i, k] = 0.0
                albedo[i, k] = 0.0
                emission[i, k] = 0.0
            depth[i] = np.inf
            material[i] = -1
            kind[i] = -1
            motion[i, 0] = 0.0
            motion[i, 1] = 0.0
            continue
        a = np.float64((np.float32(1.0) - u[i]) - v[i])
        r = _hit_geometry_jit(positions, normals, faces[f, 0], faces[f, 1], faces[f, 2], a, np.float64(u[i]),
                              np.float64(v[i]), True, cam[0], cam[1], cam[2], d64[i, 0], d64[i, 1], d64[i, 2])
        px, py, pz, gx, gy, gz = r[0], r[1], r[2], r[3], r[4], r[5]
        position[i, 0], position[i, 1], position[i, 2] = px, py, pz
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        flip = -1.0 if ((gx * dx + gz * dz) + gy * dy) < 0.0 else 1.0
        vx, vy, vz = -flip * gx, -flip * gy, -flip * gz
        geo[i, 0], geo[i, 1], geo[i, 2] = vx, vy, vz
        back = ((r[6] * vx + r[8] * vz) + r[7] * vy) < 0.0
        for k in range(3):
            normal[i, k] = -r[6 + k] if back else r[6 + k]
        m = face_material[f]
        for k in range(3):
            albedo[i, k] = albedo_table[m, k]
            emission[i, k] = emission_table[m, k] if flip < 0.0 else np.float32(0.0)
        slot = tex_slot[m]
        if slot >= 0:
            rgb = _texel_jit(uvs, faces[f, 0], faces[f, 1], faces[f, 2], a, np.float64(u[i]), np.float64(v[i]), slot,
                             tex_shape, tex_data)
            albedo[i, 0], albedo[i, 1], albedo[i, 2] = rgb[0], rgb[1], rgb[2]
        depth[i] = t[i]
        material[i] = m
        kind[i] = face_kind[f]
        if motion_on:
            qx, qy, qz = px, py, pz
            if prev_xform.shape[0] > 0:  # rigidly animated objects: the point where it was at the previous time
                o = face_object[f]
                qx = ((px * prev_xform[o, 0] + py * prev_xform[o, 1]) + pz * prev_xform[o, 2]) + prev_xform[o, 3]
                qy = ((px * prev_xform[o, 4] + py * prev_xform[o, 5]) + pz * prev_xform[o, 6]) + prev_xform[o, 7]
                qz = ((px * prev_xform[o, 8] + py * prev_xform[o, 9]) + pz * prev_xform[o, 10]) + prev_xform[o, 11]
            rx, ry, rz = qx - prev_cam[0], qy - prev_cam[1], qz - prev_cam[2]
            lx = (rx * prev_basis[1, 0] + ry * prev_basis[1, 1]) + rz * prev_basis[1, 2]
            ly = (rx * prev_basis[2, 0] + ry * prev_basis[2, 1]) + rz * prev_basis[2, 2]
            lz = (rx * prev_basis[0, 0] + ry * prev_basis[0, 1]) + rz * prev_basis[0, 2]
            z = lz if abs(lz) > 1e-12 else 1e-12
            x = 0.5 * (1.0 + lx / (z * tan_x)) * width
            y = 0.5 * (1.0 - ly * aspect / (z * tan_x)) * height
            motion[i, 0] = np.float32(x - (np.float64((first + i) % width) + 0.5))
            motion[i, 1] = np.float32(y - (np.float64((first + i) // width) + 0.5))
        else:
            motion[i, 0] = 0.0
            motion[i, 1] = 0.0


def _kernels():
    """:func:`_surface`, :func:`_facing`, :func:`_pixels` and :func:`_camera` compiled (numba, one pass over the hits
    or pixels, compiled on first use): every float64 operation in the order of the numpy expressions of
    :func:`surface_attributes_reference` / :func:`camera_rays_reference` and of the Dr.Jit G-buffer, so they give
    the same bits (motion vectors: the Dr.Jit G-buffer's order)."""
    global _compiled, _hit_geometry_jit, _texel_jit
    if _compiled is None:
        import numba

        jit = numba.njit(cache=True, nogil=True, error_model="numpy")
        _hit_geometry_jit = jit(_hit_geometry)
        _texel_jit = jit(_texel)
        _compiled = (jit(_surface), jit(_facing), jit(_pixels), jit(_camera))
    return _compiled


def surface_attributes(scene, positions, normals, prim, u, v, ray_o=None, ray_d=None, out=None):
    """Interpolated position, geometric and shading normals, albedo and emission for hit records.

    With float64 rays (``ray_o``, ``ray_d``) the position is the exact intersection of the ray with the hit
    triangle's plane, computed in float64: the tracers' float32 distance carries an error that grows with the
    distance from the origin, which would shift shadow edges in scenes far from the origin.

    Everything comes from one compiled pass over the hits (:func:`_surface`), with the bits of
    :func:`surface_attributes_reference`. ``out`` (p, ng, ns float64 (N, 3), albedo, emission float32 (N, 3), C
    order) receives the results in place of new arrays (the rows of a larger buffer, for hits split between
    threads).
    """
    prim = np.ascontiguousarray(prim, np.int64)
    u, v = np.asarray(u), np.asarray(v)
    # 1 - u - v in the barycentrics' own precision (the kernel's, where u and v share a float type), then float64
    same = u.dtype == v.dtype and u.dtype in (np.float32, np.float64)
    w0 = np.zeros(0) if same else np.ascontiguousarray(np.asarray(1.0 - u - v).astype(np.float64)).reshape(-1)
    dt = u.dtype if same else np.dtype(np.float64)
    u, v = np.ascontiguousarray(u, dt).reshape(-1), np.ascontiguousarray(v, dt).reshape(-1)
    n = len(prim)
    if out is None:
        p, ng, ns = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
        albedo, emission = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    else:
        p, ng, ns, albedo, emission = out
        for arr, want in zip(out, (np.float64,) * 3 + (np.float32,) * 2):
            if arr.shape != (n, 3) or arr.dtype != want or not arr.flags.c_contiguous:
                raise ValueError(f"surface_attributes: an output array is {arr.dtype} {arr.shape}, not C-ordered "
                                 f"{np.dtype(want)} ({n}, 3)")
    if n == 0:
        return p, ng, ns, albedo, emission
    use_ray = ray_o is not None
    ro = np.ascontiguousarray(ray_o, np.float64) if use_ray else np.zeros((1, 3))
    rd = np.ascontiguousarray(ray_d, np.float64) if use_ray else np.zeros((1, 3))
    _kernels()[0](np.ascontiguousarray(positions), np.ascontiguousarray(normals), scene.faces, prim, u, v,
                  dt.type(1.0), w0, ro, rd, use_ray, scene.face_material, *material_tables(scene),
                  np.ascontiguousarray(scene.uvs), *texture_table(scene), p, ng, ns, albedo, emission)
    return p, ng, ns, albedo, emission


def material_tables(scene):
    """(albedo (M, 3) float32, emission (M, 3) float32): the constant albedo and the emission of every material (one
    row per material, not per face: cheap enough to build per call, and never stale)."""
    return (np.array([m.albedo for m in scene.materials], np.float32),
            np.array([m.emission for m in scene.materials], np.float32))


def _materials_reference(scene, faces, prim, w0, w1, w2):
    """(albedo, emission) float32 of hits on faces ``prim`` (vertex indices ``faces``) at float64 barycentrics w0,
    w1, w2, as whole-array numpy expressions (the materials part of :func:`surface_attributes_reference`)."""
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
    albedo, emission = _materials_reference(scene, faces, prim, w[:, 0, 0], w[:, 1, 0], w[:, 2, 0])
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
    steps, result = primary_steps(scene, tracer, t_s, width, height, prev_t_s)
    pipelined(steps)
    return result()


def primary_steps(scene, tracer, t_s: float, width: int, height: int, prev_t_s: float | None = None):
    """The host path of :func:`trace_primary` as pipeline steps: ``(steps, result)``, the steps per row chunk for
    :func:`pipelined` (which may run them together with other images' steps) and ``result()`` giving
    ``(g, origins, dirs, hits)`` once they ran."""
    tracer.update(t_s)
    pose = scene.camera.pose_at(t_s)
    fov = scene.camera.fov_deg
    n = width * height
    # float64 rays give exact surface positions below; the tracers take their float32 rounding.
    o64, d64 = np.empty((n, 3)), np.empty((n, 3))
    o32, dirs = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    position = np.empty((n, 3), np.float64)
    normal, geo, albedo, emission = (np.empty((n, 3), np.float32) for _ in range(4))
    depth = np.empty(n, np.float32)
    material = np.empty(n, np.int32)
    kind = np.empty(n, np.int8)
    motion = np.empty((n, 2), np.float32)
    motion_on = prev_t_s is not None
    prev_pose = scene.camera.pose_at(prev_t_s if motion_on else t_s)
    prev_xform = _previous_transforms(scene, t_s, prev_t_s) if motion_on and scene.object_animations \
        else np.zeros((0, 12))
    kern = _kernels()
    basis = [np.asarray(b, np.float64) for b in pose.basis()]
    tan_x = float(np.tan(np.radians(fov) / 2.0))
    cam = np.asarray(pose.position, np.float64)
    geometry = (np.ascontiguousarray(scene.positions_at(t_s)), np.ascontiguousarray(scene.normals_at(t_s)),
                scene.faces)
    materials = (scene.face_material, scene.face_kind_codes(), scene.face_object, *material_tables(scene), scene.uvs,
                 *texture_table(scene), motion_on, prev_xform, np.asarray(prev_pose.position, np.float64),
                 np.stack(prev_pose.basis()).astype(np.float64), tan_x, width / height, width, height)

    queue, trace, hits = row_queries(tracer, o32, dirs, width)
    t, prim, u, v = hits.t, hits.prim, hits.u, hits.v

    def rays(r0, r1):
        """The float64 and float32 camera rays of rows r0:r1."""
        a, b = r0 * width, r1 * width
        kern[3](*basis, tan_x, width / height, width, height, r0, r1, d64)
        for c in range(3):  # column by column: numpy's broadcast of a 3-vector over rows is several times slower
            o64[a:b, c] = cam[c]
        o32[a:b] = o64[a:b]
        dirs[a:b] = d64[a:b]
        queue(r0, r1)

    def pixels(r0, r1):
        """The G-buffer fields of rows r0:r1 from their hits."""
        a, b = r0 * width, r1 * width
        kern[2](*geometry, prim[a:b], u[a:b], v[a:b], t[a:b], cam, d64[a:b], dirs[a:b], *materials, a,
                position[a:b], geo[a:b], normal[a:b], albedo[a:b], emission[a:b], depth[a:b], material[a:b],
                kind[a:b], motion[a:b])

    def result():
        valid = hits.prim >= 0
        hw = (height, width)
        g = GBuffer(position=position.reshape(*hw, 3), normal=normal.reshape(*hw, 3),
                    geo_normal=geo.reshape(*hw, 3), albedo=albedo.reshape(*hw, 3),
                    emission=emission.reshape(*hw, 3), depth=depth.reshape(hw), prim=hits.prim.reshape(hw),
                    valid=valid.reshape(hw), motion=motion.reshape(*hw, 2), view_dir=dirs.reshape(*hw, 3),
                    camera_position=np.asarray(pose.position, np.float32), material=material.reshape(hw),
                    kind=kind.reshape(hw))
        return g, o64, d64, hits

    return row_steps(height, width, rays, trace, pixels), result


# Pixels per chunk of the pipelined host passes (:func:`row_steps`): at least this many, in at most
# PIPELINE_CHUNKS chunks, so that a chunk's backend query outweighs its call overhead.
PIPELINE_MIN_PIXELS = 8192
PIPELINE_CHUNKS = 8


def row_chunks(height: int, width: int) -> list:
    """[(first row, end row)]: an image's rows in up to :data:`PIPELINE_CHUNKS` chunks of about
    :data:`PIPELINE_MIN_PIXELS` pixels or more (one chunk for a small image)."""
    count = int(max(1, min(PIPELINE_CHUNKS, (height * width) // PIPELINE_MIN_PIXELS, height)))
    # The first chunk half as tall as the others, the last two a half and a quarter: the backend starts on the first
    # chunk's rays sooner, and less work is left once the last chunk is traced (the pipeline's fill and drain).
    weight = [1.0] * count
    if count >= 3:
        weight[0], weight[-1] = 0.5, 0.25
        if count >= 5:
            weight[-2] = 0.5
    bounds, done = [0], 0.0
    for w in weight:  # plain floats: this runs several times per frame
        done += w
        bounds.append(round(height * done / sum(weight)))
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def row_queries(tracer, origins, dirs, width: int):
    """The closest-hit queries of an image's rays (row-major, ``width`` per row) by row chunk, for :func:`row_steps`:
    ``(queue, trace, hits)``. ``queue(r0, r1)``, the end of a chunk's make, puts rows r0:r1's rays in the tracer's
    frame (:func:`suite.core.pipeline.local_rays`, off the tracing thread); ``trace(r0, r1)`` queries them and
    writes their hits into ``hits``, the whole image's."""
    n = len(dirs)
    hits = Hits(np.empty(n, np.float32), np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32))
    local = {}  # first row of a chunk -> its query, made beside the previous chunk's

    def queue(r0, r1):
        a, b = r0 * width, r1 * width
        local[r0] = local_rays(tracer, origins[a:b], dirs[a:b])

    def trace(r0, r1):
        a, b = r0 * width, r1 * width
        h = trace_local(tracer, local.pop(r0), origins[a:b], dirs[a:b])
        hits.t[a:b], hits.prim[a:b], hits.u[a:b], hits.v[a:b] = h.t, h.prim, h.u, h.v

    return queue, trace, hits


def row_steps(height: int, width: int, make, trace, finish) -> list:
    """Pipeline steps (:func:`pipelined`) over an image's row chunks (:func:`row_chunks`): per chunk, ``make(r0,
    r1)`` (its rays), ``trace(r0, r1)`` and ``finish(r0, r1)`` (what is computed from its hits)."""
    from functools import partial

    return [(partial(make, a, b), partial(trace, a, b), partial(finish, a, b)) for a, b in row_chunks(height, width)]


_PACKED_TEXTURES: dict = {}  # ids of a scene's albedo textures -> (the textures, their packed table)


def texture_table(scene):
    """The albedo textures of ``scene``'s materials packed for compiled lookups: (texture slot per material (M,) int64,
    -1 for a constant albedo; (slots, 4) int64 rows of height, width, channels and offset; every texture flat in
    one float32 array). Packed once per set of texture arrays (a scene's textures do not change after loading)."""
    textures = tuple(m.albedo_texture for m in scene.materials)
    key = tuple(id(t) for t in textures)
    packed = _PACKED_TEXTURES.get(key)
    if packed is None:
        slot = np.full(len(textures), -1, np.int64)
        shapes, flat, offset = [], [], 0
        for mid, tex in enumerate(textures):
            if tex is None:
                continue
            tex = np.asarray(tex, np.float32)
            tex = tex.reshape(tex.shape[0], tex.shape[1], -1)
            if tex.shape[2] not in (1, 3):
                raise UserError(f"scene '{scene.name}': material '{scene.materials[mid].name}' has an albedo texture "
                                f"with {tex.shape[2]} channels (supported: 1 or 3)")
            slot[mid] = len(shapes)
            shapes.append((tex.shape[0], tex.shape[1], tex.shape[2], offset))
            flat.append(tex.reshape(-1))
            offset += tex.size
        table = (slot, np.array(shapes, np.int64).reshape(-1, 4),
                 np.concatenate(flat) if flat else np.zeros(1, np.float32))
        if len(_PACKED_TEXTURES) >= 4:
            _PACKED_TEXTURES.clear()
        packed = _PACKED_TEXTURES[key] = (textures, table)  # the textures stay referenced: their ids stay theirs
    return packed[1]


def _previous_transforms(scene, t_s: float, prev_t_s: float) -> np.ndarray:
    """(objects, 12) float64: per object, the 3 x 4 rows taking its points at ``t_s`` to where they were at
    ``prev_t_s`` (identity for static objects)."""
    n_obj = int(scene.face_object.max()) + 1 if len(scene.face_object) else 1
    mats = np.tile(np.eye(4)[:3].reshape(1, 12), (n_obj, 1))
    for anim in scene.object_animations:
        m = anim.transform_at(prev_t_s) @ np.linalg.inv(anim.transform_at(t_s))
        mats[anim.object_id] = m[:3].reshape(12)
    return np.ascontiguousarray(mats, np.float64)
