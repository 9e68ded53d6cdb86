"""Two-stage smoothing of the client's irradiance cache (seed 004, RAIL §4.2, eq. 5-7)."""
from __future__ import annotations

import numpy as np

DELTA_T0_MS = 100.0     # §4.2: ΔT₀ = 100 ms


def blend_cache(E_c: np.ndarray, E_s: np.ndarray, w_c: float) -> np.ndarray:
    """Stage 1: E'_c = w_c E_c + (1 − w_c) E_s for every received sample."""
    return w_c * np.asarray(E_c) + (1.0 - w_c) * np.asarray(E_s)


def interpolate(E_d: np.ndarray, E_c: np.ndarray, t_ms: float, delta_t_ms: float) -> np.ndarray:
    """Stage 2, eq. 5: E_d for t <= 0, E_c for t >= ΔT, linear in between (t: time since the cache update)."""
    if t_ms <= 0.0:
        return np.asarray(E_d)
    if t_ms >= delta_t_ms or delta_t_ms <= 0.0:
        return np.asarray(E_c)
    a = t_ms / delta_t_ms
    return np.asarray(E_d) + a * (np.asarray(E_c) - np.asarray(E_d))


class IntervalPredictor:
    """Eq. 6: ΔT_{n+1} = w_d ΔT_n + (1 − w_d) τ_n, with ΔT₀ = 100 ms; ``errors_ms`` keeps ΔT_n − τ_n."""

    def __init__(self, w_d: float, delta_t0_ms: float = DELTA_T0_MS):
        self.w_d = float(w_d)
        self.delta_t_ms = float(delta_t0_ms)
        self.errors_ms: list[float] = []

    def observe(self, tau_ms: float) -> float:
        """Records the interval τ_n that just ended; returns the prediction error ΔT_n − τ_n."""
        err = self.delta_t_ms - float(tau_ms)
        self.errors_ms.append(err)
        self.delta_t_ms = self.w_d * self.delta_t_ms + (1.0 - self.w_d) * float(tau_ms)
        return err


def prediction_errors(taus_ms, w_d: float, delta_t0_ms: float = DELTA_T0_MS) -> np.ndarray:
    """ΔT_n − τ_n over a sequence of intervals (§5.1's experiment)."""
    p = IntervalPredictor(w_d, delta_t0_ms)
    for tau in taus_ms:
        p.observe(tau)
    return np.asarray(p.errors_ms)


def modulate(taus_ms, period: int, rng: np.random.Generator) -> np.ndarray:
    """Eq. 7: τ'_n = τ_n (sin(2nπ/s) X_n + 1), X_n uniform in [0, 1)."""
    taus = np.asarray(taus_ms, np.float64)
    n = np.arange(len(taus))
    return taus * (np.sin(2.0 * n * np.pi / period) * rng.random(len(taus)) + 1.0)


def wd_sweep(taus_ms, weights, periods=(16, 32, 64), seed: int = 0) -> dict:
    """§5.1 / Fig. 8: per w_d, the mean over the sinusoid periods s of the standard deviation and of the mean
    absolute value of the prediction error on the modulated interval sequence (one fixed random sequence X
    per period, shared by every w_d)."""
    rng = np.random.default_rng(seed)
    seqs = [modulate(taus_ms, s, rng) for s in periods]
    out = {}
    for w in weights:
        errs = [prediction_errors(seq, w) for seq in seqs]
        out[float(w)] = {"std_ms": float(np.mean([e.std() for e in errs])),
                         "mean_abs_ms": float(np.mean([np.abs(e).mean() for e in errs]))}
    return out
