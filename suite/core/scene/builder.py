"""A small builder for scenes generated in code (the embedded defaults).

Geometry is accumulated primitive by primitive: quads, boxes, cylinders, emissive quads. Every primitive
has unshared vertices, so flat faces get flat shading normals, and its triangles are wound
counter-clockwise seen from the front: the geometric normal ``cross(p1 - p0, p2 - p0)`` points the same
way as the stored vertex normals. The builder checks this for every primitive it adds, so a winding slip
fails at build time instead of showing up as a black wall in a reference image.

Coordinates are y-up, right-handed, in metres; the camera's yaw 0 looks down -z (Mitsuba's default view).
UVs are planar per face and lie in [0, 1].

Example::

    b = SceneBuilder()
    wall = b.add_material("wall", albedo=(0.8, 0.5, 0.55))
    b.add_box((-3, 0, -2), (3, 2.6, 2), wall, inward=True)          # a closed room seen from inside
    b.add_point_light("ceiling", (0, 2.4, 0), intensity=5.0)
    cam = CameraScript((0, 1.6, 1.5), yaw_deg=0.0)
    cam.walk(1.0, 1.0)
    b.set_camera(cam.keys, fov_deg=60.0)
    scene = b.build("tiny_room", "one pink room")
"""
from __future__ import annotations

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import (CameraKey, CameraPath, LightAnimation, Material, PointLight, RigidAnimation,
                               Scene)

BOX_FACES = ("-x", "+x", "-y", "+y", "-z", "+z")

# Triangles below this area (m^2) are treated as a modelling mistake: they cannot be hit reliably.
_MIN_FACE_AREA_M2 = 1e-10


def _vec3(value, what: str) -> np.ndarray:
    v = np.asarray(value, np.float64)
    if v.size == 1:
        v = np.full(3, float(v))
    if v.shape != (3,) or not np.isfinite(v).all():
        raise UserError(f"{what} must be three finite numbers, got {value!r}")
    return v


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = np.linalg.norm(v)
    if n < 1e-12:
        raise UserError(f"{what} has zero length")
    return v / n


class SceneBuilder:
    """Accumulates geometry, materials, lights, a camera path and animation; ``build`` returns a Scene.

    Materials and objects are referred to by the id their ``add_material`` / ``new_object`` call returned
    or by name. Object 0, ``"static"``, holds everything added without an object.
    """

    def __init__(self):
        self._positions: list[np.ndarray] = []
        self._normals: list[np.ndarray] = []
        self._uvs: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._face_material: list[np.ndarray] = []
        self._face_object: list[np.ndarray] = []
        self._vertex_count = 0
        self._face_count = 0
        self.materials: list[Material] = []
        self.object_names: list[str] = ["static"]
        self.point_lights: list[PointLight] = []
        self.object_animations: list[RigidAnimation] = []
        self.light_animations: list[LightAnimation] = []
        self._camera: CameraPath | None = None

    # --- materials and objects ----------------------------------------------------------------
    def add_material(self, name: str, albedo, emission=0.0, kind: str = "diffuse", texture=None, **params) -> int:
        """Adds a material; ``albedo`` is linear RGB reflectance, ``emission`` radiance (W/m^2/sr), ``texture``
        an optional (H, W, 3) linear RGB albedo map (v = 0 at the bottom row). ``params`` are further
        :class:`~suite.core.scene.model.Material` fields (``specular_reflectance``, ``int_ior``, ``roughness``,
        ``distribution``, ``twosided``, ``opacity_texture``, ...). Returns its id."""
        if any(m.name == name for m in self.materials):
            raise UserError(f"material '{name}' is defined twice")
        tex = None if texture is None else np.ascontiguousarray(texture, np.float32)
        if tex is not None and (tex.ndim != 3 or tex.shape[2] != 3):
            raise UserError(f"material '{name}': texture must be an (H, W, 3) array, got shape {tex.shape}")
        self.materials.append(Material(name=name, albedo=_vec3(albedo, f"material '{name}' albedo"),
                                       albedo_texture=tex, emission=_vec3(emission, f"material '{name}' emission"),
                                       kind=kind, **params))
        return len(self.materials) - 1

    def new_object(self, name: str) -> int:
        """A new rigid-animation group; returns its object id."""
        if name in self.object_names:
            raise UserError(f"object '{name}' is defined twice")
        self.object_names.append(name)
        return len(self.object_names) - 1

    def _material_id(self, material) -> int:
        if isinstance(material, str):
            for i, m in enumerate(self.materials):
                if m.name == material:
                    return i
            raise UserError(f"unknown material '{material}'")
        mid = int(material)
        if not 0 <= mid < len(self.materials):
            raise UserError(f"material id {mid} is out of range (have {len(self.materials)})")
        return mid

    def _object_id(self, obj) -> int:
        if obj is None:
            return 0
        if isinstance(obj, str):
            if obj not in self.object_names:
                raise UserError(f"unknown object '{obj}'")
            return self.object_names.index(obj)
        oid = int(obj)
        if not 0 <= oid < len(self.object_names):
            raise UserError(f"object id {oid} is out of range (have {len(self.object_names)})")
        return oid

    # --- geometry -----------------------------------------------------------------------------
    def add_mesh(self, positions, normals, uvs, faces, material, object=None) -> np.ndarray:
        """Adds a triangle mesh (local vertex indices). Returns the global ids of its faces.

        Raises if a triangle is degenerate or wound against its vertex normals."""
        pos = np.asarray(positions, np.float64).reshape(-1, 3)
        nrm = np.asarray(normals, np.float64).reshape(-1, 3)
        uv = np.asarray(uvs, np.float64).reshape(-1, 2)
        fc = np.asarray(faces, np.int64).reshape(-1, 3)
        if not (len(pos) == len(nrm) == len(uv)) or fc.min() < 0 or fc.max() >= len(pos):
            raise UserError("add_mesh: positions, normals and uvs must match and faces must index them")
        tri = pos[fc]
        geo = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(geo, axis=1)
        if (area <= _MIN_FACE_AREA_M2).any():
            raise UserError(f"add_mesh: {int((area <= _MIN_FACE_AREA_M2).sum())} degenerate triangle(s)")
        if (np.einsum("fk,fvk->fv", geo, nrm[fc]) <= 0).any():
            raise UserError("add_mesh: a triangle is wound against its vertex normals")
        nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        mid, oid = self._material_id(material), self._object_id(object)
        self._positions.append(pos)
        self._normals.append(nrm)
        self._uvs.append(uv)
        self._faces.append(fc + self._vertex_count)
        self._face_material.append(np.full(len(fc), mid, np.int32))
        self._face_object.append(np.full(len(fc), oid, np.int32))
        ids = np.arange(self._face_count, self._face_count + len(fc))
        self._vertex_count += len(pos)
        self._face_count += len(fc)
        return ids

    def add_quad(self, quad, material, object=None) -> np.ndarray:
        """A planar quad: either 4 corners counter-clockwise seen from the front, or a tuple
        ``(center, u_half, v_half)`` whose front normal is ``cross(u_half, v_half)``. Two triangles."""
        q = [np.asarray(x, np.float64).reshape(3) for x in quad]
        if len(q) == 3:
            c, u, v = q
            corners = np.array([c - u - v, c + u - v, c + u + v, c - u + v])
        elif len(q) == 4:
            corners = np.array(q)
        else:
            raise UserError("add_quad takes 4 corners or (center, u_half, v_half)")
        return self.add_quads(corners[None], material, object)

    def add_quads(self, corners, material, object=None, facing=None) -> np.ndarray:
        """Many planar quads at once: ``corners`` (Q, 4, 3), each counter-clockwise seen from its front.
        With ``facing`` ((3,) or (Q, 3)), quads whose front points away from it are reversed instead."""
        corners = np.asarray(corners, np.float64).reshape(-1, 4, 3)
        normal = np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 1])
        if facing is not None:
            flip = np.einsum("qk,qk->q", normal, np.broadcast_to(np.asarray(facing, np.float64), normal.shape)) < 0
            corners = np.where(flip[:, None, None], corners[:, ::-1], corners)
            normal = np.where(flip[:, None], -normal, normal)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        if (length < 1e-12).any():
            raise UserError("add_quads: a quad has zero area")
        count = len(corners)
        base = 4 * np.arange(count)[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
        uvs = np.tile([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], (count, 1))
        return self.add_mesh(corners.reshape(-1, 3), np.repeat(normal / length, 4, axis=0), uvs, faces,
                             material, object)

    def add_box(self, lo, hi, material, object=None, open_faces=(), inward: bool = False) -> np.ndarray:
        """An axis-aligned box with flat faces and outward normals (``inward=True``: a closed room seen
        from inside). ``open_faces`` names faces to leave out, from ``BOX_FACES`` (e.g. ``"+y"``)."""
        lo, hi = _vec3(lo, "box min"), _vec3(hi, "box max")
        if (hi <= lo).any():
            raise UserError(f"box max {hi.tolist()} must exceed box min {lo.tolist()} on every axis")
        unknown = set(open_faces) - set(BOX_FACES)
        if unknown:
            raise UserError(f"unknown box face(s) {sorted(unknown)} (choose from {BOX_FACES})")
        center, half = (lo + hi) / 2, (hi - lo) / 2
        ids = []
        for axis in range(3):
            b, c = (axis + 1) % 3, (axis + 2) % 3
            for sign, label in ((-1.0, "-"), (1.0, "+")):
                if f"{label}{'xyz'[axis]}" in open_faces:
                    continue
                face_center = center.copy()
                face_center[axis] += sign * half[axis]
                u, v = np.zeros(3), np.zeros(3)
                u[b], v[c] = half[b], half[c]  # cross(e_b, e_c) = +e_axis
                facing = sign * (-1.0 if inward else 1.0)
                if facing < 0:
                    u, v = v, u
                ids.append(self.add_quad((face_center, u, v), material, object))
        return np.concatenate(ids) if ids else np.zeros(0, np.int64)

    def add_cylinder(self, center_base, radius: float, height: float, segments: int, material,
                     object=None, caps=(True, True)) -> np.ndarray:
        """A vertical (+y) cylinder, e.g. a column. Smooth radial normals on the side, flat caps;
        ``caps=(bottom, top)`` leaves out caps that rest on other geometry."""
        base = _vec3(center_base, "cylinder base")
        if radius <= 0 or height <= 0 or segments < 3:
            raise UserError(f"cylinder needs radius > 0, height > 0 and >= 3 segments "
                            f"(got {radius}, {height}, {segments})")
        # Angles run so that (cos a, 0, -sin a) turns counter-clockwise seen from above (+y).
        angle = np.linspace(0.0, 2.0 * np.pi, segments + 1)
        radial = np.stack([np.cos(angle), np.zeros_like(angle), -np.sin(angle)], axis=1)
        bottom = base + radius * radial
        top = bottom + np.array([0.0, height, 0.0])
        pos = np.concatenate([bottom, top])
        nrm = np.concatenate([radial, radial])
        s = np.linspace(0.0, 1.0, segments + 1)
        uv = np.concatenate([np.stack([s, np.zeros_like(s)], 1), np.stack([s, np.ones_like(s)], 1)])
        n1 = segments + 1
        i = np.arange(segments)
        faces = np.concatenate([np.stack([i, i + 1, n1 + i + 1], 1), np.stack([i, n1 + i + 1, n1 + i], 1)])
        ids = [self.add_mesh(pos, nrm, uv, faces, material, object)]
        for is_top, wanted in ((False, caps[0]), (True, caps[1])):
            if not wanted:
                continue
            ring = (top if is_top else bottom)[:-1]
            centre = base + np.array([0.0, height if is_top else 0.0, 0.0])
            cap_pos = np.concatenate([centre[None], ring])
            up = np.array([0.0, 1.0 if is_top else -1.0, 0.0])
            cap_uv = 0.5 + 0.5 * np.concatenate([[[0.0, 0.0]], radial[:-1][:, [0, 2]]])
            j = np.arange(segments)
            fan = np.stack([np.zeros(segments, np.int64), 1 + j, 1 + (j + 1) % segments], 1)
            if not is_top:
                fan = fan[:, [0, 2, 1]]
            ids.append(self.add_mesh(cap_pos, np.repeat(up[None], len(cap_pos), 0), cap_uv, fan, material, object))
        return np.concatenate(ids)

    def add_sphere(self, center, radius: float, segments: int, material, object=None) -> np.ndarray:
        """A UV sphere with smooth outward normals: ``segments`` around, ``segments / 2`` rings, single-vertex
        poles; u runs around (from +x toward +z), v from the north (+y) pole."""
        c = _vec3(center, "sphere center")
        if radius <= 0 or segments < 4:
            raise UserError(f"sphere needs radius > 0 and >= 4 segments (got {radius}, {segments})")
        rings = max(segments // 2, 2)
        theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
        phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
        st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
        ring = np.stack([st * np.cos(phi), ct * np.ones_like(phi), st * np.sin(phi)], axis=-1).reshape(-1, 3)
        unit = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]])
        south = len(unit) - 1
        faces = [(0, 1 + (j + 1) % segments, 1 + j) for j in range(segments)]
        for r in range(rings - 2):
            a, b = 1 + r * segments, 1 + (r + 1) * segments
            for j in range(segments):
                j1 = (j + 1) % segments
                faces += [(a + j, a + j1, b + j), (a + j1, b + j1, b + j)]
        last = 1 + (rings - 2) * segments
        faces += [(last + j, last + (j + 1) % segments, south) for j in range(segments)]
        uv = np.stack([np.arctan2(unit[:, 2], unit[:, 0]) / (2 * np.pi) % 1.0,
                       np.arccos(np.clip(unit[:, 1], -1, 1)) / np.pi], -1)
        return self.add_mesh(c + radius * unit, unit, uv, np.asarray(faces), material, object)

    # --- lights -------------------------------------------------------------------------------
    def add_point_light(self, name: str, position, intensity) -> int:
        """A point light; ``intensity`` in W/sr (scalar or RGB), as Mitsuba's ``point``. Returns its index."""
        if any(lt.name == name for lt in self.point_lights):
            raise UserError(f"point light '{name}' is defined twice")
        inten = _vec3(intensity, f"light '{name}' intensity")
        if (inten < 0).any():
            raise UserError(f"light '{name}' has a negative intensity")
        self.point_lights.append(PointLight(name, _vec3(position, f"light '{name}' position"), inten))
        return len(self.point_lights) - 1

    def add_area_light_quad(self, name: str, center, size_m, facing, radiance, object=None,
                            albedo=0.0) -> np.ndarray:
        """An emissive rectangle of ``size_m = (width, height)`` metres centred at ``center`` that emits
        ``radiance`` (W/m^2/sr) toward ``facing`` (its front normal). Gets its own material ``name``."""
        n = _unit(_vec3(facing, f"area light '{name}' facing"), f"area light '{name}' facing")
        ref = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        t1 = _unit(np.cross(ref, n), "area light tangent")
        t2 = np.cross(n, t1)  # cross(t1, t2) = n
        width, height = (float(x) for x in size_m)
        mat = self.add_material(name, albedo=albedo, emission=radiance)
        if not self.materials[mat].is_emissive:
            raise UserError(f"area light '{name}' needs a positive radiance")
        return self.add_quad((_vec3(center, f"area light '{name}' center"), t1 * width / 2, t2 * height / 2),
                             mat, object)

    # --- camera and animation -----------------------------------------------------------------
    def set_camera(self, keys, fov_deg: float = 60.0, resolution=(320, 180), fps: float = 30.0) -> None:
        """The default camera path: keyframes, horizontal FOV, (width, height) and frame rate."""
        self._camera = CameraPath(keys=list(keys), fov_deg=float(fov_deg),
                                  resolution=(int(resolution[0]), int(resolution[1])), fps=float(fps))

    def add_object_animation(self, object, times_s, translations, axis=(0.0, 1.0, 0.0),
                             pivot=(0.0, 0.0, 0.0), angular_speed_deg_s: float = 0.0) -> None:
        """Rigid motion of one object: translation keyframes (linear) plus a steady rotation about
        ``axis`` through ``pivot``."""
        oid = self._object_id(object)
        if oid == 0:
            raise UserError("the 'static' object cannot be animated; use new_object()")
        times = np.asarray(times_s, np.float64).reshape(-1)
        tr = np.asarray(translations, np.float64).reshape(-1, 3)
        if len(times) != len(tr) or len(times) == 0 or (np.diff(times) <= 0).any():
            raise UserError(f"object '{self.object_names[oid]}': animation needs increasing times, "
                            "one translation each")
        self.object_animations.append(RigidAnimation(oid, times, tr, np.asarray(axis, np.float64),
                                                     np.asarray(pivot, np.float64), float(angular_speed_deg_s)))

    def add_light_animation(self, light, times_s, positions) -> None:
        """Moves point light ``light`` (index or name) through position keyframes (linear)."""
        index = next((i for i, lt in enumerate(self.point_lights) if lt.name == light), None) \
            if isinstance(light, str) else int(light)
        if index is None or not 0 <= index < len(self.point_lights):
            raise UserError(f"unknown point light {light!r}")
        times = np.asarray(times_s, np.float64).reshape(-1)
        pos = np.asarray(positions, np.float64).reshape(-1, 3)
        if len(times) != len(pos) or len(times) == 0 or (np.diff(times) <= 0).any():
            raise UserError(f"light {light!r}: animation needs increasing times, one position each")
        self.light_animations.append(LightAnimation(index, times, pos))

    # --- result -------------------------------------------------------------------------------
    def build(self, name: str, description: str = "") -> Scene:
        if not self._faces:
            raise UserError(f"scene '{name}' has no geometry")
        if self._camera is None:
            raise UserError(f"scene '{name}' has no camera; call set_camera()")
        return Scene(name=name, positions=np.concatenate(self._positions).astype(np.float32),
                     normals=np.concatenate(self._normals).astype(np.float32),
                     uvs=np.concatenate(self._uvs).astype(np.float32),
                     faces=np.concatenate(self._faces).astype(np.int32),
                     face_material=np.concatenate(self._face_material),
                     face_object=np.concatenate(self._face_object),
                     object_names=list(self.object_names), materials=list(self.materials),
                     point_lights=list(self.point_lights), camera=self._camera,
                     object_animations=list(self.object_animations),
                     light_animations=list(self.light_animations), description=description)


class CameraScript:
    """Writes camera keyframes as a walk through moves: hold, walk (forward or backward), strafe, turn.

    The view direction is kept as yaw (degrees, counter-clockwise seen from above, 0 = looking down -z)
    and pitch (degrees, positive = up); each key's target is one metre ahead of its position. Turns are
    split into keys at most ``max_step_deg`` apart, because the camera path interpolates targets linearly
    and a single key pair would sweep the view at an uneven rate.
    """

    def __init__(self, position, yaw_deg: float = 0.0, pitch_deg: float = 0.0, t_s: float = 0.0,
                 max_step_deg: float = 10.0):
        self.position = _vec3(position, "camera position")
        self.yaw_deg = float(yaw_deg)
        self.pitch_deg = float(pitch_deg)
        self.t_s = float(t_s)
        self.max_step_deg = float(max_step_deg)
        self.keys: list[CameraKey] = []
        self._key()

    def forward(self) -> np.ndarray:
        yaw, pitch = np.radians(self.yaw_deg), np.radians(self.pitch_deg)
        return np.array([-np.sin(yaw) * np.cos(pitch), np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])

    def heading(self) -> np.ndarray:
        """The horizontal walking direction."""
        yaw = np.radians(self.yaw_deg)
        return np.array([-np.sin(yaw), 0.0, -np.cos(yaw)])

    def _key(self) -> None:
        self.keys.append(CameraKey(self.t_s, self.position.copy(), self.position + self.forward()))

    def hold(self, duration_s: float) -> "CameraScript":
        self.t_s += duration_s
        self._key()
        return self

    def walk(self, distance_m: float, duration_s: float, strafe_m: float = 0.0, rise_m: float = 0.0) -> "CameraScript":
        """Moves along the heading (negative distance = backward, view unchanged), optionally sideways
        (positive strafe = to the right) and up."""
        right = np.cross(self.heading(), [0.0, 1.0, 0.0])
        self.position = self.position + distance_m * self.heading() + strafe_m * right + np.array([0.0, rise_m, 0.0])
        self.t_s += duration_s
        self._key()
        return self

    def turn(self, yaw_deg: float, duration_s: float, pitch_deg: float = 0.0, walk_m: float = 0.0) -> "CameraScript":
        """Turns the view by ``yaw_deg`` (positive = left) and ``pitch_deg``, optionally while walking."""
        steps = max(1, int(np.ceil(max(abs(yaw_deg), abs(pitch_deg)) / self.max_step_deg)))
        for _ in range(steps):
            self.position = self.position + (walk_m / steps) * self.heading()
            self.yaw_deg += yaw_deg / steps
            self.pitch_deg += pitch_deg / steps
            self.t_s += duration_s / steps
            self._key()
        return self

    def play(self, moves, where: str) -> "CameraScript":
        """Applies moves written as data (TOML sidecars, map camera scripts): each a table with ``hold = s``, or
        ``turn = deg, s = ..`` (optional ``pitch``, ``walk``), or ``walk = m, s = ..`` (optional ``strafe``,
        ``rise``). A malformed move is a UserError naming ``where`` and the move's index."""
        for i, move in enumerate(moves):
            try:
                if "hold" in move:
                    self.hold(float(move["hold"]))
                elif "turn" in move:
                    self.turn(float(move["turn"]), float(move["s"]), pitch_deg=float(move.get("pitch", 0.0)),
                              walk_m=float(move.get("walk", 0.0)))
                elif "walk" in move:
                    self.walk(float(move["walk"]), float(move["s"]), strafe_m=float(move.get("strafe", 0.0)),
                              rise_m=float(move.get("rise", 0.0)))
                else:
                    raise KeyError("walk, turn or hold")
            except (KeyError, TypeError, ValueError) as exc:
                raise UserError(f"{where} move {i} {move!r} is malformed ({exc})") from None
        return self
