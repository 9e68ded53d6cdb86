"""``splitbench bench quake_drt`` runs every part on a small scene, stores one document the report reads, and
its figures are consistent (rays counted, culling saves rays, more lights cost more, the denoiser fit)."""
import json

from methods.quake_drt import bench


def test01_every_part_runs_and_is_stored(tmp_path, capsys):
    rc = bench.main(["--scene", "two_rooms", "--resolution", "48x27", "--resolutions", "32x18,48x27",
                     "--repeats", "1", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "bench" / "quake_drt.json").read_text())
    assert {"rays", "asvgf", "lights", "packages", "host"} <= set(doc)
    r = doc["rays"]
    assert r["direct"]["rays"] == r["direct"]["raw_rays"] > 0 and r["primary"]["rays"] > 0
    assert 0 < r["direct"]["ratio"] and 0 < r["primary"]["ratio"]
    rows = {row["case"]: row for row in doc["lights"]["rows"]}
    assert rows["culled, all of the row"]["shadow_rays"] < rows["all lights, no culling"]["shadow_rays"]
    assert rows["culled, k = 1"]["shaded_per_point"] == 1.0
    assert rows["culled, k = 16"]["shadow_rays"] >= rows["culled, k = 4"]["shadow_rays"]
    assert len(doc["asvgf"]["rows"]) == 2 and doc["asvgf"]["fit"]["ms_per_mp"] > 0
    assert "A-SVGF" in capsys.readouterr().out
    # a second run of one part keeps the others
    bench.main(["--scene", "two_rooms", "--parts", "rays", "--resolution", "32x18", "--repeats", "1",
                "--out", str(tmp_path)])
    doc2 = json.loads((tmp_path / "bench" / "quake_drt.json").read_text())
    assert doc2["asvgf"] == doc["asvgf"] and doc2["rays"]["resolution"] == [32, 18]
