"""Mahimahi link traces: reading them and making the synthetic LTE traces bundled in ``netsim/traces/``.

Format (Mahimahi's ``mm-link``): one integer millisecond timestamp per line; each line is one opportunity to
deliver a 1500-byte packet; several lines may share a timestamp (several packets in that millisecond). The trace
repeats with a period equal to its last timestamp. Opportunities nobody uses are lost (they do not accumulate).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from netsim.errors import NetsimError

TRACE_DIR = Path(__file__).parent / "traces"
MAHIMAHI_PACKET_BYTES = 1500


def bundled_trace(name: str) -> str:
    return str(TRACE_DIR / name)


def resolve_trace(text: str) -> str:
    """A path, or the name of a bundled trace (``lte-down.mahi`` or ``lte-down``)."""
    for candidate in (Path(text), TRACE_DIR / text, TRACE_DIR / f"{text}.mahi"):
        if candidate.is_file():
            return str(candidate)
    raise NetsimError(f"trace file not found: {text} (bundled: {', '.join(p.name for p in sorted(TRACE_DIR.glob('*.mahi')))})")


def parse_mahimahi(text: str, source: str = "trace") -> np.ndarray:
    """Delivery-opportunity times in ms (sorted, float64) from Mahimahi trace text."""
    values = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            value = int(line)
        except ValueError:
            raise NetsimError(f"{source} line {line_number}: expected an integer millisecond timestamp, got {line!r}") from None
        if value < 0:
            raise NetsimError(f"{source} line {line_number}: negative timestamp {value}")
        values.append(value)
    if not values:
        raise NetsimError(f"{source}: no delivery opportunities (empty trace)")
    times_ms = np.asarray(values, dtype=np.float64)
    if np.any(np.diff(times_ms) < 0):
        raise NetsimError(f"{source}: timestamps must be non-decreasing")
    if times_ms[-1] <= 0:
        raise NetsimError(f"{source}: the last timestamp must be > 0 ms (it is the period of the loop)")
    return times_ms


def load_mahimahi(path: str) -> np.ndarray:
    try:
        text = Path(path).read_text()
    except OSError as error:
        raise NetsimError(f"cannot read trace {path}: {error.strerror}") from None
    return parse_mahimahi(text, source=str(path))


def mean_rate_mbps(times_ms: np.ndarray) -> float:
    """Average capacity of a looped trace."""
    return len(times_ms) * MAHIMAHI_PACKET_BYTES * 8 / (times_ms[-1] * 1e-3) / 1e6


class TraceCapacity:
    """Byte-serving schedule of a looped trace: the k-th 1500-byte opportunity happens at ``time_s(k)``."""

    def __init__(self, times_ms: np.ndarray):
        self.times_s = np.asarray(times_ms, dtype=np.float64) * 1e-3
        self.period_s = float(self.times_s[-1])
        self.per_period = len(self.times_s)

    def time_s(self, index: int) -> float:
        loops, offset = divmod(index, self.per_period)
        return loops * self.period_s + float(self.times_s[offset])

    def first_index_at_or_after(self, t_s: float) -> int:
        """Index of the first opportunity at time >= t_s."""
        loops = int(t_s // self.period_s) if t_s > 0 else 0
        offset = int(np.searchsorted(self.times_s, t_s - loops * self.period_s, side="left"))
        return loops * self.per_period + offset


def synthetic_lte_trace(mean_mbps: float, duration_s: float = 30.0, seed: int = 0) -> list[int]:
    """A deterministic LTE-like trace: capacity follows a Markov chain over fading states (good / fair / deep
    fade, 0.5-3 s dwell) with per-millisecond Poisson opportunities, the coarse shape of the Verizon/T-Mobile
    LTE traces shipped with Mahimahi. Written once into netsim/traces/ (no downloads)."""
    rng = np.random.default_rng(seed)
    state_scale = np.array([1.5, 0.9, 0.25])  # capacity relative to the mean in each fading state
    state_share = np.array([0.4, 0.45, 0.15])
    state_scale = state_scale / float(np.dot(state_scale, state_share))
    duration_ms = int(duration_s * 1000)
    rate_per_ms = np.empty(duration_ms)
    t = 0
    while t < duration_ms:
        state = rng.choice(3, p=state_share)
        dwell = int(rng.uniform(500, 3000))
        rate_per_ms[t:t + dwell] = mean_mbps * state_scale[state] * 1e6 / 8 / MAHIMAHI_PACKET_BYTES / 1000
        t += dwell
    counts = rng.poisson(rate_per_ms)
    lines = []
    for ms, count in enumerate(counts, start=1):
        lines.extend([ms] * int(count))
    if not lines or lines[-1] != duration_ms:
        lines.append(duration_ms)
    return lines


def write_bundled_traces() -> None:
    """Regenerate netsim/traces/lte-{down,up}.mahi (run: python -m netsim.traces)."""
    TRACE_DIR.mkdir(exist_ok=True)
    for name, mean_mbps, seed in (("lte-down.mahi", 18.0, 0), ("lte-up.mahi", 6.0, 1)):
        lines = synthetic_lte_trace(mean_mbps, seed=seed)
        (TRACE_DIR / name).write_text("\n".join(str(v) for v in lines) + "\n")


if __name__ == "__main__":
    write_bundled_traces()
    for path in sorted(TRACE_DIR.glob("*.mahi")):
        print(path.name, f"{mean_rate_mbps(load_mahimahi(str(path))):.1f} Mbit/s mean")
