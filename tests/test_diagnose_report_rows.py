"""Issue 12 row: the diagnosis report showed `nan → nan` for a finding whose held-out RMS is not measured
(saturation is scored by a count of clipped samples), with no unit. It must say "n/a" and name the unit."""
from __future__ import annotations

import math

from onlinecal.diagnose.report import write_report
from onlinecal.diagnose.result import Diagnosis, Finding
from onlinecal.model import Calibration


def test_report_has_no_bare_nan_and_names_the_rms_unit(tmp_path):
    clip = Finding("saturation", "gyro", "x", 187.0, True, {"limit": 4.366}, {"heldout_rms_before": math.nan,
                   "heldout_rms_after": math.nan, "loglik_gain": math.nan, "bic_delta": math.nan},
                   "187 samples at the rail", threshold=10.0)
    cal = Calibration(gyro=None, accel=None, mag=None)
    diag = Diagnosis(baseline={"model": "paper"}, findings=[clip], calibration=cal, sources=["x.csv"])
    text = write_report(diag, tmp_path).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| saturation"))
    assert "nan" not in row.lower().replace("n/a", "")
    assert "n/a → n/a" in row
    assert "(1 = noise)" in text
