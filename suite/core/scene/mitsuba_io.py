"""Mitsuba 3 scenes in and out.

``load_mitsuba`` turns a Mitsuba scene (XML file or dict) into a :class:`~suite.core.scene.model.Scene`; it goes
through Mitsuba's own loader, so anything Mitsuba can read as a triangle mesh works. ``to_mitsuba_dict``
writes any Scene back as a Mitsuba dict, so the reference renderer sees exactly the geometry, materials and
lights that the methods trace.

Supported: ``diffuse`` BSDF with RGB or bitmap reflectance (also behind ``twosided``); ``point`` and
``area`` emitters; shapes Mitsuba turns into triangle meshes (obj, ply, serialized, rectangle, cube, disk is
*not* a mesh) plus ``sphere`` tessellated to ``sphere_resolution``. Anything else raises ``UserError``
naming the plugin and the shape id.
"""
from __future__ import annotations

import os

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import CameraKey, CameraPath, Material, PointLight, Scene

SUPPORTED_BSDFS = ("diffuse", "twosided")
DEFAULT_SPHERE_RESOLUTION = 32  # segments around; rings = resolution / 2


def _class_name(obj) -> str:
    for getter in ("class_name",):  # Mitsuba >= 3.6
        if hasattr(obj, getter):
            return getattr(obj, getter)()
    if hasattr(obj, "class_"):
        return obj.class_().name()
    return type(obj).__name__


def _plugin_name(obj) -> str:
    """Best-effort Mitsuba plugin name ("SmoothDiffuse" -> "diffuse") for error messages and dispatch."""
    name = _class_name(obj)
    table = {"SmoothDiffuse": "diffuse", "TwoSidedBRDF": "twosided", "PointLight": "point",
             "AreaLight": "area", "PerspectiveCamera": "perspective", "Sphere": "sphere"}
    return table.get(name, name)


def _load_mitsuba_object(source):
    from suite.core.env import mitsuba

    mi = mitsuba("llvm") if os.environ.get("SPLITBENCH_MI_VARIANT") is None else mitsuba(os.environ["SPLITBENCH_MI_VARIANT"])
    if isinstance(source, dict):
        try:
            return mi, mi.load_dict(source, optimize=False)
        except Exception as exc:  # noqa: BLE001 - Mitsuba raises RuntimeError with multi-line text
            raise UserError(f"Mitsuba could not load the scene dict: {_first_line(exc)}") from None
    path = os.fspath(source)
    if not os.path.exists(path):
        raise UserError(f"scene file '{path}' does not exist")
    try:
        return mi, mi.load_file(path, optimize=False)
    except Exception as exc:  # noqa: BLE001
        raise UserError(f"Mitsuba could not load '{path}': {_first_line(exc)}") from None


def _first_line(exc: Exception) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def _material_from_bsdf(mi, bsdf, shape_id: str) -> Material:
    plugin = _plugin_name(bsdf)
    params = mi.traverse(bsdf)
    keys = list(params.keys())
    prefix = ""
    if plugin == "twosided":
        # A two-sided diffuse is the same Lambertian on both sides; our kernels shade both sides.
        prefix = next((k.split("reflectance")[0] for k in keys if "reflectance" in k), None)
        if prefix is None:
            raise UserError(f"shape '{shape_id}': twosided BSDF must wrap a diffuse BSDF")
    elif plugin != "diffuse":
        raise UserError(f"shape '{shape_id}': unsupported BSDF plugin '{plugin}' (supported: diffuse, twosided diffuse)")
    if prefix + "reflectance.value" in keys:
        value = np.array(params[prefix + "reflectance.value"], np.float32).reshape(-1)
        albedo = np.broadcast_to(value, (3,)).astype(np.float32) if value.size in (1, 3) else value[:3]
        return Material(name=bsdf.id() or shape_id, albedo=albedo)
    if prefix + "reflectance.data" in keys:
        tex = np.array(params[prefix + "reflectance.data"], np.float32)
        if tex.ndim == 2:
            tex = tex[..., None]
        if tex.shape[-1] == 1:
            tex = np.repeat(tex, 3, axis=-1)
        tex = np.ascontiguousarray(tex[..., :3])
        return Material(name=bsdf.id() or shape_id, albedo=tex.reshape(-1, 3).mean(axis=0), albedo_texture=tex)
    raise UserError(f"shape '{shape_id}': unsupported reflectance texture (use an RGB value or a bitmap)")


def _unit_sphere(resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV sphere of radius 1: (positions, normals=positions, faces). Poles are single vertices."""
    seg = max(int(resolution), 4)
    rings = max(seg // 2, 2)
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, seg, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_pts = np.stack([st * np.cos(phi), ct * np.ones_like(phi), st * np.sin(phi)], axis=-1).reshape(-1, 3)
    pts = np.concatenate([[[0.0, 1.0, 0.0]], ring_pts, [[0.0, -1.0, 0.0]]])
    south = len(pts) - 1
    faces = []
    for j in range(seg):
        j1 = (j + 1) % seg
        faces.append((0, 1 + j1, 1 + j))  # counter-clockwise seen from outside
    for r in range(rings - 2):
        a, b = 1 + r * seg, 1 + (r + 1) * seg
        for j in range(seg):
            j1 = (j + 1) % seg
            faces.append((a + j, a + j1, b + j))
            faces.append((a + j1, b + j1, b + j))
    last = 1 + (rings - 2) * seg
    for j in range(seg):
        j1 = (j + 1) % seg
        faces.append((last + j, last + j1, south))
    return pts, pts.copy(), np.asarray(faces, np.int64)


def _mesh_arrays(mi, shape, shape_id: str, sphere_resolution: int):
    plugin = _plugin_name(shape)
    if shape.is_mesh():
        pos = np.array(shape.vertex_positions_buffer(), np.float32).reshape(-1, 3)
        faces = np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)
        if shape.has_vertex_normals():
            nrm = np.array(shape.vertex_normals_buffer(), np.float32).reshape(-1, 3)
        else:
            nrm = None
        if shape.has_vertex_texcoords():
            uv = np.array(shape.vertex_texcoords_buffer(), np.float32).reshape(-1, 2)
        else:
            uv = np.zeros((len(pos), 2), np.float32)
        return pos, nrm, uv, faces
    if plugin == "sphere":
        m = np.array(mi.traverse(shape)["to_world"].matrix, np.float64).reshape(4, 4)
        pts, nrm, faces = _unit_sphere(sphere_resolution)
        pos = pts @ m[:3, :3].T + m[:3, 3]
        n = nrm @ np.linalg.inv(m[:3, :3])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        uv = np.stack([np.arctan2(pts[:, 2], pts[:, 0]) / (2 * np.pi) + 0.5, np.arccos(np.clip(pts[:, 1], -1, 1)) / np.pi], -1)
        return pos.astype(np.float32), n.astype(np.float32), uv.astype(np.float32), faces
    raise UserError(f"shape '{shape_id}': unsupported shape plugin '{plugin}' (supported: meshes, rectangle, cube, sphere)")


def _flat_normals_split(pos, faces):
    """For meshes without normals: unshare vertices so each face gets its own flat normal."""
    tri = pos[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    new_pos = tri.reshape(-1, 3)
    new_nrm = np.repeat(n, 3, axis=0)
    new_faces = np.arange(len(new_pos)).reshape(-1, 3)
    return new_pos, new_nrm, new_faces


def default_camera_path(pose_position, pose_target, pose_up, fov_deg, resolution, duration_s: float = 2.0) -> CameraPath:
    """A gentle dolly toward the target and back: a camera path for scenes that bring only a sensor."""
    pos = np.asarray(pose_position, np.float64)
    tgt = np.asarray(pose_target, np.float64)
    toward = 0.08 * (tgt - pos)
    keys = [CameraKey(0.0, pos, tgt, pose_up), CameraKey(duration_s / 2, pos + toward, tgt, pose_up),
            CameraKey(duration_s, pos, tgt, pose_up)]
    return CameraPath(keys=keys, fov_deg=fov_deg, resolution=resolution)


def load_mitsuba(source, name: str | None = None, camera_path: CameraPath | None = None,
                 sphere_resolution: int = DEFAULT_SPHERE_RESOLUTION) -> Scene:
    """Loads a Mitsuba 3 scene (XML path or dict) through Mitsuba into a Scene.

    The sensor's pose, horizontal FOV and resolution become the default camera (a short dolly path),
    unless ``camera_path`` is given.
    """
    mi, mscene = _load_mitsuba_object(source)
    if not hasattr(mscene, "shapes"):
        raise UserError("the Mitsuba description is not a scene (no 'type': 'scene' at the top)")
    if name is None:
        name = os.path.splitext(os.path.basename(os.fspath(source)))[0] if not isinstance(source, dict) else "mitsuba_dict"

    materials: list[Material] = []
    material_index: dict[tuple, int] = {}
    positions, normals, uvs, faces, face_mat, face_obj, object_names = [], [], [], [], [], [], []
    vertex_base = 0
    for shape_index, shape in enumerate(mscene.shapes()):
        shape_id = shape.id() or f"shape{shape_index}"
        pos, nrm, uv, fc = _mesh_arrays(mi, shape, shape_id, sphere_resolution)
        if nrm is None:
            pos, nrm, fc = _flat_normals_split(pos, fc)
            uv = np.zeros((len(pos), 2), np.float32)
        mat = _material_from_bsdf(mi, shape.bsdf(), shape_id)
        if shape.is_emitter():
            em = shape.emitter()
            if _plugin_name(em) != "area":
                raise UserError(f"shape '{shape_id}': unsupported emitter plugin '{_plugin_name(em)}'")
            rad_key = next((k for k in mi.traverse(em).keys() if k.startswith("radiance")), None)
            if rad_key is None or not rad_key.endswith("value"):
                raise UserError(f"shape '{shape_id}': area emitter radiance must be a constant RGB value")
            mat.emission = np.broadcast_to(np.array(mi.traverse(em)[rad_key], np.float32).reshape(-1), (3,)).copy()
            mat.name = f"{mat.name}@{shape_id}"
        key = (mat.name, mat.albedo.tobytes(), mat.emission.tobytes(), id(mat.albedo_texture) if mat.albedo_texture is not None else 0)
        if key not in material_index:
            material_index[key] = len(materials)
            materials.append(mat)
        object_names.append(shape_id)
        positions.append(pos)
        normals.append(nrm)
        uvs.append(uv)
        faces.append(fc + vertex_base)
        face_mat.append(np.full(len(fc), material_index[key], np.int32))
        face_obj.append(np.full(len(fc), shape_index, np.int32))
        vertex_base += len(pos)
    if not faces:
        raise UserError(f"scene '{name}' has no shapes")

    lights = []
    for emitter in mscene.emitters():
        plugin = _plugin_name(emitter)
        if plugin == "area":
            continue  # handled with its shape
        if plugin != "point":
            raise UserError(f"emitter '{emitter.id() or plugin}': unsupported emitter plugin '{plugin}' (supported: point, area)")
        params = mi.traverse(emitter)
        pos_key = next(k for k in params.keys() if k.endswith("position"))
        int_key = next(k for k in params.keys() if k.startswith("intensity"))
        lights.append(PointLight(emitter.id() or f"point{len(lights)}", np.array(params[pos_key], np.float64).reshape(3),
                                 np.broadcast_to(np.array(params[int_key], np.float32).reshape(-1), (3,)).copy()))

    if camera_path is None:
        camera_path = _camera_from_sensor(mi, mscene)
    scene = Scene(name=name, positions=np.concatenate(positions), normals=np.concatenate(normals),
                  uvs=np.concatenate(uvs), faces=np.concatenate(faces), face_material=np.concatenate(face_mat),
                  face_object=np.concatenate(face_obj), object_names=object_names, materials=materials,
                  point_lights=lights, camera=camera_path,
                  description=f"Mitsuba scene loaded from {name}")
    return scene.without_degenerate_faces()


def _camera_from_sensor(mi, mscene) -> CameraPath:
    sensors = mscene.sensors()
    if not sensors:
        raise UserError("the Mitsuba scene has no sensor; give it a perspective sensor or pass a camera path")
    sensor = sensors[0]
    if _plugin_name(sensor) != "perspective":
        raise UserError(f"sensor plugin '{_plugin_name(sensor)}' is not supported (use 'perspective')")
    params = mi.traverse(sensor)
    m = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
    origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
    fov_deg = float(np.array(params["x_fov"]).reshape(-1)[0])
    size = np.array(params["film.size"]).reshape(-1)
    return default_camera_path(origin, origin + forward, up, fov_deg, (int(size[0]), int(size[1])))


# --- export -------------------------------------------------------------------------------------

def _look_at(mi, pose):
    return mi.ScalarTransform4f().look_at(origin=[float(x) for x in pose.position],
                                          target=[float(x) for x in pose.target],
                                          up=[float(x) for x in pose.up])


def sensor_dict(mi, scene: Scene, t_s: float, resolution, spp: int, rfilter: str = "box") -> dict:
    """A perspective sensor matching ``suite.core.gbuffer.camera_rays`` (horizontal FOV, pixel-centre grid).

    The box filter makes each pixel the average over its own footprint, which is what pixel-centre
    methods approximate; Mitsuba's default Gaussian would blur across pixels.
    """
    width, height = resolution
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": float(scene.camera.fov_deg),
        "near_clip": 1e-3 * max(scene.extent, 1e-3),
        "far_clip": 10.0 * max(scene.extent, 1.0) + float(np.abs(scene.positions).max()),
        "to_world": _look_at(mi, scene.camera.pose_at(t_s)),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": rfilter},
                 "pixel_format": "rgb", "component_format": "float32"},
    }


def to_mitsuba_dict(scene: Scene, t_s: float = 0.0, resolution=None, integrator=None, spp: int = 64,
                    variant: str = "llvm", rfilter: str = "box") -> dict:
    """The scene at time ``t_s`` as a Mitsuba dict: one mesh per (object, material) group.

    Surfaces are two-sided diffuse, because our shading kernels light both sides of a triangle (a closed
    room seen from inside must not depend on winding). Emissive groups carry an ``area`` emitter with the
    material's radiance; point lights become ``point`` emitters with their intensity (W/sr).
    """
    from suite.core.env import mitsuba

    mi = mitsuba(variant)
    resolution = tuple(resolution or scene.camera.resolution)
    positions = scene.positions_at(t_s)
    normals = scene.normals_at(t_s)
    out = {"type": "scene", "integrator": dict(integrator or {"type": "path", "max_depth": 8}),
           "sensor": sensor_dict(mi, scene, t_s, resolution, spp, rfilter)}
    groups = np.unique(np.stack([scene.face_object, scene.face_material], axis=1), axis=0)
    for gi, (obj, mat_id) in enumerate(groups):
        sel = np.nonzero((scene.face_object == obj) & (scene.face_material == mat_id))[0]
        verts, local_faces = np.unique(scene.faces[sel].reshape(-1), return_inverse=True)
        mat = scene.materials[int(mat_id)]
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(_bsdf_dict(mi, mat))
        if mat.is_emissive:
            props["emitter"] = mi.load_dict({"type": "area",
                                             "radiance": {"type": "rgb", "value": [float(x) for x in mat.emission]}})
        mesh = mi.Mesh(f"{scene.object_names[int(obj)]}:{mat.name}", len(verts), len(sel), props, True, True)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(np.ascontiguousarray(positions[verts], np.float32).reshape(-1))
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(normals[verts], np.float32).reshape(-1))
        params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(scene.uvs[verts], np.float32).reshape(-1))
        params["faces"] = mi.UInt32(np.ascontiguousarray(local_faces, np.uint32).reshape(-1))
        params.update()
        out[f"mesh_{gi}"] = mesh
    for i, light in enumerate(scene.lights_at(t_s)):
        out[f"point_{i}"] = {"type": "point", "position": [float(x) for x in light.position],
                             "intensity": {"type": "rgb", "value": [float(x) for x in light.intensity]}}
    return out


def _bsdf_dict(mi, mat: Material) -> dict:
    if mat.albedo_texture is not None:
        reflectance = {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(mat.albedo_texture, np.float32)),
                       "raw": True, "filter_type": "bilinear"}
    else:
        reflectance = {"type": "rgb", "value": [float(x) for x in mat.albedo]}
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}
