"""Issue 15, the per-block Python outside the compiled kernels: the magnetometer's cold-start buffer and fit,
the noise caches and the rail detector, each restructured for speed, against the rule it replaces (written
out here as it was: a concatenation per block, all three fit tests at once, the uncached noise formulas, the
per-axis runs). Decisions must be identical and values equal (the same bits where the arithmetic is the
same; 1e-12 relative otherwise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onlinecal.specs import FIELD_GAUSS, RAIL_SAMPLES, RAIL_TOL
from onlinecal.ukf import magdisturb as md
from onlinecal.ukf.attitude_init import MagCollector, fit_mag_cold
from onlinecal.ukf.config import UKFConfig
from onlinecal.ukf.detectors import RailDetector, _runs, block_runs
from onlinecal.ukf.layout import DIP, N_STATE, SENSOR_SLICE
from onlinecal.ukf.noise import NoiseModel, mag_unit_of


# ---------------------------------------------------------------- magnetometer cold-start buffer and fit
class _ConcatCollector:
    """The buffer as it was: the decimation loop, then a concatenation of the whole buffer per block."""

    def __init__(self) -> None:
        self.buf = np.zeros((0, 3))
        self.next_t = -math.inf

    def add(self, tm, m, max_len):
        sel = []
        for k, ti in enumerate(tm):
            if ti >= self.next_t:
                sel.append(k)
                self.next_t = float(ti) + 0.1
        if sel:
            self.buf = np.concatenate([self.buf, np.asarray(m, float)[sel]])
        if self.buf.shape[0] > max_len:
            self.buf = self.buf[::2]


def test_mag_collector_in_place_store_equals_the_concatenation() -> None:
    """Blocks of 0–9 samples at 50 Hz with jitter, a few with NaN times or out of order, the buffer halved
    (max_len 37) and emptied from outside (as the cold fit does): the same samples in the same order after
    every block, and the same next time."""
    rng = np.random.default_rng(7)
    new, ref = MagCollector(), _ConcatCollector()
    t, halvings = 0.0, 0
    for blk in range(600):
        k = int(rng.integers(0, 10))
        tm = t + np.cumsum(rng.uniform(0.005, 0.04, k))
        if k and blk % 37 == 5:
            tm[int(rng.integers(0, k))] = math.nan
        if k > 2 and blk % 41 == 3:
            tm = tm[::-1].copy()
        t = float(np.nanmax(tm)) if k and np.isfinite(tm).any() else t + 0.1
        m = rng.normal(size=(k, 3))
        n_before = ref.buf.shape[0]
        new.add(tm, m, 37)
        ref.add(tm, m, 37)
        halvings += ref.buf.shape[0] < n_before
        assert np.array_equal(new.buf, ref.buf) and new.next_t == ref.next_t, blk
        if blk % 173 == 100:  # the fit succeeded: MagStart empties the buffer
            new.buf, ref.buf = np.zeros((0, 3)), np.zeros((0, 3))
    assert halvings > 5


def _fails_all_at_once(x: np.ndarray, c: UKFConfig) -> bool:
    """The cold fit's acceptance as it was written: all three tests formed, then judged together."""
    m0 = x.mean(axis=0)
    xc = x - m0
    A = np.column_stack([2 * xc, np.ones(x.shape[0])])
    b = (xc**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    r2 = sol[3] + sol[:3] @ sol[:3]
    if r2 <= 0:
        return True
    r, o = math.sqrt(r2), m0 + sol[:3]
    e = b - A @ sol
    cov = float(e @ e) / max(1, x.shape[0] - 4) * np.linalg.inv(A.T @ A)
    sig_o = float(np.sqrt(np.max(np.diag(cov)[:3])))
    u = (x - o) / np.linalg.norm(x - o, axis=1)[:, None]
    spread = float(np.linalg.eigvalsh(u.T @ u / u.shape[0])[0])
    cover = float(np.linalg.eigvalsh(np.cov(u.T))[0])
    return bool(spread < c.mag_fit_min_spread or cover < c.mag_fit_min_cover
                or not sig_o < c.mag_fit_max_centre_sigma * r)


def test_fit_mag_cold_early_exits_make_the_same_decisions() -> None:
    """Raw clouds from a full sphere to a flight's band (field directions within a cone about a turning
    axis of growing half-width), with noise from small to large: the fit is refused exactly when the three
    tests judged together refuse it; both outcomes occur."""
    rng = np.random.default_rng(3)
    c = UKFConfig()
    seen = {True: 0, False: 0}
    for trial in range(200):
        n = int(rng.integers(100, 600))
        # a latitude band (a flight's turns) about a centre latitude; the kinds put each test near its
        # bound in turn: spread (a band about the equator), cover (a band off it), the centre's σ (the whole
        # sphere, noisy), then anything
        kind = trial % 4
        half = (rng.uniform(0.5, 0.7), rng.uniform(0.3, 0.45), math.pi / 2, rng.uniform(0.02, math.pi / 2))[kind]
        mid = (0.0, rng.uniform(0.5, 0.7), 0.0, rng.uniform(0, 0.6))[kind]
        noise = {1: 10 ** rng.uniform(-4, -2.5), 2: rng.uniform(0.07, 0.16)}.get(kind, 10 ** rng.uniform(-3, -0.5))
        lat = rng.uniform(-half, half, n) + mid
        lon = rng.uniform(0, 2 * math.pi, n)
        d = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
        r, o = rng.uniform(0.3, 600.0), rng.normal(0, 0.3, 3)
        x = o * r + r * d + rng.normal(0, noise * r, (n, 3))
        fails = _fails_all_at_once(x, c)
        assert (fit_mag_cold(x, c) is None) == fails, trial
        seen[fails] += 1
    assert seen[True] >= 30 and seen[False] >= 30, seen


# ---------------------------------------------------------------- noise caches
def test_mag_unit_is_numpys_mean_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    x = np.zeros(N_STATE)
    s0 = SENSOR_SLICE["mag"].start + 3
    for _ in range(2000):
        x[s0 : s0 + 3] = rng.normal(1, 0.3, 3) * 10 ** rng.uniform(-3, 3)
        assert mag_unit_of(x) == float(1.0 / np.mean(x[SENSOR_SLICE["mag"]][3:6]))


def _spec_uncached(nm: NoiseModel, r: float, x: np.ndarray) -> dict[str, float]:
    g, a, m = nm.specs["gyro"], nm.specs["accel"], nm.specs["mag"]
    unit = float(1.0 / np.mean(x[SENSOR_SLICE["mag"]][3:6]))
    return {"gyro": math.hypot(g.sigma(r), g.lsb / math.sqrt(12)),
            "accel": math.hypot(a.sigma(r), a.lsb / math.sqrt(12)),
            "mag": math.hypot(m.sigma(50.0), m.lsb / math.sqrt(12)) / FIELD_GAUSS * unit}


def _rw_uncached(nm: NoiseModel, n: int, x: np.ndarray, ext, rw: float) -> np.ndarray:
    q = np.zeros(n)
    for s, spec in nm.specs.items():
        dens = spec.density if spec.density > 0 else spec.sigma(50.0) / math.sqrt(25.0)
        unit = float(1.0 / np.mean(x[SENSOR_SLICE["mag"]][3:6])) / FIELD_GAUSS if s == "mag" else 1.0
        sl = SENSOR_SLICE[s]
        q[sl.start : sl.start + 3] = (dens * unit * rw) ** 2
        q[sl.start + 3 : sl.stop] = (dens / spec.full_scale * rw) ** 2
    q[DIP] = (1e-6) ** 2
    for sl, sig in ext:
        q[sl] = (sig * rw) ** 2
    return q


def test_noise_caches_equal_the_uncached_formulas_as_the_state_moves() -> None:
    """A mag scale that moves every block (as every update moves it), the rate changing twice, the state
    size once (an extension): spec σ and the random walk equal the formulas at every call (to 1e-12
    relative; they are the same products), where the former cache keyed on the rounded unit lagged."""
    rng = np.random.default_rng(5)
    nm = NoiseModel(UKFConfig().sensor_specs())
    s0 = SENSOR_SLICE["mag"].start + 3
    for i in range(300):
        n = N_STATE if i < 200 else N_STATE + 3
        ext = [] if i < 200 else [(slice(N_STATE, N_STATE + 3), 0.01)]
        rate = 200.0 if i < 100 else (None if i < 250 else 400.0)
        x = np.zeros(n)
        x[s0 : s0 + 3] = 2.0 * (1 + 1e-7 * rng.normal(size=3)) * (1 + 1e-3 * math.sin(i / 7))
        sp, ref = nm.spec_noise(rate, x), _spec_uncached(nm, rate or 100.0, x)
        assert sp.keys() == ref.keys()
        for k in ref:
            assert sp[k] == pytest.approx(ref[k], rel=1e-12, abs=0), (i, k)
        q, qr = nm.cal_rw(n, x, ext, 0.7), _rw_uncached(nm, n, x, ext, 0.7)
        assert q.shape == qr.shape and np.allclose(q, qr, rtol=1e-12, atol=0), i


# ---------------------------------------------------------------- rail detector
def _top_rule(det: RailDetector, s: str, v, amax, rail_min: float) -> bool:
    """The recurring-top rule as specs.rail_samples states it for a whole log, kept per block: the largest
    magnitude so far and the samples within RAIL_TOL of it since it last rose beyond that; RAIL_SAMPLES of them
    above rail_min make a rail at top·(1 − RAIL_TOL). True where this block made one known."""
    top = det.top.setdefault(s, [0.0] * 3)
    n = det.n_top.setdefault(s, [0] * 3)
    made = False
    for k in range(3):
        x = float(amax[k])
        if np.isnan(x) or x < top[k] * (1 - RAIL_TOL):
            continue
        lim = max(top[k], x) * (1 - RAIL_TOL)
        n[k] = 0 if lim > top[k] else n[k]
        top[k] = max(top[k], x)
        if x >= rail_min:
            n[k] += int(np.sum(np.abs(v[:, k]) >= lim))
            rail = det.rail.get(s)
            if n[k] >= RAIL_SAMPLES and (rail is None or rail[k] > lim):
                r = det.rail.setdefault(s, [math.inf] * 3)
                r[k] = min(r[k], lim)
                made = True
    return made


def _check_per_axis(det: RailDetector, w, a, w_absmax, a_absmax, rail_min, rail_run):
    """RailDetector.check as it was (the runs of every axis of every block through _runs), and the
    recurring-top rule (session 16)."""
    out, events = {"mag": False}, []
    for s, v, amax in (("gyro", w, w_absmax), ("accel", a, a_absmax)):
        rail = det.rail.get(s)
        hit = rail is not None and bool(np.any(amax >= np.asarray(rail) * (1 - 1e-9)))
        hit = _top_rule(det, s, v, amax, rail_min[s]) or hit
        if float(amax.max()) < rail_min[s]:
            det.run.pop(s, None)
        else:
            carry = det.run.get(s)
            new_carry = []
            for k in range(3):
                col = v[:, k]
                starts, lens = _runs(col, None if carry is None else carry[k])
                new_carry.append((float(col[-1]), int(lens[-1])))
                i = int(np.argmax(lens))
                val = abs(float(col[starts[i]]))
                if lens[i] >= rail_run and val >= rail_min[s]:
                    r = det.rail.setdefault(s, [math.inf] * 3)
                    r[k] = min(r[k], val)
                    hit = True
            det.run[s] = new_carry
        if hit and not det.clip_on[s]:
            events.append(("saturation", s))
        det.clip_on[s] = hit
        out[s] = hit
    return out, [e[0] for e in events]


@pytest.mark.parametrize("L", [1, 2, 20, 39, 40, 60])
def test_rail_detector_short_blocks_equal_the_per_axis_runs(L: int) -> None:
    """Blocks of L samples (L < rail_run = 40: one numpy pass, or the runs precomputed over the whole feed by
    block_runs; L ≥ 40: the per-axis rule itself) with
    readings from a coarse set that holds runs across blocks, at and below the rail magnitude, NaN now
    and then: the same flags, events, learnt rails and open runs after every block; rails are learnt."""
    rng = np.random.default_rng(L)
    rail_min, rail_run = {"gyro": 1.0, "accel": 14.7}, 40
    new, ref, pre = RailDetector(), RailDetector(), RailDetector()
    levels = {"gyro": np.array([-4.3, -1.5, 0.2, 0.9, 2.0, 4.3]), "accel": np.array([-19.6, -9.8, 0.1, 9.8, 19.6])}
    learnt = 0
    last = {s: rng.choice(levels[s], size=3) for s in levels}
    p_change = min(0.4, 1.5 * L / rail_run)  # per block and axis: runs of rail_run samples happen
    feed = []
    for _ in range(400):
        vs = {}
        for s in ("gyro", "accel"):
            v = np.repeat(last[s][None, :], L, axis=0)
            for k in range(3):  # the held value changes at a random sample on some axes
                if rng.random() < p_change:
                    v[int(rng.integers(0, L)):, k] = rng.choice(levels[s])
                if rng.random() < 0.01:
                    v[int(rng.integers(0, L)), k] = math.nan
            last[s] = np.where(np.isnan(v[-1]), rng.choice(levels[s], size=3), v[-1])
            vs[s] = v
        feed.append((vs["gyro"], vs["accel"]))
    # the runs of every block at once, over the whole feed (as block_stats forms them)
    lo = np.arange(400, dtype=np.intp) * L
    runs = [block_runs(np.concatenate([f[k] for f in feed]), lo, lo + L) for k in (0, 1)]
    for blk, (w, a) in enumerate(feed):
        wm, am = np.nan_to_num(np.abs(w)).max(axis=0), np.nan_to_num(np.abs(a)).max(axis=0)
        o_new, e_new = new.check(w, a, wm, am, rail_min, rail_run)
        o_pre, e_pre = pre.check(w, a, wm, am, rail_min, rail_run, (runs[0][blk], runs[1][blk]))
        o_ref, e_ref = _check_per_axis(ref, w, a, wm, am, rail_min, rail_run)
        assert o_new == o_ref and [e[0] for e in e_new] == e_ref, blk
        assert o_pre == o_ref and [e[0] for e in e_pre] == e_ref, blk
        # (repr: a NaN reading in an open run compares unequal to itself)
        for d in (new, pre):
            assert repr(d.rail) == repr(ref.rail) and repr(d.run) == repr(ref.run) and d.clip_on == ref.clip_on, blk
            assert d.top == ref.top and d.n_top == ref.n_top, blk
        if blk % 97 == 50:  # a learnt rail forgotten, so that learning happens again
            for d in (new, pre, ref):
                d.rail.pop("gyro", None)
                d.top.pop("gyro", None)
                d.n_top.pop("gyro", None)
        learnt += bool(new.rail)
    assert learnt > 0


# ---------------------------------------------------------------- magnetic disturbance gate
def _judge_numpy(x, sig, m_raw, a_raw, gravity, accel_is_gravity=True):
    """MagDisturbanceGate.judge as it was: calibrated, norm_sigma and dip_of on numpy arrays."""
    h = md.calibrated(x, "mag", m_raw.mean(axis=0))
    dev = float(np.linalg.norm(h)) - 1.0
    tol = max(md.NORM_MIN, md.NORM_K * md.norm_sigma(x, sig, h))
    if abs(dev) > tol:
        return f"field norm {1 + dev:.2f} of the model's 1 (tolerance ±{tol:.2f})"
    f = md.calibrated(x, "accel", a_raw.mean(axis=0))
    if accel_is_gravity and abs(float(np.linalg.norm(f)) / gravity - 1.0) < md.STATIC_G:
        d = math.degrees(md.dip_of(h, f) - float(x[DIP]))
        tol_d = max(md.DIP_MIN_DEG, md.DIP_K * math.degrees(float(sig[DIP])))
        if abs(d) > tol_d:
            return f"dip {math.degrees(md.dip_of(h, f)):.1f}° against the model's {math.degrees(x[DIP]):.1f}°"
    return None


def test_disturbance_gate_on_floats_judges_as_numpy() -> None:
    """Random calibrations (scale 0.5–2 with its inverse field unit, angles up to 0.2 rad, biases), fields
    disturbed by 0–60 % and turned by 0–30° in dip, accel near and off g, σ from tight to loose: the block's
    verdict (and its text) is that of the numpy functions; the calibrated field agrees to 1e-12; every
    verdict occurs."""
    rng = np.random.default_rng(11)
    sm, sa = SENSOR_SLICE["mag"], SENSOR_SLICE["accel"]
    seen: dict[str, int] = {"none": 0, "norm": 0, "dip": 0}
    for trial in range(800):
        x = np.zeros(N_STATE)
        unit = 10 ** rng.uniform(-1, 3)
        x[sm] = np.concatenate([rng.normal(0, 0.2 * unit, 3), rng.uniform(0.8, 1.25, 3) / unit,
                                rng.normal(0, 0.1, 6)])
        x[sa] = np.concatenate([rng.normal(0, 0.2, 3), rng.uniform(0.98, 1.02, 3), rng.normal(0, 0.02, 6)])
        x[DIP] = rng.uniform(-1.2, 1.2)
        sig = 10 ** rng.uniform(-4, -1, N_STATE)
        sig[DIP] = 10 ** rng.uniform(-3, -0.5)
        # a world field turned to the body by a random attitude, the raw reading through the inverse model
        ang = rng.normal(0, 1, 3)
        th = np.linalg.norm(ang)
        K = np.array([[0, -ang[2], ang[1]], [ang[2], 0, -ang[0]], [-ang[1], ang[0], 0]]) / th
        R = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
        dip = x[DIP] + math.radians(rng.uniform(-30, 30)) * (trial % 3 == 0)
        h_b = R.T @ np.array([0.0, math.cos(dip), -math.sin(dip)]) * (1 + rng.uniform(-0.6, 0.6) * (trial % 3 == 1))
        f_b = R.T @ np.array([0.0, 0.0, 9.81]) * (1 + rng.normal(0, 0.01))
        o_m, M_m = md.correction(x[None, sm])
        o_a, M_a = md.correction(x[None, sa])
        m_raw = np.linalg.solve(M_m[0], h_b) + o_m[0] + rng.normal(0, 1e-3 / x[sm][3], (5, 3))
        a_raw = np.linalg.solve(M_a[0], f_b) + o_a[0] + rng.normal(0, 1e-3, (20, 3))
        h_np = md.calibrated(x, "mag", m_raw.mean(axis=0))
        h_py = md.calibrated_floats(x[sm].tolist(), m_raw.mean(axis=0).tolist())
        assert np.allclose(h_py, h_np, rtol=1e-12, atol=1e-12 * np.linalg.norm(h_np))
        for veh in (True, False):
            why = md.MagDisturbanceGate().judge(x, sig, m_raw, a_raw, 9.81, veh)
            assert why == _judge_numpy(x, sig, m_raw, a_raw, 9.81, veh), trial
            seen["none" if why is None else why.split()[0].replace("field", "norm")] += 1
    assert min(seen.values()) >= 50, seen


# ---------------------------------------------------------------- Earth-rate noise and motion coverage
def test_earth_rate_noise_on_python_floats_equals_the_numpy_form_bit_for_bit() -> None:
    """:func:`.vehicle.earth_rate_noise` element by element against the numpy form it replaces (the bias
    topped up with np.maximum, the attitude's constant added), with the gyro's mean scale as np.mean forms
    it: the same bits, NaN variances included; both branches of the top-up occur."""
    from onlinecal.ukf.layout import ATT, index
    from onlinecal.ukf.vehicle import OMEGA_E_HORIZONTAL_RMS, earth_rate_noise

    rng = np.random.default_rng(5)
    b = index("gyro", "bias")
    raised = kept = 0
    for trial in range(3000):
        n = 40
        P = np.diag(10 ** rng.uniform(-14, -6, n))
        if trial % 50 == 0:
            P[b.start + 1, b.start + 1] = np.nan
        q = rng.uniform(0, 1e-9, n)
        x = rng.normal(1, 0.05, n)
        sx, sy, sz = x[3:6].tolist()
        s_gyr = (sx + sy + sz) / 3.0
        assert s_gyr == float(np.mean(x[3:6]))
        sigma, tau, dt = 4.2e-5, rng.uniform(1, 60), rng.uniform(0.01, 0.2)
        ref = q.copy()
        ref[b] += np.maximum(0.0, (sigma / s_gyr) ** 2 - np.diag(P)[b])
        ref[ATT] += OMEGA_E_HORIZONTAL_RMS**2 * tau * dt
        new = earth_rate_noise(q.copy(), P, b, s_gyr, (sigma,) * 3, tau, dt)
        assert np.array_equal(new, ref, equal_nan=True), trial
        raised += int(((sigma / s_gyr) ** 2 > np.diag(P)[b]).sum())
        kept += int(((sigma / s_gyr) ** 2 <= np.diag(P)[b]).sum())
    assert raised > 1000 and kept > 1000


def test_motion_coverage_on_python_floats_equals_the_numpy_form_bit_for_bit() -> None:
    """:meth:`.vehicle.MotionCoverage.add_motion` against the numpy form it replaces (np.abs, np.maximum in
    place, angle += |ω| dt) over 2000 blocks with NaN rates now and then: the same maxima and angles."""
    from onlinecal.ukf.vehicle import MotionCoverage

    rng = np.random.default_rng(6)
    cov = MotionCoverage()
    mx, ang, fl = np.zeros(3), np.zeros(3), 0.0
    for k in range(2000):
        w = rng.normal(0, 10 ** rng.uniform(-3, 1), 3)
        if k % 397 == 11:
            w[k % 3] = np.nan
        dt, air = float(rng.uniform(0.05, 0.15)), bool(k % 3)
        cov.add_motion(w, dt, air)
        r = np.abs(w)
        np.maximum(mx, r, out=mx)
        ang += r * dt
        fl += dt if air else 0.0
        assert np.array_equal(cov.max_rate, mx, equal_nan=True) and np.array_equal(cov.angle, ang, equal_nan=True)
        assert cov.flight_s == fl


def _rest_update_numpy(det, B, b, n, k, rest_blocks):
    """RestDetector.update as it was: max over the axes with numpy."""
    L = int(B.hi[b] - B.lo[b])
    n_m = int(B.mhi[b] - B.mlo[b])
    gm, am = B.w_mean[b], B.a_mean[b]
    mm = B.m_mean[b] if n_m else None
    sg, sa = n["gyro"], n["accel"]
    still = L >= 3 and float(B.w_std[b].max()) < k * sg and float(B.a_std[b].max()) < k * sa
    prev = det.prev_means
    if prev is not None and still:
        d = math.sqrt(2.0 / L)
        still = (float(np.abs(gm - prev[0]).max()) < 2 * k * sg * d
                 and float(np.abs(am - prev[1]).max()) < 2 * k * sa * d)
        if still and mm is not None and prev[2] is not None:
            still = float(np.abs(mm - prev[2]).max()) < 2 * k * n["mag"] * math.sqrt(2.0 / n_m)
    det.prev_means = (gm, am, mm if mm is not None else (prev[2] if prev is not None else None))
    det.count = det.count + 1 if still else 0
    det.still = still
    return det.count >= rest_blocks


def test_rest_detector_on_python_floats_makes_the_numpy_decisions() -> None:
    """RestDetector.update with its "max over the axes" on Python floats against the numpy form: the same
    verdicts, counts and previous means over 3000 blocks of still and moving readings near the bounds,
    blocks without mag, short blocks and NaN now and then; rests are found and ended."""
    from types import SimpleNamespace

    from onlinecal.ukf.detectors import RestDetector

    rng = np.random.default_rng(8)
    nb = 3000
    lo = np.arange(nb) * 20
    hi = lo + np.where(rng.random(nb) < 0.05, 2, 20)
    mcnt = np.where(rng.random(nb) < 0.2, 0, 5)
    mlo = np.concatenate([[0], np.cumsum(mcnt)[:-1]])
    level = np.repeat(rng.normal(0, 1, (nb // 50, 1, 3)), 50, axis=0).reshape(nb, 3)
    B = SimpleNamespace(lo=lo, hi=hi, mlo=mlo, mhi=mlo + mcnt,
                        w_mean=level * 0.01 + rng.normal(0, 2e-3, (nb, 3)),
                        a_mean=level + rng.normal(0, 0.012, (nb, 3)),
                        m_mean=level * 0.1 + rng.normal(0, 1.5e-3, (nb, 3)), w_std=rng.uniform(0, 0.0125, (nb, 3)),
                        a_std=rng.uniform(0, 0.083, (nb, 3)))
    B.lo_l, B.hi_l, B.mlo_l, B.mhi_l = lo.tolist(), hi.tolist(), mlo.tolist(), B.mhi.tolist()  # Blocks' lists
    for arr in (B.w_mean, B.a_std, B.m_mean):
        arr[rng.random(nb) < 0.01, 1] = np.nan
    n = {"gyro": 3e-3, "accel": 0.02, "mag": 3e-3}
    new, ref = RestDetector(), RestDetector()
    rests = 0
    for b in range(nb):
        r_new, r_ref = new.update(B, b, n, 4.0, 3), _rest_update_numpy(ref, B, b, n, 4.0, 3)
        assert (r_new, new.count, new.still) == (r_ref, ref.count, ref.still), b
        assert all((x is None and y is None) or np.array_equal(x, y, equal_nan=True)
                   for x, y in zip(new.prev_means, ref.prev_means, strict=True))
        rests += r_new
    assert 100 < rests < nb - 100, rests


def test_the_block_means_are_the_gates_means_to_rounding() -> None:
    """The disturbance gate takes the block's mean mag and accel readings from :func:`.blocks.block_stats`
    (``means``) instead of forming ``mean(axis=0)`` again. block_stats sums each segment with np.add.reduceat,
    numpy's mean sums in its own order: the two agree to rounding (within the sums' rounding bound, checked on
    blocks of 1–40 IMU samples and 0–9 mag samples of readings with large offsets), so the gate's verdict can
    differ only for a field within ~1e-15 of its tolerance — and on 400 fields drawn around the tolerance (norm
    and dip) the verdicts with and without ``means`` are the same."""
    from onlinecal.ukf.blocks import block_stats

    rng = np.random.default_rng(3)
    N = 4000
    t = 0.005 * np.arange(1, N + 1)
    w = rng.normal(0.3, 1.0, (N, 3))
    a = rng.normal(0.0, 0.4, (N, 3)) + [1e3 / 7, -9.81, 3.3e2]
    tm = np.sort(rng.uniform(t[0], t[-1], 800))
    m = rng.normal(0.0, 1.0, (800, 3)) * [1e-3, 0.37, 1e4] + [0.11, 412.3, -7e4]
    bounds, i = [], 0
    while i < N:
        j = min(N, i + int(rng.integers(1, 41)))
        bounds.append((i, j))
        i = j
    B = block_stats(t, w, a, tm, m, bounds, None, np.zeros(3), False)
    n_mag, differ = set(), 0
    for b, (i, j) in enumerate(bounds):
        for got, seg in ((B.a_mean[b], a[i:j]), (B.m_mean[b], m[int(B.mlo[b]) : int(B.mhi[b])])):
            if seg.shape[0] == 0:
                continue
            want = seg.mean(axis=0)
            # both within the recursive sum's error bound, (n − 1) u Σ|a_i| / n, of the exact mean
            bound = 2 * seg.shape[0] * np.finfo(float).eps * np.abs(seg).mean(axis=0)
            assert np.all(np.abs(got - want) <= bound), (b, got - want)
            differ += not np.array_equal(got, want)
        n_mag.add(int(B.mhi[b] - B.mlo[b]))
    assert {0, 1, 2, 5, 9} <= n_mag, n_mag
    assert differ > 0  # (the orders of the sums do differ: the bound above is what holds)
    # the gate's verdicts with and without ``means``, on fields around the norm tolerance and the dip's
    x = np.zeros(N_STATE)
    x[SENSOR_SLICE["mag"]] = np.r_[0.0, 0.0, 0.0, 1.0, 1.0, 1.0, np.zeros(6)]
    x[SENSOR_SLICE["accel"]] = np.r_[np.zeros(3), np.ones(3), np.zeros(6)]
    x[DIP] = math.radians(60.0)
    sig = np.full(N_STATE, 1e-3)
    seen = set()
    for k in range(400):
        norm = 1.0 + (md.NORM_MIN * rng.uniform(0.9, 1.1) if k % 2 else 0.0)
        dip = x[DIP] + math.radians(md.DIP_MIN_DEG * rng.uniform(0.9, 1.1) * (k % 4 == 0))
        mb = np.tile([0.0, norm * math.cos(dip), -norm * math.sin(dip)], (5, 1)) + rng.normal(0, 1e-3, (5, 3))
        ab = np.tile([0.0, 0.0, 9.81], (20, 1)) + rng.normal(0, 1e-2, (20, 3))
        g = md.MagDisturbanceGate()
        why = g.judge(x, sig, mb, ab, 9.81)
        assert why == g.judge(x, sig, mb, ab, 9.81, means=(mb.mean(axis=0), ab.mean(axis=0))), k
        seen.add(None if why is None else why.split()[0])
    assert seen == {None, "field", "dip"}, seen


def test_sigma_is_the_clipped_square_root_bit_for_bit() -> None:
    """OnlineCalibrator.sigma (np.maximum on the diagonal) against the np.clip form it replaced: the same bits,
    with negative, zero, tiny and NaN variances."""
    from onlinecal.ukf import OnlineCalibrator

    cal = OnlineCalibrator(None)
    rng = np.random.default_rng(8)
    d = 10 ** rng.uniform(-30, 4, cal.n)
    d[:4] = [-1e-20, 0.0, np.nan, -3.0]
    cal.P = np.diag(d) + np.triu(rng.normal(0, 1e-9, (cal.n, cal.n)), 1)
    want = np.sqrt(np.clip(np.diag(cal.P), 0.0, None))
    assert np.array_equal(cal.sigma(), want, equal_nan=True)
    assert np.isnan(cal.sigma()[2]) and cal.sigma()[0] == 0.0 and cal.sigma()[3] == 0.0


def test_a_rests_direction_formed_lazily_gives_add_rests_directions_and_time() -> None:
    """MotionCoverage.add_rest_lazy (the exact vector formed only where the rounding-level approximation could
    decide otherwise) against add_rest on every block: the same stored directions bit for bit, the same rest time,
    over drawn rests — many blocks near one attitude, new attitudes, directions within 1e-7 of the 20° boundary,
    zero and NaN vectors — and the exact vector is formed in only a small share of the blocks."""
    from onlinecal.ukf.vehicle import MotionCoverage

    rng = np.random.default_rng(4)
    a, b = MotionCoverage(), MotionCoverage()
    formed = {"n": 0}
    blocks = 0
    for rest in range(120):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        if rest % 10 == 3 and a.rest_dirs:  # at the 20° boundary of a stored direction, either side by ≤ 1e-7
            d = np.array(a.rest_dirs[0])
            perp = np.cross(d, rng.normal(size=3))
            perp /= np.linalg.norm(perp)
            ang = math.radians(20) + rng.uniform(-1e-7, 1e-7)
            u = math.cos(ang) * d + math.sin(ang) * perp
        for _ in range(int(rng.integers(1, 30))):
            exact = 9.81 * (u + rng.normal(0, 1e-3, 3)) * rng.uniform(0.5, 2.0)
            if rest == 50:
                exact = np.zeros(3)
            if rest == 51:
                exact = np.array([np.nan, 0.0, 1.0])
            approx = exact * (1 + rng.uniform(-3e-16, 3e-16, 3))  # what calibrated_floats gives: rounding apart

            def formed_exact(v=exact):
                formed["n"] += 1
                return v

            a.add_rest(exact, 0.1)
            b.add_rest_lazy(approx.tolist(), 0.1, formed_exact)
            blocks += 1
    assert a.rest_dirs == b.rest_dirs and a.rest_s == b.rest_s
    assert 10 <= len(a.rest_dirs) <= 64
    assert formed["n"] < 0.25 * blocks, (formed["n"], blocks)
