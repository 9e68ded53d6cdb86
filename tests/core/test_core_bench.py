"""``splitbench bench tracing`` and ``splitbench bench core`` on tiny cases: what they measure, the raw baselines
(device-resident Dr.Jit rays for Mitsuba, numpy for Embree), the per-stage table and the stored document."""
import json

import pytest

from suite.core.scene import load
from suite.core.trace import backend_params
from suite.core.trace import bench

BACKENDS = backend_params("embree", "mitsuba-llvm", "mitsuba-cuda")


@pytest.mark.parametrize("backend", BACKENDS)
def test01_tracing_bench_compares_suite_and_raw_on_the_backends_own_memory(backend):
    out = bench.run(load("living_room"), backend, max_rays=20_000, repeats=1, resolution=(160, 90))
    assert out["rays"] == 20_000 and out["scene"] == "living_room"
    for query in ("occluded", "intersect"):
        q = out[query]
        assert q["ratio"] == pytest.approx(q["suite_rays_per_s"] / q["raw_rays_per_s"])
        if backend == "embree":
            assert out["interface"] == "numpy" and "numpy" not in q
        else:  # Mitsuba: the headline is device-resident; the numpy-fed rates are reported beside it
            assert out["interface"].startswith("device")
            n = q["numpy"]
            assert n["suite_of_device_raw"] == pytest.approx(n["suite_rays_per_s"] / q["raw_rays_per_s"])
            # device time alone, beside the wall time of a call (which adds the host's tracing and launch)
            assert q["suite_kernel_ms"] > 0 and q["raw_kernel_ms"] > 0
            assert q["kernel_ratio"] == pytest.approx(q["raw_kernel_ms"] / q["suite_kernel_ms"])
            assert q["ratio"] == pytest.approx(q["raw_ms"] / q["suite_ms"])


@pytest.mark.parametrize("backend", BACKENDS)
def test01b_every_ratio_of_medians_comes_with_the_range_of_its_paired_repeats(backend):
    """One repeat's ratio (its two calls ran next to each other), lowest and highest: the ratio of the medians lies
    between them, as it must for any paired samples (up to the last bits: the two are computed in different
    orders)."""
    out = bench.run(load("cornell"), backend, max_rays=20_000, repeats=5, resolution=(160, 90))
    for query in ("occluded", "intersect"):
        lo, hi = out[query]["ratio_range"]
        assert 0 < lo * (1 - 1e-9) <= out[query]["ratio"] <= hi * (1 + 1e-9)
    core = bench.core(load("cornell"), backend, (32, 18), repeats=3, area_samples=1)
    for key in ("gbuffer_over_raw_intersect", "visibility_raw_over_pass"):
        if key in core:
            lo, hi = core[key + "_range"]
            assert 0 < lo * (1 - 1e-9) <= core[key] <= hi * (1 + 1e-9)


def test01c_paired_range_takes_each_repeat_as_a_pair():
    times = bench.interleaved_times([("a", lambda: None), ("b", lambda: None)], 4)
    assert [len(v) for v in times.values()] == [4, 4]
    # pairs (num[i], den[i]), not the spread of each side: 2/1, 4/4, 6/3 -> 1..2 (sorted sides would give 2/1..6/4)
    assert bench.paired_range([2.0, 4.0, 6.0], [1.0, 4.0, 3.0]) == [1.0, 2.0]
    assert bench.paired_range([1.0, 2.0], [2.0, 2.0], scale=3.0) == [1.5, 3.0]
    from suite.harness.reporting import lo_hi_text, range_text

    assert range_text([0.81234, 0.9]) == " (repeats 0.812-0.900)" and range_text(None) == ""
    assert lo_hi_text([0.5, 1.25], 2) == "0.50-1.25" and lo_hi_text(float("nan")) == ""
    with pytest.raises(ValueError, match="paired"):
        bench.paired_range([1.0, 2.0], [1.0])


@pytest.mark.parametrize("backend", BACKENDS)
def test02_core_bench_reports_every_stage_with_rays_pixels_and_copy_bytes(backend):
    out = bench.core(load("atrium"), backend, (32, 18), repeats=1, area_samples=2)
    stages = {s["stage"]: s for s in out["stages"]}
    pixels = 32 * 18
    assert {"camera_rays", "trace", "gbuffer", "raw_intersect", "visibility", "shading", "area_lights"} <= set(stages)
    assert all(s["pixels"] == pixels and s["ms"] >= 0 for s in stages.values())
    assert stages["trace"]["rays"] == pixels and stages["gbuffer"]["rays"] >= pixels
    assert stages["visibility"]["rays"] > 0 and stages["area_lights"]["rays"] > 0
    assert out["gbuffer_over_raw_intersect"] == pytest.approx(stages["gbuffer"]["ms"] / stages["raw_intersect"]["ms"])
    if backend != "embree":
        assert out["visibility_raw_over_pass"] == pytest.approx(stages["raw_occluded"]["ms"] / stages["visibility"]["ms"])
        assert stages["copy_image_to_host"]["bytes"] == pixels * 12
        assert stages["copy_gbuffer_to_host"]["bytes"] > pixels * 24
        assert out["device_counters"]["bytes_to_host"] > 0
        for name in ("gbuffer", "raw_intersect", "visibility", "raw_occluded"):
            assert stages[name]["kernel_ms"] > 0
        assert out["gbuffer_over_raw_intersect_kernels"] == pytest.approx(
            stages["gbuffer"]["kernel_ms"] / stages["raw_intersect"]["kernel_ms"])


@pytest.mark.parametrize("backend", backend_params("mitsuba-llvm", "mitsuba-cuda"))
def test02b_kernel_time_counts_the_device_work_a_call_launches(backend):
    """``Device.kernel_ms``: zero for a call that launches nothing; for a query, its kernels' time, which grows with
    the rays traced."""
    from suite.core.trace import make

    scene = load("living_room")
    dev = make(backend, scene).device
    o, d, tmax = bench.shadow_rays(scene, (320, 180))  # about 120,000 rays: a thousand times the small batch
    small, large = (dev.raw_ray(*[dev.to_device(a[:n], t) for a, t in ((o, dev.Point3f), (d, dev.Vector3f),
                                                                         (tmax, dev.Float))])
                    for n in (100, len(o)))
    assert dev.kernel_ms(lambda: None) == 0.0
    assert 0.0 < dev.kernel_ms(lambda: dev.raw_occluded(small), 5) < dev.kernel_ms(lambda: dev.raw_occluded(large), 5)


def test03_cli_runs_and_stores_both_benches(tmp_path, capsys):
    from suite.harness import cli

    assert cli.main(["bench", "core", "--scene", "living_room", "--backend", "embree,mitsuba-llvm", "--resolution",
                     "24x14", "--repeats", "1", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "G-buffer / raw intersect" in text and "stored:" in text
    doc = json.loads((tmp_path / "bench" / "core.json").read_text())
    assert [r["backend"] for r in doc["results"]] == ["embree", "mitsuba-llvm"] and doc["git"]
    assert cli.main(["bench", "tracing", "--scene", "cornell,living_room", "--backend", "embree", "--repeats", "1",
                     "--out", str(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["scene"] for r in doc["results"]] == ["cornell", "living_room"]
    assert json.loads((tmp_path / "bench" / "tracing.json").read_text())["results"][0]["backend"] == "embree"
    assert cli.main(["bench", "core", "--backend", "optix"]) == 2
    assert "unknown backend 'optix'" in capsys.readouterr().err
