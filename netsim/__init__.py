"""netsim: when does each message arrive, and which bytes are lost on the way.

    import netsim
    net = netsim.make_network("wan-50m", seed=0)   # profile | inline "bw=50mbps,delay=17ms,loss=0.1%" | dict
    d = net.send(300_000, direction="down", protocol="tcp", at_s=0.0)
    d.arrival_s, d.delivered_bytes, d.lost_ranges, d.retransmissions, d.complete

    topo = netsim.make_topology(access="lan-home", server="bw=100mbps,delay=5ms", clients=3, seed=0)
    d = topo.send(100_000, client=1, direction="down", protocol="tcp", at_s=0.25)   # same Delivery, tentative
    topo.advance(0.25)                               # promise: no later send has at_s < 0.25

Bad settings raise netsim.NetsimError (a ValueError) with a one-line message.

See docs/netsim.md for the model, the profiles and the validation against ns-3.
"""

import importlib

# Names are resolved on first use (PEP 562), so that `python -m netsim.link` and friends run their examples
# without the package having imported those modules already.
_EXPORTS = {
    "Delivery": "netsim.network", "Network": "netsim.network", "make_network": "netsim.network",
    "LinkConfig": "netsim.config", "NetworkConfig": "netsim.config", "TcpConfig": "netsim.config",
    "UdpConfig": "netsim.config", "parse_spec": "netsim.config", "list_profiles": "netsim.profiles",
    "NetsimError": "netsim.errors", "Topology": "netsim.topology", "make_topology": "netsim.topology",
    "derive_seed": "netsim.topology", "server_seed": "netsim.topology",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'netsim' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
