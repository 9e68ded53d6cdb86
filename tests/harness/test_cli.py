"""The splitbench CLI: summaries, --json, one-line errors with exit code 2, and nothing written on bad input."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from suite.harness import cli, results

REPO = Path(__file__).resolve().parents[2]


def _run(capsys, *argv):
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test01_run_prints_where_results_went_and_a_summary(fake_core, tmp_path, capsys):
    code, out, err = _run(capsys, "run", "synthetic_sync", "--scene", "toy", "--backend", "fake", "--resolution",
                          "16x8", "--frames", "2", "--net", "bw=8mbps,delay=5ms", "--out", str(tmp_path),
                          "--reference-spp", "2")
    assert code == 0, err
    run_dir = results.complete_runs(tmp_path)[0]
    assert f"results: {run_dir}" in out
    assert "frame ms" in out and "Mbit/s" in out and "DSSIM" in out


def test02_run_json_is_machine_readable(fake_core, tmp_path, capsys):
    code, out, _ = _run(capsys, "run", "synthetic_sync", "--scene", "toy", "--backend", "fake", "--resolution",
                        "16x8", "--frames", "2", "--set", "payload_bytes=100", "--out", str(tmp_path), "--json")
    doc = json.loads(out)
    assert code == 0 and doc["summary"]["bytes_down"] == 200 and Path(doc["run_dir"]).is_dir()


def test02b_run_over_a_grid_makes_one_run_per_combination(fake_core, tmp_path, capsys):
    """A repeated --set key and a repeated --net span a grid, run through the executor."""
    code, out, err = _run(capsys, "run", "synthetic_sync", "--scene", "toy", "--backend", "fake", "--resolution",
                          "16x8", "--frames", "2", "--set", "payload_bytes=100", "--set", "payload_bytes=300",
                          "--net", "ideal", "--net", "bw=8mbps,delay=5ms", "--out", str(tmp_path), "--json")
    assert code == 0, err
    docs = json.loads(out)
    assert len(docs) == 4 and len(results.complete_runs(tmp_path)) == 4
    assert sorted(d["summary"]["bytes_down"] for d in docs) == [200, 200, 600, 600]
    assert sorted({d["summary"]["net"] for d in docs}) == ["bw=8mbps,delay=5ms", "ideal"]


@pytest.mark.parametrize("args, needle", [
    (["run", "teleport"], "unknown method 'teleport'"),
    (["run", "synthetic_sync", "--scene", "atlantis"], "unknown scene 'atlantis'"),
    (["run", "synthetic_sync", "--net", "carrier-pigeon"], "unknown network profile 'carrier-pigeon'"),
    (["run", "synthetic_sync", "--set", "warp=9"], "unknown parameter 'warp'"),
    (["run", "synthetic_sync", "--set", "novalue"], "malformed --set 'novalue'"),
    (["run", "synthetic_sync", "--resolution", "0x0"], "resolution 0x0"),
    (["run", "synthetic_sync", "--frames", "-1"], "frame count must be >= 1"),
    (["run", "synthetic_sync", "--frames", "many"], "--frames must be an integer"),
    (["run", "synthetic_sync", "--protocol", "smoke-signals"], "invalid choice"),
    (["frobnicate"], "invalid choice"),
])
def test03_bad_input_is_one_line_exit_2_and_writes_nothing(fake_core, tmp_path, capsys, args, needle):
    out_dir = tmp_path / "results"
    argv = args + (["--scene", "toy"] if args[0] == "run" and "--scene" not in args else []) + \
        (["--backend", "fake", "--out", str(out_dir)] if args[0] == "run" else [])
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("splitbench: error: ") and needle in err
    assert "Traceback" not in err and not out_dir.exists()


def test04_unwritable_out_is_named(fake_core, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    code, _, err = _run(capsys, "run", "synthetic_sync", "--scene", "toy", "--backend", "fake",
                        "--out", str(blocker / "results"))
    assert code == 2 and f"cannot write to --out '{blocker / 'results'}'" in err
    assert results.complete_runs(tmp_path) == []


def test05_list_json_names_the_discovered_methods(fake_core, capsys):
    code, out, _ = _run(capsys, "list", "--json")
    doc = json.loads(out)
    assert code == 0
    assert doc["methods"]["synthetic_sync"]["mode"] == "sync"
    assert doc["methods"]["synthetic_async"]["mode"] == "async"
    assert doc["methods"]["synthetic_sync"]["doc"]["gain"] == "image brightness factor"
    assert "local_direct" in doc["methods"]


def test06_reproduce_runs_the_preset_then_builds_the_report(fake_core, tmp_path, capsys):
    code, out, err = _run(capsys, "reproduce", "--preset", "smoke", "--methods", "synthetic_sync,synthetic_async",
                          "--out", str(tmp_path / "res"), "--report", str(tmp_path / "rep"))
    assert code == 0, err
    # synthetic_sync: 2 nets x 2 payloads; synthetic_async: 1 point
    assert len(results.complete_runs(tmp_path / "res")) == 5
    assert (tmp_path / "rep" / "index.html").exists() and f"report: {tmp_path / 'rep' / 'index.html'}" in out
    code, out, _ = _run(capsys, "reproduce", "--preset", "smoke", "--methods", "synthetic_sync",
                        "--out", str(tmp_path / "res"), "--report", str(tmp_path / "rep"))
    assert "0 runs done, 4 already complete" in out


def test07_python_dash_m_suite_reports_user_errors_without_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "suite", "run", "no_such_method", "--out", str(tmp_path / "r")],
                          cwd=REPO, capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, SPLITBENCH_PROGRESS="0",
                                   PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH"))
                                                              if p)))
    assert proc.returncode == 2
    assert proc.stderr.strip() == proc.stderr.strip().splitlines()[0]
    assert "unknown method 'no_such_method'" in proc.stderr and not (tmp_path / "r").exists()


def test08_compare_prints_the_metrics_of_two_exr_files(tmp_path, capsys):
    import numpy as np

    from suite.core.imageio import write_exr

    ref = np.linspace(0, 1, 32 * 24 * 3, dtype=np.float32).reshape(24, 32, 3)
    write_exr(tmp_path / "ref.exr", ref)
    write_exr(tmp_path / "test.exr", ref * 0.5)
    code, out, _ = _run(capsys, "compare", str(tmp_path / "ref.exr"), str(tmp_path / "test.exr"), "--json")
    metrics = json.loads(out)
    assert code == 0 and set(metrics) >= {"ssim", "dssim", "psnr_db", "nrmse", "flip"}
    assert metrics["dssim"] > 0
    code, _, err = _run(capsys, "compare", str(tmp_path / "ref.exr"), str(tmp_path / "missing.exr"))
    assert code == 2 and "no such image" in err and str(tmp_path / "missing.exr") in err


def test09_reference_rejects_a_non_exr_output_before_rendering(fake_core, tmp_path, capsys):
    code, _, err = _run(capsys, "reference", "--scene", "toy", "--out", str(tmp_path / "ref.png"))
    assert code == 2 and "must end in .exr" in err and not (tmp_path / "ref.png").exists()


def test10_bench_tracing_prints_suite_and_raw_rates_and_their_ratio(fake_core, capsys, monkeypatch):
    import types

    fake_bench = types.ModuleType("suite.core.trace.bench")
    rates = {"suite_rays_per_s": 2.0e6, "raw_rays_per_s": 4.0e6, "ratio": 0.5}
    fake_bench.run = lambda scene, backend, **kwargs: {"scene": "toy", "rays": 1000, "repeats": 5,
                                                       "occluded": rates, "intersect": rates}
    monkeypatch.setitem(sys.modules, "suite.core.trace.bench", fake_bench)
    code, out, _ = _run(capsys, "bench", "tracing", "--scene", "toy", "--backend", "fake")
    assert code == 0 and out.count("suite     2,000,000 rays/s") == 2 and "raw     4,000,000 rays/s" in out
    assert "ratio 0.500" in out
    code, _, err = _run(capsys, "bench", "tracing", "--scene", "toy", "--backend", "abacus")
    assert code == 2 and "unknown backend 'abacus'" in err


def test11_an_async_run_that_no_update_reached_says_so():
    """Staleness is defined only for frames with an update in use; an async run without any says plainly that
    its client never received one, rather than printing a quality that looks like the method's."""
    summary = {"resolution": [16, 8], "method": "m", "variant": "default", "mode": "async", "scene": "toy",
               "frames": 30, "net": "wan-50m", "protocol": "tcp", "fps": 60.0, "bandwidth_mbps": 1.0,
               "bandwidth_down_mbps": 1.0, "bandwidth_up_mbps": 0.0, "bytes_down": 10, "bytes_up": 0, "rays": 0,
               "prepare_ms": 1.0, "stats": {"frame_ms": {"mean": 1.0, "p50": 1.0, "p95": 1.0}}}
    out = {"summary": summary, "run_dir": "x", "skipped": False}
    assert "no update reached the client in these 30 frames" in cli.format_summary(out)
    summary["stats"]["staleness_ms"] = {"mean": 200.0, "p50": 200.0, "p95": 300.0}
    assert "no update reached" not in cli.format_summary(out)
    summary["mode"], summary["stats"] = "sync", {}
    assert "no update reached" not in cli.format_summary(out)


def test12_a_bench_device_list_is_checked_and_a_failing_device_kernel_is_reported_not_fatal(capsys, monkeypatch):
    from suite.core import trace
    from suite.errors import UserError

    status = {"mitsuba-llvm": {"available": True, "detail": "ok"},
              "mitsuba-cuda": {"available": False, "detail": "no NVIDIA GPU"}}
    monkeypatch.setattr(trace, "backend_status", lambda: status)
    assert cli.bench_devices("") == [] and cli.bench_devices("auto") == ["mitsuba-llvm"]
    assert cli.bench_devices("mitsuba-llvm") == ["mitsuba-llvm"]
    for bad, words in (("embree", "not a Dr.Jit backend"), ("mitsuba-cuda", "does not work on this machine")):
        with pytest.raises(UserError, match=words):
            cli.bench_devices(bad)

    assert cli.device_columns("rail", "mitsuba-llvm", lambda: {"llvm_idw_ms": 1.0}) == {"llvm_idw_ms": 1.0}

    def fails():
        raise RuntimeError("jit_optix_compile(): no OptiX")

    assert cli.device_columns("rail", "mitsuba-cuda", fails) == {"cuda_error": "RuntimeError: jit_optix_compile(): "
                                                                               "no OptiX"}
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["splitbench: warning: bench rail: the device kernel on mitsuba-cuda failed: "
                                        "RuntimeError: jit_optix_compile(): no OptiX"]
