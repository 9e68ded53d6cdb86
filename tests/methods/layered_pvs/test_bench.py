"""``splitbench bench layered_pvs`` stores its figures and images where the report reads them."""
import json

from methods.layered_pvs import bench


def test01_bench_stores_stage_ratios_codec_rates_client_cost_and_images(tmp_path):
    out = bench.run(["--scene", "living_room", "--resolutions", "32x18", "--layers", "2", "--codec-size", "64",
                     "--out", str(tmp_path)])
    row = out["server"][0]
    assert row["layers_rays"] > 0 and 0 < row["layers_ratio"] and row["render_ms_per_mpix"] > 0
    assert {r["codec"] for r in out["codecs"]} >= {"quadtree_mask", "rle_huffman_mask", "jpeg_q25_444", "pvs_patch"}
    doc = json.loads((tmp_path / "bench" / "layered_pvs.json").read_text())
    assert doc["images"] and all((tmp_path / "bench" / "layered_pvs" / n).is_file() for n in doc["images"])
