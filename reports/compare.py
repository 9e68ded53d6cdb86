"""The cross-method part of the report: the answer per network profile, Pareto fronts, the noise floors of the
references, cost growth, and a page per method with its images. Reads stored results only.

Every run's metrics come from the metric registry (:mod:`suite.harness.metric_registry`). The runs of the shared
``compare`` matrix are the ones the stored preset record lists (``<results>/presets/compare.json``, written by
``splitbench reproduce``); a method that sends nothing (``uses_network = False``) runs once per scene on the ideal
network, and that run stands for it under every profile.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from reports.papers import method_title, paper_of
from suite.harness import metric_registry as mr
from suite.harness.reporting import SectionFiles, esc, label_axes, slug, table_html

# The quality every answer ranks by: the error against the full light transport (what a viewer would see of
# the real scene), noise-corrected (docs/metrics.md). Each method's error against its own light transport and its
# own zero-latency run are shown beside it.
ANSWER_QUALITY = "error_global"
FLOOR_METRIC = "error_global_floor"
# Budgets of the answer table: a 30 fps client (p95 frame time) and a 5 Mbit/s stream.
FRAME_BUDGET_MS = 1000.0 / 30.0
BANDWIDTH_BUDGET_MBPS = 5.0
# A winner counts only when its error is below the runner-up's by at least this many noise floors (the issue's
# rule: the floor is at most a fifth of the smallest difference a conclusion is drawn from).
FLOOR_FACTOR = 5.0
NET_ORDER = ("lan-home", "5g-edge", "wifi-40m", "wan-50m", "lte", "dsl-3m")
COMPARE_PRESETS = ("compare", "compare-full")


def preset_record(results_root: Path) -> dict | None:
    """The newest stored record of a shared-matrix preset (``compare-full`` before ``compare``)."""
    for name in reversed(COMPARE_PRESETS):
        path = Path(results_root) / "presets" / f"{name}.json"
        if path.is_file():
            try:
                return json.loads(path.read_text())
            except json.JSONDecodeError:
                continue
    return None


def device_text(config: dict) -> str:
    """Where a run's times come from: the backend and device that measured them ("embree · CPU x86_64, 2 cores
    (host)"; a GPU variant names the GPU), or the work-clock model with its constants (docs/results.md)."""
    run = config.get("config", {})
    if run.get("clock") == "work":
        return (f"work clock (modelled: {run.get('work_ns_per_ray', 50.0):g} ns/ray, "
                f"{run.get('work_ns_per_pixel', 20.0):g} ns/pixel, {run.get('work_ns_per_tap', 2.0):g} ns/tap, "
                f"{run.get('work_ns_per_point', 50.0):g} ns/point, "
                f"{run.get('work_ns_per_codec_byte', 5.0):g} ns/codec byte)")
    backend = config.get("backend", {})
    name = backend.get("name", "?")
    host = config.get("host", {})
    variant = str(backend.get("variant", ""))
    if "cuda" in name or "cuda" in variant:
        device = f"GPU {backend.get('device', backend.get('gpu', 'CUDA'))}"
    else:
        device = f"CPU {host.get('machine', '')}, {host.get('cpu_count', '?')} cores"
    return f"{name} · {device} ({host.get('node', '?')})"


def run_table(loaded: list[dict]) -> pd.DataFrame:
    """One row per run: identity columns, every registered metric, and where times were measured."""
    rows = []
    for run in loaded:
        s, cfg = run["summary"], run["config"]
        w, h = s["resolution"]
        variant = s["variant"]
        row = {"run": run["dir"].name, "method": s["method"], "variant": variant,
               "entry": s["method"] if variant == "default" else f"{s['method']}:{variant}",
               "scene": str(s["scene"]), "net": s["net"], "protocol": s["protocol"], "resolution": f"{w}x{h}",
               "pixels": w * h, "frames": s["frames"], "clients": s.get("clients", 1),
               "light_transport": s.get("light_transport", "direct"), "mode": s["mode"],
               "backend": cfg["config"]["backend"], "measured_on": device_text(cfg),
               "reference_spp": cfg["config"].get("reference_spp"),
               "omitted": " ".join(s.get("omitted") or [])}
        row.update(mr.evaluate(s))
        rows.append(row)
    return pd.DataFrame(rows)


def compare_cells(runs: pd.DataFrame, record: dict) -> pd.DataFrame:
    """The runs of the shared matrix, one row per (entry, scene, net, protocol): a local method's ideal-network
    run is repeated under every profile and protocol of its scene's cells (marked ``local``)."""
    names = set(record.get("run_dirs", []))
    df = runs[runs["run"].isin(names)].copy() if names else runs.iloc[0:0].copy()
    df["local"] = df["net"] == "ideal"
    nets_of = {}
    for cell in record.get("cells", []):
        for scene in cell["scenes"]:
            nets_of.setdefault(scene, [])
            nets_of[scene] += [(n, p) for n in cell["nets"] for p in cell["protocols"]]
    parts = [df[~df["local"]]]
    for _, row in df[df["local"]].iterrows():
        for net, protocol in dict.fromkeys(nets_of.get(row["scene"], [])):
            parts.append(pd.DataFrame([{**row.to_dict(), "net": net, "protocol": protocol}]))
    out = pd.concat(parts, ignore_index=True) if parts else df
    return out


def _net_key(net: str) -> int:
    return NET_ORDER.index(net) if net in NET_ORDER else len(NET_ORDER)


def _pick(df: pd.DataFrame, budget: str | None, limit: float | None):
    """(winner row, runner-up row or None) by ANSWER_QUALITY among rows within the budget."""
    q = mr.get(ANSWER_QUALITY)
    if budget is not None:
        b = mr.get(budget)
        df = df[df[budget] <= limit] if b.better == mr.LOWER else df[df[budget] >= limit]
    df = df[df[ANSWER_QUALITY].notna()]
    if df.empty:
        return None, None
    # One row per entry (its best protocol is a separate row; ranking is per entry).
    ranked = df.assign(_cost=df[ANSWER_QUALITY] * q.sign()).sort_values("_cost")
    ranked = ranked.drop_duplicates("entry")
    return ranked.iloc[0], (ranked.iloc[1] if len(ranked) > 1 else None)


def _cell_text(best, second, floor: float, fallback=None) -> tuple[str, float]:
    """"entry (error)" with "≈ runner-up" when the two are within FLOOR_FACTOR noise floors; and the gap. With no
    entry within the budget, ``fallback`` (the best at any cost) is named with its frame time."""
    if best is None:
        if fallback is None:
            return "none within budget", math.nan
        return (f"none within budget; best: {fallback['entry']} ({fallback[ANSWER_QUALITY]:.3g}, "
                f"p95 {fallback['frame_ms_p95']:.0f} ms)"), math.nan
    text = f"{best['entry']} ({best[ANSWER_QUALITY]:.3g})"
    gap = math.nan
    if second is not None:
        gap = float(second[ANSWER_QUALITY] - best[ANSWER_QUALITY])
        if math.isfinite(floor) and gap < FLOOR_FACTOR * abs(floor):
            text += f" ≈ {second['entry']}"
    return text, gap


BUDGETS = (("best quality", None, None),
           (f"best at ≤ {FRAME_BUDGET_MS:.1f} ms frame p95 (30 fps)", "frame_ms_p95", FRAME_BUDGET_MS),
           (f"best at ≤ {BANDWIDTH_BUDGET_MBPS:g} Mbit/s", "bandwidth_mbps", BANDWIDTH_BUDGET_MBPS))


def answer_tables(cells: pd.DataFrame) -> tuple[dict[str, pd.DataFrame], dict[str, list], pd.DataFrame]:
    """Per scene: rows = network profile and protocol, columns = the budgets of :data:`BUDGETS`; also, per scene,
    every gap between a winner and its runner-up (the differences the answer draws conclusions from), and the
    wins."""
    tables, gaps, wins = {}, {}, []
    for scene, sdf in cells.groupby("scene", sort=False):
        floor = float(sdf[FLOOR_METRIC].max()) if sdf[FLOOR_METRIC].notna().any() else math.nan
        rows = []
        keys = sorted({(n, p) for n, p in zip(sdf["net"], sdf["protocol"])}, key=lambda k: (_net_key(k[0]), k[1]))
        for net, protocol in keys:
            df = sdf[(sdf["net"] == net) & (sdf["protocol"] == protocol)]
            row = {"network": net, "protocol": protocol}
            overall, _ = _pick(df, None, None)
            for title, budget, limit in BUDGETS:
                best, second = _pick(df, budget, limit)
                row[title], gap = _cell_text(best, second, floor, overall if budget == "frame_ms_p95" else None)
                if best is not None:
                    wins.append({"entry": best["entry"], "network": net, "budget": title})
                if math.isfinite(gap):
                    gaps.setdefault(scene, []).append(gap)
            lat = df[df["latency_ms_p95"].notna()].sort_values("latency_ms_p95")
            row["lowest latency p95"] = (f"{lat.iloc[0]['entry']} ({lat.iloc[0]['latency_ms_p95']:.1f} ms)"
                                         if len(lat) else "–")
            rows.append(row)
        tables[scene] = pd.DataFrame(rows)
    return tables, gaps, pd.DataFrame(wins)


SUMMARY_COLUMNS = {"error_global": "error vs full GI", "error_direct": "error vs direct",
                   "error_zero_latency": "error vs zero-latency", "dssim": "DSSIM vs own ref.",
                   "dssim_floor": "DSSIM floor", "frame_ms_p95": "frame p95 ms", "latency_ms_p95": "latency p95 ms",
                   "bandwidth_mbps": "Mbit/s", "rays_per_frame": "rays/frame", "bytes_per_frame": "bytes/frame"}


def method_summary(cells: pd.DataFrame) -> pd.DataFrame:
    """Per scene and method: the median over its network cells of the errors against both references and its own
    zero-latency run, DSSIM with its floor, frame time, latency, bandwidth and work."""
    table = (cells.groupby(["scene", "entry", "light_transport"], as_index=False)[list(SUMMARY_COLUMNS)].median()
             .rename(columns={**SUMMARY_COLUMNS, "entry": "method", "light_transport": "transport"}))
    table["scene"] = table["scene"].map(_scene_short)
    return table.sort_values(["scene", "error vs full GI"])


def wins_table(wins: pd.DataFrame) -> pd.DataFrame:
    """How many (scene, protocol, budget) cells each entry wins on each network profile."""
    if wins.empty:
        return wins
    table = wins.groupby(["entry", "network"]).size().unstack(fill_value=0)
    table = table[sorted(table.columns, key=_net_key)]
    table.columns.name = None
    return table.reset_index().rename(columns={"entry": "method"})


def overview_answer(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """The first screen: rows = network profile / protocol; per scene, the winner within the frame-time budget
    (30 fps) and within the bandwidth budget."""
    merged = None
    for scene, t in tables.items():
        short = _scene_short(scene)
        part = t[["network", "protocol", BUDGETS[1][0], BUDGETS[2][0]]].rename(
            columns={BUDGETS[1][0]: f"{short}: ≤ {FRAME_BUDGET_MS:.0f} ms",
                     BUDGETS[2][0]: f"{short}: ≤ {BANDWIDTH_BUDGET_MBPS:g} Mbit/s"})
        merged = part if merged is None else merged.merge(part, on=["network", "protocol"], how="outer")
    if merged is None:
        return pd.DataFrame()
    merged["_k"] = merged["network"].map(_net_key)
    return merged.sort_values(["_k", "protocol"]).drop(columns="_k").fillna("not run")


def _scene_short(scene: str) -> str:
    return Path(scene).stem if "/" in scene else scene


# ----------------------------------------------------------------------------------------------------- plots

def _colors(entries) -> dict:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {e: cmap(k % 10) for k, e in enumerate(sorted(entries))}


def pareto_grid(cells: pd.DataFrame, scene: str, x: str, y: str, files: SectionFiles, name: str,
                logx: bool = True, logy: bool = True) -> str:
    """Small multiples for one scene: one panel per network profile, every entry's runs (TCP ●, UDP ▲) and the
    Pareto front of ``x`` against ``y`` (both registry metrics) over the panel's runs."""
    df = cells[(cells["scene"] == scene) & cells[x].notna() & cells[y].notna()]
    nets = sorted(df["net"].unique(), key=_net_key)
    if df.empty or not nets:
        return ""
    colors = _colors(cells["entry"].unique())
    cols = min(3, len(nets))
    rows = math.ceil(len(nets) / cols)
    from matplotlib.figure import Figure

    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullLocator

    width_in, height_in = 4.2 * cols + 2.2, 3.0 * rows + 0.6
    fig = Figure(figsize=(width_in, height_in), dpi=90)
    axes = fig.subplots(rows, cols, squeeze=False)
    # A fixed layout (tight_layout is slow on a grid): room for labels left and below, the legend on the right.
    fig.subplots_adjust(left=0.75 / width_in, right=1 - 2.3 / width_in, bottom=0.55 / height_in,
                        top=1 - 0.3 / height_in, wspace=0.3, hspace=0.45)
    for k, net in enumerate(nets):
        ax = axes[k // cols][k % cols]
        ndf = df[df["net"] == net]
        for (entry, protocol), g in ndf.groupby(["entry", "protocol"]):
            ax.scatter(g[x], g[y], color=colors[entry], marker="o" if protocol == "tcp" else "^", s=28,
                       label=entry if k == 0 and protocol == "tcp" else None)
        front = ndf[mr.pareto(ndf, x, y)].sort_values(x)
        ax.step(front[x], front[y], where="post", color="0.3", lw=1, ls="--")
        ax.set_title(net, fontsize=9)
        for values, axis, log in ((ndf[x], ax.xaxis, logx), (ndf[y], ax.yaxis, logy)):
            if _scale(ax, values, "log" if log else None, "x" if axis is ax.xaxis else "y"):
                decades = math.log10(values[values > 0].max() / values[values > 0].min())
                axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2 else (1.0,)))
                axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            else:
                axis.set_major_locator(MaxNLocator(5))
            axis.set_minor_locator(NullLocator())
        ax.tick_params(labelsize=7)
        if k % cols == 0:
            ax.set_ylabel(mr.get(y).description + (f" [{mr.get(y).unit}]" if mr.get(y).unit else ""), fontsize=7)
        if k // cols == rows - 1:
            ax.set_xlabel(mr.get(x).description + (f" [{mr.get(x).unit}]" if mr.get(x).unit else ""), fontsize=7)
    for k in range(len(nets), rows * cols):
        axes[k // cols][k % cols].set_visible(False)
    handles = [__import__("matplotlib.lines", fromlist=["Line2D"]).Line2D([], [], marker="o", ls="", color=c,
                                                                         label=e) for e, c in colors.items()]
    handles.append(__import__("matplotlib.lines", fromlist=["Line2D"]).Line2D([], [], marker="^", ls="",
                                                                              color="0.4", label="UDP (● TCP)"))
    fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(1 - 2.1 / width_in, 1 - 0.3 / height_in),
               fontsize=7, frameon=False)
    return files.plot(fig, name, tight=False)


def _scale(ax, values, scale, axis) -> bool:
    """A log axis only when the values are positive and span more than a decade (else a linear one reads
    better); returns whether the axis is logarithmic."""
    values = pd.to_numeric(values, errors="coerce").dropna()
    if scale == "log" and len(values) and (values > 0).all() and values.max() > 10 * values.min():
        (ax.set_xscale if axis == "x" else ax.set_yscale)("log")
        return True
    return False


def growth_plot(runs: pd.DataFrame, by: str, files: SectionFiles, name: str) -> tuple[str, pd.DataFrame]:
    """Cost against ``by`` (``pixels`` or ``clients``): client + server ms (measured, with where) and rays per frame
    (hardware-independent), one line per series of runs that differ only in ``by``."""
    keys = ["entry", "scene", "net", "protocol", "backend"] + (["clients"] if by == "pixels" else ["resolution"])
    series = []
    for key, g in runs.groupby(keys):
        if g[by].nunique() >= 2:
            g = g.groupby(by, as_index=False).agg({"client_ms": "mean", "server_ms": "mean", "rays_per_frame": "mean",
                                                   "bytes_per_frame": "mean", "measured_on": "first"})
            series.append((key, g))
    if not series:
        return "", pd.DataFrame()
    # the ten longest series (most points) are plotted, to stay readable; the CSV has them all
    series = sorted(series, key=lambda kg: -len(kg[1]))
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 3.6), dpi=90)
    axes = fig.subplots(1, 3)
    table = []
    for k, (key, g) in enumerate(series):
        label = f"{key[0]} {_scene_short(key[1])} {key[2]}"
        if k < 10:
            axes[0].plot(g[by], g["client_ms"].fillna(0) + g["server_ms"].fillna(0), marker="o", label=label)
            axes[1].plot(g[by], g["rays_per_frame"], marker="o")
            axes[2].plot(g[by], g["bytes_per_frame"], marker="o")
        for _, r in g.iterrows():
            busy_ms = np.nansum([r["client_ms"], r["server_ms"]])
            table.append({"series": label, by: r[by], "client + server ms": busy_ms,
                          "rays per frame": r["rays_per_frame"], "bytes per frame": r["bytes_per_frame"],
                          "measured on": r["measured_on"]})
    for ax, ylabel in zip(axes, ("client + server ms per frame (measured)", "rays per frame", "bytes per frame")):
        label_axes(ax, by, ylabel, xscale="log", yscale="log", legend=None)
    axes[0].legend(fontsize=6)
    return files.plot(fig, name), pd.DataFrame(table)


# --------------------------------------------------------------------------------------------------- floors

def floor_table(cells: pd.DataFrame, loaded: list[dict]) -> pd.DataFrame:
    """The noise floor of every reference set of the matrix: per scene and light transport, the metric between two
    independent renders of each pose (mean over the poses), with the references' spp."""
    names = set(cells["run"])
    rows = {}
    for run in loaded:
        if run["dir"].name not in names:
            continue
        s = run["summary"]
        scene = str(s["scene"])
        if scene in rows:
            continue
        stats = s["stats"]
        for transport, prefix in (("full GI (path)", "floor_"), ("direct only", "direct_floor_")):
            if f"{prefix}rel_mse" not in stats:
                continue
            rows[(scene, transport)] = {
                "scene": _scene_short(scene), "reference": transport,
                "spp": run["config"]["config"].get("reference_spp"), "poses": len(s.get("quality_frames", [])),
                "resolution": "x".join(str(v) for v in s["resolution"]),
                "floor rel. MSE (corrected)": stats[f"{prefix}rel_mse"]["mean"],
                "floor DSSIM": stats[f"{prefix}dssim"]["mean"], "floor FLIP": stats[f"{prefix}flip"]["mean"],
                "floor PSNR dB": stats[f"{prefix}psnr_db"]["mean"]}
        rows[scene] = None
    return pd.DataFrame([r for r in rows.values() if r])


# ---------------------------------------------------------------------------------------------- method pages

def _png(path: Path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def heat_map(frame_png: Path, reference_png: Path, out: Path) -> bool:
    """|frame − reference| of the display images (what the viewer sees), mean over RGB, as a magma heat map
    scaled to [0, 0.25]; returns whether it was written."""
    if not (frame_png.is_file() and reference_png.is_file()):
        return False
    import matplotlib
    from PIL import Image

    try:
        diff = np.abs(_png(frame_png) - _png(reference_png)).mean(axis=2)
    except (OSError, ValueError):  # an unreadable or mismatched PNG: no heat map, the page still builds
        return False
    rgb = matplotlib.colormaps["magma"](np.clip(diff / 0.25, 0.0, 1.0))[:, :, :3]
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((255 * rgb).astype(np.uint8)).save(out)
    return True


def method_page(name: str, runs: pd.DataFrame, loaded: list[dict], out_dir: Path, max_runs: int = 3) -> str | None:
    """``method-<name>.html``: the method's images in labelled columns (its frame, its zero-latency run, the
    reference of its own light transport, the other reference, the error heat map against its own reference),
    for the saved frames of up to ``max_runs`` compare runs (the slowest and the fastest network). Returns the
    page's file name, or None when it has no saved images."""
    mine = runs[runs["method"] == name]
    if mine.empty:
        return None
    by_dir = {r["dir"].name: r for r in loaded}
    networked = mine[mine["net"] != "ideal"]
    pick = pd.concat([networked.sort_values("net", key=lambda s: s.map(_net_key)).tail(1),
                      networked.sort_values("net", key=lambda s: s.map(_net_key)).head(1),
                      mine[mine["net"] == "ideal"].head(1)]).drop_duplicates("run").head(max_runs)
    files = SectionFiles(out_dir, f"method-{name}")
    blocks = []
    for _, row in pick.iterrows():
        run = by_dir[row["run"]]
        images = run["dir"] / "images"
        own = "reference" if row["light_transport"] == "global" else "direct_reference"
        other = "direct_reference" if own == "reference" else "reference"
        cols = [("method (networked)" if row["net"] != "ideal" else "method", "frame"),
                ("its zero-latency run", "zero_latency"),
                (f"reference: {'full GI' if own == 'reference' else 'direct only'} (own light transport)", own),
                (f"reference: {'direct only' if own == 'reference' else 'full GI'}", other)]
        trs = []
        for png in sorted(images.glob("frame_*.png")):
            idx = png.stem.split("_")[-1]
            tds = []
            for _, prefix in cols:
                target = files.copy(images / f"{prefix}_{idx}.png", f"{row['run']}-{prefix}_{idx}.png")
                tds.append(f"<td><img src='{esc(target)}'></td>" if target else
                           "<td class='na'>same as the method's frame (no network)</td>" if prefix == "zero_latency"
                           else "<td class='na'>–</td>")
            heat = files.folder / f"{row['run']}-heat_{idx}.png" if files.folder else None
            ok = heat is not None and heat_map(png, images / f"{own}_{idx}.png", heat)
            tds.append(f"<td><img src='{esc(files.name)}/{esc(heat.name)}'></td>" if ok else "<td class='na'>–</td>")
            trs.append(f"<tr><th>frame {int(idx)}</th>{''.join(tds)}</tr>")
        if not trs:
            continue
        head = "".join(f"<th>{esc(c)}</th>" for c, _ in cols) + "<th>|method − own reference| (display, 0–0.25)</th>"
        blocks.append(f"<h3>{esc(row['entry'])} · {esc(_scene_short(row['scene']))} · {esc(row['net'])}/"
                      f"{esc(row['protocol'])} · {esc(row['resolution'])}</h3><p>error vs full GI "
                      f"{row['error_global']:.3g}, vs direct {row['error_direct']:.3g}, vs zero-latency "
                      f"{row['error_zero_latency']:.3g} (rel. MSE); DSSIM vs own reference {row['dssim']:.3g}; "
                      f"times: {esc(row['measured_on'])}.</p>"
                      f"<table class='imgs'><tr><th></th>{head}</tr>{''.join(trs)}</table>")
    if not blocks:
        return None
    paper = paper_of(name)
    cite = f"<p>Reproduces: {esc(paper.cite())}</p>" if paper else "<p>A baseline (no paper).</p>"
    page = f"method-{name}.html"
    from suite import fileio
    from reports.build import page_html

    fileio.write_text(Path(out_dir) / page, page_html(f"{method_title(name)}: images",
                                                      f"<p><a href='index.html'>← report</a></p><h1>"
                                                      f"{esc(method_title(name))}</h1>{cite}" + "".join(blocks)))
    return page


# ------------------------------------------------------------------------------------------------- section

def sections(runs: pd.DataFrame, loaded: list[dict], results_root: Path, out_dir: Path) -> dict[str, str]:
    """HTML of the cross-method sections: ``answer`` (first screen), ``pareto``, ``floors``, ``growth``,
    ``hardware``, ``pages``; empty strings when the results hold no compare preset."""
    out = {k: "" for k in ("answer", "pareto", "floors", "growth", "hardware", "pages")}
    files = SectionFiles(out_dir, "compare")
    record = preset_record(results_root)
    cells = compare_cells(runs, record) if record else runs.iloc[0:0]
    if record and not cells.empty:
        tables, gaps, wins = answer_tables(cells)
        settings = record.get("settings", {})
        skipped = record.get("skipped_scenes", [])
        overview = overview_answer(tables)
        devices = ", ".join(sorted(set(cells["measured_on"])))
        intro = (f"<p>Preset <code>{esc(record['preset'])}</code>: {len(set(cells['entry']))} methods × "
                 f"{cells['scene'].nunique()} scenes × network profiles × TCP/UDP at {esc(settings.get('resolution'))}, "
                 f"{esc(settings.get('frames'))} client frames. Quality = rel. MSE against the full-GI path reference, "
                 "noise-corrected (lower is better). Methods that send nothing ran once per scene; that run stands "
                 f"under every profile. Frame times: {esc(devices)}; the network is simulated."
                 + (f" Skipped (scene not available on the machine): "
                                           f"{esc(', '.join(skipped))}." if skipped else "") + "</p>")
        left_out = sorted({(str(r["entry"]), str(r["scene"]), str(r["omitted"])) for _, r in cells.iterrows()
                           if r.get("omitted")})
        if left_out:  # what a method does not render of a scene (summary `omitted`), beside its errors
            intro += ("<p>Left out by a method (its errors include them): "
                      + "; ".join(f"{esc(e)} on {esc(_scene_short(sc))}: {esc(w)}" for e, sc, w in left_out) + ".</p>")
        detail = "".join(f"<h3>{esc(_scene_short(scene))}</h3>" + table_html(t) for scene, t in tables.items())
        wt = wins_table(wins)
        cells_csv = files.csv(cells, "compare_runs.csv")
        out["answer"] = ("<h2 id='answer'>The answer: which method, for which network</h2>" + intro +
                         f"<p>Best quality with a client frame time p95 ≤ {FRAME_BUDGET_MS:.1f} ms (30 fps) and "
                         f"with at most {BANDWIDTH_BUDGET_MBPS:g} Mbit/s, per network profile and scene (error in "
                         "brackets; at any cost and the lowest latency: below). \"A ≈ B\": A's lead over the runner-up B "
                         f"is within {FLOOR_FACTOR:g}× the error's noise floor, so no conclusion is drawn.</p>" + table_html(overview)
                         + "<h3>Each method's errors, time and bandwidth</h3><p>Median over the method's network "
                         "cells per scene. Error = noise-corrected rel. MSE against the full-GI reference, the "
                         "direct-lighting reference and the method's own zero-latency run (the error distribution "
                         "adds); \"transport\" is the light transport the method models.</p>"
                         + table_html(method_summary(cells))
                         + "<details open><summary>Every budget per scene (best quality; at 30 fps; at "
                         f"{BANDWIDTH_BUDGET_MBPS:g} Mbit/s; lowest latency)</summary>{detail}</details>"
                         + "<h3>Which method wins on which network</h3><p>Cells won (scene × protocol × budget) "
                         "per network profile.</p>" + table_html(wt)
                         + f"<p>Every cell of the matrix:{cells_csv}</p>")
        plots = []
        for scene in cells["scene"].unique():
            short = _scene_short(scene)
            for x, y, title in (("bandwidth_mbps", ANSWER_QUALITY, "error vs bandwidth"),
                                ("frame_ms_p50", ANSWER_QUALITY, "error vs client frame time"),
                                ("bandwidth_mbps", "latency_ms_p95", "latency vs bandwidth")):
                img = pareto_grid(cells, scene, x, y, files, f"pareto_{slug(short, x, y)}.png")
                if img:
                    plots.append(f"<h3>{esc(short)}: {esc(title)}</h3>{img}")
        out["pareto"] = ("<h2 id='pareto'>Pareto fronts per scene and network</h2><p>Each panel is one network "
                         "profile; dashed: the Pareto front (runs no other run beats on both axes). Any two "
                         "registered metrics can be plotted (<code>suite.harness.metric_registry</code>). Frame "
                         f"times: {esc(devices)}; bandwidth and latency on the simulated network.</p>"
                         + "".join(plots))
        floors = floor_table(cells, loaded)
        verdict = floor_check(cells, gaps)
        out["floors"] = ("<h2 id='floors'>References and their noise floors</h2><p>Two references per pose: full "
                         "global illumination (Mitsuba <code>path</code>) and direct lighting only (Mitsuba "
                         "<code>direct</code>, the transport of the direct-only methods). The floor is the metric "
                         "between two independent renders of the same pose (seeds 0 and 1): what a metric reads "
                         "when a method is as good as the reference can tell. The rel. MSE is noise-corrected with "
                         "the references' per-pixel variance, so its floor is near 0.</p>" + table_html(floors)
                         + verdict)
    pixel_img, pixel_tab = growth_plot(runs, "pixels", files, "growth_pixels.png")
    client_img, client_tab = growth_plot(runs, "clients", files, "growth_clients.png")
    out["growth"] = ("<h2 id='growth'>Cost growth with pixels and clients</h2>"
                     + (f"<h3>With pixels</h3>{pixel_img}" + files.csv(pixel_tab, "growth_pixels.csv")
                        if pixel_img else "<p>No runs that differ only in resolution.</p>")
                     + (f"<h3>With clients on one server</h3>{client_img}" + files.csv(client_tab, "growth_clients.csv")
                        if client_img else "<p>No runs with several clients on one server in these results.</p>"))
    out["hardware"] = hardware_section(runs)
    pages = [(name, method_page(name, cells if not cells.empty else runs, loaded, out_dir))
             for name in sorted(runs["method"].unique())]
    links = [f"<li><a href='{esc(p)}'>{esc(method_title(n))}</a></li>" for n, p in pages if p]
    out["pages"] = ("<h2 id='pages'>Method pages (images)</h2><ul>" + "".join(links) + "</ul>") if links else ""
    return out


def floor_check(cells: pd.DataFrame, gaps: dict) -> str:
    """Per scene: the error's noise floor against the smallest winner-to-runner-up gap of the answer (the rule:
    floor ≤ gap / FLOOR_FACTOR; cells that break it are marked ≈ in the answer)."""
    rows = []
    for scene, sdf in cells.groupby("scene", sort=False):
        floor = float(sdf[FLOOR_METRIC].max()) if sdf[FLOOR_METRIC].notna().any() else math.nan
        gap = min(gaps.get(scene, [math.nan]))
        ratio = floor / gap if gap > 0 else math.nan
        rows.append({"scene": _scene_short(scene), "noise floor of the error": floor,
                     "smallest gap between winner and runner-up": gap, "floor / gap": ratio,
                     f"floor ≤ gap / {FLOOR_FACTOR:g}": "yes" if ratio <= 1 / FLOOR_FACTOR else
                     ("no: marked ≈" if math.isfinite(ratio) else "–")})
    return ("<p>Is the floor small enough to rank methods? Per scene, the largest floor of the full-GI error "
            "(over the poses of the compared runs) against the smallest difference the answer draws a conclusion "
            "from:</p>" + table_html(pd.DataFrame(rows)))


def hardware_section(runs: pd.DataFrame) -> str:
    """Measured times per method and backend/device, with the hardware-independent work beside them; GPU
    (cuda) runs stand beside the CPU runs of the same cells."""
    if runs.empty:
        return ""
    table = (runs.groupby(["entry", "scene", "resolution", "measured_on"], as_index=False)
             .agg(runs=("run", "count"), client_ms=("client_ms", "median"), server_ms=("server_ms", "median"),
                  rays_per_frame=("rays_per_frame", "median"), bytes_per_frame=("bytes_per_frame", "median")))
    table["scene"] = table["scene"].map(_scene_short)
    gpu = runs["backend"].astype(str).str.contains("cuda").any()
    note = ("GPU (cuda) runs are listed beside the CPU runs of the same method, scene and resolution."
            if gpu else "No GPU (cuda backend) runs in these results: every time below is a CPU time.")
    return ("<h2 id='hardware'>Where times were measured</h2><p>Client and server ms are the stages' measured wall "
            "time on the named backend and device, or, for runs on the work clock, the time its model gives the "
            "counted work (median over runs); rays and bytes per frame are the hardware-independent work. "
            f"{note}</p>" + table_html(table))

