"""Results store: one directory per run, keyed by a hash of the full run identity. Schema: docs/results.md.

A run is written into a hidden temporary directory next to its final place and renamed when every file is in,
with ``summary.json`` written last; a directory counts as a complete run only when ``summary.json`` exists.
A rerun of a complete run is skipped.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import re
import shutil
import subprocess
import tempfile
from functools import lru_cache
from importlib import metadata
from pathlib import Path

import numpy as np

from suite import fileio

SCHEMA_VERSION = 1
REPO_DIR = Path(__file__).resolve().parents[2]
# Versions that can change results; recorded in config.json and part of the run key.
PACKAGES = ("splitbench", "numpy", "mitsuba", "drjit", "embreex", "OpenImageIO", "scikit-image",
            "colour-science", "flip-evaluator", "pandas", "pyarrow", "lz4", "zstandard", "python-lzo")


def package_versions() -> dict:
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def host_facts() -> dict:
    from suite import memory

    return {"node": platform.node(), "machine": platform.machine(), "system": platform.system(),
            "platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
            "python": platform.python_version(), "allocator": memory.setting()}


@lru_cache(maxsize=1)
def git_commit() -> dict:
    """The repository's commit (read-only git calls); 'none' when there is no commit or no git."""
    def git(*args):
        return subprocess.run(["git", "-C", str(REPO_DIR), *args], capture_output=True, text=True, timeout=10)

    try:
        head = git("rev-parse", "HEAD")
        commit = head.stdout.strip() if head.returncode == 0 else "none"
        dirty = bool(git("status", "--porcelain", "--untracked-files=no").stdout.strip()) if commit != "none" else None
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "none", None
    return {"commit": commit, "dirty": dirty}


def environment() -> dict:
    return {"packages": package_versions(), "host": host_facts(), "git": git_commit()}


def canonical_json(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


# The sources whose change can change a run's results: the suite, netsim and the method's own folder.
CODE_ROOTS = ("suite", "netsim")
CODE_SUFFIXES = (".py", ".toml")


@lru_cache(maxsize=None)
def code_digest(method: str | None = None) -> str:
    """SHA-256 over the package sources that produce a run (path and content of every .py/.toml file under
    suite/, netsim/ and methods/<method>/, plus pyproject.toml), so an edited source makes a new run even
    before it is committed. Computed once per process."""
    h = hashlib.sha256()
    roots = [REPO_DIR / r for r in CODE_ROOTS]
    if method:
        from suite.harness import registry

        roots.append(registry.get(method).path)
    files = [REPO_DIR / "pyproject.toml"]
    for root in roots:
        files += sorted(p for p in Path(root).rglob("*") if p.suffix in CODE_SUFFIXES and p.is_file()
                        and "__pycache__" not in p.parts)
    for p in files:
        if p.is_file():
            rel = p.relative_to(REPO_DIR) if p.is_relative_to(REPO_DIR) else p
            h.update(str(rel).encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def run_key(config: dict, env: dict) -> str:
    """Hash of what makes a run: schema version, config (seed, backend, code digest included), package versions,
    host."""
    # The code is identified by the config's code_digest (sources, committed or not); the commit is recorded in
    # config.json but is not part of the key, so a commit that changes no source keeps the runs.
    identity = {"schema_version": SCHEMA_VERSION, "config": config, "packages": env["packages"],
                "host": {k: env["host"][k] for k in ("node", "machine", "system")}}
    return hashlib.sha256(canonical_json(identity).encode()).hexdigest()


def _label(text) -> str:
    text = Path(str(text)).stem if os.sep in str(text) else str(text)
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", text)[:40] or "x"


def run_dir_name(config: dict, key: str) -> str:
    w, h = config["resolution"]
    parts = [config["method"], config.get("variant", "default"), _label(config["scene"]), f"{w}x{h}",
             _label(config["net"]), config["protocol"], key[:12]]
    return "-".join(_label(p) for p in parts)


def is_complete(run_dir) -> bool:
    return (Path(run_dir) / "summary.json").is_file()


def complete_runs(root) -> list[Path]:
    """Every complete run directory under ``root`` (temporary and interrupted ones are ignored)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(p.parent for p in root.rglob("summary.json")
                  if not any(part.startswith(".tmp-") for part in p.parent.relative_to(root).parts))


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_json(path, obj) -> None:
    """Writes ``obj`` as JSON (non-finite floats as null), atomically (suite.fileio)."""
    fileio.write_text(path, json.dumps(_jsonable(obj), indent=2, sort_keys=True) + "\n")


class RunWriter:
    """Writes one run into a temporary directory; :meth:`commit` renames it into place.

    Use as a context manager: leaving the block without commit (an exception, an interrupt) removes the
    temporary directory, so nothing that looks like a result is left behind.
    """

    def __init__(self, root, name: str):
        self.root = Path(root)
        self.final = self.root / name
        self.root.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{name}-", dir=self.root))
        self.committed = False

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if not self.committed:
            shutil.rmtree(self.tmp, ignore_errors=True)
        return False

    def path(self, relative: str) -> Path:
        p = self.tmp / relative
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_json(self, relative: str, obj) -> None:
        write_json(self.path(relative), obj)

    def write_table(self, relative: str, df) -> None:
        df.to_parquet(self.path(relative), index=False)

    def commit(self, summary: dict) -> Path:
        write_json(self.tmp / "summary.json", summary)
        if self.final.exists():
            if is_complete(self.final):
                # Another worker finished the same run first; its result is equivalent.
                shutil.rmtree(self.tmp, ignore_errors=True)
                self.committed = True
                return self.final
            shutil.rmtree(self.final)  # a leftover without summary.json is not a result
        os.rename(self.tmp, self.final)
        self.committed = True
        return self.final


def summarize_frames(df, columns) -> dict:
    """Mean, p50 and p95 of each numeric column that has finite values."""
    out = {}
    for col in columns:
        if col not in df:
            continue
        values = np.asarray(df[col], dtype=float)
        values = values[np.isfinite(values)]
        if values.size == 0:
            continue
        out[col] = {"mean": float(values.mean()), "p50": float(np.percentile(values, 50)),
                    "p95": float(np.percentile(values, 95))}
    return out


def load_run(run_dir) -> dict:
    """config, summary and frames (a DataFrame) of one complete run."""
    import pandas as pd

    run_dir = Path(run_dir)
    out = {"dir": run_dir, "config": json.loads((run_dir / "config.json").read_text()),
           "summary": json.loads((run_dir / "summary.json").read_text()),
           "frames": pd.read_parquet(run_dir / "frames.parquet")}
    updates = run_dir / "updates.parquet"
    out["updates"] = pd.read_parquet(updates) if updates.exists() else None
    return out
