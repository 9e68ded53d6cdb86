"""Report helpers shared by the report builder (``reports/build.py``) and the method report sections
(``methods/<name>/report.py``): escaping, HTML tables, matplotlib figures, and the files a report writes (CSV,
PNG, copies), each written atomically (:mod:`suite.fileio`). They format and write; they read no results.
"""
from __future__ import annotations

import html
import json
import re
import shutil
from pathlib import Path

import pandas as pd

from suite import fileio

# Columns whose name contains one of these words hold counts: shown as whole numbers with separators.
COUNT_WORDS = ("bytes", "pixel", "rays")


def load_bench(name: str, run_dirs, results_root) -> dict | None:
    """The benchmark document ``<results>/bench/<name>.json`` (None when absent or unreadable); without
    ``results_root`` the results root is the parent of the first run directory."""
    if results_root is None:
        dirs = [Path(d) for d in run_dirs or []]
        results_root = dirs[0].parent if dirs else None
    path = Path(results_root) / "bench" / f"{name}.json" if results_root is not None else None
    try:
        return json.loads(path.read_text()) if path is not None and path.is_file() else None
    except (OSError, json.JSONDecodeError):
        return None


def esc(value) -> str:
    """HTML-escaped text of any value."""
    return html.escape(str(value))


def slug(*parts) -> str:
    """A file-name part made of ``parts``: letters, digits, ``.``, ``-`` and ``_`` only (``lan-home,ssr=off`` →
    ``lan-home_ssr_off``)."""
    return "_".join(re.sub(r"[^A-Za-z0-9.-]+", "_", str(p)).strip("_") or "x" for p in parts)


def _float_text(v: float) -> str:
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.4g}"


def lo_hi_text(lo_hi, digits: int = 3) -> str:
    """A bench's ``..._range`` (``[lowest, highest]`` ratio of one repeat: ``suite.core.trace.bench.paired_range``)
    as ``lo-hi``; empty where none was stored (documents written before ranges were)."""
    if not isinstance(lo_hi, (list, tuple)) or len(lo_hi) != 2:
        return ""
    return f"{lo_hi[0]:.{digits}f}-{lo_hi[1]:.{digits}f}"


def straddles(lo_hi, goal: float) -> bool:
    """Whether a bench's ``..._range`` has repeats on both sides of ``goal`` (the run does not decide it)."""
    return bool(lo_hi_text(lo_hi)) and lo_hi[0] < goal <= lo_hi[1]


def range_text(lo_hi, digits: int = 3) -> str:
    """`` (repeats lo-hi)`` after a printed ratio (:func:`lo_hi_text`), or nothing."""
    text = lo_hi_text(lo_hi, digits)
    return f" (repeats {text})" if text else ""


def table_html(df: pd.DataFrame, index: bool = False, prose: bool = False) -> str:
    """An HTML table (class ``t``): count columns (:data:`COUNT_WORDS`) and floats from 1000 up as whole numbers
    with separators, other floats to 4 significant digits, missing values as "–"; cell text is escaped.
    ``prose``: cells hold sentences (class ``t prose``: the page aligns them left, at the top)."""
    df = df.copy()
    for col in df.columns:
        if any(word in str(col) for word in COUNT_WORDS) and pd.api.types.is_numeric_dtype(df[col]) \
                and not pd.api.types.is_bool_dtype(df[col]):
            df[col] = df[col].map(lambda v: "–" if pd.isna(v) else f"{v:,.0f}")
    return df.to_html(index=index, float_format=_float_text, na_rep="–", border=0,
                      classes="t prose" if prose else "t", escape=True)


def figure(width_in: float = 8.0, height_in: float = 4.0):
    """A matplotlib figure (no pyplot state, so safe in any thread) and its one axes."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    return fig, fig.add_subplot(111)


def label_axes(ax, xlabel: str, ylabel: str, xscale: str | None = None, yscale: str | None = None,
               legend: str | None = "outside", fontsize: int = 7) -> None:
    """Axis labels and scales, and a legend when anything is labelled: ``"outside"`` (right of the axes, for
    long run labels), ``"inside"`` (matplotlib's best place) or None."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if xscale:
        ax.set_xscale(xscale)
    if yscale:
        ax.set_yscale(yscale)
    if legend and ax.get_legend_handles_labels()[0]:
        if legend == "outside":
            ax.legend(fontsize=fontsize, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        else:
            ax.legend(fontsize=fontsize)


def save_figure(fig, path, tight: bool = True) -> str:
    """Lays out (``tight``: matplotlib's tight layout; False keeps the figure's own, for grids of many axes where
    it is slow) and writes ``fig`` to ``path`` (its format from the extension); returns the file name."""
    path = Path(path)
    if tight:
        fig.tight_layout()
    with fileio.atomic_target(path, suffix=f".tmp{path.suffix}") as tmp_name:
        fig.savefig(tmp_name)
    return path.name


def write_csv(df: pd.DataFrame, path, index: bool = False) -> str:
    """Writes ``df`` as CSV to ``path``; returns the file name."""
    path = Path(path)
    with fileio.atomic_target(path, suffix=".tmp.csv") as tmp_name:
        df.to_csv(tmp_name, index=index)
    return path.name


def copy_file(src, dst) -> bool:
    """Copies ``src`` to ``dst`` when ``src`` is a file; returns whether it did."""
    if not Path(src).is_file():
        return False
    with fileio.atomic_target(dst, suffix=f".tmp{Path(dst).suffix}") as tmp_name:
        shutil.copyfile(src, tmp_name)
    return True


class SectionFiles:
    """The files of one report section, in ``<out_dir>/<folder>/``, linked relative to index.html. Without an
    output directory it writes nothing and every link is empty (the section still builds)."""

    def __init__(self, out_dir, folder: str):
        self.name = folder
        self.folder = Path(out_dir) / folder if out_dir is not None else None
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)

    def csv(self, df: pd.DataFrame, name: str) -> str:
        """Writes ``df`` as ``name``; returns an HTML link to it (" " first) or ""."""
        if self.folder is None:
            return ""
        write_csv(df, self.folder / name)
        return f" <a href='{esc(self.name)}/{esc(name)}'>{esc(name)}</a>"

    def json(self, obj, name: str) -> str:
        """Writes ``obj`` as JSON; returns an HTML link to it (" " first) or ""."""
        if self.folder is None:
            return ""
        fileio.write_text(self.folder / name, json.dumps(obj, indent=1, sort_keys=True) + "\n")
        return f" <a href='{esc(self.name)}/{esc(name)}'>{esc(name)}</a>"

    def plot(self, fig, name: str, tight: bool = True) -> str:
        """Writes ``fig`` as ``name`` (``tight``: see :func:`save_figure`); returns an ``<img>`` or ""."""
        if self.folder is None:
            return ""
        save_figure(fig, self.folder / name, tight)
        return f"<img src='{esc(self.name)}/{esc(name)}'>"

    def copy(self, src, name: str) -> str | None:
        """Copies the file ``src`` as ``name``; returns its link target, or None."""
        if self.folder is None or not copy_file(src, self.folder / name):
            return None
        return f"{self.name}/{name}"
