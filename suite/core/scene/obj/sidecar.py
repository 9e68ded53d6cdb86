"""Sidecar TOML files: what an OBJ file cannot say (lights, camera path, units, material overrides).

Format (docs/scenes.md has the full description):

```toml
[scene]
name = "dabrovic_sponza"            # project sidecars: the name list_scenes() shows
extends = "other_scene"             # optional: start from that project sidecar; this file's tables replace its
                                    # tables ([scene] key by key, the others whole)
title = "..."                       # one-line description
file = "dabrovic_sponza/sponza.obj" # project sidecars: the OBJ's path on the scene search path
sha256 = "67d1b2..."                # the OBJ file's SHA-256 (required in project sidecars)
licence = "CC BY-NC"                # shown in the description
unit_m = 1.0                        # metres per file unit
up = "y"                            # the file's up axis, "y" or "z" (z-up files are turned to y up)

[materials.stone]                   # overrides an MTL material of that name, or defines a new one
kind = "diffuse"                    # any Material field: albedo, emission, roughness, distribution, ...
albedo = [0.55, 0.50, 0.42]
texture = "tex/stone.png"           # albedo texture, relative to the OBJ's folder; opacity = "..." likewise

[objects]                           # OBJ object / group names (glob patterns) -> material; first match wins
"arcs_*" = "stone"

[[lights]]                          # point lights, scene coordinates (metres, y up)
name = "lantern"
position = [0.0, 3.0, 0.0]
intensity = [10.0, 9.0, 8.0]        # W/sr (a number means grey)
keys = [{ t = 0.0, position = [0, 3, -5] }, { t = 3.5, position = [0, 3, 5] }]   # optional path

[camera]
position = [-9.0, 1.7, 0.0]
yaw_deg = -90.0                     # 0 looks down -z, positive turns left (CameraScript)
pitch_deg = 0.0
fov_deg = 75.0
resolution = [320, 180]
fps = 30.0
moves = [{ walk = 3.0, s = 1.2 }, { turn = 90.0, s = 0.3 }, { hold = 0.2 }, { walk = -2.0, s = 1.0 }]
```
"""
from __future__ import annotations

import fnmatch
import hashlib
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.search import DATA_DIR

SIDECAR_SUFFIX = ".splitbench.toml"
SCENE_KEYS = {"name", "title", "file", "sha256", "licence", "license", "unit_m", "up", "description", "extends"}
LIGHT_KEYS = {"name", "position", "intensity", "keys"}
CAMERA_KEYS = {"position", "yaw_deg", "pitch_deg", "fov_deg", "resolution", "fps", "moves"}
MATERIAL_FIELDS = {"kind", "albedo", "emission", "specular_reflectance", "specular_transmittance", "int_ior",
                   "ext_ior", "conductor_eta", "conductor_k", "roughness", "distribution", "nonlinear", "twosided",
                   "alpha_threshold"}
MATERIAL_FILES = {"texture", "opacity"}
TOP_KEYS = {"scene", "materials", "objects", "lights", "camera"}


@dataclass
class Sidecar:
    path: Path
    text_sha256: str
    scene: dict = field(default_factory=dict)
    materials: dict = field(default_factory=dict)
    objects: dict = field(default_factory=dict)
    lights: list = field(default_factory=list)
    camera: dict | None = None

    @property
    def name(self) -> str | None:
        return self.scene.get("name")

    @property
    def sha256(self) -> str | None:
        s = self.scene.get("sha256")
        return str(s).lower() if s else None

    @property
    def unit_m(self) -> float:
        return float(self.scene.get("unit_m", 1.0))

    @property
    def up(self) -> str:
        return str(self.scene.get("up", "y")).lower()

    def check_hash(self, obj_path: Path, obj_sha256: str) -> None:
        if self.sha256 and self.sha256 != obj_sha256:
            raise UserError(f"sidecar '{self.path}' is for an OBJ file with SHA-256 {self.sha256}, but '{obj_path}' has "
                            f"SHA-256 {obj_sha256} (a different version of the model; fix the file or the sidecar)")

    def material_for_object(self, object_name: str) -> str | None:
        for pattern, material in self.objects.items():
            if fnmatch.fnmatchcase(object_name, pattern):
                return material
        return None


def _err(path, msg: str) -> UserError:
    return UserError(f"sidecar '{path}': {msg}")


def _vec(path, where: str, value, n: int = 3) -> np.ndarray:
    try:
        v = np.asarray(value, np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise _err(path, f"{where} must be {n} numbers, got {value!r}") from None
    if v.size == 1 and n == 3:
        v = np.repeat(v, 3)
    if v.shape != (n,) or not np.isfinite(v).all():
        raise _err(path, f"{where} must be {n} finite numbers, got {value!r}")
    return v


def _read_doc(path: Path) -> tuple[bytes, dict]:
    try:
        raw = path.read_bytes()
        doc = tomllib.loads(raw.decode("utf-8"))
    except OSError as exc:
        raise _err(path, f"cannot read: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise _err(path, f"not valid TOML: {exc}") from None
    unknown = set(doc) - TOP_KEYS
    if unknown:
        raise _err(path, f"unknown table '{sorted(unknown)[0]}' (allowed: {', '.join(sorted(TOP_KEYS))})")
    return raw, doc


def _extended(path: Path, raw: bytes, doc: dict) -> tuple[bytes, dict]:
    """``doc`` on top of the project sidecar its ``[scene] extends`` names (one level: a base extends nothing), and
    the bytes of both files (the scene's identity changes with either)."""
    base_name = doc.get("scene", {}).get("extends")
    if base_name is None:
        return raw, doc
    base_path = project_sidecars().get(str(base_name))
    if base_path is None or base_path.resolve() == path.resolve():
        raise _err(path, f"[scene] extends '{base_name}', which is no other project sidecar (known: "
                         f"{', '.join(sorted(project_sidecars()))})")
    base_raw, base = _read_doc(base_path)
    if "extends" in base.get("scene", {}):
        raise _err(path, f"[scene] extends '{base_name}', which extends another sidecar (one level only)")
    merged = {**base, **{k: v for k, v in doc.items() if k != "scene"}}
    merged["scene"] = {**base.get("scene", {}), **doc.get("scene", {})}
    return base_raw + b"\0" + raw, merged


def read_sidecar(path: Path) -> Sidecar:
    """Parses and checks a sidecar file (unknown keys are errors, so a typo does not pass unnoticed)."""
    raw, doc = _extended(path, *_read_doc(path))
    sc = Sidecar(path=path, text_sha256=hashlib.sha256(raw).hexdigest())
    sc.scene = dict(doc.get("scene", {}))
    bad = set(sc.scene) - SCENE_KEYS
    if bad:
        raise _err(path, f"[scene]: unknown key '{sorted(bad)[0]}' (allowed: {', '.join(sorted(SCENE_KEYS))})")
    if sc.up not in ("y", "z"):
        raise _err(path, f"[scene] up must be \"y\" or \"z\", got {sc.scene.get('up')!r}")
    if not sc.unit_m > 0:
        raise _err(path, f"[scene] unit_m must be positive, got {sc.scene.get('unit_m')!r}")
    if sc.sha256 and (len(sc.sha256) != 64 or any(c not in "0123456789abcdef" for c in sc.sha256)):
        raise _err(path, f"[scene] sha256 must be 64 hex digits, got {sc.scene.get('sha256')!r}")
    for name, entry in doc.get("materials", {}).items():
        if not isinstance(entry, dict):
            raise _err(path, f"[materials.{name}] must be a table")
        bad = set(entry) - MATERIAL_FIELDS - MATERIAL_FILES
        if bad:
            raise _err(path, f"[materials.{name}]: unknown key '{sorted(bad)[0]}' (allowed: "
                             f"{', '.join(sorted(MATERIAL_FIELDS | MATERIAL_FILES))})")
        sc.materials[name] = dict(entry)
    objects = doc.get("objects", {})
    for pattern, mat in objects.items():
        if not isinstance(mat, str):
            raise _err(path, f"[objects] '{pattern}' must name a material, got {mat!r}")
        if mat not in sc.materials:
            raise _err(path, f"[objects] '{pattern}' = '{mat}': no [materials.{mat}] table")
    sc.objects = dict(objects)
    for i, light in enumerate(doc.get("lights", [])):
        bad = set(light) - LIGHT_KEYS
        if bad:
            raise _err(path, f"light {i}: unknown key '{sorted(bad)[0]}' (allowed: {', '.join(sorted(LIGHT_KEYS))})")
        name = str(light.get("name", f"light_{i}"))
        if "position" not in light or "intensity" not in light:
            raise _err(path, f"light '{name}' needs position and intensity")
        entry = {"name": name, "position": _vec(path, f"light '{name}' position", light["position"]),
                 "intensity": _vec(path, f"light '{name}' intensity", light["intensity"])}
        if (entry["intensity"] < 0).any():
            raise _err(path, f"light '{name}' intensity must not be negative")
        keys = light.get("keys")
        if keys:
            try:
                times = np.array([float(k["t"]) for k in keys])
                pos = np.stack([_vec(path, f"light '{name}' key position", k["position"]) for k in keys])
            except (KeyError, TypeError, ValueError):
                raise _err(path, f"light '{name}' keys must be tables with t and position") from None
            if not (np.diff(times) > 0).all():
                raise _err(path, f"light '{name}' key times must increase")
            entry["keys"] = (times, pos)
        sc.lights.append(entry)
    if "camera" in doc:
        cam = dict(doc["camera"])
        bad = set(cam) - CAMERA_KEYS
        if bad:
            raise _err(path, f"[camera]: unknown key '{sorted(bad)[0]}' (allowed: {', '.join(sorted(CAMERA_KEYS))})")
        if "position" not in cam:
            raise _err(path, "[camera] needs a position")
        sc.camera = cam
    return sc


def material_overrides(sc: Sidecar | None, name: str, base_dir: Path, images) -> tuple[dict, dict]:
    """``[materials.<name>]`` as Material keyword arguments, and the images it names (``{"albedo": Image,
    "opacity": Image}``, read through ``images`` relative to ``base_dir``)."""
    if sc is None or name not in sc.materials:
        return {}, {}
    out, imgs = {}, {}
    for k, v in sc.materials[name].items():
        if k in ("albedo", "emission", "specular_reflectance", "specular_transmittance", "conductor_eta",
                 "conductor_k"):
            out[k] = _vec(sc.path, f"[materials.{name}] {k}", v)
        elif k in MATERIAL_FILES:
            key, img = images.get(base_dir, str(v))
            if img is None:
                raise _err(sc.path, f"[materials.{name}] {k} '{v}' cannot be read "
                                    f"({images.errors.get(key, 'not found')}; looked in '{base_dir}')")
            imgs["albedo" if k == "texture" else "opacity"] = img
        else:
            out[k] = v
    return out, imgs


def camera_path(sc: Sidecar):
    """The sidecar's camera as a :class:`~suite.core.scene.model.CameraPath` (CameraScript moves)."""
    from suite.core.scene.builder import CameraScript
    from suite.core.scene.model import CameraPath

    cam = sc.camera
    pos = _vec(sc.path, "[camera] position", cam["position"])
    script = CameraScript(pos, yaw_deg=float(cam.get("yaw_deg", 0.0)), pitch_deg=float(cam.get("pitch_deg", 0.0)))
    script.play(cam.get("moves", []), f"sidecar '{sc.path}': [camera]")
    res = cam.get("resolution", [320, 180])
    return CameraPath(keys=script.keys, fov_deg=float(cam.get("fov_deg", 75.0)),
                      resolution=(int(res[0]), int(res[1])), fps=float(cam.get("fps", 30.0)))


# --- discovery ----------------------------------------------------------------------------------------

def project_sidecars() -> dict[str, Path]:
    """Scene name -> sidecar file in the project's data folder (``suite/core/scene/data/*.toml``)."""
    out = {}
    for p in sorted(DATA_DIR.glob("*.toml")):
        try:
            doc = tomllib.loads(p.read_text())
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
            continue
        name = doc.get("scene", {}).get("name")
        if name:
            out[str(name)] = p
    return out


def sidecar_for(obj_path: Path, obj_sha256: str) -> Sidecar | None:
    """The sidecar of an OBJ file given by path: ``<stem>.splitbench.toml`` beside it, else a project sidecar
    whose ``sha256`` is the file's."""
    beside = obj_path.with_name(obj_path.stem + SIDECAR_SUFFIX)
    if beside.is_file():
        return read_sidecar(beside)
    for p in project_sidecars().values():
        sc = read_sidecar(p)
        if sc.sha256 == obj_sha256:
            return sc
    return None
