"""``splitbench bench visibility_bitmap``: its parts on a tiny case, the stored document the report reads, the
linear fit, and the CLI hook."""
import json

import numpy as np
import pytest

from methods.visibility_bitmap import bench
from suite.core.trace import backend_params

TINY = ["--scene", "living_room", "--lights-scene", "living_room", "--resolution", "32x18", "--repeats", "1",
        "--linearity-resolutions", "16x9,32x18,48x27", "--linearity-lights", "1,2,3", "--linearity-repeats", "1",
        "--codec-resolutions", "32x18", "--codecs", "none,lz4", "--frames", "2", "--light-counts", "1,3",
        "--lights-resolution", "16x9"]


def test01_fit_line_recovers_an_exact_line_and_scores_noise_lower():
    x = np.array([1.0, 2.0, 4.0, 8.0])
    fit = bench.fit_line(x, 3.0 * x + 2.0)
    assert fit["slope"] == pytest.approx(3.0) and fit["intercept"] == pytest.approx(2.0)
    assert fit["r2"] == pytest.approx(1.0)
    assert bench.fit_line(x, [5.0, 1.0, 9.0, 2.0])["r2"] < 0.5


def test02_every_part_runs_on_a_tiny_case_and_is_stored_for_the_report(tmp_path, capsys):
    assert bench.main(TINY + ["--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "ratio" in printed and "R²" in printed and "stored:" in printed
    doc = json.loads((tmp_path / "bench" / "visibility_bitmap.json").read_text())
    assert doc == bench.load(tmp_path) and doc["schema_version"] == bench.SCHEMA_VERSION
    assert {r["backend"] for r in doc["codecs"] + doc["lights"]} == {"embree"}
    t = doc["throughput"]
    assert t["rays"] > 0 and t["ratio"] == pytest.approx(t["stage_rays_per_s"] / t["raw_rays_per_s"])
    # one repeat's ratio, lowest and highest (its stage and raw calls ran next to each other), around the ratio of
    # the medians (up to the last bits: the two are computed in different orders)
    lo, hi = t["ratio_range"]
    assert lo * (1 - 1e-9) <= t["ratio"] <= hi * (1 + 1e-9)
    lin = doc["linearity"]
    assert len(lin["points"]) == 9 and {p["pixel_lights"] for p in lin["points"]} >= {16 * 9, 48 * 27 * 3}
    assert set(lin["fit"]) == {"visibility_ms", "server_ms"}
    assert all(f["r2"] <= 1.0 for f in lin["fit"].values())
    # seed 000 §3.2: 4 bytes per pixel whatever the light count
    raw = [r for r in doc["codecs"] if r["layout"] == "paper32" and r["codec"] == "none"][0]
    assert raw["raw_bytes"] / raw["frames"] == 32 * 18 * 4 and raw["bit_exact"]
    packed = {r["light_count"]: r["raw_bytes_per_frame"] for r in doc["lights"]
              if r["layout"] == "packed8" and r["codec"] == "none"}
    assert packed == {1: 16 * 9, 3: 16 * 9}


def test03_a_part_that_runs_again_replaces_only_its_own_entry(tmp_path):
    bench.store(tmp_path, {"throughput": {"ratio": 0.5}, "linearity": {"fit": {}}})
    bench.store(tmp_path, {"throughput": {"ratio": 0.7}})
    doc = bench.load(tmp_path)
    assert doc["throughput"] == {"ratio": 0.7} and doc["linearity"] == {"fit": {}}


def test04_cli_runs_the_method_bench_and_refuses_unknown_parts(tmp_path, capsys):
    from suite.harness import cli

    code = cli.main(["bench", "visibility_bitmap", "--parts", "lights", "--lights-scene", "living_room",
                     "--light-counts", "2", "--lights-resolution", "16x9", "--frames", "1", "--out", str(tmp_path),
                     "--json"])
    out = capsys.readouterr().out
    assert code == 0 and json.loads(out)["lights"][0]["light_count"] == 2
    code = cli.main(["bench", "visibility_bitmap", "--parts", "speed"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "unknown benchmark part 'speed'" in err
    code = cli.main(["bench", "no_such_method"])
    err = capsys.readouterr().err
    assert code == 2 and "unknown benchmark 'no_such_method'" in err and "visibility_bitmap" in err


def test05_a_stored_benchmark_records_the_environment_a_run_records(tmp_path):
    from suite.harness import results

    bench.store(tmp_path, {"throughput": {"ratio": 0.5}})
    doc = bench.load(tmp_path)
    env = results.environment()
    # the same keys and facts as a run's config.json: package versions, host, git commit
    assert doc["packages"] == env["packages"] and doc["host"] == env["host"] and doc["git"] == env["git"]
    assert not list(tmp_path.glob("bench/.*"))  # written atomically: no temporary file left behind


def test06_the_tracing_benchmark_prints_the_environment_with_its_figures(capsys, monkeypatch):
    import sys
    import types

    from suite.harness import cli, results, runner

    fake = types.ModuleType("suite.core.trace.bench")
    rates = {"suite_rays_per_s": 2.0e6, "raw_rays_per_s": 4.0e6, "ratio": 0.5}
    fake.run = lambda scene, backend, **kwargs: {"scene": "toy", "rays": 1000, "repeats": 5, "occluded": rates,
                                                 "intersect": rates}
    monkeypatch.setitem(sys.modules, "suite.core.trace.bench", fake)
    monkeypatch.setattr(runner, "backend_names", lambda: ["fake"])
    monkeypatch.setattr(runner, "scene_names", lambda: ["toy"])
    monkeypatch.setattr(runner, "load_scene", lambda spec: None)
    assert cli.main(["bench", "tracing", "--scene", "toy", "--backend", "fake", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["occluded"]["ratio"] == 0.5 and doc["git"] == results.environment()["git"]
    assert set(doc["packages"]) == set(results.PACKAGES) and doc["host"]["node"]


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
def test07_device_throughput_compares_the_pass_with_device_resident_raw_rays(backend):
    """On Mitsuba the pass runs on the device and raw is ray_test on the very rays it traced, held in device
    memory; the numpy-fed rate of the same rays is reported beside it."""
    from suite.core.scene import load
    from suite.core.trace import make

    scene = load("living_room")
    tracer = make(backend, scene)
    r = bench.throughput(scene, tracer, (32, 18), repeats=1)
    assert r["path"].startswith("device") and r["raw"] == "device-resident rays"
    assert r["rays"] > 0
    assert r["ratio"] == pytest.approx(r["stage_rays_per_s"] / r["raw_rays_per_s"])
    assert r["numpy_raw_ratio"] == pytest.approx(r["numpy_raw_rays_per_s"] / r["raw_rays_per_s"])
    assert "raw fed from numpy" in bench.format_results({"throughput": dict(r, backend=backend)})
