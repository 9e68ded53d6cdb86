"""Atomic file writes: the one helper every layer uses to publish a file (images, JSON documents, report pages).

A file is written under a temporary name in the destination's directory and ``os.replace``-d over the
destination when complete, so a reader never sees a half-written file under the final name (the results store
and the report treat a present file as complete). On any error the temporary file is removed.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

_umask: int | None = None


def _file_mode() -> int:
    """0o666 minus the process umask: the mode ``open()`` would give a new file.

    mkstemp creates files readable by their owner only, so published files are chmod-ed to this. Linux
    reports the umask in /proc without changing it; elsewhere it is read once by setting and restoring it.
    """
    global _umask
    if _umask is None:
        try:
            with open("/proc/self/status") as status:
                _umask = next(int(line.split()[1], 8) for line in status if line.startswith("Umask:"))
        except (OSError, StopIteration, ValueError, IndexError):
            _umask = os.umask(0o022)
            os.umask(_umask)
    return 0o666 & ~_umask


def publish(tmp_path, path) -> None:
    """Moves a finished temporary file onto ``path`` in one step (same directory, so ``os.replace`` is
    atomic), giving it the permissions a normally created file would have."""
    os.chmod(tmp_path, _file_mode())
    os.replace(tmp_path, path)


@contextlib.contextmanager
def atomic_target(path, suffix: str = ".tmp"):
    """Yields a temporary file name beside ``path``; on success it replaces ``path`` in one step, on any
    error it is removed, so a crash never leaves a half-written file under the final name.

    ``suffix`` ends the temporary name; writers that pick a format from the extension (OpenImageIO,
    matplotlib) need it to end with the destination's own (``f".tmp{path.suffix}"``).
    """
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.",
                                    suffix=suffix)
    os.close(fd)
    try:
        yield tmp_name
        publish(tmp_name, path)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        raise


def write_text(path, text: str) -> Path:
    """Writes ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_target(path) as tmp_name:
        Path(tmp_name).write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes(path, data: bytes) -> Path:
    """Writes ``data`` to ``path`` atomically; returns the path."""
    with atomic_target(path) as tmp_name:
        Path(tmp_name).write_bytes(data)
    return Path(path)
