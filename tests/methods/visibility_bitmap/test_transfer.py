"""Modelled GPU↔CPU copies reproduce seed 000 Figure 10 and scale with bytes."""
import pytest

from methods.visibility_bitmap import transfer
from suite.errors import UserError


def test01_paper_bandwidths_give_figure10_times_for_the_1080p_bitmap():
    assert transfer.transfer_ms(8_294_400, transfer.PAPER_GPU_TO_CPU_BYTES_PER_S) == pytest.approx(13.24)
    assert transfer.transfer_ms(8_294_400, transfer.PAPER_CPU_TO_GPU_BYTES_PER_S) == pytest.approx(4.14)


def test02_implied_effective_bandwidths_are_about_626_and_2003_mb_per_s():
    assert transfer.PAPER_GPU_TO_CPU_BYTES_PER_S / 1e6 == pytest.approx(626.5, abs=0.1)
    assert transfer.PAPER_CPU_TO_GPU_BYTES_PER_S / 1e6 == pytest.approx(2003.5, abs=0.1)


def test03_time_is_latency_plus_bytes_over_bandwidth():
    assert transfer.transfer_ms(2_000_000, 1e9, latency_ms=0.5) == pytest.approx(2.5)
    assert transfer.transfer_ms(0, 1e9) == 0.0


@pytest.mark.parametrize("value", [0, -1, "fast"])
def test04_non_positive_or_non_numeric_bandwidth_is_a_user_error(value):
    with pytest.raises(UserError):
        transfer.bandwidth_from_mb_per_s(value, "gpu_to_cpu_mb_per_s")
