"""Issue 16.5: the batch's windowed statistics in bounded blocks give the values of the direct definition
(a window's own mean and std), also on a long log where one cumsum over the whole log loses precision."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from onlinecal.batch.clean import _median5
from onlinecal.batch.segment import _window_std, moving_std
from onlinecal.sim import simulate


def _direct(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Centered windows of w samples, clipped at the ends, each's own mean and std (the definition)."""
    n = x.shape[0]
    w = max(2, min(w, n))
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)
    win = sliding_window_view(x, w, axis=0)[lo]
    return win.mean(-1), win.std(-1)


@pytest.mark.parametrize("n,w,block", [(7, 5, 3), (1000, 2, 97), (1000, 100, 64), (120_001, 100, 1 << 15),
                                       (120_001, 2, 1 << 15)])
@pytest.mark.slow
def test_moving_std_in_blocks_is_the_windows_own_std(n, w, block):
    x = np.random.default_rng(n + w).normal(0.3, 1.0, (n, 3)) + np.array([0.0, 100.0, -9.81])
    m, s = moving_std(x, w, block=block)
    m_ref, s_ref = _direct(x, w)
    np.testing.assert_allclose(m, m_ref, atol=1e-10)
    np.testing.assert_allclose(s, s_ref, atol=1e-7)


def test_window_std_matches_moving_std_on_a_flight():
    d = simulate("flight", 4, duration=200, imu_rate=200.0, mag_rate=50.0).data
    gm, gs, as_ = _window_std(d, 0.5, block=4099)
    w = int(round(0.5 * d.imu_rate))
    m_ref, s_ref = _direct(d.gyro, w)
    np.testing.assert_allclose(gm, m_ref, atol=1e-10)
    np.testing.assert_allclose(gs, np.linalg.norm(s_ref, axis=1), atol=1e-7)
    np.testing.assert_allclose(as_, np.linalg.norm(_direct(d.acc, w)[1], axis=1), atol=1e-7)


def test_median5_in_blocks_is_the_neighbours_median():
    x = np.random.default_rng(5).normal(size=(10_007, 3))
    n = x.shape[0]
    for i in (0, 1, 2, 5000, n - 2, n - 1):
        nb = x[np.clip([i - 2, i - 1, i + 1, i + 2], 0, n - 1)]
        np.testing.assert_allclose(_median5(x, block=1000)[i], np.median(nb, axis=0), rtol=0, atol=0)
