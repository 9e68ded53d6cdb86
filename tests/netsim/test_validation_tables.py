"""The committed ns-3 comparisons (netsim/validation/) meet their stated goals, and netsim still produces the
netsim side of them. ns-3 itself is not needed: the stored tables are the evidence."""

import pytest

from netsim import validate


def test_the_single_link_table_covers_the_grid_and_meets_its_goals():
    rows = validate.read_table()
    keys = {(r["transport"], int(r["size_bytes"]), r["bandwidth_mbps"], r["rtt_ms"], r["loss"]) for r in rows}
    assert keys == {(c.transport, c.size_bytes, c.bandwidth_mbps, c.rtt_ms, c.loss) for c in validate.grid()}
    for transport, s in validate.summarise(rows).items():
        # Goals (docs/netsim.md): median <= 10 %, p90 <= 25 %, loss-free <= 5 %.
        assert s["median_rel_error"] <= 0.10, transport
        assert s["p90_rel_error"] <= 0.25, transport
        assert s["lossless_p90_rel_error"] <= 0.05, transport


def test_netsim_still_gives_the_stored_loss_free_single_link_results():
    # Loss-free points need no ns-3 drop pattern: netsim alone must reproduce its column of the table.
    rows = [r for r in validate.read_table() if r["loss"] == 0]
    assert len(rows) == 84
    for r in rows:
        case = validate.Case(r["transport"], int(r["size_bytes"]), r["bandwidth_mbps"], r["rtt_ms"], r["loss"])
        assert round(validate.run_netsim(case, 0)[0], 6) == pytest.approx(r["netsim_s"], abs=1.5e-6), case.key


def test_the_fairness_table_covers_its_grid_and_meets_its_stated_goals():
    rows = validate.read_fairness_table()
    cases = {(r["cc"], r["flows"], r["direction"], r["bottleneck_mbps"], r["rtt_ms"], r["start"]) for r in rows}
    assert cases == {(c.cc, c.flows, c.direction, c.bottleneck_mbps, c.rtt_ms, c.start)
                     for c in validate.fairness_grid()}
    assert {r["replica"] for r in rows} == set(range(validate.FAIRNESS_REPLICAS))
    summary = validate.summarise_fairness(rows)
    overall = summary["all"]
    # netsim/validation/README.md and docs/netsim.md, "Fairness": per flow (medians over the replicas) and the
    # aggregate meet the single-link goals, median <= 10 % and p90 <= 25 %; Jain's indices agree within 0.1.
    assert overall["median_rel_error"] <= 0.10 and overall["p90_rel_error"] <= 0.25
    assert overall["aggregate_median_rel_error"] <= 0.10 and overall["aggregate_p90_rel_error"] <= 0.25
    assert overall["jain_max_gap"] <= 0.10
    for group, s in summary.items():
        assert s["median_rel_error"] <= 0.10, group


@pytest.mark.parametrize("index", [0, 9, 37])
def test_netsim_still_gives_the_stored_fairness_results(index):
    rows = validate.read_fairness_table()
    case = validate.fairness_grid()[index]
    stored = [r for r in rows if (r["cc"], r["flows"], r["direction"], r["bottleneck_mbps"], r["rtt_ms"], r["start"],
                                  r["replica"]) == (case.cc, case.flows, case.direction, case.bottleneck_mbps,
                                                    case.rtt_ms, case.start, 0)]
    got = validate.run_fairness_netsim(case, case.replica_starts_s(0))
    assert [round(t, 6) for t in got] == pytest.approx([r["netsim_s"] for r in sorted(stored, key=lambda r: r["flow"])],
                                                       abs=1.5e-6)


def test_jain_index():
    assert validate.jain_index([1.0, 1.0, 1.0]) == pytest.approx(1.0)
    assert validate.jain_index([1.0, 0.0, 0.0, 0.0]) == pytest.approx(0.25)
