"""Modelled memory transfers: the server's GPU→CPU read-back and the client's CPU→GPU upload.

Seed 000 Figure 10 times them as their own passes ("Memory Transfer (Server GPU to CPU)" 13.24 ms, "Memory
Transfer (Client CPU to GPU)" 4.14 ms, both for the 1920×1080 bitmap of 8,294,400 bytes, §4.4.3). They are not
ray tracing and this suite runs its tracing on the CPU, so they are modelled, never measured:

    transfer_ms = latency_ms + 1e3 · bytes / bandwidth_bytes_per_s

The seed's numbers imply these effective bandwidths (their Falcor staging copies and synchronisation
included, which is why they are far below the bus's nominal rate):

- GPU→CPU: 8,294,400 B / 13.24 ms = 626.5 MB/s (:data:`PAPER_GPU_TO_CPU_BYTES_PER_S`)
- CPU→GPU: 8,294,400 B / 4.14 ms = 2,003.5 MB/s (:data:`PAPER_CPU_TO_GPU_BYTES_PER_S`)

For comparison, PCIe 3.0 ×16 (the RTX 2060's bus) carries 8 GT/s × 16 lanes × 128/130 / 8 = 15,754 MB/s
per direction (:data:`PCIE3_X16_BYTES_PER_S`): an improved variant can model a tuned pinned-memory copy.
Both transfers move the raw bitmap (the GPU texture), before encoding on the server and after decoding on
the client, as in seed 000 §4.4.3 where LZO ran on the CPU.
"""
from __future__ import annotations

from suite.errors import UserError

#: Seed 000 §4.3.1 / §5.2: 1920 × 1080 × 4 bytes.
PAPER_BITMAP_BYTES = 1920 * 1080 * 4
#: Seed 000 Figure 10.
PAPER_GPU_TO_CPU_MS = 13.24
PAPER_CPU_TO_GPU_MS = 4.14

PAPER_GPU_TO_CPU_BYTES_PER_S = PAPER_BITMAP_BYTES / (PAPER_GPU_TO_CPU_MS * 1e-3)  # ≈ 626.5e6
PAPER_CPU_TO_GPU_BYTES_PER_S = PAPER_BITMAP_BYTES / (PAPER_CPU_TO_GPU_MS * 1e-3)  # ≈ 2003.5e6
PCIE3_X16_BYTES_PER_S = 8e9 * 16 * 128 / 130 / 8  # ≈ 15.754e9


def transfer_ms(nbytes: int, bandwidth_bytes_per_s: float, latency_ms: float = 0.0) -> float:
    """Modelled time of one copy of ``nbytes`` over a link of ``bandwidth_bytes_per_s`` plus a fixed latency."""
    if nbytes < 0:
        raise ValueError(f"nbytes must be >= 0, got {nbytes}")
    if not bandwidth_bytes_per_s > 0:
        raise UserError(f"memory transfer bandwidth must be > 0 bytes/s, got {bandwidth_bytes_per_s}")
    if latency_ms < 0:
        raise UserError(f"memory transfer latency must be >= 0 ms, got {latency_ms}")
    return float(latency_ms) + 1e3 * nbytes / float(bandwidth_bytes_per_s)


def bandwidth_from_mb_per_s(value_mb_per_s: float, name: str) -> float:
    """Config values are MB/s (1 MB = 1e6 bytes); returns bytes/s, refusing non-positive values."""
    try:
        value = float(value_mb_per_s)
    except (TypeError, ValueError):
        raise UserError(f"{name} must be a number of MB/s, got {value_mb_per_s!r}") from None
    if not value > 0:
        raise UserError(f"{name} must be > 0 MB/s, got {value}")
    return value * 1e6
