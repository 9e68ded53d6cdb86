"""Verdicts on a paper's claims: each kind says how it was reached, measured kinds state their tolerance, and a
claim survives a trip through JSON and a DataFrame row."""
import json

import numpy as np
import pandas as pd
import pytest

from suite.harness import verdicts
from suite.harness.verdicts import Claim, Tolerance

SETTING = {"scene": "living_room", "backend": "embree", "resolution": "1920x1080", "net": "lan-home",
           "protocol": "tcp", "variant": "paper"}


def _frames(slowdown_ms: float) -> pd.DataFrame:
    """Synthetic stored frames of two runs: raw and compressed, the second slower by ``slowdown_ms``."""
    jitter = [-0.2, 0.2] * 3  # frame-to-frame noise that averages out
    rows = [{"variant": v, "frame": i, "frame_ms": 100.0 + (slowdown_ms if v == "lzo" else 0.0) + jitter[i]}
            for v in ("raw", "lzo") for i in range(6)]
    return pd.DataFrame(rows)


def _slowdown_pct(frames: pd.DataFrame) -> float:
    mean = frames.groupby("variant")["frame_ms"].mean()
    return 100.0 * (mean["lzo"] / mean["raw"] - 1.0)


def test01_a_measured_value_within_the_tolerance_reproduces_and_says_so():
    claim = verdicts.judge("x.slowdown", "compression makes the frame 4.3 % slower", "§4.5.3", 4.3,
                           _slowdown_pct(_frames(5.0)), "%", Tolerance(absolute=2.0), setting=SETTING)
    assert claim.kind == verdicts.REPRODUCES
    assert claim.suite_value == pytest.approx(5.0, abs=1e-6) and claim.difference == pytest.approx(0.7, abs=1e-6)
    assert "within the tolerance of ±2 percentage points (absolute)" in claim.explanation
    assert claim.verdict.startswith("reproduces: measured 5 % against the paper's 4.3 %")


def test02_a_measured_value_outside_the_tolerance_does_not_reproduce_and_says_by_how_much():
    # synthetic results in which compression makes the frame 10 % faster: the sign alone is wrong, and the
    # verdict is about the distance from +4.3 %, not about the sign
    suite = _slowdown_pct(_frames(-10.0))
    claim = verdicts.judge("x.slowdown", "compression makes the frame 4.3 % slower", "§4.5.3", 4.3, suite, "%",
                           Tolerance(absolute=2.0), setting=SETTING, note="our codec is faster than the link.")
    assert claim.kind == verdicts.DOES_NOT_REPRODUCE
    assert suite == pytest.approx(-10.0, abs=1e-6)
    assert "-14.3 percentage points" in claim.explanation
    assert "outside the tolerance of ±2 percentage points (absolute) by 12.3 percentage points" in claim.explanation
    assert claim.explanation.endswith("our codec is faster than the link.")


def test02b_a_bound_reproduces_on_its_side_only_and_a_value_that_is_not_finite_is_not_measurable():
    why = "an ordering: dynamic minus static DSSIM must be positive"
    above = verdicts.at_least("x.order", "dynamic lights raise the error", "Table 7.1", 0.0, 0.021, "", why,
                              setting=SETTING, method="m")
    assert above.kind == verdicts.REPRODUCES and above.tolerance.why == why
    assert "measured 0.021, at least the bound 0" in above.explanation
    at = verdicts.at_least("x.order", "s", "src", 1.0, 1.0, "x", why)
    assert at.kind == verdicts.REPRODUCES
    below = verdicts.at_least("x.order", "s", "src", 0.0, -0.01, "", why, note="the lights barely move.")
    assert below.kind == verdicts.DOES_NOT_REPRODUCE
    assert "below the bound 0" in below.explanation and "(short by 0.01)" in below.explanation
    assert below.explanation.endswith("the lights barely move.")
    nan = verdicts.at_least("x.order", "s", "src", 1.0, float("nan"), "x", why)
    assert nan.kind == verdicts.NOT_MEASURABLE and nan.suite_value is None and "no finite value" in nan.explanation
    with pytest.raises(ValueError, match="finite bound"):
        verdicts.at_least("x.order", "s", "src", float("inf"), 1.0, "x", why)


def test02c_a_verdict_the_uncertainty_could_change_is_not_measurable_and_keeps_its_note():
    claim = verdicts.judge("x.err", "error 0.088", "Table 7.1", 0.088, 0.2, "", Tolerance(absolute=0.03),
                           setting=SETTING, method="m", note="at 96x54.")
    assert verdicts.settled(claim, [verdicts.DOES_NOT_REPRODUCE], "floor 0.05") is claim
    assert verdicts.settled(claim, [], "no interval") is claim
    open_ = verdicts.settled(claim, [verdicts.DOES_NOT_REPRODUCE, verdicts.REPRODUCES], "floor 0.15", "at 96x54.")
    assert open_.kind == verdicts.NOT_MEASURABLE and open_.suite_value is None
    assert open_.explanation == "floor 0.15. at 96x54." and open_.paper_value == 0.088
    assert (open_.id, open_.setting, open_.method) == ("x.err", SETTING, "m")


def test03_a_relative_tolerance_scales_with_the_papers_value_and_its_edge_reproduces():
    tol = Tolerance(relative=0.10)
    assert verdicts.judge("x.ms", "s", "src", 87.33, 87.33 * 1.1, "ms", tol).kind == verdicts.REPRODUCES
    far = verdicts.judge("x.ms", "s", "src", 87.33, 110.5, "ms", tol)
    assert far.kind == verdicts.DOES_NOT_REPRODUCE
    assert "(+26.5 % of the paper's value)" in far.explanation and "±10 % of the paper's value" in far.explanation


def test04_a_calibrated_input_gives_consistent_by_calibration_never_reproduces():
    claim = verdicts.by_calibration("x.network_ms", "the network pass takes 87.33 ms", "Fig. 10",
                                    "the lan-home profile was calibrated on the paper's 87.33 ms transfer",
                                    paper_value=87.33, suite_value=88.0, unit="ms", setting=SETTING)
    assert claim.kind == verdicts.BY_CALIBRATION and claim.tolerance is None
    assert "lan-home profile was calibrated" in claim.explanation
    assert "does not test the claim" in claim.explanation and claim.suite_value == 88.0


def test05_a_construction_gives_holds_by_construction():
    claim = verdicts.by_construction("x.raw_bytes", "the bitmap is 8.3 MB", "§5.2",
                                     "one uint32 per pixel, 1920·1080·4 B", paper_value=8_294_400,
                                     suite_value=8_294_400, unit="B")
    assert claim.kind == verdicts.BY_CONSTRUCTION
    assert claim.explanation == "follows from the suite's construction: one uint32 per pixel, 1920·1080·4 B."
    assert claim.as_row()["suite"] == "8,294,400 B"


def test06_not_measurable_has_no_suite_value_and_says_why():
    claim = verdicts.not_measurable("x.fps", "7.7 fps", "§5.2", "the paper's frame time is its RTX GPU's.",
                                    paper_value=130.0, unit="ms")
    assert claim.kind == verdicts.NOT_MEASURABLE and claim.suite_value is None
    assert claim.explanation == "the paper's frame time is its RTX GPU's."
    assert claim.verdict == "not measurable here: the paper's frame time is its RTX GPU's."
    assert claim.as_row()["suite"] == "–"


def test07_measured_kinds_need_values_and_a_tolerance_and_every_verdict_an_explanation():
    with pytest.raises(ValueError, match="needs a paper value"):
        Claim(id="x", statement="s", source="src", kind=verdicts.REPRODUCES, explanation="looks right",
              paper_value=1.0, suite_value=1.0)
    with pytest.raises(ValueError, match="must say how"):
        Claim(id="x", statement="s", source="src", kind=verdicts.BY_CONSTRUCTION, explanation=" ")
    with pytest.raises(ValueError, match="unknown verdict kind"):
        Claim(id="x", statement="s", source="src", kind="roughly", explanation="e")
    with pytest.raises(ValueError, match="finite"):
        verdicts.judge("x", "s", "src", 1.0, np.nan, "ms", Tolerance(absolute=1.0))
    with pytest.raises(ValueError, match="exactly one"):
        Tolerance(absolute=1.0, relative=0.1)
    with pytest.raises(ValueError, match="exactly one"):
        Tolerance()


def test08_claims_survive_json_and_gather_into_one_table():
    claims = [
        verdicts.judge("a.share", "67 %", "Fig. 10", 67.0, 68.1, "%", Tolerance(absolute=5.0, why="rounding"),
                       setting=SETTING, method="m1"),
        verdicts.by_calibration("a.ms", "87 ms", "Fig. 10", "a calibrated link", method="m1"),
        verdicts.not_measurable("b.fps", "fps", "§5", "no GPU", method="m2"),
    ]
    back = [Claim.from_dict(json.loads(json.dumps(c.as_dict()))) for c in claims]
    assert back == claims
    table = verdicts.claims_table(claims)
    assert list(table.columns) == list(verdicts.ROW_COLUMNS) and len(table) == 3
    first = table.iloc[0]
    assert first["setting"] == ("scene living_room, backend embree, resolution 1920x1080, net lan-home, "
                                "protocol tcp, variant paper")
    assert first["tolerance"] == "±5 percentage points (absolute): rounding" and first["verdict"] == "reproduces"
    assert list(table["verdict"]) == ["reproduces", "consistent by calibration", "not measurable here"]


def test09_a_declared_claim_without_its_runs_stays_in_the_table_as_not_measurable():
    claims = verdicts.ClaimList("m", {
        "9.a": verdicts.Expected("a is 1", "§1", "the run on scene a", 1.0, "ms"),
        "9.b": verdicts.Expected("b is 2", "§2", "the run on scene b (quick preset)", 2.0)})
    measured = verdicts.judge(*claims.head("9.a"), 1.0, 1.05, "ms", verdicts.Tolerance(relative=0.1), method="m")
    done = claims.complete([measured])
    assert [c.id for c in done] == ["9.a", "9.b"] and done[0] is measured
    b = done[1]
    assert (b.kind, b.statement, b.source, b.paper_value, b.suite_value, b.method) == (
        verdicts.NOT_MEASURABLE, "b is 2", "§2", 2.0, None, "m")
    assert b.explanation == "not in these results: the run on scene b (quick preset)."
    with pytest.raises(ValueError, match="claim '9.c' is not declared"):
        claims.complete([verdicts.not_measurable("9.c", "c", "§3", "no data", method="m")])
