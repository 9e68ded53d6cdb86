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

MATERIAL_KINDS = ("diffuse", "mirror", "glass", "alpha")


@dataclass
class Material:
    """A surface description. ``kind`` marks non-diffuse surfaces for methods that handle them."""

    name: str
    albedo: np.ndarray  # (3,) linear RGB reflectance, used when there is no texture
    albedo_texture: np.ndarray | None = None  # (H, W, 3) float32 linear RGB; row 0 at v = 0 (Mitsuba bitmap layout)
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))  # (3,) radiance
    kind: str = "diffuse"

    def __post_init__(self):
        self.albedo = np.asarray(self.albedo, np.float32).reshape(3)
        self.emission = np.asarray(self.emission, np.float32).reshape(3)
        if self.kind not in MATERIAL_KINDS:
            raise UserError(f"material '{self.name}': unknown kind '{self.kind}' (choose from {MATERIAL_KINDS})")

    @property
    def is_emissive(self) -> bool:
        return bool(np.any(self.emission > 0))


@dataclass
class PointLight:
    name: str
    position: np.ndarray  # (3,) world space
    intensity: np.ndarray  # (3,) W/sr, as Mitsuba's `point` emitter

    def __post_init__(self):
        self.position = np.asarray(self.position, np.float64).reshape(3)
        self.intensity = np.asarray(self.intensity, np.float32).reshape(3)


@dataclass
class CameraPose:
    position: np.ndarray  # (3,)
    target: np.ndarray  # (3,)
    up: np.ndarray  # (3,)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward, right, up) orthonormal vectors, matching Mitsuba's look_at convention."""
        forward = _normalize(self.target - self.position)
        right = np.cross(forward, self.up)
        if np.linalg.norm(right) < 1e-12:
            raise UserError("camera 'up' vector is parallel to the viewing direction")
        right = _normalize(right)
        true_up = np.cross(right, forward)
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

    def face_albedo(self) -> np.ndarray:
        """(F, 3) constant albedo per face (textures are looked up separately by UV)."""
        table = np.stack([m.albedo for m in self.materials]).astype(np.float32)
        return table[self.face_material]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.positions.min(axis=0), self.positions.max(axis=0)

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


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n < 1e-300:
        raise UserError("zero-length direction vector")
    return v / n


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
