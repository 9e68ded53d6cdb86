"""The metric registry: every number the cross-method report can rank or plot, in the style of ann-benchmarks'
``metrics.py`` (a name, a function over one stored run, which direction is better, a description and a unit).

A metric's function takes one run's ``summary.json`` document (:func:`suite.harness.results.load_run`) and returns
a float (NaN when the run has no such value: a run without references has no reference error). Any two metrics
give a Pareto front (:func:`pareto_front`): the runs that no other run beats on both at once. The report plots
fronts per scene and network profile and answers "which method is best under a budget" from them
(:func:`best_under_budget`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

HIGHER, LOWER = "higher", "lower"


@dataclass(frozen=True)
class Metric:
    """One registered metric. ``function(summary) -> float``; ``better`` is :data:`HIGHER` or :data:`LOWER`;
    ``kind`` groups metrics in the report: ``quality``, ``time``, ``network`` or ``work`` (hardware-independent
    counts); a ``time`` metric is measured wall time on the run's backend and device, or simulated."""

    name: str
    function: Callable[[dict], float]
    better: str
    description: str
    unit: str = ""
    kind: str = "quality"

    def __post_init__(self):
        if self.better not in (HIGHER, LOWER):
            raise ValueError(f"metric '{self.name}': better must be '{HIGHER}' or '{LOWER}', not {self.better!r}")

    def __call__(self, summary: dict) -> float:
        try:
            value = self.function(summary)
        except (KeyError, TypeError, ZeroDivisionError):
            return math.nan
        return math.nan if value is None else float(value)

    def label(self) -> str:
        """Axis label: description, unit and direction."""
        unit = f" [{self.unit}]" if self.unit else ""
        return f"{self.description}{unit} ({self.better} is better)"

    def sign(self) -> float:
        """+1 when lower is better, -1 when higher is: ``sign() * value`` is a cost to minimise."""
        return 1.0 if self.better == LOWER else -1.0


METRICS: dict[str, Metric] = {}


def register(metric: Metric) -> Metric:
    """Adds ``metric`` (a name may be registered once)."""
    if metric.name in METRICS:
        raise ValueError(f"metric '{metric.name}' is already registered")
    METRICS[metric.name] = metric
    return metric


def get(name: str) -> Metric:
    from suite.errors import UserError

    if name not in METRICS:
        raise UserError(f"unknown metric '{name}' (choose from {', '.join(METRICS)})")
    return METRICS[name]


def evaluate(summary: dict) -> dict[str, float]:
    """Every registered metric of one run."""
    return {name: metric(summary) for name, metric in METRICS.items()}


def _stat(column: str, key: str = "mean") -> Callable[[dict], float]:
    return lambda s: s["stats"][column][key]


def _own(prefix: str, metric: str) -> Callable[[dict], float]:
    """The metric against the reference of the run's own light transport (global → path, direct → direct)."""
    def value(s):
        own = "" if s.get("light_transport", "direct") == "global" else "direct_"
        return s["stats"][f"{own}{prefix}{metric}"]["mean"]
    return value


def _per_frame(key: str) -> Callable[[dict], float]:
    return lambda s: s[key] / s["frames"] / s.get("clients", 1)


for _metric in (
    # Quality: the primary error is the noise-corrected relative MSE (docs/metrics.md).
    Metric("error", _own("", "rel_mse"), LOWER, "rel. MSE vs the reference of the method's own light transport, "
           "noise-corrected"),
    Metric("error_global", _stat("rel_mse"), LOWER, "rel. MSE vs full-GI (path) reference, noise-corrected"),
    Metric("error_direct", _stat("direct_rel_mse"), LOWER, "rel. MSE vs direct-lighting reference, noise-corrected"),
    Metric("error_zero_latency", _stat("zl_rel_mse"), LOWER, "rel. MSE vs the method's own zero-latency run"),
    Metric("error_floor", _own("floor_", "rel_mse"), LOWER, "noise floor of the error (two reference seeds)"),
    # The floor of the full-GI error, as a magnitude: the larger of |mean| and |p95| over the poses (the
    # corrected floor scatters around 0 with either sign).
    Metric("error_global_floor", lambda s: max(abs(s["stats"]["floor_rel_mse"]["mean"]),
                                               abs(s["stats"]["floor_rel_mse"]["p95"])), LOWER,
           "noise floor of the full-GI error (two reference seeds)"),
    Metric("dssim", _own("", "dssim"), LOWER, "DSSIM vs own-transport reference"),
    Metric("dssim_global", _stat("dssim"), LOWER, "DSSIM vs full-GI (path) reference"),
    Metric("dssim_direct", _stat("direct_dssim"), LOWER, "DSSIM vs direct-lighting reference"),
    Metric("dssim_zero_latency", _stat("zl_dssim"), LOWER, "DSSIM vs own zero-latency run"),
    Metric("dssim_floor", _own("floor_", "dssim"), LOWER, "DSSIM noise floor of the own-transport reference"),
    Metric("ssim", _own("", "ssim"), HIGHER, "SSIM vs own-transport reference"),
    Metric("psnr_db", _own("", "psnr_db"), HIGHER, "PSNR vs own-transport reference", "dB"),
    Metric("psnr_zero_latency_db", _stat("zl_psnr_db"), HIGHER, "PSNR vs own zero-latency run", "dB"),
    Metric("flip", _own("", "flip"), LOWER, "FLIP vs own-transport reference"),
    Metric("flip_floor", _own("floor_", "flip"), LOWER, "FLIP noise floor of the own-transport reference"),
    Metric("flip_zero_latency", _stat("zl_flip"), LOWER, "FLIP vs own zero-latency run"),
    # Time on the simulated clock (stage durations measured on the run's backend and device, network simulated).
    Metric("frame_ms_p50", _stat("frame_ms", "p50"), LOWER, "client frame time p50", "ms", "time"),
    Metric("frame_ms_p95", _stat("frame_ms", "p95"), LOWER, "client frame time p95", "ms", "time"),
    Metric("latency_ms_p50", _stat("latency_ms", "p50"), LOWER, "input-to-display latency p50", "ms", "time"),
    Metric("latency_ms_p95", _stat("latency_ms", "p95"), LOWER, "input-to-display latency p95", "ms", "time"),
    Metric("staleness_ms", _stat("staleness_ms"), LOWER, "staleness of the shown update (mean)", "ms", "time"),
    Metric("client_ms", _stat("client_ms"), LOWER, "client ms per frame (mean)", "ms", "time"),
    Metric("server_ms", lambda s: s.get("server_ms_per_update", s["stats"]["server_ms"]["mean"]), LOWER,
           "server ms per update (mean)", "ms", "time"),
    # Network (simulated).
    Metric("bandwidth_mbps", lambda s: s["bandwidth_mbps"], LOWER, "bandwidth down + up", "Mbit/s", "network"),
    Metric("bandwidth_down_mbps", lambda s: s["bandwidth_down_mbps"], LOWER, "bandwidth down", "Mbit/s",
           "network"),
    Metric("bandwidth_up_mbps", lambda s: s["bandwidth_up_mbps"], LOWER, "bandwidth up", "Mbit/s", "network"),
    # Hardware-independent work.
    Metric("rays_per_frame", _per_frame("rays"), LOWER, "rays traced per client frame (server + client)", "rays",
           "work"),
    Metric("bytes_per_frame", lambda s: (s["bytes_down"] + s["bytes_up"]) / s["frames"] / s.get("clients", 1),
           LOWER, "bytes sent per client frame", "bytes", "work"),
):
    register(_metric)


def pareto_front(x, y, x_better: str = LOWER, y_better: str = LOWER) -> np.ndarray:
    """Boolean mask of the points no other point dominates (at least as good on both, better on one).

    NaN points are never on the front. Equal points are all on it."""
    x = np.asarray(x, dtype=float) * (1.0 if x_better == LOWER else -1.0)
    y = np.asarray(y, dtype=float) * (1.0 if y_better == LOWER else -1.0)
    ok = np.isfinite(x) & np.isfinite(y)
    front = np.zeros(len(x), dtype=bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))
        front[i] = not dominated.any()
    return front


def pareto(df, x: str, y: str) -> np.ndarray:
    """:func:`pareto_front` of two registered metrics (columns of ``df`` named after them)."""
    return pareto_front(df[x], df[y], get(x).better, get(y).better)


def best_under_budget(df, quality: str, budget: str, limit: float):
    """The row of ``df`` with the best ``quality`` among those whose ``budget`` metric is within ``limit`` (at
    most ``limit`` when lower is better, at least when higher is); None when no row qualifies."""
    q, b = get(quality), get(budget)
    within = df[b.name] <= limit if b.better == LOWER else df[b.name] >= limit
    candidates = df[within & df[q.name].notna()]
    if candidates.empty:
        return None
    order = candidates[q.name] * q.sign()
    return candidates.loc[order.idxmin()]
