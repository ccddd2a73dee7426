import json

import numpy as np
import pytest

from onlinecal.model import (
    T_N,
    T_R,
    Calibration,
    SensorCalibration,
    compose,
    decompose,
)

rng = np.random.default_rng(42)


@pytest.mark.parametrize("i", range(20))
def test_decompose_inverts_compose_for_any_angle(i):
    s = rng.uniform(0.5, 2.5, 3)
    a = rng.uniform(-1.2, 1.2, 3)  # large angles: exact sin/cos forms
    x = rng.normal(0, 0.05, 3)
    s2, a2, x2 = decompose(compose(s, a, x))
    assert np.allclose(s2, s, atol=1e-12) and np.allclose(a2, a, atol=1e-12) and np.allclose(x2, x, atol=1e-12)


def test_small_angle_forms_agree_to_second_order():
    v = np.array([0.004, -0.003, 0.002])
    assert np.abs(T_R(v) - T_R(v, exact=False)).max() < 2 * np.dot(v, v)
    assert np.abs(T_N(v) - T_N(v, exact=False)).max() < 2 * np.dot(v, v)
    assert np.abs(T_R(10 * v) - T_R(10 * v, exact=False)).max() > 1e-4  # and differ at larger angles


def test_T_N_rows_are_unit_sensing_axes():
    xi = np.array([0.02, -0.03, 0.01])
    A = np.linalg.inv(T_N(xi))
    assert np.allclose(np.linalg.norm(A, axis=1), 1.0)
    assert np.allclose(np.triu(A, 1), 0.0)  # x is the reference axis, y lies in the xy plane


def test_inverted_axis_decomposes_to_negative_scale():
    M = compose([1.1, -0.95, 1.0], [0.01, -0.02, 0.005], [0.001, 0.002, -0.001])
    s, a, x = decompose(M)
    assert s[1] < 0 and np.allclose(compose(s, a, x), M, atol=1e-12)


def test_apply_and_inv_are_inverse():
    c = SensorCalibration.from_params([0.1, -0.2, 0.3], [1.1, 0.9, 1.05], [0.01, 0.02, -0.01], [0.003, 0, 0.001])
    raw = rng.normal(0, 3, (100, 3))
    assert np.allclose(c.inv().apply(c.apply(raw)), raw)
    assert np.allclose(c.apply(raw), (raw - c.bias) @ c.matrix.T)


def test_calibration_json_round_trips_exactly(tmp_path):
    c = SensorCalibration.from_params(rng.normal(size=3), rng.uniform(0.8, 1.2, 3), rng.normal(0, 0.02, 3),
                                      rng.normal(0, 0.01, 3), sigma={"bias": [1e-3, 2e-3, 3e-3]})
    cal = Calibration(gyro=c, accel=c.inv(), mag=None, source="batch")
    p = tmp_path / "cal.json"
    cal.save(p)
    back = Calibration.load(p)
    assert back == cal
    assert np.array_equal(back.gyro.matrix, cal.gyro.matrix)  # bit-exact
    d = json.loads(p.read_text())
    assert d["schema"] == "onlinecal.calibration/2" and "mag" not in d
    assert np.allclose(d["gyro"]["scale"], c.scale)


def test_from_dict_accepts_paper_parameters_without_matrix():
    d = {"bias": [0, 0, 0], "scale": [1.1, 1.0, 0.9], "alpha": [0.01, 0, 0], "xi": [0, 0.002, 0]}
    c = SensorCalibration.from_dict(d)
    assert np.allclose(c.scale, [1.1, 1.0, 0.9]) and np.allclose(c.alpha, [0.01, 0, 0])


def test_wrong_schema_rejected():
    with pytest.raises(ValueError, match="schema"):
        Calibration.from_dict({"schema": "something/2"})
