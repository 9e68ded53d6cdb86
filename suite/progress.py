"""Progress bars (tqdm on stderr), silenced by SPLITBENCH_PROGRESS=0 so that tests and CI logs stay clean."""
from __future__ import annotations

import os


def enabled() -> bool:
    return os.environ.get("SPLITBENCH_PROGRESS", "1") not in ("0", "false", "no", "off")


def progress(iterable=None, total=None, desc: str | None = None, unit: str = "it", leave: bool = False):
    """A tqdm bar over ``iterable`` (or a manual bar with ``total``); disabled when progress is off."""
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, disable=not enabled(),
                dynamic_ncols=True)
