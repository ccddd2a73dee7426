"""The filter on a vehicle: unknown vehicle acceleration, and what the motion determined (observability).

**Vehicle acceleration.** The accelerometer measures specific force, f = Rᵀ(a + g e_z). A rotation platform
or a hand turning a sensor about a point keeps a ≈ 0, and the filter's accelerometer update (gravity only,
:class:`onlinecal.ukf.filter.OnlineCalibrator`) is right. A vehicle in the air does not: a multirotor tilts
its thrust to accelerate (f stays along body z while gravity does not), a fixed-wing in a coordinated turn
feels its specific force along body z at any bank. Taken as gravity, that thrust direction tilts the
attitude and, through it, the gyro's scale and the mag (issue 10: 28σ gyro scales on real flights).

So once the data show a vehicle (:class:`VehicleDetector`: rotor/engine vibration far above any MEMS
accelerometer's noise, or a specific-force norm away from g by more than the calibration's own
uncertainty explains — what a body turning about a fixed point cannot produce), the vehicle's acceleration
is a modelled disturbance on every accelerometer update outside a rest: a = vehicle acceleration with σ
``accel_sigma`` per axis and correlation time ``accel_tau`` (a leg's acceleration, a turn), added to R as
σ_v² · τ_v / Δt (one independent σ_v-measurement per τ_v: a coloured disturbance must not be averaged
down block by block as if white, or a 30-s turn would claim its bank as a tilt). The accelerometer stays a
full gravity reference where the data prove it is one: at rest, which the raw-data rest test decides with
the sensor's *spec* noise (vibration and thrust cannot pass it).

**Observability.** :class:`MotionCoverage` accumulates what the motion excited (largest calibrated rate and
turned angle about each gyro axis, rest time, distinct attitudes at rest, the share of field directions
the magnetometer swept) and :func:`observability_report` says, per term, whether the data determined it
(final σ below ``ratio`` × prior σ) and, if not, why and which motion would.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..advice import face_words, faces_advice, faces_at_rest, missing_faces
from .layout import ATT

if TYPE_CHECKING:
    from .config import UKFConfig

Array = NDArray[np.float64]
AXES = ("x", "y", "z")
DEG = 180.0 / math.pi
VIBRATION_REASON = "accelerometer vibration"  # how a reason of :class:`VehicleDetector` switched on by it begins


@dataclass
class VehicleDetector:
    """Decides, from the raw data, that the log is a vehicle's (sticky for the run).

    ``vibration_sigma`` m/s²: per-sample accelerometer noise (third differences) above which the motion is
    a running motor's vibration, not sensor noise (MEMS accelerometers: 0.01–0.05 m/s² at 100–200 Hz;
    ArduPilot calls < 15 m/s² VIBE healthy, so even a well-mounted vehicle is 10× above this).
    ``dev_min`` m/s²: a specific-force norm departing from g by more than this beyond what the noise and
    the calibration's σ explain, for ``dev_blocks`` blocks in a row, is a linear acceleration.
    ``drop_min`` of the last ``drop_window`` moving blocks whose accelerometer update the gate dropped (NIS
    above its 99.9 % gate): linear accelerations the platform model lacks, which the norm test misses while
    the accelerometer's scale is uncertain (a hand panning a sensor at arm's length: MARG's ``pan-x`` file
    dropped 148 of 338; a model that holds drops 1 in 1000, so 5 in 20 by chance has probability ~1e-11).
    :attr:`vibrating`: switched on by vibration (or configured a vehicle); its accelerometer's high-frequency
    content is then noise at any rate of turn, and the noise monitor reads every block (:func:`.step.turning`).

    Sticky for the run, across the logs of a replay too: they are one unit's, carried the same way (MARG's
    hand-held files: reset per log, the first seconds of each file before the detector's evidence came in
    moved the accelerometer's bias by up to 0.5 m/s²). A vehicle detected without vibration leaves the rest
    test its measured noise (:func:`rest_noise`), so a bench file after hand-held ones still has its rests."""

    vibration_sigma: float = 0.3
    dev_min: float = 0.5
    dev_blocks: int = 5
    active: bool = False
    since: float | None = None
    reason: str = ""
    drop_window: int = 20
    drop_min: int = 5
    _dev_run: int = 0
    _drops: list[bool] = field(default_factory=list)

    @classmethod
    def of(cls, config: UKFConfig) -> VehicleDetector:
        """The detector a :class:`.config.UKFConfig` asks for (its thresholds; not yet on)."""
        return cls(config.vehicle_vibration_sigma, config.vehicle_dev_min, drop_min=config.vehicle_gate_drops)

    def update(self, acc_noise_sigma: float, dev: float | None, t: float) -> str | None:
        """Feed one block: measured accel σ (m/s², NaN if unknown), unexplained |f|−g deviation (m/s²;
        None: not evaluated for this block). Returns the reason when the detector switches on, else None."""
        if self.active:
            return None
        why = None
        if math.isfinite(acc_noise_sigma) and acc_noise_sigma > self.vibration_sigma:
            why = (f"{VIBRATION_REASON} {acc_noise_sigma:.2g} m/s² per sample (> {self.vibration_sigma:g}: "
                   "a running motor, not sensor noise)")
        if dev is not None:
            self._dev_run = self._dev_run + 1 if dev > self.dev_min else 0
        if why is None and self._dev_run >= self.dev_blocks:
            why = (f"specific-force norm {dev:.2g} m/s² away from g beyond the calibration's σ for "
                   f"{self._dev_run} blocks (a linear acceleration)")
        if why is not None:
            self.active, self.since, self.reason = True, float(t), why
        return why

    def gate(self, dropped: bool, t: float) -> str | None:
        """Feed one moving block whose accelerometer update was evaluated: ``dropped`` by the gate or not.
        Returns the reason when the detector switches on (:attr:`drop_min` of the last :attr:`drop_window`)."""
        if self.active or self.drop_min <= 0:
            return None
        d = self._drops
        d.append(bool(dropped))
        if len(d) > self.drop_window:
            del d[0]
        k = sum(d)
        if k < self.drop_min:
            return None
        why = (f"the accelerometer's gate dropped {k} of the last {len(d)} moving blocks (linear accelerations "
               "the platform model lacks)")
        self.active, self.since, self.reason = True, float(t), why
        return why

    @property
    def vibrating(self) -> bool:
        """On by vibration, or configured a vehicle (its reason says which: no state of its own, so a checkpoint
        of any schema knows it)."""
        return self.active and (self.reason == "configured" or self.reason.startswith(VIBRATION_REASON))

    def dev_switch_above(self) -> float:
        """The deviation (m/s²) above which the next :meth:`update` with a deviation and no vibration switches
        the detector on (+inf where none can: it is on, or the run of blocks would still be too short)."""
        if self.active or self._dev_run + 1 < self.dev_blocks:
            return math.inf
        return self.dev_min

    def to_dict(self) -> dict[str, Any]:
        return {"active": self.active, "since": self.since, "reason": self.reason}

    def set_state(self, d: dict[str, Any]) -> None:
        self.active = bool(d.get("active", False))
        self.since = d.get("since")
        self.reason = str(d.get("reason", ""))


VEHICLE_NOTE = ": vehicle acceleration modelled from here on"


def rest_noise(n: dict[str, float], vehicle: VehicleDetector, noise_high: bool, noise_ratio: float
               ) -> dict[str, float]:
    """The per-sample σ ``n`` (per sensor) the rest test judges against: on a vehicle detected by its
    vibration whose accel noise is raised (``noise_high``, by ``noise_ratio`` in variance) the spec's, not the
    vibration-raised level (a vibrating vehicle is not at rest, and its accelerometer then measures thrust,
    not gravity). A vehicle detected by a linear acceleration alone (a hand's push) has no vibration: the
    measured level is its sensor's own, and judging against the spec found no rest in MARG's three bench
    files (accel noise 2.3× the spec)."""
    if vehicle.vibrating and noise_high:
        return dict(n, accel=n["accel"] / math.sqrt(noise_ratio))
    return n


def vehicle_accel_var(sigma: float, tau: float, dt_block: float) -> float:
    """Per-axis variance (m/s²)² added to one block's accelerometer update for an unknown vehicle
    acceleration of σ ``sigma`` correlated over ``tau`` s: σ² · max(1, τ/Δt) (one independent measurement
    per correlation time, spread over the blocks it covers)."""
    return float(sigma**2 * max(1.0, tau / max(dt_block, 1e-6)))


# rad/s: the horizontal part of the Earth's rotation, Ω_E cos φ (Ω_E = 7.292115e-5 rad/s, WGS-84), rms over
# latitudes uniform on the Earth's surface (E[cos²φ] = 2/3): Ω_E √(2/3). It turns the attitude about one
# axis (north), at its full size, whose direction in the body frame the filter does not know
OMEGA_E_HORIZONTAL_RMS = 7.292115e-5 * (2.0 / 3.0) ** 0.5


def earth_rate_noise(q: Array, P: Array, bias: slice, s_gyr: float, sigma: tuple[float, float, float], tau: float,
                     dt: float,
                     om2: float = OMEGA_E_HORIZONTAL_RMS**2) -> Array:
    """What the Earth's rotation, which the gyro model lacks, leaves unknown in flight: added in place to
    the block's Q diagonal ``q`` (n,). ``P`` (n, n) the covariance Q adds to,
    ``bias`` the gyro bias's slice, ``s_gyr`` the gyro's mean scale (the bias is in raw units), ``sigma``
    (3,) rad/s the per-axis allowance for the Earth rate on the bias (:attr:`UKFConfig.rest_rate_sigma`, the
    zero-rate update's), ``om2`` (rad/s)² the horizontal rate error's variance (Ω_h²; both smaller where the
    latitude is known: :func:`.earth.allowance`), ``tau`` s the correlation time of the attitude disturbance
    (:attr:`UKFConfig.vehicle_accel_tau`: one independent accelerometer measurement per τ_v), ``dt`` s.

    A gyro senses Ω_E = 7.29e-5 rad/s (the Earth's sidereal rate) projected on its axes; in a local
    level frame at latitude φ that is Ω_E sin φ up and Ω_E cos φ north. Two parts, two terms:

    * **the gyro bias cannot be told from the Earth rate's projection**: the vertical part Ω_E sin φ lies on a
      level vehicle's z axis for the whole flight, the horizontal part on x/y for as long as a heading is
      held. With the magnetometer holding the heading the drift it corrects made the bias σ fall to ~3e-6
      rad/s while its error was Ω_E sin 47.4° = 5.4e-5 (bench-started flights: gyro.bias.z 19–20σ off);
      floored along the up axis only, the x/y bias σ of a cold flight still fell below the horizontal
      part its rest had left in the estimate (multirotor seed 17: gyro.bias.y 3.47σ; 1.34σ with the floor
      on every axis). So the bias variance on every axis is kept at or above σ² (the zero-rate update's
      allowance), topped up only where the data took it lower;
    * **the horizontal part turns with the heading in the body frame**, so no constant bias absorbs it: it
      tilts the attitude at Ω_E cos φ (4.9e-5 rad/s at 47.4°) about north until the accelerometer or the
      magnetometer corrects it. As a coloured rate error of that size (:data:`OMEGA_E_HORIZONTAL_RMS`,
      about an axis the filter does not know: on every axis) correlated over τ, its white equivalent adds
      Ω_h²·τ·dt to the attitude variance. Without it, bench-started flights ended their final ground rest
      with the accel NIS climbing 4 → 44 (the landing tilt outside its σ; 82 of 555 rest updates
      soft-gated, health degraded); with σ = Ω_E/√3 instead of Ω_h, one fixed-wing flight of two still
      was (63 of 528)."""
    # element by element on Python floats (issue 15: a third of the numpy calls' cost per block): the same
    # operations as q[bias] += np.maximum(0, floor − diag(P)[bias]); q[ATT] += Ω_h²τ dt, so the same bits
    for i, k in enumerate(range(bias.start, bias.stop)):
        v = (sigma[i] / s_gyr) ** 2 - P[k, k]
        q[k] += v if not v <= 0.0 else 0.0  # np.maximum(0, v): v where positive (or NaN), else 0
    a = om2 * tau * dt
    for k in range(ATT.start, ATT.stop):
        q[k] += a
    return q


@dataclass
class MotionCoverage:
    """What the motion excited, accumulated per filter block (calibrated quantities, current estimate)."""

    max_rate: Array = field(default_factory=lambda: np.zeros(3))  # rad/s, largest |ω| per gyro axis
    angle: Array = field(default_factory=lambda: np.zeros(3))  # rad, ∫|ω_i| dt over moving blocks
    rest_s: float = 0.0
    rest_dirs: list[list[float]] = field(default_factory=list)  # unit gravity directions at rests
    mag_dirs: Array = field(default_factory=lambda: np.zeros(26))  # field directions seen (26 cells)
    flight_s: float = 0.0

    def add_motion(self, rate: Array, dt: float, in_flight: bool) -> None:
        """A moving block: calibrated body rate (3,) rad/s over ``dt`` s. Element by element on Python floats
        (issue 15: once per block, a fifth of the numpy calls' cost): |ω_i|, the running maximum as
        ``np.maximum`` (NaN propagates), ∫|ω_i| dt — the same operations, so the same bits."""
        mr, ang = self.max_rate, self.angle
        for i, w in enumerate(np.asarray(rate, float).tolist()):
            r = abs(w)
            m = float(mr[i])
            mr[i] = r if (r > m or r != r) else m  # np.maximum(m, r): NaN in either wins
            ang[i] = float(ang[i]) + r * dt
        if in_flight:
            self.flight_s += dt

    def add_rest(self, f_dir: Array, dt: float) -> None:
        """A rest block: unit gravity direction (3,) in the body frame; a new attitude if > 20° from all
        seen before."""
        self.rest_s += dt
        u = np.asarray(f_dir, float)
        n = float(np.linalg.norm(u))
        if not n > 0:
            return
        u = u / n
        if not self.rest_dirs or float(np.max(np.asarray(self.rest_dirs) @ u)) < _COS20:
            if len(self.rest_dirs) < 64:
                self.rest_dirs.append(u.tolist())

    def add_rest_lazy(self, approx: Sequence[float], dt: float, exact: Callable[[], Array]) -> None:
        """:meth:`add_rest` with the exact direction formed only where it can matter (issue 15: the accel's
        calibration in numpy on one row and this method's numpy were ~90 µs of every rest block). ``approx``
        (3,): the same vector to rounding (:func:`.magdisturb.calibrated_floats`, ~1e-15 relative); ``exact``
        gives the vector :meth:`add_rest` takes. Where approx's largest cosine to a stored direction clears
        cos 20° by :data:`REST_DIR_MARGIN` — a thousand million times the rounding — the exact vector would
        find the same direction (nothing stored): only the rest's time is added. Otherwise (a new attitude, a
        near tie, a zero or NaN vector) :meth:`add_rest` decides on the exact vector, so what is stored is
        always its value and every decision is the same."""
        a0, a1, a2 = (float(v) for v in approx)
        n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        if self.rest_dirs and n > 0:
            best = max(d[0] * a0 + d[1] * a1 + d[2] * a2 for d in self.rest_dirs) / n
            if best > _COS20 + REST_DIR_MARGIN:
                self.rest_s += dt
                return
        self.add_rest(exact(), dt)

    def add_field(self, h_dir: Array) -> None:
        """Unit field directions (N, 3) in the body frame: marks the cells (26 directions of a cube's
        faces, edges and corners) they fall in."""
        h = np.asarray(h_dir, float).reshape(-1, 3)
        if h.size == 0:
            return
        c = FIELD_CELLS @ (h / np.linalg.norm(h, axis=1, keepdims=True)).T  # (26, N)
        self.mag_dirs[np.unique(np.argmax(c, axis=0))] = 1.0

    def gravity_axes(self) -> list[str]:
        """Body axes (±x, ±y, ±z) that gravity pointed along (within 30°) at some rest."""
        out = []
        for u in self.rest_dirs:
            for i, a in enumerate(AXES):
                for sgn, name in ((1, "+"), (-1, "-")):
                    if sgn * u[i] > math.cos(math.radians(30)) and name + a not in out:
                        out.append(name + a)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"max_rate_deg_s": (self.max_rate * DEG).round(3).tolist(),
                "turned_deg": (self.angle * DEG).round(1).tolist(), "rest_s": round(self.rest_s, 2),
                "rest_attitudes": len(self.rest_dirs), "gravity_axes_at_rest": self.gravity_axes(),
                "field_directions_swept": round(float(self.mag_dirs.mean()), 3),
                "flight_s": round(self.flight_s, 2)}

    def get_state(self) -> dict[str, Any]:
        return {"max_rate": self.max_rate.tolist(), "angle": self.angle.tolist(), "rest_s": self.rest_s,
                "rest_dirs": self.rest_dirs, "mag_dirs": self.mag_dirs.tolist(), "flight_s": self.flight_s}

    def set_state(self, d: dict[str, Any]) -> None:
        self.max_rate = np.asarray(d.get("max_rate", [0, 0, 0]), float)
        self.angle = np.asarray(d.get("angle", [0, 0, 0]), float)
        self.rest_s = float(d.get("rest_s", 0.0))
        self.rest_dirs = [list(map(float, u)) for u in d.get("rest_dirs", [])]
        self.mag_dirs = np.asarray(d.get("mag_dirs", np.zeros(26)), float)
        self.flight_s = float(d.get("flight_s", 0.0))


_COS20 = math.cos(math.radians(20))  # a rest within 20° of one seen before is the same attitude (add_rest)
REST_DIR_MARGIN = 1e-6  # add_rest_lazy: a cosine this far beyond cos 20° is decided without the exact vector

# the field coverage's 26 cells (unit directions of a cube's faces, edges and corners): MotionCoverage.add_field
# here, fastpath.field_cell_kernel in the compiled motion block
FIELD_CELLS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                        if (i, j, k) != (0, 0, 0)], float)
FIELD_CELLS /= np.linalg.norm(FIELD_CELLS, axis=1, keepdims=True)

# turns that excite a gyro term (small-angle eqs. 5–6): scale_k → about k; alpha_k couples the two axes
# other than k; xi_z tilts y towards x (turns about x or y), xi_y tilts z towards x, xi_x z towards y
_OTHER = {"x": ("y", "z"), "y": ("x", "z"), "z": ("x", "y")}
_XI_TURN = {"x": ("y", "z"), "y": ("x", "z"), "z": ("x", "y")}


def _why(term: str, cov: MotionCoverage, vehicle: bool, held: bool, gauge: str | None,
         mag_used: bool = True, thrust: bool = False) -> tuple[str, str]:
    """(reason, motion needed) for a term the data did not determine; ``thrust``: a vehicle detected by its
    vibration, in whose motion without the magnetometer the gyro's scales are held (:attr:`.state.StateLayout.
    gyro_tilt_terms`), and the magnetometer's soft iron always (:attr:`.state.StateLayout.mag_flight_terms`)."""
    if held:
        return (f"held at its prior: it defines the body frame (gauge: the {gauge}'s frame); no data can "
                "determine a common rotation of all sensors", "none (a convention, not a measurement)")
    if term == "dip":
        return ("the field's dip needs the calibrated magnetometer and gravity together at rest",
                "hold still for 10 s with the magnetometer calibrated")
    if term.startswith("ext."):
        return ("the regressor (temperature or specific force) did not vary enough",
                "let the temperature change (warm-up), or turn with gravity along each gyro axis")
    s, p, ax = term.split(".")
    i = AXES.index(ax)
    mr, ang = cov.max_rate * DEG, cov.angle * DEG
    if s == "gyro":
        if p == "bias":
            return (f"{cov.rest_s:.0f} s at rest in the log", "hold still (any attitude) for 10 s" if cov.rest_s < 10
                    else "none: the log holds enough rest (its σ did not shrink below half its start value)")
        if p == "scale":
            reached = f"turns about {ax} reached at most {mr[i]:.0f}°/s and {ang[i]:.0f}° in total"
            if thrust and not mag_used:
                # the turns' size is not what was missing: in flight they had no still reference
                return (reached + "; in flight the accelerometer measures thrust and no calibrated magnetometer held "
                        "the heading, so no turn had a still reference there (the scales are held in that motion: "
                        "only the attitude change between rests counts, as gravity shows it"
                        + (", and gravity does not see a turn about a vertical z)" if ax == "z" else ")"),
                        f"a full turn (360°) about {ax} at 30°/s or more with the calibrated magnetometer in use "
                        "(a tumble that calibrates it, or --init with a bench calibration), or by hand between two "
                        f"rests{' with z not vertical' if ax == 'z' else ''}")
            return (reached, f"a full turn (360°) about {ax} at 30°/s or more, against a still reference "
                    "(gravity at rest before and after, or the calibrated magnetometer)")
        turns = _OTHER[ax] if p == "alpha" else _XI_TURN[ax]
        j, k = AXES.index(turns[0]), AXES.index(turns[1])
        return (f"turns about {turns[0]} and {turns[1]} reached {mr[j]:.0f} and {mr[k]:.0f}°/s "
                f"({ang[j]:.0f}° and {ang[k]:.0f}°)",
                f"full turns about {turns[0]} and about {turns[1]} (gyro axis "
                f"{'alignment' if p == 'alpha' else 'non-orthogonality'})")
    if s == "accel":
        axes = cov.gravity_axes()
        extra = (" (in flight the accelerometer measures thrust, not gravity: only rests count)" if vehicle else "")
        if p in ("bias", "scale"):  # ask only for the faces of this axis the data lacks (onlinecal.advice)
            need = faces_advice(missing_faces(faces_at_rest(cov.rest_dirs), [ax]))
            return (f"{len(cov.rest_dirs)} distinct attitude(s) at rest, gravity along {', '.join(axes) or 'no axis'}"
                    + extra, need or f"none: the data holds {ax} up and {ax} down at rest (its σ did not shrink "
                    "below half its start value, e.g. a start already as tight as this data allows)")
        return (f"{len(cov.rest_dirs)} distinct attitude(s) at rest" + extra,
                "hold still in attitudes between the axes (e.g. 45° tilts), as in the paper's 12 positions")
    # mag
    if not mag_used:
        return ("the magnetometer was never calibrated: its cold fit needs the field to sweep directions in "
                "3-D (yaw turns with small tilts sweep a band, on which the centre and scale along the band's "
                "axis trade off against the gyro's scale)",
                "turn the vehicle through all attitudes (a tumble, or full turns about three axes) once, "
                "or start from a bench calibration (--init CAL.json)")
    sw = float(cov.mag_dirs.mean())
    if thrust and p != "bias":  # held in the vibrating vehicle's motion (.state.StateLayout.mag_flight_terms)
        return (f"the field swept {100 * sw:.0f} % of the directions around the sensor, but in flight the "
                "magnetometer's soft iron (scales, axis angles) is held: with the accelerometer measuring thrust "
                "nothing holds the attitude still while the field turns, and these terms trade off against the tilt "
                "and the gyro's scales there (only rests count; the bias, the hard iron, is learned in flight)",
                "full turns about three axes by hand with the motors off, or still rests in varied attitudes, or "
                "start from a bench calibration (--init CAL.json)")
    if p in ("bias", "scale"):
        return (f"the field swept {100 * sw:.0f} % of the directions around the sensor",
                f"turn about {_OTHER[ax][0]} and about {_OTHER[ax][1]} so the field sweeps the {ax} axis")
    return (f"the field swept {100 * sw:.0f} % of the directions around the sensor",
            "rotate through all attitudes (a tumble, or full turns about three axes)")


def observability_report(names: list[str], sigma: Array, prior_sigma: Array, cov: MotionCoverage,
                         vehicle: VehicleDetector, held: set[str], gauge: str | None,
                         ratio: float = 0.5, mag_used: bool = True) -> dict[str, Any]:
    """Which terms the data determined (final σ < ``ratio`` × prior σ) and which not, why, and what motion
    would: ``{"determined": [term...], "undetermined": [{"term", "sigma_ratio", "reason",
    "motion_needed"}...], "coverage": {...}, "vehicle": {...}, "rule": str}``. ``names`` (n,) state names
    with ``sigma``, ``prior_sigma`` (n,); only the calibration terms, dip and extensions are reported."""
    det: list[str] = []
    und: list[dict[str, Any]] = []
    for i, nm in enumerate(names):
        if nm.startswith(("att.", "hold.")) or i < 3:
            continue
        r = float(sigma[i] / prior_sigma[i]) if prior_sigma[i] > 0 else float("nan")
        if nm not in held and r < ratio:
            det.append(nm)
            continue
        why, need = _why(nm, cov, vehicle.active, nm in held, gauge, mag_used, vehicle.vibrating)
        und.append({"term": nm, "sigma_ratio": round(r, 4), "reason": why, "motion_needed": need})
    return {"rule": f"determined: final σ < {ratio:g} × prior σ; the others keep (about) their prior and "
                    "are not calibrated by this data",
            "determined": det, "undetermined": und, "caution": motion_only(det, cov), "coverage": cov.to_dict(),
            "vehicle": vehicle.to_dict()}


def motion_only(determined: list[str], cov: MotionCoverage) -> list[dict[str, str]]:
    """The accelerometer bias and scale terms in ``determined`` that the rests cannot have determined: the
    log never rested with their axis up and with it down (:func:`onlinecal.advice.faces_at_rest`), so
    at rest gravity fixes only s·(raw − o) along that axis, not the split. What split it is the motion,
    read as gravity under the quasi-static assumption — no linear acceleration beyond what the norm
    test sees (``AccelModel.deviation``). While the accelerometer's calibration is cold that test is
    blind to a hand's or a vehicle's accelerations of up to a metre per second squared (the real PX4 log
    ``px4-ulog/sample.ulg``: six seconds of handling gave its z scale 0.957 ± 0.004, the rest alone
    1.006 ± 0.036; docs/flight.md). Each: ``{"term", "reason", "motion_needed"}``."""
    seen = faces_at_rest(cov.rest_dirs) if cov.rest_dirs else []
    out = []
    for nm in determined:
        s, p, ax = nm.split(".") if nm.count(".") == 2 else ("", "", "")
        if s != "accel" or p not in ("bias", "scale"):
            continue
        miss = missing_faces(seen, [ax])
        if not miss:
            continue
        need = faces_advice(miss) or ""
        out.append({"term": nm,
                    "reason": (f"determined through motion alone: the log rested in {len(cov.rest_dirs)} attitude(s), "
                               f"never with {' or with '.join(face_words(f) for f in miss)}, so its value rests on "
                               "the motion being free of linear acceleration, which a hand or a vehicle breaks"),
                    "motion_needed": need})
    return out


def observability_text(rep: dict[str, Any]) -> list[str]:
    """The report in words, one line per undetermined group (same reason and motion), for stderr/report."""
    lines = [f"determined by the data: {', '.join(rep['determined']) or 'nothing'}"]
    groups: dict[tuple[str, str], list[str]] = {}
    for u in rep["undetermined"]:
        groups.setdefault((u["reason"], u["motion_needed"]), []).append(u["term"])
    for (why, need), terms in groups.items():
        lines.append(f"not determined: {', '.join(terms)} — {why}; would need: {need}")
    for c in rep.get("caution", []):
        lines.append(f"caution: {c['term']} — {c['reason']}; to determine it from rests: {c['motion_needed']}")
    if rep["vehicle"]["active"]:
        lines.append(f"vehicle motion from t = {rep['vehicle']['since']:.1f} s ({rep['vehicle']['reason']}): "
                     "the accelerometer is a gravity reference only at rest")
    e = rep.get("earth_rate")
    if e is not None:
        if e["latitude_deg"] is None:
            lines.append(f"the Earth's rotation is not taken out of the gyro (latitude unknown): the gyro bias "
                         f"includes its projection (up to 7.3e-05 rad/s), allowed for as "
                         f"{max(e['allowance_rad_s']):.1e} rad/s per axis (give --latitude to take it out)")
        else:
            wmm = " (World Magnetic Model)" if "World Magnetic Model" in (e.get("declination_source") or "") else ""
            part = (f"magnetic heading, declination {e.get('declination_deg') or 0.0:.2f}° ± "
                    f"{e['declination_sigma_deg']:g}°{wmm}" if e["heading_known"] else
                    "vertical part only: no heading")
            src = e.get("latitude_source")
            told = f"from {src}; " if src and src != "--latitude" else ""
            lines.append(f"the Earth's rotation is taken out of the gyro at latitude {e['latitude_deg']:g}° ({told}"
                         f"{part}); what is left is allowed for: up to {max(e['allowance_rad_s']):.1e} rad/s per axis"
                         + ("" if e["heading_known"] else
                            " — one rest's share of its horizontal part at a heading nobody knows; a log that rests at "
                            "several headings averages that share down, so the gyro bias's σ is then conservative "
                            "(on the simulated flights about twice the variance of its error: docs/flight.md)"))
    return lines
