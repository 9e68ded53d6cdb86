"""The report: reads stored results only (never runs anything) → CSV tables + PNG plots → report/index.html.

Sections: run matrix; frame-time breakdown per run (stacked by stage and network); bandwidth; SSIM/DSSIM per
frame; speed vs error across all runs; machine and versions. Extensions:

* a method may ship ``methods/<name>/report.py`` with ``section(results_df, run_dirs) -> str`` (an HTML
  fragment); it gets the frames of its own runs (with the run columns of the matrix) and their directories;
  a section that also takes the keywords ``out_dir`` (the report directory, for its own plots and CSVs, which
  it links relative to index.html) and/or ``results_root`` (to read stored documents beside the runs, such as
  benchmark output) gets them too;
* netsim's committed validation against ns-3 (``netsim/validation/validation.csv``), summarised per transport;
* every CSV under a directory listed in ``EXTRA_TABLE_DIRS`` is included as a table.
"""
from __future__ import annotations

import html
import importlib.util
import inspect
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from suite.harness import registry, results

REPO_DIR = Path(__file__).resolve().parent.parent
EXTRA_TABLE_DIRS: list[Path] = []
NETSIM_VALIDATION_CSV = REPO_DIR / "netsim" / "validation" / "validation.csv"
RUN_COLUMNS = ["run", "method", "variant", "mode", "scene", "resolution", "net", "protocol", "frames"]


def load_all(results_root) -> tuple[pd.DataFrame, pd.DataFrame, list[dict]]:
    """(runs: one row per complete run, frames: all frames with the run columns, loaded runs)."""
    loaded, run_rows, frame_tables = [], [], []
    for run_dir in results.complete_runs(results_root):
        run = results.load_run(run_dir)
        s, cfg = run["summary"], run["config"]
        w, h = s["resolution"]
        # One label per run of a preset: presets may sweep resolutions as well as networks.
        label = f"{s['method']}/{s['variant']} {Path(str(s['scene'])).stem} {w}x{h} {s['net']}/{s['protocol']}"
        row = {"run": run_dir.name, "label": label, "method": s["method"], "variant": s["variant"],
               "mode": s["mode"], "scene": Path(str(s["scene"])).stem, "resolution": f"{w}x{h}", "net": s["net"],
               "protocol": s["protocol"], "frames": s["frames"], "backend": cfg["config"]["backend"],
               "seed": cfg["seed"], "fps": s["fps"], "bandwidth_mbps": s["bandwidth_mbps"],
               "bandwidth_down_mbps": s["bandwidth_down_mbps"], "bandwidth_up_mbps": s["bandwidth_up_mbps"],
               "prepare_ms": s["prepare_ms"], "rays": s["rays"]}
        for col in ("frame_ms", "latency_ms", "staleness_ms", "ssim", "dssim", "psnr_db", "flip", "zl_dssim"):
            stats = s["stats"].get(col, {})
            row[f"{col}_mean"] = stats.get("mean", np.nan)
            if col in ("frame_ms", "latency_ms"):
                row[f"{col}_p95"] = stats.get("p95", np.nan)
        row["git_commit"] = cfg["git"]["commit"]
        run_rows.append(row)
        df = run["frames"].copy()
        for col in RUN_COLUMNS + ["label"]:
            if col not in df:
                df.insert(0, col, row[col])
        frame_tables.append(df)
        loaded.append(run)
    runs = pd.DataFrame(run_rows)
    frames = pd.concat(frame_tables, ignore_index=True) if frame_tables else pd.DataFrame()
    return runs, frames, loaded


def _figure(width_in=8.0, height_in=4.0):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    return fig, fig.add_subplot(111)


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path)
    return path.name


def breakdown_table(frames: pd.DataFrame) -> pd.DataFrame:
    """Mean ms per run of each event on the critical path (cp_*); the parts sum to the mean frame time."""
    cols = [c for c in frames.columns if c.startswith("cp_") and c.endswith("_ms")]
    table = frames.groupby("label")[cols].mean().fillna(0.0)
    table = table.loc[:, (table > 0).any()]
    table["frame_ms"] = frames.groupby("label")["frame_ms"].mean()
    return table


def stage_table(frames: pd.DataFrame) -> pd.DataFrame:
    """Mean ms per run of every stage (stage_*) and message (net_*), on the critical path or not."""
    cols = [c for c in frames.columns if (c.startswith("stage_") or c.startswith("net_")) and c.endswith("_ms")]
    table = frames.groupby("label")[cols].mean()
    return table.loc[:, table.notna().any()].fillna(0.0)


def plot_breakdown(table: pd.DataFrame, path: Path) -> str:
    fig, ax = _figure(12, 1.5 + 0.45 * max(len(table), 4))
    left = np.zeros(len(table))
    parts = [c for c in table.columns if c != "frame_ms"]
    cmap = __import__("matplotlib").colormaps["tab20"]
    for k, col in enumerate(parts):
        name = col[len("cp_"):-len("_ms")]
        is_net = name.startswith("net_")
        label = f"network: {name[len('net_'):]}" if is_net else name
        ax.barh(table.index, table[col], left=left, label=label, color=cmap(k % 20), hatch="//" if is_net else None)
        left += table[col].to_numpy()
    ax.set_xlabel("ms per frame on the critical path (client and server stages that overlap count once)")
    if parts:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(fig, path)


def plot_bandwidth(runs: pd.DataFrame, path: Path) -> str:
    fig, ax = _figure(9, 0.5 + 0.45 * max(len(runs), 2))
    ax.barh(runs["label"], runs["bandwidth_down_mbps"], label="down")
    ax.barh(runs["label"], runs["bandwidth_up_mbps"], left=runs["bandwidth_down_mbps"], label="up")
    ax.set_xlabel("Mbit/s (simulated)")
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_quality(frames: pd.DataFrame, path: Path) -> str:
    fig, ax = _figure(12, 4)
    for label, df in frames.groupby("label"):
        df = df[df["dssim"].notna() | df["zl_dssim"].notna()]
        if df.empty:
            continue
        line, = ax.plot(df["frame"], df["dssim"], marker="o", label=f"{label} vs reference")
        if df["zl_dssim"].fillna(0).abs().sum() > 0:
            ax.plot(df["frame"], df["zl_dssim"], ls="--", color=line.get_color(), label=f"{label} vs zero-latency")
    ax.set_xlabel("frame")
    ax.set_ylabel("DSSIM (lower is better)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(fig, path)


def plot_speed_vs_error(runs: pd.DataFrame, path: Path) -> str:
    fig, ax = _figure(7, 5)
    for method, df in runs.groupby("method"):
        ax.scatter(df["frame_ms_mean"], df["dssim_mean"], label=method)
    ax.set_xlabel("frame ms (mean)")
    ax.set_ylabel("DSSIM vs path-traced reference (mean)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    return _save(fig, path)


def machine_table(loaded: list[dict]) -> pd.DataFrame:
    rows = []
    for run in loaded:
        cfg = run["config"]
        row = {"run": run["dir"].name, "host": cfg["host"]["node"], "platform": cfg["host"]["platform"],
               "cpus": cfg["host"]["cpu_count"], "python": cfg["host"]["python"],
               "backend": cfg["backend"].get("name"), "git_commit": cfg["git"]["commit"]}
        row.update({f"{k}": v for k, v in cfg["packages"].items()})
        rows.append(row)
    df = pd.DataFrame(rows)
    if df.empty:
        return df
    return df.drop(columns=["run"]).drop_duplicates().reset_index(drop=True)


def method_sections(frames: pd.DataFrame, loaded: list[dict], out_dir=None, results_root=None) -> list[tuple[str, str]]:
    """HTML from each method's optional report.py ``section(results_df, run_dirs)`` (plus ``out_dir`` and
    ``results_root`` for a section that takes them)."""
    out = []
    for name, spec in registry.discover().items():
        file = spec.path / "report.py"
        if not file.is_file() or frames.empty or name not in set(frames["method"]):
            continue
        module_spec = importlib.util.spec_from_file_location(f"splitbench_methods.{name}.report", file)
        module = importlib.util.module_from_spec(module_spec)
        try:
            module_spec.loader.exec_module(module)
            run_dirs = [r["dir"] for r in loaded if r["summary"]["method"] == name]
            accepted = inspect.signature(module.section).parameters
            extra = {k: v for k, v in (("out_dir", out_dir), ("results_root", results_root))
                     if k in accepted and v is not None}
            out.append((name, module.section(frames[frames["method"] == name].copy(), run_dirs, **extra)))
        except Exception as exc:  # noqa: BLE001 - one method's section must not break the report
            out.append((name, f"<p>section failed: {html.escape(f'{type(exc).__name__}: {exc}')}</p>"))
    return out


def extra_tables() -> list[tuple[str, pd.DataFrame]]:
    tables = []
    for folder in EXTRA_TABLE_DIRS:
        for csv in sorted(Path(folder).glob("*.csv")):
            try:
                tables.append((f"{folder.relative_to(REPO_DIR) if folder.is_relative_to(REPO_DIR) else folder}"
                               f"/{csv.name}", pd.read_csv(csv)))
            except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError):
                continue
    return tables


def netsim_validation_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Median and p90 relative completion-time error of netsim against ns-3, per transport, overall and split
    into loss-free and lossy grid points (issue goals: median <= 10 %, p90 <= 25 %, loss-free <= 5 %)."""
    rows = []
    for transport, group in table.groupby("transport"):
        row = {"transport": transport, "cases": len(group)}
        for label, part in (("", group), ("loss-free ", group[group["loss"] == 0]), ("lossy ", group[group["loss"] > 0])):
            err = 100.0 * part["rel_error"]
            row[f"{label}median %"] = float(err.median()) if len(err) else np.nan
            row[f"{label}p90 %"] = float(err.quantile(0.9)) if len(err) else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def netsim_validation_section(out: Path, csv: Path = None) -> str:
    """The committed netsim-vs-ns-3 validation table (netsim/validation/), summarised; empty if absent."""
    csv = Path(csv or NETSIM_VALIDATION_CSV)
    try:
        table = pd.read_csv(csv)
        summary = netsim_validation_summary(table)
    except (OSError, KeyError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return ""
    table.to_csv(out / "netsim_validation.csv", index=False)
    worst = table.sort_values("rel_error", ascending=False).head(8)
    return ("<h2>Network model: netsim against ns-3</h2><p>Completion time of the same transfers in netsim and in "
            "ns-3 (sizes 1 kB–8 MB, 10 Mbit/s–1 Gbit/s, RTT 2–100 ms, loss 0–2 %), relative error per transport. "
            "Produced by <code>splitbench netsim validate</code>; modelling differences are in docs/netsim.md. "
            f"<a href='netsim_validation.csv'>all {len(table)} points</a></p>" + _table_html(summary)
            + "<p>Largest errors:</p>" + _table_html(worst))


def _table_html(df: pd.DataFrame) -> str:
    return df.to_html(index=False, float_format=lambda v: f"{v:.4g}", na_rep="–", border=0, classes="t")


def build(results_root, out_dir) -> Path:
    """Writes out_dir/index.html with its PNG plots and CSV tables; returns the index path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs, frames, loaded = load_all(results_root)
    body = [f"<h1>splitbench report</h1><p>results: <code>{html.escape(str(Path(results_root).resolve()))}</code>"
            f" — {len(runs)} complete runs</p>"]
    if runs.empty:
        body.append("<p>No complete runs yet. Run <code>splitbench reproduce --preset smoke</code>.</p>")
    else:
        runs.to_csv(out / "runs.csv", index=False)
        frames.to_csv(out / "frames.csv", index=False)
        matrix = runs[["method", "variant", "mode", "scene", "resolution", "net", "protocol", "frames",
                       "frame_ms_mean", "frame_ms_p95", "latency_ms_mean", "staleness_ms_mean", "bandwidth_mbps",
                       "ssim_mean", "dssim_mean", "zl_dssim_mean", "rays", "run"]]
        body.append("<h2>Run matrix</h2><p><a href='runs.csv'>runs.csv</a> · <a href='frames.csv'>frames.csv</a>"
                    "</p>" + _table_html(matrix))

        table = breakdown_table(frames)
        table.to_csv(out / "breakdown.csv")
        stage_table(frames).to_csv(out / "stages.csv")
        body.append("<h2>Frame-time breakdown</h2><p>Mean ms per frame of each stage and message (hatched) on the "
                    "critical path; a bar is the mean frame time. <a href='breakdown.csv'>breakdown.csv</a>; every "
                    "stage, on the critical path or not: <a href='stages.csv'>stages.csv</a></p>"
                    f"<img src='{plot_breakdown(table, out / 'breakdown.png')}'>")

        runs[["label", "bandwidth_mbps", "bandwidth_down_mbps", "bandwidth_up_mbps"]].to_csv(
            out / "bandwidth.csv", index=False)
        body.append("<h2>Bandwidth</h2><p><a href='bandwidth.csv'>bandwidth.csv</a></p>"
                    f"<img src='{plot_bandwidth(runs, out / 'bandwidth.png')}'>")

        quality = frames[["label", "frame", "ssim", "dssim", "psnr_db", "flip", "zl_ssim", "zl_dssim"]]
        quality = quality[quality["ssim"].notna() | quality["zl_ssim"].notna()]
        quality.to_csv(out / "quality.csv", index=False)
        body.append("<h2>SSIM / DSSIM per frame</h2><p>Solid: against the Mitsuba path-traced reference; dashed: "
                    "against the method's own zero-latency run. <a href='quality.csv'>quality.csv</a></p>"
                    f"<img src='{plot_quality(frames, out / 'quality.png')}'>")

        runs[["label", "frame_ms_mean", "dssim_mean", "bandwidth_mbps"]].to_csv(out / "speed_vs_error.csv",
                                                                                index=False)
        body.append("<h2>Speed vs error</h2><p><a href='speed_vs_error.csv'>speed_vs_error.csv</a></p>"
                    f"<img src='{plot_speed_vs_error(runs, out / 'speed_vs_error.png')}'>")

        body.append("<h2>Frames</h2>" + _thumbnails(loaded, out))

        for name, fragment in method_sections(frames, loaded, out_dir=out, results_root=Path(results_root)):
            body.append(f"<h2>Method: {html.escape(name)}</h2>{fragment}")

        machines = machine_table(loaded)
        machines.to_csv(out / "machines.csv", index=False)
        body.append("<h2>Machine and versions</h2><p><a href='machines.csv'>machines.csv</a></p>"
                    + _table_html(machines))
    body.append(netsim_validation_section(out))
    for name, df in extra_tables():
        body.append(f"<h2>Table: {html.escape(name)}</h2>" + _table_html(df))
    index = out / "index.html"
    tmp = out / ".index.html.tmp"
    tmp.write_text(_PAGE.format(body="\n".join(body)))
    tmp.replace(index)
    return index


def _thumbnails(loaded: list[dict], out: Path) -> str:
    """The last saved frame of each run, next to its reference when there is one."""
    folder = out / "frames"
    folder.mkdir(exist_ok=True)
    cells = []
    for run in loaded:
        pngs = sorted((run["dir"] / "images").glob("frame_*.png"))
        if not pngs:
            continue
        name = run["dir"].name
        shutil.copyfile(pngs[-1], folder / f"{name}.png")
        ref = run["dir"] / "images" / pngs[-1].name.replace("frame_", "reference_")
        ref_html = ""
        if ref.exists():
            shutil.copyfile(ref, folder / f"{name}-reference.png")
            ref_html = f"<img src='frames/{name}-reference.png' title='reference'>"
        s = run["summary"]
        cells.append(f"<figure><img src='frames/{name}.png'>{ref_html}<figcaption>{html.escape(s['method'])}"
                     f"/{html.escape(s['variant'])} {html.escape(str(s['net']))} — {pngs[-1].stem}"
                     f"</figcaption></figure>")
    return "".join(cells) or "<p>No saved frames.</p>"


_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>splitbench report</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1200px; }}
table.t {{ border-collapse: collapse; font-size: 0.85em; }}
table.t td, table.t th {{ padding: 2px 8px; border-bottom: 1px solid #ddd; text-align: right; }}
figure {{ display: inline-block; margin: 0.5em; }} figure img {{ image-rendering: pixelated; width: 320px; }}
</style></head><body>
{body}
</body></html>
"""
