"""Mitsuba 3 scenes in and out.

``load_mitsuba`` turns a Mitsuba scene (XML file or dict) into a :class:`~suite.core.scene.model.Scene`; it goes
through Mitsuba's own loader, so anything Mitsuba can read as a triangle mesh works. ``to_mitsuba_dict``
writes any Scene back as a Mitsuba dict, so the reference renderer sees exactly the geometry, materials and
lights that the methods trace.

Supported (docs/core.md has the full mapping):

* BSDFs: ``diffuse`` (RGB or bitmap reflectance), ``conductor`` (kind mirror: eta, k or a ``material`` preset,
  specular_reflectance), ``roughconductor`` (isotropic ``alpha``, ``beckmann`` or ``ggx``), ``dielectric``
  (kind glass: int_ior / ext_ior, specular_reflectance / transmittance), ``roughplastic``; ``twosided`` around
  a diffuse, conductor or plastic BSDF (one BSDF for both sides); ``mask`` with a bitmap ``opacity`` around any of
  them (the alpha test, threshold 0.5). Bitmaps: bilinear, repeating, identity ``to_uv``; 8/16-bit files are
  linearised the way Mitsuba looks them up (sRGB unless ``raw``).
* Emitters: ``point``; ``area`` on a shape, with constant radiance.
* Shapes Mitsuba turns into triangle meshes (obj, ply, serialized, rectangle, cube; disk is *not* a mesh) plus
  ``sphere`` tessellated to ``sphere_resolution``; one ``perspective`` sensor with an uncropped ``hdrfilm``.
  Integrators, samplers and reconstruction filters are rendering settings: accepted and not used.

Strictness: before Mitsuba builds the scene, every node of its parsed description (Mitsuba >= 3.7's scene parser)
is checked: plugin by plugin, parameter by parameter, nested objects and references included. Anything the suite
does not model raises a one-line ``UserError`` naming the plugin or parameter and the shape (or object) id.
Objects a scene dict carries already built are checked through what Mitsuba exposes (class, parameters).
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from suite.errors import UserError
from suite.core.scene.model import CameraKey, CameraPath, Material, PointLight, Scene

SUPPORTED_BSDFS = ("diffuse", "conductor", "roughconductor", "dielectric", "roughplastic", "twosided", "mask")
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
    from suite.core.env import mitsuba, variant_of

    # Reading a scene does not depend on the variant: a dict carrying Mitsuba objects is read with theirs, anything
    # else with the default one (never the LLVM backend on a machine that only has CUDA; see suite.core.env).
    mi = mitsuba(variant_of(source) if isinstance(source, dict) else None)
    if not isinstance(source, dict) and not os.path.exists(os.fspath(source)):
        raise UserError(f"scene file '{os.fspath(source)}' does not exist")
    _DescriptionCheck.run(mi, source)  # strictness first: nothing unmodelled reaches the scene silently
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


# --- strictness: the scene description --------------------------------------------------------------
# Every node of the parsed description (Mitsuba >= 3.7's scene parser) is checked before Mitsuba builds the scene:
# its plugin must be one the suite models in that place, and every parameter it sets must be one the suite reads
# (or one that cannot change what is rendered). The first violation is a one-line UserError naming the plugin,
# the parameter and the shape (or object) it belongs to.
_CONSTANT_TEXTURES = ("uniform", "srgb")
_TRANSFORM_PARAMS = ("to_world",)
_SHAPE_PARAMS = {
    "obj": ("filename", "face_normals", "flip_tex_coords", "max_smooth_angle"),
    "ply": ("filename", "face_normals", "flip_tex_coords", "max_smooth_angle"),
    "serialized": ("filename", "shape_index", "face_normals", "max_smooth_angle"),
    "rectangle": (), "cube": (), "sphere": ("center", "radius"),
}
_BSDF_PARAMS = {  # parameter -> what it may be: "color" (constant), "texture" (constant or bitmap), "float", "any"
    "diffuse": {"reflectance": "texture"},
    "conductor": {"eta": "color", "k": "color", "material": "any", "specular_reflectance": "color"},
    "roughconductor": {"eta": "color", "k": "color", "material": "any", "specular_reflectance": "color",
                       "alpha": "color", "distribution": "any", "sample_visible": "any"},
    "dielectric": {"int_ior": "any", "ext_ior": "any", "specular_reflectance": "color",
                   "specular_transmittance": "color"},
    "roughplastic": {"diffuse_reflectance": "texture", "specular_reflectance": "color", "int_ior": "any",
                     "ext_ior": "any", "alpha": "float", "distribution": "any", "nonlinear": "any",
                     "sample_visible": "any"},
    "twosided": {}, "mask": {"opacity": "bitmap"},
}
_ONE_SIDED_LEAVES = ("diffuse", "conductor", "roughconductor", "roughplastic")  # what twosided may wrap
_SENSOR_PARAMS = ("to_world", "fov", "fov_axis", "focal_length", "near_clip", "far_clip", "focus_distance",
                  "principal_point_offset_x", "principal_point_offset_y", "shutter_open", "shutter_close")
_FILM_PARAMS = ("width", "height", "pixel_format", "component_format", "file_format", "sample_border",
                "compensate", "banner", "crop_offset_x", "crop_offset_y", "crop_width", "crop_height")


class _DescriptionCheck:
    def __init__(self, mi, state):
        from mitsuba import parser

        self.mi, self.parser, self.state = mi, parser, state
        self.T = mi.ObjectType

    @staticmethod
    def run(mi, source) -> None:
        try:
            from mitsuba import parser
        except ImportError:  # Mitsuba < 3.7 has no scene parser: only the built objects are checked
            return
        cfg = parser.ParserConfig(mi.variant())
        try:
            state = parser.parse_dict(cfg, source) if isinstance(source, dict) else parser.parse_file(cfg, os.fspath(source))
            parser.transform_upgrade(cfg, state)
            parser.transform_resolve(cfg, state)
        except Exception as exc:  # noqa: BLE001 - Mitsuba raises RuntimeError with multi-line text
            what = "the scene dict" if isinstance(source, dict) else f"'{os.fspath(source)}'"
            raise UserError(f"Mitsuba could not load {what}: {_first_line(exc)}") from None
        _DescriptionCheck(mi, state).scene(state.root)

    # -- helpers
    def node_of(self, value):
        P = self.mi.Properties
        if isinstance(value, P.ResolvedReference):
            return self.state.nodes[value.index()]
        if isinstance(value, P.Reference):
            index = self.state.id_to_index.get(value.id())
            return None if index is None else self.state.nodes[index]
        return None

    def items(self, node):
        """(name, value, child node or None) of a node's properties."""
        for name in node.props.keys():
            value = node.props[name]
            yield name, value, self.node_of(value)

    @staticmethod
    def fail(where: str, what: str):
        raise UserError(f"{where}: {what}")

    def media(self, where, child, name):
        kind = {self.T.Medium: "medium", self.T.PhaseFunction: "phase function", self.T.Volume: "volume"}.get(child.type)
        if kind is not None:
            self.fail(where, f"participating media are not modelled ({kind} '{child.props.plugin_name()}' as "
                             f"'{name}')")

    # -- scene
    def scene(self, root):
        for name, value, child in self.items(root):
            if child is None:
                continue  # a built object (checked when read) or a plain value
            plugin, ident = child.props.plugin_name(), child.props.id() or name
            if child.type == self.T.Shape:
                self.shape(child, f"shape '{ident}'")
            elif child.type == self.T.Emitter:
                self.emitter(child, f"emitter '{ident}'", in_shape=False)
            elif child.type == self.T.Sensor:
                self.sensor(child, f"sensor '{ident}'")
            elif child.type == self.T.BSDF:
                self.bsdf(child, f"bsdf '{ident}'")
            elif child.type == self.T.Texture:
                self.texture(child, f"texture '{ident}'", "texture", "texture")
            elif child.type in (self.T.Integrator, self.T.Sampler, self.T.ReconstructionFilter):
                continue  # rendering settings, not scene content: the suite renders with its own
            else:
                self.media(f"object '{ident}'", child, name)
                self.fail(f"object '{ident}'", f"unsupported {str(child.type).split('.')[-1].lower()} plugin "
                                               f"'{plugin}' at the top level of the scene")

    # -- shapes and emitters
    def shape(self, node, where):
        plugin = node.props.plugin_name()
        if plugin not in _SHAPE_PARAMS:
            self.fail(where, f"unsupported shape plugin '{plugin}' (supported: {', '.join(_SHAPE_PARAMS)})")
        allowed = _SHAPE_PARAMS[plugin] + _TRANSFORM_PARAMS
        for name, value, child in self.items(node):
            if child is not None:
                self.media(where, child, name)
                if child.type == self.T.BSDF:
                    self.bsdf(child, where)
                elif child.type == self.T.Emitter:
                    self.emitter(child, where, in_shape=True)
                else:
                    self.fail(where, f"unsupported {str(child.type).split('.')[-1].lower()} "
                                     f"'{child.props.plugin_name()}' as {plugin} parameter '{name}'")
            elif name == "flip_normals":
                if bool(value):
                    self.fail(where, f"{plugin} parameter 'flip_normals' is not supported")
            elif name not in allowed and not isinstance(value, self.mi.Object):
                self.fail(where, f"{plugin} parameter '{name}' is not supported")

    def emitter(self, node, where, in_shape: bool):
        plugin = node.props.plugin_name()
        allowed = {"point": ("position", "to_world", "intensity"), "area": ("radiance",)}
        if plugin not in allowed or (plugin == "area") != in_shape:
            self.fail(where, f"unsupported emitter plugin '{plugin}'" + (" nested in a shape" if in_shape else "")
                      + " (supported: point, area on a shape)")
        for name, value, child in self.items(node):
            if name not in allowed[plugin]:
                self.fail(where, f"{plugin} emitter parameter '{name}' is not supported")
            if child is not None:
                self.texture(child, where, name, "color")

    # -- sensors
    def sensor(self, node, where):
        plugin = node.props.plugin_name()
        if plugin != "perspective":
            self.fail(where, f"sensor plugin '{plugin}' is not supported (use 'perspective')")
        for name, value, child in self.items(node):
            if child is not None:
                self.media(where, child, name)
                if child.type == self.T.Film:
                    self.film(child, where)
                elif child.type != self.T.Sampler:
                    self.fail(where, f"unsupported {str(child.type).split('.')[-1].lower()} "
                                     f"'{child.props.plugin_name()}' as perspective parameter '{name}'")
            elif name not in _SENSOR_PARAMS:
                self.fail(where, f"perspective parameter '{name}' is not supported")
            elif name.startswith("principal_point_offset") and float(value) != 0.0:
                self.fail(where, f"perspective parameter '{name}' (an off-centre projection) is not supported")

    def film(self, node, where):
        plugin = node.props.plugin_name()
        if plugin != "hdrfilm":
            self.fail(where, f"film plugin '{plugin}' is not supported (use 'hdrfilm')")
        props = node.props
        for name, value, child in self.items(node):
            if child is not None:
                if child.type != self.T.ReconstructionFilter:
                    self.fail(where, f"unsupported '{child.props.plugin_name()}' nested in the film")
            elif name not in _FILM_PARAMS:
                self.fail(where, f"hdrfilm parameter '{name}' is not supported")
        keys = set(props.keys())
        crop = [int(props[k]) for k in ("crop_offset_x", "crop_offset_y") if k in keys]
        full = all(k not in keys or (d in keys and int(props[k]) == int(props[d]))
                   for k, d in (("crop_width", "width"), ("crop_height", "height")))
        if any(crop) or not full:
            self.fail(where, "a cropped film is not supported (crop_offset_*, crop_width, crop_height)")

    # -- materials
    def bsdf(self, node, where, inside: str = ""):
        plugin = node.props.plugin_name()
        if plugin not in _BSDF_PARAMS:
            self.fail(where, f"unsupported BSDF plugin '{plugin}'" + (f" inside {inside}" if inside else "")
                      + f" (supported: {SUPPORTED_BSDF_TEXT})")
        if inside == "twosided" and plugin not in _ONE_SIDED_LEAVES:
            self.fail(where, f"twosided must wrap one of {', '.join(_ONE_SIDED_LEAVES)}, not '{plugin}'")
        if inside == "mask" and plugin == "mask":
            self.fail(where, "a mask inside a mask is not supported")
        rules = _BSDF_PARAMS[plugin]
        nested = []
        for name, value, child in self.items(node):
            if child is not None and child.type == self.T.BSDF:
                nested.append(child)
                continue
            if name not in rules:
                self.fail(where, f"{plugin} parameter '{name}' is not supported")
            rule = rules[name]
            if child is not None:
                self.texture(child, where, name, rule)
            elif rule == "bitmap":
                self.fail(where, f"{plugin} '{name}' must be a bitmap (a constant opacity is stochastic transparency, "
                                 "not modelled)")
            elif name == "distribution" and str(value).lower() not in ("beckmann", "ggx"):
                self.fail(where, f"{plugin} distribution '{value}' is not supported")
        if plugin in ("twosided", "mask"):
            if not nested:
                self.fail(where, f"{plugin} BSDF has no nested BSDF")
            if plugin == "mask" and len(nested) != 1:
                self.fail(where, "mask must wrap exactly one BSDF")
            if plugin == "twosided" and len(nested) == 2 and not nested[0] == nested[1]:
                self.fail(where, "twosided BSDF with different front and back BSDFs is not supported")
            for child in nested:
                self.bsdf(child, where, inside=plugin)
        elif nested:
            self.fail(where, f"{plugin} does not take a nested BSDF")

    def texture(self, node, where, param: str, rule: str):
        plugin = node.props.plugin_name()
        if node.type != self.T.Texture:
            self.fail(where, f"'{param}' must be a texture, got {str(node.type).split('.')[-1].lower()} '{plugin}'")
        if plugin in _CONSTANT_TEXTURES and rule in ("color", "texture", "float"):
            return
        if plugin == "bitmap" and rule in ("texture", "bitmap"):
            self.bitmap(node, where, param)
            return
        allowed = {"color": "a constant", "float": "a constant", "texture": "a constant or a bitmap",
                   "bitmap": "a bitmap"}[rule]
        self.fail(where, f"unsupported texture plugin '{plugin}' for '{param}' (must be {allowed})")

    def bitmap(self, node, where, param):
        for name, value, child in self.items(node):
            if name in ("filename", "data", "raw", "format", "accel"):
                continue
            if name == "filter_type" and str(value) == "bilinear":
                continue
            if name == "wrap_mode" and str(value) == "repeat":
                continue
            if name == "to_uv" and np.allclose(np.array(value.matrix, np.float64), np.eye(4)):
                continue
            shown = f" '{value}'" if name in ("filter_type", "wrap_mode") else ""
            self.fail(where, f"bitmap parameter '{name}'{shown} of '{param}' is not supported (the suite looks "
                             "textures up bilinearly, repeating, with identity UVs)")


# --- BSDFs from built Mitsuba objects --------------------------------------------------------------
# Mitsuba class name -> plugin name, for messages about objects (the description check names plugins directly).
_CLASS_TO_PLUGIN = {
    "SmoothDiffuse": "diffuse", "TwoSidedBRDF": "twosided", "TwoSided": "twosided", "Mask": "mask",
    "SmoothConductor": "conductor",
    "RoughConductor": "roughconductor", "SmoothDielectric": "dielectric", "RoughPlastic": "roughplastic",
    "MaskBSDF": "mask", "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
    "SmoothPlastic": "plastic", "BumpMap": "bumpmap", "NormalMap": "normalmap", "BlendBSDF": "blendbsdf",
    "NullBSDF": "null", "Principled": "principled", "PrincipledThin": "principledthin", "Polarizer": "polarizer",
    "Retarder": "retarder", "CircularPolarizer": "circular", "MeasuredBSDF": "measured", "HairBSDF": "hair",
    "PolarizedPlastic": "pplastic", "MeasuredPolarized": "measured_polarized",
}
SUPPORTED_BSDF_TEXT = "diffuse, conductor, roughconductor, dielectric, roughplastic, twosided, mask"
# sRGB -> linear for 8/16-bit bitmaps (Mitsuba keeps integer texels and converts them at lookup unless raw).


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _bitmap_texels(params, key: str, raw: bool) -> np.ndarray:
    """(H, W, C) float32 linear texels of a Mitsuba bitmap's ``data`` the way its lookups see them: integer
    formats scaled to [0, 1] and, unless ``raw``, converted from sRGB (float formats are linear already)."""
    arr = np.array(params[key])
    if arr.ndim == 2:
        arr = arr[..., None]
    if np.issubdtype(arr.dtype, np.integer):
        tex = arr.astype(np.float64) / float(np.iinfo(arr.dtype).max)
        if not raw:
            tex = _srgb_to_linear(tex)
    else:
        tex = arr.astype(np.float64)
    return np.ascontiguousarray(tex, np.float32)


class _BsdfReader:
    """Reads one Mitsuba BSDF object (and what it nests) into a Material, rejecting what the suite does not model.

    Works on built objects, so it also covers objects a scene dict carries already built; what Mitsuba does not
    expose there (a bitmap's filter and wrap modes) is checked on the scene description instead."""

    def __init__(self, mi, bsdf, shape_id: str):
        self.mi, self.shape_id = mi, shape_id
        self.params = mi.traverse(bsdf)
        self.keys = set(self.params.keys())
        self.text = str(bsdf)
        self.top = _class_name(bsdf)

    def fail(self, what: str):
        raise UserError(f"shape '{self.shape_id}': {what}")

    def plugin(self, cls: str) -> str:
        return _CLASS_TO_PLUGIN.get(cls, cls)

    def nested_class(self, label: str) -> str:
        import re

        m = re.search(re.escape(label) + r" = (\w+)\[", self.text)
        if m is None:
            self.fail(f"cannot tell which BSDF is nested in '{label}'")
        return m.group(1)

    def option(self, name: str, default: str) -> str:
        import re

        m = re.search(r"\b" + name + r" = (\w+)", self.text)
        return m.group(1) if m else default

    def bitmap_raw(self, name: str) -> bool:
        """The ``raw`` flag of the bitmap bound to parameter ``name`` (one BSDF leaf has one of each name)."""
        import re

        m = re.search(r"\b" + re.escape(name) + r" = BitmapTexture\[.*?raw = (\d)", self.text, re.S)
        if m is None:
            self.fail(f"cannot read the raw flag of bitmap '{name}'")
        return m.group(1) == "1"

    def sub(self, prefix: str) -> set:
        return {k[len(prefix):] for k in self.keys if k.startswith(prefix)}

    def rgb(self, key: str) -> np.ndarray:
        value = np.array(self.params[key], np.float64).reshape(-1)
        if value.size not in (1, 3):
            self.fail(f"parameter '{key}' has {value.size} values (expected 1 or 3)")
        return np.broadcast_to(value, (3,)).astype(np.float32)

    def scalar(self, key: str) -> float:
        return float(np.array(self.params[key], np.float64).reshape(-1)[0])

    def texture(self, prefix: str, name: str, allow_bitmap: bool):
        """(constant RGB, texture or None) of texture parameter ``name`` under ``prefix``."""
        keys = {k for k in self.sub(prefix) if k == name or k.startswith(name + ".")}
        if keys == {name + ".value"}:
            return self.rgb(prefix + name + ".value"), None
        if allow_bitmap and keys <= {name + ".data", name + ".to_uv"} and name + ".data" in keys:
            if name + ".to_uv" in keys:
                m = np.array(self.params[prefix + name + ".to_uv"].matrix, np.float64).reshape(3, 3)
                if not np.allclose(m, np.eye(3)):
                    self.fail(f"bitmap '{name}' has a to_uv transform, which is not supported")
            tex = _bitmap_texels(self.params, prefix + name + ".data", self.bitmap_raw(name))
            return None, tex
        kinds = "an RGB value or a bitmap" if allow_bitmap else "an RGB value"
        self.fail(f"unsupported texture for '{name}' (use {kinds})")

    def read(self) -> Material:
        cls, prefix, opacity, twosided = self.top, "", None, False
        if self.plugin(cls) == "mask":
            value, tex = self.texture("", "opacity", allow_bitmap=True) if self.sub("opacity") else (None, None)
            if tex is None:
                self.fail("mask opacity must be a bitmap (a constant opacity is stochastic transparency, not modelled)")
            if tex.shape[2] != 1:
                self.fail(f"mask opacity bitmap must have one channel, got {tex.shape[2]}")
            opacity, prefix, cls = tex, "nested_bsdf.", self.nested_class("nested_bsdf")
            if self.plugin(cls) == "mask":
                self.fail("a mask inside a mask is not supported")
        if self.plugin(cls) == "twosided":
            if self.sub(prefix + "brdf_1."):
                self.fail("twosided BSDF with different front and back BSDFs is not supported")
            cls = self.nested_class("brdf[0]")
            twosided, prefix = True, prefix + "brdf_0."
        mat = self.leaf(cls, prefix, twosided)
        mat.opacity_texture = opacity
        return Material(**{f.name: getattr(mat, f.name) for f in dataclasses.fields(Material)})

    def leaf(self, cls: str, prefix: str, twosided: bool) -> Material:
        plugin = self.plugin(cls)
        keys = self.sub(prefix)
        name = self.shape_id

        def only(*allowed):
            extra = sorted(k for k in keys if k.split(".")[0] not in allowed)
            if extra:
                self.fail(f"{plugin} parameter '{extra[0]}' is not supported")

        if plugin == "diffuse":
            only("reflectance")
            value, tex = self.texture(prefix, "reflectance", allow_bitmap=True)
            if tex is not None:
                if tex.shape[2] not in (1, 3):
                    self.fail(f"reflectance bitmap must have 1 or 3 channels, got {tex.shape[2]}")
                tex = np.ascontiguousarray(np.repeat(tex, 3, axis=-1) if tex.shape[2] == 1 else tex)
                return Material(name, albedo=tex.reshape(-1, 3).mean(axis=0), albedo_texture=tex)
            return Material(name, albedo=value)
        if plugin in ("conductor", "roughconductor"):
            only("eta", "k", "specular_reflectance", "alpha")
            if "alpha_u.value" in keys or "alpha_v.value" in keys:
                self.fail("roughconductor with anisotropic roughness (alpha_u, alpha_v) is not supported")
            eta, _ = self.texture(prefix, "eta", allow_bitmap=False)
            k, _ = self.texture(prefix, "k", allow_bitmap=False)
            spec = self.texture(prefix, "specular_reflectance", False)[0] if "specular_reflectance.value" in keys \
                else np.ones(3, np.float32)
            if plugin == "conductor":
                return Material(name, albedo=np.zeros(3), kind="mirror", conductor_eta=eta, conductor_k=k,
                                specular_reflectance=spec, twosided=twosided)
            alpha, _ = self.texture(prefix, "alpha", allow_bitmap=False)
            return Material(name, albedo=np.zeros(3), kind="rough_conductor", conductor_eta=eta, conductor_k=k,
                            specular_reflectance=spec, roughness=float(alpha[0]),
                            distribution=self.option("distribution", "beckmann"), twosided=twosided)
        if plugin == "dielectric":
            only("eta", "specular_reflectance", "specular_transmittance")
            ones = np.ones(3, np.float32)
            spec_r = self.texture(prefix, "specular_reflectance", False)[0] if "specular_reflectance.value" in keys else ones
            spec_t = self.texture(prefix, "specular_transmittance", False)[0] if "specular_transmittance.value" in keys \
                else ones
            # Mitsuba exposes only the relative IOR: the material keeps it as int_ior over ext_ior = 1.
            return Material(name, albedo=np.zeros(3), kind="glass", int_ior=self.scalar(prefix + "eta"), ext_ior=1.0,
                            specular_reflectance=spec_r, specular_transmittance=spec_t)
        if plugin == "roughplastic":
            only("diffuse_reflectance", "specular_reflectance", "alpha", "eta")
            value, tex = self.texture(prefix, "diffuse_reflectance", allow_bitmap=True)
            if tex is not None:
                if tex.shape[2] not in (1, 3):
                    self.fail(f"diffuse_reflectance bitmap must have 1 or 3 channels, got {tex.shape[2]}")
                tex = np.ascontiguousarray(np.repeat(tex, 3, axis=-1) if tex.shape[2] == 1 else tex)
                value = tex.reshape(-1, 3).mean(axis=0)
            spec = self.texture(prefix, "specular_reflectance", False)[0] if "specular_reflectance.value" in keys \
                else np.ones(3, np.float32)
            return Material(name, albedo=value, albedo_texture=tex, kind="rough_plastic",
                            int_ior=self.scalar(prefix + "eta"), ext_ior=1.0, specular_reflectance=spec,
                            roughness=self.scalar(prefix + "alpha"), distribution=self.option("distribution", "beckmann"),
                            nonlinear=self.option("nonlinear", "0") == "1", twosided=twosided)
        where = "inside twosided " if twosided else ""
        self.fail(f"unsupported BSDF plugin '{plugin}' {where}(supported: {SUPPORTED_BSDF_TEXT})".replace("  ", " "))


def _material_from_bsdf(mi, bsdf, shape_id: str) -> Material:
    """The Material of a shape's Mitsuba BSDF (named after the BSDF's id, else the shape's)."""
    mat = _BsdfReader(mi, bsdf, shape_id).read()
    mat.name = bsdf.id() or shape_id
    return mat


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
        for side in ("interior", "exterior"):
            if getattr(shape, f"{side}_medium", lambda: None)() is not None:
                raise UserError(f"shape '{shape_id}': participating media are not modelled ({side} medium)")
        if getattr(shape, "is_sensor", lambda: False)():
            raise UserError(f"shape '{shape_id}': a sensor attached to a shape is not supported")
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
        key = _material_key(mat)
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


def _material_key(mat: Material) -> tuple:
    """Every field of a material, by value: shapes sharing a BSDF share one material."""
    def value(x):
        return (x.dtype.str, x.shape, x.tobytes()) if isinstance(x, np.ndarray) else x

    return tuple((f.name, value(getattr(mat, f.name))) for f in dataclasses.fields(mat))


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


class MitsubaSceneDict(dict):
    """A Mitsuba scene dict that knows the variant its Mitsuba objects (meshes, BSDFs, bitmaps) were built with:
    ``.variant``. Mitsuba renders such objects black under another variant, without an error;
    :func:`suite.core.reference.render_with_stderr` renders with this variant and refuses another one."""

    variant: str = ""


def to_mitsuba_dict(scene: Scene, t_s: float = 0.0, resolution=None, integrator=None, spp: int = 64,
                    variant: str | None = None, rfilter: str = "box") -> MitsubaSceneDict:
    """The scene at time ``t_s`` as a Mitsuba dict: one mesh per (object, material) group.

    Surfaces are two-sided diffuse, because our shading kernels light both sides of a triangle (a closed
    room seen from inside must not depend on winding). Emissive groups carry an ``area`` emitter with the
    material's radiance; point lights become ``point`` emitters with their intensity (W/sr).

    ``variant`` (auto|llvm|cuda|scalar; None: :func:`suite.core.env.default_variant`) is the variant the dict's
    objects are built with; the dict carries it (``.variant``) and can only be rendered with it.
    """
    from suite.core.env import mitsuba

    mi = mitsuba(variant)
    resolution = tuple(resolution or scene.camera.resolution)
    positions = scene.positions_at(t_s)
    normals = scene.normals_at(t_s)
    out = MitsubaSceneDict({"type": "scene", "integrator": dict(integrator or {"type": "path", "max_depth": 8}),
                            "sensor": sensor_dict(mi, scene, t_s, resolution, spp, rfilter)})
    out.variant = mi.variant()
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


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(x) for x in np.asarray(value).reshape(3)]}


def _bsdf_dict(mi, mat: Material) -> dict:
    """The Mitsuba BSDF of a material (see the module docstring for the mapping)."""
    kind = mat.shading_kind
    if kind in ("diffuse", "rough_plastic"):
        if mat.albedo_texture is not None:
            reflectance = {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(mat.albedo_texture, np.float32)),
                           "raw": True, "filter_type": "bilinear"}
        else:
            reflectance = {"type": "rgb", "value": [float(x) for x in mat.albedo]}
    if kind == "diffuse":
        bsdf = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}
    elif kind == "glass":
        bsdf = {"type": "dielectric", "int_ior": mat.int_ior, "ext_ior": mat.ext_ior,
                "specular_reflectance": _rgb(mat.specular_reflectance),
                "specular_transmittance": _rgb(mat.specular_transmittance)}
    else:
        if kind == "mirror":
            bsdf = {"type": "conductor"}
        elif kind == "rough_conductor":
            bsdf = {"type": "roughconductor", "distribution": mat.distribution, "alpha": mat.roughness}
        else:
            bsdf = {"type": "roughplastic", "distribution": mat.distribution, "alpha": mat.roughness,
                    "int_ior": mat.int_ior, "ext_ior": mat.ext_ior, "nonlinear": mat.nonlinear,
                    "diffuse_reflectance": reflectance}
        if kind != "rough_plastic":
            bsdf.update(eta=_rgb(mat.conductor_eta), k=_rgb(mat.conductor_k))
        bsdf["specular_reflectance"] = _rgb(mat.specular_reflectance)
        if mat.twosided:
            bsdf = {"type": "twosided", "bsdf": bsdf}
    if mat.is_alpha_tested:
        # Mitsuba's mask is stochastic (kept with probability = opacity); for binary maps it equals the alpha test.
        bsdf = {"type": "mask", "bsdf": bsdf,
                "opacity": {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(mat.opacity_texture, np.float32)),
                            "raw": True, "filter_type": "bilinear"}}
    return bsdf
