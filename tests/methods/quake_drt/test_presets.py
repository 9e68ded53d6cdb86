"""The reproduce presets: every point validates, smoke stays tiny, and quick holds the runs the report's claims
need (Fig. 7.9 culling pair, Fig. 7.11 light-sample and spp sweeps, Fig. 7.13 path, the quality variants)."""
import pytest

from suite.harness import presets


pytestmark = pytest.mark.usefixtures("every_scene_available")  # tests/methods/conftest.py


def _configs(preset):
    configs, problems = presets.configs(preset, methods="quake_drt")
    assert problems == []
    return configs


@pytest.mark.parametrize("preset", ["smoke", "quick", "full"])
def test01_every_point_validates(preset):
    assert _configs(preset)


def test02_smoke_is_tiny():
    configs = _configs("smoke")
    assert len(configs) == 1
    c = configs[0]
    assert c["resolution"] == [160, 90] and c["frames"] <= 3 and c["scene"] == "oa:aggressor"


def test03_quick_holds_the_claims_runs():
    configs = _configs("quick")
    by = {(c["variant"], c["params"]["num_random_dl"], c["params"]["spp"], c["frames"]) for c in configs}
    assert ("all_lights", 0, 1, 4) in by and ("no_culling", 0, 1, 4) in by  # Fig. 7.9
    assert {k for v, k, s, f in by if v == "one_light" and s == 1} >= {1, 2, 4, 8, 16}  # Fig. 7.11 light samples
    assert {s for v, k, s, f in by if v == "one_light"} >= {1, 2, 4}  # traditional spp
    assert ("all_lights", 0, 1, 120) in by and ("default", 1, 1, 120) in by  # Fig. 7.13: the whole 4 s path
    quality = {c["variant"] for c in configs if c["params"]["gt_frames"] > 0}
    assert quality >= {"default", "denoiser_no_taa", "one_light", "all_lights", "all_lights_taa"}
    assert {c["scene"] for c in configs} == {"oa:aggressor@pak1-maps", "oa:kaos"}
    assert {c["scene"] for c in configs if c["variant"] == "no_culling"} == {"oa:aggressor@pak1-maps", "oa:kaos"}


def test04_full_runs_at_the_thesis_scale_and_compare_pits_local_against_streamed():
    full = _configs("full")
    assert {tuple(c["resolution"]) for c in full} >= {(640, 360), (1280, 720), (1920, 1080), (2560, 1440)}
    assert max(c["params"]["gt_frames"] for c in full) == 1500  # §7.2's accumulated ground truth
    assert {c["net"] for c in full if c["variant"] == "streamed"} == {"lan-home", "wan-50m"}
    from suite.harness import registry

    table = presets.method_compare_table(registry.get("quake_drt"), "compare")
    assert table["variants"] == ["default", "streamed"]
    assert presets.uses_network(registry.get("quake_drt"), "streamed", table["set"])
    assert not presets.uses_network(registry.get("quake_drt"), "default", table["set"])
