"""u-blox UBX binary logs: the receiver's navigation solution (UBX-NAV-PVT) as GNSS fixes and
velocities, and a moving-baseline receiver's heading (UBX-NAV-RELPOSNED), with the
receiver's own accuracy estimates.

A u-blox receiver (M8, F9, X20; ``ubxtool`` / u-center / ``str2str`` recordings, a ROS
driver's raw dump) writes UBX frames: sync ``0xB5 0x62``, class, id, a little-endian
16-bit payload length, the payload and a two-byte Fletcher checksum over class..payload.
NAV-PVT (class 0x01, id 0x07; 92 bytes, or 84 from protocol versions before 15) and
NAV-RELPOSNED (class 0x01, id 0x3C; version 0x01, 64 bytes: F9P; version 0x00, 40 bytes:
M8P) are read; every other frame, and NMEA or RTCM text between frames, is counted and
skipped.

From each NAV-PVT:

* time: the UTC date and time fields plus ``nano``, as UNIX seconds, when the frame says
  both are valid (``valid`` bits 0 and 1; else skipped, ``time_invalid``);
* fix: ``lat``, ``lon`` (1e-7 deg) and ``height`` (mm above the WGS-84 ellipsoid) when
  ``gnssFixOK`` is set and ``fixType`` is one kept (default 3: 3-D, 4: GNSS + dead
  reckoning; 2-D fixes have no height); sigmas ``hAcc`` (east and north) and ``vAcc``
  (up), mm. u-blox calls them accuracy estimates without naming the statistic; they are
  used as standard deviations;
* velocity: ``velN``, ``velE``, ``velD`` (mm/s) as east, north, up, each with sigma
  ``sAcc`` (the speed accuracy), at the same time;
* also kept: ``fixType``, ``numSV``, the carrier solution (``flags`` bits 6-7: 0 none,
  1 RTK float, 2 RTK fixed).

A latitude beyond 90 deg or a longitude beyond 180 deg in a frame whose checksum holds is
skipped (``out_of_range``).

From each NAV-RELPOSNED (the rover's vector from its reference antenna to its own; with a
moving base on the vehicle, the dual-antenna baseline from the primary (base) to the
secondary (rover) antenna, :class:`~msf_torch.types.GnssHeading`):

* heading: ``relPosHeading`` (1e-5 deg clockwise from true north, turned into rad in
  [0, 2 pi)) with sigma ``accHeading`` (1e-5 deg, as rad; 0, an accuracy not computed, is
  NaN: the estimator's configured ``gnss_heading_sigma_rad`` applies), when ``flags`` has
  ``gnssFixOK`` (bit 0), ``relPosValid`` (bit 2) and ``relPosHeadingValid`` (bit 8); else
  skipped (``heading_invalid``);
* only in moving-base mode (``isMoving``, bit 5): a rover of a fixed base station reports
  the azimuth from the station to itself, which is not the vehicle's heading
  (``heading_fixed_base``);
* version 0x00 (M8P) has no ``relPosHeading``: counted in ``heading_no_field`` and skipped;
* time: the frame carries only ``iTOW`` (ms of the GPS week); it gets the UTC time of the
  NAV-PVT of the same ``iTOW`` (the same navigation epoch; the nearest such frame in the
  file) whose time is valid, whether or not that fix is kept. Without one it is skipped
  (``heading_untimed``); repeated or backwards times keep the first
  (``heading_duplicate``).

Rules: a frame whose checksum fails is skipped (``bad_checksum``) and the scan resumes at
the next sync pair; a frame cut off by the end of the file is counted (``truncated``); a
NAV-PVT of the wrong length is a DataError naming its byte offset (``field``: the length);
repeated or backwards times keep the first (``duplicate_time``). One warning lists what was
skipped. Times must be increasing after that. A NAV-RELPOSNED whose version and length are
not 0x00 / 40 or 0x01 / 64 is a DataError naming its byte offset.

Example:
    >>> from msf_torch.io.ubx import read_ubx  # doctest: +SKIP
    >>> log = read_ubx("drive.ubx")  # doctest: +SKIP
    >>> gnss, origin = log.to_gnss()  # doctest: +SKIP
    >>> heading = log.to_gnss_heading()  # doctest: +SKIP
"""

from __future__ import annotations

__all__ = ["NAV_PVT", "NAV_RELPOSNED", "UbxLog", "read_ubx"]

import calendar
import math
import struct
import warnings
from collections import Counter
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msf_torch.io.errors import DataError
from msf_torch.io.nmea import geodetic_fixes, heading_stream, velocity_stream
from msf_torch.types import GnssFixes, GnssHeading, GnssVelocity

NAV_PVT = (0x01, 0x07)
"""UBX class and id of the navigation position-velocity-time solution."""
NAV_RELPOSNED = (0x01, 0x3C)
"""UBX class and id of the relative position (RTK baseline) solution."""

_SYNC = b"\xb5\x62"
_PVT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIH")  # the first 78 bytes (all versions)
_PVT_LENGTHS = (84, 92)
# version 0x01: version, reserved, refStationId, iTOW, relPosN/E/D, relPosLength,
# relPosHeading, 4 reserved, relPosHPN/E/D/Length, accN/E/D, accLength, accHeading,
# 4 reserved, flags
_RELPOSNED = struct.Struct("<BBHIiiiii4xbbbbIIIII4xI")
_RELPOSNED_LENGTHS = {0: 40, 1: 64}  # version -> payload bytes
_GNSS_FIX_OK, _REL_POS_VALID, _IS_MOVING, _HEADING_VALID = 1 << 0, 1 << 2, 1 << 5, 1 << 8
_HEADING_NEEDS = _GNSS_FIX_OK | _REL_POS_VALID | _HEADING_VALID
_DEG = math.pi / 180.0
DEFAULT_FIX_TYPES = (3, 4)
_OUTCOMES = (
    "kept",
    "bad_checksum",
    "truncated",
    "no_fix",
    "fix_type_not_kept",
    "time_invalid",
    "out_of_range",
    "duplicate_time",
    "heading_kept",
    "heading_invalid",
    "heading_fixed_base",
    "heading_no_field",
    "heading_untimed",
    "heading_duplicate",
)
_REASONS = {"heading_no_field": " (NAV-RELPOSNED version 0, M8P, has no relPosHeading)"}


@dataclass
class UbxLog:
    """The kept NAV-PVT solutions of a UBX log, in file order (module docstring).

    Attributes:
        t: (N,) UNIX seconds (UTC).
        latitude_deg, longitude_deg: (N,) WGS-84 degrees; height_m: (N,) above the
            ellipsoid, m.
        sigma_enu: (N, 3) m, ``[hAcc, hAcc, vAcc]``.
        velocity_enu: (N, 3) m/s, ``[velE, velN, -velD]``; velocity_sigma: (N, 3) m/s, ``sAcc``.
        fix_type, satellites, carrier: (N,) int64 ``fixType``, ``numSV``, carrier solution.
        offsets: (N,) int64 byte offset of each kept frame.
        counts: the outcomes (``kept``, ``bad_checksum``, ``truncated``, ``no_fix``,
            ``fix_type_not_kept``, ``time_invalid``, ``out_of_range``, ``duplicate_time``;
            for NAV-RELPOSNED ``heading_kept``, ``heading_invalid``, ``heading_fixed_base``,
            ``heading_no_field``, ``heading_untimed``, ``heading_duplicate``) and per
            message read, ``"CLASS-ID"`` in hex (``"01-07"`` for NAV-PVT, ``"01-3C"`` for
            NAV-RELPOSNED), plus ``not_ubx_bytes``.
        source: the path read.
        heading_t: (M,) UNIX seconds (UTC) of the kept NAV-RELPOSNED headings.
        heading_rad: (M,) ``relPosHeading``, rad clockwise from true north in [0, 2 pi).
        heading_sigma_rad: (M,) ``accHeading``, rad; NaN where the receiver gave 0.
        heading_offsets: (M,) int64 byte offset of each kept NAV-RELPOSNED.
    """

    t: np.ndarray
    latitude_deg: np.ndarray
    longitude_deg: np.ndarray
    height_m: np.ndarray
    sigma_enu: np.ndarray
    velocity_enu: np.ndarray
    velocity_sigma: np.ndarray
    fix_type: np.ndarray
    satellites: np.ndarray
    carrier: np.ndarray
    offsets: np.ndarray
    counts: dict[str, int]
    source: str
    heading_t: np.ndarray
    heading_rad: np.ndarray
    heading_sigma_rad: np.ndarray
    heading_offsets: np.ndarray

    def __len__(self) -> int:
        """Number of kept solutions N."""
        return int(self.t.shape[0])

    def to_gnss(
        self, origin: Sequence[float] | None = None, t0: float = 0.0
    ) -> tuple[GnssFixes, tuple[float, float, float]]:
        """The fixes as a B = 1 GNSS stream in local ENU metres about ``origin`` (``(lat_deg,
        lon_deg, h_m)``; None: the first fix), times minus ``t0`` (s); and the origin used.

        Raises:
            ValueError: no origin given and no fix kept.
        """
        return geodetic_fixes(
            self.t - float(t0),
            self.latitude_deg,
            self.longitude_deg,
            self.height_m,
            self.sigma_enu,
            origin,
            self.source,
        )

    def to_gnss_velocity(self, t0: float = 0.0) -> GnssVelocity:
        """The velocities as a B = 1 stream (ENU m/s, sigmas ``sAcc``), times minus ``t0``."""
        return velocity_stream(self.t - float(t0), self.velocity_enu, self.velocity_sigma)

    def to_gnss_heading(self, t0: float = 0.0) -> GnssHeading:
        """The headings as a B = 1 stream: ``t`` (1, M) s (:attr:`heading_t` minus ``t0``),
        ``heading`` (1, M) rad, ``sigma`` (1, M) rad (NaN: not given); M may be 0."""
        return heading_stream(self.heading_t - float(t0), self.heading_rad, self.heading_sigma_rad)


def _checksum(frame: bytes) -> bytes:
    """The 8-bit Fletcher checksum (CK_A, CK_B) of class..payload."""
    a = b = 0
    for byte in frame:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    return bytes((a, b))


def _frames(data: bytes, counts: Counter) -> list[tuple[int, int, int, bytes]]:
    """The checksum-valid frames ``(offset, class, id, payload)`` of ``data``."""
    out = []
    at = 0
    skipped = 0
    size = len(data)
    while True:
        start = data.find(_SYNC, at)
        if start < 0:
            skipped += size - at
            break
        skipped += start - at
        if start + 6 > size:
            counts["truncated"] += 1
            break
        length = int.from_bytes(data[start + 4 : start + 6], "little")
        end = start + 6 + length + 2
        if end > size:
            counts["truncated"] += 1
            break
        body = data[start + 2 : start + 6 + length]
        if _checksum(body) != data[end - 2 : end]:
            counts["bad_checksum"] += 1
            at = start + 1
            continue
        out.append((start, body[0], body[1], body[4:]))
        counts[f"{body[0]:02X}-{body[1]:02X}"] += 1
        at = end
    counts["not_ubx_bytes"] += skipped
    return out


def read_ubx(path: str | Path, fix_types: Collection[int] = DEFAULT_FIX_TYPES) -> UbxLog:
    """Read the NAV-PVT solutions of a u-blox UBX log (module docstring for the rules).

    Args:
        path: the binary log.
        fix_types: ``fixType`` values kept (default 3-D and GNSS + dead reckoning).

    Returns:
        :class:`UbxLog`.

    Raises:
        DataError: no such file; no UBX frame at all (e.g. an NMEA log); a NAV-PVT of the
            wrong length (naming its byte offset).
    """
    spath = str(path)
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise DataError(spath, f"cannot read ({type(err).__name__}: {err})") from None
    counts: Counter = Counter({name: 0 for name in _OUTCOMES})
    frames = _frames(data, counts)
    if not frames:
        found = "an empty file" if not data else f"{len(data)} bytes"
        raise DataError(
            spath,
            f"not a UBX log: no frame with a valid checksum in {found} "
            f"(bad checksums {counts['bad_checksum']}, cut off {counts['truncated']})",
        )
    rows = []
    epochs: dict[int, list[tuple[int, float]]] = {}  # iTOW -> [(offset, UNIX s)] of NAV-PVTs
    headings: list[tuple[int, int, float, float]] = []  # (offset, iTOW, rad, sigma rad)
    for offset, cls, ident, payload in frames:
        if (cls, ident) == NAV_RELPOSNED:
            heading = _relposned(spath, offset, payload, counts)
            if heading is not None:
                headings.append((offset, *heading))
            continue
        if (cls, ident) != NAV_PVT:
            continue
        if len(payload) not in _PVT_LENGTHS:
            raise DataError(
                spath,
                f"NAV-PVT at byte {offset} has a {len(payload)}-byte payload, expected 84 or 92",
                field="length",
            )
        (
            itow, year, month, day, hour, minute, second, valid, _tacc, nano, fix_type,
            flags, _flags2, satellites, lon, lat, height, _hmsl, h_acc, v_acc, vel_n, vel_e,
            vel_d, _gspeed, _head, s_acc, _head_acc, _pdop,
        ) = _PVT.unpack_from(payload)  # fmt: skip
        stamp = None
        if (valid & 0x03) == 0x03 and 1 <= month <= 12 and 1 <= day <= 31:
            whole = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
            stamp = whole + nano * 1e-9
            epochs.setdefault(itow, []).append((offset, stamp))
        if not flags & 0x01 or fix_type == 0:
            counts["no_fix"] += 1
            continue
        if fix_type not in fix_types:
            counts["fix_type_not_kept"] += 1
            continue
        if stamp is None:
            counts["time_invalid"] += 1
            continue
        if abs(lat) > 900_000_000 or abs(lon) > 1_800_000_000:
            counts["out_of_range"] += 1
            continue
        rows.append(
            (
                stamp,
                lat * 1e-7,
                lon * 1e-7,
                height * 1e-3,
                h_acc * 1e-3,
                v_acc * 1e-3,
                vel_e * 1e-3,
                vel_n * 1e-3,
                -vel_d * 1e-3,
                s_acc * 1e-3,
                fix_type,
                satellites,
                (flags >> 6) & 0x03,
                offset,
            )
        )
    table = np.array(rows, dtype=np.float64).reshape(-1, 14)
    keep = np.ones(table.shape[0], dtype=bool)
    if table.shape[0]:  # the first of repeated times; nothing stamped before a kept one
        latest = np.maximum.accumulate(table[:, 0])
        keep[1:] = table[1:, 0] > latest[:-1]
    counts["duplicate_time"] = int((~keep).sum())
    table = table[keep]
    counts["kept"] = int(table.shape[0])
    heading_table = _timed_headings(headings, epochs, counts)
    skipped = [
        f"{name} {counts[name]}{_REASONS.get(name, '')}"
        for name in _OUTCOMES[1:]
        if counts[name] and name != "heading_kept"
    ]
    if skipped:
        warnings.warn(f"{spath}: skipped " + "; ".join(skipped), stacklevel=2)
    integers = table[:, 10:14].astype(np.int64)
    return UbxLog(
        t=table[:, 0],
        latitude_deg=table[:, 1],
        longitude_deg=table[:, 2],
        height_m=table[:, 3],
        sigma_enu=np.stack((table[:, 4], table[:, 4], table[:, 5]), -1),
        velocity_enu=table[:, 6:9],
        velocity_sigma=np.repeat(table[:, 9:10], 3, axis=1),
        fix_type=integers[:, 0],
        satellites=integers[:, 1],
        carrier=integers[:, 2],
        offsets=integers[:, 3],
        counts=dict(counts),
        source=spath,
        heading_t=heading_table[:, 0],
        heading_rad=heading_table[:, 1],
        heading_sigma_rad=heading_table[:, 2],
        heading_offsets=heading_table[:, 3].astype(np.int64),
    )


def _relposned(
    path: str, offset: int, payload: bytes, counts: Counter
) -> tuple[int, float, float] | None:
    """``(iTOW, heading rad in [0, 2 pi), sigma rad or NaN)`` of one NAV-RELPOSNED, or None
    (counted) when it gives no heading (module docstring).

    Raises:
        DataError: a version / length pair other than 0x00 / 40 and 0x01 / 64.
    """
    version = payload[0] if payload else None
    if _RELPOSNED_LENGTHS.get(version) != len(payload):
        raise DataError(
            path,
            f"NAV-RELPOSNED at byte {offset} has version {version} and a {len(payload)}-byte "
            "payload, expected version 0 with 40 bytes or version 1 with 64",
            field="length",
        )
    if version == 0:
        counts["heading_no_field"] += 1
        return None
    fields = _RELPOSNED.unpack(payload)
    itow, heading, acc_heading, flags = fields[3], fields[8], fields[17], fields[18]
    if flags & _HEADING_NEEDS != _HEADING_NEEDS:
        counts["heading_invalid"] += 1
        return None
    if not flags & _IS_MOVING:
        counts["heading_fixed_base"] += 1
        return None
    sigma = acc_heading * 1e-5 * _DEG if acc_heading > 0 else math.nan
    return itow, (heading * 1e-5 * _DEG) % (2.0 * math.pi), sigma


def _timed_headings(
    headings: list[tuple[int, int, float, float]],
    epochs: dict[int, list[tuple[int, float]]],
    counts: Counter,
) -> np.ndarray:
    """(M, 4) ``[UNIX s, heading rad, sigma rad, byte offset]`` of the headings that get the
    time of a NAV-PVT of their ``iTOW`` (the nearest in the file), first of repeated or
    backwards times; the rest counted (``heading_untimed``, ``heading_duplicate``)."""
    rows = []
    for offset, itow, heading, sigma in headings:
        candidates = epochs.get(itow)
        if not candidates:
            counts["heading_untimed"] += 1
            continue
        _, stamp = min(candidates, key=lambda c: abs(c[0] - offset))
        rows.append((stamp, heading, sigma, offset))
    table = np.array(rows, dtype=np.float64).reshape(-1, 4)
    keep = np.ones(table.shape[0], dtype=bool)
    if table.shape[0]:
        latest = np.maximum.accumulate(table[:, 0])
        keep[1:] = table[1:, 0] > latest[:-1]
    counts["heading_duplicate"] = int((~keep).sum())
    counts["heading_kept"] = int(keep.sum())
    return table[keep]
