"""The report reads stored results only and writes index.html, plots and tables."""
import json
import re
import shutil
from pathlib import Path

import pandas as pd
import pytest

from reports import build as report
from suite.harness import executor

FAKE_METHODS = Path(__file__).parent / "fake_methods"


def test01_report_has_every_section_and_table(fake_config, tmp_path):
    configs = [fake_config(net="bw=8mbps,delay=5ms"),
               fake_config("synthetic_async", net="bw=8mbps,delay=5ms", frames=4, clock="work")]
    executor.sweep(configs, tmp_path / "res")
    index = report.build(tmp_path / "res", tmp_path / "rep")
    page = index.read_text()
    for title in ("Run matrix", "Frame-time breakdown", "Bandwidth", "SSIM / DSSIM per frame", "Speed vs error",
                  "Machine and versions"):
        assert re.search(f"<h2[^>]*>{re.escape(title)}", page), title
    for name in ("runs.csv", "breakdown.csv", "stages.csv", "bandwidth.csv", "quality.csv", "speed_vs_error.csv",
                 "machines.csv", "breakdown.png", "bandwidth.png", "quality.png", "speed_vs_error.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 0, name
    runs = pd.read_csv(tmp_path / "rep" / "runs.csv")
    assert sorted(runs["method"]) == ["synthetic_async", "synthetic_sync"]
    # the frames a method section gets carry the backend of their run; every file was written atomically
    assert set(pd.read_csv(tmp_path / "rep" / "frames.csv")["backend"]) == {"fake"}
    assert not [p.name for p in (tmp_path / "rep").rglob(".*")]


def test02_report_never_runs_anything_and_ignores_incomplete_runs(fake_config, fake_core, tmp_path, monkeypatch):
    executor.sweep([fake_config()], tmp_path / "res")
    (tmp_path / "res" / ".tmp-half-written").mkdir()
    (tmp_path / "res" / "interrupted").mkdir()
    monkeypatch.setattr(fake_core, "execute", lambda *a, **k: (_ for _ in ()).throw(AssertionError("ran")))
    report.build(tmp_path / "res", tmp_path / "rep")
    assert len(pd.read_csv(tmp_path / "rep" / "runs.csv")) == 1


def test03_method_sections_and_extra_tables_are_included(fake_config, tmp_path, monkeypatch):
    executor.sweep([fake_config()], tmp_path / "res")
    extra = tmp_path / "validation"
    extra.mkdir()
    (extra / "netsim_vs_ns3.csv").write_text("profile,ratio\nwan-50m,1.02\n")
    monkeypatch.setattr(report, "EXTRA_TABLE_DIRS", [extra])
    monkeypatch.setattr(report, "method_sections",
                        lambda frames, loaded, **kw: [("synthetic_sync", f"<p>{len(frames)} frames seen</p>")])
    page = report.build(tmp_path / "res", tmp_path / "rep").read_text()
    assert "netsim_vs_ns3.csv" in page and "1.02" in page
    # a method without a paper is headed as a baseline
    assert "<h2>Method: synthetic_sync (baseline)</h2><p>3 frames seen</p>" in page


def _method_with_report(root, source: str):
    """A copy of the synthetic_sync method under ``root`` whose report.py is ``source``; returns ``root``."""
    shutil.copytree(FAKE_METHODS / "synthetic_sync", root / "synthetic_sync")
    (root / "synthetic_sync" / "report.py").write_text(source)
    return root


def test04_method_report_py_is_discovered(fake_config, tmp_path, monkeypatch):
    root = _method_with_report(tmp_path / "methods",
                               "def section(results_df, run_dirs):\n    return f'<p>{len(run_dirs)} runs here</p>'\n")
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    executor.sweep([fake_config()], tmp_path / "res")
    page = report.build(tmp_path / "res", tmp_path / "rep").read_text()
    assert "<p>1 runs here</p>" in page


def test06_a_method_section_that_takes_out_dir_and_results_root_gets_them(fake_config, tmp_path, monkeypatch):
    root = _method_with_report(tmp_path / "methods",
                               "def section(results_df, run_dirs, out_dir=None, results_root=None):\n"
                               "    (out_dir / 'extra.csv').write_text('x\\n1\\n')\n"
                               "    return f'<p>root {results_root.name}</p>'\n")
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    executor.sweep([fake_config()], tmp_path / "res")
    page = report.build(tmp_path / "res", tmp_path / "rep").read_text()
    assert "<p>root res</p>" in page and (tmp_path / "rep" / "extra.csv").read_text() == "x\n1\n"


def test05_breakdown_parts_sum_to_the_frame_time(fake_config, tmp_path):
    executor.sweep([fake_config(net="bw=8mbps,delay=5ms")], tmp_path / "res")
    report.build(tmp_path / "res", tmp_path / "rep")
    table = pd.read_csv(tmp_path / "rep" / "breakdown.csv", index_col=0)
    parts = table.drop(columns=["frame_ms"]).sum(axis=1)
    assert parts.to_numpy() == pytest.approx(table["frame_ms"].to_numpy())
    assert "cp_net_frame_ms" in table.columns


def test_netsim_validation_is_summarised_per_transport(tmp_path):
    csv = tmp_path / "validation.csv"
    csv.write_text("transport,size_bytes,bandwidth_mbps,rtt_ms,loss,rel_error\n"
                   "udp,1000,10,2,0.0,0.01\nudp,1000,10,2,0.01,0.03\n"
                   "tcp-cubic,1000,10,2,0.0,0.02\ntcp-cubic,1000,10,2,0.02,0.20\n")
    summary = report.netsim_validation_summary(pd.read_csv(csv)).set_index("transport")
    assert summary.loc["udp", "loss-free median %"] == pytest.approx(1.0)
    assert summary.loc["tcp-cubic", "lossy median %"] == pytest.approx(20.0)
    assert summary.loc["tcp-cubic", "median %"] == pytest.approx(11.0)
    html = report.netsim_validation_section(tmp_path, csv)
    assert "netsim against ns-3" in html and (tmp_path / "netsim_validation.csv").exists()
    assert report.netsim_validation_section(tmp_path, tmp_path / "missing.csv") == ""


def test07_one_loader_imports_a_methods_files_and_never_serves_another_folders_copy(tmp_path, monkeypatch):
    from suite.errors import UserError
    from suite.harness import registry

    for k in (1, 2):  # the same method name in two roots, with different report.py files
        _method_with_report(tmp_path / f"methods{k}", f"def section(results_df, run_dirs):\n    return '{k}'\n")
    for k in (1, 2, 1):
        monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(tmp_path / f"methods{k}"))
        assert registry.load_module("synthetic_sync", "report").section(None, []) == str(k)
    assert registry.load_module("synthetic_sync", "report") is registry.load_module("synthetic_sync", "report")
    with pytest.raises(UserError, match="has no bench.py"):
        registry.load_module("synthetic_sync", "bench")
    # the project's own methods import as a package, the same module the CLI's bench hook and the builder get
    from methods.visibility_bitmap import report as vb_report
    assert registry.load_module("visibility_bitmap", "report") is vb_report


def test_the_report_marks_scenes_that_were_not_available(tmp_path):
    import json

    from reports.build import scenes_section

    (tmp_path / "scenes.json").write_text(json.dumps({"scenes": {
        "cornell": "Mitsuba's Cornell box", "oa:kaos": "unavailable: install the OpenArena packages"}}))
    html = scenes_section(tmp_path)
    assert "not measured: oa:kaos" in html and "install the OpenArena packages" in html
    assert scenes_section(tmp_path / "nowhere") == ""


def test08_the_report_shows_the_core_benchmarks_per_backend(tmp_path):
    """What `splitbench bench core` and `bench tracing` stored: each backend's stages with ms, device time, rays and
    bytes, the ratios against the raw queries with their goals, and the tracing overhead; a hint where none is."""
    from reports.build import core_bench_section
    from suite.harness import cli

    assert "No stored core benchmarks" in core_bench_section(tmp_path, tmp_path)
    assert cli.main(["bench", "core", "--scene", "living_room", "--backend", "embree,mitsuba-llvm", "--resolution",
                     "24x14", "--repeats", "1", "--out", str(tmp_path)]) == 0
    assert cli.main(["bench", "tracing", "--scene", "cornell", "--backend", "embree,mitsuba-llvm", "--repeats", "1",
                     "--max-rays", "2000", "--resolution", "64x36", "--out", str(tmp_path)]) == 0
    html = core_bench_section(tmp_path, tmp_path)
    stages = pd.read_csv(tmp_path / "core_stages.csv")
    assert {"embree", "mitsuba-llvm"} == {s.split(", ")[1].split(" ")[0] for s in stages["setting"]}
    llvm = stages[stages["setting"].str.contains("mitsuba-llvm")].set_index("stage")
    assert llvm.loc["gbuffer", "kernel_ms"] > 0 and llvm.loc["visibility", "rays"] > 0
    assert llvm.loc["copy_gbuffer_to_host", "bytes"] > 0
    for text in ("G-buffer / raw intersect (goal &lt;= 2)", "visibility raw / pass (goal &gt;= 0.9)",
                 "occluded suite/raw (goal &gt;= 0.9)", "cornell", "device (llvm_ad_rgb)", "visibility, repeats",
                 "occluded repeats"):
        assert text in html, text
    # each ratio's repeats as lowest-highest (one repeat's ratio: its two calls ran next to each other)
    core = json.loads((tmp_path / "bench" / "core.json").read_text())
    lo, hi = core["results"][1]["visibility_raw_over_pass_range"]
    assert f"{lo:.3f}-{hi:.3f}" in html


def test09_the_run_matrix_states_what_a_method_left_out_of_a_scene(fake_config, tmp_path, monkeypatch):
    from suite.harness import registry

    cls = registry.get("synthetic_sync").load()
    monkeypatch.setattr(cls, "omissions", lambda self, scene: ["its fill light is left out"], raising=False)
    executor.sweep([fake_config(), fake_config("synthetic_async")], tmp_path / "res")
    page = report.build(tmp_path / "res", tmp_path / "rep").read_text()
    matrix = page[page.index("Run matrix"):]
    assert "synthetic_sync: 1 runs, leaving part of 1 scene(s) out" in matrix
    assert "Left out (the errors include it): toy: its fill light is left out." in matrix
    assert "synthetic_async: 1 runs</summary>" in matrix  # a method that leaves nothing out says nothing
    runs = pd.read_csv(tmp_path / "rep" / "runs.csv").set_index("method")
    assert runs.loc["synthetic_sync", "omitted"] == "its fill light is left out"
