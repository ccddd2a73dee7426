"""The filter's state vector beyond the 40 base states of :mod:`.layout`: extensions and hold offsets, the
Cholesky order that lets sigma points share the mean's attitude history, the consider (gauge) mask, and
the prior a calibration (or a cold start) gives.

* :class:`StateLayout` — names and slices of every state, the dynamic sigma points, the consider mask;
* :func:`choose_gauge` — which sensor's terms define the body frame B (held as consider states);
* :func:`prior` — prior mean and σ of the 40 base states from ``init``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..model import PARAMS, SENSORS, Calibration, SensorCalibration
from .config import EXTENSIONS, UKFConfig
from .layout import ATT, AXES, DIP, N_STATE, NAMES, SENSOR_SLICE, index
from .learning import LEARNED

Array = NDArray[np.float64]


@dataclass
class StateLayout:
    """Names of the state (the 40 of :mod:`.layout`, then extensions, then hold offsets), the slices of
    the extras, the Cholesky order (attitude-relevant states first) and the consider mask.

    ``dyn_pts`` are the sigma points (of 2n + 1) that differ from the mean in a state the attitude depends
    on (attitude, gyro terms, gyro extensions, the gyro hold offset): with the factor taken in ``perm``
    order, every other point shares the mean's attitude history (:func:`.unscented.sigma_points`).
    """

    extra_states: tuple[str, ...] = ()
    holds: tuple[str, ...] = ()
    gauge: str | None = None
    gauge_terms: tuple[str, ...] = ()
    names: list[str] = field(init=False)
    ext_slice: dict[str, slice] = field(init=False)
    hold_slice: dict[str, slice] = field(init=False)
    perm: NDArray[np.intp] = field(init=False)
    perm_id: bool = field(init=False)
    dyn_pts: NDArray[np.intp] = field(init=False)
    consider: NDArray[np.bool_] = field(init=False)
    consider_vehicle: NDArray[np.bool_] = field(init=False)
    gyro_tilt_terms: NDArray[np.bool_] = field(init=False)
    learned_terms: dict[str, NDArray[np.bool_]] = field(init=False)

    def __post_init__(self) -> None:
        names = list(NAMES)
        self.ext_slice = {}
        for e in self.extra_states:
            s0 = len(names)
            names += [f"ext.{e}.{a}" for a in AXES]
            self.ext_slice[e] = slice(s0, s0 + 3)
        self.hold_slice = {}
        for s in self.holds:
            s0 = len(names)
            names += [f"hold.{s}.{a}" for a in AXES]
            self.hold_slice[s] = slice(s0, s0 + 3)
        self.names = names
        n = len(names)
        dyn = np.zeros(n, bool)
        dyn[ATT] = True
        dyn[SENSOR_SLICE["gyro"]] = True
        for e, sl in self.ext_slice.items():
            if EXTENSIONS[e][0] == "gyro":
                dyn[sl] = True
        if "gyro" in self.hold_slice:
            dyn[self.hold_slice["gyro"]] = True  # a held gyro reading is integrated with its offset
        self.perm = np.concatenate([np.flatnonzero(dyn), np.flatnonzero(~dyn)])
        self.perm_id = bool(np.array_equal(self.perm, np.arange(n)))
        nd = int(dyn.sum())
        self.dyn_pts = np.concatenate([[0], np.arange(1, nd + 1), np.arange(n + 1, n + nd + 1)])
        # Schmidt–Kalman consider states: the gauge sensor's terms (see choose_gauge)
        self.consider = np.zeros(n, bool)
        if self.gauge:
            for p in self.gauge_terms:
                self.consider[index(self.gauge, p)] = True
        # in motion on a vehicle (.vehicle.VehicleDetector on) the accelerometer's terms are held too: its
        # update there carries the vehicle's unknown acceleration and says (almost) nothing of them, so what
        # moved them was every other sensor's tilt correction through their correlation with the attitude —
        # on MARG's hand-held files the magnetometer's (NIS 5–14 in motion) walked accel.bias.x 0.2 → 1.5 m/s²
        # over one 34-s file. Rests, where the accelerometer is a gravity reference, update them.
        self.consider_vehicle = self.consider.copy()
        self.consider_vehicle[SENSOR_SLICE["accel"]] = True
        for e, sl in self.ext_slice.items():
            if EXTENSIONS[e][0] == "accel":
                self.consider_vehicle[sl] = True
        # ... and on a thrust-borne vehicle (detected by its vibration) where the accelerometer is the update's only
        # attitude reference (no magnetometer in it), the gyro's x and y scales too: a roll or pitch scale error
        # tilts the integrated attitude in proportion to the bank or pitch itself, which is exactly the tilt of a
        # coordinated turn's specific force (along body z at any bank) and of a multirotor's thrust tilted to
        # accelerate, both of which the accelerometer reads as "level". Learned there, the scales were pulled low on
        # every cold flight (session 20, 12 seeds: mean z of gyro.scale.x/y −2.1/−2.2 fixed-wing, −1.1 multirotor;
        # 0.68–0.92 for a truth of 1.14, "undetermined" at 0.7 of the prior σ); held, −0.8/−0.7, the prior's own
        # offset. The z scale (yaw) too, since session 22: with nothing else to learn it shows the same pull the other
        # way — a fixed-wing started from its truth but for the z scale (σ 0.2) and the magnetometer ended it 3.09,
        # 3.35 and 7.38σ off on 3 of 20 seeds ("determined" at σ 0.02–0.04, mean z +1.3), a multirotor 1 of 20 at
        # −3.02σ; on a cold start the wider other terms had hidden it (mean z +0.1, −0.1). Without a heading
        # reference a yaw-scale error moves nothing but the tilt the turn's specific force hides. Rests update all
        # three, the cross-covariance with the attitude kept through the motion (eq. 36's attitude change between
        # rests). Not for a hand (a vehicle by the gate's drops, no
        # vibration): there the rests' updates through that cross-covariance took MARG's cold gyro.scale.y to
        # 0.75 ± 0.16 (0.985 ± 0.057 learned in motion) and its y-turn closure from 34.6° to 171°
        self.gyro_tilt_terms = np.zeros(n, bool)
        for a in AXES:
            self.gyro_tilt_terms[names.index(f"gyro.scale.{a}")] = True
        # ... and, on a thrust-borne vehicle, the magnetometer's soft iron (its scales, alphas and xis; its bias, the
        # hard iron, is learned in flight as the autopilots' own in-flight learning does): in flight nothing holds the
        # attitude still while the field turns — the accelerometer measures thrust, and the attitude is the gyro's
        # integral with its own scale — so a soft-iron error, a tilt error and a gyro scale error explain the same
        # field readings, and learned there they were pulled together into confident wrong values. Session 23's
        # probe: flights started from their truth but for the magnetometer, at the σ its cold sphere fit gives
        # (UKFConfig.mag_fit_sigma), 20 seeds: fixed-wing 6 seeds with a determined term beyond 3σ (mag.scale.z
        # −20.0σ, gyro scales +3.1…+3.9σ), multirotor 3 (gyro.scale.y −5.6σ); with every group of one sensor widened
        # in turn, up to mag.bias.z −27σ and accel.bias.x −4.5σ through the same attitude. Held: within 2.6σ on 199
        # of 200 probe flights, one fixed-wing at 3.96σ with its verdict degraded (docs/flight.md). Rests (still
        # attitudes) and hand-held turns (no vibration) learn them as before.
        self.mag_flight_terms = np.zeros(n, bool)
        for p in ("scale", "alpha", "xi"):
            for a in AXES:
                self.mag_flight_terms[names.index(f"mag.{p}.{a}")] = True
        # a motion block at a geometry already learned (.learning.Learning) holds that sensor's terms as well (the
        # magnetometer's with the dip); consider_mask combines them
        self.learned_terms = {}
        for s in LEARNED:
            m = np.zeros(len(self.names), bool)
            m[SENSOR_SLICE[s]] = True
            if s == "mag":
                m[self.names.index("dip")] = True
            for e, sl in self.ext_slice.items():
                if EXTENSIONS[e][0] == s:
                    m[sl] = True
            self.learned_terms[s] = m
        self._masks: dict[tuple[bool, bool, bool, bool, bool], NDArray[np.bool_]] = {}

    def consider_mask(self, vehicle: bool, held_accel: bool, held_mag: bool, gyro_tilt: bool,
                      mag_flight: bool = False) -> NDArray[np.bool_]:
        """The consider mask of a motion update: :attr:`consider`, the accelerometer's terms on a ``vehicle``
        (:attr:`consider_vehicle`), the gyro's three scales where ``gyro_tilt`` (:attr:`gyro_tilt_terms`), the
        magnetometer's soft iron where ``mag_flight`` (:attr:`mag_flight_terms`; :func:`.fastpath.motion_consider`
        decides both), and each sensor's whose geometry this block does not learn (cached)."""
        key = (vehicle, held_accel, held_mag, gyro_tilt, mag_flight)
        m = self._masks.get(key)
        if m is None:
            m = (self.consider_vehicle if vehicle else self.consider).copy()
            if gyro_tilt:
                m |= self.gyro_tilt_terms
            if mag_flight:
                m |= self.mag_flight_terms
            if held_accel:
                m |= self.learned_terms["accel"]
            if held_mag:
                m |= self.learned_terms["mag"]
            self._masks[key] = m
        return m

    @property
    def n(self) -> int:
        return len(self.names)

    def with_hold(self, sensor: str) -> StateLayout:
        """The same layout with the 3 hold-offset states of ``sensor`` appended."""
        return StateLayout(self.extra_states, self.holds + (sensor,), self.gauge, self.gauge_terms)

    def public(self) -> list[tuple[int, str]]:
        """Calibration terms, dip and extensions (attitude and hold offsets are nuisance states)."""
        return [(i, nm) for i, nm in enumerate(self.names) if i >= 3 and not nm.startswith("hold.")]


def batch_gyro_from_phases(init: Calibration | None) -> bool:
    """Whether ``init``'s B is the platform's rotation axes as its gyro measured them (``gauge`` field
    "gyro_phases", set by the batch's phase method), with a gyro to hold."""
    return init is not None and init.gauge == "gyro_phases" and init.gyro is not None


def choose_gauge(init: Calibration | None, config: UKFConfig) -> tuple[str | None, tuple[str, ...]]:
    """The sensor whose terms define B and which terms are held (consider states).

    A common rotation of the body frame (every sensor's T_R turned by the same Q, the attitude by Qᵀ)
    leaves every measurement unchanged, so nothing in the data fixes it: B is defined by the prior. Left
    free, a filter linearised at moving estimates gains spurious information along it and drifts (seen in
    cold starts: all three alphas off by the same degrees at 40σ). Holding one sensor's alpha at its prior
    (with its prior σ, as a consider parameter) pins B to that sensor's frame as given by ``init`` (the
    batch's B) or to the sensor itself on a cold start. The batch defines B by the platform's three
    rotation axes as the gyro measured them (its phases): that fixes the gyro's alpha *and* xi in B, so for
    such an init both are held.

    Sensor: ``config.gauge_sensor``; for "auto" the gyro of a batch init whose gyro came from its phases,
    else the init sensor with the tightest alpha σ, else the accelerometer. Terms: ``config.gauge_terms``;
    for "auto" alpha and xi for a phase-based batch gyro, else alpha.
    """
    phases = batch_gyro_from_phases(init)
    g = config.gauge_sensor
    if g == "auto":
        g = "gyro" if phases else _tightest_alpha(init)
    t = config.gauge_terms
    if t == "auto":
        terms: tuple[str, ...] = ("alpha", "xi") if g == "gyro" and phases else ("alpha",)
    else:
        terms = tuple(t.split("+"))
    return g, terms


def _tightest_alpha(init: Calibration | None) -> str:
    best, best_s = "accel", math.inf
    if init is not None:
        for s in SENSORS:
            cal = init.sensor(s)
            if cal is None or "alpha" not in cal.sigma:
                continue
            v = float(np.mean(np.asarray(cal.sigma["alpha"], float)))
            if np.isfinite(v) and v < best_s:
                best, best_s = s, v
    return best


def given_sigma(cal: SensorCalibration) -> Array:
    """The 12 σ (bias, scale, alpha, xi) a calibration carries, NaN where it has none."""
    out = []
    for p in PARAMS:
        v = np.asarray(cal.sigma.get(p, np.full(3, np.nan)), float).reshape(-1)
        out.append(v if v.shape == (3,) else np.full(3, np.nan))
    sig = np.concatenate(out)
    return np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)


def prior(init: Calibration | None, config: UKFConfig, gauge: str | None,
          gauge_terms: tuple[str, ...]) -> tuple[Array, Array]:
    """Prior mean and σ (40,) each of the base states from ``init`` (its σ × ``init_inflation``, the
    cold σ where it has none) or cold (bias 0, scale 1, angles 0, ``cold_sigma``). Attitude entries 0
    (filled when the attitude starts); dip 60° ± 30°."""
    c = config
    x = np.zeros(N_STATE)
    sig = np.zeros(N_STATE)
    for s in SENSORS:
        cal = init.sensor(s) if init is not None else None
        sl = SENSOR_SLICE[s]
        cold = c.cold_sigma[s]
        if cal is None:
            x[sl] = np.concatenate([np.zeros(3), np.ones(3), np.zeros(6)])
            sig[sl] = np.repeat([cold[p] for p in PARAMS], 3)
            if s == gauge:
                # cold: B is this sensor's frame by definition, the held terms carry no uncertainty
                for p in gauge_terms:
                    sig[sl.start + PARAMS.index(p) * 3 : sl.start + PARAMS.index(p) * 3 + 3] = c.gauge_cold_sigma
        else:
            x[sl] = np.concatenate([cal.bias, cal.scale, cal.alpha, cal.xi])
            given = given_sigma(cal)
            cold_v = np.repeat([cold[p] for p in PARAMS], 3)
            if s == "mag":
                cold_v[:3] *= float(1.0 / np.mean(cal.scale))  # mag bias σ relative to the raw field
                cold_v[3:6] *= float(np.mean(cal.scale))
            infl = np.full(12, c.init_inflation)
            if s == gauge:
                # consider states are never updated from the data: no double use to allow for
                for p in gauge_terms:
                    infl[PARAMS.index(p) * 3 : PARAMS.index(p) * 3 + 3] = 1.0
            sig[sl] = np.where(np.isfinite(given), given * infl, cold_v)
    x[DIP] = math.radians(60.0)
    sig[DIP] = math.radians(30.0)
    return x, sig


def reset_states(x: Array, P: Array, idx: slice | int | NDArray[np.intp], value: Array | float,
                 cov: Array | float) -> None:
    """Restart the states ``idx`` of (x (n,), P (n, n)) in place: value ``value``, covariance ``cov`` (a
    matrix for a slice or index array, a variance for one index), uncorrelated with the rest."""
    x[idx] = value
    P[idx, :] = 0.0
    P[:, idx] = 0.0
    if isinstance(idx, np.ndarray):
        P[np.ix_(idx, idx)] = cov
    else:
        P[idx, idx] = cov


def initial_state(lay: StateLayout, x0: Array, sig0: Array) -> tuple[Array, Array, Array, Array]:
    """x (n,), P (n, n), prior mean and prior σ (n,) of a fresh start: the 40 base states from their prior
    (x0, sig0 of :func:`prior`), the extensions at 0 ± their prior σ, the attitude error 0 ± 0.1 rad (not a
    prior: restarted with the first block); hold offsets come later (:func:`grow`)."""
    n = lay.n
    x = np.zeros(n)
    sig = np.zeros(n)
    x[:N_STATE], sig[:N_STATE] = x0, sig0
    for e, sl in lay.ext_slice.items():
        sig[sl] = EXTENSIONS[e][1]
    prior_sigma, prior_x = sig.copy(), x.copy()
    sig[ATT] = 0.1
    return x, np.diag(sig**2), prior_x, prior_sigma


def grow(x: Array, P: Array, prior_x: Array, prior_sigma: Array, n1: int) -> tuple[Array, Array, Array, Array]:
    """The same state with zero states appended up to n1 (new hold offsets; set by the caller)."""
    n0 = x.shape[0]
    x1 = np.zeros(n1)
    x1[:n0] = x
    P1 = np.zeros((n1, n1))
    P1[:n0, :n0] = P
    return x1, P1, np.concatenate([prior_x, np.zeros(n1 - n0)]), np.concatenate([prior_sigma, np.zeros(n1 - n0)])
