"""The effects library (onlinecal.sim.effects) and its inverses (onlinecal.extensions).

Every effect is compared against the clean session of the same seed: effects never draw from the session's
generator, so the white-noise draws are identical and ``raw_effect − raw_clean`` is the effect alone, up to
the ADC's quantisation (one LSB).
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from onlinecal.extensions import (
    clipped_mask,
    correct,
    extensions_from_effects,
    process_noise,
    uninvert_nonlinearity,
    validate_extensions,
)
from onlinecal.sim import Truth, simulate
from onlinecal.sim.effects import (
    EFFECT_KEYS,
    EFFECTS,
    BiasDrift,
    EffectError,
    TemperatureBias,
    from_describe,
    parse_effect,
    random_effect,
)
from onlinecal.sim.sensors import ACCEL_SPEC, GYRO_SPEC, MAG_SPEC

SEED = 11
LSB = {"gyro": GYRO_SPEC.lsb, "accel": ACCEL_SPEC.lsb, "mag": MAG_SPEC.lsb}
FIELD = {"gyro": "gyro", "accel": "acc", "mag": "mag"}


@pytest.fixture(scope="module")
def clean():
    return simulate("paper", SEED)


def sim(*specs):
    return simulate("paper", SEED, effects=[parse_effect(s) for s in specs])


def raw(s, sensor):
    return getattr(getattr(s, "data", s), FIELD[sensor])


# -- noise alignment --------------------------------------------------------------------------------

@pytest.mark.parametrize("spec, touched", [
    ("temperature_bias", {"gyro"}), ("bias_drift:sensor=accel", {"accel"}), ("g_sensitivity", {"gyro"}),
    ("time_offset", {"mag"}), ("saturation", {"gyro"}), ("scale_nonlinearity", {"gyro"}),
    ("lever_arm", {"accel"}), ("axis_sign:sensor=mag,axis=x", {"mag"}),
])
def test_untouched_sensors_are_bit_identical(clean, spec, touched):
    """The noise draws stay aligned: a sensor an effect does not act on is bit-identical to the clean run."""
    s = sim(spec)
    for sensor in {"gyro", "accel", "mag"} - touched:
        assert np.array_equal(raw(s, sensor), raw(clean, sensor)), sensor
    for sensor in touched:
        assert not np.array_equal(raw(s, sensor), raw(clean, sensor)), sensor
    assert np.array_equal(s.data.t_imu, clean.data.t_imu) and np.array_equal(s.data.t_mag, clean.data.t_mag)
    if "temperature_bias" not in spec:
        assert np.array_equal(s.data.temp, clean.data.temp)


# -- physics of each effect -------------------------------------------------------------------------

def expected_temperature(t, rise, tau):
    t_end = t[-1]
    return 25 + rise * (1 - np.exp(-t / tau)) - 0.5 * rise * (1 - np.exp(-np.maximum(0, t - t_end / 2) / tau))


@pytest.mark.parametrize("sensor, coeff", [("gyro", 8e-4), ("accel", -6e-3)])
def test_temperature_bias_on_one_axis(clean, sensor, coeff):
    s = sim(f"temperature_bias:sensor={sensor},axis=y,coeff={coeff},rise=12,tau=60")
    t = s.data.t_imu
    T = expected_temperature(t, 12.0, 60.0)
    # the logged temperature is the warm-up with a partial cool-down (σ 0.02 °C, 0.01 °C steps)
    assert np.abs(s.data.temp - T).max() < 0.1
    i_peak = int(np.argmax(T))
    assert 0.4 * t[-1] < t[i_peak] < 0.7 * t[-1] and T[i_peak] - T[-1] > 3.0  # not a linear function of t
    d = raw(s, sensor) - raw(clean, sensor)
    assert np.abs(d[:, 1] - coeff * (T - 25)).max() <= LSB[sensor] * 1.001
    assert np.abs(coeff * (T - 25)).max() > 10 * LSB[sensor]  # the effect is well above one LSB
    assert np.all(d[:, [0, 2]] == 0)


def test_bias_drift_walk_statistics():
    """Increments of the walk are N(0, density²·dt): variance within 4 sampling σ (χ², sd √(2/n))."""
    e = BiasDrift(axis=None, density=2e-4)
    t = np.arange(200_001) / 200.0
    b = e.walk(t, np.random.default_rng(5))
    assert np.all(b[0] == 0)
    inc = np.diff(b, axis=0)
    ratio = inc.var(axis=0) / (2e-4**2 * (1 / 200.0))
    assert np.abs(ratio - 1).max() < 4 * np.sqrt(2 / inc.shape[0])
    assert np.abs(np.corrcoef(inc.T)[np.triu_indices(3, 1)]).max() < 0.02  # independent axes


def test_bias_drift_in_the_session(clean):
    """The session's raw − clean is the walk: its 1-s block means have the random walk's Allan variance
    E[(ȳ_{k+1} − ȳ_k)²] = (2/3)·density²·τ (plus the quantisation's share), and it ends where the walk ends."""
    density = 3e-4
    s = sim(f"bias_drift:sensor=gyro,density={density}")
    d = raw(s, "gyro") - raw(clean, "gyro")
    n = 100  # 1 s blocks at 100 Hz
    m = d[: (d.shape[0] // n) * n].reshape(-1, n, 3).mean(axis=1)
    diffs = np.diff(m, axis=0).ravel()
    expected = 2 / 3 * density**2 * 1.0 + 2 * (2 * LSB["gyro"] ** 2 / 12) / n
    ratio = np.mean(diffs**2) / expected
    assert abs(ratio - 1) < 4 * np.sqrt(2 / diffs.size)
    final = np.array(s.truth.effects[0]["walk_final"])
    assert np.abs(d[-50:].mean(axis=0) - final).max() < 2e-4


def test_g_sensitivity_follows_specific_force(clean):
    s = sim("g_sensitivity:axis=x,coeff=4e-4")
    f = s.trajectory.evaluate(s.data.t_imu).f
    d = raw(s, "gyro") - raw(clean, "gyro")
    assert np.abs(d[:, 0] - 4e-4 * f[:, 0]).max() <= LSB["gyro"] * 1.001
    assert np.all(d[:, 1:] == 0)
    assert np.ptp(4e-4 * f[:, 0]) > 10 * LSB["gyro"]


def lag_by_correlation(t, y, t_ref, y_ref, lags):
    """The lag τ minimising ‖y(t) − y_ref(t − τ)‖² (least-squares cross-correlation, linear interpolation)."""
    cost = [sum(np.sum((y[:, k] - np.interp(t - tau, t_ref, y_ref[:, k])) ** 2) for k in range(3)) for tau in lags]
    return lags[int(np.argmin(cost))]


@pytest.mark.parametrize("sensor, seconds", [("mag", 0.05), ("gyro", -0.03), ("accel", 0.013)])
def test_time_offset_recovered_by_cross_correlation(clean, sensor, seconds):
    s = sim(f"time_offset:sensor={sensor},seconds={seconds}")
    t = s.data.t_mag if sensor == "mag" else s.data.t_imu
    moving = (t > 150) & (t < 290)  # rotation phases and the tumble
    lags = np.round(np.arange(-0.1, 0.1, 0.001), 6)
    lag = lag_by_correlation(t[moving], raw(s, sensor)[moving], t, raw(clean, sensor), lags)
    assert abs(lag - seconds) <= 0.0015


def test_saturation_clips_at_exactly_the_limit(clean):
    limit = 1.7  # not on the LSB grid of the gyro
    s = sim(f"saturation:sensor=gyro,limit={limit}")
    g, c = raw(s, "gyro"), raw(clean, "gyro")
    top = round(limit / LSB["gyro"]) * LSB["gyro"]  # the quantiser's top code below/at the rail
    at_rail = np.abs(c) >= top
    assert at_rail.sum() > 100
    assert np.all(np.abs(g[at_rail]) == limit) and np.all(np.sign(g[at_rail]) == np.sign(c[at_rail]))
    assert np.array_equal(g[~at_rail], c[~at_rail])
    assert np.abs(g).max() == limit
    frac = s.truth.effects[0]["clipped_fraction"]
    assert frac == pytest.approx(np.mean(np.any(np.abs(g) == limit, axis=1)))
    ext = extensions_from_effects(s.truth.effects)
    assert np.array_equal(clipped_mask(s.data, ext, rtol=0)["gyro"], at_rail)
    loose = clipped_mask(s.data, ext)["gyro"]  # rtol 1e-3 for a log's rounding: also within 0.1 % of the rail
    assert np.all(loose[at_rail]) and np.all(np.abs(g[loose]) >= limit * (1 - 1e-3))


def test_saturation_default_limit_is_125_dps(clean):
    s = sim("saturation")
    assert s.truth.effects[0]["limit"] == pytest.approx(np.radians(125), rel=1e-3)
    assert np.abs(raw(s, "gyro")).max() == s.truth.effects[0]["limit"]


def test_scale_nonlinearity(clean):
    c_ = 4e-3
    s = sim(f"scale_nonlinearity:sensor=gyro,axis=z,coeff={c_}")
    g, c = raw(s, "gyro"), raw(clean, "gyro")
    # raw ← raw(1 + c|raw|) before the noise: the noise σ passes with gain 1 + 2c|raw| (≤ 1.03 here)
    sigma = clean.truth.noise["gyro"]
    err = g[:, 2] - c[:, 2] * (1 + c_ * np.abs(c[:, 2]))
    assert np.abs(err).max() <= LSB["gyro"] + 2 * c_ * np.abs(c[:, 2]).max() * 5 * sigma
    assert np.abs(c_ * c[:, 2] * np.abs(c[:, 2])).max() > 20 * LSB["gyro"]
    assert np.all(g[:, :2] == c[:, :2])


def test_lever_arm_matches_rigid_body_formula(clean):
    r = np.array([0.08, -0.04, 0.03])
    s = sim(f"lever_arm:x={r[0]},y={r[1]},z={r[2]}")
    t = s.data.t_imu
    h = 1e-4  # a different step than the simulator's, central difference of the analytic rate
    m = s.trajectory.evaluate(t)
    w_dot = (s.trajectory.evaluate(t + h).omega - s.trajectory.evaluate(t - h).omega) / (2 * h)
    a = np.cross(w_dot, r) + np.cross(m.omega, np.cross(m.omega, r))  # body frame, m/s²
    M = s.truth.calibration.accel.matrix
    expected = a @ np.linalg.inv(M).T  # the accelerometer's model maps it to raw units
    d = raw(s, "accel") - raw(clean, "accel")
    assert np.abs(d - expected).max() <= LSB["accel"] * 1.01
    assert np.abs(expected).max() > 0.3


@pytest.mark.parametrize("sensor, axis", [("gyro", "z"), ("accel", "x"), ("mag", "y")])
def test_axis_sign_flips_one_axis(clean, sensor, axis):
    s = sim(f"axis_sign:sensor={sensor},axis={axis}")
    k = "xyz".index(axis)
    x, c = raw(s, sensor), raw(clean, sensor)
    assert np.array_equal(x[:, k], -c[:, k])
    others = [i for i in range(3) if i != k]
    assert np.array_equal(x[:, others], c[:, others])


# -- parsing, combining, describing -----------------------------------------------------------------

@pytest.mark.parametrize("spec, fragment", [
    ("no_such", "unknown effect 'no_such'"),
    ("time_offset:secs=0.1", "unknown key 'secs' (valid: sensor, seconds)"),
    ("time_offset:sensor=baro", "sensor must be one of gyro, accel, mag"),
    ("g_sensitivity:sensor=accel", "sensor must be one of gyro"),
    ("temperature_bias:coeff=abc", "coeff must be a number"),
    ("temperature_bias:tau=-5", "tau must be > 0"),
    ("bias_drift:density=nan", "density must be finite"),
    ("saturation:limit=0", "limit must be > 0"),
    ("axis_sign:axis=q", "axis must be x, y, z or all"),
    ("lever_arm:x=0.1,x=0.2", "key 'x' given twice"),
    ("lever_arm:x", "expected key=value"),
    ("time_offset:seconds=5", "seconds must be <= 1"),
])
def test_parse_errors_name_the_spec_and_the_problem(spec, fragment):
    with pytest.raises(EffectError) as ei:
        parse_effect(spec)
    msg = str(ei.value)
    assert fragment in msg and repr(spec) in msg and "\n" not in msg


def test_parse_values_and_defaults():
    e = parse_effect("temperature_bias:sensor=accel,axis=x,coeff=3e-3")
    assert isinstance(e, TemperatureBias) and (e.sensor, e.axis, e.coeff, e.rise, e.tau) == ("accel", "x", 3e-3, 15, 90)
    assert parse_effect("g_sensitivity:axis=all").axis is None
    assert parse_effect("saturation:sensor=accel").limit == pytest.approx(2 * 9.80665, rel=1e-3)
    assert parse_effect(" time_offset : sensor = gyro , seconds = -0.02 ").seconds == -0.02


def test_two_effects_combine_and_order_does_not_matter(clean):
    a, b = "temperature_bias:sensor=accel,axis=y,coeff=5e-3", "time_offset:sensor=mag,seconds=0.05"
    s1, s2 = sim(a, b), sim(b, a)
    for f in ("gyro", "acc", "mag", "temp"):
        assert np.array_equal(getattr(s1.data, f), getattr(s2.data, f))
    only_mag = sim(b)
    assert np.array_equal(s1.data.mag, only_mag.data.mag)  # the temperature effect leaves mag alone
    T = expected_temperature(s1.data.t_imu, 15.0, 90.0)
    d = raw(s1, "accel") - raw(clean, "accel")
    assert np.abs(d[:, 1] - 5e-3 * (T - 25)).max() <= LSB["accel"] * 1.001
    assert [e["effect"] for e in s1.truth.effects] == ["temperature_bias", "time_offset"]


def test_time_offset_then_lever_arm_uses_the_shifted_motion(clean):
    """Stages: the lever arm acts on the motion at the accelerometer's (shifted) instants."""
    s = sim("lever_arm:x=0.1,y=0,z=0", "time_offset:sensor=accel,seconds=0.04")
    only_shift = sim("time_offset:sensor=accel,seconds=0.04")
    t = s.data.t_imu - 0.04
    m = s.trajectory.evaluate(t)
    h = 1e-4
    w_dot = (s.trajectory.evaluate(t + h).omega - s.trajectory.evaluate(t - h).omega) / (2 * h)
    r = np.array([0.1, 0, 0])
    a = (np.cross(w_dot, r) + np.cross(m.omega, np.cross(m.omega, r))) @ np.linalg.inv(
        s.truth.calibration.accel.matrix).T
    assert np.abs(raw(s, "accel") - raw(only_shift, "accel") - a).max() <= LSB["accel"] * 1.01


@pytest.mark.parametrize("specs", [
    ("time_offset:sensor=mag", "time_offset:sensor=mag,seconds=0.01"),
    ("axis_sign:sensor=gyro,axis=x", "axis_sign:sensor=gyro,axis=all"),
    ("temperature_bias:sensor=gyro,axis=x", "temperature_bias:sensor=accel,rise=5"),
])
def test_conflicting_combinations_are_refused(specs):
    with pytest.raises(EffectError):
        simulate("paper", SEED, duration=40, effects=[parse_effect(s) for s in specs])


def test_describe_round_trips_through_the_truth_file(tmp_path):
    specs = ["temperature_bias:sensor=accel,axis=z,coeff=-4e-3", "bias_drift:axis=y", "g_sensitivity",
             "time_offset:sensor=gyro,seconds=-0.02", "saturation:sensor=accel,limit=9.5", "scale_nonlinearity",
             "lever_arm:x=0.01,y=0.02,z=0.03", "axis_sign:sensor=accel,axis=x"]
    effects = [parse_effect(s) for s in specs]
    s = simulate("paper", SEED, duration=60, effects=effects)
    p = tmp_path / "t.json"
    s.truth.save(p)
    back = Truth.load(p).effects
    informative = {"clipped_fraction", "walk_final"}
    for e, d in zip(effects, back, strict=True):
        assert from_describe(d) == e
        assert set(d) - informative == {"effect", "sensor", "axis"} | set(EFFECT_KEYS[e.name])
        assert d["axis"] in ("x", "y", "z", None)
        assert parse_effect(e.spec()) == e


def test_random_effect_stays_in_the_spec_ranges(clean):
    rng = np.random.default_rng(0)
    peak = {k: np.abs(raw(clean, k)).max() for k in ("gyro", "accel")}
    seen = {n: set() for n in EFFECTS}
    for _ in range(150):
        for n in EFFECTS:
            d = random_effect(n, rng, clean).describe()
            seen[n].add((d["sensor"], d["axis"]))
            if n == "temperature_bias":
                lo, hi = (2e-4, 1e-3) if d["sensor"] == "gyro" else (3e-3, 1e-2)
                assert lo <= abs(d["coeff"]) <= hi
            elif n == "bias_drift":
                assert d["sensor"] == "gyro" and 5e-5 <= d["density"] <= 3e-4
            elif n == "g_sensitivity":
                assert 5e-5 <= abs(d["coeff"]) <= 5e-4
            elif n == "time_offset":
                assert 0.01 <= abs(d["seconds"]) <= 0.08
            elif n == "saturation":
                assert 0.6 * peak[d["sensor"]] <= d["limit"] <= 0.9 * peak[d["sensor"]]
            elif n == "scale_nonlinearity":
                assert d["sensor"] == "gyro" and 1e-3 <= d["coeff"] <= 5e-3
            elif n == "lever_arm":
                assert 0.02 <= np.linalg.norm([d["x"], d["y"], d["z"]]) <= 0.1
            elif n == "axis_sign":
                assert d["axis"] in ("x", "y", "z")
    assert len({s for s, _ in seen["axis_sign"]}) == 3 and len({a for _, a in seen["axis_sign"]}) == 3
    assert {a for _, a in seen["temperature_bias"]} == {"x", "y", "z", None}
    assert {s for s, _ in seen["time_offset"]} == {"gyro", "accel", "mag"}
    with pytest.raises(EffectError):
        random_effect("saturation", rng, None)


# -- the inverse: model extensions -------------------------------------------------------------------

def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


@pytest.mark.parametrize("spec, sensor", [
    ("temperature_bias:sensor=gyro,coeff=1e-3", "gyro"),
    ("temperature_bias:sensor=accel,axis=z,coeff=1e-2", "accel"),
    ("g_sensitivity:coeff=5e-4", "gyro"),
    ("time_offset:sensor=gyro,seconds=0.06", "gyro"),
    ("time_offset:sensor=accel,seconds=-0.04", "accel"),
    ("scale_nonlinearity:sensor=gyro,coeff=5e-3", "gyro"),
    ("scale_nonlinearity:sensor=accel,axis=y,coeff=2e-3", "accel"),
    ("lever_arm:x=0.1,y=-0.05,z=0.03", "accel"),
    ("axis_sign:sensor=accel,axis=y", "accel"),
])
def test_correct_removes_the_effect(clean, spec, sensor):
    """correct(simulated with the effect) ≈ simulated clean: within the white noise σ (same draws), and
    the residual is a small fraction of the effect."""
    s = sim(spec)
    ext = extensions_from_effects(s.truth.effects)
    out = correct(s.data, ext, s.truth.calibration)
    before = rms(raw(s, sensor) - raw(clean, sensor))
    after = rms(raw(out, sensor) - raw(clean, sensor))
    sigma = clean.truth.noise[sensor]
    # pointwise inverses leave quantisation only; resampling (time_offset) mixes in neighbours' noise (≤ √2 σ)
    bound = 1.5 * sigma if spec.startswith("time_offset") else 0.5 * sigma
    assert after < bound, (after, sigma)
    assert after < 0.1 * before
    other = {"gyro": "accel", "accel": "gyro"}[sensor]
    if not spec.startswith(("lever_arm", "g_sensitivity")):
        assert np.array_equal(raw(out, other), raw(s, other))


def test_correct_restamps_a_late_magnetometer(clean):
    s = sim("time_offset:sensor=mag,seconds=0.05")
    out = correct(s.data, extensions_from_effects(s.truth.effects))
    assert np.allclose(out.t_mag, s.data.t_mag - 0.05, atol=1e-12, rtol=0)
    assert np.array_equal(out.mag, s.data.mag)

    def model(t):  # the truth model's mag reading at instants t, noise-free
        m = s.trajectory.evaluate(t)
        return s.truth.calibration.mag.inv().apply(np.einsum("nji,j->ni", m.R, np.asarray(s.truth.field_world)))

    before = rms(s.data.mag - model(s.data.t_mag))
    after = rms(out.mag - model(out.t_mag))
    assert after < 1.5 * clean.truth.noise["mag"] and after < 0.1 * before


def test_correct_two_effects_on_one_sensor(clean):
    s = sim("scale_nonlinearity:coeff=3e-3", "temperature_bias:coeff=-7e-4", "axis_sign:sensor=gyro,axis=y")
    out = correct(s.data, extensions_from_effects(s.truth.effects))
    assert rms(out.gyro - clean.data.gyro) < 0.5 * clean.truth.noise["gyro"]


def test_nonlinearity_inverse_is_exact():
    rng = np.random.default_rng(1)
    x = rng.uniform(-40, 40, (1000, 3))
    for c in (np.array([5e-3, 1e-4, 0.0]), np.array([-1e-2, -1e-3, 2e-2])):
        xs = np.clip(x, -0.49 / np.maximum(np.abs(c), 1e-12), 0.49 / np.maximum(np.abs(c), 1e-12))
        y = xs * (1 + c * np.abs(xs))
        assert np.abs(uninvert_nonlinearity(y, c) - xs).max() < 1e-12 * 40


def test_bias_drift_and_saturation_are_not_removed_but_reported(clean):
    s = sim("bias_drift:sensor=gyro,axis=z,density=2e-4", "saturation:sensor=accel,limit=9")
    ext = extensions_from_effects(s.truth.effects)
    out = correct(s.data, ext)
    assert np.array_equal(out.gyro, s.data.gyro) and np.array_equal(out.acc, s.data.acc)
    q = process_noise(ext)
    assert np.array_equal(q["gyro"], [0, 0, 2e-4]) and np.array_equal(q["accel"], [0, 0, 0])
    mask = clipped_mask(s.data, ext, rtol=0)
    assert set(mask) == {"accel"} and np.array_equal(mask["accel"], np.abs(s.data.acc) == 9.0)


@pytest.mark.parametrize("ext, fragment", [
    ({"warp_drive": {}}, "unknown extension 'warp_drive'"),
    ({"time_offset": {"sensor": "mag", "seconds": 0.1, "lag": 2}}, "unknown key 'lag'"),
    ({"time_offset": {"sensor": "mag"}}, "missing key 'seconds'"),
    ({"temperature_bias": {"coeff": "big"}}, "coeff must be a finite number"),
    ({"temperature_bias": {"coeff": [1, 2, 3], "axis": "x"}}, "list of 3 only with axis all"),
    ({"axis_sign": {"sensor": "baro", "axis": "x"}}, "sensor must be one of"),
])
def test_extension_validation(ext, fragment):
    with pytest.raises(ValueError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        validate_extensions(ext)


def test_lever_arm_correction_needs_the_calibration(clean):
    with pytest.raises(ValueError, match="lever_arm needs the calibration"):
        correct(clean.data, {"lever_arm": {"x": 0.1, "y": 0.0, "z": 0.0}})


def test_per_axis_coefficients(clean):
    k = [2e-4, -5e-4, 0.0]
    s = sim("temperature_bias:axis=x,coeff=2e-4", )
    e = validate_extensions({"temperature_bias": {"coeff": k, "T0": 25}})["temperature_bias"][0]
    assert np.array_equal(e["coeff"], k) and e["axis"] is None
    out = correct(s.data, {"temperature_bias": {"coeff": [2e-4, 0, 0]}})
    assert rms(out.gyro - clean.data.gyro) < 0.5 * clean.truth.noise["gyro"]


# -- the command line -------------------------------------------------------------------------------

def run(*args):
    return subprocess.run([sys.executable, "-m", "onlinecal", *args], capture_output=True, text=True, timeout=120)


def test_cli_writes_the_effect_into_the_truth(tmp_path):
    out = tmp_path / "x.tlog"
    r = run("simulate", "--out", str(out), "--duration", "60", "--effect", "time_offset:sensor=mag,seconds=0.05")
    assert r.returncode == 0, r.stderr
    truth = json.loads((tmp_path / "x.tlog.truth.json").read_text())
    assert truth["effects"] == [{"effect": "time_offset", "sensor": "mag", "axis": None, "seconds": 0.05}]


@pytest.mark.parametrize("spec, fragment", [
    ("time_offset:sensor=mag,secs=0.05", "unknown key 'secs'"),
    ("no_such_effect", "unknown effect"),
])
def test_cli_bad_effect_is_exit_2_one_line(tmp_path, spec, fragment):
    out = tmp_path / "y.tlog"
    r = run("simulate", "--out", str(out), "--duration", "30", "--effect", spec)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0] and spec in lines[0]
    assert not out.exists()
