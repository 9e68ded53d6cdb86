"""``splitbench bench quake_drt`` runs every part on a small scene and stores one document the report reads. The
tests check its structure and its work counters (rays, shadow rays, filter taps), which do not depend on the
machine; wall times are only checked to be recorded."""
import json
import math

import pytest

from methods.quake_drt import bench
from suite.core.trace import backend_params, device_backends


def test01_every_part_runs_and_is_stored_with_its_work_counters(tmp_path, capsys):
    rc = bench.main(["--scene", "two_rooms", "--resolution", "48x27", "--resolutions", "32x18,48x27",
                     "--rays-larger", "64x36", "--repeats", "1", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "bench" / "quake_drt.json").read_text())
    assert {"rays", "asvgf", "lights", "packages", "host"} <= set(doc)
    r = doc["rays"]
    assert r["direct"]["rays"] == r["direct"]["raw_rays"] > 0 and r["primary"]["rays"] > 0
    # every shadow ray is one light sample; the samples below a point's horizon (the ceiling's, under its room's
    # lights) trace none
    assert r["direct"]["light_samples"] > r["direct"]["shadow_rays"] == r["direct"]["raw_rays"]
    # two_rooms has no mirror or glass: the secondary stage is measured on the gallery, and says so
    sec = r["secondary"]
    assert sec["scene"] == bench.SECONDARY_SCENE and sec["specular_pixels"] > 0
    assert sec["raw_rays"] == sum(sec["rays_per_depth"]) > 0 and sec["rays"] >= sec["raw_rays"]
    assert math.isfinite(sec["ratio"]) and sec["ratio"] > 0
    # each ratio with one repeat's lowest and highest (the stage and raw calls that ran next to each other)
    for st in ("primary", "secondary", "direct"):
        lo, hi = r[st]["ratio_range"]
        assert 0 < lo * (1 - 1e-9) <= r[st]["ratio"] <= hi * (1 + 1e-9)  # up to the last bits
    # the short stages take at least SHORT_STAGE_REPEATS calls; the direct stage the --repeats asked for
    assert r["primary"]["repeats"] == sec["repeats"] == bench.SHORT_STAGE_REPEATS and r["direct"]["repeats"] == 1
    # by pixels: this size's ratios, then the --rays-larger sizes'
    small, larger = r["by_pixels"]
    assert small["resolution"] == [48, 27] and larger["resolution"] == [64, 36]
    assert small["primary_ratio"] == r["primary"]["ratio"] and small["secondary_ratio"] == sec["ratio"]
    assert all(math.isfinite(row[f"{st}_ratio"]) and row[f"{st}_ms"] > 0 for row in (small, larger)
               for st in ("primary", "secondary", "direct"))
    # part rays again on each Dr.Jit backend that works here (mitsuba-llvm on every machine the suite installs on)
    assert [row["backend"] for row in r["on_devices"]] == device_backends()
    for row in r["on_devices"]:
        assert row["resolution"] == [48, 27]
        assert all(math.isfinite(row[f"{st}_{k}"]) and row[f"{st}_ms"] > 0 for st in ("primary", "secondary", "direct")
                   for k in ("ratio", "ratio_numpy"))
    rows = {row["case"]: row for row in doc["lights"]["rows"]}
    assert rows["culled, all of the row"]["shadow_rays"] < rows["all lights, no culling"]["shadow_rays"]
    assert rows["culled, k = 1"]["shaded_per_point"] == 1.0
    assert rows["culled, k = 16"]["shadow_rays"] >= rows["culled, k = 4"]["shadow_rays"]
    small, large = doc["asvgf"]["rows"]
    stages = ("gradient", "gradient_atrous", "temporal", "variance", "atrous", "taa")
    for row in (small, large):
        assert all(math.isfinite(row[f"{s}_ms"]) and row[f"{s}_ms"] >= 0 for s in stages)
        # the spatial a-trous: 5 passes of a 3x3 kernel per pixel; TAA: 9 + 9 + 16 taps per pixel
        pixels = row["resolution"][0] * row["resolution"][1]
        assert row["atrous_taps"] == pixels * 9 * 5 and row["taa_taps"] == pixels * 34
        assert row["denoiser_taps"] == sum(row[f"{s}_taps"] for s in stages if s != "taa")
    assert large["denoiser_taps"] > small["denoiser_taps"]
    assert "A-SVGF" in capsys.readouterr().out
    # a second run of one part keeps the others
    bench.main(["--scene", "two_rooms", "--parts", "rays", "--resolution", "32x18", "--rays-larger", "",
                "--repeats", "1", "--out", str(tmp_path)])
    doc2 = json.loads((tmp_path / "bench" / "quake_drt.json").read_text())
    assert doc2["asvgf"] == doc["asvgf"] and doc2["rays"]["resolution"] == [32, 18]


def test02_the_fit_through_the_origin_is_a_rate_per_megapixel():
    fit = bench.fit_ms_per_mp([1.0, 2.0], [10.0, 20.0])
    assert fit["ms_per_mp"] == pytest.approx(10.0) and fit["r2"] == pytest.approx(1.0)
    assert fit["exponent"] == pytest.approx(1.0)
    # two noisy sizes where the larger one happened to run faster: an affine fit's slope would be negative
    noisy = bench.fit_ms_per_mp([0.01, 0.02], [30.0, 25.0])
    assert noisy["ms_per_mp"] > 0 and noisy["exponent"] < 0
    assert bench.fit_ms_per_mp([0.01], [3.0]) == {} and bench.fit_ms_per_mp([0.01, 0.02], [0.0, 1.0]) == {}


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
def test03_on_a_drjit_backend_raw_is_the_backend_on_device_resident_rays(backend):
    """Issue 9's raw: on a Mitsuba llvm/cuda backend each stage is compared with the backend on its rays in device
    memory; the numpy-fed raw entry points are timed beside it."""
    from suite.harness import runner

    scene = bench.load_scene("two_rooms")
    tracer = runner.make_tracer(backend, scene)
    r = bench.bench_rays(scene, tracer, (48, 27), 0.5, 1, backend)
    for stage in ("primary", "direct", "secondary"):
        s = r[stage]
        assert s["raw"] == "device-resident rays" and s["raw_ms"] > 0 and s["raw_numpy_ms"] > 0, stage
        assert math.isfinite(s["ratio"]) and math.isfinite(s["ratio_numpy"]) and s["raw_rays"] > 0, stage
    assert r["direct"]["rays"] == r["direct"]["raw_rays"]
    assert "numpy-fed raw" in bench.format_results({"rays": {**r, "backend": backend}})
