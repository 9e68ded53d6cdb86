"""The harness: method contract, registry, runner, timeline, results store, executor, presets, CLI.

It drives the core (``suite.core``) and netsim; nothing in the core imports it.
"""
