"""Freed memory kept for reuse (glibc's allocator), set once when the suite is imported.

numpy takes arrays from ``malloc``. glibc serves a request above its mmap threshold (128 KiB, raised on its own up to
32 MiB as such blocks are freed) with a fresh ``mmap`` and unmaps it when it is freed, and it returns the free top of
its heap to the system beyond a trim threshold. A stage that makes its outputs afresh every frame then pays a page
fault and the kernel's zeroing for every 4 KiB page it writes, every frame: about 0.5 µs a page on this project's
2-core VM, so a 1080p frame's float64 (H, W, 3) array (50 MB) costs some 6 ms before any work is done.

:func:`keep_freed_memory` raises the mmap threshold to :data:`MMAP_THRESHOLD_BYTES` and the trim threshold to
:data:`TRIM_THRESHOLD_BYTES`, so such arrays come from the heap and pages freed by one frame serve the next. Measured
on the 2-core VM (``bench core``, living_room 1080p, Embree): G-buffer 589 -> 469 ms, visibility pass 657 -> 581 ms,
point-light shading 430 -> 377 ms. The price is that a process keeps the memory of its peak (up to the trim
threshold) mapped after it is freed.

``SPLITBENCH_KEEP_FREED_MEMORY=0`` leaves the allocator as it is; other C libraries are left alone. The setting in
force is recorded with every result (:func:`setting`, in the host facts).
"""
from __future__ import annotations

import os

MMAP_THRESHOLD_BYTES = 256 << 20
TRIM_THRESHOLD_BYTES = 1 << 30
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)

_setting = "not set"


def keep_freed_memory() -> str:
    """Sets the thresholds (once per process); returns :func:`setting`."""
    global _setting
    if _setting != "not set":
        return _setting
    if os.environ.get("SPLITBENCH_KEEP_FREED_MEMORY", "1") == "0":
        _setting = "allocator defaults (SPLITBENCH_KEEP_FREED_MEMORY=0)"
        return _setting
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 \
            and libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    except (OSError, AttributeError):
        ok = False
    _setting = (f"glibc mallopt: mmap threshold {MMAP_THRESHOLD_BYTES} B, trim threshold {TRIM_THRESHOLD_BYTES} B"
                if ok else "allocator defaults (no glibc mallopt)")
    return _setting


def setting() -> str:
    """What :func:`keep_freed_memory` did in this process."""
    return _setting
