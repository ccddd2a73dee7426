"""mag_current's inverse and its autopilot parameters (COMPASS_MOT_*, CAL_MAGn_xCOMP): the corrected field is
the interference-free one, and the parameters applied the autopilots' way (reading + param·x) undo it."""

from __future__ import annotations

import numpy as np
import pytest

from onlinecal.extensions import compassmot_params, remove_mag_current


def test_inverse_and_parameters_undo_a_current_interference() -> None:
    rng = np.random.default_rng(5)
    true = rng.normal(0, 0.3, (500, 3))  # gauss
    amps = rng.uniform(0, 40, 500)
    k = np.array([2e-3, -1.5e-3, 4e-3])  # gauss per A
    raw = true + amps[:, None] * k
    assert np.allclose(remove_mag_current(raw, amps, k), true)
    p = compassmot_params(k, "current", gauss_per_unit=1.0, instance=2)
    ap, px = p["ardupilot"], p["px4"]
    assert ap["COMPASS_MOTCT"] == 2 and px["CAL_MAG_COMP_TYP"] == 2
    # ArduPilot: mGauss per A, added to the reading in mGauss
    mot = np.array([ap["COMPASS_MOT2_X"], ap["COMPASS_MOT2_Y"], ap["COMPASS_MOT2_Z"]])
    assert np.allclose((raw * 1e3 + amps[:, None] * mot) / 1e3, true)
    # PX4: gauss per kA, added to the reading in gauss with the current in kA
    comp = np.array([px["CAL_MAG1_XCOMP"], px["CAL_MAG1_YCOMP"], px["CAL_MAG1_ZCOMP"]])
    assert np.allclose(raw + (amps / 1e3)[:, None] * comp, true)


def test_throttle_basis_and_units() -> None:
    k = np.array([50.0, 0.0, -20.0])  # milligauss at full throttle, in a log recorded in milligauss
    p = compassmot_params(k, "throttle", gauss_per_unit=1e-3)
    assert p["ardupilot"]["COMPASS_MOT_X"] == pytest.approx(-50.0) and p["ardupilot"]["COMPASS_MOTCT"] == 1
    assert p["px4"]["CAL_MAG0_ZCOMP"] == pytest.approx(0.02) and p["px4"]["CAL_MAG_COMP_TYP"] == 1
    with pytest.raises(ValueError, match="basis"):
        compassmot_params(k, "rpm", 1.0)
    with pytest.raises(ValueError, match="instance"):
        compassmot_params(k, "current", 1.0, instance=4)
