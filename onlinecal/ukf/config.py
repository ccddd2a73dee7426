"""Settings of the online calibrator (:class:`UKFConfig`) and the model extensions it can carry.

Every default comes from the sensor specs or the paper's error magnitudes, not from any one log; the
comment at each setting says what it does and, where it was chosen by a measurement, which one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from ..specs import ACCEL_SPEC, G0, GYRO_SPEC, MAG_SPEC, SensorSpec

# model extensions: name → (sensor whose bias moves, prior σ of K per axis, unit of K)
EXTENSIONS = {
    "temperature_bias:gyro": ("gyro", 1e-3, "rad/s/°C"),
    "temperature_bias:accel": ("accel", 1e-2, "m/s²/°C"),
    "g_sensitivity": ("gyro", 5e-4, "rad/s per m/s²"),
}
MIN_SAMPLES_DETECT = 64  # IMU samples at the start of a log used for the rate and the value lattice


@dataclass
class UKFConfig:
    """Settings of the online calibrator. Defaults come from the sensor specs, not from any one log."""

    block_s: float = 0.1  # IMU samples per filter step, as a duration
    sp_alpha: float = 0.3  # scaled UT spread (Wan & van der Merwe 2000), β = 2 (Gaussian), κ = 0
    sp_beta: float = 2.0
    sp_kappa: float = 0.0
    gravity: float = G0
    init_inflation: float = 2.0  # σ of an ``init`` calibration is multiplied by this for the prior
    # cold-start prior σ (init=None): wide enough for the paper's errors (Table II: 15 % gyro scale,
    # 0.16 rad/s gyro bias); mag bias and scale relative to the raw field magnitude
    cold_sigma: dict[str, dict[str, float]] = field(default_factory=lambda: {
        "gyro": {"bias": 0.2, "scale": 0.2, "alpha": 0.035, "xi": 0.02},
        "accel": {"bias": 0.5, "scale": 0.05, "alpha": 0.035, "xi": 0.02},
        "mag": {"bias": 0.6, "scale": 0.3, "alpha": 0.05, "xi": 0.035},
    })
    # σ of the mag terms after the cold-start sphere fit (bias relative to the field, scale relative)
    mag_fit_sigma: dict[str, float] = field(default_factory=lambda: {
        "bias": 0.06, "scale": 0.15, "alpha": 0.05, "xi": 0.035})
    # σ of the mag terms after the cold-start ellipsoid fit (bias floor relative to the field, scale
    # relative; alpha: the alignment to B is not in the fit; xi: the symmetric fit mixes it with alpha)
    mag_ellipsoid_sigma: dict[str, float] = field(default_factory=lambda: {
        "bias": 0.005, "scale": 0.02, "alpha": 0.05, "xi": 0.01})
    dip_sigma: float = 0.1  # rad, prior of the dip around its first estimate
    att_init_sigma: float = 0.2  # rad, prior of the attitude taken from the first block's accel (and mag)
    yaw_free_sigma: float = 1.0  # rad, σ of the heading while no mag sees it (diffuse; nothing depends on it)
    # random walk on the calibration states per √s: the white-noise density of the sensor times this
    # (bias) and the density relative to full scale times this (dimensionless terms)
    rw_factor: float = 1e-3
    # the gyro bias's random walk raised to what a trend of its rest means shows (.noise.NoiseModel.
    # walk_from_rest: a warm-up drift); diagnose turns it off, so that an unmodelled drift reads there as the
    # model error it is (temperature_bias) instead of being absorbed as noise
    measure_bias_walk: bool = True
    # quasi-static weighting of the accelerometer (adaptive R): σ² += (k·dev)² + (r ω²)², dev the part of
    # ||a|−g| beyond 3σ of what noise and the calibration's own uncertainty explain
    acc_dev_gain: float = 5.0
    acc_lever_m: float = 0.005
    acc_gate_p: float = 0.999  # chi-square gate on the accel NIS (3 dof)
    mag_gate_p: float = 0.9999  # chi-square gate on the mag NIS: soft (R inflated), never dropped
    nis_window: int = 100  # updates per NIS window
    nis_band_p: float = 0.001  # two-sided probability outside the window band
    divergence_factor: float = 5.0  # window mean NIS > factor × upper band ...
    divergence_windows: int = 3  # ... for this many windows in a row → divergence
    mag_fit_min_samples: int = 100
    mag_fit_min_spread: float = 0.1  # smallest eigenvalue of the scatter of unit field directions (1/3: a sphere)
    # smallest eigenvalue of the *covariance* (centred) of the unit field directions: a flight's yaw turns
    # and ±25° tilts sweep a band (0.001–0.009 over 10 min, multirotor and fixed-wing profiles) on which the
    # centre along the band's axis and that axis' scale trade off against the gyro's x/y scale (a cold fit
    # there ended 30–45σ off); the paper session reaches 0.058 within 60 s, 0.17 by 120 s
    mag_fit_min_cover: float = 0.03
    mag_fit_max_centre_sigma: float = 0.01  # LS σ of the sphere's centre, relative to its radius
    mag_buffer_max: int = 2000
    max_gap_s: float = 0.5  # IMU gap that restarts the attitude
    rest_k: float = 2.0  # rest: per-axis spread below k σ, mean change below 2k σ √(2/L)
    rest_blocks: int = 3  # consecutive still blocks before the zero-rate update applies
    # rad/s per axis, what a gyro at rest reads besides its bias (zero-rate update; on a vehicle also the
    # gyro-bias floor and attitude noise of .vehicle.earth_rate_noise): the Earth's rotation, which the
    # model lacks, Ω_E = 7.292115e-5 rad/s projected on the body axes — for a level body at an unknown
    # heading and latitude (uniform over the Earth's surface: E[sin²φ] = 1/3) rms Ω_E/√3 on every axis
    # (was 5e-5, "micro-motion"; with Earth rate in the flights' gyro that left the cold NEES ~0.6/dof)
    rest_rate_sigma: float = 7.292115e-5 / 3**0.5
    # deg, where the vehicle is (a log's GPS, `--latitude`): the Earth's rotation is taken out of the raw rates
    # (.earth.correct_block) and the allowances above shrink to what the declination leaves (.earth.allowance);
    # None: not known, the allowance for any latitude
    latitude_deg: float | None = None
    # where latitude_deg came from, in words ("--latitude", "latitude 47.3977° from f.bin's GPS (...)"): reported
    # with it (observability_report's earth_rate), never used by the filter
    latitude_source: str | None = None
    # deg, east positive: the magnetic declination D (the filter's heading is magnetic, the Earth's axis points to
    # true north), and its σ: unknown, 0 ± 15° (the World Magnetic Model's charts put most of the populated
    # mid-latitudes within ±15°); `--declination` gives it with σ 1° (the model's error away from local
    # anomalies is a fraction of a degree). The allowance across north is Ω_E cos φ · σ_D
    declination_deg: float = 0.0
    declination_sigma_deg: float = 15.0
    # where declination_deg came from when not from `--declination` ("declination +3.38° ± 1.0° from the World
    # Magnetic Model (WMM2020 at 2023.9; ...)": onlinecal.place): reported, never used by the filter
    declination_source: str | None = None
    trace_every_s: float = 1.0
    trace_max_rows: int = 100_000
    max_events: int = 1000  # events kept (oldest dropped beyond); the count of all is in nis_summary
    # whose alpha defines B (held at its prior as a consider state); "auto": the gyro when ``init`` is a
    # batch result whose gyro came from its rotation phases (the batch's own definition of B), else the
    # init sensor with the tightest alpha σ, else the accelerometer; None: all free
    gauge_sensor: str | None = "auto"
    # which terms of the gauge sensor are held: "alpha", "alpha+xi", or "auto" ("alpha+xi" for a
    # phase-based batch gyro — the phases fix all three axes of B in the gyro, not only a rotation)
    gauge_terms: str = "auto"
    excited_ratio: float = 0.5  # posterior σ / prior σ below this: "excited"
    quant_hold: bool = True  # model the mean error of held readings on a re-quantised lattice
    # measured noise (third differences of the raw samples) above this multiple of the spec's variance
    # (smoothed over noise_tau_blocks blocks) → the sensor's noise is scaled up and an event raised;
    # back below noise_low → back to the spec
    noise_high: float = 4.0
    noise_low: float = 2.0
    noise_tau_blocks: float = 10.0
    # rad/s: a block turning faster than this (its mean rate less the gyro bias, beyond 3σ of the bias, or its
    # rate's spread within the block beyond the gyro's noise: step.turning) is not read by the noise monitor
    # nor by the vehicle detector's vibration test, until a vehicle is detected by its vibration. In
    # a hand's turn the third difference reads the hand's own broadband specific force, not the sensor's
    # noise: on the imu_tk Xsens session the accel's reads 0.98× the spec's variance in blocks below
    # 0.02 rad/s and 5–52× (medians) in the faster ones, and hand-held sessions (Ferraris, three MARG
    # files, Xsens) were taken for vehicles from it (docs/flight.md). On a vehicle detected by its vibration
    # that is the accelerometer's noise at any rate, and every block is read
    noise_rate_max: float = 0.02
    # saturation: a reading repeated rail_run times in a row, of magnitude at least rail_min (rad/s,
    # m/s²), is the ADC rail; from then on readings at the rail are clipped
    rail_min: dict[str, float] = field(default_factory=lambda: {"gyro": 1.0, "accel": 14.7})
    rail_run: int = 40
    extra_states: tuple[str, ...] = ()  # model extensions, keys of EXTENSIONS
    # partial update in motion: the gain is that of an R at least this share of the predicted spread HPHᵀ
    # (the mean moves at most 1/(1 + share) of the way to the measurement; P, with the true R, then keeps
    # (share² + R/HPHᵀ)/(1 + share)² of the prior's variance along it: 4 → at least 64 %) and
    # the rest comes from the next blocks, linearised at the improved estimate (0: off). Costs nothing once
    # converged (HPHᵀ ≪ R): the 20-seed batch-started figures are the same at 1 and 4. On a cold start it
    # keeps the first large turns from over-narrowing the prior: with the mag from the batch, every gyro
    # and accel bias and scale ends within 3σ after 60 s of motion on 9/12 seeds at 1 (half per block),
    # 12/12 at 4 and at 8, and 12/12 on the 12 further seeds not used to choose it (benchmarks/ukf_stats.py
    # --cold 90 --set update_damping=…)
    update_damping: float = 4.0
    # the body-frame turn (degrees) of gravity (the accelerometer's reading), of the field (the magnetometer's)
    # between two motion blocks that learn that sensor's terms (.learning); the blocks between use the sensor with
    # its terms held. 0: every block learns (before session 19, when a still or straight stretch read its null
    # space's curvature as information: 3-min fixed-wing flights started from their truth ended up to 12σ off).
    # Those flights (seeds 0–5) end within 3σ at 5°, 2° and 1° alike; the prior-free NEES of what they determined
    # is 48/95, 63/103 and 83/109 [99 % band ~0.6–1.4 × dof]: the larger the angle, the more of the data is left
    # unused, so the smallest that still separates a still or straight stretch
    learn_angle_deg: float = 1.0
    # σ (rad) of the gauge sensor's held terms on a cold start: B *is* that sensor's frame by definition (a
    # convention has no uncertainty). With the cold prior's 2° there instead, the relative alignment of the
    # other sensors to it was not learned (paper session, cold: gyro and mag alphas both ~1° off in the
    # accelerometer's frame, accel matrix 1.9 % off after the common rotation; with 1e-7: 0.002°)
    gauge_cold_sigma: float = 1e-7
    # a vehicle's own acceleration (:mod:`.vehicle`): "auto" detects it from the data (vibration, a
    # specific-force norm away from g, or the gate's drops), "vehicle" assumes it from the start, "platform"
    # never. Once on, every accelerometer update outside a rest carries an unknown acceleration of σ vehicle_accel_sigma
    # per axis correlated over vehicle_accel_tau s (a multirotor's ≤ 3 m/s² legs; a fixed-wing's turns,
    # g·tan 30° ≈ 5.7 m/s² for up to 30 s), rests of a vibrating vehicle are judged with the spec noise
    # (vibration cannot pass), and the accelerometer's terms are held in motion (StateLayout.consider_vehicle)
    vehicle: str = "auto"
    vehicle_accel_sigma: float = 3.0
    vehicle_accel_tau: float = 30.0
    vehicle_vibration_sigma: float = 0.3  # m/s² per sample: above any MEMS accelerometer's own noise
    vehicle_dev_min: float = 0.5  # m/s² of unexplained ||f| − g| for 5 blocks: a linear acceleration
    # accel updates the gate dropped in the last 20 moving blocks that make a vehicle (a hand's pushes the norm
    # test misses while the scale is uncertain: .vehicle.VehicleDetector.gate); 0: not this way (diagnose's UKF
    # stage, whose NIS must show a model error rather than take it for a vehicle)
    vehicle_gate_drops: int = 5
    # the sensors' noise and ADC (onlinecal.specs): R, Q, the lattice test and the rail all scale with them
    gyro_spec: SensorSpec = GYRO_SPEC
    accel_spec: SensorSpec = ACCEL_SPEC
    mag_spec: SensorSpec = MAG_SPEC

    def __post_init__(self) -> None:
        lat = self.latitude_deg
        if lat is not None and not (math.isfinite(lat) and abs(lat) <= 90.0):
            raise ValueError(f"latitude_deg must be within ±90°, not {lat!r}")
        if not (math.isfinite(self.declination_deg) and abs(self.declination_deg) <= 180.0):
            raise ValueError(f"declination_deg must be within ±180°, not {self.declination_deg!r}")
        if not (math.isfinite(self.declination_sigma_deg) and 0.0 <= self.declination_sigma_deg <= 180.0):
            raise ValueError(f"declination_sigma_deg must be within 0…180°, not {self.declination_sigma_deg!r}")

    def sensor_specs(self) -> dict[str, SensorSpec]:
        """{sensor: spec} of gyro, accel, mag."""
        return {"gyro": self.gyro_spec, "accel": self.accel_spec, "mag": self.mag_spec}

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["extra_states"] = list(self.extra_states)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> UKFConfig:
        known = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in known}  # settings dropped since a state was saved
        if "extra_states" in d:
            d["extra_states"] = tuple(d["extra_states"])
        for k in ("gyro_spec", "accel_spec", "mag_spec"):
            if isinstance(d.get(k), dict):
                d[k] = SensorSpec(**d[k])
        return cls(**d)
