"""The report: reads stored results only (never runs anything) → CSV tables + PNG plots → report/index.html.

Sections, in order: the answer (per network profile, the best method under a frame-time or bandwidth budget,
from the shared ``compare`` matrix), Pareto fronts per scene and network, the references' noise floors, the
reproduction-fidelity table (every claim of every method section), method pages with images, where times were
measured, cost growth (:mod:`reports.compare`); then each method's own section (headed by the paper it
reproduces, :mod:`reports.papers`), the run matrix (one collapsible table per method, all runs in runs.csv),
frame-time breakdown, bandwidth, quality per frame, machine and versions, scenes, netsim validation. Plots that
would list every run show at most :data:`FOCUS_RUNS` (the compare matrix's first scene over TCP when present);
the CSVs hold all. Extensions:

* a method may ship ``methods/<name>/report.py`` with ``section(results_df, run_dirs) -> str`` (an HTML
  fragment), imported by :func:`suite.harness.registry.load_module`; it gets the frames of its own runs (with the
  run columns ``RUN_COLUMNS``) and their directories;
  a section that also takes the keywords ``out_dir`` (the report directory, for its own plots and CSVs, which
  it links relative to index.html) and/or ``results_root`` (to read stored documents beside the runs, such as
  benchmark output) gets them too;
* netsim's committed validation against ns-3 (``netsim/validation/validation.csv``), summarised per transport;
* every CSV under a directory listed in ``EXTRA_TABLE_DIRS`` is included as a table.

Tables, figures and files go through :mod:`suite.harness.reporting`, the helpers the method sections use too.
"""
from __future__ import annotations

import inspect
import json
from pathlib import Path

import numpy as np
import pandas as pd

from suite import fileio
from suite.harness import registry, results, verdicts
from suite.harness.reporting import (copy_file, esc, figure, label_axes, lo_hi_text, save_figure, table_html,
                                     write_csv)
from suite.harness.verdicts import format_value

REPO_DIR = Path(__file__).resolve().parent.parent
EXTRA_TABLE_DIRS: list[Path] = []
NETSIM_VALIDATION_CSV = REPO_DIR / "netsim" / "validation" / "validation.csv"
RUN_COLUMNS = ["run", "method", "variant", "mode", "scene", "backend", "resolution", "net", "protocol", "frames"]
# Plots with one bar or line per run show at most this many runs.
FOCUS_RUNS = 24


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
               "prepare_ms": s["prepare_ms"], "rays": s["rays"], "omitted": " ".join(s.get("omitted") or [])}
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
    fig, ax = figure(12, 1.5 + 0.45 * max(len(table), 4))
    left = np.zeros(len(table))
    parts = [c for c in table.columns if c != "frame_ms"]
    cmap = __import__("matplotlib").colormaps["tab20"]
    for k, col in enumerate(parts):
        name = col[len("cp_"):-len("_ms")]
        is_net = name.startswith("net_")
        label = f"network: {name[len('net_'):]}" if is_net else name
        ax.barh(table.index, table[col], left=left, label=label, color=cmap(k % 20), hatch="//" if is_net else None)
        left += table[col].to_numpy()
    label_axes(ax, "ms per frame on the critical path (client and server stages that overlap count once)", "")
    return save_figure(fig, path)


def plot_bandwidth(runs: pd.DataFrame, path: Path) -> str:
    fig, ax = figure(9, 0.5 + 0.45 * max(len(runs), 2))
    ax.barh(runs["label"], runs["bandwidth_down_mbps"], label="down")
    ax.barh(runs["label"], runs["bandwidth_up_mbps"], left=runs["bandwidth_down_mbps"], label="up")
    label_axes(ax, "Mbit/s (simulated)", "", legend="inside", fontsize=8)
    return save_figure(fig, path)


def plot_quality(frames: pd.DataFrame, path: Path) -> str:
    fig, ax = figure(12, 4)
    for label, df in frames.groupby("label"):
        df = df[df["dssim"].notna() | df["zl_dssim"].notna()]
        if df.empty:
            continue
        line, = ax.plot(df["frame"], df["dssim"], marker="o", label=f"{label} vs reference")
        if df["zl_dssim"].fillna(0).abs().sum() > 0:
            ax.plot(df["frame"], df["zl_dssim"], ls="--", color=line.get_color(), label=f"{label} vs zero-latency")
    label_axes(ax, "frame", "DSSIM (lower is better)")
    return save_figure(fig, path)


def plot_speed_vs_error(runs: pd.DataFrame, path: Path) -> str:
    fig, ax = figure(7, 5)
    for method, df in runs.groupby("method"):
        ax.scatter(df["frame_ms_mean"], df["dssim_mean"], label=method)
    label_axes(ax, "frame ms (mean)", "DSSIM vs path-traced reference (mean)", legend="inside", fontsize=8)
    return save_figure(fig, path)


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
        if not spec.has_module("report") or frames.empty or name not in set(frames["method"]):
            continue
        try:
            module = spec.load_module("report")
            run_dirs = [r["dir"] for r in loaded if r["summary"]["method"] == name]
            accepted = inspect.signature(module.section).parameters
            extra = {k: v for k, v in (("out_dir", out_dir), ("results_root", results_root))
                     if k in accepted and v is not None}
            out.append((name, module.section(frames[frames["method"] == name].copy(), run_dirs, **extra)))
        except Exception as exc:  # noqa: BLE001 - one method's section must not break the report
            out.append((name, f"<p>section failed: {esc(f'{type(exc).__name__}: {exc}')}</p>"))
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
        for label, part in (("", group), ("loss-free ", group[group["loss"] == 0]),
                            ("lossy ", group[group["loss"] > 0])):
            err = 100.0 * part["rel_error"]
            row[f"{label}median %"] = float(err.median()) if len(err) else np.nan
            row[f"{label}p90 %"] = float(err.quantile(0.9)) if len(err) else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def _grid_ranges(table: pd.DataFrame) -> str:
    """The validation grid's ranges, read from its table: sizes, bandwidths, RTTs, losses."""
    parts = []
    for col, name, scale, unit in (("size_bytes", "sizes", 1.0, "B"), ("bandwidth_mbps", "", 1.0, "Mbit/s"),
                                   ("rtt_ms", "RTT", 1.0, "ms"), ("loss", "loss", 100.0, "%")):
        if col in table and len(table[col].dropna()):
            lo, hi = scale * table[col].min(), scale * table[col].max()
            parts.append(f"{name} {format_value(lo)}–{format_value(hi, unit)}".strip())
    return ", ".join(parts)


def netsim_validation_section(out: Path, csv: Path = None) -> str:
    """The committed netsim-vs-ns-3 validation table (netsim/validation/), summarised; empty if absent."""
    csv = Path(csv or NETSIM_VALIDATION_CSV)
    try:
        table = pd.read_csv(csv)
        summary = netsim_validation_summary(table)
    except (OSError, KeyError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return ""
    write_csv(table, out / "netsim_validation.csv")
    worst = table.sort_values("rel_error", ascending=False).head(8)
    return ("<h2>Network model: netsim against ns-3</h2><p>Completion time of the same transfers in netsim and in "
            f"ns-3 ({_grid_ranges(table)}), relative error per transport. "
            "Produced by <code>splitbench netsim validate</code>; modelling differences are in docs/netsim.md. "
            f"<a href='netsim_validation.csv'>all {len(table)} points</a></p>" + table_html(summary)
            + "<p>Largest errors:</p>" + table_html(worst))


SCENES_FILE = "scenes.json"


def scenes_section(results_root: Path) -> str:
    """The scenes the sweep could use, and those that were not available on the machine (with the fix), from
    the ``scenes.json`` that ``splitbench reproduce`` stores beside the runs."""
    path = results_root / SCENES_FILE
    if not path.is_file():
        return ""
    import json

    doc = json.loads(path.read_text())
    rows = [{"scene": name, "available": not desc.startswith("unavailable"), "description": desc}
            for name, desc in sorted(doc.get("scenes", {}).items())]
    missing = [r["scene"] for r in rows if not r["available"]]
    note = (f"Not available on the machine that ran the sweep, so not measured: {esc(', '.join(missing))}."
            if missing else "Every listed scene was available.")
    return "<h2>Scenes</h2><p>" + note + "</p>" + table_html(pd.DataFrame(rows))


def core_bench_section(results_root: Path, out: Path) -> str:
    """The rendering core's cost per stage on each backend measured (``splitbench bench core``: ms, the device time
    alone for Dr.Jit backends, rays, pixels, bytes, and the ratios against the backend's raw queries with their
    goals) and the tracing interface's overhead (``splitbench bench tracing``), from the stored bench documents:
    what a GPU changes, where one was measured."""
    from suite.harness.reporting import load_bench

    core, tracing = load_bench("core", None, results_root), load_bench("tracing", None, results_root)
    parts = ["<h2 id='core'>Rendering core per backend</h2>"]
    if core is None and tracing is None:
        return parts[0] + ("<p><em>No stored core benchmarks. <code>splitbench bench core --backend all</code> and "
                           "<code>splitbench bench tracing --scene all --backend all --out results</code> store them "
                           "under <code>results/bench/</code>.</em></p>")
    for doc, name in ((core, "core"), (tracing, "tracing")):
        if doc is not None:
            host, git = doc.get("host") or {}, doc.get("git") or {}
            parts.append(f"<p>{name}: measured on {esc(host.get('node', '?'))} ({esc(host.get('platform', '?'))}, "
                         f"{esc(host.get('cpu_count', '?'))} CPUs), git {esc(str(git.get('commit', '?'))[:12])}.</p>")
    if core is not None:
        rows, ratios = [], []
        for r in core.get("results", []):
            w, h = r["resolution"]
            setting = f"{r['scene']} {w}x{h}, {r['backend']} [{r['path']}]"
            for st in r["stages"]:
                rows.append({"setting": setting, "stage": st["stage"], "ms": st["ms"],
                             "kernel_ms": st.get("kernel_ms", np.nan), "rays": st["rays"], "pixels": st["pixels"],
                             "bytes": st.get("bytes", np.nan), "note": st.get("note", "")})
            ratios.append({"setting": setting, "lights": r["lights"],
                           "G-buffer / raw intersect (goal <= 2)": r.get("gbuffer_over_raw_intersect", np.nan),
                           "G-buffer, repeats": lo_hi_text(r.get("gbuffer_over_raw_intersect_range")),
                           "G-buffer, device time alone": r.get("gbuffer_over_raw_intersect_kernels", np.nan),
                           "visibility raw / pass (goal >= 0.9)": r.get("visibility_raw_over_pass", np.nan),
                           "visibility, repeats": lo_hi_text(r.get("visibility_raw_over_pass_range")),
                           "visibility, device time alone": r.get("visibility_raw_over_pass_kernels", np.nan)})
        stages, ratio_table = pd.DataFrame(rows), pd.DataFrame(ratios)
        write_csv(stages, out / "core_stages.csv")
        parts.append("<p>One frame's stages (median ms of interleaved calls; <i>kernel_ms</i>: the execution time of "
                     "the launches a call makes, from Dr.Jit's kernel history, without the host's per-call costs; "
                     "<i>repeats</i>: the lowest and highest ratio of one repeat's two calls, which ran next to each "
                     "other). "
                     "<a href='core_stages.csv'>core_stages.csv</a></p>" + table_html(ratio_table)
                     + "<details><summary>every stage</summary>" + table_html(stages) + "</details>")
    if tracing is not None:
        rows = []
        for r in tracing.get("results", [tracing]):
            row = {"scene": r.get("scene"), "backend": r.get("backend"), "interface": r.get("interface", "numpy"),
                   "rays": r.get("rays")}
            for query in ("occluded", "intersect"):
                q = r.get(query) or {}
                row[f"{query} suite/raw (goal >= 0.9)"] = q.get("ratio", np.nan)
                row[f"{query} repeats"] = lo_hi_text(q.get("ratio_range"))
                row[f"{query} device time alone"] = q.get("kernel_ratio", np.nan)
                row[f"{query} queries per ray"] = q.get("queries_per_ray", np.nan)
            rows.append(row)
        parts.append("<p>The tracing interface against the backend's own query on the same shadow rays "
                     "(Dr.Jit: rays in device memory).</p>" + table_html(pd.DataFrame(rows)))
    return "".join(parts)


def focus_labels(runs: pd.DataFrame, record: dict | None) -> list[str]:
    """The run labels a per-run plot shows: the compare matrix's first scene over TCP when the results hold it,
    else the first :data:`FOCUS_RUNS` runs."""
    df = runs
    if record and record.get("run_dirs"):
        mine = runs[runs["run"].isin(set(record["run_dirs"]))]
        if not mine.empty:
            first = mine["scene"].iloc[0]
            df = mine[(mine["scene"] == first) & (mine["protocol"] == "tcp")]
    return list(df["label"].head(FOCUS_RUNS))


def gather_claims(out: Path) -> list:
    """Every claim the method sections stored (``<out>/<method>/claims.json``), in method order."""
    found = []
    for path in sorted(Path(out).glob("*/claims.json")):
        try:
            found += [verdicts.Claim.from_dict(d) for d in json.loads(path.read_text())]
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError):
            continue
    return found


def claims_section(claims: list, out: Path) -> str:
    """The reproduction-fidelity table: each claim's paper value, suite value, setting and verdict."""
    from reports.papers import paper_of

    if not claims:
        return ("<h2 id='claims'>Reproduction fidelity</h2><p>No method section stored claims (run the quick "
                "preset: <code>splitbench reproduce --preset quick</code>).</p>")
    table = verdicts.claims_table(claims)
    write_csv(table, out / "claims.csv")
    counts = table["verdict"].value_counts()
    summary = ", ".join(f"{n} {esc(kind)}" for kind, n in counts.items())
    rows = []
    for claim, row in zip(claims, table.to_dict("records")):
        paper = paper_of(claim.method)
        who = esc(paper.short()) if paper else esc(claim.method)
        rows.append(f"<tr><td>{who}<br><small>{esc(claim.method)} · {esc(row['id'])}</small></td>"
                    f"<td>{esc(row['statement'])}<br><small>{esc(row['source'])}</small></td>"
                    f"<td>{esc(row['paper'])}</td><td>{esc(row['suite'])}</td><td>{esc(row['setting'])}</td>"
                    f"<td class='v-{esc(row['verdict'].split()[0])}'>{esc(row['verdict'])}<br>"
                    f"<small>{esc(row['tolerance'])} {esc(row['how'])}</small></td></tr>")
    cited = sorted({c.method for c in claims if paper_of(c.method)})
    papers = "".join(f"<li><b>{esc(paper_of(m).short())}</b> ({esc(m)}): {esc(paper_of(m).cite())}</li>"
                     for m in cited)
    return ("<h2 id='claims'>Reproduction fidelity: every paper claim</h2>"
            + (f"<ul>{papers}</ul>" if papers else "") + "<p>From the claims each method section "
            f"stored (stored results only): {len(claims)} claims — {summary}. Verdict kinds: "
            f"{esc(', '.join(verdicts.KINDS))}. <a href='claims.csv'>claims.csv</a></p>"
            "<table class='t prose claims'><colgroup><col style='width:11%'><col style='width:30%'>"
            "<col style='width:8%'><col style='width:8%'><col style='width:15%'><col style='width:28%'></colgroup>"
            "<tr><th>paper</th><th>claim (source)</th><th>paper value</th><th>suite value</th>"
            "<th>setting</th><th>verdict (tolerance, how)</th></tr>" + "".join(rows) + "</table>")


def run_matrix_section(runs: pd.DataFrame) -> str:
    """The full run matrix: one collapsible table per method (all runs in runs.csv)."""
    cols = ["variant", "scene", "resolution", "net", "protocol", "frame_ms_mean", "frame_ms_p95", "latency_ms_mean",
            "bandwidth_mbps", "dssim_mean", "zl_dssim_mean", "rays", "backend"]
    parts = []
    for method, df in runs.groupby("method"):
        # what the method does not render of a scene (summary `omitted`), stated once per scene beside its runs
        left = sorted({(sc, w) for sc, w in zip(df["scene"], df.get("omitted", [""] * len(df))) if w})
        note = ("<p>Left out (the errors include it): " + "; ".join(f"{esc(sc)}: {esc(w)}" for sc, w in left)
                + ".</p>") if left else ""
        parts.append(f"<details><summary>{esc(method)}: {len(df)} runs"
                     + (f", leaving part of {len(left)} scene(s) out" if left else "") + "</summary>"
                     + note + table_html(df[[c for c in cols if c in df]]) + "</details>")
    return ("<h2 id='runs'>Run matrix</h2><p>Every complete run, per method (click to open). "
            "<a href='runs.csv'>runs.csv</a> · <a href='frames.csv'>frames.csv</a></p>" + "".join(parts))


def build(results_root, out_dir) -> Path:
    """Writes out_dir/index.html with its PNG plots and CSV tables; returns the index path."""
    from reports import compare
    from reports.papers import method_title

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs, frames, loaded = load_all(results_root)
    head = [f"<h1>splitbench report</h1><p>results: <code>{esc(str(Path(results_root).resolve()))}</code>"
            f" — {len(runs)} complete runs</p>"]
    body = []
    if runs.empty:
        head.append("<p>No complete runs yet. Run <code>splitbench reproduce --preset smoke</code>.</p>")
    else:
        record = compare.preset_record(Path(results_root))
        # Method sections run first: they store the claims the fidelity table gathers.
        fragments = method_sections(frames, loaded, out_dir=out, results_root=Path(results_root))
        cross = compare.sections(compare.run_table(loaded), loaded, Path(results_root), out)
        head.append("<nav>" + " · ".join(f"<a href='#{a}'>{t}</a>" for a, t in (
            ("answer", "answer"), ("pareto", "Pareto fronts"), ("floors", "noise floors"),
            ("claims", "paper claims"), ("pages", "method images"), ("hardware", "hardware"), ("core", "core"),
            ("growth", "growth"),
            ("methods", "method sections"), ("runs", "run matrix"))) + "</nav>")
        body += [cross["answer"], cross["pareto"], cross["floors"], claims_section(gather_claims(out), out),
                 cross["pages"], cross["hardware"], core_bench_section(Path(results_root), out), cross["growth"],
                 "<span id='methods'></span>"]
        for name, fragment in fragments:
            body.append(f"<h2>Method: {esc(method_title(name))}</h2>{fragment}")

        write_csv(runs, out / "runs.csv")
        write_csv(frames, out / "frames.csv")
        body.append(run_matrix_section(runs))
        labels = focus_labels(runs, record)
        shown = f"{len(labels)} of {len(runs)} runs shown" + (
            " (the compare matrix's first scene over TCP)" if record else "")
        focus_frames = frames[frames["label"].isin(labels)]
        focus_runs = runs[runs["label"].isin(labels)]

        table = breakdown_table(frames)
        write_csv(table, out / "breakdown.csv", index=True)
        write_csv(stage_table(frames), out / "stages.csv", index=True)
        body.append("<h2>Frame-time breakdown</h2><p>Mean ms per frame of each stage and message (hatched) on the "
                    f"critical path; a bar is the mean frame time; {shown}. <a href='breakdown.csv'>breakdown.csv</a>; "
                    "every stage, on the critical path or not: <a href='stages.csv'>stages.csv</a></p>"
                    f"<img src='{plot_breakdown(breakdown_table(focus_frames), out / 'breakdown.png')}'>")

        write_csv(runs[["label", "bandwidth_mbps", "bandwidth_down_mbps", "bandwidth_up_mbps"]], out / "bandwidth.csv")
        body.append(f"<h2>Bandwidth</h2><p>{shown}. <a href='bandwidth.csv'>bandwidth.csv</a></p>"
                    f"<img src='{plot_bandwidth(focus_runs, out / 'bandwidth.png')}'>")

        quality = frames[["label", "frame", "ssim", "dssim", "psnr_db", "flip", "zl_ssim", "zl_dssim"]]
        quality = quality[quality["ssim"].notna() | quality["zl_ssim"].notna()]
        write_csv(quality, out / "quality.csv")
        body.append("<h2>SSIM / DSSIM per frame</h2><p>Solid: against the Mitsuba path-traced reference; dashed: "
                    f"against the method's own zero-latency run; {shown}. <a href='quality.csv'>quality.csv</a></p>"
                    f"<img src='{plot_quality(focus_frames, out / 'quality.png')}'>")

        write_csv(runs[["label", "frame_ms_mean", "dssim_mean", "bandwidth_mbps"]], out / "speed_vs_error.csv")
        body.append("<h2>Speed vs error</h2><p><a href='speed_vs_error.csv'>speed_vs_error.csv</a></p>"
                    f"<img src='{plot_speed_vs_error(runs, out / 'speed_vs_error.png')}'>")

        body.append("<h2>Frames</h2>" + _thumbnails([r for r in loaded if r["dir"].name in
                                                     set(focus_runs["run"])], out))

        machines = machine_table(loaded)
        write_csv(machines, out / "machines.csv")
        body.append("<h2>Machine and versions</h2><p><a href='machines.csv'>machines.csv</a></p>"
                    + table_html(_transposed(machines) if len(machines) <= 3 else machines))
    body.append(scenes_section(Path(results_root)))
    body.append(netsim_validation_section(out))
    for name, df in extra_tables():
        body.append(f"<h2>Table: {esc(name)}</h2>" + table_html(df))
    return fileio.write_text(out / "index.html", page_html("splitbench report", "\n".join(head + body)))


def _transposed(df: pd.DataFrame) -> pd.DataFrame:
    """A few long rows as columns (field, machine 1, machine 2, ...), so that they fit the page's width."""
    out = df.T.reset_index()
    out.columns = ["field"] + [f"machine {k + 1}" for k in range(len(df))]
    return out


def page_html(title: str, body: str) -> str:
    """A report page: ``body`` in the report's style (every table fits a 1400 px window)."""
    return _PAGE.format(title=esc(title), body=body)


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
        copy_file(pngs[-1], folder / f"{name}.png")
        ref = run["dir"] / "images" / pngs[-1].name.replace("frame_", "reference_")
        ref_html = ""
        if copy_file(ref, folder / f"{name}-reference.png"):
            ref_html = f"<img src='frames/{name}-reference.png' title='reference'>"
        s = run["summary"]
        cells.append(f"<figure><img src='frames/{name}.png'>{ref_html}<figcaption>{esc(s['method'])}"
                     f"/{esc(s['variant'])} {esc(str(s['net']))} — {pngs[-1].stem}"
                     f"</figcaption></figure>")
    return "".join(cells) or "<p>No saved frames.</p>"


_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1320px; }}
nav {{ margin: 0 0 1em; }}
img {{ max-width: 100%; }}
table.t {{ border-collapse: collapse; font-size: 0.8em; max-width: 100%; }}
table.t td, table.t th {{ padding: 2px 6px; border-bottom: 1px solid #ddd; text-align: right; }}
table.t td {{ white-space: nowrap; }} table.prose td {{ white-space: normal; }}
table.t th {{ background: #f3f3f3; }}
figure {{ display: inline-block; margin: 0.5em; }} figure img {{ image-rendering: pixelated; width: 320px; }}
table.prose td, table.prose th {{ text-align: left; vertical-align: top; }}
table.claims {{ width: 100%; table-layout: fixed; }} table.claims td {{ font-size: 0.95em; overflow-wrap: break-word; }}
table.claims small {{ color: #555; }}
td.v-reproduces {{ background: #e3f4e1; }} td.v-does {{ background: #fbe3e1; }}
table.imgs img {{ image-rendering: pixelated; width: 240px; }} table.imgs th {{ font-size: 0.8em; max-width: 240px; }}
td.na {{ color: #777; font-size: 0.8em; max-width: 240px; }}
details {{ margin: 0.4em 0; }} summary {{ cursor: pointer; }}
p.setting {{ margin: 1em 0 0.3em; padding: 2px 6px; background: #eef3f8; display: table; }}
</style></head><body>
{body}
</body></html>
"""
