"""Locating a libLLVM that Dr.Jit's LLVM backend can JIT rendering kernels with.

Dr.Jit loads libLLVM at run time. Mitsuba's rendering kernels use the ``llvm.maximum``/``fmaximum``
intrinsics, which LLVM 15 cannot select on x86-64 ("LLVM ERROR: Cannot select: ... fmaximum"), and the
process aborts. Debian 12 ships LLVM 15 by default, so we look for LLVM >= 16 and export
``DRJIT_LIBLLVM_PATH`` before Dr.Jit is imported. We never fall back silently to an older one.

This module imports nothing heavy: the set-up script uses it before the virtualenv exists.
"""
from __future__ import annotations

import glob
import os
import re

MIN_LLVM_MAJOR = 16

SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)

FIX = (
    "install LLVM >= 16: as root `apt-get install -y libllvm19` (Debian/Ubuntu); without root "
    "`apt-get download libllvm19 && dpkg-deb -x libllvm19_*.deb ~/llvm19` and "
    "`export DRJIT_LIBLLVM_PATH=~/llvm19/usr/lib/x86_64-linux-gnu/libLLVM-19.so` (or conda-forge's libllvm19)"
)


class LLVMNotFound(RuntimeError):
    pass


def llvm_major(path: str) -> int | None:
    """Major version from a libLLVM file name (libLLVM-19.so, libLLVM.so.19.1, libLLVM-15.so.1)."""
    name = os.path.basename(os.path.realpath(path))
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)", r"libLLVM\.(\d+)\.dylib"):
        m = re.search(pattern, name)
        if m:
            return int(m.group(1))
    return None


def candidates() -> list[tuple[int, str]]:
    found = {}
    for d in SEARCH_DIRS + tuple(glob.glob("/usr/lib/llvm-*/lib")):
        for path in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(os.path.join(d, "libLLVM*.dylib")):
            major = llvm_major(path)
            if major is not None:
                found.setdefault(os.path.realpath(path), (major, path))
    return sorted(found.values(), reverse=True)


def find_libllvm() -> str:
    """The libLLVM to use: $DRJIT_LIBLLVM_PATH if set (checked), else the newest >= 16 on the system."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        if not os.path.exists(env):
            raise LLVMNotFound(f"DRJIT_LIBLLVM_PATH={env} does not exist; {FIX}")
        major = llvm_major(env)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise LLVMNotFound(
                f"DRJIT_LIBLLVM_PATH={env} is LLVM {major}, which aborts in Mitsuba kernels (fmaximum); {FIX}")
        return env
    for major, path in candidates():
        if major >= MIN_LLVM_MAJOR:
            return path
    older = ", ".join(f"{p} (LLVM {m})" for m, p in candidates()) or "none"
    raise LLVMNotFound(f"no libLLVM >= {MIN_LLVM_MAJOR} found (seen: {older}); {FIX}")


def configure_drjit_llvm() -> str:
    """Sets DRJIT_LIBLLVM_PATH for this process (must run before `import drjit`). Returns the path."""
    path = find_libllvm()
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path
