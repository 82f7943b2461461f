"""The long runs of the numerical stability suite, marked slow; the other files in this folder run
each of them 100 times shorter by default."""

import pytest

from tests.stability.test_dynamics import check_quaternion_norm_drift
from tests.stability.test_running_estimate import check_accumulation

pytestmark = pytest.mark.slow


def test_float32_accumulation_over_a_million_frames_stays_at_the_closed_form():
    """weier2016's running estimate in float32 (colour, alpha, rho and the frame number) over 10^6 frames: the
    same bound from the closed-form two-cycle as after 10^4 frames, so no drift; frame numbers stay exact below
    2^24 (about 52 hours at 90 Hz)."""
    check_accumulation(1_000_000)


def test_fusion_quaternion_norm_does_not_drift_over_10_million_updates():
    """10^7 gyro steps at 1 kHz (2.8 hours) of 2000 deg/s about a tilted axis: unit norm to 1e-14 and the
    orientation within 1e-9 of the closed-form rotation (1e-11 after 10^5: rounding adds up, it does not run away)."""
    check_quaternion_norm_drift(10_000_000, 1e-9)
