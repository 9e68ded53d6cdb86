"""splitbench: the core rendering layer (``suite.core``) and the benchmark harness (``suite.harness``).

``suite.errors`` and ``suite.progress`` are shared by both layers.
"""

__version__ = "0.1.0"
