"""Dask worker preload (``dask worker --preload tests/harness/dask_fake_core.py``): the harness tests' synthetic
scene, tracer, references and metrics in a worker process, so a real cluster runs the synthetic methods without
the renderer."""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from conftest import install_fake_core  # noqa: E402

install_fake_core(setattr)
