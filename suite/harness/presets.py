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

``compare`` and ``compare-full`` (:data:`suite.harness.registry.SHARED_PRESETS`) are one matrix for every method,
defined in ``suite/harness/compare.toml`` (:data:`COMPARE_FILE`): its cells (scenes × nets × protocols) and
settings (resolution, frames, quality poses, reference spp, backend). A method adds only its
``[presets.compare]`` table: ``variants`` (default ``["default"]``), optionally ``set`` (parameter overrides),
``backend`` and ``scenes`` (the matrix scenes it can render). A method with a ``[presets.compare-full]`` table
uses it for ``compare-full``. Scenes that are not available on the machine are skipped and recorded, in every
preset but ``smoke`` (:func:`expand` returns them; ``reproduce`` prints a note for each and stores the record as
``<results>/presets/<preset>.json``).
"""
from __future__ import annotations

import json
import tomllib
from pathlib import Path

from suite.harness import registry, runner
from suite.errors import UserError

# Reference spp of each preset unless its table sets reference_spp: enough to rank methods at that resolution
# while keeping a cold reference cache affordable (smoke runs in CI).
REFERENCE_SPP = {"smoke": 32, "quick": 128, "full": 1024}
SMOKE_DEFAULT = {"scene": "cornell", "resolution": "160x90", "frames": 3, "net": "ideal", "protocol": "tcp",
                 "variant": "default", "set": {}}


COMPARE_FILE = Path(__file__).with_name("compare.toml")
# Settings a shared matrix may give (run options of runner.make_config) and the keys of one of its cells.
MATRIX_SETTINGS = ("resolution", "frames", "quality_every", "reference_spp", "reference_max_depth", "backend",
                   "reference_direct", "reference_floor", "seed", "clock")
CELL_KEYS = ("scenes", "nets", "protocols")
METHOD_KEYS = ("variants", "set", "backend", "scenes")


def configs(preset: str, methods: str | list | None = None) -> tuple[list[dict], list[str]]:
    """(run configs, problems): a point that does not validate is a problem, not a stop for the others."""
    out, problems, _ = expand(preset, methods)
    return out, problems


def scene_available(name: str) -> bool:
    """False for a listed scene whose data this machine lacks (``splitbench list`` says "unavailable: ..." and how to
    add it): presets skip its runs and record it. True otherwise, also for a name the list does not know (a file
    path, a map it does not enumerate, a typo): the run's own scene loading judges that and names the problem."""
    from suite.core.scene import list_scenes

    desc = list_scenes().get(name)
    return desc is None or not str(desc).startswith("unavailable")


def shared_matrix(preset: str, path=None) -> dict:
    """The ``[<preset>]`` table of the shared matrix file, checked: settings and ``cells``."""
    path = Path(path or COMPARE_FILE)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise UserError(f"cannot read the shared matrix {path} ({exc})") from None
    table = doc.get(preset)
    if not isinstance(table, dict):
        raise UserError(f"{path} has no [{preset}] table")
    unknown = sorted(set(table) - set(MATRIX_SETTINGS) - {"cells"})
    if unknown:
        raise UserError(f"{path} [{preset}]: unknown setting '{unknown[0]}' (known: {', '.join(MATRIX_SETTINGS)})")
    cells = table.get("cells")
    if not isinstance(cells, list) or not cells or not all(isinstance(c, dict) for c in cells):
        raise UserError(f"{path} [{preset}]: cells must be a non-empty array of tables ([[{preset}.cells]])")
    for k, cell in enumerate(cells):
        missing = [key for key in CELL_KEYS if not isinstance(cell.get(key), list) or not cell.get(key)]
        extra = sorted(set(cell) - set(CELL_KEYS))
        if missing or extra:
            raise UserError(f"{path} [{preset}] cell {k}: needs non-empty lists {', '.join(CELL_KEYS)}"
                            + (f"; unknown key '{extra[0]}'" if extra else ""))
    return table


def method_compare_table(spec: registry.MethodSpec, preset: str) -> dict:
    """A method's part of a shared matrix: ``[presets.<preset>]`` or else ``[presets.compare]``, checked."""
    presets_table = spec.config.get("presets", {})
    table = presets_table.get(preset, presets_table.get("compare", {}))
    unknown = sorted(set(table) - set(METHOD_KEYS))
    if unknown:
        raise UserError(f"method '{spec.name}': presets.compare may only name {', '.join(METHOD_KEYS)}, "
                        f"not '{unknown[0]}' (the matrix is suite/harness/compare.toml)")
    variants = table.get("variants", ["default"])
    if not isinstance(variants, list) or not variants:
        raise UserError(f"method '{spec.name}': presets.compare.variants must be a non-empty list")
    return {"variants": [str(v) for v in variants], "set": dict(table.get("set", {})),
            "backend": table.get("backend"), "scenes": table.get("scenes")}


def shared_points(spec: registry.MethodSpec, preset: str, matrix: dict, available) -> list[dict]:
    """The points of one method in a shared matrix: every cell's product with the method's variants, on the
    available scenes it can render (``available(scene)``)."""
    mine = method_compare_table(spec, preset)
    settings = {k: v for k, v in matrix.items() if k != "cells"}
    # A method (variant) that sends nothing computes the same images and times on every network: it runs once
    # per scene on the ideal network, and the report shows that run under every profile.
    local = {variant: not uses_network(spec, variant, mine["set"]) for variant in mine["variants"]}
    points = []
    for cell in matrix["cells"]:
        for scene in cell["scenes"]:
            if not available(scene) or (mine["scenes"] is not None and scene not in mine["scenes"]):
                continue
            for net in cell["nets"]:
                for protocol in cell["protocols"]:
                    for variant in mine["variants"]:
                        point = {**settings, "method": spec.name, "scene": scene, "net": net, "protocol": protocol,
                                 "variant": variant, "set": dict(mine["set"])}
                        if local[variant]:
                            point.update(net="ideal", protocol="tcp")
                        if mine["backend"]:
                            point["backend"] = mine["backend"]
                        points.append(point)
    return _unique(points)


def uses_network(spec: registry.MethodSpec, variant: str, set_values: dict) -> bool:
    """Whether a method sends messages with these parameters: the instance's ``uses_network`` (a method may set it
    per parameter, e.g. a placement), else the class's."""
    cls = spec.load()
    params = spec.params(variant, set_values)  # a bad variant or parameter is the caller's UserError
    try:
        return bool(getattr(cls(params), "uses_network", True))
    except Exception:  # noqa: BLE001 - a constructor that needs more than params: the class says
        return bool(getattr(cls, "uses_network", True))


def expand(preset: str, methods: str | list | None = None, matrix_file=None) -> tuple[list[dict], list[str], dict]:
    """(run configs, problems, record): ``record`` describes the matrix that ran (for shared presets: its
    settings and cells, each method's variants, and the scenes skipped as unavailable)."""
    if preset not in registry.PRESETS:
        raise UserError(f"unknown preset '{preset}' (choose from {', '.join(registry.PRESETS)})")
    specs = _selected(methods)
    if preset in registry.SHARED_PRESETS:
        return _expand_shared(preset, specs, matrix_file)
    out, problems, skipped = _configs(preset, specs)
    return out, problems, {"preset": preset, "methods": sorted(specs), "skipped_scenes": skipped, "runs": len(out)}


def _selected(methods) -> dict:
    specs = registry.discover()
    if methods:
        names = methods.split(",") if isinstance(methods, str) else list(methods)
        for name in names:
            if name not in specs:
                raise UserError(f"unknown method '{name}' (choose from {', '.join(specs)})")
        specs = {n: specs[n] for n in names}
    return specs


def _expand_shared(preset: str, specs: dict, matrix_file) -> tuple[list[dict], list[str], dict]:
    matrix = shared_matrix(preset, matrix_file)
    scenes = list(dict.fromkeys(s for cell in matrix["cells"] for s in cell["scenes"]))
    availability = {s: scene_available(s) for s in scenes}
    skipped = [s for s in scenes if not availability[s]]
    # Unavailable scenes are recorded, not problems: a machine without a scene's data still reproduces the rest.
    problems = []
    out, record_methods = [], {}
    for name, spec in specs.items():
        try:
            points = shared_points(spec, preset, matrix, availability.get)
        except UserError as exc:
            problems.append(str(exc))
            continue
        record_methods[name] = {**method_compare_table(spec, preset), "runs": 0}
        for point in points:
            point = dict(point)
            set_values = point.pop("set", {})
            point.pop("method")
            try:
                out.append(runner.make_config(name, set_values=set_values, **point))
                record_methods[name]["runs"] += 1
            except UserError as exc:
                problems.append(f"method '{name}' preset '{preset}' point {point}: {exc}")
    record = {"preset": preset, "matrix_file": str(Path(matrix_file or COMPARE_FILE).name),
              "settings": {k: v for k, v in matrix.items() if k != "cells"}, "cells": matrix["cells"],
              "skipped_scenes": skipped, "methods": record_methods, "runs": len(out)}
    return out, problems, record


def _configs(preset: str, specs: dict) -> tuple[list[dict], list[str], list[str]]:
    """(run configs, problems, skipped scenes). Points on listed scenes whose data the machine lacks
    (:func:`scene_available`) are skipped and their scenes returned, as the shared matrix does, except in
    ``smoke``, whose scenes the set-up installs: there a missing scene fails its run, so a broken set-up shows."""
    out, problems, skipped = [], [], []
    available = {}
    for name, spec in specs.items():
        points = preset_points(spec, preset)
        if not points and preset == "smoke":
            points = [dict(SMOKE_DEFAULT, method=name)]
        if not points:
            problems.append(f"method '{name}' has no [presets.{preset}] table; not run")
            continue
        for point in points:
            scene = point["scene"]
            if preset != "smoke":
                if scene not in available:
                    available[scene] = scene_available(scene)
                if not available[scene]:
                    if scene not in skipped:
                        skipped.append(scene)
                    continue
            point = dict(point)
            set_values = point.pop("set", {})
            point.pop("method")
            point.setdefault("reference_spp", REFERENCE_SPP[preset])
            try:
                out.append(runner.make_config(name, set_values=set_values, **point))
            except UserError as exc:
                problems.append(f"method '{name}' preset '{preset}' point {point}: {exc}")
    return out, problems, skipped


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
    return _unique(points)


def _unique(points: list[dict]) -> list[dict]:
    unique, seen = [], set()
    for point in points:
        key = json.dumps(point, sort_keys=True, default=str)
        if key not in seen:
            seen.add(key)
            unique.append(point)
    return unique
