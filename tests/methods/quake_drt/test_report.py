"""The report section "Seed 001 — quake_drt" builds from stored results only (frames, config.json, the bench
document), states scene and backend of every table, and gives each claim the verdict kind that fits: one-sided
claims against their bound, the spp cost by construction, GPU timings not measurable."""
import json

import numpy as np
import pandas as pd
import pytest

from methods.quake_drt import report
from suite.harness import verdicts

SCENE, RES = "oa:aggressor@pak1-maps", "320x180"
PIXELS = 320 * 180
PRIMARY_RAYS = 2 * PIXELS


def _work_ms(shadow, spp=1, denoiser=False):
    return 1e-6 * (50 * spp * (shadow + PRIMARY_RAYS) + 20 * 3 * PIXELS + 2 * (8_000_000 if denoiser else 0))


def _run(root, variant, frames, frame_ms, rays, k=1, spp=1, gt=None, cull=True, denoiser=True, taa=True,
         extra=None, placement="local", net="ideal"):
    name = f"quake_drt-{variant}-k{k}-s{spp}-f{frames}-{net}"
    d = root / name
    d.mkdir(parents=True)
    params = {"num_random_dl": k, "spp": spp, "cull_lights": cull, "denoiser": denoiser, "taa": taa,
              "gt_frames": 64 if gt else 0, "placement": placement}
    (d / "config.json").write_text(json.dumps({"config": {"backend": "embree", "params": params}}))
    rows = []
    for i in range(frames):
        shadow = rays[i] if isinstance(rays, list) else rays
        row = {"run": name, "method": "quake_drt", "variant": variant, "scene": SCENE, "resolution": RES,
               "net": net, "protocol": "udp" if net != "ideal" else "tcp",
               "frames": frames, "frame": i, "frame_ms": frame_ms[i] if isinstance(frame_ms, list) else frame_ms,
               "ssim": np.nan, "info_shadow_rays": shadow, "rays": spp * (shadow + PRIMARY_RAYS),
               "pixels": 3 * PIXELS, "work_taps": 8_000_000 if denoiser else 0, "work_points": 0,
               "info_candidates_per_point": 50.0, "info_audit_pairs": 1000, "info_audit_missed": 0,
               "info_audit_missed_energy": 0.0, "stage_primary_ms": 100.0, "stage_direct_ms": 50.0}
        if gt and i == frames - 1:
            row.update({f"info_{k}": v for k, v in gt.items()})
        row.update(extra or {})
        rows.append(row)
    return d, rows


@pytest.fixture
def stored(tmp_path):
    runs = [
        _run(tmp_path, "no_culling", 4, 3000.0, 12_000_000, k=0, cull=False, denoiser=False, taa=False),
        _run(tmp_path, "all_lights", 4, 1200.0, 4_000_000, k=0, denoiser=False, taa=False),
        _run(tmp_path, "one_light", 8, 200.0, 40_000, gt={"gt_ssim": 0.30}, denoiser=False, taa=False),
        _run(tmp_path, "one_light", 8, 260.0, 100_000, k=4, gt={"gt_ssim": 0.55}, denoiser=False, taa=False),
        _run(tmp_path, "one_light", 8, 300.0, 600_000, k=16, gt={"gt_ssim": 0.75}, denoiser=False, taa=False),
        _run(tmp_path, "one_light", 8, 800.0, 160_000, spp=4, gt={"gt_ssim": 0.55}, denoiser=False, taa=False),
        _run(tmp_path, "denoiser_no_taa", 8, 600.0, 40_000,
             gt={"gt_ssim": 0.80, "detail_near": 0.9, "detail_far": 0.5}, taa=False),
        _run(tmp_path, "default", 8, 700.0, 40_000, gt={"gt_ssim": 0.84}),
        _run(tmp_path, "default", 8, 760.0, 160_000, k=4, gt={"gt_ssim": 0.85}),
        _run(tmp_path, "all_lights_taa", 8, 1300.0, 4_000_000, k=0, gt={"gt_ssim": 0.86}, denoiser=False),
        _run(tmp_path, "denoised_no_culling", 8, 650.0, 40_000, gt={"gt_ssim": 0.70}, cull=False, taa=False),
        _run(tmp_path, "all_lights", 30, [1200.0 + 400 * np.sin(i) for i in range(30)],
             [4_000_000 + 2_000_000 * (i % 3) for i in range(30)], k=0, denoiser=False, taa=False),
        _run(tmp_path, "default", 30, 700.0, [40_000 + 100 * (i % 2) for i in range(30)]),
    ]
    frames = pd.DataFrame([r for _, rows in runs for r in rows])
    bench = {"asvgf": {"scene": SCENE, "backend": "embree", "repeats": 3, "fit": {"ms_per_mp": 6000.0,
             "r2": 0.999, "exponent": 0.95},
             "rows": [{"resolution": [160, 90], "megapixels": 0.0144, "denoiser_ms": 99.0}]}}
    def stage(ratio, **kw):
        return {"rays": 1000, "ms": 2.0, "rays_per_s": 5e5, "raw_rays_per_s": 5e5 * ratio, "ratio": ratio,
                "repeats": 11, **kw}

    bench["rays"] = {"scene": SCENE, "backend": "embree", "resolution": [320, 180], "repeats": 3, "settings": "s",
                     "primary": stage(0.91, ratio_range=[0.87, 0.95]), "secondary": stage(0.6, scene="gallery"),
                     "direct": stage(0.99, shadow_rays=1000, light_samples=1600),
                     "by_pixels": [{"resolution": [320, 180], "primary_ms": 2.0, "primary_ratio": 0.91},
                                   {"resolution": [640, 360], "primary_ms": 7.5, "primary_ratio": 0.93}],
                     "on_devices": [{"backend": "mitsuba-llvm", "resolution": [320, 180], "direct_ms": 212.0,
                                     "direct_ratio": 0.5, "direct_ratio_numpy": 0.56},
                                    {"backend": "mitsuba-cuda", "cuda_error": "RuntimeError: no GPU"}]}
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "quake_drt.json").write_text(json.dumps(bench))
    return frames, [d for d, _ in runs], tmp_path


def test01_claims_get_the_verdict_kind_that_fits(stored):
    frames, dirs, root = stored
    found = {c.id: c for c in report.claims(report.prepare(frames, dirs), report.load_bench("quake_drt", dirs, root))}
    assert found["001.culling_speedup"].kind == verdicts.REPRODUCES  # 12 M against 4 M shadow rays
    assert found["001.culling_speedup"].suite_value == pytest.approx(_work_ms(12e6) / _work_ms(4e6))
    assert found["001.culling_exact"].kind == verdicts.REPRODUCES
    assert found["001.spp4_cost"].kind == verdicts.BY_CONSTRUCTION
    assert found["001.light_samples_cost"].kind == verdicts.DOES_NOT_REPRODUCE  # ~1.3x against 3x +- 50 %
    assert found["001.light_samples_cost"].suite_value == pytest.approx(_work_ms(100_000) / _work_ms(40_000))
    assert found["001.light_vs_traditional"].kind == verdicts.REPRODUCES  # 4 spp ~3.7x > 4 lights ~1.3x
    assert found["001.samples_raise_quality"].kind == verdicts.REPRODUCES
    assert found["001.denoised_samples_equal"].kind == verdicts.REPRODUCES  # 0.85 vs 0.84
    assert found["001.all_lights_taa_vs_denoiser"].kind == verdicts.REPRODUCES  # 0.86 >= 0.80 - 0.02
    assert found["001.taa_improves_denoiser"].kind == verdicts.REPRODUCES
    assert found["001.culling_helps_denoiser"].kind == verdicts.REPRODUCES
    assert found["001.far_shadows_lose_detail"].kind == verdicts.REPRODUCES
    assert found["001.frame_time_spikes"].kind == verdicts.REPRODUCES
    assert found["001.one_light_denoiser_faster"].kind == verdicts.REPRODUCES
    assert found["001.denoiser_linear"].kind == verdicts.BY_CONSTRUCTION
    assert found["001.denoiser_2ms"].kind == verdicts.NOT_MEASURABLE
    assert all(c.setting.get("scene") for c in found.values() if c.kind != verdicts.NOT_MEASURABLE)


def test02_a_bound_that_is_missed_does_not_reproduce(stored):
    frames, dirs, root = stored
    no_cull = frames["variant"] == "no_culling"
    frames.loc[no_cull, "rays"] = 5_000_000 + PRIMARY_RAYS  # culling only saves a fifth of the rays
    found = {c.id: c for c in report.claims(report.prepare(frames, dirs))}
    c = found["001.culling_speedup"]
    assert c.kind == verdicts.DOES_NOT_REPRODUCE and "short by" in c.explanation


def test03_the_section_builds_from_stored_results_and_writes_its_files(stored, tmp_path):
    frames, dirs, root = stored
    out = tmp_path / "report"
    html = report.section(frames, dirs, out_dir=out, results_root=root)
    assert "Seed 001" in html and "001.culling_speedup" in html and f"Scene {SCENE}, backend embree" in html
    claims = json.loads((out / "quake_drt" / "claims.json").read_text())
    assert {c["id"] for c in claims} >= {"001.culling_speedup", "001.denoiser_2ms"}
    assert (out / "quake_drt" / "bench_asvgf.csv").is_file()
    assert ("met by primary (0.910; repeats 0.870-0.950, on both sides of the goal), direct (0.990); not met by "
            "secondary (0.600)") in html
    rays_csv = (out / "quake_drt" / "bench_rays.csv").read_text()
    assert "repeats' range" in rays_csv.splitlines()[0] and "0.870-0.950" in rays_csv  # one repeat, lowest and highest
    assert "evaluated 1,600 light samples for its 1,000 shadow rays" in html  # the work raw does not do
    by_pixels = (out / "quake_drt" / "bench_rays_by_pixels.csv").read_text()
    assert by_pixels.splitlines()[0] == "resolution,primary_ratio,primary_ms" and "640x360" in by_pixels
    assert (out / "quake_drt" / "bench_rays.csv").is_file()
    # the stages on each Dr.Jit backend beside the bench's own, a failed one with its error
    on_devices = (out / "quake_drt" / "bench_rays_on_devices.csv").read_text()
    assert "mitsuba-llvm" in on_devices and "212.0" in on_devices and "RuntimeError: no GPU" in on_devices
    assert "on each Dr.Jit backend" in html


def test04_no_runs_no_bench_still_builds_and_every_claim_keeps_its_row(tmp_path):
    html = report.section(pd.DataFrame(), [], out_dir=tmp_path)
    assert "No stored runs" in html and "No stored benchmark" in html
    claims = {c["id"]: c for c in json.loads((tmp_path / "quake_drt" / "claims.json").read_text())}
    assert set(claims) == set(report.CLAIMS.expected)
    assert all(c["kind"] == verdicts.NOT_MEASURABLE for c in claims.values())
    assert "not in these results: the no_culling and all_lights runs" in claims["001.culling_speedup"]["explanation"]


def test05_streamed_runs_get_their_own_table_and_stay_out_of_the_thesis_claims(stored, tmp_path):
    frames, dirs, root = stored
    status = ["ok", "ok", "damaged", "frozen"]
    extra = [{"info_wire_bytes": 4000 + 100 * i, "latency_ms": 50.0 + i, "server_ms": 30.0, "info_status": st,
              "stage_encode_ms": 2.0, "net_video_ms": 10.0, "stage_decode_ms": 1.0, "zl_psnr_db": 40.0}
             for i, st in enumerate(status)]
    d, rows = _run(root, "streamed", 4, 100.0, 40_000, placement="streamed", net="wan-50m")
    for r, e in zip(rows, extra):
        r.update(e)
    # a local run the cross-method matrix repeated on another network: it sends nothing, so it adds nothing
    d2, rows2 = _run(root, "all_lights", 4, 120.0, 400_000, k=0, denoiser=False, taa=False, net="lte")
    both = pd.concat([frames, pd.DataFrame(rows + rows2)], ignore_index=True)
    local, streamed = report.split_placements(report.prepare(both, dirs + [d, d2]))
    assert set(streamed["run"]) == {d.name} and d2.name not in set(local["run"])
    t = report.streamed_table(streamed)
    assert len(t) == 1 and t.iloc[0]["damaged"] == 1 and t.iloc[0]["frozen"] == 1
    assert t.iloc[0]["wire bytes/frame"] == pytest.approx(np.mean([4100, 4200, 4300]))  # frame 0 left out
    html = report.section(both, dirs + [d, d2], out_dir=tmp_path / "report", results_root=root)
    assert "Streamed placement" in html


def test06_the_bench_table_says_which_stages_meet_the_ratio_goal():
    from methods.quake_drt import report

    rows = [{"stage": "primary", "stage / raw": 0.91}, {"stage": "secondary", "stage / raw": 0.6},
            {"stage": "direct", "stage / raw": float("nan")}]
    assert report._ratio_goal_text(rows) == ("Goal stage / raw >= 0.9: met by primary (0.910); not met by "
                                             "secondary (0.600), direct (nan).")
    assert report._ratio_goal_text(rows[:1]) == "Goal stage / raw >= 0.9: met by every stage (primary (0.910))."
    assert report._ratio_goal_text(rows[1:2]).endswith("met by no stage (secondary (0.600)).")
    assert report._ratio_goal_text([]) == ""
    # a range of the repeats is named only where it straddles the goal
    rows[0]["_range"], rows[1]["_range"] = [0.905, 0.93], [0.5, 0.91]
    assert report._ratio_goal_text(rows[:2]) == ("Goal stage / raw >= 0.9: met by primary (0.910); not met by "
                                                 "secondary (0.600; repeats 0.500-0.910, on both sides of the goal).")
