"""A run's identity follows the scene data it loads from (suite.core.scene.source_digest)."""

import pytest

from suite.core import scene as scene_mod
from suite.errors import UserError
from suite.harness import runner


def test_embedded_scenes_are_identified_by_the_code_alone():
    assert scene_mod.source_digest("living_room") == ""


def test_a_changed_obj_file_changes_the_digest(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    first = scene_mod.source_digest(str(obj))
    assert len(first) == 64 and first == scene_mod.source_digest(str(obj))
    obj.write_text("v 0 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\n")
    assert scene_mod.source_digest(str(obj)) != first


def test_a_missing_file_is_an_error_for_the_loader_and_no_identity_for_the_config(tmp_path):
    missing = str(tmp_path / "absent.obj")
    with pytest.raises(UserError):
        scene_mod.source_digest(missing)
    assert runner._scene_identity(missing) == ""


def test_openarena_maps_are_identified_by_their_archives():
    try:
        a = scene_mod.source_digest("oa:aggressor")
        b = scene_mod.source_digest("oa:aggressor@pak1-maps")
    except UserError as exc:
        pytest.skip(f"OpenArena data not available: {exc}")
    # Two versions of one map in different archives are different data.
    assert len(a) == 64 and a != b
