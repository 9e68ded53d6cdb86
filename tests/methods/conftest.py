import pytest


@pytest.fixture
def every_scene_available(monkeypatch):
    """The presets' grids as written, whatever scene data this machine has (presets skip the runs of scenes a
    machine lacks, such as the OpenArena maps; that skipping is tested with the harness)."""
    from suite.harness import presets

    monkeypatch.setattr(presets, "scene_available", lambda name: True)
