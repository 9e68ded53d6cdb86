import os

import pytest

# Keep caches of a test session away from the user's cache.
os.environ.setdefault("SPLITBENCH_CACHE", os.path.join(os.path.dirname(__file__), "..", "build", "test-cache"))


@pytest.fixture(autouse=True)
def _quiet_progress(monkeypatch):
    monkeypatch.setenv("SPLITBENCH_PROGRESS", "0")
