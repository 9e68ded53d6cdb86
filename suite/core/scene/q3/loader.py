"""Scene specs for Quake III maps, resolution through the archives, and the on-disk cache.

Specs:

* ``oa:<map>`` -- the map ``maps/<map>.bsp`` as the game would load it (the archive that wins the override
  order, see :mod:`.paks`);
* ``oa:<map>@<pak>`` -- the copy in the archive named ``<pak>`` (file name with or without ``.pk3``), e.g.
  ``oa:aggressor@pak1-maps`` for OpenArena 0.8.1's version of a map that 0.8.8 replaced;
* ``<path>.bsp`` -- a BSP file; textures and shader scripts come from the search path;
* ``<path>.pk3`` or ``<path>.pk3:<map>`` -- a map inside an archive that is added to the search path with the
  highest priority (the map name may be left out when the archive holds one map).

Cache: the converted scene (without its camera path, which is rebuilt from ``camera_paths.toml`` on every
load) is stored as an uncompressed ``.npz`` under ``$SPLITBENCH_CACHE/scenes/q3/`` (default ``./cache``),
named by the map and a SHA-256 key of the BSP's bytes, the search path's archive contents (names, sizes and
CRC-32s of every member), the conversion options and ``CONVERTER_VERSION``.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import Material, PointLight
from suite.core.scene.q3.camera import make_camera
from suite.core.scene.q3.convert import ConvertOptions, Q3Info, build
from suite.core.scene.q3.paks import PakFS, missing_data_message, search_path_paks
from suite.core.scene.q3.scene import Q3Scene
from suite.core.scene.q3.shaders import ShaderLibrary
from suite.core.scene.q3.textures import TextureLoader, decode_srgb8, linear_to_srgb
from suite.core.scene.q3.visibility import Q3Visibility

CONVERTER_VERSION = 2
PREFIX = "oa:"

_fs_cache: dict[tuple, PakFS] = {}
_shader_cache: dict[str, tuple[PakFS, ShaderLibrary]] = {}
_scene_cache: dict[str, Q3Scene] = {}
last_load_stats: dict = {}


def is_q3_spec(spec: str) -> bool:
    s = spec.lower()
    return s.startswith(PREFIX) or s.endswith((".bsp", ".pk3")) or ".pk3:" in s


def _stat_key(paths) -> tuple:
    out = []
    for p in paths:
        try:
            st = os.stat(p)
            out.append((p, st.st_size, st.st_mtime_ns))
        except OSError:
            out.append((p, -1, -1))
    return tuple(out)


def file_system(extra_paks: tuple[str, ...] = ()) -> PakFS:
    """The search path's :class:`PakFS` (plus ``extra_paks`` on top), reused while the archives are unchanged."""
    extra = [os.path.abspath(p) for p in extra_paks]
    paks = [p for p in search_path_paks() if os.path.abspath(p) not in extra] + extra
    key = _stat_key(paks)
    if key not in _fs_cache:
        _fs_cache.clear()
        _fs_cache[key] = PakFS(paks)
    return _fs_cache[key]


def _shaders(fs: PakFS) -> ShaderLibrary:
    cached = _shader_cache.get("library")
    if cached is None or cached[0] is not fs:  # keep the file system alive with it: ids are reused
        _shader_cache["library"] = (fs, ShaderLibrary(fs))
    return _shader_cache["library"][1]


def available_maps() -> dict[str, list[str]]:
    """Map name -> archives holding it (lowest priority first; the last one is what ``oa:<map>`` loads)."""
    fs = file_system()
    return {m: [os.path.basename(e.pak) for e in fs.versions(f"maps/{m}.bsp")] for m in fs.maps()}


def resolve(spec: str):
    """(scene name, map name, bsp bytes, source description, fs) for a spec."""
    raw = spec
    low = spec.lower()
    if low.startswith(PREFIX):
        body = spec[len(PREFIX):]
        name, _, pak = body.partition("@")
        name = name.strip()
        if not name:
            raise UserError(f"scene spec '{raw}' names no map (use oa:<map>, e.g. oa:aggressor)")
        fs = file_system()
        if not fs:
            raise UserError(f"cannot load '{raw}': " + missing_data_message())
        versions = fs.versions(f"maps/{name}.bsp")
        if not versions:
            maps = sorted(fs.maps())
            raise UserError(f"unknown OpenArena map '{name}' ({len(maps)} maps in the archives: "
                            f"{', '.join(maps[:12])}{', ...' if len(maps) > 12 else ''})")
        entry = versions[-1]
        if pak:
            want = pak.lower().removesuffix(".pk3")
            match = [e for e in versions if os.path.basename(e.pak).lower().removesuffix(".pk3") == want]
            if not match:
                raise UserError(f"map '{name}' is not in an archive named '{pak}' (it is in: "
                                f"{', '.join(os.path.basename(e.pak) for e in versions)})")
            entry = match[-1]
        source = f"{os.path.basename(entry.pak)}:{entry.name}"
        return f"{PREFIX}{name}" + (f"@{pak}" if pak else ""), name.lower(), fs.read("", entry), source, fs
    # Paths.
    pk3_path, inner = spec, ""
    if ".pk3:" in low:
        idx = low.index(".pk3:")
        pk3_path, inner = spec[:idx + 4], spec[idx + 5:]
    if pk3_path.lower().endswith(".pk3"):
        if not os.path.isfile(pk3_path):
            raise UserError(f"archive '{pk3_path}' does not exist")
        fs = file_system((pk3_path,))
        try:
            with zipfile.ZipFile(pk3_path) as zf:
                bsps = [n for n in zf.namelist() if n.lower().startswith("maps/") and n.lower().endswith(".bsp")]
        except (OSError, zipfile.BadZipFile) as exc:
            raise UserError(f"cannot read archive '{pk3_path}': {exc}") from None
        names = {os.path.basename(n)[:-4].lower(): n for n in bsps}
        if not names:
            raise UserError(f"archive '{pk3_path}' holds no maps/*.bsp")
        if inner:
            key = inner.lower().removesuffix(".bsp")
            if key not in names:
                raise UserError(f"archive '{pk3_path}' has no map '{inner}' (it has: {', '.join(sorted(names))})")
        elif len(names) > 1:
            raise UserError(f"archive '{pk3_path}' holds {len(names)} maps; pick one with "
                            f"'{pk3_path}:<map>' ({', '.join(sorted(names))})")
        else:
            key = next(iter(names))
        data = fs.read("", fs.versions(names[key])[-1])
        return spec, key, data, f"{os.path.basename(pk3_path)}:{names[key]}", fs
    if low.endswith(".bsp"):
        try:
            data = Path(spec).read_bytes()
        except OSError as exc:
            raise UserError(f"cannot read BSP file '{spec}': {exc.strerror or exc}") from None
        return spec, Path(spec).stem.lower(), data, os.path.abspath(spec), file_system()
    raise UserError(f"'{raw}' is not a Quake III scene spec (oa:<map>, <file>.bsp, <file>.pk3[:<map>])")


def cache_dir() -> Path:
    root = os.environ.get("SPLITBENCH_CACHE") or os.path.join(os.getcwd(), "cache")
    return Path(root) / "scenes" / "q3"


def source_digest(spec: str) -> str:
    """A content hash of what a spec loads from: the map's BSP bytes and the archives' fingerprint (names, sizes
    and CRC-32s of every member, so a changed texture or shader file changes it too)."""
    _, _, data, _, fs = resolve(spec)
    key = hashlib.sha256(hashlib.sha256(data).digest())
    key.update(fs.fingerprint().encode())
    return key.hexdigest()


def load_q3(spec: str, *, unit_m: float | None = None, patch_level: int | None = None,
            light_scale: float | None = None, max_texture_size: int | None = None,
            use_cache: bool = True) -> Q3Scene:
    """Loads a Quake III map spec as a :class:`Q3Scene` (see the module docstring for specs and caching)."""
    opts = ConvertOptions()
    for k, v in (("unit_m", unit_m), ("patch_level", patch_level), ("light_scale", light_scale),
                 ("max_texture_size", max_texture_size)):
        if v is not None:
            setattr(opts, k, type(getattr(opts, k))(v))
    if opts.unit_m <= 0 or opts.patch_level < 1 or opts.light_scale < 0 or opts.max_texture_size < 1:
        raise UserError(f"invalid Quake III load options {vars(opts)}")
    t0 = time.perf_counter()
    name, map_name, data, source, fs = resolve(spec)
    key = hashlib.sha256()
    key.update(hashlib.sha256(data).digest())
    key.update(fs.fingerprint().encode())
    key.update(f"{opts.key()}|v{CONVERTER_VERSION}".encode())
    digest = key.hexdigest()
    t_resolve = time.perf_counter() - t0
    if use_cache and digest in _scene_cache:
        last_load_stats.update(spec=spec, mode="memory", resolve_s=t_resolve, total_s=time.perf_counter() - t0)
        return _scene_cache[digest]
    path = cache_dir() / f"{map_name}-{digest[:24]}.npz"
    parts = info = vis = None
    mode = "cold"
    if use_cache and path.is_file():
        try:
            parts, info, vis = _read_cache(path)
            mode = "disk"
        except Exception:  # a damaged or foreign cache file is rebuilt
            parts = None
    timings = {}
    if parts is None:
        with TextureLoader(fs, opts.max_texture_size) as textures:
            parts, info, vis, timings = build(data, map_name, source, _shaders(fs), textures, opts)
        # The cache holds the 8-bit texels the cold path decoded, so both paths give identical floats.
        if use_cache:
            _write_cache(path, parts, info, vis)
    tris = parts["positions"][parts["faces"]]
    camera, cam_desc = make_camera(map_name, info.spawn_points, tris, opts.unit_m)
    c = info.counts
    lk = c["lights_by_kind"]
    description = (f"OpenArena map '{map_name}'" + (f" ({info.message})" if info.message else "") +
                   f" from {source}: {c['triangles']} triangles, {c['point_lights']} point lights "
                   f"({c['light_entities']} light entities of which {lk['spot']} spots; {lk['sun']} suns; "
                   f"{lk['sky']} sky-dome lights), "
                   f"{c['surface_light_triangles']} surface-light triangles, "
                   f"{c['clusters']} clusters. Camera: {cam_desc}.")
    scene = Q3Scene(name=name, camera=camera, description=description, visibility=vis, q3=info, **parts)
    if use_cache:
        _scene_cache[digest] = scene
    last_load_stats.clear()
    last_load_stats.update({f"convert_{k}": v for k, v in timings.items()})
    last_load_stats.update(spec=spec, mode=mode, resolve_s=t_resolve, total_s=time.perf_counter() - t0,
                           cache_file=str(path))
    return scene


# --- cache file ---------------------------------------------------------------------------------------

def _write_cache(path: Path, parts: dict, info: Q3Info, vis: Q3Visibility) -> None:
    from suite.fileio import atomic_target

    arrays = {k: parts[k] for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object")}
    mats = []
    for i, m in enumerate(parts["materials"]):
        entry = {"name": m.name, "albedo": m.albedo.tolist(), "emission": m.emission.tolist(), "kind": m.kind,
                 "int_ior": m.int_ior, "alpha_threshold": m.alpha_threshold, "texture": m.albedo_texture is not None}
        if m.albedo_texture is not None:
            arrays[f"tex_{i}"] = np.rint(linear_to_srgb(m.albedo_texture) * 255.0).astype(np.uint8)
        mats.append(entry)
    for i, mask in info.alpha_masks.items():
        arrays[f"alpha_{i}"] = mask
    lights = parts["point_lights"]
    arrays["light_position"] = np.array([lt.position for lt in lights], np.float64).reshape(-1, 3)
    arrays["light_intensity"] = np.array([lt.intensity for lt in lights], np.float32).reshape(-1, 3)
    arrays.update(vis.to_arrays())
    for k in Q3Info.ARRAYS:
        arrays[f"info_{k}"] = getattr(info, k)
    meta = {"materials": mats, "object_names": parts["object_names"], "light_names": [lt.name for lt in lights],
            "info": {k: getattr(info, k) for k in ("map_name", "source", "bsp_sha256", "message", "options",
                                                   "shaders", "lights", "counts")},
            "alpha_masks": sorted(info.alpha_masks)}
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_target(path, suffix=".tmp.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _read_cache(path: Path):
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(bytes(z["meta_json"]).decode())
        materials = []
        alpha = {int(i): z[f"alpha_{i}"] for i in meta["alpha_masks"]}
        for i, m in enumerate(meta["materials"]):
            tex = decode_srgb8(z[f"tex_{i}"]) if m["texture"] else None
            opacity = alpha[i][:, :, None].astype(np.float32) / 255.0 if i in alpha else None
            materials.append(Material(name=m["name"], albedo=np.array(m["albedo"]), albedo_texture=tex,
                                      emission=np.array(m["emission"]), kind=m["kind"], int_ior=m["int_ior"],
                                      opacity_texture=opacity, alpha_threshold=m["alpha_threshold"]))
        pos, inten = z["light_position"], z["light_intensity"]
        lights = [PointLight(n, pos[i], inten[i]) for i, n in enumerate(meta["light_names"])]
        parts = {k: z[k] for k in ("positions", "normals", "uvs", "faces", "face_material", "face_object")}
        parts.update(materials=materials, point_lights=lights, object_names=meta["object_names"])
        vis = Q3Visibility.from_arrays(z)
        info = Q3Info(**meta["info"], **{k: z[f"info_{k}"] for k in Q3Info.ARRAYS}, alpha_masks=alpha)
    return parts, info, vis
