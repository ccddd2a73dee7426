"""When a motion update may learn a sensor's terms: only where the reference vector's direction in the body is new.

At one attitude the magnetometer's 3-vector cannot separate the heading from its bias across the field, nor the dip
from its bias in the north-up plane; the accelerometer's cannot separate the tilt from its bias and alignment
across gravity. A consistent filter keeps its σ along those directions however many samples arrive at that
geometry; the unscented (or extended) update does not: each look is linearised at a slightly different mean and
spread, its measurement's row space turns a little, and look after look the curvature of the null space is read
as information (``benchmarks/nullspace_leak.py``: 100 looks at one attitude take the heading's σ from 0.068 to
0.007 rad, 5.5σ off; on the 5-term model with the truth drawn from the prior, the mean z² of the heading after 200
looks is 69 where the exact posterior's is 1.0). A rest avoids it by applying its running means once, from the
state it began with (:mod:`.rest`); a vehicle's straight leg, a hover and an armed vehicle on the ground are
motion blocks at one geometry.

The remedy is ArduPilot EKF3's "learn the magnetometer's states only when manoeuvring" (``EK3_MAG_CAL`` = 1), with
manoeuvring defined by what makes the terms observable — the reference vector turning in the body: a motion
block's update learns a sensor's terms only where its raw mean reading has moved by the chord of ``angle`` (rad)
on the reading's sphere since the last block that learned them (or since the rest that applied its mean there);
every other block uses the sensor with its terms held as Schmidt consider states (zero gain, their covariance and
cross-covariances kept exact), so it still corrects the attitude, no better than the terms' own σ allows. On the
same 5-term model, 200 looks with every one held keep the heading's z² at 1.04 (σ 0.067 rad, the exact
posterior's 0.067); with the first look learning, as here, 2.3 (σ 0.45–1.1 × the exact; that one unscented update
of a curved model at a signal-to-noise of ~1700 is what remains, ``tests/test_learning_gate.py``). The
chord is measured on the raw reading less the state's bias, so neither the calibration's change nor an offset
larger than the field moves it. The magnetometer's held terms include the dip, which it shares with no sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
LEARNED = ("accel", "mag")  # the sensors measured against a reference vector (gravity, the Earth's field)


@dataclass
class LearningGate:
    """The geometry one sensor's terms were last learned at.

    ``angle``: the body-frame turn (rad) of the reference vector between two learning blocks; 0 learns in every
    block (the behaviour before session 19). ``anchor``: the raw mean reading (3,) of the last learning block or
    rest; None: the next block learns."""

    angle: float
    anchor: Array | None = None

    def learns(self, mean: Array, bias: Array) -> bool:
        """Whether a motion block with raw mean reading ``mean`` (3,) learns the sensor's terms (``bias`` (3,)
        the state's bias, raw units). A block that learns becomes the anchor."""
        if self.angle <= 0.0 or self.anchor is None:
            self.anchor = np.array(mean, dtype=float)
            return True
        # on Python floats: ~2 µs a motion block instead of numpy's ~10 (issue 15)
        m0, m1, m2 = mean.tolist()
        b0, b1, b2 = bias.tolist()
        a0, a1, a2 = self.anchor.tolist()
        chord = 2.0 * math.sin(0.5 * self.angle)
        f2 = (m0 - b0) ** 2 + (m1 - b1) ** 2 + (m2 - b2) ** 2
        if (m0 - a0) ** 2 + (m1 - a1) ** 2 + (m2 - a2) ** 2 >= chord * chord * f2:
            self.anchor = np.array(mean, dtype=float)
            return True
        return False

    def seen(self, mean: Array) -> None:
        """A rest applied its mean reading ``mean`` (3,) as one measurement: that geometry is learned."""
        self.anchor = np.array(mean, dtype=float)

    def reset(self) -> None:
        """The sensor's state or the attitude restarted: the next block learns."""
        self.anchor = None


@dataclass
class Learning:
    """The accelerometer's and the magnetometer's :class:`LearningGate`, and this block's decision ``held``:
    per sensor of :data:`LEARNED`, whether its terms are held in the block's update.

    A held look's NIS is kept out of the consistency windows (:class:`.health.NisMonitor`; the divergence
    checks still see it): at a geometry already seen it re-measures the held terms' error, the same error look
    after look — not an independent sample. Counted, a bench start whose errors are below their σ read as
    "noise overstated" (fixed-wing flights started from their truth: mag mean NIS 1.25 against [1.5, 6])."""

    angle: float
    gates: dict[str, LearningGate] = field(default_factory=dict)  # (a checkpoint passes them in)
    held: tuple[bool, bool] = (False, False)

    def __post_init__(self) -> None:
        if not self.gates:
            self.gates = {s: LearningGate(self.angle) for s in LEARNED}

    def decide(self, accel: tuple[Array, Array] | None, mag: tuple[Array, Array] | None) -> tuple[bool, bool]:
        """This motion block's ``held`` from each sensor's (raw mean (3,), state bias (3,)), None where the block
        does not update with that sensor (or its terms are held anyway)."""
        g = self.gates
        self.held = (accel is not None and not g["accel"].learns(*accel),
                     mag is not None and not g["mag"].learns(*mag))
        return self.held

    def holds(self, sensor: str) -> bool:
        """Whether this block's update holds ``sensor``'s terms (False for a sensor not in :data:`LEARNED`)."""
        return sensor in LEARNED and self.held[LEARNED.index(sensor)]

    def seen(self, sensor: str, mean: Array) -> None:
        """A rest applied ``sensor``'s mean reading ``mean`` (3,) as one measurement (:meth:`LearningGate.seen`)."""
        self.gates[sensor].seen(mean)

    def reset(self, sensor: str | None = None) -> None:
        for s, g in self.gates.items():
            if sensor is None or s == sensor:
                g.reset()
