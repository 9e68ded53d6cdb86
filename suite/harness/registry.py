"""Method discovery: every folder under ``methods/`` (and under ``SPLITBENCH_METHOD_PATHS``) with a config.toml.

The runner asks the registry by name; no method is named in the harness. ``method.py`` is imported from its
file path, so a method folder need not be an installed package.
"""
from __future__ import annotations

import difflib
import importlib.util
import inspect
import itertools
import os
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from suite.errors import UserError
from suite.harness.method import Method

METHODS_DIR = Path(__file__).resolve().parents[2] / "methods"
PRESETS = ("smoke", "quick", "full", "compare", "compare-full")
# Presets whose matrix is the shared one of suite/harness/compare.toml (each method adds only its
# [presets.compare] variants / set / backend), not each method's own [presets.<name>] grid.
SHARED_PRESETS = ("compare", "compare-full")
LIGHT_TRANSPORTS = ("direct", "global")
RESERVED_PARAMS = ("client_fps", "update_fps", "max_in_flight")


@dataclass
class MethodSpec:
    """One discovered method folder and its parsed config.toml."""

    name: str
    path: Path
    config: dict = field(repr=False)

    @property
    def description(self) -> str:
        return str(self.config.get("method", {}).get("description", ""))

    @property
    def default_scene(self) -> str | None:
        """``[method] scene``: the scene a run takes when none is given (one the method renders), or None."""
        scene = self.config.get("method", {}).get("scene")
        if scene is not None and not (isinstance(scene, str) and scene):
            raise UserError(f"method '{self.name}': [method] scene must be a scene name, got {scene!r}")
        return scene

    @property
    def defaults(self) -> dict:
        return dict(self.config.get("defaults", {}))

    @property
    def docs(self) -> dict:
        return dict(self.config.get("doc", {}))

    @property
    def aliases(self) -> dict:
        """``[aliases]``: the paper's own names for parameters (the thesis's console commands), each accepted by
        ``--set`` in any letter case (as Quake III's console takes its variables) and stored under the parameter's
        name, so every spelling makes the same run."""
        aliases = dict(self.config.get("aliases", {}))
        defaults = self.defaults
        for alias, target in aliases.items():
            if alias in defaults or target not in defaults:
                raise UserError(f"method '{self.name}': alias '{alias}' must name a parameter of [defaults] and not "
                                f"be one, got '{alias}' = {target!r}")
        return aliases

    @property
    def variants(self) -> list[str]:
        names = ["default"]
        if "paper" in self.config:
            names.append("paper")
        return names + sorted(self.config.get("variants", {}))

    def variant_overrides(self, variant: str) -> dict:
        if variant in ("default", "", None):
            return {}
        if variant == "paper" and "paper" in self.config:
            return dict(self.config["paper"])
        if variant in self.config.get("variants", {}):
            return dict(self.config["variants"][variant])
        raise UserError(f"method '{self.name}' has no variant '{variant}' (choose from {', '.join(self.variants)})")

    def params(self, variant: str = "default", overrides: dict | None = None) -> dict:
        """[defaults] ← variant ← overrides, with each override checked against the defaults' keys and types."""
        params, aliases = self.defaults, self.aliases
        folded = {alias.lower(): target for alias, target in aliases.items()}
        merged = {}
        for layer in (self.variant_overrides(variant), overrides or {}):  # the later layer wins
            given = {}
            for key, value in layer.items():
                name = key if key in params else folded.get(key.lower(), key)
                if name in given and given[name][1] != value:  # one parameter under two of its names, differently
                    raise UserError(f"parameter '{name}' of method '{self.name}' is given twice: {given[name][0]} = "
                                    f"{given[name][1]!r} and {key} = {value!r}")
                given[name] = (key, value)
            merged.update({name: value for name, (_, value) in given.items()})
        for name, value in merged.items():
            params[name] = check_param(self.name, params, name, value, aliases)
        return params

    def has_module(self, part: str) -> bool:
        """Whether the folder ships ``<part>.py`` (``method``, ``report``, ``bench``)."""
        return (self.path / f"{part}.py").is_file()

    def load_module(self, part: str):
        """Imports this method's ``<part>.py``; see :func:`load_module`."""
        return _import_part(self, part)

    def load(self) -> type[Method]:
        """Imports method.py and returns its one Method subclass."""
        module = self.load_module("method")
        classes = [c for _, c in inspect.getmembers(module, inspect.isclass)
                   if issubclass(c, Method) and c is not Method and c.__module__ == module.__name__]
        if len(classes) != 1:
            raise UserError(f"method '{self.name}': method.py must define exactly one Method subclass, "
                            f"found {len(classes)}")
        cls = classes[0]
        if cls.mode not in ("sync", "async"):
            raise UserError(f"method '{self.name}': mode must be 'sync' or 'async', not {cls.mode!r}")
        if getattr(cls, "light_transport", "direct") not in LIGHT_TRANSPORTS:
            raise UserError(f"method '{self.name}': light_transport must be one of {', '.join(LIGHT_TRANSPORTS)}, "
                            f"not {cls.light_transport!r}")
        return cls

    def preset_points(self, preset: str) -> list[dict]:
        """The runs of one preset: product(scenes, resolutions, nets, protocols, variants, clients, server_nets,
        *grid values)."""
        if preset in SHARED_PRESETS:
            # The shared matrix (suite/harness/compare.toml) with this method's variants: its table is no grid.
            from suite.harness import presets

            return presets.shared_points(self, preset, presets.shared_matrix(preset), presets.scene_available)
        table = self.config.get("presets", {}).get(preset)
        if table is None:
            return []
        grid = dict(table.get("grid", {}))
        keys = sorted(grid)
        points = []
        for scene, res, net, proto, variant, clients, server_net, *values in itertools.product(
                table.get("scenes", ["cornell"]), table.get("resolutions", ["160x90"]), table.get("nets", ["ideal"]),
                table.get("protocols", ["tcp"]), table.get("variants", ["default"]), table.get("clients", [1]),
                table.get("server_nets", ["none"]),
                *[v if isinstance(v, list) else [v] for v in (grid[k] for k in keys)]):
            point = {"method": self.name, "scene": scene, "resolution": res, "net": net, "protocol": proto,
                     "variant": variant, "frames": int(table.get("frames", 3)), "set": dict(zip(keys, values))}
            if clients != 1:
                point["clients"] = clients
            if server_net != "none":
                point["server_net"] = server_net
            for opt in ("backend", "reference_spp", "reference_max_depth", "quality_every", "clock", "seed"):
                if opt in table:
                    point[opt] = table[opt]
            points.append(point)
        return points


def check_param(method: str, defaults: dict, key: str, value, aliases: dict | None = None):
    """Validates one parameter override against [defaults]: known key, compatible type. An unknown key's error
    names the closest known parameter or alias (``aliases``: alias → parameter)."""
    if key not in defaults:
        known = ", ".join(sorted(defaults)) or "none"
        raise UserError(f"unknown parameter '{key}' for method '{method}'{_suggestion(key, defaults, aliases or {})} "
                        f"(known: {known})")
    default = defaults[key]
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise UserError(f"parameter '{key}' of method '{method}' must be {type(default).__name__}, got {value!r}")
    return value


def _suggestion(key: str, defaults: dict, aliases: dict) -> str:
    """", did you mean 'x'?" for the known parameter or alias closest to ``key`` (case aside), or ''."""
    names = {n.lower(): n for n in [*defaults, *aliases]}
    close = difflib.get_close_matches(key.lower(), list(names), n=1, cutoff=0.75)
    if not close:
        return ""
    name = names[close[0]]
    return f", did you mean '{name}'" + (f" (the paper's name for '{aliases[name]}')" if name in aliases else "") + "?"


def parse_set_value(text: str):
    """Parses a --set value as a TOML value (8, 0.5, true, "x", [1, 2]); a bare word stays a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def method_roots() -> list[Path]:
    roots = [METHODS_DIR]
    for extra in os.environ.get("SPLITBENCH_METHOD_PATHS", "").split(os.pathsep):
        if extra.strip():
            roots.append(Path(extra).resolve())
    return roots


def discover() -> dict[str, MethodSpec]:
    """All method folders (name → spec), sorted by name. A malformed config.toml is a UserError naming it."""
    specs: dict[str, MethodSpec] = {}
    for root in method_roots():
        if not root.is_dir():
            continue
        for cfg in sorted(root.glob("*/config.toml")):
            name = cfg.parent.name
            if name in specs:
                continue
            try:
                config = tomllib.loads(cfg.read_text())
            except tomllib.TOMLDecodeError as exc:
                raise UserError(f"{cfg}: malformed TOML ({exc})") from None
            specs[name] = MethodSpec(name, cfg.parent, config)
    return dict(sorted(specs.items()))


METHOD_PARTS = ("method", "report", "bench")


def load_module(method: str | MethodSpec, part: str):
    """Imports one file of a method folder: ``part`` is ``"method"``, ``"report"`` or ``"bench"``.

    The one way the harness, the CLI and the report builder import a method's files. A folder of the project's
    own ``methods`` package is imported as ``methods.<name>.<part>``, so that its relative and absolute imports
    of sibling modules both work; a folder under ``SPLITBENCH_METHOD_PATHS`` is imported from its file as
    ``splitbench_methods.<name>.<part>`` (kept in ``sys.modules`` while it is the same file). A missing file is
    a UserError naming it.
    """
    spec = method if isinstance(method, MethodSpec) else get(method)
    return _import_part(spec, part)


def _import_part(spec: MethodSpec, part: str):
    if part not in METHOD_PARTS:
        raise ValueError(f"unknown method file '{part}' (choose from {', '.join(METHOD_PARTS)})")
    file = spec.path / f"{part}.py"
    if not file.is_file():
        raise UserError(f"method '{spec.name}' has no {part}.py in {spec.path}")
    if spec.path.parent == METHODS_DIR and (METHODS_DIR / "__init__.py").is_file():
        return importlib.import_module(f"methods.{spec.name}.{part}")
    module_name = f"splitbench_methods.{spec.name}.{part}"
    module = sys.modules.get(module_name)
    # Two roots may hold a method of the same name (tests do): reuse a module only if it is this very file.
    if module is not None and Path(getattr(module, "__file__", "") or "").resolve() == file.resolve():
        return module
    module_spec = importlib.util.spec_from_file_location(module_name, file)
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[module_name] = module
    try:
        module_spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[module_name]
        raise
    return module


def get(name: str) -> MethodSpec:
    specs = discover()
    if name not in specs:
        raise UserError(f"unknown method '{name}' (choose from {', '.join(specs) or 'none'})")
    return specs[name]
