"""Where the logs of a replay were recorded, as the filter's Earth-rate settings: the latitude from the logs' GPS
(:mod:`onlinecal.io.position`) and the magnetic declination there from the World Magnetic Model.

The filter's heading is magnetic; the Earth's rotation axis points to true north. With a position and a date
the declination D is known to the model's own uncertainty (NOAA/BGS's error model of each WMM release,
δD = √(0.26² + (5417 nT / H)²)° for WMM2025, H the field's horizontal intensity: ~0.4° at mid-latitudes, growing
towards the magnetic poles), which the filter is told with a floor of 1° — what ``--declination`` promises
— for the crustal anomalies and the vehicle's own field the model does not know. The WMM comes from
``pygeomag`` (NOAA's coefficient files, 2010–2030); a log dated outside them, or not dated at all, is given
today's date (a note says so; D drifts by up to ~0.2° a year at mid-latitudes).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from typing import Any, NamedTuple

from onlinecal.io.base import decimal_year

# what the filter does with a latitude, said after where it came from (replay and run alike)
TAKEN_OUT = "the Earth's rotation is taken out of the gyro (--latitude none: not)"
# what the batch does with it (eqs. 34-35 at its rests)
TAKEN_OUT_BATCH = "the Earth rotation's vertical part is taken out of the rests' gyro bias (--latitude none: not)"
DECLINATION_FLOOR_DEG = 1.0  # crustal anomalies and the vehicle's own field: what --declination promises
# (first year, last year, pygeomag coefficient file): NOAA's releases, each valid five years
_WMM = ((2010.0, 2015.0, "wmm/WMM_2010.COF"), (2015.0, 2020.0, "wmm/WMM_2015v2.COF"),
        (2020.0, 2025.0, "wmm/WMM_2020.COF"), (2025.0, 2030.0, "wmm/WMM_2025.COF"))


@dataclass(frozen=True)
class Declination:
    """The magnetic declination at a place and date: ``deg`` east positive, ``sigma_deg`` as the filter is told
    it (the model's δD, at least :data:`DECLINATION_FLOOR_DEG`), ``model_sigma_deg`` the model's own δD,
    ``model`` e.g. "WMM2025", ``year`` the decimal year evaluated, ``note`` why the date is not the log's
    (None when it is)."""

    deg: float
    sigma_deg: float
    model_sigma_deg: float
    model: str
    year: float
    note: str | None = None

    def describe(self) -> str:
        return (f"declination {self.deg:+.2f}° ± {self.sigma_deg:.1f}° from the World Magnetic Model "
                f"({self.model} at {self.year:.1f}; its own ± {self.model_sigma_deg:.2f}°)")


def wmm_declination(lat_deg: float, lon_deg: float, year: float | None, alt_km: float = 0.0) -> Declination:
    """The WMM's declination at (``lat_deg``, ``lon_deg``) and decimal ``year`` (None: today). Raises ValueError
    for a position outside ±90°/±180°."""
    from pygeomag import GeoMag

    if not (abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0):
        raise ValueError(f"no position at latitude {lat_deg!r}, longitude {lon_deg!r}")
    note = None
    if year is None or not _WMM[0][0] <= year < _WMM[-1][1]:
        today = decimal_year(_dt.datetime.now(tz=_dt.UTC).timestamp())
        note = ("the log is not dated" if year is None else f"the log's date {year:.1f} is outside the WMM's "
                f"{_WMM[0][0]:.0f}–{_WMM[-1][1]:.0f}") + f": evaluated at today's date, {today:.1f}"
        year = today
    lo, hi, coef = next(((a, b, c) for a, b, c in _WMM if a <= year < b), _WMM[-1])
    res: Any = GeoMag(coefficients_file=coef).calculate(glat=lat_deg, glon=lon_deg, alt=alt_km, time=year,
                                                        allow_date_outside_lifespan=True)
    try:
        model_sigma = float(res.calculate_uncertainty().d)
    except ValueError:  # a date without NOAA's error model (before 2015)
        model_sigma = DECLINATION_FLOOR_DEG
    # near the magnetic poles H → 0 and δD grows without bound; the filter's prior takes at most 180°
    return Declination(float(res.d), min(180.0, max(DECLINATION_FLOOR_DEG, model_sigma)), model_sigma,
                       f"WMM{int(lo)}", float(year), note)


class EarthRateSetting(NamedTuple):
    """What :func:`earth_rate_config` decided: ``config`` (a UKFConfig, or None for the defaults); ``source``
    where the latitude came from when it came from the logs (None: ``--latitude`` or none at all);
    ``declination_line`` the World Magnetic Model's declination in words, where it was used; ``warnings``."""

    config: Any
    source: str | None
    declination_line: str | None
    warnings: list[str]


def told_line(latitude_deg: float, source: str, effect: str = TAKEN_OUT) -> str:
    """The line that says where a latitude came from and what is done with it."""
    return f"latitude {latitude_deg:.4f}° from {source}: {effect}"


def earth_rate_config(latitude: float | str | None, declination: float | None,
                      paths: list[str] | None) -> EarthRateSetting:
    """The filter's configuration for the Earth's rotation, from the command line and the logs:
    ``latitude`` a number (``--latitude``), "none" (off) or None (the logs' GPS); ``declination`` a number
    (``--declination``, ± 1°) or None (the WMM at the logs' fix, where they have one; else unknown, 0 ± 15°).

    Raises ValueError where the options cannot be honoured (a declination without any latitude)."""
    from onlinecal.ukf.config import UKFConfig

    if latitude == "none":
        if declination is not None:
            raise ValueError("--declination places the Earth's rotation, which --latitude none turns off")
        return EarthRateSetting(None, None, None, [])
    notes: list[str] = []
    if latitude is None and paths:
        from onlinecal.io.position import logs_place

        where, source, notes = logs_place(paths)
        if where is not None:
            config, line = config_at(where, source or "", declination, None)
            return EarthRateSetting(config, source, line, notes)
    if latitude is None:
        if declination is not None:
            raise ValueError("--declination needs --latitude (it places the Earth's rotation, which needs the "
                             "latitude), or a log with a GPS fix")
        return EarthRateSetting(None, None, None, notes)
    extra: dict[str, Any] = {}
    if declination is not None:
        extra = {"declination_deg": float(declination), "declination_sigma_deg": DECLINATION_FLOOR_DEG}
    return EarthRateSetting(UKFConfig(latitude_deg=float(latitude), latitude_source="--latitude", **extra),
                            None, None, [])


def config_at(where: Any, source: str, declination: float | None, base: Any) -> tuple[Any, str | None]:
    """``base`` (a UKFConfig; None: the defaults) told the position ``where`` (an io.position.LogPosition):
    its latitude, and ``declination`` (± 1°) or else the WMM's at the position and its date. Returns the config
    and, where the WMM gave the declination, its line in words."""
    from dataclasses import replace

    from onlinecal.ukf.config import UKFConfig

    line = None
    if declination is not None:
        extra: dict[str, Any] = {"declination_deg": float(declination),
                                 "declination_sigma_deg": DECLINATION_FLOOR_DEG, "declination_source": None}
    else:
        d = wmm_declination(where.latitude_deg, where.longitude_deg, where.year)
        extra = {"declination_deg": d.deg, "declination_sigma_deg": d.sigma_deg, "declination_source": d.describe()}
        line = d.describe() + (f" ({d.note})" if d.note else f" (the log's date from {where.year_source})")
    config = replace(base if base is not None else UKFConfig(), latitude_deg=float(where.latitude_deg),
                     latitude_source=source, **extra)
    return config, line
