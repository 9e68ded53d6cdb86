"""Mitsuba / Dr.Jit set-up: one place that picks the libLLVM and the variant.

Import Mitsuba through :func:`mitsuba` rather than ``import mitsuba`` so that ``DRJIT_LIBLLVM_PATH``
is set before Dr.Jit loads (see :mod:`suite.core.llvm`).

Variants: ``llvm`` → ``llvm_ad_rgb`` (CPU, the default), ``cuda`` → ``cuda_ad_rgb`` (when a GPU is present),
``scalar`` → ``scalar_rgb`` (last resort, slow; only when asked for by name). ``auto`` picks cuda when a GPU is
usable, else llvm. There is no silent fall-back: a variant that cannot start raises :class:`UserError`.
"""
from __future__ import annotations

import os
import subprocess
import sys

from suite.errors import UserError
from suite.core.llvm import LLVMNotFound, configure_drjit_llvm

VARIANTS = {"llvm": "llvm_ad_rgb", "cuda": "cuda_ad_rgb", "scalar": "scalar_rgb"}

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


def cuda_available() -> bool:
    _configure_once()
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001 - any driver problem means "no CUDA"
        return False


def resolve_variant(name: str = "auto") -> str:
    """Maps a backend flavour (auto|llvm|cuda|scalar or a full variant name) to a Mitsuba variant."""
    _configure_once()
    if name in ("auto", None, ""):
        name = "cuda" if cuda_available() else "llvm"
    variant = VARIANTS.get(name, name)
    if variant not in VARIANTS.values():
        raise UserError(f"unknown Mitsuba variant '{name}' (choose from auto, {', '.join(VARIANTS)})")
    if variant.startswith("llvm") and os.environ.get("SPLITBENCH_LLVM_PROBLEM"):
        raise UserError(os.environ["SPLITBENCH_LLVM_PROBLEM"])
    if variant.startswith("cuda") and not cuda_available():
        raise UserError("Mitsuba variant 'cuda' needs an NVIDIA GPU with a working driver; none was found")
    return variant


def mitsuba(variant: str = "auto"):
    """Returns the ``mitsuba`` module with the requested variant active."""
    variant = resolve_variant(variant)
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


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
