"""Wavefront OBJ scenes (OBJ + MTL + textures, read by tinyobjloader) with a sidecar TOML for what OBJ cannot say.

``load_obj(spec)`` turns a path ending in ``.obj``, or the name of a project scene (``dabrovic_sponza``: a sidecar
in ``suite/core/scene/data/`` whose OBJ is found on the scene search path), into an :class:`ObjScene`: the shared
scene model plus ``scene.obj`` (:class:`ObjInfo`: source files, hashes, counts, what was not modelled). See
docs/scenes.md.

Modules: :mod:`.reader` (OBJ geometry and checks), :mod:`.mtl` (materials and textures), :mod:`.sidecar`
(the TOML format), :mod:`.loader` (specs, conversion, cache).
"""
from __future__ import annotations

from suite.core.scene.obj.loader import (ObjInfo, ObjScene, cache_dir, is_obj_spec, last_load_stats, list_obj_scenes,
                                         load_obj)

__all__ = ["load_obj", "list_obj_scenes", "is_obj_spec", "ObjScene", "ObjInfo", "cache_dir", "last_load_stats"]
