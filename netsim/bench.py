"""Speed benchmark: CPU time to simulate an 8 MB TCP transfer, without loss and at 1 % loss.

Targets (issue 4): <= 20 ms of CPU without loss, <= 100 ms at 1 % loss. CPU time is ``time.process_time``; each
figure is the median of several repeats with different seeds. Run: ``python -m netsim.bench``.
"""

from __future__ import annotations

import statistics
import time

import netsim

TRANSFER_BYTES = 8 * 1024 * 1024
# A 100 Mbit/s, 20 ms RTT path: enough segments in flight that the window logic is exercised.
BASE_SPEC = "bw=100mbps,rtt=20ms"


def _cpu_ms(spec: str, seed: int) -> tuple[float, float]:
    net = netsim.make_network(spec, seed=seed)
    start = time.process_time()
    delivery = net.send(TRANSFER_BYTES, direction="down", protocol="tcp", at_s=0.0)
    return (time.process_time() - start) * 1e3, delivery.arrival_s


def run(repeats: int = 7) -> dict:
    """{"tcp_8mb_lossless_cpu_ms": median, "tcp_8mb_loss1pct_cpu_ms": median, ...}."""
    results = {}
    for label, spec in (("lossless", BASE_SPEC), ("loss1pct", BASE_SPEC + ",loss=1%")):
        samples = [_cpu_ms(spec, seed) for seed in range(repeats)]
        results[f"tcp_8mb_{label}_cpu_ms"] = statistics.median(s[0] for s in samples)
        results[f"tcp_8mb_{label}_sim_s"] = statistics.median(s[1] for s in samples)
    results["targets_cpu_ms"] = {"lossless": 20.0, "loss1pct": 100.0}
    results["repeats"] = repeats
    return results


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
