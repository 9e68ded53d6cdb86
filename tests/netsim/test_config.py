"""Profiles, inline specs and every impossible setting."""

import json
import math

import pytest

import netsim
from netsim.traces import load_mahimahi, mean_rate_mbps
from netsim.errors import NetsimError

REQUIRED_PROFILES = ("ideal", "lan-home", "wan-50m", "wifi-40m", "dsl-3m", "lte", "5g-edge")


def test_every_required_profile_is_listed_with_a_description():
    profiles = netsim.list_profiles()
    for name in REQUIRED_PROFILES:
        assert name in profiles and len(profiles[name]) > 10


@pytest.mark.parametrize("name", REQUIRED_PROFILES)
def test_every_profile_parses_and_describes_itself_as_json(name):
    net = netsim.make_network(name, seed=0)
    description = net.describe()
    assert json.loads(json.dumps(description))["name"] == name
    assert net.send(10_000, at_s=0.0).complete or name in ("wifi-40m", "lte")


def test_ideal_is_zero_delay_infinite_bandwidth_and_lossless():
    net = netsim.make_network("ideal", seed=0)
    for protocol in ("tcp", "udp"):
        delivery = net.send(8_000_000, protocol=protocol, at_s=2.5)
        assert delivery.arrival_s == 2.5 and delivery.complete and delivery.lost_ranges == []


def test_lan_home_moves_seed_000s_bitmap_in_about_87_ms():
    # Seed 000, results: the 8.3 MB (1920 * 1080 * 4 bytes) visibility bitmap took 87.33 ms per frame over a
    # warm connection (frames every ~130 ms).
    net = netsim.make_network("lan-home", seed=0)
    bitmap_bytes = 1920 * 1080 * 4
    at_s = 0.0
    for _ in range(4):  # the first frames warm the connection up (slow start, then the window settles)
        frame = net.send(bitmap_bytes, at_s=at_s)
        transfer_s = frame.arrival_s - at_s
        at_s = frame.arrival_s + 0.043  # the rest of seed 000's ~130 ms frame
    assert transfer_s == pytest.approx(0.087, rel=0.05)


def test_wan_50m_is_seed_002s_path():
    config = netsim.parse_spec("wan-50m")
    assert config.down.bandwidth_mbps == 50 and config.down.delay_ms == 17


def test_wifi_40m_is_seed_002s_target_link_and_dsl_3m_seed_004s_class():
    assert netsim.parse_spec("wifi-40m").down.bandwidth_mbps == 40
    assert netsim.parse_spec("dsl-3m").down.bandwidth_mbps == 3


def test_lte_follows_the_committed_synthetic_trace():
    config = netsim.parse_spec("lte")
    rate = mean_rate_mbps(load_mahimahi(config.down.trace_path))
    assert 10 < rate < 25
    assert mean_rate_mbps(load_mahimahi(config.up.trace_path)) < rate


def test_inline_spec_sets_both_directions():
    config = netsim.parse_spec("bw=50mbps,delay=17ms,loss=0.1%")
    for link in (config.down, config.up):
        assert (link.bandwidth_mbps, link.delay_ms, link.loss) == (50, 17, pytest.approx(0.001))


def test_inline_spec_units_and_directions():
    config = netsim.parse_spec("down.bw=1gbps,up.bw=500kbps,rtt=30ms,jitter=2ms,queue=100p,mtu=9000,cc=newreno")
    assert config.down.bandwidth_mbps == 1000 and config.up.bandwidth_mbps == 0.5
    assert config.down.delay_ms == 15 and config.up.delay_ms == 15 and config.down.jitter_ms == 2
    assert config.down.queue_bytes == 100 * 9000 and config.tcp.congestion_control == "newreno"


def test_inline_spec_can_modify_a_profile():
    config = netsim.parse_spec("wan-50m,loss=1%")
    assert config.down.bandwidth_mbps == 50 and config.down.loss == pytest.approx(0.01)


def test_a_dict_spec_works_like_an_inline_one():
    assert netsim.parse_spec({"bw": 50, "delay": 17, "loss": 0.001}).down == \
        netsim.parse_spec("bw=50mbps,delay=17ms,loss=0.1%").down


@pytest.mark.parametrize("spec, named", [
    ("bw=0", "bandwidth"), ("bw=-5mbps", "bandwidth"), ("delay=-1ms", "delay"), ("loss=1", "loss"),
    ("loss=100%", "loss"), ("loss=-0.1", "loss"), ("jitter=-1ms", "jitter"), ("mtu=20", "MTU"),
    ("queue=100", "queue"), ("bw=fast", "bandwidth"), ("bw=5furlongs", "unit"), ("colour=red", "colour"),
    ("no-such-profile", "profile"), ("wan-50m,bogus", "key=value"), ("jitter_dist=cauchy", "jitter"),
    ("ge_p=0.1,ge_r=0", "ge_r"), ("cc=vegas", "congestion"), ("iw=0", "initial window"),
    ("fec_k=0,fec_r=2", "fec_k"), ("pacing=0", "pacing"), ("trace=/no/such/file", "trace"), ("rwnd=0", "window"),
    ("", "spec"),
])
def test_impossible_settings_raise_a_user_error_naming_them(spec, named):
    with pytest.raises(NetsimError, match=named):
        netsim.make_network(spec)


@pytest.mark.parametrize("kwargs, named", [
    ({"size_bytes": 0}, "size"), ({"size_bytes": -10}, "size"), ({"size_bytes": 1.5}, "size"),
    ({"size_bytes": 10, "direction": "sideways"}, "direction"), ({"size_bytes": 10, "protocol": "quic"}, "protocol"),
    ({"size_bytes": 10, "at_s": -1.0}, "time"), ({"size_bytes": 10, "at_s": math.nan}, "time"),
    ({"size_bytes": 10, "deadline_s": 0.0}, "deadline"),
])
def test_impossible_messages_raise_a_user_error_naming_them(kwargs, named):
    with pytest.raises(NetsimError, match=named):
        netsim.make_network("wan-50m").send(**kwargs)


def test_send_times_must_not_go_backwards():
    net = netsim.make_network("wan-50m")
    net.send(100, at_s=1.0)
    with pytest.raises(NetsimError, match="must not decrease"):
        net.send(100, at_s=0.5)


def test_seed_must_be_an_integer():
    with pytest.raises(NetsimError, match="seed"):
        netsim.make_network("wan-50m", seed="x")
