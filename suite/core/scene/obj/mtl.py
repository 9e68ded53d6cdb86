"""MTL materials -> the scene model's :class:`~suite.core.scene.model.Material`, with their textures.

Values come from tinyobjloader's ``material_t`` (``Kd``, ``d``/``Tr``, ``illum``, ``Ks``, ``Ns``, ``Ni``, texture
names). Its Python bindings expose neither the emission ``Ke`` nor texture options, so a statement census of the
MTL text (:func:`mtl_census`, one pass over its lines) supplies those and records every statement the suite does
not model.

Conversion (documented in docs/scenes.md):

* ``Kd`` -> ``albedo``; ``map_Kd`` -> ``albedo_texture`` (decoded by OpenImageIO; 8-bit images from sRGB,
  float images as linear), which replaces ``Kd`` as in most renderers (the MTL specification multiplies them).
* ``Ke`` -> ``emission`` (radiance, W/m^2/sr per linear RGB channel): the material's triangles are area lights.
* ``map_d`` -> ``opacity_texture`` (alpha-tested at 0.5): the image's alpha channel, or the mean of its colour
  channels when it has none (8-bit values / 255).
* Everything else that would change the image (``Ks``/``Ns`` highlights, ``Ka``, ``d`` < 1 without ``map_d``,
  ``illum`` >= 3, ``Ni``/``Tf``, ``Pr``/``Pm``/... PBR terms, bump / normal / displacement / specular / ambient /
  emissive / reflection maps, texture options other than ``-blendu``/``-blendv``/``-boost``) is counted per
  statement in ``unsupported``; a texture file that is missing or unreadable is listed in ``missing_textures``.
  A sidecar material override (docs/scenes.md) can give such a material the kind and parameters it needs.

Textures are looked up relative to the MTL file's folder, with ``\\`` read as ``/`` and, when the exact name is
not there, a case-insensitive match (files authored on Windows). Images larger than ``max_texture_size`` texels
a side are box-filtered down by powers of two in linear light, then stored as 8-bit sRGB again (like the
Quake III textures), so a scene read back from the cache is identical to a freshly converted one.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from suite.errors import UserError
from suite.core.scene.q3.textures import decode_srgb8, linear_to_srgb

# Texture statements and what the suite does with them.
TEXTURE_USED = {"map_Kd": "albedo_texture", "map_d": "opacity_texture"}
TEXTURE_STATEMENTS = {"map_Ka", "map_Kd", "map_Ks", "map_Ns", "map_d", "map_bump", "map_Bump", "bump", "disp",
                      "map_disp", "map_Disp", "decal", "refl", "map_refl", "map_Ke", "map_Pr", "map_Pm", "map_Ps",
                      "map_Tr", "norm", "map_aniso", "map_anisor"}
HARMLESS_OPTIONS = {"-blendu", "-blendv", "-boost"}
OPTION_ARITY = {"-blendu": 1, "-blendv": 1, "-boost": 1, "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1,
                "-clamp": 1, "-bm": 1, "-imfchan": 1, "-type": 1, "-cc": 1, "-colorspace": 1}
# Statements whose effect the model has (or which cannot change the image).
SCALAR_USED = {"newmtl", "Kd", "Ke", "d", "Tr", "illum"}
DEFAULT_MAX_TEXTURE_SIZE = 512


@dataclass
class MtlStatements:
    """One material's statements as written: keyword -> list of argument lists."""

    name: str
    source: str
    statements: dict = field(default_factory=dict)

    def first(self, keyword: str):
        values = self.statements.get(keyword)
        return values[0] if values else None


def mtl_census(path: Path) -> dict[str, MtlStatements]:
    """Material name -> its statements, from one MTL file (comments and blank lines skipped)."""
    try:
        text = path.read_bytes().decode("utf-8", "replace")
    except OSError as exc:
        raise UserError(f"cannot read material file '{path}': {exc.strerror or exc}") from None
    out: dict[str, MtlStatements] = {}
    current = None
    for n, raw in enumerate(text.splitlines(), 1):
        words = raw.split("#", 1)[0].split() if not raw.lstrip().startswith("#") else []
        if not words:
            continue
        kw, args = words[0], words[1:]
        if kw == "newmtl":
            name = raw.strip()[len("newmtl"):].strip()
            current = out.setdefault(name, MtlStatements(name, str(path)))
            continue
        if current is None:
            raise UserError(f"{path}: not a valid MTL file: line {n}: '{kw}' before any 'newmtl'")
        current.statements.setdefault(kw, []).append(args)
    return out


def _options(args: list[str]) -> list[str]:
    """The option names in a texture statement's arguments (``-s 2 2 1 name.png`` -> ``['-s']``)."""
    found, i = [], 0
    while i < len(args) and args[i].startswith("-") and args[i] in OPTION_ARITY:
        opt = args[i]
        found.append(opt)
        i += 1
        taken = 0
        while taken < OPTION_ARITY[opt] and i < len(args) - 1:
            if opt in ("-o", "-s", "-t") and taken >= 1:
                try:
                    float(args[i])
                except ValueError:
                    break
            i += 1
            taken += 1
    return found


def _floats(args, n: int, what: str, mat: MtlStatements) -> np.ndarray:
    try:
        values = [float(a) for a in args[:n]]
    except ValueError:
        values = []
    if len(values) == 1 and n == 3:
        values = values * 3
    if len(values) != n or not np.isfinite(values).all():
        raise UserError(f"{mat.source}: not a valid MTL file: material '{mat.name}': malformed '{what}' "
                        f"{' '.join(args)!r}")
    return np.asarray(values, np.float64)


def find_texture(base_dir: Path, name: str) -> Path | None:
    """A texture file named in an MTL file: the path as written (``\\`` as ``/``) relative to ``base_dir``,
    else a case-insensitive match of each component."""
    rel = name.strip().strip('"').replace("\\", "/")
    p = Path(rel) if os.path.isabs(rel) else base_dir / rel
    if p.is_file():
        return p
    cur = Path(p.anchor) if os.path.isabs(rel) else base_dir
    for part in Path(rel).parts[1:] if os.path.isabs(rel) else Path(rel).parts:
        try:
            match = [c for c in os.listdir(cur) if c.lower() == part.lower()]
        except OSError:
            return None
        if not match:
            return None
        cur = cur / sorted(match)[0]
    return cur if cur.is_file() else None


# --- images ---------------------------------------------------------------------------------------------

@dataclass
class Image:
    """A decoded texture: 8-bit sRGB (or linear float for float files) RGB, and its alpha / matte channel."""

    rgb8: np.ndarray | None  # (H, W, 3) uint8 sRGB, row 0 = top row
    rgb_linear: np.ndarray | None  # (H, W, 3) float32 for float images
    alpha8: np.ndarray | None  # (H, W) uint8 (the alpha channel; the mean of RGB when there is none)
    alpha_float: np.ndarray | None

    def albedo(self) -> np.ndarray:
        if self.rgb8 is not None:
            return decode_srgb8(self.rgb8)
        return np.ascontiguousarray(np.clip(self.rgb_linear, 0.0, None), np.float32)

    def opacity(self) -> np.ndarray:
        if self.alpha8 is not None:
            return (self.alpha8.astype(np.float32) / 255.0)[:, :, None]
        return np.clip(self.alpha_float, 0.0, 1.0).astype(np.float32)[:, :, None]


def read_image(path: Path, max_size: int) -> Image:
    """Decodes an image with OpenImageIO and shrinks it to at most ``max_size`` texels a side."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(oiio.geterror() or "cannot open")
    try:
        spec = inp.spec()
        is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT if is_float else oiio.UINT8)
        if pixels is None or not hasattr(pixels, "shape"):
            raise OSError(inp.geterror() or "cannot read")
    finally:
        inp.close()
    img = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    c = img.shape[2]
    alpha_index = spec.alpha_channel if 0 <= spec.alpha_channel < c else (3 if c == 4 else 1 if c == 2 else -1)
    colour = [i for i in range(c) if i != alpha_index][:3]
    rgb = img[:, :, colour]
    if rgb.shape[2] == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    elif rgb.shape[2] == 2:
        rgb = np.concatenate([rgb, rgb[:, :, 1:]], axis=2)
    if alpha_index >= 0:
        alpha = img[:, :, alpha_index]
    else:
        alpha = rgb.astype(np.float32).mean(axis=2)
        alpha = np.rint(alpha).astype(np.uint8) if not is_float else alpha
    factor = 1
    h, w = rgb.shape[:2]
    while max(h, w) // factor > max_size and min(h, w) // factor >= 2:
        factor *= 2
    if factor > 1:
        h2, w2 = h // factor, w // factor
        crop = rgb[:h2 * factor, :w2 * factor]
        a = alpha[:h2 * factor, :w2 * factor].astype(np.float32).reshape(h2, factor, w2, factor).mean(axis=(1, 3))
        if is_float:
            rgb = crop.astype(np.float32).reshape(h2, factor, w2, factor, 3).mean(axis=(1, 3))
            alpha = a
        else:
            lin = decode_srgb8(crop).reshape(h2, factor, w2, factor, 3).mean(axis=(1, 3))
            rgb = np.rint(linear_to_srgb(lin) * 255.0).astype(np.uint8)
            alpha = np.rint(a).astype(np.uint8)
    if is_float:
        return Image(None, np.ascontiguousarray(rgb, np.float32), None, np.ascontiguousarray(alpha, np.float32))
    return Image(np.ascontiguousarray(rgb, np.uint8), None, np.ascontiguousarray(alpha, np.uint8), None)


class ImageCache:
    """Decodes each texture file once per load; remembers what could not be read."""

    def __init__(self, max_size: int):
        self.max_size = int(max_size)
        self.images: dict[str, Image] = {}
        self.errors: dict[str, str] = {}
        self.files: dict[str, Path] = {}  # texture key -> file read (for the cache's dependency list)

    def get(self, base_dir: Path, name: str) -> tuple[str, Image | None]:
        key = name.strip().replace("\\", "/")
        path = find_texture(base_dir, name)
        if path is None:
            self.errors.setdefault(key, "file not found")
            return key, None
        ident = str(path.resolve())
        if ident not in self.images and ident not in self.errors:
            try:
                self.images[ident] = read_image(path, self.max_size)
                self.files[ident] = path
            except (OSError, ValueError) as exc:
                self.errors[ident] = str(exc).splitlines()[0] if str(exc) else "unreadable"
        if ident in self.errors:
            self.errors.setdefault(key, self.errors[ident])
            return key, None
        return key, self.images[ident]


# --- conversion ---------------------------------------------------------------------------------------

@dataclass
class ConvertedMaterial:
    name: str
    params: dict  # Material keyword arguments (without textures)
    albedo_image: Image | None = None
    opacity_image: Image | None = None
    albedo_texture_name: str = ""
    opacity_texture_name: str = ""
    unsupported: dict = field(default_factory=dict)  # statement -> count
    missing: list = field(default_factory=list)  # texture names that could not be read


def convert(mat, stmts: MtlStatements | None, base_dir: Path, images: ImageCache) -> ConvertedMaterial:
    """One tinyobjloader material (plus its statements) -> Material parameters and textures."""
    name = mat.name
    st = stmts.statements if stmts is not None else {}
    out = ConvertedMaterial(name=name, params={})
    unsupported = out.unsupported

    def note(what: str, n: int = 1):
        unsupported[what] = unsupported.get(what, 0) + n

    kd = np.clip(np.asarray(mat.diffuse, np.float64), 0.0, 1.0)
    emission = np.zeros(3)
    if "Ke" in st:
        emission = np.maximum(_floats(st["Ke"][-1], 3, "Ke", stmts), 0.0)
    out.params.update(albedo=kd, emission=emission)

    # Textures used.
    for kw, slot in (("map_Kd", "albedo"), ("map_d", "opacity")):
        texname = mat.diffuse_texname if kw == "map_Kd" else mat.alpha_texname
        if not texname:
            continue
        for opt in _options(st.get(kw, [[]])[-1]):
            if opt not in HARMLESS_OPTIONS:
                note(f"{kw} {opt}")
        key, img = images.get(base_dir, texname)
        if img is None:
            out.missing.append(key)
            continue
        if slot == "albedo":
            out.albedo_image, out.albedo_texture_name = img, key
        else:
            out.opacity_image, out.opacity_texture_name = img, key
    # Everything else that would change the image.
    for kw, values in st.items():
        if kw in SCALAR_USED or kw in TEXTURE_USED:
            continue
        if kw in TEXTURE_STATEMENTS:
            note(kw, len(values))
        elif kw == "Ka":
            if np.any(np.asarray(mat.ambient) > 0):
                note(kw, len(values))
        elif kw in ("Ks", "Ns"):
            if np.any(np.asarray(mat.specular) > 0):
                note(kw, len(values))
        elif kw in ("Ni", "Tf"):
            if int(mat.illum) >= 4:  # transparency / refraction illumination models
                note(kw, len(values))
        else:
            note(kw, len(values))
    if int(mat.illum) >= 3:
        note(f"illum {int(mat.illum)}")
    if float(mat.dissolve) < 1.0 and out.opacity_image is None and not mat.alpha_texname:
        note("d < 1 (translucency)")
    return out
