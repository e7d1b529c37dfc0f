"""NMEA 0183 GNSS logs (u-blox, Septentrio, NovAtel serial logs; ``nmea_msgs/Sentence``
dumps) -> GNSS fixes in local ENU metres (:class:`~msf_torch.types.GnssFixes`), the
horizontal velocity over ground in m/s (:class:`~msf_torch.types.GnssVelocity`) and a
dual-antenna receiver's heading in rad (:class:`~msf_torch.types.GnssHeading`).

Lines
    One sentence per line, ``$<address>,<field>,...[*hh]``, optionally after a receive
    timestamp of the logging host (seconds, e.g. UNIX time), separated by a comma or
    whitespace: ``1634567890.123,$GNGGA,...`` or ``1634567890.123 $GNGGA,...``. The
    sentence starts at the last ``$`` of the line; blank lines are ignored; lines without a
    ``$`` are counted (``not_nmea``); a prefix that is not a plain decimal number is counted
    (``unreadable_prefix``) and the sentence is read without a receive time. Any talker id
    (``GP``, ``GN``, ``GL``, ``GA``, ``GB``, ``BD``, ``QZ``, ...) is accepted.

Sentences read
    * GGA (fix): UTC ``hhmmss.ss``, latitude ``ddmm.mmmm`` + ``N``/``S``, longitude
      ``dddmm.mmmm`` + ``E``/``W``, quality, satellites, HDOP, altitude above mean sea level
      + ``M``, geoid separation + ``M``, ... Heights go to the WGS-84 ellipsoid: altitude +
      separation; a fix with an empty separation keeps its MSL altitude and sets
      :attr:`NmeaLog.geoid_separation_missing` (warned: its height is off by the geoid
      undulation, tens of metres).
    * GST (error statistics): UTC, RMS, semi-major, semi-minor, orientation, sigma latitude,
      sigma longitude, sigma altitude (m). The sigmas attach to the kept GGA fix of the same
      UTC time of day (to the millisecond; the nearest such GGA in the file) as
      ``sigma_enu = [sigma lon, sigma lat, sigma alt]`` (east, north, up). A fix without a
      GST, or a GST field left empty or zero (receivers write 0 where they computed
      nothing; a zero sigma would claim an exact fix), has NaN there: the estimator's configured
      ``gnss_sigma_m`` applies, as for a ``NavSatFix`` without covariance.
    * RMC (``ddmmyy``; years 80-99 are 19xx, the others 20xx) and ZDA (day, month, year)
      give the UTC date.
    * RMC (UTC, status ``A``/``V``, ..., speed over ground in knots, course over ground in
      degrees true, date, magnetic variation, ``E``/``W``, mode indicator, navigational
      status) and VTG (course true + ``T``, course magnetic + ``M``, speed in knots + ``N``,
      speed in km/h + ``K``, mode indicator) give the velocity over ground, section
      Velocities.
    * HDT (heading in degrees true + ``T``) and THS (heading in degrees true, mode indicator)
      give the heading, section Headings.
    * Any other sentence (GSV, GSA, GLL, proprietary ``$P...``) is counted by its type and
      skipped.

Velocities
    Speed ``s`` (knots x 1852/3600 m/s; VTG: knots when given, else km/h / 3.6) and course
    ``c`` (degrees clockwise from true north) give ``east = s sin(c)``, ``north = s cos(c)``,
    ``up = NaN`` (not measured) m/s, in the ENU frame of the fixes. The course is measured
    from the north at the antenna; the frame's north is that of its origin: they differ by
    the meridian convergence, about ``delta_lon sin(lat)`` (0.01 deg 1 km east of an origin
    at 49 N), which is not corrected. NMEA gives no velocity accuracy: ``sigma`` is NaN (the
    estimator's configured ``gnss_velocity_sigma_mps`` applies).

    * A stationary receiver may leave the course empty: speed 0 with an empty course is the
      measurement (0, 0); a speed above 0 with an empty course (u-blox below its heading
      threshold) gives no direction and is skipped (``velocity_no_course``).
    * RMC status ``V``, navigational status ``V`` or mode ``N`` (not valid; u-blox writes
      ``$GPVTG,,,,,,,,,N`` without a fix) are skipped (``velocity_invalid``); so are modes
      ``E`` (dead reckoning), ``M`` (manual input) and ``S`` (simulator), which measure
      nothing, as GGA qualities 6-8 (``velocity_mode_not_kept``). Kept: ``A`` autonomous,
      ``D`` differential, ``F`` RTK float, ``P`` precise, ``R`` RTK fixed, and an absent
      mode (NMEA before 2.3; the RMC status decides).
    * A valid sentence with an empty speed is skipped (``velocity_empty``).
    * Times: an RMC's velocity has the RMC's UTC time. VTG has no time field: it belongs to
      the epoch of the latest UTC time read on an earlier line (GGA, GST, RMC, ZDA), which is
      the receiver's own epoch when it writes an epoch's sentences together (u-blox: RMC,
      VTG, GGA, ...; others GGA, ..., VTG); a VTG with no UTC time before it, or after a
      no-fix GGA, is skipped (``velocity_untimed``). UTC times are turned into UNIX seconds
      as the fixes' are (same dates, same rollovers); with ``time="receive"`` a velocity has
      its own line's receive stamp.
    * One velocity per epoch: an RMC and a VTG of the same UTC epoch give the first in the
      file (the later one is counted in ``velocity_same_epoch``: receivers write both every
      epoch, so it is not warned about); a velocity at or before the time of the previous
      epoch's is counted in ``velocity_duplicate`` (warned).

Headings
    A dual-antenna receiver (Septentrio, NovAtel, u-blox moving base, Trimble) writes the
    azimuth of the baseline from its primary to its secondary antenna, degrees clockwise
    from true north, as HDT or THS; it becomes rad in [0, 2 pi). NMEA gives no heading
    accuracy: ``sigma`` is NaN (the estimator's configured ``gnss_heading_sigma_rad``
    applies). The angle is from the north at the antenna, like a course (Velocities).

    * THS mode ``A`` (autonomous) is kept; ``V`` (not valid) is skipped
      (``heading_invalid``); ``E`` (estimated, dead reckoning), ``M`` (manual input) and
      ``S`` (simulator) measure nothing (``heading_mode_not_kept``). HDT has no mode: a
      receiver without a heading leaves the field empty.
    * An empty heading is skipped (``heading_empty``).
    * Times as VTG's: neither sentence has a time field, so a heading belongs to the epoch of
      the latest UTC time read on an earlier line (``heading_untimed`` when there is none, or
      after a no-fix GGA); with ``time="receive"`` it has its own line's receive stamp.
    * One heading per epoch: an HDT and a THS of the same UTC epoch give the first in the file
      (the later one counted in ``heading_same_epoch``, not warned); a heading at or before
      the time of the previous epoch's is counted in ``heading_duplicate`` (warned).

Rules
    * A checksum ``*hh`` is verified when present. A mismatch (or an unreadable ``*hh``)
      skips the line, counted in ``bad_checksum``: one corrupted serial byte does not make
      the log unreadable.
    * A sentence whose checksum is right (or absent) but whose fields are malformed raises
      :class:`~msf_torch.io.errors.DataError` naming the file, line and field
      (``utc_time``, ``latitude``, ``latitude_hemisphere``, ``longitude``,
      ``longitude_hemisphere``, ``quality``, ``satellites``, ``hdop``, ``altitude``,
      ``altitude_unit``, ``geoid_separation``, ``separation_unit``, ``sigma_latitude``,
      ``sigma_longitude``, ``sigma_altitude``, ``date``, ``receive_time``, ``status``,
      ``mode``, ``speed_knots``, ``speed_kmh``, ``course``, ``course_unit``,
      ``speed_knots_unit``, ``speed_kmh_unit``, ``heading``, ``heading_unit``).
    * The receiver's "no fix" forms -- quality 0, or empty latitude and longitude -- are
      skipped and counted (``no_fix``); so are fixes whose quality code is not in
      ``qualities`` (``quality_not_kept``). The quality is the GGA code (1 GPS, 2 DGPS,
      3 PPS, 4 RTK fixed, 5 RTK float, 6 dead reckoning, 7 manual input, 8 simulator): a
      code, not a ranking; by default (:data:`DEFAULT_QUALITIES`) 1-5 are kept, the
      measured fixes.
    * Times: ``time="utc"`` gives UNIX seconds from the UTC time of day and the date of the
      latest RMC/ZDA; fixes before the first date get that date back-filled, and a time of
      day more than 12 h below the previous one rolls to the next day. Without any date the
      times are seconds since 00:00 UTC of the first day (still rolling over; warned).
      ``time="receive"`` uses the receive timestamps (DataError at a kept GGA, an RMC /
      VTG giving a velocity or an HDT / THS giving a heading, without one). ``time="auto"``
      (default) uses them when every kept GGA and every such RMC / VTG / HDT / THS has one,
      else UTC.
    * Fixes must not go back in time (DataError naming the line); a fix at exactly the time of
      the previous one (a second talker's GGA of the same epoch) is dropped
      (``duplicate_time``). Velocities and headings likewise (``velocity_duplicate``,
      ``heading_duplicate``).
    * One warning lists whatever was skipped.

Units: degrees (WGS-84), metres, seconds.

Example:
    >>> log = read_nmea("drive.nmea")  # doctest: +SKIP
    >>> gnss, origin = log.to_gnss(t0=log.t[0])  # doctest: +SKIP
    >>> write_gnss_csv("run/gnss.csv", gnss)  # doctest: +SKIP
    >>> velocity = log.to_gnss_velocity(t0=log.t[0])  # doctest: +SKIP
    >>> write_stream_csv("run/gnss_velocity.csv", "gnss_velocity", velocity)  # doctest: +SKIP
    >>> heading = log.to_gnss_heading(t0=log.t[0])  # doctest: +SKIP

On the command line: ``msf nmea drive.nmea --out run/gnss.csv`` (also writes
``run/gnss_velocity.csv`` and ``run/gnss_heading.csv`` when the log has velocities and
headings).
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_QUALITIES",
    "TIME_SOURCES",
    "NmeaLog",
    "geodetic_fixes",
    "heading_stream",
    "read_nmea",
    "velocity_stream",
    "write_gnss_csv",
]

import datetime
import math
import os
import re
import warnings
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.errors import DataError
from msf_torch.io.geodesy import geodetic_to_enu
from msf_torch.io.native import write_stream_csv
from msf_torch.types import GnssFixes, GnssHeading, GnssVelocity

DEFAULT_QUALITIES = (1, 2, 3, 4, 5)
"""GGA quality codes kept by default: the measured fixes (GPS, DGPS, PPS, RTK fixed, RTK
float), not dead reckoning (6), manual input (7) or a simulator (8)."""
TIME_SOURCES = ("auto", "utc", "receive")
"""Accepted values of ``read_nmea(time=...)`` (module docstring, Rules)."""

# one way to match each digit run: ``\d+\.?\d*`` backtracks quadratically on a long run
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)")
_STAMP = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_UNSIGNED = re.compile(r"\d{1,9}")  # fits int64, a date's year check and int()'s digit limit
_HEX2 = re.compile(r"[0-9A-Fa-f]{2}")
_ADDRESS = re.compile(r"[A-Z][A-Z0-9]{1,9}")
_TIME = re.compile(r"(\d\d)(\d\d)(\d\d)(\.\d*)?")
_ANGLE = re.compile(r"(\d+)(\d\d(?:\.\d*)?)")
_DDMMYY = re.compile(r"(\d\d)(\d\d)(\d\d)")
_GGA_FIELDS = (
    "utc_time",
    "latitude",
    "latitude_hemisphere",
    "longitude",
    "longitude_hemisphere",
    "quality",
    "satellites",
    "hdop",
    "altitude",
    "altitude_unit",
)
_GST_SIGMAS = ("sigma_latitude", "sigma_longitude", "sigma_altitude")
_OUTCOMES = (
    "kept",
    "no_fix",
    "quality_not_kept",
    "duplicate_time",
    "bad_checksum",
    "not_nmea",
    "unreadable_prefix",
    "gst_unmatched",
    "velocity_kept",
    "velocity_invalid",
    "velocity_mode_not_kept",
    "velocity_empty",
    "velocity_no_course",
    "velocity_untimed",
    "velocity_same_epoch",
    "velocity_duplicate",
    "heading_kept",
    "heading_invalid",
    "heading_mode_not_kept",
    "heading_empty",
    "heading_untimed",
    "heading_same_epoch",
    "heading_duplicate",
)
_NOT_WARNED = ("kept", "velocity_kept", "velocity_same_epoch", "heading_kept", "heading_same_epoch")
_SENTENCES_READ = ("GGA", "GST", "RMC", "ZDA", "VTG", "HDT", "THS")
_THS_MODES = frozenset("AEMSV")  # autonomous, estimated, manual, simulator, not valid
_MODES_KEPT = frozenset("ADFPR")  # autonomous, differential, RTK float, precise, RTK fixed
_MODES_NOT_KEPT = frozenset("EMS")  # dead reckoning, manual input, simulator
_KNOT_M = 1852.0  # metres per international nautical mile
_HALF_DAY_S = 43200.0
_DAY_S = 86400
_EPOCH_ORDINAL = datetime.date(1970, 1, 1).toordinal()


@dataclass
class NmeaLog:
    """The kept GGA fixes, RMC / VTG velocities and HDT / THS headings of an NMEA log, in
    file order (module docstring for the rules).

    Attributes:
        t: (N,) s float64, from ``time_source``.
        latitude_deg, longitude_deg: (N,) WGS-84 degrees (south, west negative).
        altitude_m: (N,) height above the WGS-84 ellipsoid (MSL altitude + geoid
            separation), m.
        quality: (N,) int64 GGA fix quality code.
        satellites: (N,) int64 satellites used; -1 where the field is empty.
        hdop: (N,) float64 horizontal dilution of precision; NaN where empty.
        sigma_enu: (N, 3) m ``[east, north, up]`` standard deviations from GST; NaN where
            none was given.
        lines: (N,) int64 1-based line of each fix's GGA.
        time_source: ``"utc"`` or ``"receive"``.
        counts: ``kept``, ``no_fix``, ``quality_not_kept``, ``duplicate_time``,
            ``bad_checksum``, ``not_nmea``, ``unreadable_prefix``, ``gst_unmatched`` (GSTs
            with no kept GGA of their time), ``velocity_kept``, ``velocity_invalid``,
            ``velocity_mode_not_kept``, ``velocity_empty``, ``velocity_no_course``,
            ``velocity_untimed``, ``velocity_same_epoch``, ``velocity_duplicate`` (module
            docstring, Velocities), ``heading_kept``, ``heading_invalid``,
            ``heading_mode_not_kept``, ``heading_empty``, ``heading_untimed``,
            ``heading_same_epoch``, ``heading_duplicate`` (Headings), and
            per sentence type read (upper case: ``GGA``, ``GST``, ``GSV``, ``PUBX``, ...).
        source: the path read.
        geoid_separation_missing: True when some kept fix had an empty geoid separation
            (its height is the MSL altitude).
        dated: True when an RMC or ZDA gave a date (UTC times are then UNIX seconds).
        velocity_t: (M,) s float64 of the kept velocities, on the clock of :attr:`t`.
        velocity_enu: (M, 3) m/s ``[east, north, up]`` over ground; up is NaN (not
            measured).
        velocity_lines: (M,) int64 1-based line of each velocity's RMC or VTG.
        heading_t: (H,) s float64 of the kept headings, on the clock of :attr:`t`.
        heading_rad: (H,) clockwise from true north, rad in [0, 2 pi).
        heading_lines: (H,) int64 1-based line of each heading's HDT or THS.
    """

    t: np.ndarray
    latitude_deg: np.ndarray
    longitude_deg: np.ndarray
    altitude_m: np.ndarray
    quality: np.ndarray
    satellites: np.ndarray
    hdop: np.ndarray
    sigma_enu: np.ndarray
    lines: np.ndarray
    time_source: str
    counts: dict[str, int]
    source: str
    geoid_separation_missing: bool
    dated: bool
    velocity_t: np.ndarray
    velocity_enu: np.ndarray
    velocity_lines: np.ndarray
    heading_t: np.ndarray
    heading_rad: np.ndarray
    heading_lines: np.ndarray

    def __len__(self) -> int:
        """Number of kept fixes N."""
        return int(self.t.shape[0])

    def to_gnss(
        self, origin: Sequence[float] | None = None, t0: float = 0.0
    ) -> tuple[GnssFixes, tuple[float, float, float]]:
        """The fixes as a B = 1 GNSS stream in local ENU metres.

        Args:
            origin: ``(lat_deg, lon_deg, alt_m)`` of the ENU origin (ellipsoidal height);
                None: the first kept fix.
            t0: subtracted from :attr:`t`, s.

        Returns:
            ``(gnss, origin)``: :class:`~msf_torch.types.GnssFixes` with ``t`` (1, N) s,
            ``position`` (1, N, 3) m (:func:`~msf_torch.io.geodesy.geodetic_to_enu`),
            ``sigma`` (1, N, 3) m = :attr:`sigma_enu`, float64, all-True mask; and the
            origin used as three floats.

        Raises:
            ValueError: no origin given and no fix kept; a bad origin.
        """
        return geodetic_fixes(
            self.t - float(t0),
            self.latitude_deg,
            self.longitude_deg,
            self.altitude_m,
            self.sigma_enu,
            origin,
            self.source,
        )

    def to_gnss_velocity(self, t0: float = 0.0) -> GnssVelocity:
        """The velocities as a B = 1 stream in the ENU frame of :meth:`to_gnss`.

        Args:
            t0: subtracted from :attr:`velocity_t`, s (the ``t0`` given to :meth:`to_gnss`).

        Returns:
            :class:`~msf_torch.types.GnssVelocity` with ``t`` (1, M) s, ``velocity``
            (1, M, 3) m/s = :attr:`velocity_enu` (up NaN), ``sigma`` (1, M, 3) all NaN (NMEA
            gives none: the estimator's default applies), float64, all-True mask; M may be 0.
        """
        sigma = np.full(self.velocity_enu.shape, np.nan)
        return velocity_stream(self.velocity_t - float(t0), self.velocity_enu, sigma)

    def to_gnss_heading(self, t0: float = 0.0) -> GnssHeading:
        """The headings as a B = 1 stream: ``t`` (1, H) s (:attr:`heading_t` minus ``t0``),
        ``heading`` (1, H) rad = :attr:`heading_rad`, ``sigma`` (1, H) all NaN (NMEA gives
        none: the estimator's default applies), float64, all-True mask; H may be 0."""
        sigma = np.full(self.heading_rad.shape, np.nan)
        return heading_stream(self.heading_t - float(t0), self.heading_rad, sigma)


def geodetic_fixes(
    t: np.ndarray,
    latitude_deg: np.ndarray,
    longitude_deg: np.ndarray,
    height_m: np.ndarray,
    sigma_enu: np.ndarray,
    origin: Sequence[float] | None,
    source: str,
) -> tuple[GnssFixes, tuple[float, float, float]]:
    """Receiver fixes as a B = 1 GNSS stream in local ENU metres (NMEA, UBX readers).

    Args:
        t: (N,) s. latitude_deg, longitude_deg: (N,) WGS-84 degrees. height_m: (N,) above
            the ellipsoid. sigma_enu: (N, 3) m (NaN: not given).
        origin: ``(lat_deg, lon_deg, h_m)`` of the ENU origin; None: the first fix.
        source: the file, named in the error.

    Returns:
        ``(GnssFixes (1, N), origin used as three floats)``.

    Raises:
        ValueError: no origin given and no fix.
    """
    if origin is None:
        if t.shape[0] == 0:
            raise ValueError(f"{source}: no fix kept, so no origin; give one")
        origin = (float(latitude_deg[0]), float(longitude_deg[0]), float(height_m[0]))
    enu = geodetic_to_enu(latitude_deg, longitude_deg, height_m, origin)
    used = (float(origin[0]), float(origin[1]), float(origin[2]))
    n = int(t.shape[0])
    gnss = GnssFixes(
        t=torch.as_tensor(t, dtype=torch.float64).reshape(1, n),
        position=torch.as_tensor(enu, dtype=torch.float64).reshape(1, n, 3),
        sigma=torch.tensor(sigma_enu, dtype=torch.float64).reshape(1, n, 3),
        mask=torch.ones((1, n), dtype=torch.bool),
    )
    return gnss, used


def velocity_stream(t: np.ndarray, velocity_enu: np.ndarray, sigma: np.ndarray) -> GnssVelocity:
    """Receiver velocities as a B = 1 stream: ``t`` (M,) s, ``velocity_enu`` (M, 3) m/s
    (up NaN: not measured), ``sigma`` (M, 3) m/s (NaN: not given)."""
    m = int(t.shape[0])
    return GnssVelocity(
        t=torch.as_tensor(t, dtype=torch.float64).reshape(1, m),
        velocity=torch.tensor(velocity_enu, dtype=torch.float64).reshape(1, m, 3),
        sigma=torch.tensor(sigma, dtype=torch.float64).reshape(1, m, 3),
        mask=torch.ones((1, m), dtype=torch.bool),
    )


def heading_stream(t: np.ndarray, heading_rad: np.ndarray, sigma_rad: np.ndarray) -> GnssHeading:
    """Receiver headings as a B = 1 stream (NMEA, UBX readers): ``t`` (M,) s,
    ``heading_rad`` (M,) clockwise from true north, ``sigma_rad`` (M,) (NaN: not given)."""
    m = int(t.shape[0])
    return GnssHeading(
        t=torch.as_tensor(t, dtype=torch.float64).reshape(1, m),
        heading=torch.tensor(heading_rad, dtype=torch.float64).reshape(1, m),
        sigma=torch.tensor(sigma_rad, dtype=torch.float64).reshape(1, m),
        mask=torch.ones((1, m), dtype=torch.bool),
    )


def write_gnss_csv(path: str | os.PathLike[str], gnss: GnssFixes) -> Path:
    """Write a B = 1 GNSS stream as a native ``gnss.csv`` table, atomically.

    Columns ``t,x,y,z`` (s, ENU m), plus ``sigma_x,sigma_y,sigma_z`` (m; ``nan`` where
    unknown) unless every sigma is NaN -- the layout :func:`msf_torch.io.read_native` reads
    in a CSV folder. Only real samples (mask True) are written, numbers as shortest exact
    ``repr``.

    Args:
        path: the file to write (normally ``FOLDER/gnss.csv``); its folder must exist.
        gnss: the stream, B = 1.

    Returns:
        the path written.

    Raises:
        ValueError: B != 1.
    """
    return write_stream_csv(path, "gnss", gnss)


@dataclass
class _Fix:
    """One GGA fix as read (before timing)."""

    line: int
    tod: tuple[int, float]  # whole seconds of the day, fraction
    rolls: int  # day rollovers seen before it
    date_index: int  # index into _Reader.dates of the latest date before it, -1: none
    latitude: float
    longitude: float
    altitude: float
    separation_missing: bool
    quality: int
    satellites: int
    hdop: float
    stamp: float | None


@dataclass
class _Velocity:
    """One RMC / VTG velocity as read (before timing); fields as :class:`_Fix`."""

    line: int
    tod: tuple[int, float]
    rolls: int
    date_index: int
    stamp: float | None
    east: float  # m/s
    north: float  # m/s


@dataclass
class _Heading:
    """One HDT / THS heading as read (before timing); fields as :class:`_Fix`."""

    line: int
    tod: tuple[int, float]
    rolls: int
    date_index: int
    stamp: float | None
    heading: float  # rad clockwise from true north, [0, 2 pi)


class _Reader:
    """Line-by-line state of :func:`read_nmea`."""

    def __init__(self, path: str, qualities: frozenset[int]) -> None:
        self.path = path
        self.qualities = qualities
        self.counts: dict[str, int] = dict.fromkeys(_OUTCOMES, 0)
        self.bad_lines: list[int] = []
        self.fixes: list[_Fix] = []
        self.velocities: list[_Velocity] = []
        self.headings: list[_Heading] = []
        # GST sigmas by time of day (ms): [(line, [east, north, up])]
        self.gst_sigmas: dict[int, list[tuple[int, list[float]]]] = {}
        # (roll count, day number) of each date sentence, in order
        self.dates: list[tuple[int, int]] = []
        self.rolls = 0
        self.last_tod: float | None = None
        # the latest UTC time of day read (a VTG's epoch); None after a no-fix GGA
        self.clock: tuple[int, float] | None = None

    # ---------------------------------------------------------------- fields
    def error(self, line: int, field: str, problem: str) -> DataError:
        return DataError(self.path, problem, line=line, field=field)

    def number(self, line: int, field: str, text: str) -> float:
        if not _NUMBER.fullmatch(text):
            raise self.error(line, field, f"not a number: {_tables.shown(text)}")
        value = float(text)
        if not math.isfinite(value):
            raise self.error(line, field, f"beyond the float range: {_tables.shown(text)}")
        return value

    def time_of_day(self, line: int, text: str) -> tuple[int, float]:
        match = _TIME.fullmatch(text)
        if match is None:
            raise self.error(line, "utc_time", f"expected hhmmss.ss, got {_tables.shown(text)}")
        hours, minutes, seconds = (int(g) for g in match.groups()[:3])
        if hours > 23 or minutes > 59 or seconds > 60:
            raise self.error(line, "utc_time", f"not a time of day: {_tables.shown(text)}")
        fraction = float("0" + match.group(4)) if match.group(4) else 0.0
        self.clock = (3600 * hours + 60 * minutes + seconds, fraction)
        return self.clock

    def angle(self, line: int, field: str, text: str, hemi: str, signs: str, top: int) -> float:
        """Degrees from ``[d]ddmm.mmmm`` and its hemisphere letter (``signs`` = "NS"/"EW")."""
        match = _ANGLE.fullmatch(text)
        if match is None:
            raise self.error(
                line, field, f"expected degrees and minutes, got {_tables.shown(text)}"
            )
        degrees, minutes = float(match.group(1)), float(match.group(2))
        value = degrees + minutes / 60.0
        if minutes >= 60.0 or value > top:
            raise self.error(line, field, f"out of range: {_tables.shown(text)}")
        if hemi not in signs:
            raise self.error(
                line,
                f"{field}_hemisphere",
                f"expected {signs[0]} or {signs[1]}, got {_tables.shown(hemi)}",
            )
        return -value if hemi == signs[1] else value

    @staticmethod
    def missing(names: Sequence[str], fields: list[str]) -> str | None:
        return names[len(fields)] if len(fields) < len(names) else None

    # ---------------------------------------------------------------- time of day
    def see_time(self, tod: tuple[int, float]) -> None:
        """Count a UTC day rollover when the time of day drops by more than 12 h."""
        value = tod[0] + tod[1]
        if self.last_tod is not None and value < self.last_tod - _HALF_DAY_S:
            self.rolls += 1
        self.last_tod = value

    # ---------------------------------------------------------------- sentences
    def gga(self, line: int, f: list[str], stamp: float | None) -> None:
        no_quality = len(f) > 5 and _UNSIGNED.fullmatch(f[5]) and int(f[5]) == 0
        if no_quality or (len(f) > 3 and f[1] == "" and f[3] == ""):
            self.counts["no_fix"] += 1
            self.clock = None
            return
        absent = self.missing(_GGA_FIELDS, f)
        if absent is not None:
            raise self.error(line, absent, f"missing: the GGA sentence has {len(f)} fields")
        if not _UNSIGNED.fullmatch(f[5]):
            raise self.error(line, "quality", f"expected a fix quality code, got {f[5]!r}")
        quality = int(f[5])
        tod = self.time_of_day(line, f[0])
        latitude = self.angle(line, "latitude", f[1], f[2], "NS", 90)
        longitude = self.angle(line, "longitude", f[3], f[4], "EW", 180)
        satellites = -1
        if f[6]:
            if not _UNSIGNED.fullmatch(f[6]):
                raise self.error(line, "satellites", f"not a count: {_tables.shown(f[6])}")
            satellites = int(f[6])
        hdop = self.number(line, "hdop", f[7]) if f[7] else math.nan
        if hdop < 0:
            raise self.error(line, "hdop", f"must not be negative, got {f[7]}")
        if not f[8]:
            raise self.error(line, "altitude", "empty in a fix")
        altitude = self.number(line, "altitude", f[8])
        if f[9] not in ("M", ""):
            raise self.error(line, "altitude_unit", f"expected M, got {_tables.shown(f[9])}")
        separation_missing = len(f) < 11 or f[10] == ""
        if not separation_missing:
            altitude += self.number(line, "geoid_separation", f[10])
            if not math.isfinite(altitude):
                raise self.error(
                    line,
                    "geoid_separation",
                    "altitude + geoid separation is beyond the float range",
                )
            if len(f) > 11 and f[11] not in ("M", ""):
                raise self.error(line, "separation_unit", f"expected M, got {_tables.shown(f[11])}")
        if quality not in self.qualities:
            self.counts["quality_not_kept"] += 1
            return
        self.see_time(tod)
        self.fixes.append(
            _Fix(
                line=line,
                tod=tod,
                rolls=self.rolls,
                date_index=len(self.dates) - 1,
                latitude=latitude,
                longitude=longitude,
                altitude=altitude,
                separation_missing=separation_missing,
                quality=quality,
                satellites=satellites,
                hdop=hdop,
                stamp=stamp,
            )
        )

    def gst(self, line: int, f: list[str]) -> None:
        names = ("utc_time", "rms", "semi_major", "semi_minor", "orientation", *_GST_SIGMAS)
        absent = self.missing(names, f)
        if absent is not None:
            raise self.error(line, absent, f"missing: the GST sentence has {len(f)} fields")
        if not f[0]:
            return
        seconds, fraction = self.time_of_day(line, f[0])
        sigmas = []
        for name, text in zip(_GST_SIGMAS, f[5:8], strict=True):
            value = self.number(line, name, text) if text else math.nan
            if value < 0:
                raise self.error(line, name, f"a standard deviation must not be negative: {text}")
            # a zero sigma is no claim of a perfect fix but a field the receiver did not
            # compute: read it as not given (NaN: the configured sigma applies)
            sigmas.append(value if value > 0 else math.nan)
        north, east, up = sigmas
        key = round(1000 * (seconds + fraction))
        self.gst_sigmas.setdefault(key, []).append((line, [east, north, up]))

    def date(self, line: int, tod_text: str, day: int, month: int, year: int) -> None:
        try:
            ordinal = datetime.date(year, month, day).toordinal()
        except ValueError as err:
            raise self.error(line, "date", f"not a date: {err}") from None
        if tod_text:
            self.see_time(self.time_of_day(line, tod_text))
        self.dates.append((self.rolls, ordinal - _EPOCH_ORDINAL))

    def rmc(self, line: int, f: list[str], stamp: float | None) -> None:
        if len(f) >= 9 and f[8]:
            match = _DDMMYY.fullmatch(f[8])
            if match is None:
                raise self.error(line, "date", f"expected ddmmyy, got {_tables.shown(f[8])}")
            day, month, year = (int(g) for g in match.groups())
            self.date(line, f[0], day, month, year + (1900 if year >= 80 else 2000))
        status = f[1] if len(f) > 1 else ""
        if status not in ("A", "V"):
            raise self.error(line, "status", f"expected A or V, got {_tables.shown(status)}")
        tod = self.time_of_day(line, f[0]) if f and f[0] else None
        speed = self.speed(line, "speed_knots", f[6] if len(f) > 6 else "", _KNOT_M)
        course = self.course(line, f[7] if len(f) > 7 else "")
        valid = status == "A" and not (len(f) > 12 and f[12] == "V")
        self.velocity(line, valid, self.mode(line, f, 11), speed, course, tod, stamp)

    def vtg(self, line: int, f: list[str], stamp: float | None) -> None:
        for index, letter, name in (
            (1, "T", "course"),
            (5, "N", "speed_knots"),
            (7, "K", "speed_kmh"),
        ):
            if len(f) > index and f[index] not in (letter, ""):
                raise self.error(
                    line, f"{name}_unit", f"expected {letter}, got {_tables.shown(f[index])}"
                )
        course = self.course(line, f[0])
        speed = self.speed(line, "speed_knots", f[4] if len(f) > 4 else "", _KNOT_M)
        kmh = self.speed(line, "speed_kmh", f[6] if len(f) > 6 else "", 1000.0)
        self.velocity(
            line,
            True,
            self.mode(line, f, 8),
            kmh if speed is None else speed,
            course,
            self.clock,
            stamp,
        )

    def mode(self, line: int, f: list[str], index: int) -> str:
        """The mode indicator letter at ``f[index]``; "" when absent (NMEA before 2.3)."""
        mode = f[index] if len(f) > index else ""
        if mode and mode not in _MODES_KEPT | _MODES_NOT_KEPT | {"N"}:
            raise self.error(
                line, "mode", f"expected one of A D E F M N P R S, got {_tables.shown(mode)}"
            )
        return mode

    def speed(self, line: int, field: str, text: str, unit_m: float) -> float | None:
        """m/s from a speed in ``unit_m`` metres per hour; None when empty."""
        if not text:
            return None
        value = self.number(line, field, text)
        if value < 0:
            raise self.error(line, field, f"must not be negative, got {_tables.shown(text)}")
        return value * unit_m / 3600.0

    def course(self, line: int, text: str, field: str = "course") -> float | None:
        """Course over ground (or a heading: ``field``), degrees true in [0, 360]; None when
        empty."""
        if not text:
            return None
        value = self.number(line, field, text)
        if not 0.0 <= value <= 360.0:
            raise self.error(line, field, f"not in [0, 360] degrees: {_tables.shown(text)}")
        return value

    def velocity(
        self,
        line: int,
        valid: bool,
        mode: str,
        speed: float | None,
        course: float | None,
        tod: tuple[int, float] | None,
        stamp: float | None,
    ) -> None:
        """Keep, or count as skipped, one velocity (module docstring, Velocities)."""
        if not valid or mode == "N":
            skipped = "velocity_invalid"
        elif mode in _MODES_NOT_KEPT:
            skipped = "velocity_mode_not_kept"
        elif speed is None:
            skipped = "velocity_empty"
        elif course is None and speed > 0:
            skipped = "velocity_no_course"
        elif tod is None:
            skipped = "velocity_untimed"
        else:
            heading = math.radians(course or 0.0)
            self.see_time(tod)
            self.velocities.append(
                _Velocity(
                    line=line,
                    tod=tod,
                    rolls=self.rolls,
                    date_index=len(self.dates) - 1,
                    stamp=stamp,
                    east=speed * math.sin(heading),
                    north=speed * math.cos(heading),
                )
            )
            return
        self.counts[skipped] += 1

    def hdt(self, line: int, f: list[str], stamp: float | None) -> None:
        if len(f) > 1 and f[1] not in ("T", ""):
            raise self.error(line, "heading_unit", f"expected T, got {_tables.shown(f[1])}")
        self.heading(line, "A", f[0] if f else "", stamp)

    def ths(self, line: int, f: list[str], stamp: float | None) -> None:
        mode = f[1] if len(f) > 1 else ""
        if mode not in _THS_MODES:
            raise self.error(line, "mode", f"expected one of A E M S V, got {_tables.shown(mode)}")
        self.heading(line, mode, f[0], stamp)

    def heading(self, line: int, mode: str, text: str, stamp: float | None) -> None:
        """Keep, or count as skipped, one heading of THS ``mode`` (HDT: ``"A"``) and degrees
        ``text`` (module docstring, Headings)."""
        degrees = self.course(line, text, "heading")
        if mode == "V":
            skipped = "heading_invalid"
        elif mode != "A":
            skipped = "heading_mode_not_kept"
        elif degrees is None:
            skipped = "heading_empty"
        elif self.clock is None:
            skipped = "heading_untimed"
        else:
            self.see_time(self.clock)
            self.headings.append(
                _Heading(
                    line=line,
                    tod=self.clock,
                    rolls=self.rolls,
                    date_index=len(self.dates) - 1,
                    stamp=stamp,
                    heading=math.radians(degrees) % (2.0 * math.pi),
                )
            )
            return
        self.counts[skipped] += 1

    def zda(self, line: int, f: list[str]) -> None:
        if len(f) < 4 or not (f[1] and f[2] and f[3]):
            return
        if not all(_UNSIGNED.fullmatch(x) for x in f[1:4]):
            raise self.error(line, "date", f"expected day, month, year, got {','.join(f[1:4])!r}")
        self.date(line, f[0], int(f[1]), int(f[2]), int(f[3]))

    # ---------------------------------------------------------------- one line
    def read_line(self, number: int, text: str) -> None:
        text = text.strip()
        if not text:
            return
        start = text.rfind("$")
        if start < 0:
            self.counts["not_nmea"] += 1
            return
        prefix, sentence = text[:start].strip().rstrip(",;").strip(), text[start + 1 :]
        stamp = None
        if prefix:
            if _STAMP.fullmatch(prefix) and math.isfinite(float(prefix)):
                stamp = float(prefix)
            else:
                self.counts["unreadable_prefix"] += 1
        star = sentence.rfind("*")
        if star >= 0:
            given, sentence = sentence[star + 1 :], sentence[:star]
            checksum = 0
            for byte in sentence.encode("utf-8", errors="replace"):
                checksum ^= byte
            if not _HEX2.fullmatch(given) or int(given, 16) != checksum:
                self.counts["bad_checksum"] += 1
                self.bad_lines.append(number)
                return
        fields = sentence.split(",")
        address = fields[0]
        if not _ADDRESS.fullmatch(address):
            self.counts["not_nmea"] += 1
            return
        kind = address if address.startswith("P") or len(address) != 5 else address[2:]
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if kind == "GGA":
            self.gga(number, fields[1:], stamp)
        elif kind == "GST":
            self.gst(number, fields[1:])
        elif kind == "RMC":
            self.rmc(number, fields[1:], stamp)
        elif kind == "VTG":
            self.vtg(number, fields[1:], stamp)
        elif kind == "ZDA":
            self.zda(number, fields[1:])
        elif kind == "HDT":
            self.hdt(number, fields[1:], stamp)
        elif kind == "THS":
            self.ths(number, fields[1:], stamp)


def _read_text(path: str) -> str:
    """The log as text; bytes that are not UTF-8 (serial noise) become U+FFFD, so only
    their lines are affected (their checksums fail)."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise DataError(path, "no such file") from None
    except IsADirectoryError:
        raise DataError(path, "is a folder, expected an NMEA log file") from None
    return data.decode("utf-8-sig", errors="replace")


def _utc_times(
    dates: list[tuple[int, int]], records: Sequence[_Fix] | Sequence[_Velocity] | Sequence[_Heading]
) -> np.ndarray:
    """UNIX seconds (N,) of fixes, velocities or headings from their time of day, the latest date
    before them (the first date for those before it) and the rollovers since; without a
    date, seconds since 00:00 UTC of the first day."""
    seconds = np.empty(len(records))
    for i, record in enumerate(records):
        if not dates:
            day = record.rolls
        else:
            rolls, anchor = dates[max(record.date_index, 0)]
            day = anchor + record.rolls - rolls
        seconds[i] = float(day * _DAY_S + record.tod[0]) + record.tod[1]
    return seconds


def _forward(path: str, t: np.ndarray, lines: np.ndarray, field: str) -> np.ndarray:
    """(N,) bool: True where ``t`` is later than the time before it (False: a duplicate).

    Raises:
        DataError: a time before the previous one, naming its line and ``field``.
    """
    back = np.flatnonzero(t[1:] < t[:-1])
    if back.size:
        i = int(back[0]) + 1
        raise DataError(
            path,
            f"time goes back: {t[i]!r} s after {t[i - 1]!r} s (line {lines[i - 1]})",
            line=int(lines[i]),
            field=field,
        )
    return np.concatenate(([True], t[1:] > t[:-1]))[: t.shape[0]]


def _attach_sigmas(reader: _Reader) -> np.ndarray:
    """(N, 3) ENU sigmas from the GST of each fix's time of day (nearest line), NaN if none."""
    sigma = np.full((len(reader.fixes), 3), np.nan)
    used: set[int] = set()
    for i, fix in enumerate(reader.fixes):
        candidates = reader.gst_sigmas.get(round(1000 * (fix.tod[0] + fix.tod[1])))
        if candidates:
            line, values = min(candidates, key=lambda c: abs(c[0] - fix.line))
            sigma[i] = values
            used.add(line)
    total = sum(len(v) for v in reader.gst_sigmas.values())
    reader.counts["gst_unmatched"] = total - len(used)
    return sigma


def read_nmea(
    path: str | os.PathLike[str],
    *,
    qualities: Collection[int] = DEFAULT_QUALITIES,
    time: str = "auto",
) -> NmeaLog:
    """Read the GGA fixes of an NMEA 0183 log, with GST sigmas and RMC/ZDA dates.

    Args:
        path: the log file (text, one sentence per line, module docstring).
        qualities: the GGA quality codes kept (1-9; quality 0 is never a fix); default
            :data:`DEFAULT_QUALITIES`, e.g. ``(4,)`` for RTK-fixed fixes only.
        time: ``"auto"``, ``"utc"`` or ``"receive"`` (module docstring, Rules).

    Returns:
        an :class:`NmeaLog` of the kept fixes (N may be 0 when every GGA was skipped).

    Raises:
        DataError: no such file; a malformed sentence with a valid or absent checksum
            (naming line and field); no GGA sentence at all; ``time="receive"`` and a kept
            GGA without a receive timestamp; fixes going back in time.
        ValueError: bad ``qualities`` or ``time``.
    """
    if time not in TIME_SOURCES:
        raise ValueError(f"time must be one of {', '.join(TIME_SOURCES)}, got {time!r}")
    codes = list(qualities)
    if not codes or any(
        isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 9 for q in codes
    ):
        raise ValueError(f"qualities must be GGA quality codes 1-9, got {qualities!r}")
    spath = os.fspath(path)
    reader = _Reader(spath, frozenset(codes))
    for number, text in enumerate(_tables.split_lines(_read_text(spath)), start=1):
        reader.read_line(number, text)
    counts = reader.counts
    if counts.get("GGA", 0) == 0:
        found = ", ".join(f"{k} {v}" for k, v in counts.items() if v) or "nothing"
        raise DataError(spath, f"no GGA sentence in this file (found: {found})")
    fixes, velocities, headings = reader.fixes, reader.velocities, reader.headings
    stamps = [fix.stamp for fix in fixes]
    others = [r.stamp for r in (*velocities, *headings)]
    if time == "receive" or (time == "auto" and fixes and None not in stamps + others):
        for record in sorted((*fixes, *velocities, *headings), key=lambda r: r.line):
            if record.stamp is None:
                raise DataError(
                    spath,
                    "time='receive' needs a receive timestamp before every GGA sentence, "
                    "every RMC / VTG that gives a velocity and every HDT / THS that gives a "
                    "heading",
                    line=record.line,
                    field="receive_time",
                )
        source, time_field = "receive", "receive_time"
        t = np.array(stamps, dtype=np.float64)
        velocity_t = np.array([v.stamp for v in velocities], dtype=np.float64)
        heading_t = np.array([h.stamp for h in headings], dtype=np.float64)
    else:
        source, time_field = "utc", "utc_time"
        t = _utc_times(reader.dates, fixes)
        velocity_t = _utc_times(reader.dates, velocities)
        heading_t = _utc_times(reader.dates, headings)
        if (fixes or velocities or headings) and not reader.dates:
            warnings.warn(
                f"{spath}: no RMC or ZDA date; times are seconds since 00:00 UTC of the first day",
                stacklevel=2,
            )
    sigma = _attach_sigmas(reader)
    keep = _forward(spath, t, np.array([fix.line for fix in fixes]), time_field)
    counts["duplicate_time"] = int((~keep).sum())
    kept = [fix for fix, k in zip(fixes, keep, strict=True) if k]
    velocity_keep = _one_per_epoch(reader, "velocity", velocities, velocity_t, time_field)
    heading_keep = _one_per_epoch(reader, "heading", headings, heading_t, time_field)
    counts["kept"] = len(kept)
    separation_missing = any(fix.separation_missing for fix in kept)
    _warn_skipped(spath, counts, reader.bad_lines)
    if separation_missing:
        n_missing = sum(fix.separation_missing for fix in kept)
        warnings.warn(
            f"{spath}: {n_missing} of {len(kept)} fixes have no geoid separation; their "
            "height is the altitude above mean sea level, not the WGS-84 ellipsoid",
            stacklevel=2,
        )

    def column(name: str, dtype: type) -> np.ndarray:
        return np.array([getattr(fix, name) for fix in kept], dtype=dtype)

    return NmeaLog(
        t=t[keep],
        latitude_deg=column("latitude", np.float64),
        longitude_deg=column("longitude", np.float64),
        altitude_m=column("altitude", np.float64),
        quality=column("quality", np.int64),
        satellites=column("satellites", np.int64),
        hdop=column("hdop", np.float64),
        sigma_enu=sigma[keep].reshape(-1, 3),
        lines=column("line", np.int64),
        time_source=source,
        counts=counts,
        source=spath,
        geoid_separation_missing=separation_missing,
        dated=bool(reader.dates),
        velocity_t=velocity_t[velocity_keep],
        velocity_enu=np.array(
            [[velocities[i].east, velocities[i].north, math.nan] for i in velocity_keep],
            dtype=np.float64,
        ).reshape(-1, 3),
        velocity_lines=np.array([velocities[i].line for i in velocity_keep], dtype=np.int64),
        heading_t=heading_t[heading_keep],
        heading_rad=np.array([headings[i].heading for i in heading_keep], dtype=np.float64),
        heading_lines=np.array([headings[i].line for i in heading_keep], dtype=np.int64),
    )


def _one_per_epoch(
    reader: _Reader,
    name: str,
    records: Sequence[_Velocity] | Sequence[_Heading],
    t: np.ndarray,
    time_field: str,
) -> np.ndarray:
    """Indices into ``records`` (velocities or headings, ``name``) kept: the first of each
    UTC epoch (an RMC and a VTG of one epoch have two receive stamps; ``<name>_same_epoch``),
    then those later than the epoch before (``<name>_duplicate``); ``<name>_kept`` counted.

    Raises:
        DataError: a time before the previous epoch's, naming its line and ``time_field``.
    """
    utc = _utc_times(reader.dates, records)
    epoch = np.concatenate(([True], utc[1:] != utc[:-1]))[: utc.shape[0]]
    lines = np.array([r.line for r in records], dtype=np.int64)[epoch]
    keep = np.flatnonzero(epoch)[_forward(reader.path, t[epoch], lines, time_field)]
    reader.counts[f"{name}_same_epoch"] = len(records) - int(epoch.sum())
    reader.counts[f"{name}_duplicate"] = int(epoch.sum()) - int(keep.shape[0])
    reader.counts[f"{name}_kept"] = int(keep.shape[0])
    return keep


def _warn_skipped(path: str, counts: dict[str, int], bad_lines: list[int]) -> None:
    """One warning listing what was skipped (nothing when nothing was)."""
    parts = []
    for name in _OUTCOMES:
        if counts[name] and name not in _NOT_WARNED:
            parts.append(f"{name} {counts[name]}")
        if name == "bad_checksum" and bad_lines:
            more = ", ..." if len(bad_lines) > 5 else ""
            parts[-1] += f" (lines {', '.join(map(str, bad_lines[:5]))}{more})"
    others = [
        f"{name} {n}" for name, n in counts.items() if name not in (*_OUTCOMES, *_SENTENCES_READ)
    ]
    if others:
        parts.append("other sentences: " + ", ".join(others))
    if parts:
        warnings.warn(f"{path}: skipped " + "; ".join(parts), stacklevel=3)
