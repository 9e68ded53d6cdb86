"""Mitsuba / Dr.Jit set-up: one place that picks the libLLVM and the variant.

Import Mitsuba through :func:`mitsuba` rather than ``import mitsuba`` so that ``DRJIT_LIBLLVM_PATH``
is set before Dr.Jit loads (see :mod:`suite.core.llvm`).

Variants: ``llvm`` → ``llvm_ad_rgb`` (CPU), ``cuda`` → ``cuda_ad_rgb`` (when a GPU is present), ``scalar`` →
``scalar_rgb`` (last resort, slow; only when asked for by name). ``auto`` picks cuda when a GPU is usable, else
llvm. There is no silent fall-back: a variant that cannot start raises :class:`UserError`.

The variant is chosen lazily and explicitly, per use:

* a tracer (``make("mitsuba-cuda", scene)``) and a reference render take the variant they are given and keep it
  (``tracer.variant``; a Mitsuba scene dict from :func:`suite.core.scene.mitsuba_io.to_mitsuba_dict` carries the
  variant its objects were built with, and rendering it with another one is an error, not a black image);
* code that only *reads* a scene through Mitsuba (the loader, the embedded Cornell box) uses
  :func:`default_variant`: ``SPLITBENCH_MI_VARIANT`` if set, else the vectorised variant already active, else the
  first variant that works on this machine (llvm, then cuda, then scalar). So a CUDA user without libLLVM never
  needs it, and nothing asks for the LLVM backend before it is really used.
"""
from __future__ import annotations

import os
import subprocess
import sys

from suite.errors import UserError
from suite.core.llvm import LLVMNotFound, configure_drjit_llvm

VARIANTS = {"llvm": "llvm_ad_rgb", "cuda": "cuda_ad_rgb", "scalar": "scalar_rgb"}
_SHORT = {v: k for k, v in VARIANTS.items()}
NO_GPU = "Mitsuba variant 'cuda' needs an NVIDIA GPU with a working driver; none was found"

_configured = False


def _configure_once() -> None:
    global _configured
    if _configured:
        return
    if "drjit" not in sys.modules:
        try:
            configure_drjit_llvm()
        except LLVMNotFound as exc:
            # CUDA and scalar variants do not need LLVM; remember the problem for llvm only.
            os.environ.setdefault("SPLITBENCH_LLVM_PROBLEM", str(exc))
    _configured = True


def llvm_problem() -> str | None:
    """Why the LLVM variant cannot run here (no suitable libLLVM), or None. Imports nothing heavy."""
    _configure_once()
    return os.environ.get("SPLITBENCH_LLVM_PROBLEM") or None


def cuda_available() -> bool:
    _configure_once()
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001 - any driver problem means "no CUDA"
        return False


def llvm_available() -> bool:
    """A libLLVM >= 16 was found and Dr.Jit's LLVM backend initialises with it."""
    if llvm_problem():
        return False
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.LLVM))
    except Exception:  # noqa: BLE001
        return False


def short_name(variant: str) -> str:
    """``llvm_ad_rgb`` → ``llvm`` (names that are not full variant names are returned unchanged)."""
    return _SHORT.get(variant, variant)


def resolve_variant(name: str = "auto") -> str:
    """Maps a backend flavour (auto|llvm|cuda|scalar or a full variant name) to a Mitsuba variant that can run
    here; a variant that cannot is a :class:`UserError` naming the fix."""
    _configure_once()
    if name in ("auto", None, ""):
        name = "cuda" if cuda_available() else "llvm"
    variant = VARIANTS.get(name, name)
    if variant not in VARIANTS.values():
        raise UserError(f"unknown Mitsuba variant '{name}' (choose from auto, {', '.join(VARIANTS)})")
    if variant.startswith("llvm") and llvm_problem():
        raise UserError(llvm_problem())
    if variant.startswith("cuda") and not cuda_available():
        raise UserError(NO_GPU)
    return variant


def active_variant() -> str | None:
    """The variant Mitsuba has active in this process, or None (Mitsuba not imported or no variant set)."""
    if "mitsuba" not in sys.modules:
        return None
    try:
        return sys.modules["mitsuba"].variant()
    except Exception:  # noqa: BLE001
        return None


def default_variant() -> str:
    """The variant for work whose result does not depend on it (reading scenes through Mitsuba, building dicts
    when the caller names none): ``$SPLITBENCH_MI_VARIANT`` if set; else the llvm or cuda variant already active in
    this process; else llvm if it works here, else cuda if a GPU is usable, else scalar. Never fails for a missing
    libLLVM when another variant can do the job."""
    explicit = os.environ.get("SPLITBENCH_MI_VARIANT")
    if explicit:
        return resolve_variant(explicit)
    active = active_variant()
    if active in (VARIANTS["llvm"], VARIANTS["cuda"]):
        return active
    if llvm_available():
        return VARIANTS["llvm"]
    if cuda_available():
        return VARIANTS["cuda"]
    return VARIANTS["scalar"]


def mitsuba(variant: str | None = "auto"):
    """Returns the ``mitsuba`` module with the requested variant active (None: :func:`default_variant`)."""
    variant = default_variant() if variant is None else resolve_variant(variant)
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def variant_of(obj) -> str | None:
    """The Mitsuba variant a Mitsuba object or Dr.Jit array was built with, found in nested dicts and lists (the
    first one found), or None when ``obj`` holds none (plain dicts, numbers, strings)."""
    if isinstance(obj, dict):
        for value in obj.values():
            found = variant_of(value)
            if found:
                return found
        return None
    if isinstance(obj, (list, tuple)):
        for value in obj:
            found = variant_of(value)
            if found:
                return found
        return None
    if obj is None or isinstance(obj, (str, bytes, int, float, bool)):
        return None
    module = type(obj).__module__ or ""
    if module.startswith("drjit."):
        if module.startswith("drjit.llvm"):
            return VARIANTS["llvm"]
        if module.startswith("drjit.cuda"):
            return VARIANTS["cuda"]
        if module.startswith("drjit.scalar"):
            return VARIANTS["scalar"]
        return None
    if not module.startswith("mitsuba"):
        return None
    # Some classes are one class in every variant (the scalar transforms and points a sensor's ``to_world`` holds):
    # an object of a class that several loaded variants share belongs to none of them.
    loaded = [(v, sys.modules[f"mitsuba.{v}"]) for v in VARIANTS.values() if f"mitsuba.{v}" in sys.modules]
    for cls in type(obj).__mro__:
        owners = [v for v, mod in loaded if getattr(mod, cls.__name__, None) is cls]
        if len(owners) == 1:
            return owners[0]
        if owners:
            return None
    return None


def check_same_variant(obj, variant: str, what: str = "the scene dict") -> None:
    """UserError when ``obj`` holds Mitsuba objects of another variant than ``variant``: Mitsuba would accept them
    and render black."""
    import importlib

    try:  # loaded, so that classes it shares with another variant are seen as shared
        importlib.import_module(f"mitsuba.{variant}")
    except ImportError:  # a variant that cannot load here (cuda without a GPU): no object can be of it
        pass
    found = variant_of(obj)
    if found and found != variant:
        raise UserError(f"{what} holds Mitsuba objects built for {found}, but it is being used with {variant} "
                        f"(Mitsuba would render it black): build it with variant='{short_name(variant)}' or use "
                        f"variant='{short_name(found)}'")


def variant_status() -> dict[str, dict]:
    """Per variant short name: ``{"variant", "available", "detail"}`` on this machine, and ``"auto"``: what
    ``auto`` resolves to (cheap: no kernel is compiled)."""
    out = {}
    problem = llvm_problem()
    llvm_ok = llvm_available()
    out["llvm"] = {"variant": VARIANTS["llvm"], "available": llvm_ok,
                   "detail": f"libLLVM {os.environ.get('DRJIT_LIBLLVM_PATH', '?')}" if llvm_ok
                   else (problem or "Dr.Jit's LLVM backend did not initialise")}
    cuda_ok = cuda_available()
    out["cuda"] = {"variant": VARIANTS["cuda"], "available": cuda_ok,
                   "detail": "NVIDIA GPU found" if cuda_ok else NO_GPU}
    try:
        import mitsuba  # noqa: F401

        out["scalar"] = {"variant": VARIANTS["scalar"], "available": True, "detail": "one ray at a time"}
    except ImportError as exc:
        out["scalar"] = {"variant": VARIANTS["scalar"], "available": False, "detail": str(exc)}
    if cuda_ok:
        auto = {"variant": VARIANTS["cuda"], "available": True, "detail": "a GPU is usable"}
    elif llvm_ok:
        auto = {"variant": VARIANTS["llvm"], "available": True, "detail": "no usable GPU"}
    else:
        auto = {"variant": None, "available": False, "detail": f"neither cuda ({NO_GPU}) nor llvm ({out['llvm']['detail']})"}
    out["auto"] = auto
    return out


def check_llvm_backend() -> str:
    """Renders a tiny Cornell box with the LLVM variant in a child process.

    A bad libLLVM aborts the whole process, so the probe runs out of process. Returns the libLLVM path;
    raises SystemExit(2) with the fix when the probe fails.
    """
    try:
        path = configure_drjit_llvm()
    except LLVMNotFound as exc:
        raise SystemExit(f"splitbench: error: {exc}")
    probe = (
        "import mitsuba as mi; mi.set_variant('llvm_ad_rgb');"
        "d = mi.cornell_box(); d['sensor']['film']['width'] = 16; d['sensor']['film']['height'] = 16;"
        "import numpy as np; img = np.array(mi.render(mi.load_dict(d), spp=4));"
        "assert np.isfinite(img).all() and img.mean() > 0"
    )
    proc = subprocess.run([sys.executable, "-c", probe], env=dict(os.environ, DRJIT_LIBLLVM_PATH=path),
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"splitbench: error: Dr.Jit's LLVM backend failed with {path}: {tail[0]}")
    return path
