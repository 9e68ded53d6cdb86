"""The scene model every backend and method shares.

A scene is one indexed triangle soup with per-face material and object ids, a list of point lights,
area lights implied by emissive materials, a scripted camera path and optional rigid animation.
Arrays are numpy, float32 for geometry (both tracing backends work in float32), in world space.

Units follow Mitsuba: a point light has intensity I in W/sr; an emissive material has radiance L_e;
a diffuse material has albedo rho (the BRDF is rho / pi).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError

# What a surface does with light (``Material.kind``), following the Mitsuba plugin it exports to:
#   diffuse          Lambertian reflectance ``albedo`` (texture allowed); shaded on both sides (`twosided` `diffuse`)
#   mirror           smooth conductor (`conductor`): specular reflectance x conductor Fresnel term (eta + i k)
#   glass            smooth dielectric (`dielectric`): Fresnel-weighted specular reflection and refraction
#   rough_conductor  glossy metal (`roughconductor`): microfacet BRDF, roughness ``roughness`` (Mitsuba's alpha)
#   rough_plastic    glossy plastic (`roughplastic`): microfacet coating over a Lambertian base ``albedo``
#   alpha            kept for compatibility: shaded exactly like ``diffuse``
# Alpha testing is not a kind: any material with an ``opacity_texture`` is alpha-tested (Mitsuba `mask`).
MATERIAL_KINDS = ("diffuse", "mirror", "glass", "alpha", "rough_conductor", "rough_plastic")
# Codes of the shading kinds in G-buffers (``GBuffer.kind``); -1 marks background pixels. "alpha" shades as diffuse.
KIND_CODES = {"diffuse": 0, "mirror": 1, "glass": 2, "rough_conductor": 3, "rough_plastic": 4}
# Kinds whose reflection is a Dirac delta (a path continues through them; no light sampling there).
SPECULAR_KINDS = ("mirror", "glass")
# Kinds with a microfacet lobe (light sampling with the full BRDF).
GLOSSY_KINDS = ("rough_conductor", "rough_plastic")
MICROFACET_DISTRIBUTIONS = ("beckmann", "ggx")
# Alpha-test threshold: a surface point exists where its opacity >= 0.5, like Quake III's `alphaFunc GE128`.
DEFAULT_ALPHA_THRESHOLD = 0.5
# Mitsuba's default indices of refraction (`lookup_ior`): bk7 glass, polypropylene, air.
IOR_BK7 = 1.5046
IOR_POLYPROPYLENE = 1.49
IOR_AIR = 1.000277


@dataclass
class Material:
    """A surface description: a BSDF ``kind`` with its parameters, optional emission and alpha-tested opacity.

    Parameters follow the Mitsuba plugins (same names, same defaults); those a kind does not use are ignored:

    * ``albedo`` / ``albedo_texture``: diffuse reflectance (diffuse, alpha) and rough_plastic's
      ``diffuse_reflectance``.
    * ``specular_reflectance``: mirror, rough_conductor, glass, rough_plastic; ``specular_transmittance``: glass.
    * ``int_ior`` / ``ext_ior``: glass and rough_plastic (relative IOR ``eta = int_ior / ext_ior``; None picks
      Mitsuba's default: bk7 / polypropylene inside, air outside).
    * ``conductor_eta`` / ``conductor_k``: complex IOR of mirror and rough_conductor per RGB channel; the default
      (0, 1) is Mitsuba's ``conductor`` default, a Fresnel factor of exactly 1 (a perfect mirror).
    * ``roughness``: Mitsuba's ``alpha`` of rough_conductor / rough_plastic, with ``distribution`` "beckmann"
      (Mitsuba's default) or "ggx"; ``nonlinear``: rough_plastic's option of the same name.
    * ``twosided``: whether mirror / rough_conductor / rough_plastic reflect on the back side too (Mitsuba's
      `twosided` adapter); without it the back side is black, as Mitsuba's one-sided plugins are. Diffuse
      materials are always shaded on both sides; glass always refracts on both.
    * ``opacity_texture``: (H, W, 1) float32 opacity in Mitsuba's bitmap layout (row 0 at v = 0), looked up
      bilinearly; where it is below ``alpha_threshold`` the surface does not exist for any ray (alpha test).
    """

    name: str
    albedo: np.ndarray  # (3,) linear RGB reflectance, used when there is no texture
    albedo_texture: np.ndarray | None = None  # (H, W, 3) float32 linear RGB; row 0 at v = 0 (Mitsuba bitmap layout)
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))  # (3,) radiance
    kind: str = "diffuse"
    specular_reflectance: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))
    specular_transmittance: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))
    int_ior: float | None = None
    ext_ior: float | None = None
    conductor_eta: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    conductor_k: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))
    roughness: float = 0.1
    distribution: str = "beckmann"
    nonlinear: bool = False
    twosided: bool = False
    opacity_texture: np.ndarray | None = None
    alpha_threshold: float = DEFAULT_ALPHA_THRESHOLD

    def __post_init__(self):
        self.albedo = np.asarray(self.albedo, np.float32).reshape(3)
        self.emission = np.asarray(self.emission, np.float32).reshape(3)
        if self.kind not in MATERIAL_KINDS:
            raise UserError(f"material '{self.name}': unknown kind '{self.kind}' (choose from {MATERIAL_KINDS})")
        for attr in ("specular_reflectance", "specular_transmittance", "conductor_eta", "conductor_k"):
            value = np.asarray(getattr(self, attr), np.float32).reshape(-1)
            if value.size == 1:
                value = np.repeat(value, 3)
            if value.shape != (3,) or not np.isfinite(value).all() or (value < 0).any():
                raise UserError(f"material '{self.name}': {attr} must be 1 or 3 finite non-negative numbers")
            setattr(self, attr, value)
        if self.int_ior is None:
            self.int_ior = IOR_POLYPROPYLENE if self.kind == "rough_plastic" else IOR_BK7
        if self.ext_ior is None:
            self.ext_ior = IOR_AIR
        self.int_ior, self.ext_ior = float(self.int_ior), float(self.ext_ior)
        if self.kind in ("glass", "rough_plastic") and not (self.int_ior > 0 and self.ext_ior > 0
                                                            and self.int_ior != self.ext_ior):
            raise UserError(f"material '{self.name}': int_ior and ext_ior must be positive and differ "
                            f"(got {self.int_ior}, {self.ext_ior})")
        self.roughness = float(self.roughness)
        if not (np.isfinite(self.roughness) and self.roughness > 0):
            raise UserError(f"material '{self.name}': roughness (alpha) must be positive, got {self.roughness}")
        self.distribution = str(self.distribution).lower()
        if self.distribution not in MICROFACET_DISTRIBUTIONS:
            raise UserError(f"material '{self.name}': unknown microfacet distribution '{self.distribution}' "
                            f"(choose from {MICROFACET_DISTRIBUTIONS})")
        self.nonlinear, self.twosided = bool(self.nonlinear), bool(self.twosided)
        self.alpha_threshold = float(self.alpha_threshold)
        if not 0.0 < self.alpha_threshold <= 1.0:
            raise UserError(f"material '{self.name}': alpha_threshold must be in (0, 1], got {self.alpha_threshold}")
        if self.opacity_texture is not None:
            tex = np.asarray(self.opacity_texture, np.float32)
            if tex.ndim == 2:
                tex = tex[..., None]
            if tex.ndim != 3 or tex.shape[2] != 1 or tex.size == 0 or not np.isfinite(tex).all():
                raise UserError(f"material '{self.name}': opacity_texture must be a finite (H, W) or (H, W, 1) "
                                f"array, got shape {np.shape(self.opacity_texture)}")
            self.opacity_texture = np.ascontiguousarray(tex)

    @property
    def is_emissive(self) -> bool:
        return bool(np.any(self.emission > 0))

    @property
    def shading_kind(self) -> str:
        """The BSDF the kernels evaluate: ``kind``, with the legacy "alpha" meaning "diffuse"."""
        return "diffuse" if self.kind == "alpha" else self.kind

    @property
    def is_specular(self) -> bool:
        """Mirror or glass: reflection (and refraction) along single directions."""
        return self.kind in SPECULAR_KINDS

    @property
    def is_glossy(self) -> bool:
        return self.kind in GLOSSY_KINDS

    @property
    def is_alpha_tested(self) -> bool:
        return self.opacity_texture is not None

    @property
    def eta(self) -> float:
        """Relative index of refraction int_ior / ext_ior (glass, rough_plastic)."""
        return self.int_ior / self.ext_ior


@dataclass
class PointLight:
    name: str
    position: np.ndarray  # (3,) world space
    intensity: np.ndarray  # (3,) W/sr, as Mitsuba's `point` emitter

    def __post_init__(self):
        self.position = np.asarray(self.position, np.float64).reshape(3)
        self.intensity = np.asarray(self.intensity, np.float32).reshape(3)


@dataclass
class TriangleLights:
    """The scene's emissive triangles as a list of one-sided area lights (Mitsuba's `area` emitter), at one time.

    Row i describes face ``faces[i]``: its corners, its unit normal on the emitting side (the side the stored
    vertex normals point to, whatever the winding), its radiance L_e (W/m^2/sr) and area (m^2). A light source
    of many small triangles (e.g. Quake III surface lights) is just many rows.
    """

    faces: np.ndarray  # (E,) int32 global face ids
    vertices: np.ndarray  # (E, 3, 3) float64 corners
    normal: np.ndarray  # (E, 3) float64 unit normal of the emitting side
    radiance: np.ndarray  # (E, 3) float64
    area: np.ndarray  # (E,) float64

    def __len__(self) -> int:
        return int(len(self.faces))

    @property
    def power(self) -> np.ndarray:
        """(E,) emitted power per triangle: pi * area * mean radiance (W, RGB mean)."""
        return np.pi * self.area * self.radiance.mean(axis=-1) if len(self.faces) else np.zeros(0)


@dataclass
class CameraPose:
    position: np.ndarray  # (3,)
    target: np.ndarray  # (3,)
    up: np.ndarray  # (3,)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward, right, up) orthonormal vectors, matching Mitsuba's look_at convention."""
        forward = _normalize(self.target - self.position)
        right = _cross(forward, np.asarray(self.up))
        if np.linalg.norm(right) < 1e-12:
            raise UserError("camera 'up' vector is parallel to the viewing direction")
        right = _normalize(right)
        true_up = _cross(right, forward)
        return forward, right, true_up


@dataclass
class CameraKey:
    t_s: float
    position: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    def __post_init__(self):
        self.position = np.asarray(self.position, np.float64).reshape(3)
        self.target = np.asarray(self.target, np.float64).reshape(3)
        self.up = np.asarray(self.up, np.float64).reshape(3)


@dataclass
class CameraPath:
    """A deterministic scripted camera: keyframes, linearly interpolated, clamped at the ends.

    ``fov_deg`` is the horizontal field of view (Mitsuba's default ``fov_axis='x'``).
    """

    keys: list[CameraKey]
    fov_deg: float = 45.0
    resolution: tuple[int, int] = (320, 180)  # (width, height)
    fps: float = 30.0

    def __post_init__(self):
        if not self.keys:
            raise UserError("camera path has no keyframes")
        self.keys = sorted(self.keys, key=lambda k: k.t_s)
        if not (0.0 < self.fov_deg < 180.0):
            raise UserError(f"camera fov {self.fov_deg} deg is outside (0, 180)")

    @property
    def duration_s(self) -> float:
        return self.keys[-1].t_s - self.keys[0].t_s

    def pose_at(self, t_s: float) -> CameraPose:
        keys = self.keys
        if t_s <= keys[0].t_s or len(keys) == 1:
            k = keys[0]
            return CameraPose(k.position.copy(), k.target.copy(), k.up.copy())
        if t_s >= keys[-1].t_s:
            k = keys[-1]
            return CameraPose(k.position.copy(), k.target.copy(), k.up.copy())
        times = np.array([k.t_s for k in keys])
        i = int(np.searchsorted(times, t_s, side="right")) - 1
        a, b = keys[i], keys[i + 1]
        w = (t_s - a.t_s) / max(b.t_s - a.t_s, 1e-12)
        lerp = lambda x, y: (1.0 - w) * x + w * y  # noqa: E731
        return CameraPose(lerp(a.position, b.position), lerp(a.target, b.target), _normalize(lerp(a.up, b.up)))

    def frame_time_s(self, frame_index: int) -> float:
        return self.keys[0].t_s + frame_index / self.fps


@dataclass
class RigidAnimation:
    """Moves every face whose object id is ``object_id``: translation keyframes plus a rotation about
    ``pivot`` around ``axis`` at ``angular_speed_deg_s``. Linear in time; clamped to the keys' span."""

    object_id: int
    times_s: np.ndarray  # (K,)
    translations: np.ndarray  # (K, 3)
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_speed_deg_s: float = 0.0

    def transform_at(self, t_s: float) -> np.ndarray:
        """4x4 world transform at time t (relative to the rest pose)."""
        times = np.asarray(self.times_s, np.float64)
        tr = np.asarray(self.translations, np.float64)
        translation = np.array([np.interp(t_s, times, tr[:, c]) for c in range(3)])
        angle = np.radians(self.angular_speed_deg_s * (np.clip(t_s, times[0], times[-1]) - times[0]))
        rot = _axis_angle(np.asarray(self.axis, np.float64), angle)
        pivot = np.asarray(self.pivot, np.float64)
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = pivot - rot @ pivot + translation
        return m


@dataclass
class LightAnimation:
    """Moves point light ``light_index`` through position keyframes (linear, clamped)."""

    light_index: int
    times_s: np.ndarray
    positions: np.ndarray  # (K, 3)

    def position_at(self, t_s: float) -> np.ndarray:
        p = np.asarray(self.positions, np.float64)
        return np.array([np.interp(t_s, self.times_s, p[:, c]) for c in range(3)])


@dataclass
class Scene:
    """Triangles, materials, lights, camera path and animation of one scene.

    ``positions``/``normals``/``uvs`` are per vertex; ``faces`` index them. ``face_material`` and
    ``face_object`` give each face's material and object (rigid-animation group). ``object_names[i]`` names
    object i (Mitsuba shape ids for loaded scenes). Area lights are the faces whose material is emissive.
    """

    name: str
    positions: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32 shading normals (face normals are used where a mesh had none)
    uvs: np.ndarray  # (V, 2) float32
    faces: np.ndarray  # (F, 3) int32
    face_material: np.ndarray  # (F,) int32
    face_object: np.ndarray  # (F,) int32
    object_names: list[str]
    materials: list[Material]
    point_lights: list[PointLight]
    camera: CameraPath
    object_animations: list[RigidAnimation] = field(default_factory=list)
    light_animations: list[LightAnimation] = field(default_factory=list)
    description: str = ""

    def __post_init__(self):
        self.positions = np.ascontiguousarray(self.positions, np.float32).reshape(-1, 3)
        self.normals = np.ascontiguousarray(self.normals, np.float32).reshape(-1, 3)
        self.uvs = np.ascontiguousarray(self.uvs, np.float32).reshape(-1, 2)
        self.faces = np.ascontiguousarray(self.faces, np.int32).reshape(-1, 3)
        self.face_material = np.ascontiguousarray(self.face_material, np.int32).reshape(-1)
        self.face_object = np.ascontiguousarray(self.face_object, np.int32).reshape(-1)
        self.validate()

    # --- derived quantities -------------------------------------------------------------------
    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def is_dynamic(self) -> bool:
        return bool(self.object_animations or self.light_animations)

    def triangles(self, positions: np.ndarray | None = None) -> np.ndarray:
        """(F, 3, 3) float32 vertex positions per face."""
        p = self.positions if positions is None else positions
        return p[self.faces]

    def face_normals(self, positions: np.ndarray | None = None) -> np.ndarray:
        tri = self.triangles(positions).astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)).astype(np.float32)

    def face_areas(self, positions: np.ndarray | None = None) -> np.ndarray:
        tri = self.triangles(positions).astype(np.float64)
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    def emissive_faces(self) -> np.ndarray:
        """Indices of faces with an emissive material (the triangle area lights)."""
        emissive = np.array([m.is_emissive for m in self.materials], bool)
        return np.nonzero(emissive[self.face_material])[0].astype(np.int32)

    def area_light_triangles(self, t_s: float = 0.0) -> TriangleLights:
        """Every emissive triangle as an area light at time ``t_s`` (see :class:`TriangleLights`)."""
        faces = self.emissive_faces()
        tri = self.positions_at(t_s)[self.faces[faces]].astype(np.float64)  # the emissive faces' rows only
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=-1)
        ng = cross / np.maximum(2.0 * area, 1e-300)[:, None]
        # Emission side follows the stored vertex normals (the mesh's intended front), whatever the winding.
        vn = self.normals_at(t_s)[self.faces[faces]].astype(np.float64).sum(axis=1)
        normal = np.where(np.einsum("ij,ij->i", ng, vn)[:, None] < 0, -ng, ng)
        radiance = np.stack([self.materials[m].emission for m in self.face_material[faces]]).astype(np.float64) \
            if len(faces) else np.zeros((0, 3))
        return TriangleLights(faces, tri, normal, radiance, area)

    def face_kind_codes(self) -> np.ndarray:
        """(F,) int8 shading-kind code per face (:data:`KIND_CODES`; the legacy kind "alpha" is diffuse)."""
        table = np.array([KIND_CODES[m.shading_kind] for m in self.materials], np.int8)
        return table[self.face_material]

    @property
    def has_alpha_tested(self) -> bool:
        """True when some material is alpha-tested (tracers then skip its transparent texels)."""
        return any(m.is_alpha_tested for m in self.materials)

    def face_albedo(self) -> np.ndarray:
        """(F, 3) constant albedo per face (textures are looked up separately by UV)."""
        table = np.stack([m.albedo for m in self.materials]).astype(np.float32)
        return table[self.face_material]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        # Column by column: numpy's reduction over axis 0 of (V, 3) rows is about 25x slower (10 ms on Sponza's
        # 144 k vertices, paid by every light-tracing pass of rail); min and max are exact either way.
        p = self.positions
        return (np.array([p[:, c].min() for c in range(3)], p.dtype).reshape(3),
                np.array([p[:, c].max() for c in range(3)], p.dtype).reshape(3))

    @property
    def extent(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    # --- animation ----------------------------------------------------------------------------
    def positions_at(self, t_s: float) -> np.ndarray:
        """Vertex positions at time t with every rigid animation applied."""
        return self._animated(self.positions, t_s, translate=True)

    def normals_at(self, t_s: float) -> np.ndarray:
        """Vertex normals at time t (rotated with their objects)."""
        return self._animated(self.normals, t_s, translate=False)

    def _animated(self, vectors: np.ndarray, t_s: float, translate: bool) -> np.ndarray:
        if not self.object_animations:
            return vectors
        out = vectors.astype(np.float64).copy()
        vert_object = np.full(len(out), -1, np.int64)
        vert_object[self.faces.reshape(-1)] = np.repeat(self.face_object, 3)
        for anim in self.object_animations:
            sel = vert_object == anim.object_id
            m = anim.transform_at(t_s)
            out[sel] = out[sel] @ m[:3, :3].T + (m[:3, 3] if translate else 0.0)
        return out.astype(np.float32)

    def lights_at(self, t_s: float) -> list[PointLight]:
        lights = [dataclasses.replace(lt) for lt in self.point_lights]
        for anim in self.light_animations:
            lights[anim.light_index].position = anim.position_at(t_s)
        return lights

    def moved_objects(self, t0_s: float, t1_s: float) -> list[int]:
        """Object ids whose transform differs between two times (for cheap tracer updates)."""
        return [a.object_id for a in self.object_animations
                if not np.allclose(a.transform_at(t0_s), a.transform_at(t1_s))]

    # --- checks -------------------------------------------------------------------------------
    def validate(self) -> None:
        nv, nf = len(self.positions), len(self.faces)
        if nf == 0:
            raise UserError(f"scene '{self.name}' has no triangles")
        if len(self.normals) != nv or len(self.uvs) != nv:
            raise UserError(f"scene '{self.name}': normals/uvs must have one row per vertex ({nv})")
        if self.faces.min() < 0 or self.faces.max() >= nv:
            raise UserError(f"scene '{self.name}': face indices out of range")
        if len(self.face_material) != nf or len(self.face_object) != nf:
            raise UserError(f"scene '{self.name}': face_material/face_object must have one entry per face")
        if self.face_material.max() >= len(self.materials) or self.face_material.min() < 0:
            raise UserError(f"scene '{self.name}': face material index out of range")
        if not np.isfinite(self.positions).all():
            raise UserError(f"scene '{self.name}': vertex positions contain NaN or Inf")

    def without_degenerate_faces(self, min_area: float = 0.0) -> "Scene":
        """A copy without zero-area (or NaN-area) triangles; they cannot be hit and have no normal."""
        area = self.face_areas()
        keep = np.isfinite(area) & (area > min_area)
        if keep.all():
            return self
        return dataclasses.replace(self, faces=self.faces[keep], face_material=self.face_material[keep],
                                   face_object=self.face_object[keep])

    def translated(self, offset) -> "Scene":
        """The same scene moved rigidly by ``offset`` (camera, lights and animations included)."""
        off = np.asarray(offset, np.float64).reshape(3)
        keys = [CameraKey(k.t_s, k.position + off, k.target + off, k.up) for k in self.camera.keys]
        cam = dataclasses.replace(self.camera, keys=keys)
        lights = [PointLight(lt.name, lt.position + off, lt.intensity) for lt in self.point_lights]
        objs = [dataclasses.replace(a, pivot=np.asarray(a.pivot) + off) for a in self.object_animations]
        lanims = [dataclasses.replace(a, positions=np.asarray(a.positions) + off) for a in self.light_animations]
        return dataclasses.replace(self, name=f"{self.name}+offset", positions=(self.positions + off).astype(np.float32),
                                   point_lights=lights, camera=cam, object_animations=objs, light_animations=lanims)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors (the same products and differences, so the same bits) without its general
    machinery, which costs tens of microseconds per call: camera bases are made several times per frame."""
    a0, a1, a2 = a[0], a[1], a[2]
    b0, b1, b2 = b[0], b[1], b[2]
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], np.result_type(a, b))


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n < 1e-300:
        raise UserError("zero-length direction vector")
    return v / n


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
