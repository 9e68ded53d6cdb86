"""Scenes: the shared model, embedded defaults and Mitsuba scenes.

``load(spec)`` accepts an embedded scene name (see :func:`list_scenes`), a path to a Mitsuba 3 XML file,
a Mitsuba scene dict, a Quake III / OpenArena map: ``oa:<map>``, ``oa:<map>@<pak>``, a ``.bsp`` path or a
``.pk3[:<map>]`` path (:mod:`suite.core.scene.q3`), or a Wavefront OBJ scene: a ``.obj`` path or a project OBJ scene
such as ``dabrovic_sponza``, found on the scene search path (:mod:`suite.core.scene.obj`, docs/scenes.md).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

from suite.errors import UserError
from suite.core.scene.model import (CameraKey, CameraPath, CameraPose, LightAnimation, Material, PointLight,
                               RigidAnimation, Scene)

__all__ = ["load", "list_scenes", "Scene", "Material", "PointLight", "CameraKey", "CameraPath", "CameraPose",
           "RigidAnimation", "LightAnimation"]

_cache: dict[str, Scene] = {}


def list_scenes() -> dict[str, str]:
    """Embedded scene names, the project's OBJ scenes and the OpenArena scenes with scripted camera paths, with a
    one-line description. A scene whose data is missing is listed with a description starting ``unavailable:``
    that names the fix."""
    from suite.core.scene.embedded import EMBEDDED
    from suite.core.scene.q3 import list_q3_scenes

    def first_line(fn):
        doc = (fn.__doc__ or "").strip().splitlines()
        return doc[0] if doc else ""

    scenes = {name: first_line(EMBEDDED[name]) for name in sorted(EMBEDDED)}
    from suite.core.scene.obj import list_obj_scenes

    scenes.update(list_obj_scenes())
    scenes.update(list_q3_scenes())
    return scenes


def source_digest(spec) -> str:
    """A content hash of the files a scene spec loads from ('' for embedded scenes, which the code defines), so
    that a run's identity changes when its scene data does. A missing file raises the same error as load()."""
    spec = os.fspath(spec)
    from suite.core.scene.embedded import EMBEDDED

    if spec in EMBEDDED:
        return ""
    from suite.core.scene.q3 import is_q3_spec
    from suite.core.scene.q3.loader import source_digest as q3_digest

    if is_q3_spec(spec):
        return q3_digest(spec)
    from suite.core.scene.obj import is_obj_spec
    from suite.core.scene.obj.loader import source_digest as obj_digest

    if is_obj_spec(spec):
        return obj_digest(spec)
    if os.path.isfile(spec):
        return hashlib.sha256(Path(spec).read_bytes()).hexdigest()
    return ""


def load(spec) -> Scene:
    """An embedded scene by name, a Mitsuba XML scene by path, or a Mitsuba scene dict."""
    if isinstance(spec, Scene):
        return spec
    if isinstance(spec, dict):
        from suite.core.scene.mitsuba_io import load_mitsuba

        return load_mitsuba(spec)
    spec = os.fspath(spec)
    from suite.core.scene.embedded import EMBEDDED

    if spec in EMBEDDED:
        if spec not in _cache:
            _cache[spec] = EMBEDDED[spec]()
        return _cache[spec]
    from suite.core.scene.q3 import is_q3_spec, load_q3

    if is_q3_spec(spec):
        return load_q3(spec)
    from suite.core.scene.obj import is_obj_spec, load_obj

    if is_obj_spec(spec):
        return load_obj(spec)
    if spec.endswith(".xml") or os.sep in spec:
        from suite.core.scene.mitsuba_io import load_mitsuba

        return load_mitsuba(spec)
    raise UserError(f"unknown scene '{spec}' (embedded: {', '.join(sorted(EMBEDDED))}; or a path to a Mitsuba .xml "
                    f"or a Wavefront .obj; or oa:<map> for an OpenArena map)")
