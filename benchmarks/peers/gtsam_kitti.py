"""GTSAM peer pipeline for the KITTI IMU+GPS drive shipped with the ``gtsam`` wheel.

This is a port of GTSAM's own ``gtsam/examples/IMUKittiExampleGPS.py`` (and the C++
``IMUKittiExampleGPS.cpp``) into a function that takes plain numpy arrays, so a benchmark
can feed it exactly the inputs it feeds our estimator.

Pipeline (as in the example):

* one state ``X(i)`` (Pose3), ``V(i)`` (velocity), ``B(i)`` (IMU bias) per GPS time,
  starting at ``first_gps_index`` (the example uses 1: fix 0 coincides with the first IMU
  row, whose ``dt`` is meaningless, and is followed by a 1.9 s IMU gap);
* IMU samples with ``t_prev <= t_imu <= t`` are preintegrated between consecutive GPS
  times, each with ``dt = t_imu[j] - t_imu[j-1]`` (identical to the file's ``dt`` column);
* initial state: position at the first used GPS fix, identity rotation with **zero**
  precision on rotation and unit precision on translation, zero velocity with sigma
  1000 m/s, zero bias with sigmas 0.1 (accel) / 5e-5 (gyro).  The example does not derive
  a heading from GPS: the rotation prior is uninformative and heading becomes observable
  from the GPS track during a warm-up before the first ISAM2 update;
* warm-up: the example makes its first ISAM2 update once ``i > first + 2 * gps_skip``,
  i.e. after 20 GPS intervals with its ``gps_skip = 10``; here the warm-up is
  ``warmup_intervals = 20`` GPS intervals regardless of ``gps_skip`` (same first-update
  time as the example);
* preintegration with ``MakeSharedU(9.8)``, accelerometer / gyroscope / integration
  covariances ``sigma**2 * I`` from the metadata, zero Coriolis, ``body_P_sensor`` from
  the metadata (``Rot3.RzRyRx(rx, ry, rz)``, translation ``(tx, ty, tz)``);
* GPS noise as in the example: information ``1 / 0.07`` per position axis, i.e. sigma
  ``sqrt(0.07) ~= 0.265 m``;
* ISAM2 with ``relinearizeSkip = 10`` (default threshold); one ``update`` per GPS time
  after the warm-up.

Deviations from the example (deliberate):

1. ``CombinedImuFactor`` (``PreintegrationCombinedParams``) instead of ``ImuFactor`` +
   ``BetweenFactorConstantBias``.  The bias random walk is the continuous-time one,
   ``biasAccCovariance = accel_bias_rw_sigma**2 * I`` and
   ``biasOmegaCovariance = gyro_bias_rw_sigma**2 * I`` (per second).  The example instead
   uses a between-factor with sigma ``sqrt(n) * bias_sigma`` where ``n`` is the *cumulative*
   number of IMU samples integrated so far (its counter is never reset), so its bias
   factor loosens over the run.
2. ISAM2 factorization defaults to ``"QR"`` instead of ``"CHOLESKY"``.  With gtsam 4.3.0
   the unmodified example aborts with ``IndeterminantLinearSystemException`` (near
   ``x21``, its first update) under CHOLESKY, and so does this pipeline; the cause is
   conditioning (it goes away if the gyro-bias random walk is loosened to ~1e-3), not
   rank.  With QR the unmodified example runs (smoothed RMSE vs GPS ~0.77 m).
3. GPS enters as a 3-D ``GPSFactor`` with the same position information instead of a
   ``PriorFactorPose3`` whose rotation part has zero precision; equivalent information.
4. GPS is used at every GPS time (``gps_skip=1``; the example uses 10), except fixes
   whose time lies inside ``outage = (t0, t1)`` (inclusive).  States inside the outage
   are still created and linked by IMU factors.  As in the example a fix is used only
   when ``i % gps_skip == 0``.  The first state has no GPS factor, only the position
   prior centred on its fix (as in the example).
5. Initial values of new states come from the IMU prediction
   (``PreintegratedCombinedMeasurements.predict``) from the latest estimate of the
   previous state, with the position replaced by the GPS fix where one is used.  The
   example uses the previous state's estimate (pose with the GPS position substituted).
   This matters during outages, where the previous pose is a poor linearization point.
6. Only the newest state is extracted after each update
   (``calculateEstimatePose3/Vector/ConstantBias``) instead of the full
   ``calculateEstimate``, which keeps the per-step cost independent of trajectory length.
7. The example refuses a non-identity ``body_P_sensor``; here it is passed to the
   preintegration parameters (it is identity for this dataset anyway).
8. Optional, off by default: ``init_from_gps=True`` sets the initial *value* (not the
   prior, which keeps zero rotation precision) to the yaw of the first GPS displacement
   and the velocity to that displacement over its duration (with ``gps_velocity``: the
   course and the velocity of the first state's measured velocity when it has one).
9. Optional inputs for other data (the defaults are the example's and leave the KITTI
   results unchanged): ``gravity``, ``gps_sigma`` (per-axis sigmas instead of the
   example's precision), ``init_bias_sigmas``, and ``gps_velocity``: a world-frame
   velocity measurement at each GPS time, entered as ``PriorFactorVector(V(i), v, sigma)``
   at every state whose fix is used (the first one included). That is the antenna's
   velocity only with a zero lever arm (no ``R (w x l)`` term here), which the caller
   must ensure. A fix (or velocity) with a non-finite entry is not used.
10. Optional, off by default: ``gps_heading``, a dual-antenna (moving-baseline) GNSS
    heading at each GPS time: the azimuth, clockwise from north, of the antenna baseline
    ``heading_baseline`` (body frame; default body x), as ``msf_torch.sensors.gnss``
    models it. Each state whose time has a finite heading (and sigma) and lies outside
    ``outage`` gets one ``gtsam.CustomFactor`` on ``X(i)`` (:func:`heading_factor`;
    Gaussian, no robust kernel, like the GPS factors; independent of ``gps_skip``). With
    ``init_from_gps`` and a heading at the first state, the initial rotation *value* is
    the level rotation whose baseline has that azimuth (it replaces the course of the
    first velocity or displacement; the initial velocity value is still theirs; the
    rotation prior keeps zero precision).
11. Optional, off by default: ``mag_field``, magnetometer readings at the GPS times,
    already corrected for hard and soft iron (``W (m - b)``, body frame, uT), as GTSAM
    users add a magnetometer: one ``gtsam.MagPoseFactorPose3`` on ``X(i)`` per state with
    a finite reading, GTSAM's 3-D model ``R^T (scale * direction) + bias`` with the known
    local field ``mag_world`` (ENU, uT: ``scale = |mag_world|``, ``direction`` its unit
    vector) and ``bias = 0`` (the readings are corrected), isotropic ``mag_sigma`` uT per
    axis, wrapped in ``gtsam.noiseModel.Robust`` when ``mag_robust`` (an
    ``mEstimator``) is given. Used inside the outage too (the magnetometer does not stop
    with the GNSS). With ``init_from_gps``, no heading and a reading at the first state,
    the initial rotation *value* is the level rotation whose reading points at the
    field's azimuth (the declination); the rotation prior keeps zero precision. The
    initial velocity value (item 8) is the displacement to the next finite fix, so GPS
    times without a fix (states between fixes) may follow the first one.

States created during the warm-up have no causal "filter" estimate: they get the value
from the first update (a small batch that already sees up to ``warmup_intervals`` fixes
into their future) and are flagged ``causal=False`` in the result.
"""

from __future__ import annotations

import math
import time
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

GRAVITY = 9.8
"""Gravity magnitude used by the example (m/s^2)."""

GPS_PRECISION = 1.0 / 0.07
"""Per-axis GPS position information used by the example (1/m^2)."""

INIT_POSITION_PRECISION = 1.0
"""Per-axis information of the initial position prior (rotation part has zero)."""

INIT_VELOCITY_SIGMA = 1000.0
"""Sigma of the initial velocity prior (m/s)."""

INIT_BIAS_SIGMAS = (0.1, 5.0e-5)
"""Sigmas of the initial accelerometer / gyroscope bias prior."""


def make_imu_params(
    meta: dict[str, Any], gravity: float = GRAVITY
) -> gtsam.PreintegrationCombinedParams:
    """Build the combined preintegration parameters from the metadata dict; ``gravity``
    magnitude in m/s^2 (navigation frame z up)."""
    eye = np.eye(3)
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity)
    params.setAccelerometerCovariance(eye * float(meta["accel_noise_sigma"]) ** 2)
    params.setGyroscopeCovariance(eye * float(meta["gyro_noise_sigma"]) ** 2)
    params.setIntegrationCovariance(eye * float(meta["integration_sigma"]) ** 2)
    params.setBiasAccCovariance(eye * float(meta["accel_bias_rw_sigma"]) ** 2)
    params.setBiasOmegaCovariance(eye * float(meta["gyro_bias_rw_sigma"]) ** 2)
    params.setOmegaCoriolis(np.zeros(3))
    tx, ty, tz, rx, ry, rz = (float(v) for v in meta["body_p_sensor"])
    params.setBodyPSensor(gtsam.Pose3(gtsam.Rot3.RzRyRx(rx, ry, rz), np.array([tx, ty, tz])))
    return params


def heading_error(
    rotation: np.ndarray, baseline: np.ndarray, heading: float
) -> tuple[float, np.ndarray]:
    """Heading residual and its Jacobian on Pose3's tangent space.

    ``u = R b`` (ENU); ``r = wrap(atan2(u_e, u_n) - heading)`` in (-pi, pi]. Pose3's
    tangent is ``[w, v]`` (rotation first) with ``R <- R Exp(w)``, so ``du = -R [b]x w``
    and ``dr/dw = [u_n, -u_e, 0] / (u_e^2 + u_n^2) (-R [b]x)``; ``dr/dv = 0``. Undefined
    where ``u`` points straight up or down (no azimuth).

    Args:
        rotation: (3, 3) body -> world (ENU).
        baseline: (3,) primary -> secondary antenna, body frame, m (direction only).
        heading: measured azimuth clockwise from north, rad.

    Returns:
        (residual rad, Jacobian (1, 6) rad per unit tangent).
    """
    east, north, _ = rotation @ baseline
    residual = math.pi - (math.pi - (math.atan2(east, north) - heading)) % (2.0 * math.pi)
    d_azimuth = np.array([north, -east, 0.0]) / (east**2 + north**2)
    bx, by, bz = baseline
    hat = np.array([[0.0, -bz, by], [bz, 0.0, -bx], [-by, bx, 0.0]])
    jac = np.zeros((1, 6))
    jac[0, :3] = -(d_azimuth @ rotation @ hat)
    return residual, jac


def heading_factor(
    key: int, heading: float, sigma: float, baseline: np.ndarray
) -> gtsam.CustomFactor:
    """A dual-antenna GNSS heading factor on the Pose3 at ``key`` (:func:`heading_error`)
    with a 1-D Gaussian noise of ``sigma`` rad."""

    def error(
        this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None
    ) -> np.ndarray:
        rotation = values.atPose3(this.keys()[0]).rotation().matrix()
        residual, jac = heading_error(rotation, baseline, heading)
        if jacobians is not None:
            jacobians[0] = jac
        return np.array([residual])

    noise = gtsam.noiseModel.Isotropic.Sigma(1, float(sigma))
    return gtsam.CustomFactor(noise, [key], error)


def level_yaw_for_heading(heading: float, baseline: np.ndarray) -> float:
    """Yaw (rad, counter-clockwise from east about up) of the level rotation whose
    baseline (3,) body frame has the azimuth ``heading`` (rad clockwise from north)."""
    return math.pi / 2.0 - heading - math.atan2(baseline[1], baseline[0])


def run_gtsam_kitti(
    imu_t: np.ndarray,
    imu_acc: np.ndarray,
    imu_gyro: np.ndarray,
    gps_t: np.ndarray,
    gps_xyz: np.ndarray,
    meta: dict[str, Any],
    outage: tuple[float, float] | None = None,
    first_gps_index: int = 1,
    gps_skip: int = 1,
    warmup_intervals: int = 20,
    init_from_gps: bool = False,
    factorization: str = "QR",
    gravity: float = GRAVITY,
    gps_sigma: np.ndarray | None = None,
    init_bias_sigmas: tuple[float, float] = INIT_BIAS_SIGMAS,
    gps_velocity: np.ndarray | None = None,
    gps_velocity_sigma: np.ndarray | None = None,
    gps_heading: np.ndarray | None = None,
    gps_heading_sigma: float | np.ndarray | None = None,
    heading_baseline: np.ndarray | None = None,
    mag_field: np.ndarray | None = None,
    mag_world: np.ndarray | None = None,
    mag_sigma: float | None = None,
    mag_robust: Any = None,
) -> dict[str, Any]:
    """Run the GTSAM CombinedImuFactor + GPSFactor ISAM2 pipeline.

    Args:
        imu_t: IMU timestamps (N,), seconds, same clock as ``gps_t``.
        imu_acc: specific force (N, 3), m/s^2.
        imu_gyro: angular rate (N, 3), rad/s.
        gps_t: GPS timestamps (M,).
        gps_xyz: GPS positions (M, 3) in the navigation frame, m.
        meta: noise/calibration dict: ``accel_noise_sigma``, ``gyro_noise_sigma``,
            ``integration_sigma``, ``accel_bias_rw_sigma``, ``gyro_bias_rw_sigma`` and
            ``body_p_sensor`` (``[tx, ty, tz, rx, ry, rz]``), optionally ``average_delta_t``
            (s, the first sample's dt), as ``benchmarks._common.peer_arrays`` takes it from
            the data files' metadata.
        outage: ``(t0, t1)``; GPS fixes with ``t0 <= t <= t1`` are withheld.
        first_gps_index: index of the GPS time of the first state (the example uses 1).
        gps_skip: use a fix at state ``i`` only when ``i % gps_skip == 0`` (example: 10).
        warmup_intervals: GPS intervals accumulated before the first ISAM2 update.
        init_from_gps: initial yaw/velocity values from the first GPS displacement
            (default: identity rotation and zero velocity, as in the example).
        factorization: ISAM2 factorization, ``"QR"`` or ``"CHOLESKY"`` (see module doc).
        gravity: gravity magnitude, m/s^2 (default the example's 9.8).
        gps_sigma: (3,) per-axis GPS position sigmas, m (default: the example's precision
            ``1 / 0.07`` per axis).
        init_bias_sigmas: sigmas of the initial (accelerometer m/s^2, gyroscope rad/s) bias
            prior (default the example's).
        gps_velocity: (M, 3) world-frame velocity at each GPS time, m/s, or None (no
            velocity factors: the example's graph). A row with a non-finite entry (in it or
            in its sigmas) is skipped.
        gps_velocity_sigma: (3,) or (M, 3) per-axis sigmas of ``gps_velocity``, m/s
            (required with it).
        gps_heading: (M,) dual-antenna heading at each GPS time, rad clockwise from north
            (module doc, item 10), or None (no heading factors). A non-finite row (or
            sigma) has none.
        gps_heading_sigma: scalar or (M,) sigma of ``gps_heading``, rad (required with it).
        heading_baseline: (3,) primary -> secondary antenna in the body frame (default
            ``[1, 0, 0]``, the body's x axis); it must have a horizontal part.
        mag_field: (M, 3) corrected magnetometer reading at each GPS time, body frame, uT
            (module doc, item 11), or None (no magnetometer factors). A non-finite row has
            none.
        mag_world: (3,) the local earth field, ENU, uT (required with ``mag_field``).
        mag_sigma: per-axis sigma of ``mag_field``, uT (required with it).
        mag_robust: a ``gtsam.noiseModel.mEstimator`` (e.g. ``Huber.Create(1.345)``) for
            the magnetometer factors, or None (Gaussian).

    Returns:
        dict with ``t`` (M',) state times (``gps_t[first_gps_index:]``),
        ``filter_position`` (M', 3) newest-state position right after the update that
        added it, ``smoothed_position`` (M', 3) final ISAM2 estimate,
        ``filter_rotation`` / ``smoothed_rotation`` (M', 3, 3) the same for the
        body -> world rotation, ``gps_used`` (M',) bool, ``heading_used`` (M',) bool (a
        heading factor at the state), ``mag_used`` (M',) bool (a magnetometer factor),
        ``causal`` (M',) bool (False for warm-up states),
        ``wall_s`` (graph building + ISAM2 updates + estimate extraction; input reading
        excluded), ``n_states``, ``n_factors`` (in the final graph), ``n_updates``,
        ``outage``, ``first_gps_index``.
    """
    imu_t = np.asarray(imu_t, dtype=float)
    imu_acc = np.asarray(imu_acc, dtype=float)
    imu_gyro = np.asarray(imu_gyro, dtype=float)
    gps_t = np.asarray(gps_t, dtype=float)
    gps_xyz = np.asarray(gps_xyz, dtype=float)
    if not 0 <= first_gps_index < len(gps_t) - 1:
        raise ValueError("first_gps_index must leave at least two GPS times")
    if gps_skip < 1 or warmup_intervals < 0:
        raise ValueError("gps_skip must be >= 1 and warmup_intervals >= 0")
    if not np.all(np.isfinite(gps_xyz[first_gps_index])):
        raise ValueError(f"the first state's GPS fix {first_gps_index} is not finite")
    vel_sigma = None
    if gps_velocity is not None:
        gps_velocity = np.asarray(gps_velocity, dtype=float)
        if gps_velocity.shape != gps_xyz.shape:
            raise ValueError(
                f"gps_velocity has shape {gps_velocity.shape}, expected {gps_xyz.shape}"
            )
        if gps_velocity_sigma is None:
            raise ValueError("gps_velocity needs gps_velocity_sigma")
        vel_sigma = np.broadcast_to(np.asarray(gps_velocity_sigma, dtype=float), gps_xyz.shape)
    baseline = np.array([1.0, 0.0, 0.0] if heading_baseline is None else heading_baseline, float)
    if baseline.shape != (3,) or math.hypot(baseline[0], baseline[1]) < 1e-9:
        raise ValueError(f"heading_baseline must be (3,) with a horizontal part, got {baseline}")
    head_sigma = None
    if gps_heading is not None:
        gps_heading = np.asarray(gps_heading, dtype=float)
        if gps_heading.shape != gps_t.shape:
            raise ValueError(f"gps_heading has shape {gps_heading.shape}, expected {gps_t.shape}")
        if gps_heading_sigma is None:
            raise ValueError("gps_heading needs gps_heading_sigma")
        head_sigma = np.broadcast_to(np.asarray(gps_heading_sigma, dtype=float), gps_t.shape)
    if mag_field is not None:
        mag_field = np.asarray(mag_field, dtype=float)
        if mag_field.shape != (len(gps_t), 3):
            raise ValueError(f"mag_field has shape {mag_field.shape}, expected {(len(gps_t), 3)}")
        if mag_world is None or mag_sigma is None:
            raise ValueError("mag_field needs mag_world and mag_sigma")
        mag_world = np.asarray(mag_world, dtype=float)
        if mag_world.shape != (3,) or math.hypot(mag_world[0], mag_world[1]) < 1e-9:
            raise ValueError(f"mag_world must be (3,) with a horizontal part, got {mag_world}")

    imu_dt = np.empty_like(imu_t)
    imu_dt[1:] = np.diff(imu_t)
    imu_dt[0] = float(meta.get("average_delta_t", imu_dt[1] if len(imu_t) > 1 else 0.0))

    first = first_gps_index
    n_states = len(gps_t) - first
    filter_pos = np.full((n_states, 3), np.nan)
    filter_rot = np.full((n_states, 3, 3), np.nan)
    gps_used = np.zeros(n_states, dtype=bool)
    heading_used = np.zeros(n_states, dtype=bool)
    mag_used = np.zeros(n_states, dtype=bool)
    causal = np.zeros(n_states, dtype=bool)
    warmup_end = first + warmup_intervals  # first update once i > warmup_end

    def in_outage(t: float) -> bool:
        return outage is not None and outage[0] <= t <= outage[1]

    start = time.perf_counter()
    imu_params = make_imu_params(meta, gravity)
    if gps_sigma is None:
        noise_gps = gtsam.noiseModel.Diagonal.Precisions(np.full(3, GPS_PRECISION))
    else:
        noise_gps = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(gps_sigma, dtype=float))
    noise_init_x = gtsam.noiseModel.Diagonal.Precisions(
        np.array([0.0, 0.0, 0.0] + [INIT_POSITION_PRECISION] * 3)
    )
    noise_init_v = gtsam.noiseModel.Isotropic.Sigma(3, INIT_VELOCITY_SIGMA)
    noise_init_b = gtsam.noiseModel.Diagonal.Sigmas(
        np.array([init_bias_sigmas[0]] * 3 + [init_bias_sigmas[1]] * 3)
    )

    def velocity_at(i: int) -> np.ndarray | None:
        """The velocity measured at GPS time ``i`` if one is given and finite (its sigmas
        too)."""
        if gps_velocity is None or not np.all(np.isfinite(gps_velocity[i])):
            return None
        if not np.all(np.isfinite(vel_sigma[i])):
            return None
        return gps_velocity[i]

    def add_velocity_prior(i: int) -> np.ndarray | None:
        """Put the velocity prior of GPS time ``i`` (if any) on ``V(i)``; return it."""
        v_meas = velocity_at(i)
        if v_meas is not None:
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(vel_sigma[i]))
            new_factors.push_back(gtsam.PriorFactorVector(V(i), v_meas, noise))
        return v_meas

    def heading_at(i: int) -> float | None:
        """The heading measured at GPS time ``i`` if one is given, finite (its sigma too)
        and outside the outage."""
        if gps_heading is None or in_outage(gps_t[i]):
            return None
        if not (np.isfinite(gps_heading[i]) and np.isfinite(head_sigma[i])):
            return None
        return float(gps_heading[i])

    def add_heading_factor(i: int) -> None:
        """Put the heading factor of GPS time ``i`` (if any) on ``X(i)``."""
        z = heading_at(i)
        if z is not None:
            new_factors.push_back(heading_factor(X(i), z, head_sigma[i], baseline))
            heading_used[i - first] = True

    def add_mag_factor(i: int) -> None:
        """Put the magnetometer factor of GPS time ``i`` (if any) on ``X(i)``."""
        if mag_field is None or not np.all(np.isfinite(mag_field[i])):
            return
        scale = float(np.linalg.norm(mag_world))
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(mag_sigma))
        if mag_robust is not None:
            noise = gtsam.noiseModel.Robust.Create(mag_robust, noise)
        new_factors.push_back(
            gtsam.MagPoseFactorPose3(
                X(i), mag_field[i], scale, mag_world / scale, np.zeros(3), noise
            )
        )
        mag_used[i - first] = True

    isam_params = gtsam.ISAM2Params()
    isam_params.setFactorization(factorization)
    isam_params.relinearizeSkip = 10
    isam = gtsam.ISAM2(isam_params)

    new_factors = gtsam.NonlinearFactorGraph()
    new_values = gtsam.Values()

    pose = gtsam.Pose3(gtsam.Rot3(), gps_xyz[first])
    vel = np.zeros(3)
    if init_from_gps:
        fixed = np.flatnonzero(np.isfinite(gps_xyz[first + 1 :]).all(axis=1))
        after = first + 1 + (int(fixed[0]) if fixed.size else 0)
        disp = gps_xyz[after] - gps_xyz[first]
        yaw = float(np.arctan2(disp[1], disp[0]))
        vel = disp / (gps_t[after] - gps_t[first])
        v_first = velocity_at(first)
        if v_first is not None:
            vel = v_first.copy()
            yaw = float(np.arctan2(vel[1], vel[0]))
        if mag_field is not None and np.all(np.isfinite(mag_field[first])):
            declination = math.atan2(mag_world[0], mag_world[1])
            yaw = level_yaw_for_heading(declination, mag_field[first])
        z_first = heading_at(first)
        if z_first is not None:
            yaw = level_yaw_for_heading(z_first, baseline)
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gps_xyz[first])
    bias = gtsam.imuBias.ConstantBias()
    new_values.insert(X(first), pose)
    new_values.insert(V(first), vel)
    new_values.insert(B(first), bias)
    new_factors.addPriorPose3(X(first), pose, noise_init_x)
    new_factors.addPriorVector(V(first), vel, noise_init_v)
    new_factors.addPriorConstantBias(B(first), bias, noise_init_b)
    add_velocity_prior(first)
    add_heading_factor(first)
    add_mag_factor(first)
    gps_used[0] = True  # the initial position prior is centred on this fix

    j = int(np.searchsorted(imu_t, gps_t[first], side="left"))
    n_updates = 0
    for i in range(first + 1, len(gps_t)):
        t_prev, t = gps_t[i - 1], gps_t[i]
        pim = gtsam.PreintegratedCombinedMeasurements(imu_params, bias)
        while j < len(imu_t) and imu_t[j] <= t:
            if imu_t[j] >= t_prev:
                pim.integrateMeasurement(imu_acc[j], imu_gyro[j], imu_dt[j])
            j += 1
        new_factors.push_back(
            gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i), pim)
        )

        pred = pim.predict(gtsam.NavState(pose, vel), bias)
        pose, vel = pred.pose(), pred.velocity()
        if i % gps_skip == 0 and not in_outage(t) and np.all(np.isfinite(gps_xyz[i])):
            new_factors.push_back(gtsam.GPSFactor(X(i), gps_xyz[i], noise_gps))
            pose = gtsam.Pose3(pose.rotation(), gps_xyz[i])
            gps_used[i - first] = True
            v_meas = add_velocity_prior(i)
            if v_meas is not None:
                vel = v_meas.copy()
        add_heading_factor(i)
        add_mag_factor(i)
        new_values.insert(X(i), pose)
        new_values.insert(V(i), vel)
        new_values.insert(B(i), bias)

        if i > warmup_end:
            isam.update(new_factors, new_values)
            new_factors.resize(0)
            new_values.clear()
            n_updates += 1
            pose = isam.calculateEstimatePose3(X(i))
            vel = isam.calculateEstimateVector(V(i))
            bias = isam.calculateEstimateConstantBias(B(i))
            filter_pos[i - first] = pose.translation()
            filter_rot[i - first] = pose.rotation().matrix()
            causal[i - first] = True
            if n_updates == 1:  # warm-up states: their value at the first update
                for k in range(first, i):
                    warm = isam.calculateEstimatePose3(X(k))
                    filter_pos[k - first] = warm.translation()
                    filter_rot[k - first] = warm.rotation().matrix()

    if new_values.size() > 0:  # too few GPS times to leave the warm-up
        isam.update(new_factors, new_values)
        n_updates += 1
    result = isam.calculateEstimate()
    poses = [result.atPose3(X(i)) for i in range(first, len(gps_t))]
    smoothed = np.array([p.translation() for p in poses])
    smoothed_rot = np.array([p.rotation().matrix() for p in poses])
    unset = np.isnan(filter_pos[:, 0])
    filter_pos[unset] = smoothed[unset]
    filter_rot[unset] = smoothed_rot[unset]
    wall_s = time.perf_counter() - start

    return {
        "t": gps_t[first:].copy(),
        "filter_position": filter_pos,
        "smoothed_position": smoothed,
        "filter_rotation": filter_rot,
        "smoothed_rotation": smoothed_rot,
        "gps_used": gps_used,
        "heading_used": heading_used,
        "mag_used": mag_used,
        "causal": causal,
        "wall_s": wall_s,
        "n_states": n_states,
        "n_factors": isam.getFactorsUnsafe().size(),
        "n_updates": n_updates,
        "outage": None if outage is None else (float(outage[0]), float(outage[1])),
        "first_gps_index": first,
    }
