"""The scene search path: where named file-based scenes (OBJ models such as ``dabrovic_sponza``) are found.

Folders are searched in this order:

1. the entries of ``SPLITBENCH_SCENE_PATH`` (an ``os.pathsep``-separated list; ``~`` is expanded, empty
   entries are skipped), first entry first;
2. the project's own data folder, ``suite/core/scene/data/`` (sidecar TOML files and small scene files).

A scene names its file by a path relative to a search-path folder (for Sponza ``dabrovic_sponza/sponza.obj``);
the first folder that holds it wins. Nothing outside this path is consulted, so a checkout does not depend on
where scene data happens to lie; tests and make targets set the variable where the data lives.
"""
from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "SPLITBENCH_SCENE_PATH"
DATA_DIR = Path(__file__).with_name("data")


def scene_path() -> list[Path]:
    """The search-path folders in priority order (highest first), whether or not they exist."""
    dirs: list[Path] = []
    for entry in os.environ.get(ENV_VAR, "").split(os.pathsep):
        entry = entry.strip()
        if entry:
            p = Path(os.path.expanduser(entry))
            if p not in dirs:
                dirs.append(p)
    if DATA_DIR not in dirs:
        dirs.append(DATA_DIR)
    return dirs


def find_scene_file(relative: str) -> Path | None:
    """The first ``<folder>/<relative>`` on the search path that is a file, or None."""
    rel = Path(relative.replace("\\", "/"))
    for folder in scene_path():
        candidate = folder / rel
        if candidate.is_file():
            return candidate
    return None


def missing_file_message(relative: str, what: str = "scene file") -> str:
    """One line naming the fix when ``relative`` is on no search-path folder."""
    searched = ", ".join(str(d) for d in scene_path())
    return (f"{what} '{relative}' is not on the scene search path ({searched}): add the folder that holds "
            f"'{relative}' to {ENV_VAR} (os.pathsep-separated)")
