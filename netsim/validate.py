"""Validation against ns-3 (PyPI package ``ns3``, optional extra ``splitbench[ns3]``).

The same transfers run in netsim and in ns-3 on one point-to-point link (rate, one-way delay, packet loss on the
receiving device, drop-tail queue), and the completion times are compared:

- TCP (NewReno and CUBIC): a bulk transfer of N bytes starting at t = 1 s; completion = the sink receiving the
  last byte (ns-3 ``PacketSink`` Rx trace; netsim ``arrival_s``), handshake included on both sides.
- UDP: N bytes in 1472-byte datagrams paced at 90 % of the link rate (ns-3 ``UdpClient``); completion = last
  datagram received (netsim ``settled_s``), and the delivered bytes.

Both are configured alike: MSS 1460 (no TCP timestamps), IW 10, SACK on, no delayed ACKs, 200 ms minimum RTO,
1 s initial RTO / SYN timeout, 1 MiB receive buffer (it bounds the window: ns-3's SACK
scoreboard gets slow with thousands of segments in flight), no HyStart, 2 bytes of PPP framing, a 1000-packet drop-tail
device queue and no queue disc. Lossy points run several seeds and compare median completion times. For TCP the
ns-3 run records which segments its error model dropped (a small C++ probe on the receiving device) and netsim
loses exactly those segments (common random numbers): where a loss falls decides a short transfer's fate, so two
independent draws would mostly compare the luck of the draws. UDP points draw losses independently in each
simulator and compare completion time and delivered bytes. The table goes to ``netsim/validation/validation.csv`` and a summary to
``netsim/validation/README.md``. Run: ``splitbench netsim validate [--quick]`` or ``python -m netsim validate``.

Fairness (``validate --fairness``): a dumbbell, N bulk TCP flows from a server to N clients (or back), each client
behind its own fast access link, all crossing one shared drop-tail bottleneck (:mod:`netsim.topology` against the
same nodes and links in ns-3); per-flow completion times, the last one (the aggregate) and Jain's fairness index
over the flows' throughputs are compared. The table goes to ``netsim/validation/fairness.csv``.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import itertools
import math
import statistics
import time
from contextlib import redirect_stderr
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import netsim

VALIDATION_DIR = Path(__file__).parent / "validation"
QUEUE_PACKETS = 1000
PPP_BYTES = 2
START_S = 1.0
RECEIVE_BUFFER_BYTES = 1024 * 1024

# The grid (issue 4): sizes 1 kB-8 MB, 10 Mbit/s-1 Gbit/s, RTT 2-100 ms, loss 0-2 %.
SIZES_BYTES = (1_000, 64_000, 1_000_000, 8_000_000)
BANDWIDTHS_MBPS = (10.0, 100.0, 1000.0)
RTTS_MS = (2.0, 20.0, 100.0)
LOSSES = (0.0, 0.005, 0.02)
LOSSY_SEEDS = 10
QUICK_SIZES_BYTES = (64_000, 1_000_000)
QUICK_BANDWIDTHS_MBPS = (10.0, 100.0)
QUICK_RTTS_MS = (20.0,)
QUICK_LOSSES = (0.0, 0.02)
QUICK_SEEDS = 3


@dataclass(frozen=True)
class Case:
    transport: str  # "tcp-newreno", "tcp-cubic", "udp"
    size_bytes: int
    bandwidth_mbps: float
    rtt_ms: float
    loss: float

    @property
    def key(self) -> str:
        return (f"{self.transport} {self.size_bytes}B {self.bandwidth_mbps:g}Mbps {self.rtt_ms:g}ms "
                f"loss={self.loss:g}")


def ns3_available() -> bool:
    return importlib.util.find_spec("ns") is not None


def grid(quick: bool = False) -> list[Case]:
    sizes, rates, rtts, losses = ((QUICK_SIZES_BYTES, QUICK_BANDWIDTHS_MBPS, QUICK_RTTS_MS, QUICK_LOSSES) if quick
                                  else (SIZES_BYTES, BANDWIDTHS_MBPS, RTTS_MS, LOSSES))
    cases = []
    for transport in ("tcp-newreno", "tcp-cubic", "udp"):
        for size, rate, rtt, loss in itertools.product(sizes, rates, rtts, losses):
            if loss > 0 and size <= 1_000 and transport != "udp":
                continue  # one packet: the outcome is all-or-RTO, a coin toss rather than a model check
            if transport == "udp" and rtt != rtts[len(rtts) // 2]:
                continue  # paced UDP does not depend on the RTT: one RTT is enough
            cases.append(Case(transport, size, rate, rtt, loss))
    return cases


# -- netsim side -------------------------------------------------------------------------------------------------
def netsim_spec(case: Case) -> dict:
    spec = {"bw": case.bandwidth_mbps, "delay": case.rtt_ms / 2, "loss": case.loss,
            "queue": QUEUE_PACKETS * 1500.0, "overhead": PPP_BYTES, "handshake": True, "sack": True,
            "rwnd": float(RECEIVE_BUFFER_BYTES), "min_rto": 200.0, "initial_rto": 1000.0, "delack": False}
    if case.transport.startswith("tcp"):
        spec["cc"] = case.transport.split("-")[1]
    else:
        spec["pacing"] = 0.9 * case.bandwidth_mbps
    # Losses apply to the data direction only (ns-3's error model sits on the receiving device).
    spec["up.loss"] = 0.0
    return spec


def run_netsim(case: Case, seed: int, replay: list[tuple[int, int]] | None = None) -> tuple[float, int]:
    """One netsim run. ``replay``: ns-3's dropped packets as (sequence number, kind); the same segments are then
    lost in netsim instead of drawing losses (common random numbers)."""
    spec = netsim_spec(case)
    if replay is not None:
        spec["loss"] = 0.0
    net = netsim.make_network(spec, seed=seed)
    if replay is not None:
        _script_drops(net, replay)
    protocol = "udp" if case.transport == "udp" else "tcp"
    delivery = net.send(case.size_bytes, direction="down", protocol=protocol, at_s=START_S)
    if protocol == "udp":
        return delivery.settled_s - START_S, delivery.delivered_bytes
    return delivery.arrival_s - START_S, delivery.delivered_bytes


def _script_drops(net, replay: list[tuple[int, int]]) -> None:
    """Map ns-3 drops onto netsim: the k-th lost copy of the segment starting at byte seq - 1 (data starts at
    sequence number 1 after the SYN), and the k-th lost SYN = the k-th packet offered (SYNs go first)."""
    attempts: dict[int, int] = {}
    syn_drops = 0
    for seq, kind in replay:
        if kind == 2:
            net.links["down"].scripted_losses.add(syn_drops)
            syn_drops += 1
        elif kind == 1:
            segment = (seq - 1) // 1460
            attempt = attempts.get(segment, 0)
            attempts[segment] = attempt + 1
            net.tcp["down"].scripted_drops.add((segment, attempt))


# -- ns-3 side ---------------------------------------------------------------------------------------------------
_NS = None


# Python callbacks cannot be attached to ns-3 trace sources, so a few lines of C++ (compiled by cppyy) record the
# time of the last byte the sink received. FlowMonitor's timeLastRxPacket would include the FIN exchange that the
# bulk sender starts when it is done, one round trip after the data.
_SINK_PROBE = '''
#include "ns3/core-module.h"
#include "ns3/network-module.h"
#include "ns3/internet-module.h"
#include "ns3/point-to-point-module.h"
namespace splitbench_probe {
std::vector<long long> drop_seq;   // TCP sequence number of each packet the error model dropped
std::vector<int> drop_kind;        // 1 = data, 2 = SYN, 0 = other (pure ACK, FIN)
void on_drop(ns3::Ptr<const ns3::Packet> packet) {
    ns3::Ptr<ns3::Packet> copy = packet->Copy();
    ns3::PppHeader ppp;
    copy->RemoveHeader(ppp);
    ns3::Ipv4Header ip;
    copy->RemoveHeader(ip);
    ns3::TcpHeader tcp;
    copy->RemoveHeader(tcp);
    drop_seq.push_back((long long)tcp.GetSequenceNumber().GetValue());
    int kind = 0;
    if (tcp.GetFlags() & ns3::TcpHeader::SYN) kind = 2;
    else if (copy->GetSize() > 0) kind = 1;
    drop_kind.push_back(kind);
}
void attach_drops(ns3::Ptr<ns3::NetDevice> device) {
    drop_seq.clear();
    drop_kind.clear();
    device->TraceConnectWithoutContext("PhyRxDrop", ns3::MakeCallback(&on_drop));
}
double last_rx_s = -1.0;
unsigned long long rx_bytes = 0;
void on_rx(ns3::Ptr<const ns3::Packet> packet, const ns3::Address &) {
    last_rx_s = ns3::Simulator::Now().GetSeconds();
    rx_bytes += packet->GetSize();
}
void attach(ns3::Ptr<ns3::Application> sink) {
    last_rx_s = -1.0;
    rx_bytes = 0;
    sink->TraceConnectWithoutContext("Rx", ns3::MakeCallback(&on_rx));
}
}
'''


def _ns3_tcp_defaults(ns, cc: str, receive_buffer_bytes: int) -> None:
    """ns-3's TCP configured like netsim's defaults (both validations): MSS 1460 without timestamps, IW 10, SACK,
    no delayed ACKs, 200 ms minimum RTO, 1 s initial RTO and SYN timeout, no HyStart."""
    socket_type = "ns3::TcpNewReno" if cc == "newreno" else "ns3::TcpCubic"
    ns.Config.SetDefault("ns3::TcpL4Protocol::SocketType", ns.StringValue(socket_type))
    ns.Config.SetDefault("ns3::TcpSocket::SegmentSize", ns.UintegerValue(1460))
    ns.Config.SetDefault("ns3::TcpSocket::InitialCwnd", ns.UintegerValue(10))
    ns.Config.SetDefault("ns3::TcpSocket::DelAckCount", ns.UintegerValue(1))
    ns.Config.SetDefault("ns3::TcpSocket::SndBufSize", ns.UintegerValue(1 << 27))
    ns.Config.SetDefault("ns3::TcpSocket::RcvBufSize", ns.UintegerValue(receive_buffer_bytes))
    ns.Config.SetDefault("ns3::TcpSocket::ConnTimeout", ns.TimeValue(ns.Seconds(1.0)))
    ns.Config.SetDefault("ns3::TcpSocketBase::Timestamp", ns.BooleanValue(False))
    ns.Config.SetDefault("ns3::TcpSocketBase::Sack", ns.BooleanValue(True))
    ns.Config.SetDefault("ns3::TcpSocketBase::MinRto", ns.TimeValue(ns.MilliSeconds(200)))
    ns.Config.SetDefault("ns3::RttEstimator::InitialEstimation", ns.TimeValue(ns.Seconds(1.0)))
    ns.Config.SetDefault("ns3::TcpCubic::HyStart", ns.BooleanValue(False))


def _ns():
    global _NS
    if _NS is None:
        with redirect_stderr(io.StringIO()):
            from ns import ns  # ~10-40 s: cppyy compiles the bindings

            import cppyy

            cppyy.cppdef(_SINK_PROBE)
        _NS = ns
    return _NS


def _probe():
    import cppyy

    return cppyy.gbl.splitbench_probe


def run_ns3(case: Case, seed: int, on_started=None) -> tuple[float, int, list[tuple[int, int]]]:
    """One ns-3 run: (completion s, bytes received, TCP drops as (sequence number, kind)).
    ``on_started(sender_application)`` is called just after the sender starts (to attach extra trace probes when
    investigating a difference)."""
    ns = _ns()
    ns.RngSeedManager.SetSeed(1)
    ns.RngSeedManager.SetRun(seed + 1)
    tcp = case.transport.startswith("tcp")
    if tcp:
        _ns3_tcp_defaults(ns, "newreno" if case.transport == "tcp-newreno" else "cubic", RECEIVE_BUFFER_BYTES)
    nodes = ns.NodeContainer()
    nodes.Create(2)
    p2p = ns.PointToPointHelper()
    p2p.SetDeviceAttribute("DataRate", ns.StringValue(f"{int(case.bandwidth_mbps * 1e6)}bps"))
    p2p.SetChannelAttribute("Delay", ns.StringValue(f"{case.rtt_ms / 2 * 1000:.0f}us"))
    p2p.SetQueue("ns3::DropTailQueue", "MaxSize", ns.StringValue(f"{QUEUE_PACKETS}p"))
    devices = p2p.Install(nodes)
    ns.InternetStackHelper().Install(nodes)
    addresses = ns.Ipv4AddressHelper()
    addresses.SetBase(ns.Ipv4Address("10.1.1.0"), ns.Ipv4Mask("255.255.255.0"))
    interfaces = addresses.Assign(devices)
    ns.TrafficControlHelper().Uninstall(devices)  # no default queue disc: the device's drop-tail queue only
    if case.loss > 0:
        error_model = ns.CreateObject["RateErrorModel"]()
        error_model.SetAttribute("ErrorRate", ns.DoubleValue(case.loss))
        error_model.SetAttribute("ErrorUnit", ns.StringValue("ERROR_UNIT_PACKET"))
        devices.Get(1).SetAttribute("ReceiveErrorModel", ns.PointerValue(error_model))
    port = 9
    remote = ns.InetSocketAddress(interfaces.GetAddress(1), port).ConvertTo()
    local = ns.InetSocketAddress(ns.Ipv4Address.GetAny(), port).ConvertTo()
    if tcp:
        sender = ns.BulkSendHelper("ns3::TcpSocketFactory", remote)
        sender.SetAttribute("MaxBytes", ns.UintegerValue(case.size_bytes))
        sink = ns.PacketSinkHelper("ns3::TcpSocketFactory", local)
    else:
        payload = 1472
        count = -(-case.size_bytes // payload)
        sender = ns.UdpClientHelper(remote)
        sender.SetAttribute("MaxPackets", ns.UintegerValue(count))
        sender.SetAttribute("PacketSize", ns.UintegerValue(payload))
        # netsim paces on the IP packet (payload + 28); ns-3's interval is per packet.
        interval_s = (payload + 28) * 8 / (0.9 * case.bandwidth_mbps * 1e6)
        sender.SetAttribute("Interval", ns.TimeValue(ns.Seconds(interval_s)))
        sink = ns.PacketSinkHelper("ns3::UdpSocketFactory", local)
    sinks = sink.Install(nodes.Get(1))
    sinks.Start(ns.Seconds(0.0))
    probe = _probe()
    probe.attach(sinks.Get(0))
    if tcp:
        probe.attach_drops(devices.Get(1))
    apps = sender.Install(nodes.Get(0))
    apps.Start(ns.Seconds(START_S))
    if on_started is not None:
        ns.Simulator.Stop(ns.Seconds(START_S + 1e-6))
        ns.Simulator.Run()
        on_started(apps.Get(0))
    ns.Simulator.Stop(ns.Seconds(START_S + 600.0))
    ns.Simulator.Run()
    last_rx_s = float(probe.last_rx_s)
    received = int(ns.DynamicCast["PacketSink"](sinks.Get(0)).GetTotalRx())
    drops = [(int(seq), int(kind)) for seq, kind in zip(probe.drop_seq, probe.drop_kind)] if tcp else []
    ns.Simulator.Destroy()
    if last_rx_s < 0:
        return math.inf, received, drops
    return last_rx_s - START_S, received, drops


# -- comparison --------------------------------------------------------------------------------------------------
def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return math.nan
    position = (len(ordered) - 1) * q
    low = int(math.floor(position))
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def compare(quick: bool = False, progress=None) -> tuple[list[dict], dict]:
    rows = []
    seeds = QUICK_SEEDS if quick else LOSSY_SEEDS
    for case in grid(quick):
        runs = seeds if case.loss > 0 else 1
        started = time.perf_counter()
        ns3_results = [run_ns3(case, seed) for seed in range(runs)]
        if case.loss > 0 and case.transport != "udp":
            # TCP with losses: netsim loses the very segments ns-3 lost (common random numbers), so the comparison
            # measures the transport model, not two different draws of a heavy-tailed loss process.
            netsim_results = [run_netsim(case, seed, replay=r[2]) for seed, r in enumerate(ns3_results)]
        else:
            netsim_results = [run_netsim(case, seed) for seed in range(runs)]
        # Medians: one RTO more or less moves a lossy run by 200 ms or more; the median is robust to that.
        netsim_s = statistics.median(r[0] for r in netsim_results)
        ns3_s = statistics.median(r[0] for r in ns3_results)
        netsim_bytes = statistics.median(r[1] for r in netsim_results)
        ns3_bytes = statistics.median(r[1] for r in ns3_results)
        row = {"transport": case.transport, "size_bytes": case.size_bytes, "bandwidth_mbps": case.bandwidth_mbps,
               "rtt_ms": case.rtt_ms, "loss": case.loss, "seeds": runs,
               "netsim_s": round(netsim_s, 6), "ns3_s": round(ns3_s, 6),
               "rel_error": round(abs(netsim_s - ns3_s) / ns3_s, 4) if ns3_s > 0 else math.nan,
               "netsim_delivered_bytes": round(netsim_bytes), "ns3_delivered_bytes": round(ns3_bytes)}
        rows.append(row)
        if progress:
            progress(f"{case.key}: netsim {netsim_s * 1e3:.1f} ms, ns-3 {ns3_s * 1e3:.1f} ms, "
                     f"error {row['rel_error']:.1%} ({time.perf_counter() - started:.1f} s)")
    return rows, summarise(rows)


def summarise(rows: list[dict]) -> dict:
    summary = {}
    for transport in sorted({r["transport"] for r in rows}):
        errors = [r["rel_error"] for r in rows if r["transport"] == transport]
        lossless = [r["rel_error"] for r in rows if r["transport"] == transport and r["loss"] == 0]
        lossy = [r["rel_error"] for r in rows if r["transport"] == transport and r["loss"] > 0]
        summary[transport] = {"cases": len(errors), "median_rel_error": _percentile(errors, 0.5),
                              "p90_rel_error": _percentile(errors, 0.9),
                              "lossless_median_rel_error": _percentile(lossless, 0.5),
                              "lossless_p90_rel_error": _percentile(lossless, 0.9),
                              "lossy_median_rel_error": _percentile(lossy, 0.5),
                              "lossy_p90_rel_error": _percentile(lossy, 0.9)}
    return summary


def write_outputs(rows: list[dict], summary: dict, directory: Path = VALIDATION_DIR, ns3_version: str = "",
                  write_table: bool = True) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    if write_table:
        with open(directory / "validation.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    write_readme(directory, ns3_version=ns3_version, rows=rows, summary=summary)


_PRODUCED = {"single": r"Produced by `splitbench netsim validate` \(ns-3 ([^)]*)\)",
             "fairness": r"Produced by `splitbench netsim validate --fairness` \(ns-3 ([^)]*)\)"}


def write_readme(directory: Path = VALIDATION_DIR, ns3_version: str | None = None,
                 fairness_ns3_version: str | None = None, rows: list[dict] | None = None,
                 summary: dict | None = None) -> None:
    """netsim/validation/README.md from the committed tables: the single-link grid, then the fairness dumbbell.
    A section whose table was not just produced keeps the ns-3 version the README named for it."""
    import re

    readme = directory / "README.md"
    previous = readme.read_text() if readme.exists() else ""

    def version(kind: str, given: str | None) -> str:
        if given:
            return given
        match = re.search(_PRODUCED[kind], previous)
        return match.group(1) if match else "unknown"

    lines = []
    if rows is None and (directory / "validation.csv").exists():
        rows = read_table(directory / "validation.csv")
    if rows:
        summary = summary or summarise(rows)
        lines += ["# netsim vs ns-3", "",
                  f"Produced by `splitbench netsim validate` (ns-3 {version('single', ns3_version)}). Completion-time "
                  "relative error |netsim - ns3| / ns3 per grid point. Lossy points: median over seeds; for TCP, "
                  "netsim loses the very segments ns-3 lost in each seed (common random numbers), for UDP each "
                  "simulator draws its own losses. Goals: median <= 10 %, p90 <= 25 %, loss-free <= 5 %. Full "
                  "table: `validation.csv`; settings and known differences: docs/netsim.md.", "",
                  "| transport | cases | median | p90 | loss-free median | loss-free p90 | lossy median | lossy p90 |",
                  "|---|---|---|---|---|---|---|---|"]
        for transport, s in summary.items():
            lines.append(f"| {transport} | {s['cases']} | {s['median_rel_error']:.1%} | {s['p90_rel_error']:.1%} | "
                         f"{s['lossless_median_rel_error']:.1%} | {s['lossless_p90_rel_error']:.1%} | "
                         f"{s['lossy_median_rel_error']:.1%} | {s['lossy_p90_rel_error']:.1%} |")
        worst = sorted(rows, key=lambda r: -r["rel_error"])[:8]
        lines += ["", "Largest errors:", "",
                  "| transport | bytes | Mbit/s | RTT ms | loss | netsim s | ns-3 s | error |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in worst:
            lines.append(f"| {r['transport']} | {int(r['size_bytes'])} | {r['bandwidth_mbps']:g} | {r['rtt_ms']:g} | "
                         f"{r['loss']:g} | {r['netsim_s']:.4f} | {r['ns3_s']:.4f} | {r['rel_error']:.1%} |")
    if (directory / "fairness.csv").exists():
        fair = read_fairness_table(directory / "fairness.csv")
        fair_summary = summarise_fairness(fair)
        replicas = max(int(r["replica"]) for r in fair) + 1
        lines += ["", "## Fairness: flows sharing one bottleneck", "",
                  f"Produced by `splitbench netsim validate --fairness` (ns-3 "
                  f"{version('fairness', fairness_ns3_version)}). A dumbbell: N bulk TCP flows, one per client, "
                  f"each client behind its own {ACCESS_MBPS:g} Mbit/s, {ACCESS_DELAY_MS:g} ms access link, all "
                  f"through one shared bottleneck with a {QUEUE_PACKETS}-packet drop-tail queue, loss-free; flows "
                  f"started together or staggered over {FAIRNESS_STAGGER_S:g} s; together they need "
                  f"{FAIRNESS_TOTAL_S:g} s of the bottleneck. Each case runs {replicas} times with start times "
                  f"moved by up to {FAIRNESS_JITTER_S * 1e3:g} ms (the same in both simulators). Per flow: the "
                  "median completion time (after the flow's start) over the replicas, for a start slot when starts "
                  "are staggered and for a rank (k-th fastest) when they are simultaneous, since flows started "
                  "together are interchangeable; single run: every replica's flows compared flow i with flow i. "
                  "Aggregate: the last completion after the first start (median over replicas). Jain's index over "
                  "the flows' mean throughputs (median over replicas). Goals (as for the single link): median "
                  "<= 10 %, p90 <= 25 %. Full table: `fairness.csv`; discussion: docs/netsim.md.", "",
                  "| group | cases | flows | per-flow median | per-flow p90 | per-flow max | single-run median | "
                  "single-run p90 | aggregate median | aggregate p90 | aggregate max | min Jain netsim | "
                  "min Jain ns-3 | max Jain gap |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for label, s in fair_summary.items():
            lines.append(f"| {label} | {s['cases']} | {s['flows']} | {s['median_rel_error']:.1%} | "
                         f"{s['p90_rel_error']:.1%} | {s['max_rel_error']:.1%} | "
                         f"{s['single_run_median_rel_error']:.1%} | {s['single_run_p90_rel_error']:.1%} | "
                         f"{s['aggregate_median_rel_error']:.1%} | {s['aggregate_p90_rel_error']:.1%} | "
                         f"{s['aggregate_max_rel_error']:.1%} | {s['netsim_jain_min']:.3f} | "
                         f"{s['ns3_jain_min']:.3f} | {s['jain_max_gap']:.3f} |")
        overall = fair_summary["all"]
        over = [f"{label} (p90 {s['p90_rel_error']:.1%})" for label, s in fair_summary.items()
                if label != "all" and (s["median_rel_error"] > 0.10 or s["p90_rel_error"] > 0.25)]
        met = overall["median_rel_error"] <= 0.10 and overall["p90_rel_error"] <= 0.25
        lines += ["", f"Over all flows the per-flow goals are {'met' if met else 'not met'} (median "
                      f"{overall['median_rel_error']:.1%}, p90 {overall['p90_rel_error']:.1%}); "
                      + (f"groups above them: {', '.join(over)}. " if over else "every group meets them. ")
                      + f"Single runs compared flow by flow: median {overall['single_run_median_rel_error']:.1%}, "
                        f"p90 {overall['single_run_p90_rel_error']:.1%}."]
        lines += ["", "Per case (medians over the replicas):", "",
                  "| cc | flows | direction | Mbit/s | RTT ms | start | aggregate netsim s | aggregate ns-3 s | "
                  "error | Jain netsim | Jain ns-3 | per-flow median error | per-flow max error |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for c in fairness_cases(fair):
            lines.append(f"| {c['cc']} | {c['flows']} | {c['direction']} | {c['bottleneck_mbps']:g} | "
                         f"{c['rtt_ms']:g} | {c['start']} | {c['netsim_aggregate_s']:.3f} | "
                         f"{c['ns3_aggregate_s']:.3f} | {c['aggregate_error']:.1%} | {c['netsim_jain']:.3f} | "
                         f"{c['ns3_jain']:.3f} | {_percentile(c['flow_errors'], 0.5):.1%} | "
                         f"{max(c['flow_errors']):.1%} |")
    readme.write_text("\n".join(lines) + "\n")


def read_table(path: Path = VALIDATION_DIR / "validation.csv") -> list[dict]:
    """The committed table, with numbers parsed (to re-summarise without re-running ns-3)."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        for key, value in row.items():
            if key != "transport":
                row[key] = float(value)
    return rows


# -- fairness: N flows through one shared bottleneck (a dumbbell) -------------------------------------------------
ACCESS_MBPS = 1000.0
ACCESS_DELAY_MS = 1.0
# As for the single link: 1 MiB (718 segments). It caps a flow that runs alone at 100 Mbit/s, 50 ms (BDP 417
# packets) below the 1000-packet queue; with two flows or more the queue overflows and congestion control decides.
# Larger buffers make ns-3's SACK scoreboard very slow (an 8-flow CUBIC case took ~8 min with 4 MiB).
FAIRNESS_RECEIVE_BUFFER_BYTES = RECEIVE_BUFFER_BYTES
FAIRNESS_TOTAL_S = 6.0   # each case moves about this many seconds of bottleneck capacity
FAIRNESS_STAGGER_S = 4.0  # staggered starts spread over this long: flow i starts at i * 4 s / N
# Which of several flows a drop-tail queue happens to favour is chaotic: it turns on the order of packets that
# arrive within microseconds of each other, and each simulator breaks exact ties its own way. So each case runs as
# several replicas whose start times are moved by up to 1 ms (the same offsets in both simulators: common random
# numbers), and the comparison is of medians over the replicas, as the lossy single-link points use seeds.
FAIRNESS_REPLICAS = 5
FAIRNESS_JITTER_S = 1e-3


@dataclass(frozen=True)
class FairnessCase:
    cc: str               # "newreno", "cubic"
    flows: int
    bottleneck_mbps: float
    rtt_ms: float
    start: str            # "simultaneous", "staggered"
    direction: str = "down"

    @property
    def key(self) -> str:
        return (f"tcp-{self.cc} {self.flows} flows {self.direction} {self.bottleneck_mbps:g}Mbps {self.rtt_ms:g}ms "
                f"{self.start}")

    @property
    def size_bytes(self) -> int:
        """Per flow: together the flows need FAIRNESS_TOTAL_S of the bottleneck."""
        return int(self.bottleneck_mbps * 1e6 / 8 * FAIRNESS_TOTAL_S / self.flows)

    @property
    def starts_s(self) -> list[float]:
        step = FAIRNESS_STAGGER_S / self.flows if self.start == "staggered" else 0.0
        return [START_S + i * step for i in range(self.flows)]

    def replica_starts_s(self, replica: int) -> list[float]:
        """The start times of one replica: each flow's nominal start plus up to FAIRNESS_JITTER_S, drawn from a
        generator seeded by the replica number (whole microseconds, which ns-3 represents exactly)."""
        rng = np.random.default_rng([replica, self.flows])
        offsets_us = rng.integers(0, int(FAIRNESS_JITTER_S * 1e6) + 1, self.flows)
        return [start + int(us) * 1e-6 for start, us in zip(self.starts_s, offsets_us)]

    @property
    def bottleneck_delay_ms(self) -> float:
        # The round trip is both access links' delays (client and server side are one hop: the access link) plus
        # the bottleneck's, both ways.
        return self.rtt_ms / 2 - ACCESS_DELAY_MS


def fairness_grid(quick: bool = False) -> list[FairnessCase]:
    if quick:
        return [FairnessCase("newreno", 2, 50.0, 20.0, "staggered"), FairnessCase("cubic", 8, 100.0, 20.0, "simultaneous")]
    cases = [FairnessCase(cc, n, rate, rtt, start)
             for cc in ("newreno", "cubic") for n in (2, 8) for rate in (50.0, 100.0) for rtt in (20.0, 50.0)
             for start in ("simultaneous", "staggered")]
    # The up direction (clients to the server): flows merge into the shared link from N access links.
    cases += [FairnessCase(cc, 8, 100.0, rtt, start, "up")
              for cc in ("newreno", "cubic") for rtt in (20.0, 50.0) for start in ("simultaneous", "staggered")]
    return cases


def fairness_specs(case: FairnessCase) -> tuple[dict, dict]:
    """The netsim topology's access and server specs for a case (settings matched to ns-3 as above)."""
    access = {"bw": ACCESS_MBPS, "delay": ACCESS_DELAY_MS, "queue": QUEUE_PACKETS * 1500.0, "overhead": PPP_BYTES,
              "cc": case.cc, "handshake": True, "sack": True, "rwnd": float(FAIRNESS_RECEIVE_BUFFER_BYTES),
              "min_rto": 200.0, "initial_rto": 1000.0, "delack": False}
    server = {"bw": case.bottleneck_mbps, "delay": case.bottleneck_delay_ms, "queue": QUEUE_PACKETS * 1500.0,
              "overhead": PPP_BYTES}
    return access, server


def run_fairness_netsim(case: FairnessCase, starts_s: list[float] | None = None) -> list[float]:
    """Each flow's completion time (s after its own start) in a netsim topology."""
    starts_s = case.starts_s if starts_s is None else starts_s
    access, server = fairness_specs(case)
    topo = netsim.make_topology(access=access, server=server, clients=case.flows, seed=0)
    deliveries = [topo.send(case.size_bytes, client=i, direction=case.direction, protocol="tcp", at_s=start)
                  for i, start in enumerate(starts_s)]
    return [d.arrival_s - start for d, start in zip(deliveries, starts_s)]


_DUMBBELL_PROBE = """
#include "ns3/core-module.h"
#include "ns3/network-module.h"
namespace splitbench_dumbbell {
std::vector<double> last_rx;            // per flow: time of the last byte its sink received
std::vector<unsigned long long> rx_bytes;
void on_rx(int flow, ns3::Ptr<const ns3::Packet> packet, const ns3::Address &) {
    last_rx[flow] = ns3::Simulator::Now().GetSeconds();
    rx_bytes[flow] += packet->GetSize();
}
void reset(int flows) {
    last_rx.assign(flows, -1.0);
    rx_bytes.assign(flows, 0);
}
void attach(ns3::Ptr<ns3::Application> sink, int flow) {
    sink->TraceConnectWithoutContext("Rx", ns3::MakeBoundCallback(&on_rx, flow));
}
}
"""
_DUMBBELL_READY = False


def run_fairness_ns3(case: FairnessCase, starts_s: list[float] | None = None) -> list[float]:
    """The same dumbbell in ns-3: a server node, a router, N client nodes. The bottleneck is the server-router
    link (its drop-tail device queue, 1000 packets, on the sending side: the server's device down, the router's
    up); each client hangs off the router on its own 1 Gbit/s access link. Every device has a 1000-packet drop-tail
    queue and no queue disc; routing is ns-3's global routing."""
    global _DUMBBELL_READY
    starts_s = case.starts_s if starts_s is None else starts_s
    ns = _ns()
    import cppyy

    if not _DUMBBELL_READY:
        with redirect_stderr(io.StringIO()):
            cppyy.cppdef(_DUMBBELL_PROBE)
        _DUMBBELL_READY = True
    probe = cppyy.gbl.splitbench_dumbbell
    ns.RngSeedManager.SetSeed(1)
    ns.RngSeedManager.SetRun(1)
    _ns3_tcp_defaults(ns, case.cc, FAIRNESS_RECEIVE_BUFFER_BYTES)
    n = case.flows
    server = ns.NodeContainer()
    server.Create(1)
    router = ns.NodeContainer()
    router.Create(1)
    clients = ns.NodeContainer()
    clients.Create(n)
    stack = ns.InternetStackHelper()
    stack.Install(server)
    stack.Install(router)
    stack.Install(clients)
    addresses = ns.Ipv4AddressHelper()

    def link(a, b, rate_mbps: float, delay_ms: float, subnet: str):
        p2p = ns.PointToPointHelper()
        p2p.SetDeviceAttribute("DataRate", ns.StringValue(f"{int(rate_mbps * 1e6)}bps"))
        p2p.SetChannelAttribute("Delay", ns.StringValue(f"{delay_ms * 1000:.0f}us"))
        p2p.SetQueue("ns3::DropTailQueue", "MaxSize", ns.StringValue(f"{QUEUE_PACKETS}p"))
        devices = p2p.Install(a, b)
        addresses.SetBase(ns.Ipv4Address(subnet), ns.Ipv4Mask("255.255.255.0"))
        interfaces = addresses.Assign(devices)
        ns.TrafficControlHelper().Uninstall(devices)
        return interfaces

    link(server.Get(0), router.Get(0), case.bottleneck_mbps, case.bottleneck_delay_ms, "10.0.0.0")
    client_addresses = []
    for i in range(n):
        interfaces = link(router.Get(0), clients.Get(i), ACCESS_MBPS, ACCESS_DELAY_MS, f"10.1.{i}.0")
        client_addresses.append(interfaces.GetAddress(1))
    server_address = ns.Ipv4Address("10.0.0.1")
    ns.Ipv4GlobalRoutingHelper.PopulateRoutingTables()
    probe.reset(n)
    keep = []
    for i, start_s in enumerate(starts_s):
        port = 9 + i
        if case.direction == "down":
            sender_node, sink_node, destination = server.Get(0), clients.Get(i), client_addresses[i]
        else:
            sender_node, sink_node, destination = clients.Get(i), server.Get(0), server_address
        remote = ns.InetSocketAddress(destination, port).ConvertTo()
        local = ns.InetSocketAddress(ns.Ipv4Address.GetAny(), port).ConvertTo()
        sender = ns.BulkSendHelper("ns3::TcpSocketFactory", remote)
        sender.SetAttribute("MaxBytes", ns.UintegerValue(case.size_bytes))
        sinks = ns.PacketSinkHelper("ns3::TcpSocketFactory", local).Install(sink_node)
        sinks.Start(ns.Seconds(0.0))
        probe.attach(sinks.Get(0), i)
        apps = sender.Install(sender_node)
        apps.Start(ns.MicroSeconds(round(start_s * 1e6)))
        keep += [sender, sinks, apps]
    ns.Simulator.Stop(ns.Seconds(START_S + 600.0))
    ns.Simulator.Run()
    last_rx = [float(probe.last_rx[i]) for i in range(n)]
    received = [int(probe.rx_bytes[i]) for i in range(n)]
    ns.Simulator.Destroy()
    return [(t - start if t >= 0 and got >= case.size_bytes else math.inf)
            for t, start, got in zip(last_rx, starts_s, received)]


def jain_index(values: list[float]) -> float:
    """Jain's fairness index (sum x)^2 / (n sum x^2): 1 when all equal, 1/n when one takes everything."""
    return sum(values) ** 2 / (len(values) * sum(v * v for v in values))


def compare_fairness(quick: bool = False, progress=None) -> tuple[list[dict], dict]:
    """One row per (case, replica, flow): its start and completion time in both simulators. Everything else
    (medians, aggregates, Jain's index) is derived from these rows by :func:`summarise_fairness`."""
    rows = []
    replicas = 2 if quick else FAIRNESS_REPLICAS
    for case in fairness_grid(quick):
        started = time.perf_counter()
        for replica in range(replicas):
            starts_s = case.replica_starts_s(replica)
            ns3_s = run_fairness_ns3(case, starts_s)
            netsim_s = run_fairness_netsim(case, starts_s)
            for flow, (a, b) in enumerate(zip(netsim_s, ns3_s)):
                rows.append({"cc": case.cc, "flows": case.flows, "direction": case.direction,
                             "bottleneck_mbps": case.bottleneck_mbps, "rtt_ms": case.rtt_ms, "start": case.start,
                             "replica": replica, "flow": flow, "start_s": round(starts_s[flow] - START_S, 6),
                             "size_bytes": case.size_bytes, "netsim_s": round(a, 6), "ns3_s": round(b, 6)})
        if progress:
            c = fairness_cases(rows)[-1]
            progress(f"{case.key}: aggregate netsim {c['netsim_aggregate_s']:.3f} s, ns-3 "
                     f"{c['ns3_aggregate_s']:.3f} s; Jain netsim {c['netsim_jain']:.3f}, ns-3 {c['ns3_jain']:.3f}; "
                     f"flow errors median {_percentile(c['flow_errors'], 0.5):.1%}, max {max(c['flow_errors']):.1%} "
                     f"({time.perf_counter() - started:.1f} s)")
    return rows, summarise_fairness(rows)


def fairness_cases(rows: list[dict]) -> list[dict]:
    """Per case, medians over its replicas.

    flow_errors: per flow, the error of the median completion time; a flow is its start slot when starts are
    staggered, and its rank (k-th fastest) when they are simultaneous, since flows started together are
    interchangeable. single_run_errors: every replica's flows compared one by one, flow i with flow i (what one
    run of each simulator would show). Aggregate: the last completion after the first start. Jain's index over the
    flows' mean throughputs (size / completion time)."""
    grouped: dict = {}
    for r in rows:
        key = (r["cc"], int(r["flows"]), r["direction"], float(r["bottleneck_mbps"]), float(r["rtt_ms"]), r["start"])
        grouped.setdefault(key, {}).setdefault(int(r["replica"]), []).append(r)
    cases = []
    for (cc, flows, direction, rate, rtt, start), replicas in grouped.items():
        per_replica = [sorted(flow_rows, key=lambda r: int(r["flow"])) for _, flow_rows in sorted(replicas.items())]
        netsim_runs = [[float(r["netsim_s"]) for r in run] for run in per_replica]
        ns3_runs = [[float(r["ns3_s"]) for r in run] for run in per_replica]
        if start == "simultaneous":
            netsim_slots = [sorted(run) for run in netsim_runs]
            ns3_slots = [sorted(run) for run in ns3_runs]
        else:
            netsim_slots, ns3_slots = netsim_runs, ns3_runs
        netsim_median = [statistics.median(run[k] for run in netsim_slots) for k in range(flows)]
        ns3_median = [statistics.median(run[k] for run in ns3_slots) for k in range(flows)]
        single = [abs(a - b) / b for na, nb in zip(netsim_runs, ns3_runs) for a, b in zip(na, nb)]

        def aggregate(run, flow_rows):
            return max(t + float(r["start_s"]) for t, r in zip(run, flow_rows)) - min(
                float(r["start_s"]) for r in flow_rows)

        size = float(per_replica[0][0]["size_bytes"])
        netsim_aggregate = statistics.median(aggregate(a, fr) for a, fr in zip(netsim_runs, per_replica))
        ns3_aggregate = statistics.median(aggregate(b, fr) for b, fr in zip(ns3_runs, per_replica))
        cases.append({"cc": cc, "flows": flows, "direction": direction, "bottleneck_mbps": rate, "rtt_ms": rtt,
                      "start": start, "replicas": len(per_replica),
                      "netsim_median_s": netsim_median, "ns3_median_s": ns3_median,
                      "flow_errors": [abs(a - b) / b for a, b in zip(netsim_median, ns3_median)],
                      "single_run_errors": single,
                      "netsim_aggregate_s": netsim_aggregate, "ns3_aggregate_s": ns3_aggregate,
                      "aggregate_error": abs(netsim_aggregate - ns3_aggregate) / ns3_aggregate,
                      "netsim_jain": statistics.median(jain_index([size / t for t in run]) for run in netsim_runs),
                      "ns3_jain": statistics.median(jain_index([size / t for t in run]) for run in ns3_runs)})
    return cases


def summarise_fairness(rows: list[dict]) -> dict:
    """Per congestion control, flow count and direction, and over all: median and p90 of the per-flow errors (of
    medians over replicas), the same for single runs compared flow by flow, the aggregate's errors, and the
    smallest Jain index of each simulator with the largest gap between them."""
    summary = {}
    cases = fairness_cases(rows)
    groups = sorted({(c["cc"], c["flows"], c["direction"]) for c in cases})
    for group in groups + [None]:
        selected = [c for c in cases if group is None or (c["cc"], c["flows"], c["direction"]) == group]
        errors = [e for c in selected for e in c["flow_errors"]]
        single = [e for c in selected for e in c["single_run_errors"]]
        aggregate = [c["aggregate_error"] for c in selected]
        label = "all" if group is None else f"tcp-{group[0]} {group[1]} flows {group[2]}"
        summary[label] = {"cases": len(selected), "flows": len(errors),
                          "median_rel_error": _percentile(errors, 0.5), "p90_rel_error": _percentile(errors, 0.9),
                          "max_rel_error": max(errors),
                          "single_run_median_rel_error": _percentile(single, 0.5),
                          "single_run_p90_rel_error": _percentile(single, 0.9),
                          "aggregate_median_rel_error": _percentile(aggregate, 0.5),
                          "aggregate_p90_rel_error": _percentile(aggregate, 0.9),
                          "aggregate_max_rel_error": max(aggregate),
                          "netsim_jain_min": min(c["netsim_jain"] for c in selected),
                          "ns3_jain_min": min(c["ns3_jain"] for c in selected),
                          "jain_max_gap": max(abs(c["netsim_jain"] - c["ns3_jain"]) for c in selected)}
    return summary


def write_fairness_outputs(rows: list[dict], directory: Path = VALIDATION_DIR, ns3_version: str = "") -> None:
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / "fairness.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    write_readme(directory, fairness_ns3_version=ns3_version)


def read_fairness_table(path: Path = VALIDATION_DIR / "fairness.csv") -> list[dict]:
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        for key, value in row.items():
            if key not in ("cc", "start", "direction"):
                row[key] = float(value)
            if key in ("flows", "replica", "flow"):
                row[key] = int(float(value))
    return rows


def ns3_version() -> str:
    try:
        from importlib.metadata import version

        return version("ns3")
    except Exception:  # metadata missing: report without a version
        return "unknown"
