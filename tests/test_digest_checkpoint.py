"""A live run's checkpoint carries the samples' raw digest (session 20).

What was wrong: `onlinecal run --checkpoint FILE` saved the filter but not :class:`onlinecal.health.RawDigest`, what
the health verdict reads of the samples fed (gravity at rest, the rail). After a kill and `--resume` the verdict —
and `--apply`'s guard, which keeps a sensor's parameters off the vehicle where those checks name it — judged only the
samples fed since the resume: a ground rest before the crash no longer counted.

Now the digest's block rows are appended to FILE.digest before each checkpoint (which records their count) and its
small part rides in the checkpoint. The truth these tests hold it to is the digest of the same samples fed without
an interruption, and the checks' verdicts on them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from onlinecal.health import RawDigest, gravity_checks, rail_checks
from onlinecal.io.base import LogError
from onlinecal.model import SensorCalibration
from onlinecal.sim import simulate
from onlinecal.ukf.live_files import DigestFile, digest_path, load_digest


def _feed(d: RawDigest, w: np.ndarray, a: np.ndarray, lo: int, hi: int, rng: np.random.Generator) -> None:
    i = lo
    while i < hi:
        j = min(hi, i + int(rng.integers(1, 400)))
        d.add(w[i:j], a[i:j])
        i = j


def _checkpoint(d: RawDigest, f: DigestFile) -> dict:
    """What `_LiveRun.save_checkpoint` does with the digest, through JSON as the checkpoint file does."""
    f.append(d.rows(f.written or 0))
    return json.loads(json.dumps({"schema": "onlinecal.live-checkpoint/2",
                                  "digest": {"file": f.path.name, "state": d.state()}}))


@pytest.fixture(scope="module")
def flight() -> tuple[np.ndarray, np.ndarray, object]:
    sim = simulate("multirotor", 2, duration=90.0, imu_rate=200.0)  # a 35-s ground rest, then flight
    w = sim.data.gyro.copy()
    w[40 * 200: 60 * 200] = np.clip(w[40 * 200: 60 * 200] * 8.0, -2.0, 2.0)  # a stretch at a ±2 rad/s rail
    return w, sim.data.acc, sim.truth.calibration


def test_a_digest_resumed_from_its_checkpoint_equals_the_uninterrupted_one(tmp_path: Path, flight) -> None:
    w, a, truth = flight
    n = w.shape[0]
    cuts = [3_001, 7_000 + 17, 9_950, 12_345, n]  # checkpoints mid-block, in the rest, in the rail, at the end
    logs = [0, 8_000]  # a vehicle reboot (a new log) at 40 s
    whole = RawDigest()
    for lo, hi in zip(logs, [*logs[1:], n], strict=True):
        whole.new_log()
        _feed(whole, w, a, lo, hi, np.random.default_rng(lo))
    # the same samples, checkpointed at every cut and resumed from the files alone (a new process each time)
    ck_path = tmp_path / "run.ckpt"
    d, f, i = RawDigest(), DigestFile(digest_path(ck_path)), 0
    rng = np.random.default_rng(7)
    for cut in cuts:
        while i < cut:
            j = min([cut, *(b for b in logs if b > i)])  # up to the cut or the next reboot
            if i in logs:
                d.new_log()
            _feed(d, w, a, i, j, rng)
            i = j
        ck = _checkpoint(d, f)
        if cut != n:
            d, f, lost = load_digest(ck, ck_path)
            assert lost is None
    assert d.blocks == whole.blocks == 8_000 // 50 + (n - 8_000) // 50  # blocks never span the reboot
    for s in RawDigest.SENSORS:
        for got, want in zip(d.block_stats(s), whole.block_stats(s), strict=True):
            assert np.array_equal(got, want)  # the same bits
        assert all(np.array_equal(x, y) for x, y in zip(d.rails(s)[:2], whole.rails(s)[:2], strict=True))
        assert d.rails(s)[2] == whole.rails(s)[2]
    wrong = truth.replace(accel=SensorCalibration(truth.accel.bias + np.array([0.0, 0.0, 0.3]), truth.accel.matrix,
                                                  {"bias": [1e-3] * 3, "scale": [1e-4] * 3}))
    assert gravity_checks(wrong, d) == gravity_checks(wrong, whole)
    assert gravity_checks(wrong, d)[0][0][0] == "degraded"  # the check's premise: the ground rest shows it
    assert rail_checks(d) == rail_checks(whole) and rail_checks(d)[1]["gyro"] >= 100


def test_rows_written_after_the_checkpoint_are_cut_off_on_resume(tmp_path: Path, flight) -> None:
    """A crash between the rows' append and the checkpoint's rename: the file holds more rows than the checkpoint on
    disk records; the resume keeps the recorded ones and the run appends after them."""
    w, a, _ = flight
    ck_path = tmp_path / "run.ckpt"
    d, f = RawDigest(), DigestFile(digest_path(ck_path))
    _feed(d, w, a, 0, 5_000, np.random.default_rng(1))
    ck = _checkpoint(d, f)
    _feed(d, w, a, 5_000, 9_000, np.random.default_rng(2))
    f.append(d.rows(f.written or 0))  # appended, then the process died before the checkpoint was renamed
    size_before = digest_path(ck_path).stat().st_size
    r, f2, lost = load_digest(ck, ck_path)
    assert lost is None and r.blocks == 100 and f2.written == 100
    assert digest_path(ck_path).stat().st_size == len(DigestFile.MAGIC) + 100 * RawDigest.ROW * 8 < size_before


def test_a_lost_or_damaged_digest_file_resumes_the_calibration_and_says_so(tmp_path: Path, flight) -> None:
    w, a, _ = flight
    ck_path = tmp_path / "run.ckpt"
    d, f = RawDigest(), DigestFile(digest_path(ck_path))
    _feed(d, w, a, 0, 5_000, np.random.default_rng(1))
    ck = _checkpoint(d, f)
    p = digest_path(ck_path)
    good = p.read_bytes()
    for damage, words in ((lambda: p.unlink(), "missing"),
                          (lambda: p.write_bytes(good[:-200]), "holds 98 of the 100 blocks"),
                          (lambda: p.write_bytes(b"x" + good[1:]), "not a raw digest")):
        p.write_bytes(good)
        damage()
        r, f2, lost = load_digest(ck, ck_path)
        assert lost is not None and words in lost and str(p) in lost and "from this resume on" in lost
        assert r.blocks == 0 and f2.written is None  # started anew at the next checkpoint
    # a checkpoint of schema /1 (before the digest was in it): resumed, and said
    r, _, lost = load_digest({"schema": "onlinecal.live-checkpoint/1"}, ck_path)
    assert r.blocks == 0 and lost is not None and "without the samples' raw digest" in lost
    # the checkpoint's own entry malformed: a damaged checkpoint, one line naming it
    for bad in ({"state": None}, {"state": {**ck["digest"]["state"], "blocks": -1}},
                {"state": {**ck["digest"]["state"], "carry": [[[0.0, 0.0, 0.0]], []]}},
                {"state": {**ck["digest"]["state"], "top": {"gyro": [1.0], "accel": [0.0] * 3}}}):
        p.write_bytes(good)
        with pytest.raises(LogError) as e:
            load_digest({**ck, "digest": bad}, ck_path)
        assert str(ck_path) in str(e.value) and "raw digest" in str(e.value) and "\n" not in str(e.value)
