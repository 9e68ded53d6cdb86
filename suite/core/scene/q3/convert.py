"""A parsed Quake III map -> the suite's scene model (:class:`Q3Scene`).

Geometry: the faces of the world (model 0) and of the brush entities that the game draws (every ``*N`` model an
entity refers to, except ``trigger_*``), the latter at rest and moved by the entity's ``origin``; planar faces
(type 1) and triangle meshes (type 3) through their meshverts, Bezier patches (type 2) tessellated
(:mod:`.patches`), billboards (type 4) skipped. Coordinates: Quake units are inches with z up; a point
``(x, y, z)`` becomes ``unit_m * (x, z, -y)`` (y up, right-handed; ``unit_m`` = 0.0254 by default) for
geometry, lights and camera alike. Triangles are wound counter-clockwise around their vertex normals (the
visible side is the front). Zero-area triangles are dropped and counted.

Surfaces by shader (:mod:`.shaders`, plus the compiled surface flags and contents in the BSP's shader lump):

======================  ========================================================  ======================
what                    rule                                                      result
======================  ========================================================  ======================
sky                     ``surfaceparm sky`` / SURF_SKY or ``skyparms``            excluded, counted; its
                                                                                  light: sun / sky-dome
                                                                                  point lights (lights.py)
nodraw                  ``surfaceparm nodraw`` / SURF_NODRAW                      excluded, counted
fog volume              ``surfaceparm fog`` / CONTENTS_FOG and no stage to draw    excluded, counted
sprite                  ``deformVertexes autosprite(2)`` (faces the viewer)        excluded, counted
decal                   ``polygonOffset`` (lies on another surface)                excluded, counted
additive effect         first stage's destination factor GL_ONE (``add``, ...)     excluded, counted
mirror / portal         ``portal`` / ``sort portal`` / ``surfaceparm portal``      kept, kind ``mirror``
translucent             first stage ``blend`` / ``filter`` (or another non-        kept, kind ``glass``
                        additive blend with ``surfaceparm trans``)                (IOR 1.333 if liquid)
alpha-tested            a stage with ``alphaFunc GT0/LT128/GE128``                 kept, ``diffuse`` with
                                                                                  an ``opacity_texture``
everything else         opaque                                                    kept, kind ``diffuse``
======================  ========================================================  ======================

A material per shader: the diffuse stage's texture (``ShaderInfo.diffuse_image``) decoded to linear RGB, its
mean as the constant albedo; a texture that is not found becomes the flat colour ``MISSING_TEXTURE_ALBEDO``
(and is counted by name). Surface lights (``q3map_surfacelight``) get an emission (see :mod:`.lights`).
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import Material, PointLight
from suite.core.scene.q3.bsp import (MST_FLARE, MST_PATCH, MST_PLANAR, MST_TRIANGLE_SOUP, BspFile, gather_ranges,
                                     parse_bsp)
from suite.core.scene.q3.lights import (SUN_DISTANCE_M, convert_light_entities, display_color_to_linear,
                                        sky_dome_lights, sun_light, surface_radiance)
from suite.core.scene.q3.patches import DEFAULT_LEVEL, tessellate_patch
from suite.core.scene.q3.shaders import ShaderInfo, ShaderLibrary
from suite.core.scene.q3.textures import TextureLoader, decode_srgb8
from suite.core.scene.q3.visibility import Q3_TO_SCENE, Q3Visibility, triangle_clusters

UNIT_M = 0.0254  # one Quake unit is an inch
MISSING_TEXTURE_ALBEDO = (0.5, 0.5, 0.5)  # linear RGB of a surface whose texture is not found
MAX_TEXTURE_SIZE = 256
MIN_TRIANGLE_AREA_M2 = 1e-10
SPAWN_CLASSES = ("info_player_deathmatch", "info_player_start", "team_CTF_redspawn", "team_CTF_bluespawn",
                 "team_CTF_redplayer", "team_CTF_blueplayer")

# Compiled flags in the BSP shader lump (Quake III surfaceflags.h).
SURF_SKY, SURF_NODRAW, SURF_NOLIGHTMAP, SURF_NONSOLID = 0x4, 0x80, 0x400, 0x4000
CONTENTS_LAVA, CONTENTS_SLIME, CONTENTS_WATER, CONTENTS_FOG = 0x8, 0x10, 0x20, 0x40
CONTENTS_TRANSLUCENT = 0x20000000

# Per-face flags (Q3Info.face_flags).
FLAG_NAMES = ("sky", "nodraw", "nonsolid", "trans", "nolightmap", "alpha_test", "blend_add", "blend_blend",
              "blend_filter", "mirror", "glass", "surfacelight", "fog", "liquid", "decal", "sprite", "twosided",
              "billboard", "excluded")
FLAGS = {name: 1 << i for i, name in enumerate(FLAG_NAMES)}
EXCLUDE_ORDER = ("sky", "nodraw", "fog", "sprite", "decal", "blend_add")


@dataclass
class ConvertOptions:
    unit_m: float = UNIT_M
    patch_level: int = DEFAULT_LEVEL
    light_scale: float = 1.0
    max_texture_size: int = MAX_TEXTURE_SIZE

    def key(self) -> str:
        return f"u{self.unit_m!r}-p{self.patch_level}-l{self.light_scale!r}-t{self.max_texture_size}"


@dataclass
class ShaderRecord:
    """What the converter decided for one shader of the map."""

    name: str
    flags: int
    excluded: str | None  # reason, or None when drawn
    kind: str
    blend_mode: str
    texture: str | None  # image path found in the archives (None: missing -> flat colour)
    requested_texture: str
    surfacelight: float
    light_color: list[float]
    emission: list[float]
    alpha_func: str | None
    source: str


@dataclass
class Q3Info:
    """Everything Quake-specific a method or test may want besides the scene model itself."""

    map_name: str
    source: str  # "pak.pk3:maps/name.bsp" or a file path
    bsp_sha256: str
    message: str
    options: dict
    shaders: list[dict]
    lights: list[dict]  # converted light entities (see lights.Q3Light.record)
    counts: dict
    face_type: np.ndarray  # (faces,) BSP face type
    face_shader: np.ndarray  # (faces,) BSP shader index
    face_model: np.ndarray  # (faces,) model index, -1 for faces of no drawn model
    face_flags: np.ndarray  # (faces,) FLAGS bits
    triangle_face: np.ndarray  # (T,) BSP face of each scene triangle
    alpha_masks: dict = field(default_factory=dict)  # material index -> (H, W) uint8 opacity (8-bit form of its
    #                                                  Material.opacity_texture)
    spawn_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (S, 4): x, y, z (scene), Quake
    #                                                                    angle (deg) of counts["spawn_class"]

    ARRAYS = ("face_type", "face_shader", "face_model", "face_flags", "triangle_face", "spawn_points")


def _shader_flags(info: ShaderInfo, surface_flags: int, contents: int) -> int:
    p = info.surfaceparms
    f = 0
    if "sky" in p or surface_flags & SURF_SKY or info.sky:
        f |= FLAGS["sky"]
    if "nodraw" in p or surface_flags & SURF_NODRAW:
        f |= FLAGS["nodraw"]
    if "nonsolid" in p or surface_flags & SURF_NONSOLID:
        f |= FLAGS["nonsolid"]
    if "trans" in p or contents & CONTENTS_TRANSLUCENT:
        f |= FLAGS["trans"]
    if "nolightmap" in p or surface_flags & SURF_NOLIGHTMAP:
        f |= FLAGS["nolightmap"]
    if ("fog" in p or contents & CONTENTS_FOG) and info.first_stage is None:
        f |= FLAGS["fog"]  # a fog volume's surface draws nothing but fog; one with stages (lava) is drawn
    if p & {"water", "lava", "slime"} or contents & (CONTENTS_WATER | CONTENTS_LAVA | CONTENTS_SLIME):
        f |= FLAGS["liquid"]
    if info.alpha_stage is not None:
        f |= FLAGS["alpha_test"]
    mode = info.blend_mode
    if mode == "add":
        f |= FLAGS["blend_add"]
    elif mode == "blend":
        f |= FLAGS["blend_blend"]
    elif mode == "filter":
        f |= FLAGS["blend_filter"]
    if info.portal or "portal" in p:
        f |= FLAGS["mirror"]
    if info.polygon_offset:
        f |= FLAGS["decal"]
    if info.autosprite:
        f |= FLAGS["sprite"]
    if info.cull in ("none", "back"):
        f |= FLAGS["twosided"]
    if info.surfacelight > 0:
        f |= FLAGS["surfacelight"]
    if not f & (FLAGS["mirror"] | FLAGS["blend_add"]) and (
            mode in ("blend", "filter") or (f & FLAGS["trans"] and mode == "other")):
        f |= FLAGS["glass"]
    return f


def _excluded_reason(flags: int) -> str | None:
    for name in EXCLUDE_ORDER:
        if flags & FLAGS[name]:
            return {"blend_add": "additive"}.get(name, name)
    return None


def _kind(flags: int) -> str:
    """The Material kind: mirror, glass or diffuse (alpha-tested surfaces are diffuse with an opacity map)."""
    if flags & FLAGS["mirror"]:
        return "mirror"
    if flags & FLAGS["glass"]:
        return "glass"
    return "diffuse"


# alphaFunc -> (use 1 - alpha, threshold) for the model's test "exists where opacity >= threshold" on 8-bit
# alpha a: GE128 is a >= 128, GT0 is a >= 1, LT128 is 255 - a >= 128 (tr_shade.c / GLS_ATEST_* semantics).
ALPHA_TESTS = {"ge128": (False, 128.0 / 255.0), "gt0": (False, 0.5 / 255.0), "lt128": (True, 128.0 / 255.0)}
IOR_WATER = 1.333


def _light_color(info: ShaderInfo, textures: TextureLoader) -> tuple[np.ndarray, str]:
    """q3map2's surface-light colour: q3map_lightRGB, else the normalised mean of the light image (light image,
    editor image, shader name, implicit map in that order), else white."""
    if info.light_rgb is not None:
        return display_color_to_linear(info.light_rgb), "q3map_lightRGB"
    for name in info.light_image_candidates():
        avg = textures.average_srgb8(name)
        if avg is not None:
            return display_color_to_linear(avg), name
    return np.ones(3), "white (no light image found)"


def _entity_models(entities) -> dict[int, dict]:
    """Model index -> the entity drawing it (models referred to as ``"model" "*N"``)."""
    out = {}
    for e in entities:
        m = e.get("model", "")
        if m.startswith("*"):
            try:
                out[int(m[1:])] = e
            except ValueError:
                continue
    return out


def _vec(text, default=(0.0, 0.0, 0.0)):
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        v = []
    return np.array(v[:3] if len(v) >= 3 else default, np.float64)


def build(bsp_bytes: bytes, map_name: str, source: str, shaders: ShaderLibrary, textures: TextureLoader,
          options: ConvertOptions):
    """Returns ``(scene_parts, info, timings)``: the arrays and objects of a Q3Scene (without its camera)."""
    t0 = time.perf_counter()
    timings = {}
    b: BspFile = parse_bsp(bsp_bytes, source)
    timings["parse_s"] = time.perf_counter() - t0
    n_faces = len(b.faces)
    faces = b.faces
    names = b.shader_names

    # --- shaders -----------------------------------------------------------------------------------
    shader_infos = [shaders.get(n) for n in names]
    shader_flags = np.array([_shader_flags(si, int(fl), int(ct)) for si, fl, ct in
                             zip(shader_infos, b.shaders["flags"], b.shaders["contents"])], np.int64)

    # --- which faces are drawn ---------------------------------------------------------------------
    face_model = np.full(n_faces, -1, np.int64)
    model_offset = np.zeros((len(b.models), 3))
    drawn_models = {0: {"classname": "worldspawn"}}
    for m, e in _entity_models(b.entities).items():
        if 0 < m < len(b.models) and not e.get("classname", "").lower().startswith("trigger_"):
            drawn_models[m] = e
            if "origin" in e:  # q3map2 stores such a model's vertexes relative to its origin (SetEntityOrigins)
                model_offset[m] = _vec(e["origin"])
    object_names = ["static"]
    model_object = np.zeros(len(b.models), np.int64)
    for m in sorted(drawn_models):
        lo, n = int(b.models["face"][m]), int(b.models["n_faces"][m])
        face_model[lo:lo + n] = m
        if m:
            model_object[m] = len(object_names)
            object_names.append(f"*{m} {drawn_models[m].get('classname', '?')}")

    ftype = faces["type"].astype(np.int64)
    fflags = shader_flags[faces["shader"]]
    fflags = np.where(ftype == MST_FLARE, fflags | FLAGS["billboard"], fflags)
    reason_by_shader = np.array([_excluded_reason(int(f)) or "" for f in shader_flags] + [""], object)
    # A world face that no leaf with a cluster lists is never drawn by the engine (R_RecursiveWorldNode walks
    # leaf surface lists): geometry outside the level.
    cluster_leaf = b.leafs["cluster"] >= 0
    listed = np.zeros(n_faces, bool)
    listed[gather_ranges(b.leaffaces, b.leafs["leafface"][cluster_leaf], b.leafs["n_leaffaces"][cluster_leaf])] = True
    # One reason per skipped face, first match wins.
    reason = np.full(n_faces, "", object)
    rules = [("billboard (type 4)", ftype == MST_FLARE),
             ("unknown face type", ~np.isin(ftype, [MST_PLANAR, MST_PATCH, MST_TRIANGLE_SOUP, MST_FLARE])),
             ("not in a drawn model", face_model < 0)]
    shader_reason = reason_by_shader[faces["shader"]]
    rules += [(r, shader_reason == r) for r in ("sky", "nodraw", "fog", "sprite", "decal", "additive")]
    rules += [("world face in no leaf", (face_model == 0) & ~listed)]
    for name, sel in rules:
        reason = np.where((reason == "") & sel, name, reason)
    use = reason == ""
    fflags = np.where(use, fflags, fflags | FLAGS["excluded"])

    counts: dict = {"faces": int(n_faces), "faces_by_type": b.face_type_counts(),
                    "vertexes": int(len(b.vertexes)), "meshverts": int(len(b.meshverts)),
                    "leafs": int(len(b.leafs)), "clusters": int(b.n_clusters), "entities": int(len(b.entities)),
                    "visdata_bytes": int(b.lump_bytes["visdata"]), "models": int(len(b.models)),
                    "drawn_models": len(drawn_models), "shaders": int(len(names)),
                    "faces_skipped": {name: int((reason == name).sum()) for name, _ in rules},
                    "faces_drawn": int(use.sum())}

    # --- triangles: planar and meshes through meshverts --------------------------------------------
    t1 = time.perf_counter()
    vx = b.vertexes
    base_pos = vx["position"].astype(np.float64)
    # Brush models with an origin: move their vertexes (each vertex belongs to one face).
    if np.any(model_offset != 0):
        vert_model = np.full(len(vx), -1, np.int64)
        owner = np.repeat(np.arange(n_faces), faces["n_vertexes"])
        vert_model[gather_ranges(np.arange(len(vx)), faces["vertex"], faces["n_vertexes"])] = face_model[owner]
        moved = vert_model > 0
        base_pos[moved] += model_offset[vert_model[moved]]
    attrs = np.concatenate([base_pos, vx["texcoord"].astype(np.float64), vx["normal"].astype(np.float64)], axis=1)

    soup = use & ((ftype == MST_PLANAR) | (ftype == MST_TRIANGLE_SOUP))
    with_mv = soup & (faces["n_meshverts"] > 0)
    fan = soup & (faces["n_meshverts"] == 0) & (faces["n_vertexes"] >= 3)
    ids = np.nonzero(with_mv)[0]
    mv = gather_ranges(b.meshverts, faces["meshvert"][ids], faces["n_meshverts"][ids]).astype(np.int64)
    mv += np.repeat(faces["vertex"][ids].astype(np.int64), faces["n_meshverts"][ids])
    tri_list = [mv.reshape(-1, 3)]
    tri_face_list = [np.repeat(ids, faces["n_meshverts"][ids] // 3)]
    fan_ids = np.nonzero(fan)[0]
    if len(fan_ids):  # no meshverts: a convex polygon, fanned from its first vertex
        k = faces["n_vertexes"][fan_ids].astype(np.int64) - 2
        first = np.repeat(faces["vertex"][fan_ids].astype(np.int64), k)
        j = np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k)
        tri_list.append(np.stack([first, first + j + 1, first + j + 2], axis=1))
        tri_face_list.append(np.repeat(fan_ids, k))
    counts["planar_faces_fanned"] = int(len(fan_ids))
    soup_tris = sum(len(t) for t in tri_list)

    # --- patches ------------------------------------------------------------------------------------
    vert_blocks = [attrs]
    n_vert = len(attrs)
    patch_ids = np.nonzero(use & (ftype == MST_PATCH))[0]
    patch_tris = 0
    for f in patch_ids:
        w, h = (int(x) for x in faces["size"][f])
        v0, nv = int(faces["vertex"][f]), int(faces["n_vertexes"][f])
        grid, tris = tessellate_patch(attrs[v0:v0 + nv], w, h, options.patch_level)
        vert_blocks.append(grid)
        tri_list.append(tris + n_vert)
        tri_face_list.append(np.full(len(tris), f, np.int64))
        n_vert += len(grid)
        patch_tris += len(tris)
    counts["patch_level"] = options.patch_level
    counts["patch_triangles"] = int(patch_tris)
    counts["soup_triangles"] = int(soup_tris)
    allv = np.concatenate(vert_blocks)
    tri = np.concatenate(tri_list).astype(np.int64)
    tri_face = np.concatenate(tri_face_list).astype(np.int64)
    timings["tessellate_s"] = time.perf_counter() - t1

    # --- scene coordinates, winding, degenerate triangles -------------------------------------------
    pos_q3 = allv[:, 0:3]
    pos = pos_q3 @ Q3_TO_SCENE.T * options.unit_m
    nrm = allv[:, 5:8] @ Q3_TO_SCENE.T
    uv = allv[:, 3:5]
    p = pos[tri]
    geo = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(geo, axis=1)
    vn = nrm[tri].sum(axis=1)
    vn = np.where((np.linalg.norm(vn, axis=1) > 1e-6)[:, None], vn, b.faces["normal"][tri_face] @ Q3_TO_SCENE.T)
    flip = np.einsum("ij,ij->i", geo, vn) < 0
    counts["triangles_rewound"] = int(flip.sum())
    tri = np.where(flip[:, None], tri[:, [0, 2, 1]], tri)
    good = np.isfinite(area) & (area > MIN_TRIANGLE_AREA_M2)
    counts["degenerate_triangles_dropped"] = int((~good).sum())
    tri, tri_face = tri[good], tri_face[good]
    if len(tri) == 0:
        raise UserError(f"{source}: no drawable triangles")
    # Compact the vertex array to the vertexes triangles use.
    used, inverse = np.unique(tri.reshape(-1), return_inverse=True)
    tri = inverse.reshape(-1, 3).astype(np.int32)
    pos, nrm, uv, pos_q3 = pos[used], nrm[used], uv[used], pos_q3[used]
    nlen = np.linalg.norm(nrm, axis=1, keepdims=True)
    fn = np.cross(pos[tri[:, 1]] - pos[tri[:, 0]], pos[tri[:, 2]] - pos[tri[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    fallback = np.zeros_like(nrm)
    fallback[tri.reshape(-1)] = np.repeat(fn, 3, axis=0)
    nrm = np.where(nlen > 1e-6, nrm / np.maximum(nlen, 1e-30), fallback)

    # --- materials ----------------------------------------------------------------------------------
    t2 = time.perf_counter()
    used_shaders = np.unique(faces["shader"][tri_face])
    materials: list[Material] = []
    shader_material = np.full(len(names), -1, np.int64)
    records: list[ShaderRecord] = []
    by_name: dict[str, int] = {}
    missing: list[str] = []
    alpha_masks: dict[int, np.ndarray] = {}
    for s in range(len(names)):
        info, flags = shader_infos[s], int(shader_flags[s])
        requested = info.diffuse_image
        found = textures.find(requested)
        light = np.zeros(3)
        emission = np.zeros(3)
        if info.surfacelight > 0:
            light, _ = _light_color(info, textures)
            emission = surface_radiance(info.surfacelight, options.light_scale) * light
        rec = ShaderRecord(names[s], flags, reason_by_shader[s] or None, _kind(flags), info.blend_mode,
                           found, requested, float(info.surfacelight), light.tolist(), emission.tolist(),
                           info.alpha_stage.alpha_func if info.alpha_stage else None, info.source)
        records.append(rec)
        if s not in used_shaders:
            continue
        key = names[s].lower()
        if key in by_name:
            shader_material[s] = by_name[key]
            continue
        img = textures.load(requested) if found else None
        if img is None:
            missing.append(requested)
            texture, albedo = None, np.asarray(MISSING_TEXTURE_ALBEDO, np.float64)
            rec.texture = None
        else:
            texture = decode_srgb8(img[:, :, :3])
            albedo = texture.reshape(-1, 3).mean(axis=0)
        mat_id = len(materials)
        extra = {}
        if rec.kind == "glass" and flags & FLAGS["liquid"]:
            extra["int_ior"] = IOR_WATER
        if info.alpha_stage is not None:
            mask_img = textures.load(info.alpha_stage.image)
            if mask_img is None:
                missing.append(info.alpha_stage.image)
            else:
                invert, threshold = ALPHA_TESTS[info.alpha_stage.alpha_func]
                alpha8 = 255 - mask_img[:, :, 3] if invert else mask_img[:, :, 3]
                alpha_masks[mat_id] = np.ascontiguousarray(alpha8)
                extra.update(opacity_texture=alpha8[:, :, None].astype(np.float32) / 255.0,
                             alpha_threshold=threshold)
        materials.append(Material(name=names[s], albedo=albedo, albedo_texture=texture, emission=emission,
                                  kind=rec.kind, **extra))
        by_name[key] = mat_id
        shader_material[s] = mat_id
    face_material = shader_material[faces["shader"][tri_face]].astype(np.int32)
    face_object = model_object[face_model[tri_face]].astype(np.int32)
    counts["missing_textures"] = sorted(set(missing))
    counts["textures_loaded"] = int(sum(m.albedo_texture is not None for m in materials))
    counts["materials"] = len(materials)
    timings["materials_s"] = time.perf_counter() - t2

    emissive = np.array([m.is_emissive for m in materials], bool)[face_material]
    counts["triangles"] = int(len(tri))
    counts["surface_light_triangles"] = int(emissive.sum())
    counts["surface_light_shaders"] = sorted({materials[i].name for i in np.unique(face_material[emissive])})
    sl_shader = np.array([shader_infos[s].surfacelight > 0 for s in range(len(names))], bool)
    sl_face = sl_shader[faces["shader"]]
    counts["surface_light_faces_excluded"] = {name: int((sl_face & (reason == name)).sum())
                                              for name, _ in rules if (sl_face & (reason == name)).any()}
    kind_names = ("diffuse", "mirror", "glass")
    kind_of = np.array([kind_names.index(m.kind) for m in materials])
    kc = np.bincount(kind_of[face_material], minlength=len(kind_names))
    counts["triangles_by_kind"] = {k: int(c) for k, c in zip(kind_names, kc)}
    tested = np.array([m.is_alpha_tested for m in materials], bool)
    counts["triangles_alpha_tested"] = int(tested[face_material].sum())

    # --- lights -------------------------------------------------------------------------------------
    q3lights, light_skipped = convert_light_entities(b.entities, options.unit_m, options.light_scale)

    def to_scene(q):
        return np.asarray(q, np.float64) @ Q3_TO_SCENE.T * options.unit_m

    point_lights = [PointLight(f"{lt.kind}_{lt.index}", to_scene(lt.origin_q3), lt.rgb_w_sr) for lt in q3lights]
    light_records = [lt.record(to_scene) for lt in q3lights]
    # Suns of the sky shaders the map's drawn-or-not faces use (q3map2 creates them from any surface's shader).
    centre = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    no_shader_sun = bool(b.entities) and b.entities[0].get("_noshadersun", "")[:1] == "1"
    sun_shaders = [] if no_shader_sun else [s for s in np.unique(faces["shader"]) if shader_infos[s].suns]
    for s in sun_shaders:
        for k, (color, intensity, degrees, elevation) in enumerate(shader_infos[s].suns):
            if intensity <= 0:
                continue
            position, direction, rgb = sun_light(color, intensity, degrees, elevation, centre, options.light_scale)
            point_lights.append(PointLight(f"sun_{names[s]}_{k}", position, rgb))
            light_records.append({"entity": -1, "kind": "sun", "shader": names[s], "position": position.tolist(),
                                  "direction": direction.tolist(), "sun_intensity": intensity,
                                  "irradiance_w_m2": float(rgb.max() / SUN_DISTANCE_M ** 2),
                                  "color": display_color_to_linear(color).tolist(),
                                  "intensity_w_sr": float(rgb.max())})
    # Sky light: a dome of distant point lights per sky shader with a surface light.
    sky_shaders = [s for s in np.unique(faces["shader"]) if shader_flags[s] & FLAGS["sky"]
                   and shader_infos[s].surfacelight > 0]
    for s in sky_shaders:
        color, _ = _light_color(shader_infos[s], textures)
        radiance = surface_radiance(shader_infos[s].surfacelight, options.light_scale) * color
        positions, directions, rgbs = sky_dome_lights(radiance, centre)
        for k, (position, direction, rgb) in enumerate(zip(positions, directions, rgbs)):
            point_lights.append(PointLight(f"sky_{names[s]}_{k}", position, rgb))
            light_records.append({"entity": -1, "kind": "sky", "shader": names[s], "position": position.tolist(),
                                  "direction": direction.tolist(), "sky_radiance": radiance.tolist(),
                                  "intensity_w_sr": float(rgb.max())})
    counts["light_entities"] = int(sum(1 for e in b.entities if e.get("classname", "")[:5].lower() == "light"))
    counts["sun_lights"] = int(sum(1 for r in light_records if r["kind"] == "sun"))
    counts["point_lights"] = len(point_lights)
    counts["lights_by_kind"] = {k: sum(1 for r in light_records if r["kind"] == k)
                                for k in ("point", "spot", "linear", "sun", "sky")}
    counts["lights_skipped"] = light_skipped

    # --- visibility ---------------------------------------------------------------------------------
    t3 = time.perf_counter()
    vis = Q3Visibility(planes_normal=b.planes["normal"].astype(np.float64),
                       planes_dist=b.planes["dist"].astype(np.float64),
                       node_plane=b.nodes["plane"].astype(np.int32), node_children=b.nodes["children"].astype(np.int32),
                       leaf_cluster=b.leafs["cluster"].astype(np.int32), leaf_area=b.leafs["area"].astype(np.int32),
                       leaf_mins_q3=b.leafs["mins"].astype(np.float64), leaf_maxs_q3=b.leafs["maxs"].astype(np.float64),
                       pvs_rows=None if b.visdata is None else np.ascontiguousarray(b.visdata.rows),
                       n_clusters=b.n_clusters, triangle_cluster_offsets=np.zeros(1, np.int64),
                       triangle_cluster_ids=np.zeros(0, np.int32), triangle_cluster=np.zeros(0, np.int32),
                       unit_m=options.unit_m)
    # World faces use the leaf lists; brush-entity faces (face_model > 0) are treated as not listed.
    list_face = np.where(face_model[tri_face] == 0, tri_face, -1)
    offsets, ids, merged = triangle_clusters(b, list_face, pos_q3[tri], vis.leaf_of_q3)
    vis.triangle_cluster_offsets, vis.triangle_cluster_ids, vis.triangle_cluster = offsets, ids, merged
    counts["triangles_without_cluster"] = int((np.diff(offsets) == 0).sum())
    counts["pvs_symmetry"] = vis.symmetry() if vis.has_vis else None
    timings["visibility_s"] = time.perf_counter() - t3

    # --- spawn points -------------------------------------------------------------------------------
    # info_player_deathmatch; a map without one (some CTF maps) uses the first class of SPAWN_CLASSES it has.
    spawns = []
    spawn_class = next((k for k in SPAWN_CLASSES if any(e.get("classname") == k for e in b.entities)), None)
    for e in b.entities:
        if e.get("classname") == spawn_class:
            q = _vec(e.get("origin"))
            try:
                angle = float(e.get("angle", "0") or 0)
            except ValueError:
                angle = 0.0
            spawns.append([*to_scene(q), angle])
    spawn_points = np.array(spawns, np.float64).reshape(-1, 4)
    counts["spawn_points"] = len(spawns)
    counts["spawn_class"] = spawn_class

    message = b.entities[0].get("message", "") if b.entities else ""
    info = Q3Info(map_name=map_name, source=source, bsp_sha256=hashlib.sha256(bsp_bytes).hexdigest(),
                  message=" ".join(message.split()), options=dict(vars(options)),
                  shaders=[vars(r) for r in records], lights=light_records, counts=counts,
                  face_type=ftype.astype(np.int32), face_shader=faces["shader"].astype(np.int32),
                  face_model=face_model.astype(np.int32), face_flags=fflags.astype(np.int64),
                  triangle_face=tri_face.astype(np.int32), alpha_masks=alpha_masks, spawn_points=spawn_points)
    parts = dict(positions=pos.astype(np.float32), normals=nrm.astype(np.float32), uvs=uv.astype(np.float32),
                 faces=tri, face_material=face_material, face_object=face_object, object_names=object_names,
                 materials=materials, point_lights=point_lights)
    timings["total_s"] = time.perf_counter() - t0
    return parts, info, vis, timings
