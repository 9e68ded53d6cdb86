"""Preset matrices for ``splitbench reproduce``: each method's [presets.<name>] grid, expanded into run configs.

``smoke`` runs every registered method: a method without a [presets.smoke] table gets the default smoke point
(cornell, 160x90, 3 frames, ideal network, default parameters). ``quick`` and ``full`` run the methods that
define them. The path-traced reference uses ``REFERENCE_SPP[preset]`` unless the preset table sets
``reference_spp``.

A preset table is one product (``MethodSpec.preset_points``). A method that needs sets that are not one product
(a resolution sweep for one variant only, a few expensive runs at 1080p) adds sub-grids::

    [presets.quick]                 # the main product
    variants = ["paper", "h264"]
    ...
    [[presets.quick.runs]]          # one more product: every key it names replaces the main table's key
    resolutions = ["1920x1080"]     # (``grid`` as a whole); the keys it omits are inherited
    variants = ["paper"]
    reference_spp = 0

The points of every sub-grid are added to the main product's; a point that two of them produce runs once.
"""
from __future__ import annotations

import json

from suite.harness import registry, runner
from suite.errors import UserError

# Reference spp of each preset unless its table sets reference_spp: enough to rank methods at that resolution
# while keeping a cold reference cache affordable (smoke runs in CI).
REFERENCE_SPP = {"smoke": 32, "quick": 128, "full": 1024}
SMOKE_DEFAULT = {"scene": "cornell", "resolution": "160x90", "frames": 3, "net": "ideal", "protocol": "tcp",
                 "variant": "default", "set": {}}


def configs(preset: str, methods: str | list | None = None) -> tuple[list[dict], list[str]]:
    """(run configs, problems): a point that does not validate is a problem, not a stop for the others."""
    if preset not in registry.PRESETS:
        raise UserError(f"unknown preset '{preset}' (choose from {', '.join(registry.PRESETS)})")
    specs = registry.discover()
    if methods:
        names = methods.split(",") if isinstance(methods, str) else list(methods)
        for name in names:
            if name not in specs:
                raise UserError(f"unknown method '{name}' (choose from {', '.join(specs)})")
        specs = {n: specs[n] for n in names}
    out, problems = [], []
    for name, spec in specs.items():
        points = preset_points(spec, preset)
        if not points and preset == "smoke":
            points = [dict(SMOKE_DEFAULT, method=name)]
        if not points:
            problems.append(f"method '{name}' has no [presets.{preset}] table; not run")
            continue
        for point in points:
            point = dict(point)
            set_values = point.pop("set", {})
            point.pop("method")
            point.setdefault("reference_spp", REFERENCE_SPP[preset])
            try:
                out.append(runner.make_config(name, set_values=set_values, **point))
            except UserError as exc:
                problems.append(f"method '{name}' preset '{preset}' point {point}: {exc}")
    return out, problems


def preset_points(spec: registry.MethodSpec, preset: str) -> list[dict]:
    """The main product of ``[presets.<preset>]`` plus one product per ``[[presets.<preset>.runs]]`` sub-grid,
    without duplicate points (see the module docstring)."""
    table = spec.config.get("presets", {}).get(preset)
    if table is None:
        return []
    subs = table.get("runs", [])
    if not isinstance(subs, list) or not all(isinstance(sub, dict) for sub in subs):
        raise UserError(f"method '{spec.name}': presets.{preset}.runs must be an array of tables "
                        f"([[presets.{preset}.runs]])")
    main = {k: v for k, v in table.items() if k != "runs"}
    points = spec.preset_points(preset)
    for k, sub in enumerate(subs):
        if "runs" in sub:
            raise UserError(f"method '{spec.name}': presets.{preset}.runs[{k}] may not nest runs")
        sub_spec = registry.MethodSpec(spec.name, spec.path,
                                       {**spec.config, "presets": {preset: {**main, **sub}}})
        points += sub_spec.preset_points(preset)
    unique, seen = [], set()
    for point in points:
        key = json.dumps(point, sort_keys=True, default=str)
        if key not in seen:
            seen.add(key)
            unique.append(point)
    return unique
