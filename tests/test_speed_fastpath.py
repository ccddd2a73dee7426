"""The fast path (onlinecal.ukf.fastpath: a motion block in two compiled calls, a rest block's update in one)
against the numpy reference path and against the compiled path without it: whole replays — a cold-started flight
(rests, the magnetometer's cold start), a paper session with a magnetic disturbance, and a forced
divergence — end with the same state x, covariance P and events.

Tolerances as tests/test_speed_replay.py (whose docstring gives the reason for σ's): an estimate within
1e-9 × max(|x|, σ), a σ within 1e-8 relative and so a covariance entry within 1e-8 × σ_i σ_j (a posterior
covariance is a difference of larger terms: the rounding of either path is 1e-9–1e-8 of it); events
identical. Against the compiled path without the fast path (the same kernels, in the same order) the
tolerances are 100 times tighter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onlinecal.sim import simulate
from onlinecal.sim.effects import MagDisturbance
from onlinecal.ukf import OnlineCalibrator, fastpath, kernels
from onlinecal.ukf import divergence as dv
from onlinecal.ukf.attitude_init import fold_attitude
from onlinecal.ukf.layout import ATT

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed: only the numpy path exists")


def _run(data, backend: str, fast: bool, init=None, force_div_at: float | None = None):
    """Replay ``data`` on ``backend`` with the fast path on or off; returns the calibrator and how many
    motion blocks and rest blocks took the fast path. ``force_div_at``: from that log time on, the first NIS
    record declares a divergence, as tests/test_robust_divergence.py does."""
    calls = {"motion": 0, "rest": 0}
    real = {"motion": fastpath.motion_step_fast, "rest": fastpath.rest_update_fast}

    def counter(kind: str):
        def counted(*a, **k):
            calls[kind] += 1
            return real[kind](*a, **k)
        return counted

    old = fastpath.set_enabled(fast)
    fastpath.motion_step_fast = counter("motion")
    fastpath.rest_update_fast = counter("rest")
    try:
        with kernels.use_backend(backend):
            cal = OnlineCalibrator(init)
            if force_div_at is None:
                cal.feed(data)
            else:
                n0 = int(np.searchsorted(data.t_imu, force_div_at))
                cal.feed(data.slice_imu(0, n0))
                rec = cal._nis.record
                fired = {"done": False}

                def forced(s, nis, t, inflated=0.0, held=False):
                    if not fired["done"]:
                        fired["done"] = True
                        return f"{s} NIS window mean forced"
                    return rec(s, nis, t, inflated, held=held)

                cal._nis.record = forced  # type: ignore[method-assign]
                with pytest.warns(dv.DivergenceWarning):
                    cal.feed(data.slice_imu(n0, data.n_imu))
            cal.flush()
    finally:
        fastpath.set_enabled(old)
        fastpath.motion_step_fast = real["motion"]  # type: ignore[assignment]
        fastpath.rest_update_fast = real["rest"]  # type: ignore[assignment]
    return cal, calls


def _assert_same(a: OnlineCalibrator, b: OnlineCalibrator, rtol: float = 1e-9, rtol_P: float = 1e-8) -> None:
    """x within rtol × max(|x|, σ); P within rtol_P × σ_i σ_j and σ within rtol_P × σ; the same
    attitude, events and NIS counts."""
    assert a.n == b.n and a._n_blocks == b._n_blocks
    sa, sb = a.sigma(), b.sigma()
    assert np.all(np.abs(a.x - b.x) <= rtol * np.maximum(np.abs(b.x), sb)), np.max(np.abs(a.x - b.x) / sb)
    assert np.all(np.abs(a.P - b.P) <= rtol_P * np.outer(sb, sb)), np.max(np.abs(a.P - b.P) / np.outer(sb, sb))
    assert np.all(np.abs(sa - sb) <= rtol_P * sb)
    assert np.allclose(a.R_nom, b.R_nom, rtol=0, atol=1e-9)
    assert [(e["kind"], e["t"]) for e in a.events] == [(e["kind"], e["t"]) for e in b.events]
    # the field cells swept (the fast path calibrates the block's field on Python floats) and the rests' gravity
    # directions (unit vectors from the state, which the paths share to ~1e-9 of σ): the same cells, the same
    # directions
    assert np.array_equal(a._coverage.mag_dirs, b._coverage.mag_dirs)
    assert len(a._coverage.rest_dirs) == len(b._coverage.rest_dirs)
    assert np.allclose(a._coverage.rest_dirs, b._coverage.rest_dirs, rtol=0, atol=1e-8)
    for s in ("accel", "mag"):
        ma, mb = a.nis_summary()[s], b.nis_summary()[s]
        assert ma.get("updates") == mb.get("updates") and ma.get("rejected") == mb.get("rejected"), s


@pytest.mark.parametrize("profile, seconds, event", [("flight", 60.0, "vehicle"), ("paper", 110.0, "mag_cold_start")])
def test_cold_start_fast_path_equals_the_numpy_reference(profile: str, seconds: float, event: str) -> None:
    """Cold start: 60 s of a simulated 200 Hz flight (motion, rests, the vehicle detector fed by the fast
    path's deviation) and 110 s of the paper session (static positions, turns, the magnetometer's cold start
    and then its updates, with the hold offsets of its coarse lattice, on the fast path)."""
    d = (simulate("flight", 3, duration=seconds, imu_rate=200) if profile == "flight"
         else simulate("paper", 1, duration=seconds)).data
    fast, n_fast = _run(d, "numba", True)
    ref, n_ref = _run(d, "numpy", False)
    slow, n_slow = _run(d, "numba", False)
    assert sum(n_ref.values()) == 0 and sum(n_slow.values()) == 0
    assert n_fast["motion"] > 100 and n_fast["rest"] > 50  # motion and rests both on the fast path
    assert any(e["kind"] == event for e in ref.events), ref.events
    _assert_same(fast, ref)
    _assert_same(fast, slow)


def test_paper_session_with_a_magnetic_disturbance_fast_path_equals_the_numpy_reference() -> None:
    """The paper's motion with a 0.5 G disturbance for 6 s, from the true calibration (the magnetometer in
    use from the start, so that the disturbance gate arms and then leaves the stretch out)."""
    eff = MagDisturbance(start=55.0, duration=6.0, amplitude=0.5, direction=(1.0, 0.5, 0.0))
    sim = simulate("paper", 1, duration=80.0, effects=[eff])
    fast, n_fast = _run(sim.data, "numba", True, init=sim.truth.calibration)
    ref, _ = _run(sim.data, "numpy", False, init=sim.truth.calibration)
    assert n_fast["motion"] > 100 and n_fast["rest"] > 50
    kinds = [e["kind"] for e in ref.events]
    assert "mag_disturbance" in kinds, kinds
    assert fast._coverage.mag_dirs.sum() >= 6  # the field coverage is exercised: the mag used from the start
    _assert_same(fast, ref)


def test_a_forced_divergence_restarts_both_paths_alike() -> None:
    """A divergence declared by the NIS bookkeeping in the middle of a flight: the state restarts and the
    filter carries on; the fast path and the reference end alike."""
    d = simulate("flight", 5, duration=50, imu_rate=200).data
    fast, n_fast = _run(d, "numba", True, force_div_at=30.0)
    ref, _ = _run(d, "numpy", False, force_div_at=30.0)
    assert n_fast["motion"] > 100
    assert sum(e["kind"] == "divergence" for e in ref.events) >= 1
    _assert_same(fast, ref)


@pytest.mark.parametrize("yaw_free", [False, True])
def test_the_compiled_fold_equals_fold_attitude(yaw_free: bool) -> None:
    """fold_kernel (symmetrise, R_nom exp([δθ]ₓ), δθ = 0, the heading's variance reset) against
    :func:`onlinecal.ukf.attitude_init.fold_attitude` on a random posterior; a NaN is reported."""
    rng = np.random.default_rng(7 + yaw_free)
    n = 40
    A = rng.normal(size=(n, n))
    P = A @ A.T * 1e-3 + np.eye(n) * 1e-4
    P[0, 1] += 1e-5  # not symmetric: the fold symmetrises
    x = rng.normal(0, 0.01, n)
    x[ATT] = [0.02, -0.01, 0.03]
    R_nom = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R_nom *= np.sign(np.linalg.det(R_nom))
    xs, Ps, R, fine = fastpath.fold_kernel(x, P, R_nom, 0.5 if yaw_free else -1.0)
    R_ref, x_ref, P_ref = fold_attitude(R_nom, x.copy(), P.copy(), 0.5 if yaw_free else None, ATT)
    assert fine
    assert np.allclose(R, R_ref, rtol=0, atol=1e-14)
    assert np.array_equal(xs, x_ref) and np.all(xs[ATT] == 0.0)
    assert np.allclose(Ps, P_ref, rtol=0, atol=1e-15) and np.allclose(Ps, Ps.T, rtol=0, atol=1e-15)
    if yaw_free:  # the heading (about world z, body direction R[2]) has exactly the variance given
        u = R[2]
        assert math.isclose(float(u @ Ps[:3, :3] @ u), 0.5, rel_tol=1e-12)
    P[5, 5] = np.nan
    assert not fastpath.fold_kernel(x, P, R_nom, -1.0)[3]


def _exactly_equal(a: OnlineCalibrator, b: OnlineCalibrator) -> None:
    """The same bits: state, covariance, attitude, coverage, events, NIS bookkeeping, trace."""
    assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P) and np.array_equal(a.R_nom, b.R_nom)
    assert np.array_equal(a._coverage.max_rate, b._coverage.max_rate)
    assert np.array_equal(a._coverage.angle, b._coverage.angle) and a._coverage.flight_s == b._coverage.flight_s
    assert [(e["kind"], e["t"], e["detail"]) for e in a.events] == [(e["kind"], e["t"], e["detail"]) for e in b.events]
    assert a._nis.stats == b._nis.stats
    ra, rb = a.trace_rows(), b.trace_rows()
    assert [list(r) for r in ra] == [list(r) for r in rb]  # the same columns; values NaN-aware (a NIS not yet seen)
    assert np.array_equal([list(r.values()) for r in ra], [list(r.values()) for r in rb], equal_nan=True)


@pytest.mark.parametrize("force_div_at", [None, 30.0])
def test_one_call_per_block_equals_two_calls_bit_for_bit(force_div_at: float | None) -> None:
    """motion_kernel (prediction, accel R, coverage, update and fold in one call) against predict_kernel +
    update_fold_kernel with Python between them: a cold-started flight whose vehicle detector switches on
    from the specific-force deviation (the block that switches it stops after the prediction and finishes
    on the two-call path: its event comes before that block's update, as on the two-call path), with and
    without a divergence forced in the NIS bookkeeping. Equal to the last bit."""
    d = simulate("flight", 3, duration=50, imu_rate=200).data
    # motion_kernel calls update_fold_kernel through the module's global: compiled (or loaded) before the global is
    # swapped for the counting wrapper below, or numba would meet a Python function there where the cache is stale
    # (after an edit of fastpath.py: "Untyped global name 'update_fold_kernel'")
    from onlinecal.ukf import warmup

    fastpath.motion_kernel.compile(warmup._types(warmup.SIGNATURES["fastpath:motion_kernel"]))
    calls = {"n": 0}
    real = fastpath.update_fold_kernel

    def counted(*a, **k):
        calls["n"] += 1
        return real(*a, **k)

    fastpath.update_fold_kernel = counted  # (called from Python only where a merged call stopped early)
    old = fastpath.set_merged(True)
    try:
        one, n_one = _run(d, "numba", True, force_div_at=force_div_at)
        stopped = calls["n"]
        fastpath.set_merged(False)
        calls["n"] = 0
        two, _ = _run(d, "numba", True, force_div_at=force_div_at)
    finally:
        fastpath.set_merged(old)
        fastpath.update_fold_kernel = real  # type: ignore[assignment]
    assert n_one["motion"] > 100 and calls["n"] == n_one["motion"]  # the two-call run: every motion block
    assert 1 <= stopped < 5  # the merged run: only the block(s) whose prediction switched the detector
    assert any(e["kind"] == "vehicle" and "specific-force" in e["detail"] for e in one.events)
    if force_div_at is not None:
        assert any(e["kind"] == "divergence" for e in one.events)
    _exactly_equal(one, two)


@pytest.mark.parametrize("has_mag, turn, extra", [(False, 1.0, False), (True, 1.0, False), (True, 60.0, False),
                                                   (True, 1.0, True)])
def test_the_sample_major_propagation_equals_the_point_major_loop(has_mag: bool, turn: float, extra: bool) -> None:
    """propagate_kernel (all dynamic sigma points one sample at a time, the Rodrigues series for all and its
    closed form where a step reaches 0.05 rad) against the point-at-a-time loop it replaced
    (_propagate_points_kernel): the same bits, for slow turns (series only), fast ones (×60: 6–12 rad/s, both
    forms), with the mag's interpolation weights and with extra gyro offsets (the general path's)."""
    from onlinecal.ukf.kernels_propagate import _propagate_points_kernel, propagate_kernel
    from onlinecal.ukf.kernels_update import sigma_points_kernel

    rng = np.random.default_rng(11 + int(has_mag) + int(turn) + 5 * int(extra))
    n, L = 40, 20
    A = rng.normal(size=(n, n)) * 0.05
    P = A @ A.T + np.eye(n) * 1e-4
    x = np.zeros(n)
    x[3:15] = np.r_[rng.normal(0, 0.01, 3), 1 + rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 6)]
    X, ok = sigma_points_kernel(x, P, 1.5, np.arange(n, dtype=np.intp))
    assert ok
    dyn = np.arange(0, 31, dtype=np.intp)
    o_g = X[dyn, 3:6].copy()
    M_g = np.stack([np.diag(X[s, 6:9]) + 0.01 * rng.normal(size=(3, 3)) for s in dyn])
    w = rng.normal(0, 0.1, (L + 1, 3)) * turn
    dt = np.full(L, 0.005) + rng.normal(0, 1e-5, L)
    c_mag = rng.random(L + 1) if has_mag else np.zeros(1)
    b_extra = rng.normal(0, 0.01, (dyn.size, L + 1, 3)) if extra else np.zeros((1, 1, 3))
    R_nom = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    ref = _propagate_points_kernel(X, R_nom, w, dt, c_mag, has_mag, dyn, o_g, M_g, b_extra, extra, 39)
    new = propagate_kernel(X, R_nom, w, dt, c_mag, has_mag, dyn, o_g, M_g, b_extra, extra, 39)
    for r, v in zip(ref, new, strict=True):
        assert np.array_equal(r, v)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_motion_blocks_moments_equal_the_full_unscented_transform(seed: int) -> None:
    """unscented_motion_kernel (P_pred formed only in the attitude's rows and columns, P + diag(q) elsewhere)
    against unscented_kernel's full product on sigma points drawn from (x, P) whose attitude columns alone were
    then moved, as a motion block's propagation moves them: x_pred and Y the same bits, P_pred within 1e-13 of
    σ_i σ_j, exactly symmetric; P of covariances over 14 decades, the scaled spread of the filter (α = 0.3)."""
    from onlinecal.ukf.kernels_update import sigma_points_kernel, unscented_kernel, unscented_motion_kernel

    rng = np.random.default_rng(40 + seed)
    n = 40
    sd = 10 ** rng.uniform(-7, 0, n)
    A = rng.normal(size=(n, n)) * 0.3 + np.eye(n) * 2.0
    C = A @ A.T
    dC = np.sqrt(np.diag(C))
    P = C / np.outer(dC, dC) * np.outer(sd, sd)
    x = rng.normal(size=n) * sd
    x[:3] = 0.0
    lam = 0.3**2 * n - n
    Wm = np.full(2 * n + 1, 1.0 / (2 * (n + lam)))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = Wm[0] + (1 - 0.3**2 + 2.0)
    X, ok = sigma_points_kernel(x, P, lam + n, np.arange(n, dtype=np.intp))
    assert ok
    dyn = np.arange(31)
    X[dyn, :3] = rng.normal(size=(31, 3)) * 1e-3  # the propagated points' attitude errors
    X[0, :3] = 0.0
    q = 10 ** rng.uniform(-12, -6, n)
    xr, Yr, Pr = unscented_kernel(X, Wm, Wc, q)
    xf, Yf, Pf = unscented_motion_kernel(X, Wm, Wc, q, P)
    assert np.array_equal(xr, xf) and np.array_equal(Yr, Yf)
    s = np.sqrt(np.diag(Pr))
    rel = np.abs(Pf - Pr) / np.outer(s, s)
    assert rel.max() < 1e-13, rel.max()
    assert np.array_equal(Pf, Pf.T)


def test_the_compiled_third_difference_median_equals_the_numpy_one() -> None:
    """third_diff_var on the numba backend (each segment's windows sorted on their own) against the numpy
    reference (one sort of the whole feed by segment and value): the same bits, on blocks with dropped
    samples (windows across a gap left out), too few windows (NaN), NaN readings and a constant reading."""
    from onlinecal.ukf.blocks import third_diff_var

    rng = np.random.default_rng(5)
    N = 4000
    t = np.cumsum(np.full(N, 0.005))
    keep = rng.random(N) > 0.05  # dropped samples: some windows span a gap
    t = t[keep]
    v = rng.normal(0, 0.01, (t.size, 3)) + np.sin(t)[:, None]
    v[100:103] = np.nan
    v[500:540] = 1.0
    seg = np.minimum(np.arange(t.size) // 19, 10_000).astype(np.intp)
    seg[seg >= 150] += 1  # an empty segment
    n_seg = int(seg[-1]) + 3
    with kernels.use_backend("numpy"):
        ref = third_diff_var(v, t, seg, n_seg)
    with kernels.use_backend("numba"):
        new = third_diff_var(v, t, seg, n_seg)
    assert np.isnan(ref).sum() >= 3 and np.isfinite(ref).sum() > 100
    assert np.array_equal(ref, new, equal_nan=True)


@pytest.mark.parametrize("vehicle", [False, True])
def test_the_compiled_block_q_equals_the_python_process_noise(vehicle: bool) -> None:
    """block_q_kernel (the block's base Q inside the compiled motion call) against the Python it replaced,
    :func:`onlinecal.ukf.step.earth_rate_q` of ``OnlineCalibrator._process_noise`` (the random walk with the mag
    bias's entries from the state's mag scale, the gyro's angle random walk on the attitude, and on a vehicle
    the Earth-rate floor on the gyro bias — some axes below it, one above, one NaN — and the horizontal
    allowance on the attitude): the same bits, over mag scales and block lengths."""
    from onlinecal.ukf import step
    from onlinecal.ukf.layout import SENSOR_SLICE

    rng = np.random.default_rng(3 + vehicle)
    cal = OnlineCalibrator(None)
    cal._rate = 200.0
    cal._vehicle.active = vehicle
    g0, m0 = SENSOR_SLICE["gyro"].start, SENSOR_SLICE["mag"].start
    from onlinecal.ukf.earth import allowance

    for trial in range(40):
        # even trials the unknown latitude's allowance, odd ones a known latitude's per axis (no heading, tilted)
        up = rng.normal(size=3)
        cal._earth = allowance(None if trial % 2 == 0 else 47.4, False, cal.config.rest_rate_sigma, 15.0,
                               (up / np.linalg.norm(up)).tolist())
        floor = cal._earth[0][0] ** 2
        cal.x[m0 + 3 : m0 + 6] = rng.uniform(0.001, 3.0, 3)  # mag scale: gauss to milli-gauss units
        cal.x[g0 + 3 : g0 + 6] = 1.0 + rng.normal(0, 0.05, 3)
        A = rng.normal(size=(cal.n, cal.n)) * 1e-3
        cal.P = A @ A.T + np.eye(cal.n) * 1e-9
        cal.P[g0, g0], cal.P[g0 + 1, g0 + 1] = floor * rng.uniform(0.1, 0.9), floor * rng.uniform(1.1, 3.0)
        if trial == 7:
            cal.P[g0 + 2, g0 + 2] = np.nan  # a NaN passes (np.maximum's rule), as in the Python
        dt, s_g = float(rng.uniform(0.02, 0.3)), float(rng.uniform(1e-4, 1e-2))
        ref = step.earth_rate_q(cal, cal._process_noise(dt, s_g), dt).copy()
        rw, (mag_q, dens, fg, rwf) = fastpath._q_args(cal)
        new = fastpath.block_q_kernel(rw, dt, cal._rate, s_g, SENSOR_SLICE["mag"].start if mag_q else -1, dens, fg,
                                      rwf, cal.x, cal.P, vehicle, g0, g0 + 3, np.asarray(cal._earth[0]),
                                      cal.config.vehicle_accel_tau, cal._earth[1], fastpath._TWO)
        assert np.array_equal(ref, new, equal_nan=True), trial
        assert (ref[g0] > rw[g0] * dt) == vehicle and ref[0] > 0  # the floor topped the first axis up


def _old_trace_row(t, x, sig, lay, nis_last):
    """The trace row as it was built before its columns were cached (one key at a time from lay.public())."""
    row = {"t": t}
    for i, nm in lay.public():
        row[nm] = float(x[i])
        row[nm + ".sigma"] = float(sig[i])
    for s, v in nis_last.items():
        row[f"nis.{s}"] = v
    return row


def test_the_trace_row_from_cached_columns_equals_the_one_built_key_by_key() -> None:
    """outputs.trace_row (columns cached per layout) against the row built key by key from lay.public(): the
    same keys in the same order and the same values, for the base layout and one with hold offsets and an
    extension (left out / kept), and after the layout changed."""
    from onlinecal.ukf.outputs import trace_row
    from onlinecal.ukf.state import StateLayout

    rng = np.random.default_rng(2)
    for lay in (StateLayout(), StateLayout(("temperature_bias:gyro",), ("accel", "mag")), StateLayout((), ("mag",))):
        x, sig = rng.normal(size=lay.n), rng.random(lay.n)
        nis = {"accel": 1.5, "mag": float("nan")}
        new, old = trace_row(2.5, x, sig, lay, nis), _old_trace_row(2.5, x, sig, lay, nis)
        assert list(new) == list(old) and not any(k.startswith("hold.") for k in new)
        assert np.array_equal(list(new.values()), list(old.values()), equal_nan=True)


@pytest.mark.parametrize("vehicle", [False, True])
def test_the_inline_nis_bookkeeping_equals_gated_bookkeeping(vehicle: bool) -> None:
    """fastpath._finish_motion's NIS bookkeeping (the kernel's status and NIS arrays read as Python values)
    against step.gated_bookkeeping on the UpdateResult it replaced, block by block: ok, soft-gated and
    dropped updates of accel and mag, accel alone, mag alone, windows completing (a run far above the band
    declares a divergence), a vehicle-inflated accel R, and the numerical failures (NaN, inf, a negative
    NIS) that declare one at once — the same NIS statistics, events (the vehicle detector switched on by the accel
    drops included) and divergences."""
    from onlinecal.ukf import step
    from onlinecal.ukf.kernels_unscented import _STATUS
    from onlinecal.ukf.unscented import UpdateResult

    rng = np.random.default_rng(9 + vehicle)
    from onlinecal.ukf.filter import UKFConfig

    a, b = (OnlineCalibrator(None, UKFConfig(nis_window=10)) for _ in range(2))  # windows complete within the run
    var_v = 4.0 * a.config.vehicle_accel_sigma**2 if vehicle else 0.0
    k_v = var_v / a.config.vehicle_accel_sigma**2 if var_v > 0 else 0.0
    with pytest.warns(dv.DivergenceWarning):
        for blk in range(600):
            use_acc, has_mag = [(True, True), (True, False), (False, True)][blk % 3]
            nb = int(use_acc) + int(has_mag)
            nis = rng.chisquare(3, nb) * (40.0 if 200 <= blk < 330 else 1.0)  # a run far above the band
            if blk in (77, 400, 500):
                nis[0] = [np.nan, np.inf, -1e-6][(77, 400, 500).index(blk)]
            status = rng.choice([0, 0, 0, 1, 2, -1], nb).astype(np.int64)
            tl = 0.1 * (blk + 1)
            for cal in (a, b):
                cal.R_nom = np.eye(3)
            codes = status.tolist() if blk % 2 else [float(v) for v in status]  # (motion_kernel's: floats)
            fastpath._finish_motion(a, step, a.x.copy(), a.P.copy(), nis.tolist(), codes, True, np.eye(3),
                                    True, use_acc, has_mag, var_v, tl)
            res = UpdateResult(b.x.copy(), b.P.copy())
            names = (["accel"] if use_acc else []) + (["mag"] if has_mag else [])
            for k, s in enumerate(names):
                if status[k] >= 0:
                    res.nis.append((s, float(nis[k]), _STATUS[int(status[k])]))
            k_div = b._div.count
            step.gated_bookkeeping(b, res, tl, True, k_v, motion=True)
            if b._div.count == k_div:
                step.commit_folded(b, np.eye(3), res.x, res.P, True, tl)
            assert a._nis.stats == b._nis.stats and a._n_blocks == b._n_blocks, blk
            assert [(e["kind"], e["t"], e["detail"]) for e in a.events] == [
                (e["kind"], e["t"], e["detail"]) for e in b.events], blk
    kinds = [e["detail"] for e in a.events if e["kind"] == "divergence"]
    assert all(any(w in d for d in kinds) for w in ("NaN", "infinite", "negative")), kinds
    assert any("window mean" in d for d in kinds), kinds
    acc = a._nis.stats["accel"]["vehicle"] if vehicle else a._nis.stats["accel"]  # (the inflated accel's stream)
    assert acc["rejected"] > 10 and acc["updates"] > 10 and a._nis.stats["mag"]["rejected"] > 10


def test_the_compiled_rail_pass_equals_the_rail_detector_block_by_block() -> None:
    """RailDetector.prepass (every block of a feed in one compiled call per sensor) against RailDetector.check
    block by block: the same clip flags, saturation events (with the rail they name) and state (learnt rails,
    open runs, clipped stretch), over feeds that carry runs and rails from one to the next — gyro and accel
    readings clipped on some axes at rails they reach in stretches longer than rail_run, runs that cross block
    and feed boundaries, stretches below rail_min, NaN readings; a feed with a block of rail_run samples or
    more is left to the per-block rule (None, nothing changed)."""
    from onlinecal.ukf.blocks import block_stats
    from onlinecal.ukf.detectors import RailDetector

    rng = np.random.default_rng(4)
    rail_min, rail_run = {"gyro": 1.0, "accel": 14.7}, 40
    fast, ref = RailDetector(), RailDetector()
    t0, n_events = 0.0, 0
    for feed in range(12):
        N = 600
        t = t0 + 0.005 * np.arange(1, N + 1)
        w = np.cumsum(rng.normal(0, 0.08, (N, 3)), axis=0) * (1 + feed % 3)
        a = np.cumsum(rng.normal(0, 0.6, (N, 3)), axis=0) + 9.8
        w = np.clip(w, -2.5, 2.5 - 0.5 * (feed % 2))  # rails (the limit moves: the learnt rail is a minimum)
        a = np.clip(a, -16.0, 16.0)
        w = np.round(w, 3)  # a lattice: identical readings in a row away from the rails too
        if feed == 5:
            w[100:110, 1] = np.nan
        if feed == 7:  # the last samples at a rail: the run carries into the next feed
            w[-60:, 0] = 2.5
        bounds = []
        i = 0
        while i < N:
            L = int(rng.integers(2, rail_run)) if feed != 9 else 50  # feed 9: long blocks (the per-block rule)
            bounds.append((i, min(N, i + L)))
            i += L
        if bounds[-1][1] - bounds[-1][0] < 2:
            bounds[-2] = (bounds[-2][0], N)
            bounds.pop()
        B = block_stats(t, w, a, np.zeros(0), np.zeros((0, 3)), bounds, None, np.zeros(3), False)
        pre = fast.prepass(B, w, a, rail_min, rail_run)
        for b, (i, j) in enumerate(bounds):
            clip, ev = ref.check(w[i:j], a[i:j], B.w_absmax[b], B.a_absmax[b], rail_min, rail_run,
                                 (B.w_runs[b], B.a_runs[b]))
            if pre is None:
                clip_f, ev_f = fast.check(w[i:j], a[i:j], B.w_absmax[b], B.a_absmax[b], rail_min, rail_run,
                                          (B.w_runs[b], B.a_runs[b]))
            else:
                clip_f, ev_f = {"mag": False, "gyro": pre[0][b], "accel": pre[1][b]}, pre[2].get(b, [])
            assert clip_f == clip and ev_f == ev, (feed, b)
            n_events += len(ev)
        assert (pre is None) == (feed == 9)
        assert fast.rail == ref.rail and fast.run == ref.run and fast.clip_on == ref.clip_on, feed
        assert fast.top == ref.top and fast.n_top == ref.n_top, feed
        t0 = float(t[-1])
    assert n_events >= 6 and set(ref.rail) == {"gyro", "accel"}, (n_events, ref.rail)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_rail_pass_learns_a_recurring_top_mid_feed_as_the_block_rule_does(seed: int) -> None:
    """A gyro and accel clipped in short stretches only (2–6 samples: the run rule never learns them) — the
    recurring-top rule learns the rail somewhere inside a feed; RailDetector.prepass (its one compiled call split
    there) against RailDetector.check block by block: the same flags, events with the rail they name, state."""
    from onlinecal.ukf.blocks import block_stats
    from onlinecal.ukf.detectors import RailDetector

    rng = np.random.default_rng(seed)
    rail_min, rail_run = {"gyro": 1.0, "accel": 14.7}, 40
    fast, ref = RailDetector(), RailDetector()
    t0, learnt_mid = 0.0, 0
    for feed in range(6):
        N = 800
        t = t0 + 0.005 * np.arange(1, N + 1)
        w = rng.normal(0, 1.2, (N, 3))
        a = rng.normal(9.8, 3.0, (N, 3))
        for _ in range(6):  # short clipped stretches at ±4.3657 (gyro) and ±19.6133 (accel), both signs
            i = int(rng.integers(0, N - 8))
            k = int(rng.integers(0, 3))
            n = int(rng.integers(2, 7))
            w[i : i + n, k] = 4.3657 * rng.choice([-1.0, 1.0])
            a[i : i + n, k] = 19.6133 * rng.choice([-1.0, 1.0])
        if feed == 2:
            w[50:60, 2] = np.nan
        bounds = []
        i = 0
        while i < N:
            L = int(rng.integers(2, 30))
            bounds.append((i, min(N, i + L)))
            i += L
        if bounds[-1][1] - bounds[-1][0] < 2:
            bounds[-2] = (bounds[-2][0], N)
            bounds.pop()
        had = {s: list(v) for s, v in ref.rail.items()}
        B = block_stats(t, w, a, np.zeros(0), np.zeros((0, 3)), bounds, None, np.zeros(3), False)
        pre = fast.prepass(B, w, a, rail_min, rail_run)
        assert pre is not None
        for b, (i, j) in enumerate(bounds):
            clip, ev = ref.check(w[i:j], a[i:j], B.w_absmax[b], B.a_absmax[b], rail_min, rail_run,
                                 (B.w_runs[b], B.a_runs[b]))
            assert {"mag": False, "gyro": pre[0][b], "accel": pre[1][b]} == clip and pre[2].get(b, []) == ev, (feed, b)
        assert fast.rail == ref.rail and fast.run == ref.run and fast.clip_on == ref.clip_on, feed
        assert fast.top == ref.top and fast.n_top == ref.n_top, feed
        learnt_mid += ref.rail != had
        t0 = float(t[-1])
    assert learnt_mid >= 1
    for s, lim in (("gyro", 4.3657), ("accel", 19.6133)):  # the rail: the clip level, on every axis it hit
        got = [r for r in ref.rail[s] if np.isfinite(r)]
        assert got and all(abs(r - lim) <= 1e-3 * lim for r in got), (s, ref.rail[s])


def test_the_motion_blocks_constants_follow_the_layout_and_the_noise_model() -> None:
    """fastpath._block_consts (λ + n, the Cholesky order, the random walk and Q's constants, the gates: kept on
    the calibrator) against the values computed afresh, after each thing it depends on changed: a hold
    offset appended (a new layout of 43 states), the gates, the sigma-point spread, rw_factor."""
    from onlinecal.ukf.kernels_unscented import _identity

    cal = OnlineCalibrator(None)

    def fresh():
        c, lay = cal.config, cal.lay
        lam = c.sp_alpha**2 * (lay.n + c.sp_kappa) - lay.n
        order = _identity(lay.n) if lay.perm_id else np.asarray(lay.perm, dtype=np.intp)
        rw, q_args = fastpath._q_args(cal)
        return lam + lay.n, order, rw.copy(), q_args, [cal._gates["accel"], cal._gates["mag"]]

    def check():
        got, ref = fastpath._block_consts(cal), fresh()
        assert got[0] == ref[0] and np.array_equal(got[1], ref[1]) and np.array_equal(got[2], ref[2])
        assert got[3] == ref[3] and got[4].tolist() == ref[4] and got[2].shape == (cal.n,)

    check()
    first = fastpath._block_consts(cal)
    assert fastpath._block_consts(cal) is first  # kept while nothing changed
    cal._add_hold("mag", 0.01)
    check()
    cal._gates = {"accel": 5.0, "mag": 9.0}
    check()
    cal.config.sp_alpha = 0.5
    check()
    cal.config.rw_factor = 2e-3
    check()
    assert fastpath._block_consts(cal)[2][5] == pytest.approx(first[2][5] * 4)  # a bias entry: (2 × rw)²


def test_a_warm_up_s_bias_walk_reaches_the_fast_motion_step() -> None:
    """A warm-up drift of the gyro bias (the simulator's thermal temperature_bias) switches the measured bias
    walk on in the first rest (event bias_walk); the motion blocks after it take the walk from the random-walk
    vector the fast path keeps between blocks (updated in place, NoiseModel.apply_walk): the fast path and the
    numpy reference end alike, and the walk is in both."""
    from onlinecal.sim.effects import TemperatureBias

    sim = simulate("paper", 43, duration=90.0, effects=[TemperatureBias(sensor="gyro", axis="y", coeff=8e-4)])
    fast, n_fast = _run(sim.data, "numba", True)
    ref, _ = _run(sim.data, "numpy", False)
    assert n_fast["motion"] > 100
    assert any(e["kind"] == "bias_walk" for e in ref.events), ref.events
    assert fast._noise.q_walk > 0.0 and fast._noise.q_walk == pytest.approx(ref._noise.q_walk, rel=1e-9)
    _assert_same(fast, ref)


def test_the_field_coverage_of_one_block_equals_the_general_form() -> None:
    """The fast path's magnetometer weights (fastpath.interp_weights_kernel: the same bits as interp_weights for up
    to 2L + 2 samples a block) and its field coverage (fastpath.field_cell_kernel): the block's mean field
    calibrated on scalars (magdisturb.calibrated_floats, compiled into the kernel) against start.calibrated's numpy
    (eq. 1) within 1e-13 relative, and the cell it marks the one MotionCoverage.add_field marks for that numpy
    field, over 5000 states with the paper's magnitudes of scale, angles and bias and readings of any size, a NaN
    reading included (cell 0); every cell occurs."""
    import warnings

    from onlinecal.ukf.layout import SENSOR_SLICE
    from onlinecal.ukf.magdisturb import calibrated_floats
    from onlinecal.ukf.propagate import interp_weights
    from onlinecal.ukf.start import calibrated
    from onlinecal.ukf.vehicle import FIELD_CELLS, MotionCoverage

    rng = np.random.default_rng(11)
    cal = OnlineCalibrator(None)
    sl = SENSOR_SLICE["mag"]
    seen = set()
    for k in range(5000):
        x = cal.x.copy()
        x[sl] = np.concatenate([rng.normal(0, 0.3, 3), rng.uniform(0.5, 3.0, 3), rng.normal(0, 0.05, 6)])
        cal.x = x
        m = rng.normal(0, 1.0, 3) * 10 ** rng.uniform(-3, 3)
        if k == 0:
            m[1] = np.nan
        ref = calibrated(cal, "mag", m)
        if k:
            got = calibrated_floats(x[sl].tolist(), m.tolist())
            assert np.allclose(got, ref, rtol=1e-13, atol=1e-13 * float(np.linalg.norm(ref)))
        cov = MotionCoverage()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (add_field's division of the NaN field)
            cov.add_field(ref)
        cell = fastpath.field_cell_kernel(x[sl].copy(), m, FIELD_CELLS)
        assert cov.mag_dirs[cell] == 1.0 and cov.mag_dirs.sum() == 1.0, (k, cell)
        seen.add(cell)
    assert len(seen) == 26
    for L in (1, 5, 20, 40):  # the mag's interpolation weights, compiled: the same bits
        for _ in range(100):
            n_m = int(rng.integers(1, 2 * L + 3))
            j = np.sort(rng.integers(1, L + 1, n_m)).astype(np.intp)
            frac = rng.random(n_m)
            assert np.array_equal(fastpath.interp_weights_kernel(j, frac, L), interp_weights(j, frac, L))
    with pytest.raises(ZeroDivisionError):  # (no mag sample: an error, as the Python's, never a silent NaN)
        fastpath.interp_weights_kernel(np.zeros(0, np.intp), np.zeros(0), 20)
