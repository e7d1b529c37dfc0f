"""Simulated three-axis magnetometer: the earth's field seen in the body, distorted by the
vehicle's iron, with local magnetic anomalies along the route.

Model (body frame, uT), at ``k / rate`` s:

    m = S (R^T (f_w + a_w(p))) + b + n,    n ~ N(0, sigma^2 I)

* ``f_w``: the local earth field in the world (ENU) from its magnitude ``F``, inclination
  ``I`` (dip below the horizon, positive down, as in the northern hemisphere) and
  declination ``D`` (magnetic north's azimuth clockwise from true north):
  ``f_w = F [cos I sin D, cos I cos D, -sin I]``.
* ``S``: soft-iron distortion (a 3 x 3 matrix; the correction ``W`` the filter wants,
  ``EskfConfig.magnetometer_soft_iron``, is ``S^-1``), ``b``: hard-iron offset.
* ``a_w(p)``: anomalies, each a fixed world vector of magnitude ``A_k`` (steel structures,
  rebar, parked cars, buried pipes) weighted by ``exp(-d^2 / (2 r_k^2))`` with ``d`` the
  horizontal distance from the vehicle to the anomaly's centre. Centres lie beside the route
  (``r_k / 2`` off the path at a random time), so every anomaly is driven through. The
  intervals where ``|a_w| > ANOMALY_LABEL_FRACTION * F`` are labelled
  ``"magnetic_anomaly"``.
"""

from __future__ import annotations

__all__ = ["ANOMALY_LABEL_FRACTION", "earth_field", "simulate_magnetometer"]

import math
from typing import Any

import numpy as np

ANOMALY_LABEL_FRACTION = 0.05
"""An anomaly is labelled where its field exceeds this fraction of the earth's."""


def earth_field(field_uT: float, inclination_rad: float, declination_rad: float) -> np.ndarray:
    """The earth's field in the world frame (ENU), (3,) uT.

    Args:
        field_uT: magnitude ``F``, uT (25-65 on the earth's surface).
        inclination_rad: dip below the horizon, rad (positive down).
        declination_rad: magnetic north's azimuth clockwise from true north, rad.
    """
    horizontal = field_uT * math.cos(inclination_rad)
    return np.array(
        [
            horizontal * math.sin(declination_rad),
            horizontal * math.cos(declination_rad),
            -field_uT * math.sin(inclination_rad),
        ]
    )


def simulate_magnetometer(
    config: Any, path: Any, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Magnetometer readings of one run (module docstring).

    Args:
        config: a ``SimConfig`` (its ``magnetometer_*`` fields and ``duration_s``).
        path: the run's ``GroundPath`` (``evaluate(t)`` -> position, rotation).
        rng: the magnetometer's own random stream (anomalies first, then the noise).

    Returns:
        times (M,) s, readings (M, 3) uT, anomaly label intervals (K, 2) s, and the
        ``meta["magnetometer"]`` record (the earth field, anomalies, distortion).
    """
    n = int(math.floor(config.duration_s * config.magnetometer_rate_hz + 1e-9)) + 1
    times = np.arange(n) / config.magnetometer_rate_hz
    state = path.evaluate(times)
    field_world = earth_field(
        config.magnetometer_field_uT,
        config.magnetometer_inclination_rad,
        config.magnetometer_declination_rad,
    )
    anomalies = []
    low, high = config.magnetometer_anomaly_uT
    radius_low, radius_high = config.magnetometer_anomaly_radius_m
    for _ in range(config.magnetometer_anomaly_count):
        when = rng.uniform(0.0, config.duration_s)
        radius = rng.uniform(radius_low, radius_high)
        side = rng.uniform(0.0, 2.0 * math.pi)
        centre = path.evaluate(np.array([when])).position[0, :2] + 0.5 * radius * np.array(
            [math.cos(side), math.sin(side)]
        )
        direction = rng.normal(size=3)
        vector = rng.uniform(low, high) * direction / np.linalg.norm(direction)
        anomalies.append((centre, radius, vector))
    anomaly = np.zeros((n, 3))
    for centre, radius, vector in anomalies:
        distance2 = ((state.position[:, :2] - centre) ** 2).sum(-1)
        anomaly += np.exp(-0.5 * distance2 / radius**2)[:, None] * vector
    body = np.einsum("nji,nj->ni", state.rotation, field_world + anomaly)
    distortion = np.reshape(np.asarray(config.magnetometer_distortion, np.float64), (3, 3))
    hard_iron = np.asarray(config.magnetometer_hard_iron_uT, np.float64)
    readings = body @ distortion.T + hard_iron
    readings += rng.normal(0.0, config.magnetometer_sigma_uT, (n, 3))
    labelled = np.linalg.norm(anomaly, axis=-1) > ANOMALY_LABEL_FRACTION * (
        config.magnetometer_field_uT
    )
    edges = np.flatnonzero(np.diff(np.concatenate(([0], labelled.astype(np.int8), [0]))))
    intervals = np.stack((times[edges[0::2]], times[edges[1::2] - 1]), -1)
    meta = {
        "earth_field_world_uT": [float(x) for x in field_world],
        "anomalies": [
            {
                "centre_m": [float(x) for x in centre],
                "radius_m": float(radius),
                "field_world_uT": [float(x) for x in vector],
            }
            for centre, radius, vector in anomalies
        ],
        "soft_iron_correction": [float(x) for x in np.linalg.inv(distortion).reshape(-1)],
    }
    return times, readings, intervals.reshape(-1, 2), meta
