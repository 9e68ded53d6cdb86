"""splitbench: the core rendering layer (``suite.core``) and the benchmark harness (``suite.harness``).

``suite.errors``, ``suite.progress`` and ``suite.memory`` are shared by both layers. Importing the suite keeps
freed memory for reuse (:mod:`suite.memory`).
"""
from suite.memory import keep_freed_memory

__version__ = "0.1.0"

keep_freed_memory()
