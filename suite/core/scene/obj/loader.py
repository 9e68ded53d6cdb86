"""OBJ scenes: specs, sidecars, conversion to the scene model, and the on-disk cache.

Specs: a path ending in ``.obj``, or the name of a project scene (a sidecar in ``suite/core/scene/data/`` whose
``[scene] file`` is found on the scene search path, :mod:`suite.core.scene.search`).

Cache: the converted scene (geometry, materials with their 8-bit texels, counts; not the lights and camera,
which are rebuilt from the sidecar on every load) is stored as an uncompressed ``.npz`` in
``$SPLITBENCH_CACHE/scenes/obj/`` (default ``./cache``), named by the OBJ's file name and a SHA-256 key of
the OBJ's bytes, the sidecar's bytes, the options and :data:`LOADER_VERSION`. The files it was built from
besides the OBJ (MTL files, textures) are listed in it with their SHA-256, and textures that were missing with
the paths tried; a cache entry whose list no longer matches the disk is rebuilt.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import CameraKey, CameraPath, LightAnimation, Material, PointLight, Scene
from suite.core.scene.obj import mtl as mtlmod
from suite.core.scene.obj.reader import read_obj
from suite.core.scene.obj.sidecar import (Sidecar, camera_path, material_overrides, project_sidecars, read_sidecar,
                                          sidecar_for)
from suite.core.scene.search import find_scene_file, missing_file_message

LOADER_VERSION = 2
DEFAULT_MATERIAL = "default"
DEFAULT_ALBEDO = (0.5, 0.5, 0.5)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_scene_cache: dict[str, "ObjScene"] = {}
last_load_stats: dict = {}


@dataclass
class ObjInfo:
    """What the conversion read and did: source files, hashes, counts, and what was not modelled."""

    source: str
    sha256: str
    sidecar: str | None
    mtl_files: list
    counts: dict
    unsupported: dict  # statement -> count, OBJ and MTL (e.g. "l": 12, "map_bump": 25, "map_Kd -s": 1)
    missing_textures: list  # texture names that could not be read
    defaults: list = field(default_factory=list)  # what came from defaults (no sidecar light / camera)
    # Files the conversion read besides the OBJ ({"files": {path: sha256}}) and paths it found missing
    # ({"absent": [...]}): a cache entry is stale when one of them changed, vanished or appeared.
    deps: dict = field(default_factory=dict)

    def problems(self) -> str:
        """One line summarising what was not modelled, or ''."""
        parts = []
        if self.unsupported:
            parts.append("not modelled: " + ", ".join(f"{k} x{v}" for k, v in sorted(self.unsupported.items())))
        if self.missing_textures:
            shown = ", ".join(self.missing_textures[:5]) + (", ..." if len(self.missing_textures) > 5 else "")
            parts.append(f"{len(self.missing_textures)} missing texture(s) (flat Kd colour used): {shown}")
        return "; ".join(parts)


@dataclass(eq=False)
class ObjScene(Scene):
    """The shared scene model plus the OBJ's records (``obj``: :class:`ObjInfo`) and an optional ``visibility``
    (for instance a :func:`suite.core.scene.cellvis.computed_visibility` result attached by the caller)."""

    visibility: object | None = None
    obj: object | None = None

    def translated(self, offset) -> "ObjScene":
        moved = super().translated(offset)
        if self.visibility is None:
            return moved
        return dataclasses.replace(moved, visibility=self.visibility.translated(offset))

    def without_degenerate_faces(self, min_area: float = 0.0) -> "ObjScene":
        area = self.face_areas()
        keep = np.isfinite(area) & (area > min_area)
        if keep.all():
            return self
        vis = None if self.visibility is None else self.visibility.subset_triangles(keep)
        return dataclasses.replace(self, faces=self.faces[keep], face_material=self.face_material[keep],
                                   face_object=self.face_object[keep], visibility=vis)


def is_obj_spec(spec: str) -> bool:
    return str(spec).lower().endswith(".obj") or str(spec) in project_sidecars()


def cache_dir() -> Path:
    root = os.environ.get("SPLITBENCH_CACHE") or os.path.join(os.getcwd(), "cache")
    return Path(root) / "scenes" / "obj"


def list_obj_scenes() -> dict[str, str]:
    """Project OBJ scenes (sidecars in the data folder) with a one-line description, or ``unavailable: ...``
    naming the fix when the OBJ is not on the scene search path."""
    out = {}
    for name, path in project_sidecars().items():
        try:
            sc = read_sidecar(path)
        except UserError as exc:
            out[name] = f"unavailable: {exc}"
            continue
        rel = str(sc.scene.get("file", ""))
        if rel and find_scene_file(rel) is None:
            out[name] = "unavailable: " + missing_file_message(rel, "OBJ file")
        else:
            out[name] = str(sc.scene.get("title") or f"OBJ scene {name}")
    return out


def resolve(spec: str, sidecar: str | os.PathLike | None = None) -> tuple[str, Path, Sidecar | None]:
    """(scene name, OBJ path, sidecar or None) of a spec. The OBJ's hash is checked later."""
    named = project_sidecars()
    if spec in named:
        sc = read_sidecar(named[spec])
        rel = sc.scene.get("file")
        if not rel:
            raise UserError(f"sidecar '{sc.path}' names no OBJ file ([scene] file)")
        path = find_scene_file(str(rel))
        if path is None:
            raise UserError(f"cannot load scene '{spec}': " + missing_file_message(str(rel), "OBJ file"))
        return spec, path, sc
    path = Path(spec)
    if not path.is_file():
        raise UserError(f"OBJ file '{spec}' does not exist")
    sc = read_sidecar(Path(sidecar)) if sidecar is not None else None
    return path.stem, path, sc


def source_digest(spec) -> str:
    """A content hash of what a spec loads from: the OBJ's bytes and its sidecar's text. (Material and texture
    files are checked against the conversion cache's recorded hashes when the scene loads.)"""
    name, path, sc = resolve(os.fspath(spec))
    try:
        sha = _file_sha(path)
    except OSError as exc:
        raise UserError(f"cannot read OBJ file '{path}': {exc.strerror or exc}") from None
    if sc is None:
        sc = sidecar_for(path, sha)
    return hashlib.sha256(f"{sha}|{sc.text_sha256 if sc else '-'}".encode()).hexdigest()


def load_obj(spec, *, sidecar=None, max_texture_size: int = mtlmod.DEFAULT_MAX_TEXTURE_SIZE, strict: bool = False,
             use_cache: bool = True) -> ObjScene:
    """Loads an OBJ scene (module docstring). ``sidecar`` overrides the sidecar lookup for a path spec;
    ``strict`` turns anything not modelled (``ObjInfo.unsupported``, missing textures) into a UserError."""
    t0 = time.perf_counter()
    spec = os.fspath(spec)
    if int(max_texture_size) < 1:
        raise UserError(f"max_texture_size must be >= 1, got {max_texture_size}")
    name, path, sc = resolve(spec, sidecar)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read OBJ file '{path}': {exc.strerror or exc}") from None
    sha = hashlib.sha256(data).hexdigest()
    if sc is None and sidecar is None:
        sc = sidecar_for(path, sha)
    if sc is not None:
        sc.check_hash(path, sha)
        name = sc.name or name
    key = hashlib.sha256(f"{sha}|{sc.text_sha256 if sc else '-'}|{int(max_texture_size)}|v{LOADER_VERSION}".encode())
    digest = key.hexdigest()
    t_hash = time.perf_counter() - t0
    mode = "memory"
    if use_cache and digest in _scene_cache and _deps_unchanged(_scene_cache[digest].obj.deps):
        scene = _scene_cache[digest]
    else:
        cache_file = cache_dir() / f"{path.stem}-{digest[:24]}.npz"
        parts = None
        mode = "cold"
        if use_cache and cache_file.is_file():
            try:
                parts = _read_cache(cache_file)
                if not _deps_unchanged(parts["info"].deps):
                    parts = None
                else:
                    mode = "disk"
            except Exception:  # a damaged or foreign cache file is rebuilt
                parts = None
        if parts is None:
            parts = convert(path, data, sha, sc, int(max_texture_size))
            if use_cache:
                _write_cache(cache_file, parts)
        scene = _assemble(name, parts, sc)
        if use_cache:
            _scene_cache[digest] = scene
    info = scene.obj
    problems = info.problems()
    if strict and problems:
        raise UserError(f"{path}: {problems}")
    if problems and mode != "memory":
        print(f"splitbench: warning: {path}: {problems}", file=sys.stderr)
    last_load_stats.clear()
    last_load_stats.update(spec=spec, mode=mode, hash_s=t_hash, total_s=time.perf_counter() - t0)
    return scene


# --- conversion ---------------------------------------------------------------------------------------

def _file_sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _deps_unchanged(deps: dict) -> bool:
    for p, want in deps.get("files", {}).items():
        try:
            if _file_sha(Path(p)) != want:
                return False
        except OSError:
            return False
    return not any(Path(p).exists() for p in deps.get("absent", []))


def convert(path: Path, data: bytes, sha: str, sc: Sidecar | None, max_texture_size: int) -> dict:
    """OBJ + MTL + sidecar -> arrays, material records and info (without lights and camera)."""
    t0 = time.perf_counter()
    geo = read_obj(path, data)
    t_read = time.perf_counter() - t0
    base = path.parent
    images = mtlmod.ImageCache(max_texture_size)
    unsupported = dict(geo.census.unsupported)
    deps = {"files": {}, "absent": []}

    # MTL statements (for Ke, texture options and the census of what is not modelled).
    stmts: dict[str, mtlmod.MtlStatements] = {}
    mtl_files = []
    for lib in geo.census.mtllibs:
        p = mtlmod.find_texture(base, lib)
        if p is None:
            unsupported[f"missing MTL file {lib}"] = 1
            deps["absent"].append(str(base / lib.replace("\\", "/")))
            continue
        mtl_files.append(str(p))
        deps["files"][str(p)] = _file_sha(p)
        for n, st in mtlmod.mtl_census(p).items():
            stmts.setdefault(n, st)

    # Materials: the MTL's, each with its sidecar override, then the sidecar's own, then the default.
    records, index, missing = [], {}, []
    for m in geo.materials:
        conv = mtlmod.convert(m, stmts.get(m.name), base, images)
        for k, v in conv.unsupported.items():
            unsupported[k] = unsupported.get(k, 0) + v
        missing += conv.missing
        index[m.name] = len(records)
        records.append(_record(conv.name, conv.params, conv.albedo_image, conv.opacity_image, sc, base, images))
    if sc is not None:
        for n in sc.materials:
            if n not in index:
                index[n] = len(records)
                records.append(_record(n, {"albedo": np.array(DEFAULT_ALBEDO)}, None, None, sc, base, images))
    n_mtl = len(geo.materials)
    face_material = np.empty(len(geo.faces), np.int64)
    mtl_to_record = np.array([index[m.name] for m in geo.materials] + [-1], np.int64)
    face_material[:] = mtl_to_record[np.where(geo.face_mtl >= 0, geo.face_mtl, n_mtl)]
    # Objects the sidecar maps to a material.
    mapped = 0
    if sc is not None and sc.objects:
        shape_mat = np.array([index[sc.material_for_object(n)] if sc.material_for_object(n) else -2
                              for n in geo.shape_names], np.int64)
        per_face = shape_mat[geo.face_shape]
        sel = per_face >= 0
        face_material[sel] = per_face[sel]
        mapped = int(sel.sum())
    if (face_material < 0).any():
        if DEFAULT_MATERIAL not in index:
            index[DEFAULT_MATERIAL] = len(records)
            records.append(_record(DEFAULT_MATERIAL, {"albedo": np.array(DEFAULT_ALBEDO)}, None, None, sc, base,
                                   images))
        face_material[face_material < 0] = index[DEFAULT_MATERIAL]
    for ident, p in images.files.items():
        deps["files"][str(p)] = _file_sha(p)
    for key, why in images.errors.items():
        if why == "file not found":
            deps["absent"].append(str(base / key))

    # Units and axes.
    positions, normals = geo.positions, geo.normals
    if sc is not None and sc.up == "z":
        positions, normals = positions @ Z_UP_TO_Y_UP.T, normals @ Z_UP_TO_Y_UP.T
    unit = sc.unit_m if sc is not None else 1.0
    positions = positions * unit
    # Zero-area triangles cannot be hit and have no normal: dropped and counted.
    tri = positions[geo.faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = area2 > 0
    faces = geo.faces[keep]
    used, faces_new = np.unique(faces, return_inverse=True)
    faces = faces_new.reshape(-1, 3)
    counts = {
        "obj_statements": geo.census.counts, "triangles_read": int(len(geo.faces)),
        "triangles": int(keep.sum()), "zero_area_triangles_dropped": int((~keep).sum()),
        "vertices": int(len(used)), "objects": len(geo.shape_names), "mtl_materials": n_mtl,
        "materials": len(records), "faces_mapped_by_sidecar": mapped,
        "emissive_triangles": int(sum(int((face_material[keep] == i).sum()) for i, r in enumerate(records)
                                      if np.any(np.asarray(r["params"].get("emission", 0)) > 0))),
        "alpha_tested_materials": sum(1 for r in records if r["opacity"] is not None),
        "textured_materials": sum(1 for r in records if r["albedo"] is not None),
        **geo.counts, "read_s": round(t_read, 4), "convert_s": round(time.perf_counter() - t0, 4),
    }
    info = ObjInfo(source=str(path), sha256=sha, sidecar=str(sc.path) if sc else None, mtl_files=mtl_files,
                   counts=counts, unsupported=unsupported, missing_textures=sorted(set(missing)), deps=deps)
    return {"positions": positions[used].astype(np.float32), "normals": normals[used].astype(np.float32),
            "uvs": geo.uvs[used].astype(np.float32), "faces": faces.astype(np.int32),
            "face_material": face_material[keep].astype(np.int32),
            "face_object": geo.face_shape[keep].astype(np.int32), "object_names": list(geo.shape_names),
            "materials": records, "info": info}


def _record(name, params, albedo_img, opacity_img, sc, base, images) -> dict:
    over, imgs = material_overrides(sc, name, base, images)
    params = {**params, **over}
    if "albedo_texture" in params or "opacity_texture" in params:
        raise UserError(f"material '{name}': textures are given as files")
    return {"name": name, "params": params, "albedo": imgs.get("albedo", albedo_img),
            "opacity": imgs.get("opacity", opacity_img)}


def _material(rec: dict) -> Material:
    params = dict(rec["params"])
    if rec["albedo"] is not None:
        params["albedo_texture"] = rec["albedo"].albedo()
    if rec["opacity"] is not None:
        params["opacity_texture"] = rec["opacity"].opacity()
    return Material(name=rec["name"], **params)


def _assemble(name: str, parts: dict, sc: Sidecar | None) -> ObjScene:
    materials = [_material(r) for r in parts["materials"]]
    info: ObjInfo = dataclasses.replace(parts["info"], defaults=[])
    lights, anims = [], []
    if sc is not None and sc.lights:
        for i, lt in enumerate(sc.lights):
            lights.append(PointLight(lt["name"], lt["position"], lt["intensity"]))
            if "keys" in lt:
                anims.append(LightAnimation(i, lt["keys"][0], lt["keys"][1]))
    pos = parts["positions"]
    lo, hi = pos.min(axis=0).astype(np.float64), pos.max(axis=0).astype(np.float64)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    if sc is not None and sc.camera is not None:
        camera = camera_path(sc)
    else:
        camera = default_camera(centre, radius)
        info.defaults.append("camera")
    has_area = any(m.is_emissive for m in materials)
    if not lights and not has_area:
        # A head light above the default or scripted camera's start, bright enough for the scene's size.
        start = camera.keys[0].position
        lights.append(PointLight("default_light", start + np.array([0.0, 0.25 * radius, 0.0]),
                                 np.full(3, 0.5 * radius ** 2)))
        info.defaults.append("light")
    c = info.counts
    src = Path(info.source).name
    licence = (sc.scene.get("licence") or sc.scene.get("license")) if sc else None
    desc = (f"OBJ scene '{name}' from {src}: {c['triangles']} triangles, {c['objects']} objects, "
            f"{c['materials']} materials ({c['textured_materials']} textured, {c['alpha_tested_materials']} "
            f"alpha-tested), {len(lights)} point lights" + (f" ({len(anims)} moving)" if anims else "") +
            f", {c['emissive_triangles']} emissive triangles" +
            (f"; defaults used for: {', '.join(info.defaults)}" if info.defaults else "") +
            (f"; {info.problems()}" if info.problems() else "") + (f". Licence: {licence}" if licence else ""))
    if sc is not None and sc.scene.get("description"):
        desc = str(sc.scene["description"]).strip() + " " + desc
    return ObjScene(name=name, positions=parts["positions"], normals=parts["normals"], uvs=parts["uvs"],
                    faces=parts["faces"], face_material=parts["face_material"], face_object=parts["face_object"],
                    object_names=parts["object_names"], materials=materials, point_lights=lights, camera=camera,
                    light_animations=anims, description=desc, obj=info)


def default_camera(centre: np.ndarray, radius: float) -> CameraPath:
    """For an OBJ without a sidecar camera: outside the bounding sphere looking at its centre, a 4 s dolly in and
    back (no scene knowledge, so no walk through it)."""
    pos = centre + np.array([0.0, 0.5, 2.0]) * max(radius, 1e-3)
    toward = 0.15 * (centre - pos)
    keys = [CameraKey(0.0, pos, centre), CameraKey(2.0, pos + toward, centre), CameraKey(4.0, pos, centre)]
    return CameraPath(keys=keys, fov_deg=60.0, resolution=(320, 180), fps=30.0)


# --- cache file ---------------------------------------------------------------------------------------

def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def _write_cache(path: Path, parts: dict) -> None:
    from suite.fileio import atomic_target

    arrays = {k: parts[k] for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object")}
    mats = []
    for i, rec in enumerate(parts["materials"]):
        entry = {"name": rec["name"], "params": {k: _jsonable(v) for k, v in rec["params"].items()}}
        for slot in ("albedo", "opacity"):
            img = rec[slot]
            if img is None:
                continue
            for attr in ("rgb8", "rgb_linear", "alpha8", "alpha_float"):
                if getattr(img, attr) is not None:
                    arrays[f"{slot}_{i}_{attr}"] = getattr(img, attr)
            entry[slot] = True
        mats.append(entry)
    info: ObjInfo = parts["info"]
    meta = {"materials": mats, "object_names": parts["object_names"], "info": dataclasses.asdict(info)}
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_target(path, suffix=".tmp.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _read_cache(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(bytes(z["meta_json"]).decode())
        parts = {k: z[k] for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object")}
        files = set(z.files)
        records = []
        for i, m in enumerate(meta["materials"]):
            rec = {"name": m["name"], "params": {k: (np.asarray(v, np.float64) if isinstance(v, list) else v)
                                                 for k, v in m["params"].items()}}
            for slot in ("albedo", "opacity"):
                if not m.get(slot):
                    rec[slot] = None
                    continue
                kw = {a: (z[f"{slot}_{i}_{a}"] if f"{slot}_{i}_{a}" in files else None)
                      for a in ("rgb8", "rgb_linear", "alpha8", "alpha_float")}
                rec[slot] = mtlmod.Image(**kw)
            records.append(rec)
    parts.update(materials=records, object_names=meta["object_names"], info=ObjInfo(**meta["info"]))
    return parts
