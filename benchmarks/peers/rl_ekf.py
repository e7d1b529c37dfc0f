"""robot_localization's EKF (ROS ``ekf_localization_node``) rewritten in numpy, as a peer.

robot_localization is ROS C++ and cannot be installed here, so this module does what its
EKF does, written from reading its source (cra-ros-pkg/robot_localization): ``src/ekf.cpp``
(``Ekf::predict``, ``Ekf::correct``), ``src/filter_base.cpp`` (``FilterBase::reset``,
``processMeasurement``, ``checkMahalanobisThreshold``, ``wrapStateAngles``),
``src/ros_filter.cpp`` (the measurement queue, ``prepareAcceleration`` with
``imu0_remove_gravitational_acceleration``, ``forceTwoD``) and ``params/ekf_template.yaml``
/ the navsat_transform docs (GNSS enters as an odometry pose x, y, z in the world frame).

Model (state order of ``filter_common.h``)::

    x = [x y z  roll pitch yaw  vx vy vz  vroll vpitch vyaw  ax ay az]   (15,)

Position and Euler angles (tf2 ``setRPY``: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, body ->
world) in the world frame; velocities, angular rates and accelerations in the body frame.
Predict over ``dt`` (s) with the kinematic "omnidirectional" transfer matrix ``F(x, dt)``::

    p     <- p + R (v dt + a dt^2 / 2)
    rpy   <- rpy + E(roll, pitch) w dt      (E: body rates -> Euler-angle rates)
    v     <- v + a dt;   w, a constant
    P     <- J P J^T + Q dt                 (J: the analytic Jacobian of F(x, dt) x)

then the three angles are wrapped to (-pi, pi]. A measurement updates only the state entries
in its update vector (``H`` = rows of the identity), innovation ``z - x`` with the angles
wrapped, a Mahalanobis gate ``d^2 < threshold^2`` (default: none, as robot_localization's
``*_rejection_threshold`` default of DBL_MAX), and the Joseph-form covariance update.
Measurement variances below 1e-9 are raised to 1e-9, as ``Ekf::correct`` does.

Measurements are processed in time order (stable: at one stamp the IMU angular velocity,
the IMU acceleration, the wheel twist, the GNSS pose, then the GNSS heading; the node's
queue orders equal stamps by arrival), each predicting from the last
stamp to its own (no prediction when ``dt <= 0``), as ``FilterBase::processMeasurement``.
The first measurement initialises the filter (its update-vector entries and their
variances; the rest stays at the initial state), unless ``initial_state`` is given (the
``initial_state`` parameter of robot_localization's ROS 2 node; the filter then starts
initialised at the first stamp).

Sensors as a wheeled robot's config has them (``ekf_template.yaml``, "Preparing your data"):

* ``imu0``: angular velocity (vroll, vpitch, vyaw) and linear acceleration (ax, ay, az),
  ``imu0_remove_gravitational_acceleration: true`` with no orientation in the message
  (orientation covariance -1), so gravity ``R(roll, pitch, yaw)^T [0, 0, g]`` is removed
  with the filter's own attitude. robot_localization reads that attitude in the IMU
  callback, i.e. before the queue is integrated; here it is the state after the previous
  stamp (before predicting to this one), the closest an offline loop gets. The IMU is
  taken as mounted at base_link with identity rotation (the simulator's);
* ``odom0``: wheel odometry as body twist (vx, vy, vz, vyaw) with vx = (v_l + v_r) / 2,
  vyaw = (v_r - v_l) / track and vy = vz = 0 (a differential drive cannot move sideways or
  vertically), ``odom0_differential: false``;
* ``odom1``: GNSS fixes as pose x, y, z (navsat_transform's ``odometry/gps``; the caller
  gives ENU positions in the filter's world frame), variances from the fix sigmas;
* ``imu1`` (optional): a dual-antenna GNSS heading as a second IMU-type input with only yaw
  enabled (e.g. the u-blox driver's ``navheading`` sensor_msgs/Imu; ``imu1_config`` true
  for yaw only, ``imu1_differential`` and ``imu1_relative`` false), at its own stamps.
  ``RosFilter::preparePose`` with ``imu_data`` and an identity mounting passes the
  message's yaw (ENU, counter-clockwise from east, one branch: here wrapped like the
  state's angles) and the yaw entry of its orientation covariance through unchanged;
  ``Ekf::correct`` then updates the yaw row alone with the innovation wrapped
  (``clampRotation``), so a heading across +-pi pulls the short way round.

``two_d_mode`` (off by default) does what ``forceTwoD`` does to every measurement: z, roll,
pitch, vz, vroll, vpitch, az measured as 0 with variance 1e-6.

Not reimplemented (unused by this configuration): control input, differential / relative
modes, the dynamic process noise (``use_dynamic_process_noise_covariance``, off by default
in the template), sensor transforms other than identity, history / smoothing of lagged
data, the periodic ``predict_to_current_time`` output.
"""

from __future__ import annotations

__all__ = [
    "STATE_SIZE",
    "DEFAULT_PROCESS_NOISE",
    "INITIAL_COVARIANCE",
    "rotation_rpy",
    "transfer_matrix",
    "transfer_jacobian",
    "RlEkf",
    "run_rl_ekf",
]

import math
from typing import Any

import numpy as np

STATE_SIZE = 15
X, Y, Z, ROLL, PITCH, YAW, VX, VY, VZ, VROLL, VPITCH, VYAW, AX, AY, AZ = range(STATE_SIZE)
ANGLES = (ROLL, PITCH, YAW)
TWO_D_ENTRIES = (Z, ROLL, PITCH, VZ, VROLL, VPITCH, AZ)
TWO_D_VARIANCE = 1e-6
MIN_VARIANCE = 1e-9

DEFAULT_PROCESS_NOISE = np.array(
    [0.05, 0.05, 0.06, 0.03, 0.03, 0.06, 0.025, 0.025, 0.04, 0.01, 0.01, 0.02, 0.01, 0.01, 0.015]
)
"""Diagonal of robot_localization's default process noise covariance (``FilterBase::reset``,
``ekf_template.yaml``), per second: ``Q dt`` is added at each predict."""

INITIAL_COVARIANCE = 1e-9
"""Diagonal of its default initial estimate covariance (``initial_estimate_covariance``)."""


def _wrap(angle: float) -> float:
    """Angle wrapped to [-pi, pi) (``filter_utilities::clampRotation``)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body -> world rotation (3, 3) of tf2's ``setRPY``: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def transfer_matrix(state: np.ndarray, dt: float) -> np.ndarray:
    """robot_localization's transfer matrix ``F(x, dt)`` (15, 15); the predicted state is
    ``F @ x`` (before angle wrapping).

    Args:
        state: (15,) state (m, rad, m/s, rad/s, m/s^2).
        dt: time step, s.
    """
    roll, pitch, yaw = state[ROLL], state[PITCH], state[YAW]
    rot = rotation_rpy(roll, pitch, yaw)
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    f = np.eye(STATE_SIZE)
    f[X : Z + 1, VX : VZ + 1] = rot * dt
    f[X : Z + 1, AX : AZ + 1] = rot * (0.5 * dt * dt)
    # Euler-angle rates from body rates
    f[ROLL, VROLL] = dt
    f[ROLL, VPITCH] = sr * sp / cp * dt
    f[ROLL, VYAW] = cr * sp / cp * dt
    f[PITCH, VPITCH] = cr * dt
    f[PITCH, VYAW] = -sr * dt
    f[YAW, VPITCH] = sr / cp * dt
    f[YAW, VYAW] = cr / cp * dt
    f[VX, AX] = f[VY, AY] = f[VZ, AZ] = dt
    return f


def transfer_jacobian(state: np.ndarray, dt: float) -> np.ndarray:
    """Jacobian (15, 15) of ``x -> transfer_matrix(x, dt) @ x`` (``Ekf::predict``'s
    ``transfer_function_jacobian_``): the transfer matrix plus the derivatives of its
    angle-dependent entries.

    robot_localization derives the terms by hand. Its ROS 2 ``ekf.cpp`` (rclcpp; stored
    commit 0108d3f) has the sign of the ``cr tan(pitch) / cos(pitch) vyaw`` term of
    d(yaw)/d(pitch) flipped; its ROS 1 ``ekf.cpp`` (commit 1bfc112) has the exact
    derivative, which this follows. The term is zero at zero pitch.
    """
    roll, pitch, yaw = state[ROLL], state[PITCH], state[YAW]
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    tp, cpi = sp / cp, 1.0 / cp
    v = state[VX : VZ + 1]
    a = state[AX : AZ + 1]
    motion = v * dt + a * (0.5 * dt * dt)  # body-frame displacement over dt
    # derivatives of R = Rz Ry Rx with respect to roll, pitch and yaw
    d_roll = np.array(
        [
            [0.0, cy * sp * cr + sy * sr, -cy * sp * sr + sy * cr],
            [0.0, sy * sp * cr - cy * sr, -sy * sp * sr - cy * cr],
            [0.0, cp * cr, -cp * sr],
        ]
    )
    d_pitch = np.array(
        [
            [-cy * sp, cy * cp * sr, cy * cp * cr],
            [-sy * sp, sy * cp * sr, sy * cp * cr],
            [-cp, -sp * sr, -sp * cr],
        ]
    )
    d_yaw = np.array(
        [
            [-sy * cp, -sy * sp * sr - cy * cr, -sy * sp * cr + cy * sr],
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [0.0, 0.0, 0.0],
        ]
    )
    wp, wy = state[VPITCH], state[VYAW]
    j = transfer_matrix(state, dt)
    j[X : Z + 1, ROLL] = d_roll @ motion
    j[X : Z + 1, PITCH] = d_pitch @ motion
    j[X : Z + 1, YAW] = d_yaw @ motion
    j[ROLL, ROLL] = 1.0 + (cr * tp * wp - sr * tp * wy) * dt
    j[ROLL, PITCH] = (cpi * cpi * sr * wp + cpi * cpi * cr * wy) * dt
    j[PITCH, ROLL] = (-sr * wp - cr * wy) * dt
    j[YAW, ROLL] = (cr * cpi * wp - sr * cpi * wy) * dt
    j[YAW, PITCH] = (sr * tp * cpi * wp + cr * tp * cpi * wy) * dt
    return j


class RlEkf:
    """The filter: state (15,), covariance (15, 15), process noise per second (15, 15).

    Args:
        process_noise: (15,) diagonal or (15, 15) process noise covariance per second;
            default :data:`DEFAULT_PROCESS_NOISE`.
        two_d_mode: force z, roll, pitch and their rates and az to 0 in every measurement.
    """

    def __init__(self, process_noise: np.ndarray | None = None, two_d_mode: bool = False):
        q = DEFAULT_PROCESS_NOISE if process_noise is None else np.asarray(process_noise, float)
        self.process_noise = np.diag(q) if q.ndim == 1 else q.copy()
        if self.process_noise.shape != (STATE_SIZE, STATE_SIZE):
            raise ValueError(f"process_noise must be (15,) or (15, 15), got {q.shape}")
        self.two_d_mode = two_d_mode
        self.state = np.zeros(STATE_SIZE)
        self.covariance = np.eye(STATE_SIZE) * INITIAL_COVARIANCE
        self.initialized = False
        self.last_time = 0.0
        self.rejected = 0

    def set_initial(self, state: np.ndarray, time: float) -> None:
        """Start initialised at ``time`` (s) with ``state`` (15,) (ROS 2's ``initial_state``)."""
        self.state = np.asarray(state, float).copy()
        self.initialized = True
        self.last_time = time

    def predict(self, dt: float) -> None:
        """Predict over ``dt`` s (``Ekf::predict`` without control input)."""
        jac = transfer_jacobian(self.state, dt)
        self.state = transfer_matrix(self.state, dt) @ self.state
        for i in ANGLES:
            self.state[i] = _wrap(self.state[i])
        self.covariance = jac @ self.covariance @ jac.T + self.process_noise * dt

    def correct(
        self, index: np.ndarray, z: np.ndarray, variance: np.ndarray, threshold: float
    ) -> bool:
        """Partial-state update (``Ekf::correct``) of the entries ``index`` (K,) measured as
        ``z`` (K,) with diagonal variances (K,); gated at ``threshold`` (Mahalanobis, sigmas).

        Returns:
            whether the measurement passed the gate and was applied.
        """
        index = np.asarray(index)
        r = np.diag(np.maximum(np.abs(variance), MIN_VARIANCE))
        pht = self.covariance[:, index]
        s_inv = np.linalg.inv(pht[index] + r)
        gain = pht @ s_inv
        innovation = np.asarray(z, float) - self.state[index]
        for k, i in enumerate(index):
            if i in ANGLES:
                innovation[k] = _wrap(innovation[k])
        if innovation @ s_inv @ innovation >= threshold * threshold:
            self.rejected += 1
            return False
        self.state = self.state + gain @ innovation
        ikh = np.eye(STATE_SIZE)
        ikh[:, index] -= gain
        self.covariance = ikh @ self.covariance @ ikh.T + gain @ r @ gain.T
        for i in ANGLES:
            self.state[i] = _wrap(self.state[i])
        return True

    def process(
        self,
        time: float,
        index: np.ndarray,
        z: np.ndarray,
        variance: np.ndarray,
        threshold: float = math.inf,
    ) -> None:
        """``FilterBase::processMeasurement``: predict to ``time`` (s) when later than the
        last stamp, then correct; the first measurement initialises the filter."""
        index, z, variance = np.asarray(index), np.asarray(z, float), np.asarray(variance, float)
        if self.two_d_mode:
            keep = ~np.isin(index, TWO_D_ENTRIES)
            index = np.concatenate((index[keep], TWO_D_ENTRIES))
            z = np.concatenate((z[keep], np.zeros(len(TWO_D_ENTRIES))))
            variance = np.concatenate((variance[keep], np.full(len(TWO_D_ENTRIES), TWO_D_VARIANCE)))
        if not self.initialized:
            self.state[index] = z
            self.covariance[index, index] = variance
            self.initialized = True
            self.last_time = time
            return
        dt = time - self.last_time
        if dt > 0.0:
            self.predict(dt)
        self.correct(index, z, variance, threshold)
        if dt >= 0.0:
            self.last_time = time


IMU_POSE, IMU_TWIST, IMU_ACCEL, ODOM_TWIST, GNSS_POSE, GNSS_HEADING = range(6)
_ODOM_INDEX = np.array([VX, VY, VZ, VYAW])
_GYRO_INDEX = np.array([VROLL, VPITCH, VYAW])
_ACCEL_INDEX = np.array([AX, AY, AZ])
_POSE_INDEX = np.array([X, Y, Z])
_ORIENTATION_INDEX = np.array([ROLL, PITCH, YAW])
_YAW_INDEX = np.array([YAW])


def run_rl_ekf(
    imu_t: np.ndarray,
    imu_gyro: np.ndarray,
    imu_accel: np.ndarray,
    gyro_variance: np.ndarray,
    accel_variance: np.ndarray,
    wheel_t: np.ndarray,
    wheel_left: np.ndarray,
    wheel_right: np.ndarray,
    wheel_track_m: float,
    wheel_twist_variance: np.ndarray,
    gnss_t: np.ndarray,
    gnss_xyz: np.ndarray,
    gnss_sigma: np.ndarray,
    gravity: float = 9.80665,
    process_noise: np.ndarray | None = None,
    initial_state: np.ndarray | None = None,
    two_d_mode: bool = False,
    rejection_threshold: float = math.inf,
    imu_rpy: np.ndarray | None = None,
    rpy_variance: np.ndarray | None = None,
    heading_t: np.ndarray | None = None,
    heading_yaw: np.ndarray | None = None,
    heading_variance: np.ndarray | None = None,
) -> dict[str, Any]:
    """Run the robot_localization EKF over IMU, wheel and GNSS streams (one run).

    Args:
        imu_t: (N,) s; imu_gyro: (N, 3) body angular velocity, rad/s; imu_accel: (N, 3)
            body specific force (accelerometer, gravity included), m/s^2.
        gyro_variance, accel_variance: (3,) per-sample variances, (rad/s)^2 and (m/s^2)^2.
        wheel_t: (W,) s; wheel_left, wheel_right: (W,) rim speeds, m/s.
        wheel_track_m: distance between the wheels, m.
        wheel_twist_variance: (4,) variances of vx, vy, vz (m/s)^2 and vyaw (rad/s)^2.
        gnss_t: (M,) s; gnss_xyz: (M, 3) ENU fixes, m (rows with NaN are skipped);
            gnss_sigma: (M, 3) or (3,) 1-sigma, m.
        gravity: m/s^2, removed from the accelerometer with the filter's attitude.
        process_noise: (15,) or (15, 15) per second; default :data:`DEFAULT_PROCESS_NOISE`.
        initial_state: (15,) start state at ``min(times)``; default: robot_localization's
            zero state initialised by the first measurement.
        two_d_mode: robot_localization's ``two_d_mode``.
        rejection_threshold: Mahalanobis threshold of every sensor (default: none).
        imu_rpy: (N, 3) the IMU's own orientation (an AHRS output: roll, pitch, yaw in the
            world frame, rad) at ``imu_t``, fused as ``imu0``'s roll / pitch / yaw before
            its rates (robot_localization's order within an IMU message); None: the IMU
            reports no orientation (orientation covariance -1).
        rpy_variance: (3,) variances of ``imu_rpy``, rad^2.
        heading_t: (H,) s, stamps of a yaw-only orientation input (``imu1``: a dual-antenna
            GNSS heading); None: no such input.
        heading_yaw: (H,) its yaw, ENU (counter-clockwise from east), rad, any branch
            (``pi / 2 - azimuth`` for a receiver whose baseline is the body x axis); rows
            with a non-finite yaw or variance are skipped.
        heading_variance: (H,) its variances, rad^2.

    Returns:
        dict with ``t`` (S,) the distinct measurement stamps, s; ``position`` (S, 3) m and
        ``rpy`` (S, 3) rad after the last measurement at each stamp; ``rejected`` the
        number of gated-out measurements.
    """
    imu_t, wheel_t, gnss_t = (np.asarray(a, float) for a in (imu_t, wheel_t, gnss_t))
    gnss_xyz = np.asarray(gnss_xyz, float)
    gnss_var = np.broadcast_to(np.asarray(gnss_sigma, float) ** 2, gnss_xyz.shape)
    for name, arr, n in (
        ("imu_gyro", imu_gyro, imu_t.size),
        ("imu_accel", imu_accel, imu_t.size),
        ("gnss_xyz", gnss_xyz, gnss_t.size),
    ):
        if np.shape(arr) != (n, 3):
            raise ValueError(f"{name} must be ({n}, 3), got {np.shape(arr)}")
    if np.shape(wheel_left) != wheel_t.shape or np.shape(wheel_right) != wheel_t.shape:
        raise ValueError("wheel_left and wheel_right must match wheel_t's shape")
    # the queue: (time, kind, row), stable order of kinds at equal times
    events = [(t, IMU_TWIST, i) for i, t in enumerate(imu_t)]
    if imu_rpy is not None:
        if np.shape(imu_rpy) != (imu_t.size, 3) or np.shape(rpy_variance) != (3,):
            raise ValueError("imu_rpy must be (N, 3) at imu_t and rpy_variance (3,)")
        events += [(t, IMU_POSE, i) for i, t in enumerate(imu_t)]
    events += [(t, IMU_ACCEL, i) for i, t in enumerate(imu_t)]
    events += [(t, ODOM_TWIST, i) for i, t in enumerate(wheel_t)]
    events += [(t, GNSS_POSE, i) for i, t in enumerate(gnss_t) if np.all(np.isfinite(gnss_xyz[i]))]
    given = [a is not None for a in (heading_t, heading_yaw, heading_variance)]
    if any(given):
        if not all(given):
            raise ValueError("heading_t, heading_yaw and heading_variance go together")
        heading_t = np.asarray(heading_t, float)
        heading_yaw = np.asarray(heading_yaw, float)
        heading_variance = np.asarray(heading_variance, float)
        shapes = (heading_t.shape, heading_yaw.shape, heading_variance.shape)
        if heading_t.ndim != 1 or len(set(shapes)) != 1:
            raise ValueError(
                f"heading_t, heading_yaw and heading_variance must be (H,) each, got {shapes}"
            )
        usable = np.isfinite(heading_yaw) & np.isfinite(heading_variance)
        events += [(t, GNSS_HEADING, i) for i, t in enumerate(heading_t) if usable[i]]
    events.sort(key=lambda e: (e[0], e[1]))
    ekf = RlEkf(process_noise, two_d_mode)
    if initial_state is not None:
        ekf.set_initial(initial_state, events[0][0])
    gyro_variance = np.asarray(gyro_variance, float)
    accel_variance = np.asarray(accel_variance, float)
    wheel_twist_variance = np.asarray(wheel_twist_variance, float)
    gravity_w = np.array([0.0, 0.0, gravity])
    stamps, positions, rpys = [], [], []
    for k, (t, kind, i) in enumerate(events):
        if kind == IMU_POSE:
            ekf.process(t, _ORIENTATION_INDEX, imu_rpy[i], rpy_variance, rejection_threshold)
        elif kind == IMU_TWIST:
            ekf.process(t, _GYRO_INDEX, imu_gyro[i], gyro_variance, rejection_threshold)
        elif kind == IMU_ACCEL:
            rot = rotation_rpy(*ekf.state[ROLL : YAW + 1])
            linear = np.asarray(imu_accel[i], float) - rot.T @ gravity_w
            ekf.process(t, _ACCEL_INDEX, linear, accel_variance, rejection_threshold)
        elif kind == ODOM_TWIST:
            vl, vr = float(wheel_left[i]), float(wheel_right[i])
            z = np.array([0.5 * (vl + vr), 0.0, 0.0, (vr - vl) / wheel_track_m])
            ekf.process(t, _ODOM_INDEX, z, wheel_twist_variance, rejection_threshold)
        elif kind == GNSS_POSE:
            ekf.process(t, _POSE_INDEX, gnss_xyz[i], gnss_var[i], rejection_threshold)
        else:
            yaw = np.array([_wrap(float(heading_yaw[i]))])
            ekf.process(t, _YAW_INDEX, yaw, heading_variance[i : i + 1], rejection_threshold)
        if k + 1 == len(events) or events[k + 1][0] != t:
            stamps.append(t)
            positions.append(ekf.state[X : Z + 1].copy())
            rpys.append(ekf.state[ROLL : YAW + 1].copy())
    return {
        "t": np.asarray(stamps),
        "position": np.asarray(positions).reshape(-1, 3),
        "rpy": np.asarray(rpys).reshape(-1, 3),
        "rejected": ekf.rejected,
    }
