"""splitbench core: scenes, tracing backends, G-buffer, shading, references, metrics and the harness."""

__version__ = "0.1.0"
