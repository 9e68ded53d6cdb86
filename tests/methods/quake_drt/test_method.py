"""The method through the harness: contract, declared outputs, stages, determinism, and the ground truth and
culling audit outputs. Runs on the smallest OpenArena map when its data is installed."""
import numpy as np
import pandas as pd
import pytest

from suite.errors import UserError
from suite.harness import registry, runner


def test01_a_local_sync_method_without_network_that_declares_its_outputs():
    cls = registry.get("quake_drt").load()
    params = registry.get("quake_drt").params()
    m = cls(params)
    assert cls.mode == "sync" and m.uses_network is False
    assert m.place("primary") == "client" and m.place("asvgf_atrous") == "client"
    with pytest.raises(UserError, match="placement 'cloud'"):
        cls({**params, "placement": "cloud"})
    with pytest.raises(UserError, match="spp"):
        cls({**params, "spp": 2})  # traditional samples need the denoiser off


def _execute(tmp_path, scene, seed=0, **sets):
    cfg = runner.make_config("quake_drt", scene=scene, resolution="48x27", frames=3, reference_spp=0, seed=seed,
                             set_values={"gt_frames": 2, "gt_every": 3, "cull_audit_points": 64, **sets})
    out = runner.execute(cfg, tmp_path, force=True)
    return out, pd.read_parquet(f"{out['run_dir']}/frames.parquet")


def test02_runs_are_deterministic_and_record_their_facts(tmp_path, small_map):
    out_a, a = _execute(tmp_path / "a", small_map)
    out_b, b = _execute(tmp_path / "b", small_map)
    assert list(a["image_sha256"]) == list(b["image_sha256"])
    assert len(set(a["image_sha256"])) == 3
    _, c = _execute(tmp_path / "c", small_map, seed=1)
    assert list(c["image_sha256"]) != list(a["image_sha256"])
    assert out_a["summary"]["zero_latency_run"] is False
    for stage in ("asvgf_rng_forward", "primary", "direct", "asvgf_gradient", "asvgf_gradient_atrous",
                  "asvgf_temporal", "asvgf_variance", "asvgf_atrous", "composition", "taa"):
        assert f"stage_{stage}_ms" in a.columns
    assert (a["work_taps"] > 0).all() and (a["rays"] > 0).all()
    assert (a["info_pvs_source"] == "bsp").all() and (a["info_audit_missed"] == 0).all()
    assert a["info_shaded_per_point"].max() <= 1.0 and a["info_candidates_per_point"].min() > 1.0
    assert list(a["info_gt_frames"]) == [0, 0, 2]
    last = a.iloc[-1]
    assert 0.0 < last["info_gt_ssim"] <= 1.0 and np.isfinite(last["info_detail_far"])
    assert (a["info_gradient_samples"].iloc[1:] > 0).all()


def test03_switches_change_what_is_traced(tmp_path, small_map):
    _, culled = _execute(tmp_path / "a", small_map, num_random_dl=0, denoiser=False, taa=False)
    _, full = _execute(tmp_path / "b", small_map, num_random_dl=0, denoiser=False, taa=False, cull_lights=False)
    assert (culled["info_shadow_rays"] < full["info_shadow_rays"]).all()
    assert list(culled["image_sha256"]) == list(full["image_sha256"])  # culling changes no pixel here
    assert "stage_asvgf_atrous_ms" not in culled.columns and "stage_taa_ms" not in culled.columns
    _, spp = _execute(tmp_path / "c", small_map, denoiser=False, taa=False, spp=2)
    assert "stage_primary_s2_ms" in spp.columns
