"""Quake III Arena / OpenArena maps (IBSP version 46) as scenes.

``load_q3(spec)`` turns ``oa:<map>``, ``oa:<map>@<pak>``, a ``.bsp`` path or a ``.pk3[:<map>]`` path into a
:class:`Q3Scene`: the shared scene model (triangles, materials with textures, point lights, emissive
triangles as area lights, a camera path) plus ``scene.visibility`` (:class:`Q3Visibility`: point -> cluster,
cluster PVS, clusters per triangle) and ``scene.q3`` (:class:`Q3Info`: per-face flags, shader and light
records, counts). See docs/scenes.md.

Modules: :mod:`.paks` (archives and search path), :mod:`.bsp` (file format), :mod:`.patches` (Bezier
tessellation), :mod:`.shaders` (shader scripts), :mod:`.textures` (images), :mod:`.lights` (unit conversions),
:mod:`.visibility`, :mod:`.convert` (map -> scene), :mod:`.camera` (paths), :mod:`.loader` (specs, cache).
"""
from __future__ import annotations

from suite.core.scene.q3.convert import FLAGS, Q3Info
from suite.core.scene.q3.loader import PREFIX, available_maps, is_q3_spec, load_q3
from suite.core.scene.q3.paks import missing_data_message, search_dirs
from suite.core.scene.q3.scene import Q3Scene
from suite.core.scene.q3.visibility import Q3Visibility

__all__ = ["load_q3", "list_q3_scenes", "is_q3_spec", "available_maps", "Q3Scene", "Q3Visibility", "Q3Info",
           "FLAGS", "missing_data_message", "search_dirs", "PREFIX"]


def list_q3_scenes() -> dict[str, str]:
    """The OpenArena scenes with a scripted camera path (``camera_paths.toml``), each with a one-line
    description, or, when the archives are missing, marked unavailable with the fix. Every other map in the
    archives loads as ``oa:<map>`` too (automatic camera path)."""
    from suite.core.scene.q3.camera import load_scripts

    scripts = load_scripts()
    try:
        maps = available_maps()
    except Exception as exc:  # an unreadable archive must not break listing
        maps, problem = {}, f"unavailable: {exc}"
    else:
        problem = "unavailable: " + missing_data_message()
    out = {}
    for name, script in sorted(scripts.items()):
        entries = [(PREFIX + name, script.get("title", f"OpenArena map {name}"), None)]
        entries += [(f"{PREFIX}{name}@{pak}", title, pak) for pak, title in script.get("variants", {}).items()]
        for spec, title, pak in entries:
            have = name in maps and (pak is None or any(p.lower().removesuffix(".pk3") == pak.lower()
                                                        for p in maps[name]))
            out[spec] = str(title) if have else problem
    return out
