"""Core rendering: scenes, tracing backends, G-buffer, shading kernels, references, metrics, images.

The core never imports the harness (``suite.harness``); a test enforces it.
"""
