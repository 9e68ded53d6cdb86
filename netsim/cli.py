"""``splitbench netsim`` commands: ``transfer`` (one message through a simple path) and ``validate`` (ns-3).

The lead's CLI mounts them with ``netsim.cli.register(subparsers)``; ``python -m netsim ...`` runs them alone.
Either way a :class:`~netsim.errors.NetsimError` is printed as one line on stderr and the command exits with
status 2: the command functions handle it themselves, so a parent CLI needs to know nothing about netsim's errors.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys

from netsim.errors import NetsimError

PROG = "netsim"


def _one_line_errors(command):
    """Run a command; a NetsimError becomes ``netsim: error: <message>`` on stderr and exit status 2."""

    @functools.wraps(command)
    def run(args) -> int:
        try:
            return command(args)
        except NetsimError as error:
            print(f"{PROG}: error: {error}", file=sys.stderr)
            return NetsimError.exit_code

    return run


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``netsim`` command (with ``transfer`` and ``validate``) to an argparse subparsers object."""
    parser = subparsers.add_parser("netsim", help="network model: single transfers, validation against ns-3",
                                   description="Network model: single transfers and validation against ns-3.")
    commands = parser.add_subparsers(dest="netsim_command", metavar="{transfer,validate}")
    commands.required = True

    transfer = commands.add_parser("transfer", help="simulate one message over a path and print what happened")
    transfer.add_argument("--bytes", type=int, required=True, dest="size_bytes", help="message size in bytes")
    transfer.add_argument("--bandwidth-mbps", type=float, required=True, help="link rate, Mbit/s (both ways)")
    transfer.add_argument("--rtt-ms", type=float, required=True, help="round-trip propagation delay, ms")
    transfer.add_argument("--loss", type=float, default=0.0, help="packet loss probability (0.01 = 1 %%)")
    transfer.add_argument("--protocol", choices=("tcp", "udp"), default="tcp")
    transfer.add_argument("--cc", choices=("newreno", "cubic"), default="cubic", help="TCP congestion control")
    transfer.add_argument("--seed", type=int, default=0)
    transfer.add_argument("--json", action="store_true", help="print JSON")
    transfer.set_defaults(func=cmd_transfer)

    validate = commands.add_parser("validate", help="compare completion times with ns-3 (needs the ns3 package); "
                                                    "--fairness: flows sharing a bottleneck")
    validate.add_argument("--quick", action="store_true", help="a small grid (about a minute)")
    validate.add_argument("--json", action="store_true", help="print the summary as JSON")
    validate.add_argument("--no-write", action="store_true",
                          help="do not overwrite netsim/validation/ with the new table")
    validate.add_argument("--fairness", action="store_true",
                          help="the dumbbell instead: N TCP flows through one shared bottleneck (netsim.topology), "
                               "per-flow completion times and Jain's index against ns-3 (fairness.csv)")
    validate.set_defaults(func=cmd_validate)
    return parser


def _check_loss(loss: float) -> float:
    if not 0 <= loss < 1:
        raise NetsimError(f"--loss must be in [0, 1), got {loss}")
    return loss


@_one_line_errors
def cmd_transfer(args) -> int:
    import netsim

    _check_loss(args.loss)
    if args.rtt_ms < 0 or not math.isfinite(args.rtt_ms):
        raise NetsimError(f"--rtt-ms must be a finite number >= 0, got {args.rtt_ms}")
    spec = {"bw": args.bandwidth_mbps, "delay": args.rtt_ms / 2, "loss": args.loss, "cc": args.cc}
    net = netsim.make_network(spec, seed=args.seed)
    delivery = net.send(args.size_bytes, direction="down", protocol=args.protocol, at_s=0.0)
    result = delivery.to_dict()
    result["completion_ms"] = None if math.isinf(delivery.arrival_s) else delivery.arrival_s * 1e3
    result["settled_ms"] = None if math.isinf(delivery.settled_s) else delivery.settled_s * 1e3
    result["network"] = net.describe()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    completion = "never (incomplete)" if result["completion_ms"] is None else f"{result['completion_ms']:.3f} ms"
    print(f"completion time:   {completion}")
    print(f"delivered bytes:   {delivery.delivered_bytes} of {delivery.size_bytes}")
    print(f"retransmissions:   {delivery.retransmissions}")
    ranges = ", ".join(f"[{a}, {b})" for a, b in delivery.lost_ranges) or "none"
    print(f"lost ranges:       {ranges}")
    return 0


@_one_line_errors
def cmd_validate(args) -> int:
    from netsim import validate

    if not validate.ns3_available():
        raise NetsimError("ns-3 is not installed: pip install 'splitbench[ns3]' (package ns3 >= 3.44, Linux x86_64, "
                        "needs a C++ compiler) to run netsim validate")
    progress = None if args.json else (lambda line: print(line, flush=True))
    if args.fairness:
        rows, summary = validate.compare_fairness(quick=args.quick, progress=progress)
        if not args.no_write:
            validate.write_fairness_outputs(rows, ns3_version=validate.ns3_version())
        if args.json:
            print(json.dumps(summary, indent=2))
        else:
            for group, s in summary.items():
                print(f"{group}: {s['cases']} cases, {s['flows']} flows, per-flow median error "
                      f"{s['median_rel_error']:.1%}, p90 {s['p90_rel_error']:.1%}; aggregate median "
                      f"{s['aggregate_median_rel_error']:.1%}; min Jain netsim {s['netsim_jain_min']:.3f}, "
                      f"ns-3 {s['ns3_jain_min']:.3f}")
        return 0
    rows, summary = validate.compare(quick=args.quick, progress=progress)
    if not args.no_write:
        validate.write_outputs(rows, summary, ns3_version=validate.ns3_version())
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for transport, s in summary.items():
            print(f"{transport}: {s['cases']} cases, median error {s['median_rel_error']:.1%}, "
                  f"p90 {s['p90_rel_error']:.1%}, loss-free median {s['lossless_median_rel_error']:.1%}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m netsim")
    subparsers = parser.add_subparsers(dest="command", required=True)
    register(subparsers)
    # Without the outer command name: python -m netsim transfer ... == splitbench netsim transfer ...
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(["netsim", *argv])
    return args.func(args)
