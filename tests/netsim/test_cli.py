"""The netsim CLI: transfer and validate."""

import argparse
import json

import pytest

from netsim import cli, validate


def test_transfer_prints_completion_delivered_bytes_retransmissions_and_lost_ranges(capsys):
    assert cli.main(["transfer", "--bytes", "200000", "--bandwidth-mbps", "20", "--rtt-ms", "30",
                     "--loss", "0.05", "--protocol", "udp", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["size_bytes"] == 200000 and result["lost_ranges"]
    assert result["delivered_bytes"] + sum(b - a for a, b in result["lost_ranges"]) == 200000


def test_transfer_text_output(capsys):
    assert cli.main(["transfer", "--bytes", "100000", "--bandwidth-mbps", "10", "--rtt-ms", "20"]) == 0
    out = capsys.readouterr().out
    for label in ("completion time", "delivered bytes", "retransmissions", "lost ranges"):
        assert label in out


def test_transfer_with_impossible_settings_exits_2(capsys):
    assert cli.main(["transfer", "--bytes", "0", "--bandwidth-mbps", "10", "--rtt-ms", "20"]) == 2
    assert cli.main(["transfer", "--bytes", "10", "--bandwidth-mbps", "10", "--rtt-ms", "20", "--loss", "1"]) == 2
    assert "error" in capsys.readouterr().err


def test_validate_without_ns3_says_so_and_exits_2(monkeypatch, capsys):
    monkeypatch.setattr(validate, "ns3_available", lambda: False)
    assert cli.main(["validate", "--quick"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ns-3 is not installed" in err[0]


def test_register_mounts_the_netsim_command_on_a_parent_parser():
    parser = argparse.ArgumentParser(prog="splitbench")
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["netsim", "transfer", "--bytes", "10", "--bandwidth-mbps", "1", "--rtt-ms", "1"])
    assert args.func is cli.cmd_transfer
    assert parser.parse_args(["netsim", "validate", "--quick"]).func is cli.cmd_validate


def test_validation_summary_statistics():
    rows = [{"transport": "udp", "loss": 0.0, "rel_error": e} for e in (0.0, 0.1, 0.2, 0.3, 0.4)]
    summary = validate.summarise(rows)["udp"]
    assert summary["median_rel_error"] == 0.2
    assert summary["p90_rel_error"] == pytest.approx(0.36)


def test_errors_are_one_line_on_stderr_with_exit_status_2_also_when_mounted(capsys):
    # python -m netsim and a parent CLI (splitbench) that mounts the commands: the command itself reports.
    assert cli.main(["transfer", "--bytes", "10", "--bandwidth-mbps", "-5", "--rtt-ms", "20"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("netsim: error:") and "bandwidth" in err[0]
    parser = argparse.ArgumentParser(prog="splitbench")
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["netsim", "transfer", "--bytes", "0", "--bandwidth-mbps", "1", "--rtt-ms", "1"])
    assert args.func(args) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_python_dash_m_netsim_exits_2_on_a_bad_setting():
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "netsim", "transfer", "--bytes", "100", "--bandwidth-mbps", "10",
                             "--rtt-ms", "20", "--loss", "2"], capture_output=True, text=True)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "loss" in result.stderr
