"""u-blox UBX binary logs: the receiver's navigation solution (UBX-NAV-PVT) as GNSS fixes and
velocities, with the receiver's own accuracy estimates.

A u-blox receiver (M8, F9, X20; ``ubxtool`` / u-center / ``str2str`` recordings, a ROS
driver's raw dump) writes UBX frames: sync ``0xB5 0x62``, class, id, a little-endian
16-bit payload length, the payload and a two-byte Fletcher checksum over class..payload.
Only NAV-PVT (class 0x01, id 0x07; 92 bytes, or 84 from protocol versions before 15) is
read; every other frame, and NMEA or RTCM text between frames, is counted and skipped.

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

Rules: a frame whose checksum fails is skipped (``bad_checksum``) and the scan resumes at
the next sync pair; a frame cut off by the end of the file is counted (``truncated``); a
NAV-PVT of the wrong length is a DataError naming its byte offset (``field``: the length);
repeated or backwards times keep the first (``duplicate_time``). One warning lists what was
skipped. Times must be increasing after that.

Example:
    >>> from msf_torch.io.ubx import read_ubx  # doctest: +SKIP
    >>> log = read_ubx("drive.ubx")  # doctest: +SKIP
    >>> gnss, origin = log.to_gnss()  # doctest: +SKIP
"""

from __future__ import annotations

__all__ = ["NAV_PVT", "UbxLog", "read_ubx"]

import calendar
import struct
import warnings
from collections import Counter
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msf_torch.io.errors import DataError
from msf_torch.io.nmea import geodetic_fixes, velocity_stream
from msf_torch.types import GnssFixes, GnssVelocity

NAV_PVT = (0x01, 0x07)
"""UBX class and id of the navigation position-velocity-time solution."""

_SYNC = b"\xb5\x62"
_PVT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIH")  # the first 78 bytes (all versions)
_PVT_LENGTHS = (84, 92)
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
)


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
            ``fix_type_not_kept``, ``time_invalid``, ``out_of_range``, ``duplicate_time``)
            and per message
            read, ``"CLASS-ID"`` in hex (``"01-07"`` for NAV-PVT), plus ``not_ubx_bytes``.
        source: the path read.
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
    for offset, cls, ident, payload in frames:
        if (cls, ident) != NAV_PVT:
            continue
        if len(payload) not in _PVT_LENGTHS:
            raise DataError(
                spath,
                f"NAV-PVT at byte {offset} has a {len(payload)}-byte payload, expected 84 or 92",
                field="length",
            )
        (
            _itow, year, month, day, hour, minute, second, valid, _tacc, nano, fix_type,
            flags, _flags2, satellites, lon, lat, height, _hmsl, h_acc, v_acc, vel_n, vel_e,
            vel_d, _gspeed, _head, s_acc, _head_acc, _pdop,
        ) = _PVT.unpack_from(payload)  # fmt: skip
        if not flags & 0x01 or fix_type == 0:
            counts["no_fix"] += 1
            continue
        if fix_type not in fix_types:
            counts["fix_type_not_kept"] += 1
            continue
        if (valid & 0x03) != 0x03 or not (1 <= month <= 12 and 1 <= day <= 31):
            counts["time_invalid"] += 1
            continue
        if abs(lat) > 900_000_000 or abs(lon) > 1_800_000_000:
            counts["out_of_range"] += 1
            continue
        whole = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
        rows.append(
            (
                whole + nano * 1e-9,
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
    skipped = [f"{name} {counts[name]}" for name in _OUTCOMES[1:] if counts[name]]
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
    )
