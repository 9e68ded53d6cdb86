"""The shared compare matrix, the metric registry with its Pareto fronts, and the cross-method report built from
stored results only (answer first, the claims of every method section in one table)."""
import re
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from reports import build as report, compare
from suite.errors import UserError
from suite.harness import cli, executor, metric_registry as mr, presets

HERE = Path(__file__).parent
TINY = HERE / "compare_tiny.toml"
SYNTHETIC = "synthetic_sync,synthetic_async"


@pytest.fixture
def real_scene_names(fake_core, monkeypatch):
    """Validation accepts the matrix's real scene names and backend; Sponza counts as unavailable."""
    matrix = tomllib.loads(presets.COMPARE_FILE.read_text())["compare"]
    names = sorted({s for cell in matrix["cells"] for s in cell["scenes"]})
    monkeypatch.setattr(fake_core, "scene_names", lambda: names)
    monkeypatch.setattr(fake_core, "backend_names", lambda: ["fake", matrix["backend"]])
    monkeypatch.setattr(presets, "scene_available", lambda scene: scene != "dabrovic_sponza")
    return matrix


def test_the_compare_preset_expands_to_the_documented_matrix_and_records_unavailable_scenes(real_scene_names):
    matrix = real_scene_names
    configs, problems, record = presets.expand("compare", methods=SYNTHETIC)
    assert not problems and record["skipped_scenes"] == ["dabrovic_sponza"]
    expected = set()
    for cell in matrix["cells"]:
        for scene in cell["scenes"]:
            if scene == "dabrovic_sponza":
                continue
            for net in cell["nets"]:
                for protocol in cell["protocols"]:
                    expected |= {("synthetic_sync", v, scene, net, protocol) for v in ("default", "dim")}
                    expected.add(("synthetic_async", "default", scene, net, protocol))
    got = [(c["method"], c["variant"], c["scene"], c["net"], c["protocol"]) for c in configs]
    assert sorted(got) == sorted(expected) and len(got) == len(set(got))
    # the matrix's settings, and the method's own [presets.compare] set, reach every run
    w, h = (int(v) for v in matrix["resolution"].split("x"))
    for c in configs:
        assert c["resolution"] == [w, h] and c["frames"] == matrix["frames"]
        assert c["reference_spp"] == matrix["reference_spp"] and c["quality_every"] == matrix["quality_every"]
        # every method on one machine model: the work clock (docs/results.md "The compare preset")
        assert matrix["clock"] == "work" and c["clock"] == "work"
    assert {c["params"]["work_ms"] for c in configs if c["method"] == "synthetic_sync"} == {60.0}
    assert record["methods"]["synthetic_sync"]["runs"] + record["methods"]["synthetic_async"]["runs"] == len(got)


def test_a_method_without_messages_runs_once_per_scene_on_the_ideal_network(fake_core, tmp_path, monkeypatch,
                                                                          fake_method_copy):
    root = tmp_path / "methods"
    folder = fake_method_copy(root, "synthetic_sync", as_name="synthetic_local")
    source = (folder / "method.py").read_text()
    (folder / "method.py").write_text(
        source.replace('name = "synthetic_sync"', 'name = "synthetic_local"\n    uses_network = False'))
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    monkeypatch.setattr(presets, "scene_available", lambda scene: scene == "toy")
    configs, _, record = presets.expand("compare", methods="synthetic_local", matrix_file=TINY)
    assert sorted((c["variant"], c["net"], c["protocol"]) for c in configs) == [
        ("default", "ideal", "tcp"), ("dim", "ideal", "tcp")]
    assert record["skipped_scenes"] == ["missing_scene"]


@pytest.mark.parametrize("text, message", [
    ('[presets.compare]\nnets = ["lte"]\n', "may only name variants, set, backend, scenes"),
    ('[presets.compare]\nvariants = []\n', "non-empty list"),
])
def test_a_method_may_name_only_its_variants_set_backend_and_scenes(fake_core, tmp_path, monkeypatch, text, message,
                                                                   fake_method_copy):
    root = tmp_path / "methods"
    fake_method_copy(root, "synthetic_async", lambda cfg: cfg.split("[presets.compare]")[0] + text)
    monkeypatch.setenv("SPLITBENCH_METHOD_PATHS", str(root))
    monkeypatch.setattr(presets, "scene_available", lambda scene: True)
    _, problems, _ = presets.expand("compare", methods="synthetic_async", matrix_file=TINY)
    assert any(message in p for p in problems), problems


def test_a_malformed_shared_matrix_is_a_user_error(tmp_path):
    bad = tmp_path / "m.toml"
    bad.write_text('[compare]\nresolution = "16x8"\nspeed = 3\ncells = [{scenes = ["toy"]}]\n')
    with pytest.raises(UserError, match="unknown setting 'speed'"):
        presets.shared_matrix("compare", bad)
    bad.write_text('[compare]\n[[compare.cells]]\nscenes = ["toy"]\nnets = ["lte"]\n')
    with pytest.raises(UserError, match="needs non-empty lists scenes, nets, protocols"):
        presets.shared_matrix("compare", bad)


# ------------------------------------------------------------------------------------------- metric registry

def test_times_name_their_source_the_measuring_device_or_the_work_model():
    host = {"machine": "x86_64", "cpu_count": 2, "node": "vm"}
    measured = {"config": {"clock": "measured"}, "backend": {"name": "embree"}, "host": host}
    work = {"config": {"clock": "work", "work_ns_per_ray": 50.0}, "backend": {"name": "embree"}, "host": host}
    assert compare.device_text(measured) == "embree · CPU x86_64, 2 cores (vm)"
    assert compare.device_text(work).startswith("work clock (modelled: 50 ns/ray, 20 ns/pixel")


def test_every_registered_metric_states_its_direction_description_and_kind():
    assert {"error", "error_global", "error_direct", "error_zero_latency", "error_floor", "frame_ms_p50",
            "frame_ms_p95", "latency_ms_p95", "bandwidth_mbps", "server_ms", "client_ms", "rays_per_frame",
            "bytes_per_frame", "dssim", "flip", "psnr_db"} <= set(mr.METRICS)
    for m in mr.METRICS.values():
        assert m.better in (mr.HIGHER, mr.LOWER) and m.description and m.kind in ("quality", "time", "network", "work")
    with pytest.raises(ValueError, match="already registered"):
        mr.register(mr.Metric("error", lambda s: 0.0, mr.LOWER, "again"))
    with pytest.raises(ValueError, match="better must be"):
        mr.Metric("x", lambda s: 0.0, "smaller", "x")


def test_the_own_transport_error_follows_the_methods_light_transport():
    stats = {"rel_mse": {"mean": 0.3}, "direct_rel_mse": {"mean": 0.1}}
    assert mr.get("error")({"light_transport": "direct", "stats": stats}) == 0.1
    assert mr.get("error")({"light_transport": "global", "stats": stats}) == 0.3
    assert np.isnan(mr.get("error_zero_latency")({"stats": stats}))  # missing values are NaN, not errors


def test_the_pareto_front_excludes_dominated_points():
    # (bandwidth, error): C is dominated by B (more bandwidth, more error); D is NaN; E ties A exactly.
    bandwidth = [1.0, 2.0, 3.0, np.nan, 1.0, 0.5]
    error = [0.5, 0.2, 0.3, 0.1, 0.5, 0.9]
    assert list(mr.pareto_front(bandwidth, error)) == [True, True, False, False, True, True]
    # higher-is-better flips the comparison: with PSNR (higher better) F's 0.9 is the best on y
    assert list(mr.pareto_front(bandwidth, error, y_better=mr.HIGHER)) == [False, False, False, False, False, True]


def test_best_under_budget_picks_the_best_quality_within_the_budget():
    df = pd.DataFrame({"entry": ["a", "b", "c"], "error_global": [0.1, 0.2, 0.05],
                       "frame_ms_p95": [50.0, 20.0, 40.0]})
    assert mr.best_under_budget(df, "error_global", "frame_ms_p95", 33.3)["entry"] == "b"
    assert mr.best_under_budget(df, "error_global", "frame_ms_p95", 45.0)["entry"] == "c"
    assert mr.best_under_budget(df, "error_global", "frame_ms_p95", 10.0) is None


# ---------------------------------------------------------------------------------------------------- report

CLAIMS_REPORT = '''
from suite.harness import verdicts
from suite.harness.reporting import SectionFiles


def section(results_df, run_dirs, out_dir=None):
    claim = verdicts.judge("{name}-1", "{name} claim", "Table 1", 10.0, 10.5, "ms", verdicts.Tolerance(relative=0.1),
                           setting={{"scene": "toy"}}, method="{name}")
    return "<p>ok</p>" + SectionFiles(out_dir, "{name}").json([claim.as_dict()], "claims.json")
'''


def _harness_conftest():
    """This folder's conftest as a module (a module-scoped fixture cannot use the function-scoped fake_core)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("harness_conftest", HERE / "conftest.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def compare_results(tmp_path_factory):
    """The tiny compare matrix run serially by ``reproduce`` (once for the module), with two methods whose sections
    store a claim."""
    conftest = _harness_conftest()
    tmp_path = tmp_path_factory.mktemp("compare")
    root = tmp_path / "methods"
    for name in ("synthetic_sync", "synthetic_async"):
        # no interruption here: no sleep
        folder = conftest.copy_fake_method(root, name, lambda cfg: cfg.replace("work_ms = 60.0", "work_ms = 0.0"))
        (folder / "report.py").write_text(CLAIMS_REPORT.format(name=name))
    with open(root / "synthetic_sync" / "method.py", "a") as f:  # a method that leaves part of the scene out
        f.write("\nSyntheticSync.omissions = lambda self, scene: ['its fill light is left out']\n")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SPLITBENCH_METHOD_PATHS", str(root))
        conftest.install_fake_core(mp.setattr)
        mp.setattr(presets, "scene_available", lambda scene: scene == "toy")
        assert cli.main(["reproduce", "--preset", "compare", "--matrix", str(TINY), "--methods", SYNTHETIC,
                         "--out", str(tmp_path / "res"), "--report", str(tmp_path / "rep")]) == 0
        yield tmp_path


def test_the_report_builds_from_stored_results_only_and_opens_with_the_answer(compare_results, fake_core, tmp_path,
                                                                              monkeypatch):
    def no_rendering(*args, **kwargs):
        raise AssertionError("the report must not render or run anything")

    for hook in ("reference_set", "reference_image", "execute", "simulate", "compare_images"):
        monkeypatch.setattr(fake_core, hook, no_rendering)
    monkeypatch.setattr(executor, "run_one", no_rendering)
    page = report.build(compare_results / "res", tmp_path / "again").read_text()
    headings = re.findall(r"<h2[^>]*>([^<]*)", page)
    assert headings[0].startswith("The answer")
    answer = page[page.index("The answer"):page.index("<h2", page.index("The answer"))]
    # one row per network profile and protocol of the matrix, each naming a winner
    for net in ("bw=8mbps,delay=5ms", "bw=2mbps,delay=20ms"):
        assert answer.count(f"<td>{net}</td>") >= 2
    assert "missing_scene" in answer  # the skipped scene is recorded where the answer is
    assert "synthetic_sync on toy: its fill light is left out" in answer  # and what a method does not render
    assert "Pareto fronts" in headings[1] and list((tmp_path / "again" / "compare").glob("pareto_*.png"))
    assert "noise floors" in headings[2]
    runs = pd.read_csv(tmp_path / "again" / "compare" / "compare_runs.csv")
    assert {"error_global", "error_direct", "error_zero_latency", "error_floor"} <= set(runs.columns)


def test_the_claims_table_gathers_the_claims_of_every_method_report(compare_results):
    page = (compare_results / "rep" / "index.html").read_text()
    claims = page[page.index("id='claims'"):]
    claims = claims[:claims.index("<h2")]
    assert "synthetic_sync claim" in claims and "synthetic_async claim" in claims
    assert claims.count("reproduces") >= 2
    table = pd.read_csv(compare_results / "rep" / "claims.csv")
    assert sorted(table["id"]) == ["synthetic_async-1", "synthetic_sync-1"]


def test_each_method_gets_a_page_with_labelled_image_columns(compare_results):
    page = (compare_results / "rep" / "method-synthetic_sync.html").read_text()
    for column in ("method (networked)", "its zero-latency run", "own light transport", "|method − own reference|"):
        assert column in page
    assert "synthetic_sync (baseline)" in page
