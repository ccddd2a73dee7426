"""Bias instability and angle random walk in a datasheet's units from the Allan deviation (IEEE Std 952)."""

from __future__ import annotations

import numpy as np

from onlinecal.diagnose.stats import allan, allan_datasheet


def test_white_noise_gives_the_angle_random_walk_and_only_a_bound_on_instability() -> None:
    rate, s = 100.0, 1e-3  # rad/s white noise per sample: N = s/√rate rad/√s
    x = np.random.default_rng(0).standard_normal((60_000, 3)) * s
    taus, devs = allan(x, rate, 12)
    ds = allan_datasheet(taus, devs)
    expected = s / np.sqrt(rate) * np.degrees(1.0) * 60.0  # °/√h
    assert np.allclose(ds["angle_random_walk_deg_sqrt_h"], expected, rtol=0.05)
    # white noise has no flicker floor: the curve still falls at the longest τ, so B is only a bound
    assert all(ds["bias_instability_is_bound"])


def test_flicker_floor_is_read_as_bias_instability() -> None:
    """White noise plus a slow random walk: the Allan curve has a minimum inside the τ range, and B is the
    minimum / 0.664 in °/h, within the band that minimum sets."""
    rng = np.random.default_rng(1)
    rate = 100.0
    n = 200_000
    x = rng.standard_normal((n, 1)) * 2e-3 + np.cumsum(rng.standard_normal((n, 1)), axis=0) * 2e-6
    taus, devs = allan(x, rate, 14)
    ds = allan_datasheet(taus, devs)
    assert not ds["bias_instability_is_bound"][0]
    assert np.isclose(ds["bias_instability_deg_h"][0], devs.min() / 0.664 * np.degrees(1.0) * 3600.0)
