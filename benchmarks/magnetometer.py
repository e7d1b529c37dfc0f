"""Magnetometer heading through a GNSS outage: our ESKF vs GTSAM's ISAM2 and
robot_localization's EKF, on simulated runs, clean and past magnetic disturbances.

What it measures
    N simulated wheeled runs (``msf_torch.sim.simulate_run``, seeds ``seed0 .. seed0+N-1``,
    default 10 runs of 90 s): IMU at 200 Hz (ADIS16470 noise), wheel rim speeds at 25 Hz,
    GNSS fixes at 1 Hz (sigma 0.5 / 0.5 / 1.0 m), zero antenna lever arm, one GNSS outage of
    ``--outage-s`` (default 20 s) starting at random after ``--outage-after-s`` (default
    40 s), and a three-axis magnetometer at 50 Hz (``SimConfig(magnetometer=True)``: a
    48-uT field, 1.05 rad inclination, per-axis noise 0.3 uT) with a declination of
    :data:`DECLINATION_RAD`, the hard iron :data:`HARD_IRON_UT` and the soft-iron
    distortion :data:`DISTORTION` (up to 5 % off the identity). It keeps reading through the
    outage. Every estimator is given the correct calibration (the fusion is compared, not
    the calibration): the corrected field ``W (m - b)`` with ``W`` the distortion's inverse,
    the declination, and the local field's magnitude and inclination.

    Each seed is simulated twice: clean, and disturbed (``--anomalies`` local anomalies,
    default 4, of 10-40 uT over 2-5 m beside the route, the simulator's
    ``magnetometer_anomaly_count``). The anomalies have their own random stream: the two
    simulations must carry identical IMU, wheel, GNSS, truth and outage (checked, else the
    run stops), so the columns without the magnetometer are run once, on the clean one.

    * ours: ``run_eskf`` with ``load_sequence_config(seq.meta)`` plus the magnetometer keys
      above (:func:`magnetometer_config`), its defaults otherwise (2 Hz fused, sigma from the
      readings, 0.03-rad floor, the magnitude / gyro-consistency / dip tests), under
      ``torch.no_grad()``. Without wheels (``ours``, ``ours_no_mag``) the config's ``nhc:
      auto`` turns the non-holonomic constraint on, which the GTSAM peer does not have, so
      ``ours_no_nhc`` / ``ours_no_nhc_no_mag`` show ours with ``nhc: off`` (the peer's
      information); ``ours_wheels`` / ``ours_wheels_no_mag`` get the wheels too (the
      robot_localization peer's information);
    * ``peer``: GTSAM, ``benchmarks/peers/gtsam_kitti.py`` ``run_gtsam_kitti``
      (CombinedImuFactor + GPSFactor under ISAM2, set up as in ``benchmarks/gnss_velocity.py``
      and ``benchmarks/gnss_heading.py``: same IMU noise, gravity, GNSS sigmas, initial bias
      sigmas, 20-s warm-up) plus the magnetometer as GTSAM users add it, a
      ``gtsam.MagPoseFactorPose3`` (the 3-D field model ``R^T f_w``: the known field's
      direction and magnitude, zero bias, the corrected reading as the measurement) on one
      state every 0.5 s, at the reading the front end would fuse (the first of each 2-Hz
      bin), so the peer's states are 2 Hz (GNSS on every other one) and its warm-up 40
      intervals (the same 20 s). Its per-axis sigma is :func:`peer_mag_sigma`
      ``sqrt(sigma^2 + (floor H)^2)`` (H the horizontal field), the heading information
      ours gets; unlike ours it also constrains roll and pitch through the field's dip.
      Its noise model is Huber (``gtsam.noiseModel.mEstimator.Huber``, k = 1.345 on the
      whitened error), GTSAM's own disturbance rejection; nothing else. Its initial rotation
      value is level with the yaw of the first reading (``peer_no_mag``: of the first GNSS
      displacement, its states at the 1-Hz fixes, as ``gnss_heading.py``'s
      ``peer_no_heading``); the rotation prior has zero precision. Its causal estimate
      (newest state right after each update) is scored;
    * ``rl_peer``: robot_localization's EKF (``benchmarks/peers/rl_ekf.py`` ``run_rl_ekf``,
      configured as in ``benchmarks/robot_localization.py``'s ``peer_heading``: IMU rates and
      accelerations, wheel twist, GNSS pose, its default process noise, start state =
      ours_wheels' initial state, no rejection thresholds) plus the magnetometer the way a
      ROS user feeds a compass or ``imu_filter_madgwick``'s yaw: a yaw-only ``imu1`` at the
      same 2-Hz readings, the tilt-compensated compass yaw (:func:`compass_yaw`: roll and
      pitch from that instant's accelerometer, the corrected field levelled by them, its
      azimuth minus the declination), variance ``sigma^2 / H^2 + floor^2`` (ours' formula,
      ``msf_torch.sensors.magnetometer.magnetometer_heading_variance``, with the levelling
      rotation).

    The disturbed simulation gives the columns ``disturbed_ours``, ``disturbed_ours_no_nhc``,
    ``disturbed_ours_wheels``, ``disturbed_peer`` and ``disturbed_rl_peer``.

    Scoring, the same for all (``benchmarks/gnss_heading.py``'s): at the 1-Hz GNSS grid times
    (ours and robot_localization interpolated there: positions linearly, yaw linearly after
    unwrapping), position ``rmse_m`` over the run, ``rmse_after_warmup_m``,
    ``outage_max_error_m`` and ``outage_rmse_m``, and yaw error against the simulator's truth
    (``yaw_rmse_deg``, ``yaw_rmse_after_warmup_deg``, ``outage_yaw_max_deg``). Medians over
    the runs; ``wins`` counts, per pair of :data:`PAIRS` and metric, the runs where ours is
    below the peer. Wall time of each call (median over runs); the ratio ours / GTSAM peer.
    The robot_localization peer is a numpy rewrite of a C++ node: its wall time says nothing
    about the node's, so there is no ratio for it. No target: no issue sets one.

How to run
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/magnetometer.py            # ~4 min
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/magnetometer.py --seeds 1 \\
        --duration-s 45 --outage-after-s 22 --outage-s 10                   # smoke run

    Per-run lines go to stderr; the last line on stdout is one JSON object.

Options
    --seeds N           number of simulated runs (default 10)
    --seed0 S           first seed (default 100)
    --duration-s T      run length, s (default 90)
    --outage-s D        outage length, s (default 20)
    --outage-after-s A  earliest outage start, s (default 40; must leave the peer's 20-s
                        warm-up first)
    --anomalies K       magnetic anomalies of the disturbed simulation (default 4)
    --repeats N         timed repeats of every call (median; default 1)
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import gtsam  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks import robot_localization  # noqa: E402
from benchmarks._common import emit_json, time_repeats  # noqa: E402
from benchmarks.gnss_heading import ALL_METRICS, truth_yaw, yaw_at, yaw_of, yaw_score  # noqa: E402
from benchmarks.gnss_velocity import (  # noqa: E402
    NO_NHC,
    PEER_WARMUP_INTERVALS,
    medians,
    outage_inputs,
    outage_parser,
    outage_runs,
    peer_inputs,
    score,
)
from benchmarks.peers.gtsam_kitti import level_yaw_for_heading, run_gtsam_kitti  # noqa: E402
from benchmarks.peers.rl_ekf import rotation_rpy, run_rl_ekf  # noqa: E402
from msf_torch.eval.outage import interpolate_positions  # noqa: E402
from msf_torch.frontend.config import EskfConfig, load_sequence_config  # noqa: E402
from msf_torch.frontend.eskf import run_eskf  # noqa: E402
from msf_torch.sensors.magnetometer import (  # noqa: E402
    corrected_field,
    magnetometer_heading_variance,
)
from msf_torch.sim import SimConfig, SimulatedRun, simulate_run  # noqa: E402
from msf_torch.sim.magnetometer import earth_field  # noqa: E402
from msf_torch.types import Sequence  # noqa: E402

DECLINATION_RAD = 0.2
"""The simulated declination (magnetic north 11.5 deg east of true north), rad."""
HARD_IRON_UT = (12.0, -7.0, 4.0)
"""The simulated hard iron ``b``, uT."""
DISTORTION = (1.05, 0.02, 0.0, 0.02, 0.96, 0.01, 0.0, 0.01, 1.0)
"""The simulated soft-iron distortion ``S`` (row-major 3 x 3); the correction is ``S^-1``."""
PEER_HUBER_K = 1.345
"""Huber threshold of the GTSAM peer's magnetometer noise model (whitened units)."""

OURS: dict[str, dict[str, Any]] = {
    "ours": {"mag": True, "wheels": False, "config": {}},
    "ours_no_mag": {"mag": False, "wheels": False, "config": {}},
    "ours_no_nhc": {"mag": True, "wheels": False, "config": NO_NHC},
    "ours_no_nhc_no_mag": {"mag": False, "wheels": False, "config": NO_NHC},
    "ours_wheels": {"mag": True, "wheels": True, "config": {}},
    "ours_wheels_no_mag": {"mag": False, "wheels": True, "config": {}},
}
"""Our columns: magnetometer used, wheels used, config overrides."""

PEERS: dict[str, dict[str, bool]] = {
    "peer": {"gtsam": True, "mag": True},
    "peer_no_mag": {"gtsam": True, "mag": False},
    "rl_peer": {"gtsam": False, "mag": True},
    "rl_peer_no_mag": {"gtsam": False, "mag": False},
}
"""Peer columns: GTSAM (else robot_localization), magnetometer used."""

DISTURBED = "disturbed_"
"""Prefix of the columns on the disturbed simulation (the magnetometer columns only)."""

PAIRS = (
    ("ours", "peer"),
    ("ours_no_nhc", "peer"),
    ("ours_no_mag", "peer_no_mag"),
    ("ours_wheels", "rl_peer"),
    ("ours_wheels_no_mag", "rl_peer_no_mag"),
    (DISTURBED + "ours", DISTURBED + "peer"),
    (DISTURBED + "ours_no_nhc", DISTURBED + "peer"),
    (DISTURBED + "ours_wheels", DISTURBED + "rl_peer"),
)
"""(ours, peer) column pairs that ``wins`` and the ratios compare."""

HEADLINE = ("yaw_rmse_deg", "rmse_m", "outage_max_error_m")
"""The metrics of the ratios and wins."""


def columns_of(spec: dict[str, dict[str, Any]], disturbed: bool) -> list[str]:
    """Column names of ``spec`` (:data:`OURS` or :data:`PEERS`) on one simulation: all on
    the clean one, the magnetometer ones prefixed :data:`DISTURBED` on the disturbed one."""
    if not disturbed:
        return list(spec)
    return [DISTURBED + name for name, s in spec.items() if s["mag"]]


def magnetometer_config(sim_cfg: SimConfig) -> dict[str, Any]:
    """Our config keys for the simulator's magnetometer: its declination, the correction of
    its iron (hard iron ``b``, soft iron ``S^-1`` row-major) and the local field's magnitude
    (uT) and inclination (rad)."""
    soft = np.linalg.inv(np.reshape(sim_cfg.magnetometer_distortion, (3, 3)))
    return {
        "magnetometer_declination_rad": sim_cfg.magnetometer_declination_rad,
        "magnetometer_hard_iron_uT": list(sim_cfg.magnetometer_hard_iron_uT),
        "magnetometer_soft_iron": soft.reshape(-1).tolist(),
        "magnetometer_field_uT": sim_cfg.magnetometer_field_uT,
        "magnetometer_inclination_rad": sim_cfg.magnetometer_inclination_rad,
    }


def fused_readings(seq: Sequence, cfg: EskfConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The readings the peers get: the first of each ``1 / magnetometer_rate_hz`` bin on the
    absolute clock (the front end's rate rule), corrected with ``cfg``'s iron.

    Returns:
        times (K,) s, corrected fields (K, 3) body frame, uT, and per-axis sigmas (K,) uT
        (a NaN sigma: ``cfg.magnetometer_sigma_uT``).
    """
    mag = seq.magnetometer
    keep = mag.mask[0]
    t = mag.t[0, keep].numpy()
    bins = np.floor(t * cfg.magnetometer_rate_hz + 1e-9)
    first = np.concatenate(([True], bins[1:] != bins[:-1]))
    field = corrected_field(
        mag.field[0, keep][first],
        torch.tensor(cfg.magnetometer_hard_iron_uT, dtype=torch.float64),
        torch.tensor(cfg.magnetometer_soft_iron, dtype=torch.float64).reshape(3, 3),
    )
    sigma = mag.sigma[0, keep][first].numpy()
    return t[first], field.numpy(), np.where(np.isnan(sigma), cfg.magnetometer_sigma_uT, sigma)


def peer_mag_sigma(sigma: float, floor: float, field_world: np.ndarray) -> float:
    """The GTSAM peer's per-axis magnetometer sigma, uT: ``sqrt(sigma^2 + (floor H)^2)``, so
    that its heading's variance is ours' ``sigma^2 / H^2 + floor^2`` (``H`` the horizontal
    magnitude of ``field_world`` (3,) uT; ``sigma`` uT, ``floor`` rad)."""
    horizontal = math.hypot(field_world[0], field_world[1])
    return math.sqrt(sigma**2 + (floor * horizontal) ** 2)


def gtsam_mag_inputs(
    arrays: dict[str, Any], seq: Sequence, cfg: EskfConfig
) -> tuple[dict[str, Any], int]:
    """``run_gtsam_kitti`` inputs with the magnetometer: the 1-Hz GNSS grid of ``arrays``
    (``gnss_velocity.peer_inputs``) refined to ``cfg.magnetometer_rate_hz`` (NaN fixes
    between the fixes), a corrected reading at each state time (:func:`fused_readings`), the
    simulator's earth field, :func:`peer_mag_sigma` and a Huber kernel.

    Returns:
        (keyword inputs, states per GNSS interval ``k``).
    """
    grid = arrays["gps_t"]
    gnss_rate = 1.0 / float(grid[1] - grid[0])
    k = int(round(cfg.magnetometer_rate_hz / gnss_rate))
    if k < 1 or not math.isclose(k * gnss_rate, cfg.magnetometer_rate_hz):
        raise ValueError("the magnetometer rate must be a multiple of the GNSS rate")
    fine = np.arange((len(grid) - 1) * k + 1) / (gnss_rate * k)
    xyz = np.full((len(fine), 3), np.nan)
    xyz[::k] = arrays["gps_xyz"]
    t, field, sigma = fused_readings(seq, cfg)
    index = np.rint(t * gnss_rate * k).astype(int)
    on_grid = (index < len(fine)) & np.isclose(fine[np.minimum(index, len(fine) - 1)], t)
    mag = np.full((len(fine), 3), np.nan)
    mag[index[on_grid]] = field[on_grid]
    world = np.asarray(seq.meta["magnetometer"]["earth_field_world_uT"], dtype=float)
    if np.ptp(sigma) > 0.0:
        raise ValueError("the peer takes one magnetometer sigma; the readings carry several")
    return {
        **arrays,
        "gps_t": fine,
        "gps_xyz": xyz,
        "mag_field": mag,
        "mag_world": world,
        "mag_sigma": peer_mag_sigma(float(sigma[0]), cfg.magnetometer_heading_floor_rad, world),
        "mag_robust": gtsam.noiseModel.mEstimator.Huber.Create(PEER_HUBER_K),
    }, k


def compass_yaw(seq: Sequence, cfg: EskfConfig) -> dict[str, np.ndarray]:
    """``run_rl_ekf``'s yaw-only ``imu1`` from the magnetometer, a tilt-compensated compass:
    at each of :func:`fused_readings`' times, roll ``atan2(a_y, a_z)`` and pitch
    ``atan2(-a_x, sqrt(a_y^2 + a_z^2))`` from the IMU's specific force at that instant level
    the corrected field; the level yaw whose field points at the declination is the ENU yaw.
    Variance: ours' ``sigma^2 / H^2 + floor^2`` through the levelling rotation.

    Returns:
        dict with ``heading_t`` (K,) s, ``heading_yaw`` (K,) rad, ``heading_variance`` (K,)
        rad^2.
    """
    t, field, sigma = fused_readings(seq, cfg)
    imu = seq.imu
    imu_t = imu.t[0, imu.mask[0]].numpy()
    index = np.clip(np.searchsorted(imu_t, t - 1e-9), 0, len(imu_t) - 1)
    if not np.allclose(imu_t[index], t, rtol=0.0, atol=1e-9):
        raise ValueError("the magnetometer readings are not at IMU sample times")
    accel = imu.accel[0, imu.mask[0]][index].numpy()
    roll = np.arctan2(accel[:, 1], accel[:, 2])
    pitch = np.arctan2(-accel[:, 0], np.hypot(accel[:, 1], accel[:, 2]))
    level = np.stack([rotation_rpy(r, p, 0.0) for r, p in zip(roll, pitch, strict=True)])
    levelled = np.einsum("nij,nj->ni", level, field)
    declination = cfg.magnetometer_declination_rad
    yaw = np.array([level_yaw_for_heading(declination, f) for f in levelled])
    variance = magnetometer_heading_variance(
        torch.as_tensor(level),
        torch.as_tensor(field),
        torch.as_tensor(sigma),
        cfg.magnetometer_heading_floor_rad,
    )
    return {"heading_t": t, "heading_yaw": yaw, "heading_variance": variance.numpy()}


def check_same_but_magnetometer(clean: Sequence, disturbed: Sequence) -> None:
    """Raise ``RuntimeError`` unless the clean and disturbed simulations of one seed carry
    identical IMU, wheel, GNSS and truth streams and outage labels."""
    for name in ("imu", "wheel", "gnss", "ground_truth"):
        a, b = getattr(clean, name), getattr(disturbed, name)
        if not all(
            torch.equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        ):
            raise RuntimeError(f"{name} differs between the clean and disturbed simulations")
    if not torch.equal(clean.labels["gnss_outage"], disturbed.labels["gnss_outage"]):
        raise RuntimeError("the outage differs between the clean and disturbed simulations")


def run_set(run: SimulatedRun, sim_cfg: SimConfig, repeats: int, disturbed: bool) -> dict[str, Any]:
    """The columns of one simulation (:func:`columns_of`): ``{column: metrics + wall_s}``."""
    seq = run.sequence
    labels = seq.labels["gnss_outage"][0]
    if labels.shape[0] != 1:
        raise RuntimeError(f"{labels.shape[0]} outages, expected 1")
    outage = (float(labels[0, 0]), float(labels[0, 1]))
    arrays = peer_inputs(seq, outage)
    grid = arrays["gps_t"]
    grid_t = torch.as_tensor(grid)
    truth = interpolate_positions(seq.ground_truth, grid_t)
    yaw_true = truth_yaw(run, grid)
    mag_keys = magnetometer_config(sim_cfg)
    prefix = DISTURBED if disturbed else ""
    row: dict[str, Any] = {}

    def variant(mag: bool, wheels: bool) -> Sequence:
        return dataclasses.replace(
            seq,
            magnetometer=seq.magnetometer if mag else None,
            wheel=seq.wheel if wheels else None,
        )

    for name in columns_of(OURS, disturbed):
        spec = OURS[name.removeprefix(prefix)]
        data = variant(spec["mag"], spec["wheels"])
        cfg = load_sequence_config(seq.meta, **mag_keys, **spec["config"])

        def ours(data: Sequence = data, cfg: EskfConfig = cfg) -> Any:
            with torch.no_grad():
                return run_eskf(data, cfg)

        wall, _, result = time_repeats(ours, repeats)
        estimate = result.trajectory()
        row[name] = {
            **score(interpolate_positions(estimate, grid_t), truth, grid, outage),
            **yaw_score(yaw_at(estimate, grid), yaw_true, grid, outage),
            "wall_s": wall,
        }
    cfg = load_sequence_config(seq.meta, **mag_keys)
    for name in columns_of(PEERS, disturbed):
        spec = PEERS[name.removeprefix(prefix)]
        if spec["gtsam"]:
            kwargs, k = gtsam_mag_inputs(arrays, seq, cfg) if spec["mag"] else (arrays, 1)

            def peer(kwargs: dict[str, Any] = kwargs, k: int = k) -> dict[str, Any]:
                return run_gtsam_kitti(
                    **kwargs,
                    first_gps_index=0,
                    warmup_intervals=PEER_WARMUP_INTERVALS * k,
                    init_from_gps=True,
                )

            wall, _, res = time_repeats(peer, repeats)
            if not np.array_equal(res["t"][::k], grid):
                raise RuntimeError("the peer's states are not at the GNSS grid")
            if spec["mag"] and not res["mag_used"].any():
                raise RuntimeError("the peer used no magnetometer reading")
            position = torch.as_tensor(res["filter_position"][::k])
            yaw = yaw_of(res["filter_rotation"][::k])
        else:
            data = variant(spec["mag"], True)
            rl_kwargs = robot_localization.peer_inputs(data, cfg)
            if spec["mag"]:
                rl_kwargs.update(compass_yaw(data, cfg))

            def peer(kwargs: dict[str, Any] = rl_kwargs) -> dict[str, Any]:
                return run_rl_ekf(**kwargs)

            wall, _, res = time_repeats(peer, repeats)
            estimate = robot_localization.peer_trajectory(res)
            position = interpolate_positions(estimate, grid_t)
            yaw = np.interp(grid, res["t"], np.unwrap(res["rpy"][:, 2]))
        row[name] = {
            **score(position, truth, grid, outage),
            **yaw_score(yaw, yaw_true, grid, outage),
            "wall_s": wall,
        }
    return {"outage_s": list(outage), **row}


def run_seed(seed: int, sim_cfg: SimConfig, repeats: int, anomalies: int) -> dict[str, Any]:
    """Every column on one seed, clean and disturbed (``anomalies`` anomalies)."""
    clean = simulate_run(sim_cfg, seed=seed)
    disturbed = simulate_run(
        dataclasses.replace(sim_cfg, magnetometer_anomaly_count=anomalies), seed=seed
    )
    check_same_but_magnetometer(clean.sequence, disturbed.sequence)
    row = run_set(clean, sim_cfg, repeats, disturbed=False)
    row.update(run_set(disturbed, sim_cfg, repeats, disturbed=True))
    return {"seed": seed, **row}


def main(argv: list[str] | None = None) -> int:
    parser = outage_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--anomalies", type=int, default=4, help="anomalies when disturbed")
    args = parser.parse_args(argv)
    if args.anomalies < 1:
        parser.error("--anomalies must be >= 1")
    streams = {
        "magnetometer": True,
        "magnetometer_declination_rad": DECLINATION_RAD,
        "magnetometer_hard_iron_uT": HARD_IRON_UT,
        "magnetometer_distortion": DISTORTION,
    }
    sim_cfg, rows, machine = outage_runs(
        parser,
        args,
        streams,
        lambda seed, cfg, repeats: run_seed(seed, cfg, repeats, args.anomalies),
        lambda m: f"yaw {m['yaw_rmse_deg']:.2f} deg max {m['outage_max_error_m']:.2f} m",
    )
    names = [
        *columns_of(OURS, False),
        *columns_of(PEERS, False),
        *columns_of(OURS, True),
        *columns_of(PEERS, True),
    ]
    columns = {name: medians(rows, name, ALL_METRICS) for name in names}
    defaults = EskfConfig()
    world = earth_field(
        sim_cfg.magnetometer_field_uT,
        sim_cfg.magnetometer_inclination_rad,
        sim_cfg.magnetometer_declination_rad,
    )
    ratio = {
        f"{metric}_{ours}_over_{peer}": columns[ours][metric] / columns[peer][metric]
        for ours, peer in PAIRS
        for metric in HEADLINE
    }
    for prefix in ("", DISTURBED):
        ratio[f"wall_{prefix}ours_over_{prefix}peer"] = (
            columns[prefix + "ours"]["wall_s"] / columns[prefix + "peer"]["wall_s"]
        )
    for name in ("ours", "ours_no_nhc", "ours_wheels", "peer", "rl_peer"):
        for prefix in ("", DISTURBED):
            ratio[f"yaw_rmse_{prefix}{name}_over_{name}_no_mag"] = (
                columns[prefix + name]["yaw_rmse_deg"] / columns[f"{name}_no_mag"]["yaw_rmse_deg"]
            )
    record = {
        "benchmark": "magnetometer",
        "inputs": {
            **outage_inputs(args, sim_cfg, rows),
            "magnetometer": {
                key: getattr(sim_cfg, key)
                for key in (
                    "magnetometer_rate_hz",
                    "magnetometer_sigma_uT",
                    "magnetometer_field_uT",
                    "magnetometer_inclination_rad",
                    "magnetometer_declination_rad",
                    "magnetometer_hard_iron_uT",
                    "magnetometer_distortion",
                    "magnetometer_anomaly_uT",
                    "magnetometer_anomaly_radius_m",
                )
            },
            "anomalies_disturbed": args.anomalies,
            "ours_magnetometer_config": magnetometer_config(sim_cfg),
            "ours_columns": OURS,
            "peer": "GTSAM CombinedImuFactor + GPSFactor + MagPoseFactorPose3 (2 Hz, "
            "corrected readings, known field, Huber k = 1.345), ISAM2 "
            "(benchmarks/peers/gtsam_kitti.py); peer_no_mag: its 1-Hz graph without it",
            "peer_mag_sigma_uT": peer_mag_sigma(
                sim_cfg.magnetometer_sigma_uT, defaults.magnetometer_heading_floor_rad, world
            ),
            "rl_peer": "robot_localization EKF numpy rewrite (benchmarks/peers/rl_ekf.py) as "
            "benchmarks/robot_localization.py's peer_heading: imu0 rates + accelerations, "
            "odom0 wheel twist, odom1 GNSS pose, imu1 yaw only = tilt-compensated compass "
            "yaw at 2 Hz, variance sigma^2 / H^2 + floor^2; start state = ours_wheels' "
            "initial state; no rejection threshold",
            "wall_time_note": "rl_peer's wall time is a numpy rewrite's: no ratio",
        },
        "ours": columns["ours"],
        "peer": columns["peer"],
        "columns": columns,
        "ratio": ratio,
        "wins": {
            f"{ours}_vs_{peer}": {
                metric: sum(r[ours][metric] < r[peer][metric] for r in rows) for metric in HEADLINE
            }
            for ours, peer in PAIRS
        },
        "accuracy": {name: {k: columns[name][k] for k in ALL_METRICS} for name in names},
        "runs": rows,
        "machine": machine,
    }
    emit_json(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
