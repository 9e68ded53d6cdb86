"""The scene search path: SPLITBENCH_SCENE_PATH, then the project's data folder; unavailable scenes name the fix."""
import os

import pytest

from suite.errors import UserError
from suite.core.scene import list_scenes, load
from suite.core.scene.obj import loader as obj_loader
from suite.core.scene.obj.samples import write_textured_room
from suite.core.scene.search import DATA_DIR, ENV_VAR, find_scene_file, scene_path


def test01_search_path_order(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        (d / "s").mkdir(parents=True)
        (d / "s" / "x.obj").write_text(str(d))
    monkeypatch.setenv(ENV_VAR, os.pathsep.join([str(a), "", str(b), str(a)]))
    assert scene_path() == [a, b, DATA_DIR]  # empty and repeated entries dropped, the data folder last
    assert find_scene_file("s/x.obj") == a / "s" / "x.obj"
    assert find_scene_file("s\\x.obj") == a / "s" / "x.obj"
    monkeypatch.setenv(ENV_VAR, str(b))
    assert find_scene_file("s/x.obj") == b / "s" / "x.obj"
    assert find_scene_file("s/none.obj") is None
    monkeypatch.delenv(ENV_VAR)
    assert scene_path() == [DATA_DIR]


def test02_missing_sponza_is_listed_unavailable_with_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    desc = list_scenes()["dabrovic_sponza"]
    assert desc.startswith("unavailable:") and ENV_VAR in desc and "dabrovic_sponza/sponza.obj" in desc
    obj_loader._scene_cache.clear()
    with pytest.raises(UserError, match=f"cannot load scene 'dabrovic_sponza'.*{ENV_VAR}"):
        load("dabrovic_sponza")


def test03_nothing_outside_the_search_path_is_consulted(monkeypatch):
    """Without SPLITBENCH_SCENE_PATH only the project's data folder is searched, and it holds sidecars only: the
    suite does not fall back to a shared folder beside the checkout."""
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert list_scenes()["dabrovic_sponza"].startswith("unavailable:")
    assert list_scenes()["dabrovic_sponza_static"].startswith("unavailable:")
    assert sorted(p.name for p in DATA_DIR.iterdir() if not p.name.startswith(".")) == [
        "dabrovic_sponza.toml", "dabrovic_sponza_static.toml"]


def test04_scene_found_on_the_path_by_its_sidecar_hash(tmp_path, monkeypatch):
    """An OBJ given by path picks up a project sidecar only when the hashes match (here: none does)."""
    obj = write_textured_room(tmp_path, sidecar=False)
    monkeypatch.setenv("SPLITBENCH_CACHE", str(tmp_path / "cache"))
    obj_loader._scene_cache.clear()
    scene = load(str(obj))
    assert scene.obj.sidecar is None and scene.name == "textured_room"
