"""Preset expansion: the main product of [presets.<name>] plus [[presets.<name>.runs]] sub-grids that inherit
the keys they omit, without duplicate points; malformed sub-grids are user errors."""
import shutil
from pathlib import Path

import pytest

from suite.harness import presets, registry
from suite.errors import UserError

FAKE_METHODS = Path(__file__).parent / "fake_methods"

SUBGRIDS = """
[presets.quick]
scenes = ["toy"]
resolutions = ["16x8"]
frames = 3
nets = ["ideal", "bw=8mbps,delay=5ms"]
protocols = ["tcp"]
variants = ["default", "dim"]
backend = "fake"
reference_spp = 4

[[presets.quick.runs]]
resolutions = ["32x16"]
variants = ["paper"]
reference_spp = 0
quality_every = -1
[presets.quick.runs.grid]
payload_bytes = [1000, 2000]

[[presets.quick.runs]]
nets = ["ideal"]
variants = ["default"]
"""


@pytest.fixture
def method_with_subgrids(tmp_path, fake_core, monkeypatch):
    root = tmp_path / "methods"
    shutil.copytree(FAKE_METHODS / "synthetic_sync", root / "synthetic_sync")
    cfg = root / "synthetic_sync" / "config.toml"
    cfg.write_text(cfg.read_text() + SUBGRIDS)
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    return cfg


def test01_subgrids_add_their_products_and_inherit_the_keys_they_omit(method_with_subgrids):
    points = presets.preset_points(registry.get("synthetic_sync"), "quick")
    main = [p for p in points if p["resolution"] == "16x8"]
    extra = [p for p in points if p["resolution"] == "32x16"]
    assert len(main) == 4  # 2 nets x 2 variants; the second sub-grid's 1 point is one of them
    assert len(extra) == 2 * 2  # 2 nets (inherited) x 2 payloads
    assert all(p["variant"] == "paper" and p["reference_spp"] == 0 and p["quality_every"] == -1
               and p["frames"] == 3 and p["backend"] == "fake" for p in extra)
    assert sorted(p["set"]["payload_bytes"] for p in extra) == [1000, 1000, 2000, 2000]
    assert all(p["set"] == {} and p["reference_spp"] == 4 and "quality_every" not in p for p in main)


def test02_configs_validates_every_subgrid_point(method_with_subgrids):
    configs, problems = presets.configs("quick", methods="synthetic_sync")
    assert problems == [] and len(configs) == 8
    assert sorted({tuple(c["resolution"]) for c in configs}) == [(16, 8), (32, 16)]


def test02b_points_on_unavailable_scenes_are_skipped_and_recorded_except_in_smoke(method_with_subgrids, monkeypatch):
    cfg = method_with_subgrids
    cfg.write_text(cfg.read_text().replace('scenes = ["toy"]', 'scenes = ["toy", "missing_scene"]'))  # every preset
    monkeypatch.setattr(presets, "scene_available", lambda scene: scene != "missing_scene")
    configs, problems, record = presets.expand("quick", methods="synthetic_sync")
    assert problems == [] and len(configs) == 8 and {c["scene"] for c in configs} == {"toy"}
    assert record["skipped_scenes"] == ["missing_scene"]
    # smoke's scenes are installed by the set-up: a missing one is not skipped but stays a point (here the fake core
    # rejects it when the config is made: a problem; a real scene whose data is missing fails its run), so it shows
    configs, problems, record = presets.expand("smoke", methods="synthetic_sync")
    assert record["skipped_scenes"] == [] and {c["scene"] for c in configs} == {"toy"}
    assert problems and all("missing_scene" in p for p in problems)


def test02c_only_listed_scenes_whose_data_is_missing_are_skipped(monkeypatch):
    """A name the scene list does not know (a path, a typo) is not 'unavailable': its run's loading names the
    problem instead of a note that hides it."""
    monkeypatch.setenv("SPLITBENCH_SCENE_PATH", "")  # nothing but the project's own data folder
    assert not presets.scene_available("dabrovic_sponza")  # listed, its OBJ not on the path
    assert presets.scene_available("living_room")  # embedded
    assert presets.scene_available("no_such_scene") and presets.scene_available("scenes/x.xml")


@pytest.mark.parametrize("text, message", [
    ('\n[presets.quick]\nruns = [1, 2]\n', "must be an array of tables"),
    ('\n[presets.quick]\n[[presets.quick.runs]]\n[[presets.quick.runs.runs]]\n', "may not nest runs"),
])
def test03_malformed_subgrids_are_user_errors(tmp_path, fake_core, monkeypatch, text, message, fake_method_copy):
    root = tmp_path / "methods"
    fake_method_copy(root, "synthetic_sync", lambda cfg: cfg + text)
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    with pytest.raises(UserError, match=message):
        presets.preset_points(registry.get("synthetic_sync"), "quick")
