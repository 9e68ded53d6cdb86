"""Network settings: one :class:`LinkConfig` per direction plus the transport options, and the parser for
profile names, inline specs (``"bw=50mbps,delay=17ms,loss=0.1%"``) and plain dicts.

Every impossible setting (zero or negative bandwidth, loss >= 1, an MTU too small for the headers, ...) raises
:class:`netsim.errors.NetsimError` with a one-line message naming the setting, so that nothing downstream can hang.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import re
from dataclasses import dataclass, field
from pathlib import Path

from netsim.errors import NetsimError

# IPv4 (20) + TCP (20) without options; the same header ns-3 puts on a segment when timestamps are off.
TCP_HEADER_BYTES = 40
# IPv4 (20) + UDP (8).
UDP_HEADER_BYTES = 28

JITTER_DISTRIBUTIONS = ("none", "uniform", "exponential", "normal")
CONGESTION_CONTROLS = ("newreno", "cubic")


@dataclass(frozen=True)
class LinkConfig:
    """One direction of the path (a single bottleneck hop).

    bandwidth_mbps: link rate in Mbit/s (``math.inf`` for the ideal link); ignored while a trace is set.
    delay_ms: one-way propagation delay.
    jitter_ms: scale of the extra per-packet delay (mean for exponential, half-width for uniform, sigma for
        normal truncated at 0). Packets keep their order unless ``reorder`` is true (a FIFO link cannot overtake).
    loss: Bernoulli drop probability per packet (0 <= loss < 1).
    ge_p / ge_r / ge_loss_bad / ge_loss_good: Gilbert-Elliott two-state loss (p = P(good->bad), r = P(bad->good),
        per packet). Active when ge_p > 0; then ``loss`` is ignored.
    mtu_bytes: largest IP packet; a TCP segment carries mtu - 40 bytes, a UDP datagram mtu - 28.
    queue_bytes: drop-tail buffer in front of the link (``math.inf`` = unlimited).
    link_overhead_bytes: extra framing per packet counted in serialisation (2 for PPP as in ns-3's point-to-point).
    trace_path: Mahimahi trace (one ms timestamp per line = one 1500-byte delivery opportunity), looped.
    """

    bandwidth_mbps: float = 100.0
    delay_ms: float = 10.0
    jitter_ms: float = 0.0
    jitter_distribution: str = "none"
    reorder: bool = False
    loss: float = 0.0
    ge_p: float = 0.0
    ge_r: float = 1.0
    ge_loss_bad: float = 1.0
    ge_loss_good: float = 0.0
    mtu_bytes: int = 1500
    queue_bytes: float = math.inf
    link_overhead_bytes: int = 0
    trace_path: str | None = None

    def validate(self, direction: str) -> "LinkConfig":
        name = f"{direction} link"
        if self.trace_path is None:
            _check(_is_number(self.bandwidth_mbps) and self.bandwidth_mbps > 0,
                   f"{name}: bandwidth must be > 0 Mbit/s, got {self.bandwidth_mbps!r}")
        else:
            _check(Path(self.trace_path).is_file(), f"{name}: trace file not found: {self.trace_path}")
        _check(_is_number(self.delay_ms) and 0 <= self.delay_ms < math.inf,
               f"{name}: delay must be a finite number >= 0 ms, got {self.delay_ms!r}")
        _check(_is_number(self.jitter_ms) and 0 <= self.jitter_ms < math.inf,
               f"{name}: jitter must be a finite number >= 0 ms, got {self.jitter_ms!r}")
        _check(self.jitter_distribution in JITTER_DISTRIBUTIONS,
               f"{name}: unknown jitter distribution {self.jitter_distribution!r} "
               f"(choose from {', '.join(JITTER_DISTRIBUTIONS)})")
        _check(_is_number(self.loss) and 0 <= self.loss < 1,
               f"{name}: loss must be in [0, 1), got {self.loss!r}")
        for key in ("ge_p", "ge_r", "ge_loss_bad", "ge_loss_good"):
            value = getattr(self, key)
            _check(_is_number(value) and 0 <= value <= 1, f"{name}: {key} must be in [0, 1], got {value!r}")
        if self.ge_p > 0:
            _check(self.ge_r > 0, f"{name}: ge_r must be > 0 or the link stays in the bad state for ever")
            _check(self.ge_loss_good < 1, f"{name}: ge_loss_good must be < 1")
            stationary_loss = self.ge_stationary_loss()
            _check(stationary_loss < 1, f"{name}: Gilbert-Elliott loss rate is 1; nothing can be delivered")
        _check(isinstance(self.mtu_bytes, int) and self.mtu_bytes > TCP_HEADER_BYTES,
               f"{name}: MTU must be an integer > {TCP_HEADER_BYTES} bytes (the IP+TCP headers), "
               f"got {self.mtu_bytes!r}")
        _check(_is_number(self.queue_bytes) and self.queue_bytes >= self.mtu_bytes,
               f"{name}: queue must hold at least one MTU ({self.mtu_bytes} bytes), got {self.queue_bytes!r}")
        _check(isinstance(self.link_overhead_bytes, int) and self.link_overhead_bytes >= 0,
               f"{name}: link overhead must be an integer >= 0 bytes")
        return self

    def ge_stationary_loss(self) -> float:
        """Long-run drop rate of the Gilbert-Elliott chain (pi_bad = p / (p + r))."""
        pi_bad = self.ge_p / (self.ge_p + self.ge_r)
        return pi_bad * self.ge_loss_bad + (1 - pi_bad) * self.ge_loss_good

    @property
    def is_ideal(self) -> bool:
        return (self.trace_path is None and math.isinf(self.bandwidth_mbps) and self.delay_ms == 0
                and self.jitter_ms == 0 and self.loss == 0 and self.ge_p == 0)


@dataclass(frozen=True)
class TcpConfig:
    """TCP sender/receiver options (defaults follow Linux where RFCs leave a choice).

    initial_window_segments: IW (RFC 6928: 10).
    min_rto_ms / initial_rto_ms / max_rto_ms: RFC 6298 timer bounds; Linux uses a 200 ms minimum.
    slow_start_restart: RFC 5681 section 4.1, cwnd back to IW after an idle period longer than one RTO.
    delayed_ack: acknowledge every second segment, or after delayed_ack_timeout_ms (RFC 1122 4.2.3.2).
    receive_window_bytes: advertised window cap on the bytes in flight.
    count_handshake: charge the SYN/SYN-ACK round trip to the first message of the session.
    sack: SACK-based loss recovery (RFC 6675, on in Linux); off = NewReno's one-hole-per-RTT recovery (RFC 6582).
    """

    congestion_control: str = "cubic"
    initial_window_segments: int = 10
    min_rto_ms: float = 200.0
    initial_rto_ms: float = 1000.0
    max_rto_ms: float = 60000.0
    slow_start_restart: bool = True
    delayed_ack: bool = False
    delayed_ack_timeout_ms: float = 40.0
    receive_window_bytes: float = 6 * 1024 * 1024
    count_handshake: bool = False
    sack: bool = True

    def validate(self) -> "TcpConfig":
        _check(self.congestion_control in CONGESTION_CONTROLS,
               f"unknown TCP congestion control {self.congestion_control!r} "
               f"(choose from {', '.join(CONGESTION_CONTROLS)})")
        _check(isinstance(self.initial_window_segments, int) and self.initial_window_segments >= 1,
               f"TCP initial window must be an integer >= 1 segment, got {self.initial_window_segments!r}")
        _check(_is_number(self.min_rto_ms) and self.min_rto_ms > 0, "TCP min_rto_ms must be > 0")
        _check(_is_number(self.initial_rto_ms) and self.initial_rto_ms > 0, "TCP initial_rto_ms must be > 0")
        _check(_is_number(self.max_rto_ms) and self.max_rto_ms >= self.min_rto_ms,
               "TCP max_rto_ms must be >= min_rto_ms")
        _check(_is_number(self.delayed_ack_timeout_ms) and self.delayed_ack_timeout_ms >= 0,
               "TCP delayed_ack_timeout_ms must be >= 0")
        _check(_is_number(self.receive_window_bytes) and self.receive_window_bytes > 0,
               f"TCP receive window must be > 0 bytes, got {self.receive_window_bytes!r}")
        return self


@dataclass(frozen=True)
class UdpConfig:
    """UDP sender options.

    pacing_mbps: send datagrams at this rate; None = at the link's own rate (its mean rate for a trace), which
        never builds a queue. burst: send all datagrams at once instead (the drop-tail queue then decides).
    nack_rounds: after the first pass the receiver reports the missing datagrams (one RTT later) and the sender
        resends them, up to this many times.
    fec_k / fec_r: block FEC, every k data datagrams followed by r parity datagrams; a block with at most r losses
        is recovered entirely (an MDS code such as Reed-Solomon). fec_r = 0 disables it.
    """

    pacing_mbps: float | None = None
    burst: bool = False
    nack_rounds: int = 0
    fec_k: int = 0
    fec_r: int = 0

    def validate(self) -> "UdpConfig":
        if self.pacing_mbps is not None:
            _check(_is_number(self.pacing_mbps) and self.pacing_mbps > 0,
                   f"UDP pacing rate must be > 0 Mbit/s, got {self.pacing_mbps!r}")
        _check(isinstance(self.nack_rounds, int) and self.nack_rounds >= 0, "UDP nack_rounds must be an integer >= 0")
        _check(isinstance(self.fec_r, int) and self.fec_r >= 0, "UDP fec_r must be an integer >= 0")
        _check(isinstance(self.fec_k, int) and self.fec_k >= 0, "UDP fec_k must be an integer >= 0")
        if self.fec_r > 0:
            _check(self.fec_k >= 1, "UDP FEC needs fec_k >= 1 data datagrams per block")
        return self


@dataclass(frozen=True)
class NetworkConfig:
    """Both directions and the transports. ``down`` = server -> client, ``up`` = client -> server."""

    name: str = "custom"
    down: LinkConfig = field(default_factory=LinkConfig)
    up: LinkConfig = field(default_factory=LinkConfig)
    tcp: TcpConfig = field(default_factory=TcpConfig)
    udp: UdpConfig = field(default_factory=UdpConfig)
    # Hard cap on simulated time per message; a transfer that has not finished by then is reported incomplete.
    max_sim_time_s: float = 600.0

    def validate(self) -> "NetworkConfig":
        self.down.validate("down")
        self.up.validate("up")
        self.tcp.validate()
        self.udp.validate()
        _check(_is_number(self.max_sim_time_s) and 0 < self.max_sim_time_s < math.inf,
               "max_sim_time_s must be a finite number > 0")
        return self

    @property
    def is_ideal(self) -> bool:
        return self.down.is_ideal and self.up.is_ideal

    def to_dict(self) -> dict:
        return _jsonable(dataclasses.asdict(self))


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return value


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and not math.isnan(value)


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise NetsimError(message)


# ---------------------------------------------------------------------------------------------------------------
# Parsing

_UNIT_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|inf)\s*([a-zA-Z%/]*)\s*$")
_BANDWIDTH_UNITS = {"": 1.0, "mbps": 1.0, "mbit": 1.0, "mbit/s": 1.0, "m": 1.0, "kbps": 1e-3, "kbit": 1e-3,
                    "kbit/s": 1e-3, "k": 1e-3, "gbps": 1e3, "gbit": 1e3, "gbit/s": 1e3, "g": 1e3, "bps": 1e-6}
_TIME_UNITS = {"": 1.0, "ms": 1.0, "s": 1e3, "us": 1e-3}
_SIZE_UNITS = {"": 1.0, "b": 1.0, "kb": 1e3, "kib": 1024.0, "mb": 1e6, "mib": 1024.0 ** 2, "p": None, "pkt": None,
               "packets": None}

# key -> (section, field, kind). "both" sets the two directions.
_LINK_KEYS = {
    "bw": "bandwidth_mbps", "bandwidth": "bandwidth_mbps", "rate": "bandwidth_mbps",
    "delay": "delay_ms", "owd": "delay_ms",
    "jitter": "jitter_ms", "jitter_dist": "jitter_distribution", "reorder": "reorder",
    "loss": "loss", "ge_p": "ge_p", "ge_r": "ge_r", "ge_loss_bad": "ge_loss_bad", "ge_loss_good": "ge_loss_good",
    "mtu": "mtu_bytes", "queue": "queue_bytes", "overhead": "link_overhead_bytes", "trace": "trace_path",
}
_TCP_KEYS = {"cc": "congestion_control", "iw": "initial_window_segments", "min_rto": "min_rto_ms",
             "initial_rto": "initial_rto_ms", "ssr": "slow_start_restart", "delack": "delayed_ack",
             "rwnd": "receive_window_bytes", "handshake": "count_handshake", "sack": "sack"}
_UDP_KEYS = {"pacing": "pacing_mbps", "burst": "burst", "nack": "nack_rounds", "fec_k": "fec_k", "fec_r": "fec_r"}


def _parse_number(text: str, units: dict, what: str) -> float:
    match = _UNIT_RE.match(str(text))
    if not match:
        raise NetsimError(f"cannot read {what} value {text!r}")
    number = float(match.group(1))
    unit = match.group(2).lower()
    if unit not in units:
        raise NetsimError(f"unknown unit {match.group(2)!r} in {what} value {text!r} "
                        f"(use one of {', '.join(u for u in units if u)})")
    return number * units[unit]


def _parse_bool(text: str, what: str) -> bool:
    lowered = str(text).strip().lower()
    if lowered in ("1", "true", "yes", "on"):
        return True
    if lowered in ("0", "false", "no", "off"):
        return False
    raise NetsimError(f"{what} must be on/off, got {text!r}")


def _link_value(field_name: str, text, mtu_bytes: int):
    if not isinstance(text, str):
        return text
    if field_name == "bandwidth_mbps":
        return _parse_number(text, _BANDWIDTH_UNITS, "bandwidth")
    if field_name in ("delay_ms", "jitter_ms"):
        return _parse_number(text, _TIME_UNITS, field_name.split("_")[0])
    if field_name in ("loss", "ge_p", "ge_r", "ge_loss_bad", "ge_loss_good"):
        text = text.strip()
        return _parse_number(text[:-1], {"": 1.0}, field_name) / 100 if text.endswith("%") else \
            _parse_number(text, {"": 1.0}, field_name)
    if field_name in ("mtu_bytes", "link_overhead_bytes"):
        value = _parse_number(text, {"": 1.0, "b": 1.0}, field_name)
        if value != int(value):
            raise NetsimError(f"{field_name} must be a whole number of bytes, got {text!r}")
        return int(value)
    if field_name == "queue_bytes":
        match = _UNIT_RE.match(text)
        if match and match.group(2).lower() in ("p", "pkt", "packets"):
            return float(match.group(1)) * mtu_bytes
        return _parse_number(text, {k: v for k, v in _SIZE_UNITS.items() if v is not None}, "queue")
    if field_name == "reorder":
        return _parse_bool(text, "reorder")
    if field_name == "trace_path":
        from netsim.traces import resolve_trace
        return resolve_trace(text)
    return text.strip()


def _other_value(field_name: str, text):
    if not isinstance(text, str):
        return text
    if field_name in ("slow_start_restart", "delayed_ack", "count_handshake", "sack", "burst"):
        return _parse_bool(text, field_name)
    if field_name in ("initial_window_segments", "nack_rounds", "fec_k", "fec_r"):
        value = _parse_number(text, {"": 1.0}, field_name)
        if value != int(value):
            raise NetsimError(f"{field_name} must be a whole number, got {text!r}")
        return int(value)
    if field_name in ("min_rto_ms", "initial_rto_ms"):
        return _parse_number(text, _TIME_UNITS, field_name)
    if field_name == "pacing_mbps":
        return _parse_number(text, _BANDWIDTH_UNITS, "pacing")
    if field_name == "receive_window_bytes":
        return _parse_number(text, {k: v for k, v in _SIZE_UNITS.items() if v is not None}, "rwnd")
    return text.strip().lower()


def apply_settings(base: NetworkConfig, settings: dict) -> NetworkConfig:
    """Return ``base`` with ``settings`` applied. Keys: link keys (bw, delay, loss, ...) for both directions,
    ``up.``/``down.``-prefixed link keys (or ``up_bw``, ``down_delay``, ...) for one, and TCP/UDP keys."""
    down = dataclasses.asdict(base.down)
    up = dataclasses.asdict(base.up)
    tcp = dataclasses.asdict(base.tcp)
    udp = dataclasses.asdict(base.udp)
    top = {"name": base.name, "max_sim_time_s": base.max_sim_time_s}
    # The MTU first: a queue given in packets ("queue=100p") is counted in MTUs.
    ordered = sorted(settings.items(), key=lambda item: 0 if str(item[0]).strip().lower().endswith("mtu") else 1)
    for raw_key, value in ordered:
        key = str(raw_key).strip().lower()
        targets = [down, up]
        for prefix in ("down.", "up.", "down_", "up_"):
            if key.startswith(prefix):
                targets = [down] if prefix.startswith("down") else [up]
                key = key[len(prefix):]
                break
        if key in _LINK_KEYS or key in _LINK_KEYS.values():
            field_name = _LINK_KEYS.get(key, key)
            for target in targets:
                target[field_name] = _link_value(field_name, value, int(target["mtu_bytes"]))
        elif key in _TCP_KEYS or key in _TCP_KEYS.values():
            field_name = _TCP_KEYS.get(key, key)
            tcp[field_name] = _other_value(field_name, value)
        elif key in _UDP_KEYS or key in _UDP_KEYS.values():
            field_name = _UDP_KEYS.get(key, key)
            udp[field_name] = _other_value(field_name, value)
        elif key in ("rtt",):
            # Symmetric path: half the round-trip time each way.
            for target in (down, up):
                target["delay_ms"] = _parse_number(value, _TIME_UNITS, "rtt") / 2 if isinstance(value, str) \
                    else float(value) / 2
        elif key in ("name", "max_sim_time_s"):
            top[key] = value if key == "name" else float(value)
        else:
            raise NetsimError(f"unknown network setting {raw_key!r}")
    try:
        config = NetworkConfig(name=top["name"], down=LinkConfig(**down), up=LinkConfig(**up),
                               tcp=TcpConfig(**tcp), udp=UdpConfig(**udp), max_sim_time_s=top["max_sim_time_s"])
    except TypeError as error:  # a value of the wrong type reached a dataclass
        raise NetsimError(f"invalid network setting: {error}") from None
    return config.validate()


def parse_spec(spec) -> NetworkConfig:
    """Turn a profile name, ``"ideal"``, an inline spec or a dict into a validated :class:`NetworkConfig`.

    Inline specs are comma-separated ``key=value`` pairs, optionally starting with a profile name to modify:
    ``"bw=50mbps,delay=17ms,loss=0.1%"``, ``"wan-50m,loss=1%"``, ``"down.bw=40mbps,up.bw=5mbps,rtt=30ms"``.
    """
    from netsim.profiles import PROFILES, profile_config

    if isinstance(spec, NetworkConfig):
        return spec.validate()
    if isinstance(spec, dict):
        settings = dict(spec)
        base_name = settings.pop("profile", None)
        base = profile_config(base_name) if base_name else NetworkConfig(name="custom")
        return apply_settings(base, settings)
    if not isinstance(spec, str) or not spec.strip():
        raise NetsimError(f"network spec must be a profile name, an inline spec or a dict, got {spec!r}")
    text = spec.strip()
    if text in PROFILES:
        return profile_config(text)
    parts = [part.strip() for part in text.split(",") if part.strip()]
    base = NetworkConfig(name="custom")
    if parts and "=" not in parts[0]:
        base = profile_config(parts[0])
        parts = parts[1:]
    settings = {}
    for part in parts:
        if "=" not in part:
            raise NetsimError(f"network spec item {part!r} is not key=value (in {spec!r})")
        key, value = part.split("=", 1)
        settings[key.strip()] = value.strip()
    config = apply_settings(base, settings)
    return dataclasses.replace(config, name=text if base.name == "custom" else f"{base.name}+custom")
