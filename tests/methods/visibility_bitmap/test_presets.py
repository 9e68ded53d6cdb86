"""The reproduce presets produce the runs the report section needs, every point validates, smoke stays tiny."""
import pytest

from suite.harness import presets


pytestmark = pytest.mark.usefixtures("every_scene_available")  # tests/methods/conftest.py


def _points(preset):
    configs, problems = presets.configs(preset, methods="visibility_bitmap")
    assert problems == []
    return [(c["variant"], "x".join(map(str, c["resolution"])), c["net"], c["protocol"]) for c in configs], configs


def test01_quick_preset_has_the_figure10_claim_network_codec_and_resolution_runs():
    points, configs = _points("quick")
    for variant in ("paper", "paper_lzo"):  # Fig. 10 and the LZO claim, with and without slow-start restart
        for net in ("lan-home", "lan-home,ssr=off"):
            assert (variant, "1920x1080", net, "tcp") in points
    for net in ("lan-home", "wan-50m", "wifi-40m", "dsl-3m", "lte", "5g-edge"):
        for protocol in ("tcp", "udp"):
            assert ("paper", "640x360", net, protocol) in points
    for variant in ("paper", "paper_lzo", "packed_lz4", "bitplane_zstd", "delta_zstd", "h264"):
        for net in ("lan-home", "wan-50m"):
            assert (variant, "640x360", net, "tcp") in points
    assert {"paper", "paper_ambient"} <= {v for v, r, n, p in points if r == "640x360"}
    assert {"640x360", "1280x720", "1920x1080"} <= {r for v, r, n, p in points if v == "paper"}
    # 1080p runs skip the path-traced references (minutes each on 2 cores)
    assert all(c["reference_spp"] == 0 for c in configs if c["resolution"] == [1920, 1080])
    runs = [(c["scene"], *p) for c, p in zip(configs, points)]
    assert len(runs) == len(set(runs))
    # a real level with more lights than a 32-bit word, in the multi-word layouts
    assert {c["params"]["layout"] for c in configs if c["scene"] == "oa:aggressor@pak1-maps"} == {"words32", "packed8"}


def test02_smoke_preset_stays_tiny():
    points, configs = _points("smoke")
    assert len(configs) <= 4 and all(c["resolution"] == [160, 90] and c["frames"] <= 3 for c in configs)


@pytest.mark.parametrize("preset", ["smoke", "quick", "full"])
def test03_every_point_of_every_preset_validates(preset):
    points, _ = _points(preset)
    assert points
