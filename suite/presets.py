"""Preset matrices for ``splitbench reproduce``: each method's [presets.<name>] grid, expanded into run configs.

``smoke`` runs every registered method: a method without a [presets.smoke] table gets the default smoke point
(cornell, 160x90, 3 frames, ideal network, default parameters). ``quick`` and ``full`` run the methods that
define them. The path-traced reference uses ``REFERENCE_SPP[preset]`` unless the preset table sets
``reference_spp``.
"""
from __future__ import annotations

from suite import registry, runner
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
        points = spec.preset_points(preset)
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
