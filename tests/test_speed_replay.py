"""The whole online filter on both kernel backends: a replay with the compiled kernels equals the numpy
reference's, estimate by estimate and σ by σ, within 1e-9 relative (rounding only: the kernels do the same
arithmetic in another order, and ~600 nonlinear updates carry that rounding along)."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.model import PARAMS, SENSORS
from onlinecal.sim import simulate
from onlinecal.ukf import UKFConfig, kernels, replay

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: only the numpy path exists")


def _both(data, config=None):  # type: ignore[no-untyped-def]
    out = {}
    for be in ("numba", "numpy"):
        with kernels.use_backend(be):
            out[be] = replay([data], None, config)
    return out["numba"], out["numpy"]


def _assert_same(a, b, rtol: float = 1e-9, rtol_sigma: float = 1e-8) -> None:  # type: ignore[no-untyped-def]
    """Every estimate within rtol × max(|value|, σ) (a value of exactly 0 with σ > 0, e.g. a gauge term
    held at its prior, is compared on the scale of its σ) and every σ within rtol_sigma × σ.

    Why σ gets 1e-8: a posterior variance is the prior's less what the data explained, P − K S Kᵀ, and
    for a well-observed term (gyro bias: prior σ 0.2 rad/s, posterior 3e-5) the difference is ~1e-8 of
    the terms it is taken from, so the rounding of either path (1e-16 of the terms) is ~1e-9–1e-8 of
    the result — as much as any other valid order of the same sums would give the numpy path itself."""
    for s in SENSORS:
        ca, cb = a.calibration.sensor(s), b.calibration.sensor(s)
        for p in PARAMS:
            va, vb = np.asarray(ca.params()[p], float), np.asarray(cb.params()[p], float)
            sa, sb = np.asarray(ca.sigma[p], float), np.asarray(cb.sigma[p], float)
            assert np.all(np.abs(va - vb) <= rtol * np.maximum(np.abs(vb), sb)), (s, p, va - vb, sb)
            assert np.all(np.abs(sa - sb) <= rtol_sigma * sb), (s, p, sa - sb, sb)
    for k in a.calibration.extensions:
        ea, eb = a.calibration.extensions[k], b.calibration.extensions[k]
        sg = np.asarray(b.calibration.meta["online"]["extensions_sigma"][next(
            e for e in b.calibration.meta["online"]["extensions_sigma"] if e.startswith(k))])
        assert np.all(np.abs(np.subtract(ea["coeff"], eb["coeff"])) <= rtol * sg), k
    assert [e["kind"] for e in a.events] == [e["kind"] for e in b.events]
    for sensor, st in b.nis.items():
        if isinstance(st, dict) and "mean" in st:
            if not np.isfinite(st["mean"]):  # no NIS window filled yet: both say so
                assert not np.isfinite(a.nis[sensor]["mean"]), sensor
                continue
            assert abs(a.nis[sensor]["mean"] - st["mean"]) <= rtol * abs(st["mean"]), sensor


def test_flight_replay_equal_on_both_backends():
    """Cold start, 60 s of a simulated flight at 200 Hz with the mag: motion, rests, the mag cold start."""
    d = simulate("flight", 3, duration=60, imu_rate=200).data
    a, b = _both(d)
    assert a.calibration.meta["online"]["blocks"] == b.calibration.meta["online"]["blocks"] > 500
    _assert_same(a, b)


def test_extension_states_equal_on_both_backends():
    """With the gyro extensions (temperature bias, g-sensitivity): the extra gyro bias per sigma point and
    sample goes through the kernel too."""
    d = simulate("flight", 4, duration=40, imu_rate=100).data
    cfg = UKFConfig(extra_states=("temperature_bias:gyro", "g_sensitivity"))
    a, b = _both(d, cfg)
    assert set(a.calibration.extensions) == {"temperature_bias", "g_sensitivity"}
    _assert_same(a, b)
