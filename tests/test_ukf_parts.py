"""The online filter's parts, each on its own (issue 14): measurement models against model.py, sigma points
against filterpy, the update against the closed-form Kalman update, consider states, damping, the hot-path
geometry against scipy, and the calibration value (gauge, schema /2, immutability)."""

from __future__ import annotations

import json
import math
import pickle

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from onlinecal.model import Calibration, FrozenDict, SensorCalibration, compose, model_matrices
from onlinecal.specs import G0
from onlinecal.ukf.geometry import (
    prefix_products_cm,
    rodrigues,
    rodrigues1,
    rodrigues_cm,
    rodrigues_n,
    rot_log,
    triad,
    yaw_rotation,
)
from onlinecal.ukf.health import NisMonitor
from onlinecal.ukf.layout import N_STATE, SENSOR_SLICE, index
from onlinecal.ukf.measurements import AccelModel, MagModel, Offsets, ZeroRateModel, field_body, gravity_body
from onlinecal.ukf.unscented import Gating, Measurement, merwe_weights, predict_moments, sigma_points, update

rng = np.random.default_rng(7)


def _params(n: int) -> np.ndarray:
    """n random parameter sets (bias, scale, alpha, xi) of one sensor, (n, 12)."""
    return np.column_stack([rng.normal(0, 0.2, (n, 3)), rng.uniform(0.8, 1.2, (n, 3)),
                            rng.normal(0, 0.1, (n, 3)), rng.normal(0, 0.03, (n, 3))])


def _cal(p: np.ndarray) -> SensorCalibration:
    return SensorCalibration.from_params(p[:3], p[3:6], p[6:9], p[9:12])


# ---------------------------------------------------------------------------------------------------------
# model.py broadcasts; the measurement models are eq. 1 inverted
def test_model_broadcasts_over_leading_axes():
    p = _params(6).reshape(2, 3, 12)
    o, M, Minv = model_matrices(p)
    for i in range(2):
        for j in range(3):
            c = _cal(p[i, j])
            assert np.allclose(M[i, j], c.matrix, atol=1e-14)
            assert np.allclose(Minv[i, j], np.linalg.inv(c.matrix), atol=1e-13)
            assert np.array_equal(o[i, j], p[i, j, :3])
    assert np.allclose(compose(p[..., 3:6], p[..., 6:9], p[..., 9:12]), M, atol=0)
    raw = rng.normal(size=(4, 5, 3))
    c = _cal(p[0, 0])
    assert np.allclose(c.apply(raw), np.einsum("ij,...j->...i", c.matrix, raw - c.bias), atol=1e-14)
    assert np.allclose(c.inv().apply(c.apply(raw)), raw, atol=1e-12)


def test_accel_and_mag_models_are_the_sensor_model_of_model_py():
    """h(x) of accel and mag = SensorCalibration.inv().apply(body quantity) for every sigma point."""
    S = 9
    X = np.zeros((S, N_STATE))
    X[:, SENSOR_SLICE["accel"]] = _params(S)
    X[:, SENSOR_SLICE["mag"]] = _params(S)
    X[:, 39] = rng.uniform(0.5, 1.2, S)  # dip
    R = Rotation.random(S, random_state=3).as_matrix()  # world ← body
    Za = AccelModel(G0, 5.0, 0.005).h(X, gravity_body(R))
    Zm = MagModel().h(X, field_body(R, X[:, 39]))
    for s in range(S):
        f = R[s].T @ np.array([0.0, 0.0, G0])  # specific force at rest, ENU z up
        d = X[s, 39]
        h = R[s].T @ np.array([0.0, math.cos(d), -math.sin(d)])  # unit field, north +y, dipping down
        assert np.allclose(Za[s], _cal(X[s, SENSOR_SLICE["accel"]]).inv().apply(f), atol=1e-12)
        assert np.allclose(Zm[s], _cal(X[s, SENSOR_SLICE["mag"]]).inv().apply(h), atol=1e-12)


def test_offsets_add_to_the_reading():
    S, n = 5, N_STATE + 6
    X = np.zeros((S, n))
    X[:, SENSOR_SLICE["accel"]] = _params(S)
    X[:, SENSOR_SLICE["gyro"]] = _params(S)
    X[:, N_STATE : N_STATE + 3] = rng.normal(size=(S, 3))
    X[:, N_STATE + 3 :] = rng.normal(size=(S, 3))
    hold, temp = slice(N_STATE, N_STATE + 3), slice(N_STATE + 3, N_STATE + 6)
    f = np.tile([0.0, 0.0, 1.0], (S, 1))
    acc = AccelModel(G0, 5.0, 0.005)
    base = acc.h(X, f)
    assert np.allclose(acc.h(X, f, Offsets(hold=hold, temp=temp), T_reg=2.0) - base, X[:, hold] + 2 * X[:, temp])
    zr = ZeroRateModel((5e-5, 5e-5, 2e-5))  # per gyro axis (.earth.allowance)
    assert np.array_equal(zr.h(X), X[:, index("gyro", "bias")])
    fc = np.array([0.1, -0.2, 9.8])
    assert np.allclose(zr.h(X, Offsets(hold=hold, gsens=temp), f_cal=fc), X[:, index("gyro", "bias")] + X[:, hold]
                       + X[:, temp] * fc)
    assert zr.variance(1e6, 1.0) == pytest.approx([1e-6 + 5e-5**2, 1e-6 + 5e-5**2, 1e-6 + 2e-5**2], rel=1e-15)


def test_accel_variance_is_the_noise_when_the_norm_is_gravity():
    """|f| = g at every sigma point: no deviation, R = σ² of the mean; a turn adds (r ω²)²."""
    S = 7
    M = np.tile(np.eye(3), (S, 1, 1))
    o = np.zeros((S, 3))
    Wm, Wc = merwe_weights(3, 0.3, 2.0, 0.0)
    acc = AccelModel(G0, 5.0, 0.01)
    a = np.array([0.0, 0.0, G0])
    var, f = acc.variance(M, o, a, Wm, Wc, 0.02)
    assert var == pytest.approx(0.02**2, rel=1e-12) and np.allclose(f, a)
    var_r, _ = acc.variance(M, o, a, Wm, Wc, 0.02, rate=3.0)
    assert var_r == pytest.approx(0.02**2 + (0.01 * 9.0) ** 2, rel=1e-12)
    # 1 m/s² of unexplained |f| − g: well above the noise → the weight drops by orders of magnitude
    var_d, _ = acc.variance(M, o, a + [0, 0, 1.0], Wm, Wc, 0.02)
    assert var_d > 100 * 0.02**2


# ---------------------------------------------------------------------------------------------------------
# the unscented transform and the update
def _spd(n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_sigma_points_and_weights_are_filterpys():
    n = 8
    x, P = rng.normal(size=n), _spd(n)
    ref = MerweScaledSigmaPoints(n, 0.3, 2.0, 0.0)
    X = sigma_points(x, P, 0.3, 0.0, np.arange(n), True)
    assert np.allclose(X, ref.sigma_points(x, P), atol=1e-12)
    Wm, Wc = merwe_weights(n, 0.3, 2.0, 0.0)
    assert np.array_equal(Wm, ref.Wm) and np.array_equal(Wc, ref.Wc)


def test_permuted_factor_keeps_the_moments_and_the_dynamic_states():
    """Factor taken with states 5, 6 first: still a valid set (mean and covariance exact), and every point
    past the first 2 of each half leaves states 5, 6 at the mean."""
    n = 8
    x, P = rng.normal(size=n), _spd(n)
    perm = np.array([5, 6, 0, 1, 2, 3, 4, 7])
    X = sigma_points(x, P, 0.3, 0.0, perm, False)
    Wm, Wc = merwe_weights(n, 0.3, 2.0, 0.0)
    x_m, _, P_m = predict_moments(X, Wm, Wc, np.zeros(n))
    assert np.allclose(x_m, x, atol=1e-12) and np.allclose(P_m, P, atol=1e-10)
    rest = np.r_[3 : n + 1, n + 3 : 2 * n + 1]
    assert np.array_equal(X[rest][:, [5, 6]], np.tile(x[[5, 6]], (rest.size, 1)))


def _linear_case(n: int = 6, m: int = 3):
    x, P = rng.normal(size=n), _spd(n)
    H = rng.normal(size=(m, n))
    r = rng.uniform(0.5, 2.0, m)
    z = H @ x + rng.normal(size=m)
    Wm, Wc = merwe_weights(n, 0.3, 2.0, 0.0)
    X = sigma_points(x, P, 0.3, 0.0, np.arange(n), True)
    return x, P, H, r, z, Wm, Wc, X


def test_update_is_the_kalman_update_on_a_linear_gaussian_model():
    x, P, H, r, z, Wm, Wc, X = _linear_case()
    res = update(X - x, x, P, [Measurement("mag", z, X @ H.T, r)], Wm, Wc, Gating({"mag": 1e9}, False),
                 np.zeros(x.size, bool))
    S = H @ P @ H.T + np.diag(r)
    K = P @ H.T @ np.linalg.inv(S)
    nu = z - H @ x
    assert np.allclose(res.x, x + K @ nu, atol=1e-10)
    assert np.allclose(res.P, (np.eye(x.size) - K @ H) @ P, atol=1e-10)
    assert res.nis == [("mag", pytest.approx(nu @ np.linalg.solve(S, nu), rel=1e-10), "ok")]


def test_consider_states_are_not_updated_and_their_cross_covariance_is_kept_honest():
    """Schmidt–Kalman: zero gain on the consider states; P is the error covariance of that gain,
    (I − KH) P (I − KH)ᵀ + K R Kᵀ (Joseph form), which keeps the consider block as it was."""
    x, P, H, r, z, Wm, Wc, X = _linear_case()
    cons = np.zeros(x.size, bool)
    cons[[1, 4]] = True
    res = update(X - x, x, P, [Measurement("mag", z, X @ H.T, r)], Wm, Wc, Gating({"mag": 1e9}, False), cons)
    S = H @ P @ H.T + np.diag(r)
    K = P @ H.T @ np.linalg.inv(S)
    K[cons] = 0.0
    IKH = np.eye(x.size) - K @ H
    assert np.array_equal(res.x[cons], x[cons])
    assert np.allclose(res.x, x + K @ (z - H @ x), atol=1e-10)
    assert np.allclose(res.P, IKH @ P @ IKH.T + K @ np.diag(r) @ K.T, atol=1e-10)
    assert np.allclose(res.P[np.ix_(cons, cons)], P[np.ix_(cons, cons)], atol=1e-10)


def test_damping_is_the_gain_of_an_inflated_R_and_P_stays_its_error_covariance():
    """damp d, scalar case with R ≪ d·HPHᵀ: gain p/((1 + d) p); P = (1 − K)² p + K² r (the true R)."""
    x, P = np.array([0.3]), np.array([[4.0]])
    Wm, Wc = merwe_weights(1, 0.3, 2.0, 0.0)
    X = sigma_points(x, P, 0.3, 0.0, np.arange(1), True)
    z, r, d = np.array([1.3]), 0.01, 4.0
    res = update(X - x, x, P, [Measurement("rest", z, X, np.array([r]))], Wm, Wc, Gating({}, True),
                 np.zeros(1, bool), damp=d)
    K = 4.0 / (4.0 * (1 + d))
    assert res.x[0] == pytest.approx(0.3 + K * 1.0, rel=1e-12)
    assert res.P[0, 0] == pytest.approx((1 - K) ** 2 * 4.0 + K**2 * r, rel=1e-12)


def test_gating_drops_an_accel_outlier_in_motion_and_inflates_at_rest():
    x, P, H, r, z, Wm, Wc, X = _linear_case()
    z = z + 100.0
    gate = {"accel": float(chi2.ppf(0.999, 3))}
    meas = [Measurement("accel", z, X @ H.T, r)]
    moving = update(X - x, x, P, meas, Wm, Wc, Gating(gate, False), np.zeros(x.size, bool))
    assert moving.nis[0][2] == "drop" and np.array_equal(moving.x, x) and np.array_equal(moving.P, P)
    still = update(X - x, x, P, meas, Wm, Wc, Gating(gate, True), np.zeros(x.size, bool))
    assert still.nis[0][2] == "soft"
    # inflated to the gate's size: the innovation's NIS against the inflated S equals the gate
    nu = z - H @ x
    S = H @ P @ H.T + np.diag(r)
    nis = nu @ np.linalg.solve(S, nu)
    S_inf = S + np.diag(r * (nis / gate["accel"] - 1))
    K = P @ H.T @ np.linalg.inv(S_inf)
    assert np.allclose(still.x, x + K @ nu, atol=1e-8)


def test_nis_band_and_divergence():
    mon = NisMonitor(window=10, band_p=0.01, factor=5.0, windows=2)
    lo, hi = mon.band()
    assert lo == pytest.approx(chi2.ppf(0.005, 30) / 10) and hi == pytest.approx(chi2.ppf(0.995, 30) / 10)
    why = [mon.record("accel", 3.0, t) for t in range(10)]
    assert why == [None] * 10 and mon.stats["accel"]["windows"][-1][1] == pytest.approx(3.0)
    why = [mon.record("accel", 10 * hi, t) for t in range(20)]
    assert why[:19] == [None] * 19 and why[19] is not None and "accel" in why[19]


# ---------------------------------------------------------------------------------------------------------
# the hot-path geometry against scipy
def test_rotation_formulas_equal_scipy():
    th = Rotation.random(50, random_state=1).as_rotvec() * rng.uniform(0, 1, (50, 1))
    th[:5] *= 1e-7  # the series branches
    ref = Rotation.from_rotvec(th).as_matrix()
    assert np.allclose(rodrigues(th), ref, atol=1e-14)
    assert np.allclose(rodrigues_n(th), ref, atol=1e-14)
    assert np.allclose(rodrigues_cm(th.T.copy()).transpose(2, 0, 1), ref, atol=1e-14)
    assert all(np.allclose(rodrigues1(v), R, atol=1e-14) for v, R in zip(th, ref, strict=True))
    assert np.allclose(rot_log(ref), Rotation.from_matrix(ref).as_rotvec(), atol=1e-12)
    small = rodrigues_cm(th[:5].T.copy()).transpose(2, 0, 1)  # all angles small: the series form
    assert np.allclose(small, ref[:5], atol=1e-15)
    P = prefix_products_cm(ref[:7].transpose(1, 2, 0)[:, :, None, :])[:, :, 0, :].transpose(2, 0, 1)
    acc = Rotation.identity()
    for k in range(7):
        acc = acc * Rotation.from_matrix(ref[k])
        assert np.allclose(P[k], acc.as_matrix(), atol=1e-13)
    assert np.allclose(yaw_rotation(0.7), Rotation.from_euler("z", 0.7).as_matrix(), atol=1e-15)


def test_triad_equals_scipy_align_vectors_with_the_primary_pair_exact():
    R_true = Rotation.random(random_state=4)
    b1, b2 = rng.normal(size=3), rng.normal(size=3)
    w1, w2 = R_true.apply(b1), R_true.apply(b2) + rng.normal(0, 0.05, 3)
    R = triad(b1, b2, w1, w2)
    ref, _ = Rotation.align_vectors([w1, w2], [b1, b2], weights=[np.inf, 1.0])
    assert np.allclose(R, ref.as_matrix(), atol=1e-12)
    assert np.allclose(R @ (b1 / np.linalg.norm(b1)), w1 / np.linalg.norm(w1), atol=1e-14)


# ---------------------------------------------------------------------------------------------------------
# the calibration as data
def test_gauge_schema_2_round_trip_and_schema_1_migration():
    c = _cal(_params(1)[0])
    cal = Calibration(gyro=c, accel=c, source="batch", gauge="gyro_phases", health={"ok": True, "nis": [1, 2]},
                      meta={"batch": {"steps": {"gyro": {"figures": {"method": "phases (eqs. 28-31, 36)"}}}}})
    d = json.loads(cal.to_json())
    assert d["schema"] == "onlinecal.calibration/2" and d["gauge"] == "gyro_phases" and d["health"]["ok"] is True
    assert d["raw_units"]["gyro"] == "rad/s"
    back = Calibration.from_dict(d)
    assert back == cal and back.gauge == "gyro_phases" and back.health == {"ok": True, "nis": [1, 2]}
    # a /1 file: no gauge field; the batch's phase method is migrated once, on load
    d1 = {k: v for k, v in d.items() if k not in ("gauge", "raw_units", "health")}
    d1["schema"] = "onlinecal.calibration/1"
    assert Calibration.from_dict(d1).gauge == "gyro_phases"
    d1["meta"]["batch"]["steps"]["gyro"]["figures"]["method"] = "all transitions (eq. 36 generalised)"
    assert Calibration.from_dict(d1).gauge is None
    with pytest.raises(ValueError, match="gauge"):
        Calibration(gauge="phases")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="schema"):
        Calibration.from_dict(d | {"schema": "onlinecal.calibration/9"})


def test_calibration_is_immutable_and_still_plain_json():
    c = SensorCalibration.from_params(sigma={"bias": [1e-3, 2e-3, 3e-3]})
    cal = Calibration(gyro=c, extensions={"g_sensitivity": {"sensor": "gyro", "coeff": [1e-4, 0, 0]}},
                      meta={"online": {"events": [{"t": 1.0}]}})
    for mutate in (lambda: cal.meta.__setitem__("x", 1), lambda: cal.meta["online"]["events"].append({}),
                   lambda: cal.meta["online"]["events"][0].update(t=2.0),
                   lambda: cal.extensions["g_sensitivity"]["coeff"].__setitem__(0, 1.0),
                   lambda: cal.gyro.sigma.pop("bias")):
        with pytest.raises(TypeError, match="immutable"):
            mutate()
    with pytest.raises(ValueError):
        cal.gyro.sigma["bias"][0] = 1.0  # read-only array
    assert isinstance(cal.meta, dict) and isinstance(cal.meta, FrozenDict)
    assert json.loads(json.dumps(cal.to_dict()))["meta"]["online"]["events"] == [{"t": 1.0}]
    back = pickle.loads(pickle.dumps(cal))
    assert back == cal and isinstance(back.meta, FrozenDict)
    d = cal.to_dict()
    d["meta"]["online"]["events"].append({"t": 2.0})  # to_dict gives plain copies
    assert len(cal.meta["online"]["events"]) == 1
    new = cal.replace(meta={**cal.meta, "extra": 1})
    assert new.meta["extra"] == 1 and "extra" not in cal.meta


def test_ellipsoid_fit_recovers_hard_and_soft_iron_within_its_budget():
    """eq. 17 on noisy samples of a known ellipsoid ‖M (x − o)‖ = 1 (M symmetric, as the fit has it): o and M
    within a few of the fit's own σ, and a cloud that carries no ellipsoid costs a bounded time."""
    import time

    from onlinecal.ukf.attitude_init import ellipsoid_gn

    A = np.array([[2.1, 0.05, -0.03], [0.05, 1.9, 0.02], [-0.03, 0.02, 2.0]])
    o = np.array([0.1, -0.05, 0.2])
    u = rng.normal(size=(1500, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    x = u @ np.linalg.inv(A).T + o + rng.normal(0, 0.002, (1500, 3))
    o_e, M_e, cov, rms = ellipsoid_gn(x, x.mean(axis=0), np.eye(3) * 2.0)
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(o_e - o) < 5 * sd[:3]) and np.max(sd[:3]) < 1e-3
    assert np.all(np.abs(M_e[np.triu_indices(3)] - A[np.triu_indices(3)]) < 5 * sd[3:])
    assert rms == pytest.approx(0.002 * 2.0, rel=0.2)  # residual ≈ noise × |M|
    flat = np.column_stack([rng.normal(size=(2000, 2)), 1e-3 * rng.normal(size=2000)])  # no ellipsoid in it
    t0 = time.process_time()
    ellipsoid_gn(flat, flat.mean(axis=0), np.eye(3))
    assert time.process_time() - t0 < 1.0


def test_align_gauge_turns_every_sensor_by_one_rotation():
    """align_gauge gives the chosen sensor the asked alpha and leaves every relative orientation (M_acc⁻¹ M_s,
    unchanged by M → Q M) and every bias as it was."""
    from onlinecal.ukf.gauge import align_gauge

    sens = {s: _cal(_params(1)[0]) for s in ("gyro", "accel", "mag")}
    cal = Calibration(**sens)
    target = np.array([0.01, -0.02, 0.005])
    out = align_gauge(cal, "accel", target)
    assert np.allclose(out.accel.alpha, target, atol=1e-10)
    for s in ("gyro", "mag"):
        rel0 = np.linalg.inv(cal.accel.matrix) @ cal.sensor(s).matrix
        rel1 = np.linalg.inv(out.accel.matrix) @ out.sensor(s).matrix
        assert np.allclose(rel0, rel1, atol=1e-12) and np.array_equal(out.sensor(s).bias, cal.sensor(s).bias)
    Q = out.gyro.matrix @ np.linalg.inv(cal.gyro.matrix)
    assert np.allclose(Q @ Q.T, np.eye(3), atol=1e-12) and np.linalg.det(Q) == pytest.approx(1.0)


@pytest.mark.parametrize(("n", "alpha", "beta", "kappa"), [(1, 0.3, 2.0, 0.0), (38, 0.3, 2.0, 0.0), (40, 0.3, 2.0, 0.0),
                                                          (7, 1e-3, 2.0, 3.0), (12, 0.5, 0.0, -2.0)])
def test_weights_are_filterpys_bit_for_bit(n, alpha, beta, kappa) -> None:
    """The weights are written out (filterpy's import costs every start-up ~1 s); they must be the
    reference implementation's own numbers, not merely close."""
    from filterpy.kalman import MerweScaledSigmaPoints

    ref = MerweScaledSigmaPoints(n, alpha, beta, kappa)
    Wm, Wc = merwe_weights(n, alpha, beta, kappa)
    assert np.array_equal(Wm, ref.Wm) and np.array_equal(Wc, ref.Wc)


@pytest.mark.parametrize(("p", "dof"), [(0.999, 3), (0.9999, 3), (0.0005, 300.0), (0.9995, 300.0), (0.5, 1)])
def test_chi2_quantile_is_scipys_bit_for_bit(p, dof) -> None:
    """The χ² quantile without importing scipy.stats (~0.5 s of every start-up): scipy's own numbers."""
    from scipy.stats import chi2

    from onlinecal.ukf.health import chi2_ppf

    assert chi2_ppf(p, dof) == float(chi2.ppf(p, dof))
