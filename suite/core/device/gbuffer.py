"""The G-buffer as Dr.Jit kernels (one code path for ``llvm_ad_rgb`` and ``cuda_ad_rgb``).

:func:`render_gbuffer` traces the pixel-centre camera rays and interpolates the surface attributes in one fused
kernel and returns a :class:`DeviceGBuffer` whose fields are Dr.Jit arrays on the tracer's device. It computes
what :func:`suite.core.gbuffer.render_gbuffer` computes on the host, operation for operation in the same precision
(float64 camera rays, the float64 ray/plane intersection for positions, float64 barycentric interpolation, the
same texture filter, the same order of sums in the motion vectors' projection), so on ``llvm_ad_rgb`` the rays,
primitive ids and positions are the host path's bit for bit (tests).

Positions stay float64 on the device (Dr.Jit has float64 on both backends): shadow rays leave from
``offset_ray_origin`` of them, rounded to float32 only in the scene-centred tracing frame, exactly as on the host
(:mod:`suite.core.trace.robust`). The float64 work is a few dozen operations per pixel.

Every scalar a frame changes (camera basis, light positions, times) enters the kernels as an opaque value, so a new
frame reuses the compiled kernels.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from suite.core.trace.base import MAX_RAY_LENGTH

_HOST_FIELDS = ("position", "normal", "geo_normal", "albedo", "emission", "depth", "prim", "valid", "motion",
                "view_dir", "material", "kind")


@dataclass
class DeviceGBuffer:
    """The G-buffer on the device: flat Dr.Jit arrays of ``width * height`` pixels in row-major order (pixel
    ``i * width + j`` is row i, column j; row 0 at the top). Field meanings are :class:`suite.core.gbuffer.GBuffer`'s.
    ``to_host()`` makes the numpy GBuffer (an explicit copy; its bytes are counted in ``device.counters``)."""

    device: object  # suite.core.device.Device
    width: int
    height: int
    t_s: float
    camera_position: np.ndarray  # (3,) float32
    position: object  # Point3d: float64 world position (0 for background)
    normal: object  # Vector3f: shading normal facing the camera
    geo_normal: object  # Vector3f: geometric normal facing the camera
    albedo: object  # Vector3f
    emission: object | None  # Vector3f: radiance toward the camera (front of area lights, from `front`); None: zero
    depth: object  # Float: distance along the ray, inf for background
    prim: object  # Int32: global face index, -1 for background
    valid: object  # Bool
    view_dir: object | None  # Vector3f: unit primary-ray directions (None: recomputed when asked for, see get())
    material: object  # Int32, -1 for background
    kind: object | None  # Int32 kind code, -1 for background (None: looked up from material when asked for)
    u: object  # Float: barycentrics of the hits (0 for background)
    v: object  # Float
    motion: object | None = None  # Vector2f, None when no previous time was given (all zero)
    rays: int = 0  # backend queries the G-buffer made (camera rays plus alpha re-traces)
    stage_ms: dict = field(default_factory=dict)  # per-stage wall times when traced stage by stage (benchmarks)
    camera: tuple | None = None  # (pose, fov_deg) the view directions are recomputed from
    front: object | None = None  # Bool: the camera ray met the hit's front (where the scene emits; see render_gbuffer)

    def get(self, name: str):
        """A field by name, computing the ones the G-buffer kernel does not store (view directions, kind codes, zero
        emission) on first use; they are then kept."""
        value = getattr(self, name)
        if value is not None or name == "motion":
            return value
        dev, dr = self.device, self.device.dr
        if name == "view_dir":
            pose, fov = self.camera
            value = dev.Vector3f(camera_rays(dev, pose, fov, self.width, self.height)[0])
        elif name == "kind":
            value = dr.select(self.valid, dr.gather(dev.Int32, dev.tables.kind, dr.maximum(self.material, 0),
                                                    self.valid), -1)
        elif name in ("u", "v"):
            raise ValueError("this G-buffer kept no barycentrics (render_gbuffer(..., keep_hits=True) keeps them)")
        elif name == "emission":
            value = dr.zeros(dev.Vector3f, self.pixels)
        dr.eval(value)
        setattr(self, name, value)
        return value

    @property
    def resolution(self) -> tuple[int, int]:
        return self.width, self.height

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def fields(self):
        """The stored Dr.Jit arrays (what the G-buffer kernel writes; ``valid``, ``material`` and ``kind`` are cheap
        expressions of ``prim`` that kernels using them recompute, so they are not stored)."""
        out = [self.position, self.normal, self.geo_normal, self.albedo, self.emission, self.depth, self.prim,
               self.view_dir, self.u, self.v, self.motion, self.front]
        return [x for x in out if x is not None]

    def to_host(self, names=None, with_bytes: bool = False):
        """The numpy :class:`~suite.core.gbuffer.GBuffer` (all fields, or only ``names``; the others are None). With
        ``with_bytes`` returns ``(g, bytes_copied)``."""
        from suite.core.gbuffer import GBuffer

        dev = self.device
        names = _HOST_FIELDS if names is None else tuple(names)
        h, w = self.height, self.width
        out = {name: None for name in _HOST_FIELDS}
        if "motion" in names and self.motion is None:
            out["motion"] = np.zeros((h, w, 2), np.float32)
        copied = [name for name in _HOST_FIELDS if name in names and out[name] is None]
        dtypes = [{"position": np.float64, "prim": np.int32, "valid": bool, "material": np.int32,
                   "kind": np.int8}.get(name, np.float32) for name in copied]
        copies = dev.to_host_all([self.get(name) for name in copied], dtypes, with_bytes=True)  # one evaluation
        nbytes = sum(c.nbytes for c in copies)
        for name, copy in zip(copied, copies):
            out[name] = copy.array.reshape((h, w) + copy.array.shape[1:])
        g = GBuffer(camera_position=np.asarray(self.camera_position, np.float32), **out)
        return (g, nbytes) if with_bytes else g

    def to_host_twin(self):
        """:meth:`to_host` with read-only arrays that keep a reference to this device G-buffer (``g.device``), so host
        code on the same tracer can shade it on the device without uploading it again."""
        g = self.to_host()
        for name in _HOST_FIELDS:
            a = getattr(g, name)
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
        g.device = self
        return g

    @classmethod
    def from_host(cls, dev, g) -> "DeviceGBuffer":
        """Uploads a host :class:`~suite.core.gbuffer.GBuffer` (counted in ``dev.counters``)."""
        h, w = g.depth.shape
        n = h * w

        def up(a, dtype):
            a = np.ascontiguousarray(a)
            return dev.to_device(a.reshape(n, -1) if a.ndim == 3 else a.reshape(n), dtype)

        zeros = dev.dr.zeros(dev.Float, n)
        kind = g.kind if g.kind is not None else np.where(g.valid, 0, -1)
        material = g.material if g.material is not None else np.where(g.valid, 0, -1)
        out = cls(device=dev, width=w, height=h, t_s=float("nan"), camera_position=np.asarray(g.camera_position),
                  position=up(g.position.astype(np.float64), dev.Point3d), normal=up(g.normal, dev.Vector3f),
                  geo_normal=up(g.geo_normal, dev.Vector3f), albedo=up(g.albedo, dev.Vector3f),
                  emission=up(g.emission, dev.Vector3f), depth=up(g.depth.astype(np.float32), dev.Float),
                  prim=up(g.prim.astype(np.int32), dev.Int32), valid=up(g.valid.astype(bool), dev.Bool),
                  view_dir=up(g.view_dir.astype(np.float32), dev.Vector3f),
                  material=up(np.asarray(material, np.int32), dev.Int32), kind=up(np.asarray(kind, np.int32), dev.Int32),
                  u=zeros, v=zeros, motion=up(g.motion.astype(np.float32), dev.Vector2f))
        dev.eval(*out.fields())
        return out

    def hits_to_host(self):
        """The primary hits as a host :class:`~suite.core.trace.base.Hits` (t, prim, u, v)."""
        from suite.core.trace.base import Hits

        dev = self.device
        return Hits(dev.to_host(self.depth, np.float32), dev.to_host(self.prim, np.int32),
                    dev.to_host(self.get("u"), np.float32), dev.to_host(self.get("v"), np.float32))


def camera_scalars(pose, fov_deg: float, width: int, height: int) -> list:
    """The per-frame scalars of :func:`camera_rays` (13 values: sizes, tan of the half angle, aspect, camera basis)."""
    forward, right, up = (np.asarray(v, np.float64) for v in pose.basis())
    tan_x = float(np.tan(np.radians(fov_deg) / 2.0))
    return [width, height, tan_x, width / height, *forward, *right, *up]


def camera_rays(dev, pose, fov_deg: float, width: int, height: int):
    """Pixel-centre rays as :func:`suite.core.gbuffer.camera_rays` computes them in float64, on the device: returns
    unit directions (Vector3d, row-major from the top-left pixel). Bit-identical to the host on ``llvm_ad_rgb``."""
    return camera_rays_from(dev, dev.opaques(camera_scalars(pose, fov_deg, width, height)), width, height)


def row_col(dev, idx, width: int):
    """(row, column) UInt32 of row-major pixel indices ``idx`` (UInt32) in rows of ``width``.

    The row without an integer division (a scalar division per lane on a CPU, where no SIMD instruction divides
    integers): ``(idx + 0.5) / width`` lies at least ``0.5 / width`` inside ``(row, row + 1)``, and its float64 product
    with the rounded reciprocal is off by at most about 2^-52 of the quotient, below that margin for any index under
    2^51. Exact."""
    U, F64 = dev.UInt32, dev.Float64
    row = U(dev.dr.floor((F64(idx) + 0.5) * dev.opaque(F64, 1.0 / width)))
    # the width as a broadcast scalar: a gathered one reads 0 in the masked tail lanes of a packet
    return row, idx - row * dev.opaque(U, width)


def camera_rays_from(dev, ops, width: int, height: int):
    """:func:`camera_rays` from the values of :func:`camera_scalars` on the device (read from memory: no
    recompilation per frame; exact division)."""
    dr, F64 = dev.dr, dev.Float64
    w, h, tan_op, aspect_op, *basis = ops
    fwd_op, right_op, up_op = basis[0:3], basis[3:6], basis[6:9]
    row, col = row_col(dev, dev.arange(width * height), width)
    sx = (F64(col) + 0.5) / w
    sy = (F64(row) + 0.5) / h
    px = (2.0 * sx - 1.0) * tan_op
    py = -(2.0 * sy - 1.0) * tan_op / aspect_op
    d = [(fwd_op[c] + px * right_op[c]) + py * up_op[c] for c in range(3)]
    norm = dr.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])
    return dev.Vector3d(d[0] / norm, d[1] / norm, d[2] / norm), row, col


def _dot(a, b):
    """(x + y) + z: a BLAS-free dot product in the order of plain numpy expressions."""
    return (a.x * b.x + a.y * b.y) + a.z * b.z


def einsum_dot(a, b):
    """``np.einsum("ij,ij->i", a, b)`` of contiguous float64 rows: numpy sums the 3 products as (x + z) + y."""
    return (a.x * b.x + a.z * b.z) + a.y * b.y


def render_gbuffer(scene, tracer, t_s: float, resolution=None, prev_t_s: float | None = None,
                   stages: bool = False, keep_hits: bool = False) -> DeviceGBuffer:
    """Pixel-centre primary rays for the camera at ``t_s``, on the tracer's device. ``stages=True`` evaluates camera
    rays, tracing and attributes separately and records their wall times in ``stage_ms`` (for the benchmarks; the
    default fuses everything into one kernel). ``keep_hits`` also stores the hits' barycentrics (``u``, ``v``).

    The fused kernel is recorded once per (resolution, fields kept) and replayed on later frames
    (:meth:`~suite.core.device.context.Device.frozen`): the host prepares the frame's scalars (camera, previous
    camera, object transforms) and hands them in with the scene's tables, so a replay traces no Python at all."""
    import time

    from suite.core.gbuffer import _previous_transforms, check_resolution

    dev = tracer.device
    if dev is None:
        raise ValueError(f"backend {tracer.name} has no device path")
    dr, I = dev.dr, dev.Int32
    width, height = check_resolution(resolution or scene.camera.resolution)
    tracer.update(t_s)
    tables = dev.tables
    pose = scene.camera.pose_at(t_s)
    n = width * height
    # the frame's scalars: camera rays, then the tracing-frame origin (the host hands float32(position) to the
    # tracer, which subtracts the shift in float64 and rounds) and the float64 position, then the previous camera
    cam64 = np.asarray(pose.position, np.float64)
    o_local = (cam64.astype(np.float32).astype(np.float64) - tracer.shift).astype(np.float32)
    scalars = camera_scalars(pose, scene.camera.fov_deg, width, height) + [*o_local, *cam64]
    motion_table = None
    if prev_t_s is not None:
        scalars += _motion_scalars(scene, prev_t_s, width, height)
        if scene.object_animations:
            motion_table = dev.to_device(_previous_transforms(scene, t_s, prev_t_s).reshape(-1), dev.Float64)
    stage_ms = {}
    kernel, mark = dev.frozen("gbuffer", _gbuffer_kernel), None
    if stages:  # traced stage by stage, each evaluated and timed
        clock = [time.perf_counter()]

        def mark(name, *values):
            dev.eval(*values)
            now = time.perf_counter()
            stage_ms[name] = 1e3 * (now - clock[0])
            clock[0] = now

        kernel = _gbuffer_kernel
    out = kernel(dev, dev.opaques(scalars), motion_table, width, height, keep_hits, prev_t_s is not None, mark)
    dev.sync()
    traced = out.pop("traced", None)
    g = DeviceGBuffer(device=dev, width=width, height=height, t_s=float(t_s),
                      camera_position=np.asarray(pose.position, np.float32), valid=None, view_dir=None,
                      material=None, kind=None, camera=(pose, float(scene.camera.fov_deg)),
                      emission=None, **{name: out.get(name) for name in ("position", "normal", "geo_normal", "albedo",
                                                                         "depth", "prim", "u", "v", "motion")})
    # Cheap expressions of the stored primitive ids (and facing), fused into whatever kernel reads them.
    g.valid = g.prim >= 0
    g.material = dr.select(g.valid, dr.gather(I, tables.face_material, dr.maximum(g.prim, 0), g.valid), -1)
    g.front = out.get("front")
    if g.front is not None:
        g.emission = tables.front_emission(g.material, g.front)
    g.rays = n if traced is None else dev.sum_u32(traced)
    tracer.counters["rays_intersect"] += g.rays
    g.stage_ms = stage_ms
    return g


def hit_surface(dev, prim, u, v, valid, ray_o, d64, d_in, bary64: bool = False) -> SimpleNamespace:
    """Surface attributes at closest hits, lazily: :func:`suite.core.gbuffer.surface_attributes` and the facing of
    :func:`suite.core.gbuffer.render_gbuffer`, in float64 where the host is, operation for operation.

    ``prim``, ``u``, ``v``: the hits (``valid`` where ``prim >= 0``); ``ray_o`` (Point3d, world) and ``d64`` (Vector3d):
    the rays in float64, whose intersection with the hit triangle's plane is the position (the tracers' float32
    distance carries an error that grows with the distance from the origin); ``d_in`` (Vector3d): the direction the
    normals are turned against; ``bary64``: the first barycentric's precision (below). Returns ``position``
    (Point3d), ``ng`` and ``ns`` (Vector3d, geometric and shading normal facing the ray; ``ng_raw`` and ``ns_raw`` as
    wound and interpolated), ``albedo`` (Vector3f: the material's constant or its texture), ``mat`` (Int32) and
    ``front`` (Bool: the ray met the geometric normal's front)."""
    dr, F, F64, I = dev.dr, dev.Float, dev.Float64, dev.Int32
    tables = dev.tables
    vid = tables.triangle(prim, valid)
    tri = [dev.Vector3d(tables.vertex(tables.vpos, vid[k], valid)) for k in range(3)]
    # The first barycentric as surface_attributes computes it: in float32, then widened; ``bary64``: (1 - u) - v in
    # float64, as methods.quake_drt.primary's surface pass does.
    w0 = (1.0 - F64(u)) - F64(v) if bary64 else F64(1.0 - u - v)
    w = (w0, F64(u), F64(v))
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    ng = dev.Vector3d(e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z, e1.x * e2.y - e1.y * e2.x)
    ng_len = dr.maximum(dr.sqrt((ng.x * ng.x + ng.y * ng.y) + ng.z * ng.z), 1e-30)
    ng = dev.Vector3d(ng.x / ng_len, ng.y / ng_len, ng.z / ng_len)
    p_bary = (tri[0] * w[0] + tri[1] * w[1]) + tri[2] * w[2]
    denom = einsum_dot(d64, ng)
    ok = dr.abs(denom) > 1e-12
    t_plane = einsum_dot(tri[0] - ray_o, ng) / dr.select(ok, denom, 1.0)
    p_plane = ray_o + t_plane * d64
    position = dev.Point3d(dr.select(ok, p_plane, p_bary))
    nrm = [dev.Vector3d(tables.vertex(tables.vnrm, vid[k], valid)) for k in range(3)]
    ns = (nrm[0] * w[0] + nrm[1] * w[1]) + nrm[2] * w[2]
    ns_len = dr.sqrt((ns.x * ns.x + ns.y * ns.y) + ns.z * ns.z)
    ns_safe = dr.maximum(ns_len, 1e-30)
    ns = dev.Vector3d(dr.select(ns_len > 1e-12, dev.Vector3d(ns.x / ns_safe, ns.y / ns_safe, ns.z / ns_safe), ng))
    s = einsum_dot(ng, d_in)
    flip = dr.select(s > 0.0, 1.0, dr.select(s < 0.0, -1.0, 1.0))  # np.sign with 0 -> 1
    front = flip < 0.0
    ng_view = dev.Vector3d(-flip * ng.x, -flip * ng.y, -flip * ng.z)
    ns_view = dr.select(einsum_dot(ns, ng_view) < 0.0, -ns, ns)
    mat = dr.gather(I, tables.face_material, dr.maximum(prim, 0), valid)
    albedo = dr.gather(dev.Vector3f, tables.albedo, mat, valid)
    if tables.albedo_tex.any:
        textured = valid & tables.albedo_tex.has(mat, valid)
        uvx, uvy = tables.uv_f64(vid, w, textured)
        tex = tables.albedo_tex.lookup(mat, uvx, uvy, textured)
        albedo = dr.select(textured, dev.Vector3f(F(tex[0]), F(tex[1]), F(tex[2])), albedo)
    return SimpleNamespace(position=position, ng=ng_view, ns=ns_view, ng_raw=ng, ns_raw=ns, albedo=albedo, mat=mat,
                           front=front)


def _gbuffer_kernel(dev, scalars, motion_table, width: int, height: int, keep_hits: bool, with_motion: bool,
                    mark) -> dict:
    """The G-buffer's fields from the frame's scalars (:func:`render_gbuffer`), evaluated: one kernel, or one per
    stage where ``mark`` evaluates and times them. Reads every array through ``dev`` (its tables, the tracer's
    scene and id tables), which a recording binds to its inputs."""
    dr, F = dev.dr, dev.Float
    tables = dev.tables
    n = width * height
    mark = mark or (lambda name, *values: None)

    # 1. camera rays (float64, then the float32 rays the tracer gets, as on the host)
    d64, row, col = camera_rays_from(dev, scalars[:13], width, height)
    d32 = dev.Vector3f(d64)
    o_local = dev.Point3f(*[F(x) for x in scalars[13:16]])
    ray_o = dev.Point3d(*scalars[16:19])
    mark("camera_rays_ms", d64, d32)

    # 2. closest hits
    length = dr.full(F, float(MAX_RAY_LENGTH), n)
    t, prim, u, v, traced = dev.closest(o_local, d32, length)
    valid = prim >= 0
    mark("trace_ms", t, prim, u, v, *([traced] if traced is not None else []))

    # 3. attributes (surface_attributes + the facing of render_gbuffer), float64 where the host is
    hit = hit_surface(dev, prim, u, v, valid, ray_o, d64, dev.Vector3d(d32))
    position, ns_view, ng_view, albedo, front = hit.position, hit.ns, hit.ng, hit.albedo, hit.front
    zero3 = dev.Vector3f(0.0, 0.0, 0.0)
    out = {}
    # Not stored when they can be had later for little: emission (a gather by material where the ray met the front,
    # so the facing is stored, a byte per pixel instead of twelve), kind codes (from the material), view directions
    # (from the camera); each costs memory traffic at every pixel of every frame.
    if tables.any_emissive:
        out["front"] = valid & front
    out["position"] = position = dr.select(valid, position, dev.Point3d(0.0, 0.0, 0.0))
    out["normal"] = dr.select(valid, dev.Vector3f(ns_view), zero3)
    out["geo_normal"] = dr.select(valid, dev.Vector3f(ng_view), zero3)
    out["albedo"] = dr.select(valid, albedo, zero3)
    out["depth"] = dr.select(valid, t, dr.inf)
    out["prim"] = prim
    if keep_hits:
        out["u"], out["v"] = dr.select(valid, u, 0.0), dr.select(valid, v, 0.0)

    # 4. motion vectors (camera and rigid object motion), float64
    if with_motion:
        out["motion"] = _motion(dev, tables, position, prim, valid, row, col, scalars[19:], motion_table)
    if traced is not None:
        out["traced"] = traced
    mark("attributes_ms", *out.values())
    dr.eval(*out.values())
    return out


def _motion_scalars(scene, prev_t_s: float, width: int, height: int) -> list:
    """The per-frame scalars of :func:`_motion` (16 values: the previous camera's position and basis, tan of the
    half angle, aspect, sizes)."""
    pose = scene.camera.pose_at(prev_t_s)
    forward, right, up = (np.asarray(v, np.float64) for v in pose.basis())
    tan_x = float(np.tan(np.radians(scene.camera.fov_deg) / 2.0))
    return [*np.asarray(pose.position, np.float64), *right, *up, *forward, tan_x, width / height, width, height]


def _motion(dev, tables, position, prim, valid, row, col, ops, table):
    """Previous-frame pixel position minus the current one (the motion of :func:`suite.core.gbuffer.trace_primary` on
    the device, operation for operation). ``ops``: the values of :func:`_motion_scalars` on the device; ``table``:
    the objects' previous-frame transforms (12 float64 per object), None without animated objects."""
    dr, F64, I = dev.dr, dev.Float64, dev.Int32
    prev = position
    if table is not None:
        obj = dr.gather(I, tables.face_object, dr.maximum(prim, 0), valid)
        base = dev.UInt32(dr.maximum(obj, 0)) * 12
        r = [dr.gather(F64, table, base + k, valid) for k in range(12)]
        prev = dev.Point3d(*[((prev.x * r[4 * i] + prev.y * r[4 * i + 1]) + prev.z * r[4 * i + 2]) + r[4 * i + 3]
                             for i in range(3)])
    cam = dev.Point3d(*ops[0:3])
    rel = prev - cam
    lx = _dot(rel, dev.Vector3d(*ops[3:6]))
    ly = _dot(rel, dev.Vector3d(*ops[6:9]))
    lz = _dot(rel, dev.Vector3d(*ops[9:12]))
    tan_op, aspect_op, w_op, h_op = ops[12:16]
    safe_z = dr.select(dr.abs(lz) > 1e-12, lz, 1e-12)
    x = 0.5 * (1.0 + lx / (safe_z * tan_op)) * w_op
    y = 0.5 * (1.0 - ly * aspect_op / (safe_z * tan_op)) * h_op
    mx = dev.Float(x - (F64(col) + 0.5))
    my = dev.Float(y - (F64(row) + 0.5))
    return dr.select(valid, dev.Vector2f(mx, my), dev.Vector2f(0.0, 0.0))
