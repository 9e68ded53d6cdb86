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
        socket_type = "ns3::TcpNewReno" if case.transport == "tcp-newreno" else "ns3::TcpCubic"
        ns.Config.SetDefault("ns3::TcpL4Protocol::SocketType", ns.StringValue(socket_type))
        ns.Config.SetDefault("ns3::TcpSocket::SegmentSize", ns.UintegerValue(1460))
        ns.Config.SetDefault("ns3::TcpSocket::InitialCwnd", ns.UintegerValue(10))
        ns.Config.SetDefault("ns3::TcpSocket::DelAckCount", ns.UintegerValue(1))
        ns.Config.SetDefault("ns3::TcpSocket::SndBufSize", ns.UintegerValue(1 << 27))
        ns.Config.SetDefault("ns3::TcpSocket::RcvBufSize", ns.UintegerValue(RECEIVE_BUFFER_BYTES))
        ns.Config.SetDefault("ns3::TcpSocket::ConnTimeout", ns.TimeValue(ns.Seconds(1.0)))
        ns.Config.SetDefault("ns3::TcpSocketBase::Timestamp", ns.BooleanValue(False))
        ns.Config.SetDefault("ns3::TcpSocketBase::Sack", ns.BooleanValue(True))
        ns.Config.SetDefault("ns3::TcpSocketBase::MinRto", ns.TimeValue(ns.MilliSeconds(200)))
        ns.Config.SetDefault("ns3::RttEstimator::InitialEstimation", ns.TimeValue(ns.Seconds(1.0)))
        ns.Config.SetDefault("ns3::TcpCubic::HyStart", ns.BooleanValue(False))
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
    lines = ["# netsim vs ns-3", "",
             f"Produced by `splitbench netsim validate` (ns-3 {ns3_version}). Completion-time relative error "
             "|netsim - ns3| / ns3 per grid point. Lossy points: median over seeds; for TCP, netsim loses the very "
             "segments ns-3 lost in each seed (common random numbers), for UDP each simulator draws its own "
             "losses. Goals: median <= 10 %, p90 <= 25 %, loss-free <= 5 %. Full table: `validation.csv`; "
             "settings and known differences: docs/netsim.md.", "",
             "| transport | cases | median | p90 | loss-free median | loss-free p90 | lossy median | lossy p90 |",
             "|---|---|---|---|---|---|---|---|"]
    for transport, s in summary.items():
        lines.append(f"| {transport} | {s['cases']} | {s['median_rel_error']:.1%} | {s['p90_rel_error']:.1%} | "
                     f"{s['lossless_median_rel_error']:.1%} | {s['lossless_p90_rel_error']:.1%} | "
                     f"{s['lossy_median_rel_error']:.1%} | {s['lossy_p90_rel_error']:.1%} |")
    worst = sorted(rows, key=lambda r: -r["rel_error"])[:8]
    lines += ["", "Largest errors:", "", "| transport | bytes | Mbit/s | RTT ms | loss | netsim s | ns-3 s | error |",
              "|---|---|---|---|---|---|---|---|"]
    for r in worst:
        lines.append(f"| {r['transport']} | {int(r['size_bytes'])} | {r['bandwidth_mbps']:g} | {r['rtt_ms']:g} | "
                     f"{r['loss']:g} | {r['netsim_s']:.4f} | {r['ns3_s']:.4f} | {r['rel_error']:.1%} |")
    (directory / "README.md").write_text("\n".join(lines) + "\n")


def read_table(path: Path = VALIDATION_DIR / "validation.csv") -> list[dict]:
    """The committed table, with numbers parsed (to re-summarise without re-running ns-3)."""
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        for key, value in row.items():
            if key != "transport":
                row[key] = float(value)
    return rows


def ns3_version() -> str:
    try:
        from importlib.metadata import version

        return version("ns3")
    except Exception:  # metadata missing: report without a version
        return "unknown"
