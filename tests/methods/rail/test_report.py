"""The report section reads stored runs only and turns them into claims with verdicts."""
import pandas as pd

from methods.rail import report
from suite.harness import runner, verdicts


def test01_section_builds_from_stored_runs_and_judges_what_they_measure(tmp_path):
    cfg = runner.make_config("rail", scene="living_room", resolution="32x18", frames=4, net="lan-home",
                             reference_spp=0, quality_every=-1, clock="work",
                             set_values={"target_points": 300, "dart_sources": 256, "vpls": 8, "pass_hz": 0.0})
    out = runner.execute(cfg, tmp_path, force=True)
    runs = report.load_runs([out["run_dir"]])
    assert len(runs) == 1 and runs[0]["clients"] == 1
    rates = report.steady_rates(runs[0])
    assert rates["mbps"] > 0 and rates["roundtrip_hz"] > 0 and rates["cycle_ms"] > 0
    am = report.amortisation(runs[0])
    assert am["t_ms"] > 0 and am["actual_ms"] >= am["t_ms"] and am["speedup"] <= 1.0 + 1e-9
    html = report.section(pd.DataFrame(), [out["run_dir"]], out_dir=tmp_path / "rep", results_root=tmp_path)
    assert "Seed 004" in html and "not measurable here" in html
    found, _ = report.claims(runs, None)
    kinds = {c.id: c.kind for c in found}
    assert kinds["004.bandwidth_crytek"] == verdicts.NOT_MEASURABLE   # the scene is not available here
    # no Sponza run: no verdict made up; the claim keeps its row and says what it needs
    by_id = {c.id: c for c in found}
    sponza = by_id["004.bandwidth_dabrovic"]
    assert sponza.kind == verdicts.NOT_MEASURABLE and sponza.suite_value is None
    assert "not in these results" in sponza.explanation
    assert set(kinds) == set(report.CLAIMS.expected)
