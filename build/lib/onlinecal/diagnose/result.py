"""The Diagnosis value object and its JSON (contract: ``"schema": "onlinecal.diagnosis/1"``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..files import sanitize
from ..model import Calibration

SCHEMA = "onlinecal.diagnosis/1"
GAIN_KEYS = ("heldout_rms_before", "heldout_rms_after", "loglik_gain", "bic_delta")
# the UKF stage's figures (window-mean NIS per update, expected 3; share of windows outside the band), where run
OPT_GAIN_KEYS = ("gain_spread",)
UKF_GAIN_KEYS = ("ukf_nis_before", "ukf_nis_after", "ukf_outside_before", "ukf_outside_after")


_plain = sanitize  # one JSON sanitiser for every output (onlinecal.files)


@dataclass
class Finding:
    """One candidate effect: named cause, where, how strongly (score = held-out log-likelihood gain, nats),
    whether it clears the session's own null, its fitted parameters (the effect spec's keys) and gain."""

    effect: str
    sensor: str
    axis: str | None
    score: float
    significant: bool
    parameters: dict[str, Any]
    gain: dict[str, float]
    evidence: str
    threshold: float = float("nan")
    null_score: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return _plain({"effect": self.effect, "sensor": self.sensor, "axis": self.axis, "score": self.score,
                       "significant": self.significant, "parameters": self.parameters,
                       "gain": {**{k: self.gain.get(k, float("nan")) for k in GAIN_KEYS},
                                **{k: self.gain[k] for k in OPT_GAIN_KEYS + UKF_GAIN_KEYS if k in self.gain}},
                       "evidence": self.evidence, "threshold": self.threshold, "null_score": self.null_score})


@dataclass
class Diagnosis:
    baseline: dict[str, Any]
    findings: list[Finding]
    calibration: Calibration  # the baseline model with the significant findings as ``extensions``
    untestable: list[str] = field(default_factory=list)
    simulation_check: dict[str, Any] = field(default_factory=dict)
    timing: dict[str, float] = field(default_factory=dict)
    sources: list[str] = field(default_factory=list)
    ukf_extended: dict[str, Any] = field(default_factory=dict)  # the UKF with the extensions (stage 6)

    @property
    def significant(self) -> list[Finding]:
        return [f for f in self.findings if f.significant]

    @property
    def verdict(self) -> str:
        sig = self.significant
        return sig[0].effect if sig else "none"

    def to_dict(self) -> dict[str, Any]:
        return _plain({
            "schema": SCHEMA,
            "sources": self.sources,
            "baseline": self.baseline,
            "findings": [f.to_dict() for f in self.findings],
            "verdict": self.verdict,
            "extended_calibration": self.calibration.to_dict(),
            "simulation_check": self.simulation_check,
            "ukf_extended": self.ukf_extended,
            "untestable": self.untestable,
            "timing_s": self.timing,
        })

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False)

    def save(self, path: str | Path) -> None:
        from ..files import atomic_write  # the package's one writer

        atomic_write(path, self.to_json() + "\n")
