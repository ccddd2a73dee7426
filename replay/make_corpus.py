"""Regenerate the replay corpus: simulated sessions with their truth, a few MB in all.

    python replay/make_corpus.py            # writes replay/corpus/*.tlog|csv + *.truth.json

Each session is deterministic in its seed, so the corpus is reproducible byte for byte.
"""

from __future__ import annotations

from pathlib import Path

from onlinecal.io import write_log
from onlinecal.sim import simulate

HERE = Path(__file__).resolve().parent
# (file name, profile, seed, duration, IMU rate, mag rate)
SESSIONS = [
    ("paper-s1.tlog", "paper", 1, None, 100.0, 50.0),
    ("paper-s2.bin", "paper", 2, None, 100.0, 50.0),
    ("flight-s4.tlog", "flight", 4, 120.0, 100.0, 50.0),
]


def main() -> None:
    out = HERE / "corpus"
    out.mkdir(exist_ok=True)
    for name, profile, seed, duration, rate, mag_rate in SESSIONS:
        sim = simulate(profile, seed, duration, rate, mag_rate)
        write_log(out / name, sim.data)
        sim.truth.save(out / (name + ".truth.json"))
        print(f"{name}: {sim.data.n_imu} IMU samples, {sim.data.duration:.0f} s")


if __name__ == "__main__":
    main()
