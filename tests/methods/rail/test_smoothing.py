"""Seed 004 §4.2 two-stage smoothing (eq. 5, 6) and §5.1's interval experiment (eq. 7)."""
import numpy as np
import pytest

from methods.rail import smoothing


def test01_stage1_blends_cache_and_server_values_with_w_c():
    E_c, E_s = np.array([2.0, 4.0]), np.array([4.0, 0.0])
    assert smoothing.blend_cache(E_c, E_s, 0.5) == pytest.approx([3.0, 2.0])
    assert smoothing.blend_cache(E_c, E_s, 0.0) == pytest.approx(E_s)
    assert smoothing.blend_cache(E_c, E_s, 1.0) == pytest.approx(E_c)


def test02_eq5_interpolates_linearly_over_the_predicted_interval():
    E_d, E_c = np.array([1.0]), np.array([3.0])
    assert smoothing.interpolate(E_d, E_c, -5.0, 100.0) == pytest.approx(E_d)
    assert smoothing.interpolate(E_d, E_c, 0.0, 100.0) == pytest.approx(E_d)
    assert smoothing.interpolate(E_d, E_c, 25.0, 100.0) == pytest.approx([1.5])
    assert smoothing.interpolate(E_d, E_c, 100.0, 100.0) == pytest.approx(E_c)
    assert smoothing.interpolate(E_d, E_c, 400.0, 100.0) == pytest.approx(E_c)


def test03_eq6_estimates_the_next_interval_from_delta_t0():
    p = smoothing.IntervalPredictor(0.65)
    assert p.delta_t_ms == 100.0                                    # ΔT₀ = 100 ms
    err = p.observe(200.0)
    assert err == pytest.approx(-100.0)
    assert p.delta_t_ms == pytest.approx(0.65 * 100 + 0.35 * 200)
    p1 = smoothing.IntervalPredictor(1.0)
    p1.observe(300.0)
    assert p1.delta_t_ms == 100.0                                   # w_d = 1: the estimate never moves
    p0 = smoothing.IntervalPredictor(0.0)
    p0.observe(300.0)
    assert p0.delta_t_ms == 300.0                                   # w_d = 0: the last interval


def test04_eq7_modulates_intervals_within_their_bounds():
    rng = np.random.default_rng(0)
    taus = np.full(100, 160.0)
    mod = smoothing.modulate(taus, 16, rng)
    assert (mod >= 0).all() and (mod <= 320.0).all() and mod[0] == 160.0
    sweep = smoothing.wd_sweep(taus, [0.0, 0.65, 1.0])
    assert set(sweep) == {0.0, 0.65, 1.0} and all(v["std_ms"] >= 0 for v in sweep.values())
