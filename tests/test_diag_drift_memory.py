"""Issue 13 item: the drift walk's regressors have a duration-independent column count (at most
DRIFT_MAX_KNOTS knots per log) and are built per knot support, so diagnose's memory grows linearly with
the log's duration (it grew as T²: 4.9 GB for a 30-minute flight)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from onlinecal.diagnose.detectors import DRIFT_KNOT_S, DRIFT_MAX_KNOTS, _raw_cols, drift_cols, drift_knots, hats
from onlinecal.diagnose.motion import prepare
from onlinecal.diagnose.regressors import Design
from onlinecal.sim import simulate


def _design(duration: float, seed: int = 2) -> tuple[Design, object]:
    sim = simulate("paper", seed, duration=duration)
    cal = sim.truth.calibration
    from onlinecal.batch.segment import noise_floors, segment

    sg = segment(sim.data, noise_floors([sim.data]))
    return Design(prepare(sim.data, cal, sg.rests), 9.80665, 0), cal


def test_drift_columns_equal_the_dense_hat_construction() -> None:
    """The per-support build gives the same columns as the dense samples × knots hat matrix."""
    d, cal = _design(120.0)
    kn = drift_knots(d)
    H = hats(d.s.t, kn)
    ref = []
    for k in range(H.shape[1]):
        nz = np.flatnonzero(H[:, k])
        r0, r1 = d.local_range(int(nz[0]), int(nz[-1]) + 1)
        if r1 >= d.s.n - d.b.L:
            r1 = d.s.n
        ref.append(_raw_cols(d, cal, "gyro", np.repeat(H[r0:r1, k : k + 1], 3, axis=1), r0, r1))
    R = np.concatenate(ref, axis=1)
    X = drift_cols("gyro")(d, cal)
    assert X.shape == R.shape == (d.y.size, 3 * (kn.size - 1))
    assert np.allclose(X, R, rtol=1e-12, atol=1e-12 * np.abs(R).max())


def test_knot_count_is_bounded_and_spacing_kept_for_short_logs() -> None:
    d, _ = _design(120.0)
    kn = drift_knots(d)
    assert np.allclose(np.diff(kn), np.diff(kn)[0]) and np.diff(kn)[0] <= DRIFT_KNOT_S + 1e-9
    long_d, _ = _design(309.0)
    assert drift_knots(long_d, max_knots=11).size == 11
    assert drift_knots(long_d).size <= DRIFT_MAX_KNOTS


_PEAK = """
import sys, tracemalloc
from onlinecal.sim import simulate
from onlinecal.diagnose import diagnose
s = simulate("multirotor", 1, duration=float(sys.argv[1]))
tracemalloc.start()
diagnose([s.data], check=False, ukf=False)
print(tracemalloc.get_traced_memory()[1])
"""


@pytest.mark.slow
def test_diagnose_memory_linear_in_duration() -> None:
    """Peak traced memory of diagnose on a 10- and a 20-minute flight (both at the knot bound): ratio
    within 2 × 1.25 (it was ≈ 4 × with the fixed 10-s knot spacing, the drift block's rows × knots)."""
    peaks = {}
    for dur in (600, 1200):
        out = subprocess.run([sys.executable, "-c", _PEAK, str(dur)], capture_output=True, text=True, check=True)
        peaks[dur] = int(out.stdout.split()[-1])
    assert peaks[1200] / peaks[600] < 2.5, peaks
