"""Command line: ``msf run | eval | simulate | config | posegraph | ranges | nmea | encoders |
lidar-map | magcal``.

Each command parses its arguments, calls the library and prints its result as one JSON
line last. Errors in the input (a bad file, a bad config key) end with a one-line message
naming the problem and exit status 2.
"""

from __future__ import annotations

__all__ = ["main", "build_parser"]

import argparse
import json
import math
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from msf_torch.backend.robust import RobustKernel

NAMED_DATASETS = ("kitti-gtsam",)


def _outage(text: str) -> tuple[float, float]:
    try:
        start, end = (float(x) for x in text.split(":"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected T0:T1 in seconds, got {text!r}") from err
    if end <= start:
        raise argparse.ArgumentTypeError(f"outage end must exceed start, got {text!r}")
    return start, end


def _version() -> str:
    """``msf <msf_torch version> (torch <version>, <device>)``, for ``msf --version``."""
    import torch

    from msf_torch import __version__

    device = "CUDA available" if torch.cuda.is_available() else "CPU only"
    return f"msf {__version__} (torch {torch.__version__}, {device})"


def build_parser() -> argparse.ArgumentParser:
    """The ``msf`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="msf",
        description="msf_torch: multi-sensor state estimation for wheeled robots and vehicles.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run the ESKF front end on a recorded sequence")
    run.add_argument(
        "sequence",
        nargs="*",
        default=[],
        help="path (native .npz / CSV folder, EuRoC folder, KITTI raw drive, ROS bag with "
        "--topics) or a named "
        f"dataset ({', '.join(NAMED_DATASETS)}); default: the bundled sample. Two or more "
        "run as one batch (one config for all) with outputs in OUT/<name>/, runs.csv and a "
        "batch summary",
    )
    run.add_argument(
        "--topics",
        type=Path,
        default=None,
        metavar="ROBOT.yaml",
        help="read SEQUENCE as a ROS bag (rosbag1 .bag or rosbag2 folder) with this robot "
        "config: topics -> sensors, frames, estimator settings",
    )
    run.add_argument(
        "--export",
        type=_exports,
        default=(),
        metavar="FORMATS",
        help="also write the trajectory as kitti (trajectory.kitti + trajectory_times.txt), "
        "rosbag2 (nav_msgs/Odometry in trajectory_rosbag2/), geojson, kml and / or gpx (on "
        "the map, with the GNSS fixes: needs the run's geodetic origin, meta.json "
        "gnss_origin; gpx has UTC times with an absolute time origin), comma separated",
    )
    run.add_argument(
        "--format",
        dest="fmt",
        default=None,
        help="native | npz | csv | euroc | kitti-raw | kitti-gtsam (default: detect)",
    )
    run.add_argument("--config", type=Path, default=None, help="YAML front-end config")
    run.add_argument(
        "--out",
        type=Path,
        default=Path("out"),
        help="output folder (default: ./out; files of an earlier run there that this run "
        "does not rewrite are named on stderr)",
    )
    run.add_argument(
        "--gnss-outage",
        type=_outage,
        default=None,
        metavar="T0:T1",
        help="withhold GNSS fixes between T0 and T1 s from the first sample",
    )
    run.add_argument(
        "--no-slip-detection", action="store_true", help="switch the wheel slip factor off"
    )
    run.add_argument(
        "--sort", action="store_true", help="sort out-of-order timestamps instead of failing"
    )
    run.add_argument("--no-plot", action="store_true", help="skip overview.png")
    run.add_argument(
        "--device",
        type=_device,
        default="cpu",
        help="where the estimator runs: cpu (default), cuda or cuda:N; a batch of many "
        "sequences gains the most on a GPU, one sequence is faster on the CPU",
    )
    _progress_argument(run)
    run.add_argument(
        "--smooth",
        choices=("full", "window"),
        default=None,
        help="smooth the front end's keyframes (full batch or sliding window; settings from "
        "the config's 'smoother:' section); trajectory.tum then holds the smoothed trajectory",
    )
    learned = run.add_mutually_exclusive_group()
    learned.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="CovNet checkpoint that sets the filter's noise (default: "
        "checkpoints/covnet_default.pt when it exists)",
    )
    learned.add_argument(
        "--no-learned",
        action="store_true",
        help="use the config's noise, not the shipped covariance network",
    )

    ev = sub.add_parser(
        "eval", help="ATE and RPE of an estimate against a reference (TUM, ground truth, GNSS)"
    )
    ev.add_argument("estimate", type=Path, help="estimated trajectory (TUM)")
    ev.add_argument(
        "reference",
        type=Path,
        help="reference: a TUM trajectory, or a recorded sequence (native folder / .npz, EuRoC "
        "folder, kitti-gtsam) whose ground truth or GNSS fixes are the reference",
    )
    ev.add_argument(
        "--reference-stream",
        choices=("auto", "ground_truth", "gnss"),
        default="auto",
        help="a sequence's stream to score against (default: the ground truth if it has one, "
        "else the GNSS fixes: positions only, so ATE without RPE)",
    )
    ev.add_argument(
        "--lever-arm",
        type=_triple,
        default=None,
        metavar="X,Y,Z",
        help="score the estimate at this point of the body frame, m (e.g. the GNSS antenna)",
    )
    ev.add_argument(
        "--align",
        choices=("se3", "sim3", "none"),
        default=None,
        help="align the estimate to the reference first: rigid, with scale, or not (default: "
        "none against GNSS fixes, which are the estimator's own world frame, else se3)",
    )
    ev.add_argument("--max-dt", type=_tolerance, default=0.01, help="association tolerance, s")
    ev.add_argument(
        "--sort", action="store_true", help="sort each file's poses by time instead of failing"
    )
    ev.add_argument("--delta", type=float, default=1.0, help="RPE step")
    ev.add_argument("--delta-unit", choices=("frames", "m", "s"), default="frames")
    ev.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="PNG",
        help="write a figure: aligned estimate and reference from above, error over time",
    )

    sim = sub.add_parser("simulate", help="write a simulated labelled wheeled-robot run")
    sim.add_argument("--duration", type=float, default=120.0, help="seconds")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument(
        "--slip-episodes",
        type=int,
        default=None,
        help="default 3; with --weather, drawn from the ground friction of the schedule",
    )
    sim.add_argument(
        "--gnss-outages",
        type=int,
        default=1,
        help="GNSS outages in the run (default 1; 0 for none, e.g. for runs under about 45 s)",
    )
    sim.add_argument(
        "--gnss-velocity",
        action="store_true",
        help="also write the GNSS antenna velocity at the fix times (gnss_velocity.csv, "
        "Doppler-like, sigma 0.05 m/s horizontal, 0.1 m/s up)",
    )
    sim.add_argument(
        "--gnss-heading",
        action="store_true",
        help="also write a dual-antenna GNSS heading at the fix times (gnss_heading.csv: "
        "the body x axis's azimuth clockwise from north, sigma 0.005 rad)",
    )
    sim.add_argument(
        "--magnetometer",
        action="store_true",
        help="also write a 50-Hz three-axis magnetometer (magnetometer.csv, uT, sigma 0.3; "
        "earth field 48 uT, dip 60 deg, declination 0, no iron: the front end's defaults)",
    )
    sim.add_argument(
        "--magnetometer-anomalies",
        type=int,
        default=0,
        metavar="K",
        help="with --magnetometer: K local magnetic anomalies along the route (label "
        "magnetic_anomaly; default 0)",
    )
    sim.add_argument(
        "--weather",
        action="store_true",
        help="apply a random weather schedule (labels weather:<condition>; VO and LiDAR "
        "pose sources, written as poses_vo / poses_lidar)",
    )
    sim.add_argument(
        "--weather-seed",
        type=int,
        default=None,
        help="seed of the weather schedule, slip draw and degradation (default: --seed)",
    )
    sim.add_argument(
        "--out", type=Path, required=True, help="native output: FILE.npz or a folder of CSVs"
    )

    config = sub.add_parser("config", help="check a robot or front-end config YAML")
    config_sub = config.add_subparsers(dest="config_command", required=True)
    check = config_sub.add_parser("check", help="validate FILE; print what it configures")
    check.add_argument("file", type=Path)

    pg = sub.add_parser("posegraph", help="optimise a 2-D or 3-D pose graph (g2o / TORO) by LM")
    pg.add_argument(
        "graph", help="g2o / TORO file (2-D or 3-D), or the name of a graph shipped with gtsam"
    )
    pg.add_argument("--out", type=Path, default=None, help="write the optimised graph (g2o)")
    pg.add_argument(
        "--robust",
        type=_robust,
        default=None,
        metavar="KERNEL[:SCALE]",
        help="robust kernel on every edge: huber, cauchy, geman_mcclure or tukey; scale in "
        "sigmas (default: the kernel's 95%%-efficiency constant, geman_mcclure 1)",
    )
    pg.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="PNG",
        help="write a figure: top and side views before and after, cost per iteration",
    )
    pg.add_argument("--max-iterations", type=_positive_int, default=100, help="most linear solves")
    pg.add_argument(
        "--start",
        choices=("file", "incremental"),
        default="file",
        help="LM from the file's poses (default, GTSAM's start) or, for 2-D graphs, from an "
        "estimate grown --chunk vertices at a time (long loops, landmark runs)",
    )
    pg.add_argument(
        "--chunk", type=_positive_int, default=200, help="vertices per step of --start incremental"
    )
    pg.add_argument(
        "--tolerance",
        type=_tolerance,
        default=1e-5,
        help="stop when a step lowers the cost by at most this fraction (GTSAM's relativeErrorTol)",
    )

    rg = sub.add_parser(
        "ranges",
        help="smooth wheel odometry + anchor ranges (UWB, radio beacons) over a whole run",
    )
    rg.add_argument(
        "run",
        nargs="?",
        default=None,
        choices=("plaza1", "plaza2"),
        help="a real run shipped with gtsam (settings calibrated on the other one); or give "
        "--odometry, --ranges and --anchors",
    )
    rg.add_argument("--odometry", type=Path, help="CSV t,x,y,heading (odometry poses)")
    rg.add_argument("--ranges", type=Path, help="CSV t,anchor,range")
    rg.add_argument(
        "--anchors",
        type=Path,
        help="CSV anchor,x,y (map frame); with --solve-anchors first guesses, or left out",
    )
    rg.add_argument("--truth", type=Path, help="CSV t,x,y reference positions (errors)")
    rg.add_argument("--out", type=Path, default=None, help="folder: trajectory.tum, anchors.csv")
    rg.add_argument("--plot", type=Path, default=None, metavar="PNG", help="write a figure")
    rg.add_argument("--range-sigma", type=_positive_float, default=None, help="m (default 0.3)")
    rg.add_argument("--range-bias", type=_finite_float, default=None, help="m, subtracted")
    rg.add_argument(
        "--robust",
        type=_robust_or_none,
        default="cauchy",
        metavar="KERNEL[:SCALE]|none",
        help="robust kernel on the ranges (default cauchy:2.3849)",
    )
    rg.add_argument(
        "--odometry-noise",
        type=_triple,
        default=None,
        metavar="FWD,LAT,HEADING",
        help="odometry variance per metre travelled: m^2/m, m^2/m, rad^2/m "
        "(default 6e-4,6e-4,5e-5)",
    )
    rg.add_argument(
        "--start", type=_triple, default=None, metavar="X,Y,HEADING", help="start pose (map)"
    )
    rg.add_argument(
        "--solve-anchors",
        action="store_true",
        help="solve for the anchors too (range-only SLAM): the anchors file gives first "
        "guesses; without one the map frame is the odometry's start",
    )
    rg.add_argument(
        "--range-timing",
        choices=("interpolate", "next_pose"),
        default="interpolate",
        help="where a range counts: between the odometry poses around its time (default) or "
        "at the next pose (GTSAM's graph)",
    )

    nm = sub.add_parser(
        "nmea",
        help="convert an NMEA 0183 GNSS log (GGA, GST, RMC, VTG, ZDA, HDT, THS) to a native "
        "gnss.csv, gnss_velocity.csv and gnss_heading.csv",
    )
    _receiver_arguments(
        nm,
        "NMEA log: one sentence per line, optional stamps",
        "the RMC / VTG speed and course over ground",
        "the HDT / THS dual-antenna headings",
    )
    nm.add_argument(
        "--time",
        choices=("auto", "utc", "receive"),
        default="auto",
        help="fix times: UTC from the sentences (UNIX s), the lines' receive stamps, or "
        "receive stamps when every GGA has one (default)",
    )
    nm.add_argument(
        "--quality",
        type=_quality_codes,
        default=(1, 2, 3, 4, 5),
        metavar="Q[,Q...]",
        help="GGA quality codes kept (default 1,2,3,4,5: GPS, DGPS, PPS, RTK fixed, RTK float; "
        "e.g. 4 for RTK-fixed only)",
    )

    ub = sub.add_parser(
        "ubx",
        help="convert a u-blox UBX binary log (NAV-PVT, NAV-RELPOSNED) to a native gnss.csv, "
        "gnss_velocity.csv and gnss_heading.csv with the receiver's accuracy estimates",
    )
    _receiver_arguments(
        ub,
        "UBX binary log (other messages are skipped)",
        "the NAV-PVT Doppler velocities",
        "the NAV-RELPOSNED moving-baseline headings",
    )
    ub.add_argument(
        "--fix-types",
        type=_quality_codes,
        default=(3, 4),
        metavar="F[,F...]",
        help="NAV-PVT fixType values kept (default 3,4: 3-D and GNSS + dead reckoning)",
    )

    en = sub.add_parser(
        "encoders", help="convert wheel-encoder counts (ticks) to a native wheel.csv of speeds"
    )
    en.add_argument("log", type=Path, help="CSV with a header: time (s) and each side's count")
    en.add_argument(
        "--out", type=Path, required=True, help="CSV to write, normally FOLDER/wheel.csv"
    )
    en.add_argument(
        "--ticks-per-rev",
        type=_one_or_two,
        required=True,
        metavar="N[,N]",
        help="counts per wheel revolution (one for both sides, or left,right)",
    )
    en.add_argument(
        "--radius",
        type=_one_or_two,
        required=True,
        metavar="R[,R]",
        help="wheel radius, m (one for both sides, or left,right)",
    )
    en.add_argument(
        "--rollover",
        type=_finite_float,
        default=None,
        help="the count at which the counters wrap (e.g. 65536 for 16 bits); default: none",
    )
    en.add_argument(
        "--columns",
        default="t,left_ticks,right_ticks",
        metavar="T,LEFT,RIGHT",
        help="names of the time, left-count and right-count columns (default "
        "t,left_ticks,right_ticks)",
    )
    en.add_argument("--sort", action="store_true", help="sort rows by time instead of failing")

    lm = sub.add_parser(
        "lidar-map", help="2D LiDAR scan odometry (PLICP) and an occupancy map (PNG + YAML)"
    )
    lm.add_argument("scans", nargs="?", type=Path, default=None, help="scan file (.npz)")
    lm.add_argument("--out", type=Path, required=True, help="output folder")
    lm.add_argument(
        "--simulate",
        choices=("corridor", "warehouse"),
        default=None,
        help="simulate a run in this map instead (written to OUT/scans.npz)",
    )
    lm.add_argument("--seed", type=int, default=0, help="seed of --simulate")
    lm.add_argument("--duration", type=float, default=None, help="seconds of --simulate")
    lm.add_argument("--resolution", type=float, default=0.05, help="map cell size, m")
    lm.add_argument(
        "--identity-guess",
        action="store_true",
        help="start PLICP from identity, not from the scans' wheel odometry",
    )

    mc = sub.add_parser(
        "magcal",
        help="fit the magnetometer's hard and soft iron to a sequence's readings (the sensor "
        "turned through many orientations, or a robot yawing round on level ground) and write "
        "the config keys",
    )
    mc.add_argument(
        "sequence",
        help="recorded sequence with magnetometer readings (native .npz / folder, or a ROS "
        "bag with --topics)",
    )
    mc.add_argument(
        "--topics",
        type=Path,
        default=None,
        metavar="ROBOT.yaml",
        help="read SEQUENCE as a ROS bag with this robot config (its magnetometer sensor; the "
        "readings turned into the body axes, so the fit is the front end's body-frame keys)",
    )
    mc.add_argument(
        "--format",
        dest="fmt",
        default=None,
        help="native | npz | csv | euroc | kitti-raw | kitti-gtsam (default: detect)",
    )
    mc.add_argument(
        "--model",
        choices=("auto", "ellipsoid", "ellipse", "sphere"),
        default="auto",
        help="ellipsoid: hard and soft iron (the sensor turned every way); ellipse: hard and "
        "soft iron in the plane (a robot that only yaws, b_z = 0); sphere: hard iron only; "
        "auto (default): the ellipse when the readings lie in one plane, else the ellipsoid",
    )
    mc.add_argument(
        "--level",
        action="store_true",
        help="a robot yawing on uneven ground: run the front end without the magnetometer "
        "(IMU with GNSS and / or wheels), level the readings with its roll and pitch and fit "
        "the hard and soft iron so that they have one horizontal and one vertical component "
        "(fit_magnetometer_levelled; --model does not apply)",
    )
    mc.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="FILE.yaml",
        help="write magnetometer_hard_iron_uT, magnetometer_soft_iron and "
        "magnetometer_field_uT as a front-end config (for --config, or to copy into one)",
    )
    tn = sub.add_parser(
        "tune",
        help="fit the front end's noise to recorded runs by maximum likelihood of its "
        "innovations (no ground truth needed) and write the config keys",
    )
    tn.add_argument(
        "sequence",
        nargs="+",
        help="recorded runs (native .npz / folder, EuRoC, KITTI raw, kitti-gtsam, or ROS "
        "bags with --topics); one config fits them all",
    )
    tn.add_argument(
        "--topics",
        type=Path,
        default=None,
        metavar="ROBOT.yaml",
        help="read the sequences as ROS bags with this robot config",
    )
    tn.add_argument(
        "--format",
        dest="fmt",
        default=None,
        help="native | npz | csv | euroc | kitti-raw | kitti-gtsam (default: detect)",
    )
    tn.add_argument(
        "--config", type=Path, default=None, help="start config YAML (its noise is the start)"
    )
    tn.add_argument(
        "--params",
        type=lambda text: [p.strip() for p in text.split(",") if p.strip()],
        default=None,
        metavar="P1,P2",
        help="what to tune: gyro_noise_density, accel_noise_density, gyro_bias_rw_density, "
        "accel_bias_rw_density, wheel_speed_sigma_mps, wheel_lateral_sigma_mps, "
        "wheel_yaw_rate_sigma_radps, nhc_sigma_mps, gnss_sigma_scale, pose:<name> (default: "
        "the IMU's white noises and every fused sensor's sigma)",
    )
    tn.add_argument(
        "--piece-s",
        type=_positive_float,
        default=30.0,
        help="the runs are cut into pieces this long, filtered as one batch (s; default 30)",
    )
    tn.add_argument(
        "--burn-in-s",
        type=float,
        default=5.0,
        help="the first seconds of each piece do not count (its initialisation; default 5)",
    )
    tn.add_argument(
        "--max-evaluations",
        type=_positive_int,
        default=100,
        help="most filter runs with gradient (L-BFGS evaluations; default 100; a warning "
        "says when it stopped there still improving)",
    )
    tn.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="FILE.yaml",
        help="write the start config's keys with the tuned values as a front-end config",
    )
    _progress_argument(tn)
    return parser


def _progress_argument(parser: argparse.ArgumentParser) -> None:
    """``--progress auto|on|off``: a progress bar on stderr (auto: when it is a terminal)."""
    parser.add_argument(
        "--progress",
        choices=("auto", "on", "off"),
        default="auto",
        help="progress bar on stderr (auto: when stderr is a terminal)",
    )


def _receiver_arguments(
    parser: argparse.ArgumentParser, log_help: str, velocities: str, headings: str
) -> None:
    """The arguments ``msf nmea`` and ``msf ubx`` share: the log, ``--out``, ``--origin``,
    ``--t0``, ``--no-velocity`` and ``--no-heading`` (``velocities``, ``headings``: what
    ``gnss_velocity.csv`` and ``gnss_heading.csv`` hold)."""
    parser.add_argument("log", type=Path, help=log_help)
    parser.add_argument(
        "--out", type=Path, required=True, help="CSV to write, normally FOLDER/gnss.csv"
    )
    parser.add_argument(
        "--origin",
        type=_triple,
        default=None,
        metavar="LAT,LON,ALT",
        help="ENU origin: degrees, degrees, m above the WGS-84 ellipsoid (default: the "
        "gnss_origin of the folder's meta.json, else the first fix); stored in that meta.json",
    )
    parser.add_argument(
        "--t0", type=_finite_float, default=0.0, help="seconds subtracted from the fix times"
    )
    parser.add_argument(
        "--no-velocity",
        action="store_true",
        help=f"do not write {velocities} as gnss_velocity.csv next to --out (written by "
        "default when the log has them)",
    )
    parser.add_argument(
        "--no-heading",
        action="store_true",
        help=f"do not write {headings} as gnss_heading.csv next to --out (written by default "
        "when the log has them; the baseline goes in the run config: gnss_heading_baseline_m)",
    )


EXPORTS = ("kitti", "rosbag2", "geojson", "kml", "gpx")
"""Extra trajectory formats ``msf run --export`` writes."""


def _exports(text: str) -> tuple[str, ...]:
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    unknown = [x for x in names if x not in EXPORTS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown export {', '.join(unknown) or repr(text)}; choose from {', '.join(EXPORTS)}"
        )
    return names


ROBUST_SCALES = {"huber": 1.345, "cauchy": 2.3849, "geman_mcclure": 1.0, "tukey": 4.6851}
"""Default robust-kernel scales (whitened units): 95% efficiency under Gaussian noise for
Huber, Cauchy and Tukey; 1 for Geman-McClure."""


def _robust(text: str) -> RobustKernel:
    """``KERNEL[:SCALE]`` -> RobustKernel (scale from :data:`ROBUST_SCALES` when omitted)."""
    from msf_torch.backend.robust import RobustKernel

    name, _, scale = text.partition(":")
    if name not in ROBUST_SCALES:
        raise argparse.ArgumentTypeError(
            f"unknown kernel {name!r}; choose one of {', '.join(ROBUST_SCALES)}"
        )
    try:
        return RobustKernel(name, float(scale) if scale else ROBUST_SCALES[name])
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"bad kernel scale in {text!r}: {err}") from err


def _positive_int(text: str) -> int:
    """An integer >= 1 (``--max-iterations``)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def _tolerance(text: str) -> float:
    """A finite number >= 0 (``--tolerance``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def _finite_float(text: str) -> float:
    """A finite number."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _finite_float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _triple(text: str) -> tuple[float, float, float]:
    """Three finite numbers separated by commas."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers A,B,C, got {text!r}")
    return tuple(_finite_float(part) for part in parts)  # type: ignore[return-value]


def _robust_or_none(text: str) -> RobustKernel | None:
    """``none`` or a kernel as :func:`_robust` reads it."""
    return None if text == "none" else _robust(text)


def _load(args, source: str | None) -> tuple[Any, Any, str]:
    """Sequence, config and a label of the input ``source`` (None: the sample) for
    ``msf run``."""
    from msf_torch.backend.window import load_smoother_config
    from msf_torch.frontend.config import load_sequence_config, packaged_config
    from msf_torch.io import load_sequence
    from msf_torch.io.units import check_units
    from msf_torch.runner import DEFAULT_SAMPLE

    if args.topics is not None:
        return _load_bag(args, source)
    if source is None:
        if not DEFAULT_SAMPLE.exists():
            from msf_torch.io.native import write_native
            from msf_torch.sim import sample_slip_config, simulate_run

            write_native(simulate_run(sample_slip_config(), seed=7).sequence, DEFAULT_SAMPLE)
        source = str(DEFAULT_SAMPLE)
    seq = load_sequence(source, fmt=args.fmt, sort=args.sort)
    check_units(seq, source)
    config_path = args.config
    if config_path is None and source in NAMED_DATASETS:
        config_path = packaged_config(source)
    overrides = {}
    if args.no_slip_detection:
        overrides["slip_detection"] = False
    cfg = load_sequence_config(seq.meta, config_path, **overrides)
    if config_path is not None:
        load_smoother_config(config_path)  # a bad smoother: section fails with or without --smooth
    return seq, cfg, source


def _load_bag(args, source: str | None) -> tuple[Any, Any, str]:
    """Sequence and config for ``msf run BAG --topics ROBOT.yaml``."""
    from msf_torch.io.rosbag import read_rosbag
    from msf_torch.io.units import check_units
    from msf_torch.robot.config import load_robot_config

    if source is None:
        raise ValueError("--topics needs the bag to read (msf run BAG --topics ROBOT.yaml)")
    if args.fmt is not None:
        raise ValueError("--format does not apply to a ROS bag read with --topics")
    robot = load_robot_config(args.topics)
    seq = read_rosbag(source, robot.layout, sort=args.sort)
    check_units(seq, source)
    overrides = _config_overrides(args.config)
    if args.no_slip_detection:
        overrides["slip_detection"] = False
    return seq, robot.eskf_config(seq.meta, overrides), source


def _config_overrides(path: Path | None) -> dict[str, Any]:
    """Front-end keys of a ``--config`` YAML (validated), used over a robot config's."""
    if path is None:
        return {}
    from msf_torch.frontend.config import load_config, read_config_keys

    load_config(path)
    values = read_config_keys(path)
    values.pop("smoother", None)
    return values


def _one_or_two(text: str) -> tuple[float, float]:
    """``X`` (both sides) or ``LEFT,RIGHT``: positive finite numbers."""
    parts = [_finite_float(part) for part in text.split(",")]
    if len(parts) not in (1, 2) or not all(x > 0 for x in parts):
        raise argparse.ArgumentTypeError(f"expected X or LEFT,RIGHT (positive), got {text!r}")
    return (parts[0], parts[-1])


def _device(text: str) -> str:
    """``--device cpu|cuda|cuda:N``: a device torch can use here."""
    import torch

    try:
        device = torch.device(text)
    except RuntimeError:
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}") from None
    if device.type == "cpu":
        return "cpu"
    if device.type != "cuda":
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
    if not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(
            f"{text}: this torch ({torch.__version__}) sees no CUDA device"
        )
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise argparse.ArgumentTypeError(
            f"{text}: there are {torch.cuda.device_count()} CUDA device(s), numbered from 0"
        )
    return str(device)


def _quality_codes(text: str) -> tuple[int, ...]:
    """``--quality 4,5``: GGA quality codes 1-9."""
    try:
        codes = tuple(int(part) for part in text.split(","))
    except ValueError:
        codes = ()
    if not codes or not all(1 <= q <= 9 for q in codes):
        raise argparse.ArgumentTypeError(
            f"expected GGA quality codes 1-9 separated by commas, got {text!r}"
        )
    return codes


def _progress_factory(mode: str, unit: str = "epoch"):
    if mode == "off" or (mode == "auto" and not sys.stderr.isatty()):
        return None

    def factory():
        from tqdm import tqdm

        bar = tqdm(total=None, unit=unit, file=sys.stderr, leave=False, mininterval=0.2)

        def update(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        return update, bar.close

    return factory


def _smoother_config(args, source: str | None) -> Any:
    """The ``smoother:`` settings for ``--smooth`` (None without it): from ``--config``, else
    a named dataset's packaged config, else the ``--topics`` robot YAML, else defaults."""
    if args.smooth is None:
        return None
    from msf_torch.backend.window import load_smoother_config
    from msf_torch.frontend.config import packaged_config

    path = args.config
    if path is None and source in NAMED_DATASETS:
        path = packaged_config(source)
    if path is None and args.topics is not None:
        path = args.topics
    return load_smoother_config(path)


def _cmd_run(args) -> dict[str, Any]:
    from msf_torch.runner import RunOptions, run_sequence

    if len(args.sequence) > 1:
        return _cmd_run_batch(args)
    seq, cfg, source = _load(args, args.sequence[0] if args.sequence else None)
    smoother = _smoother_config(args, source)
    learned = _learned(args)
    if learned is not None:
        _check_filter_settings(args, source, learned)
    options = RunOptions(
        out_dir=args.out,
        gnss_outage_s=args.gnss_outage,
        plot=not args.no_plot,
        progress=_progress_factory(args.progress),
        smooth=args.smooth,
        smoother=smoother,
        learned=learned,
        exports=args.export,
        device=args.device,
    )
    summary = run_sequence(seq, cfg, options)
    _notes(summary, "")
    print(f"msf run: outputs in {args.out}", file=sys.stderr)
    return summary


def _notes(summary: dict[str, Any], label: str) -> None:
    """stderr lines on what a run's summary shows a user should know: filled-in IMU
    stretches, divergence resets, no absolute aiding, stale files in the output folder."""
    filled = summary.get("imu_filled_stretches", {})
    if filled.get("count"):
        print(
            f"msf run: {label}{filled['count']} IMU stretch(es), {filled['seconds']:.1f} s in "
            "all, were filled in by the recorder (samples on a straight line); bridged as IMU "
            "gaps (imu_interpolated_min_samples, imu_gap_noise_scale)",
            file=sys.stderr,
        )
    resets = summary.get("divergence_resets")
    if resets:
        first = ", ".join(f"{t:.3f}" for t in summary.get("divergence_first_t_s", []))
        print(
            f"msf run: warning: {label}the filter diverged and was reset {resets} time(s) "
            f"(first at t = {first} s; causes {summary.get('divergence_causes')}): the "
            "estimate is unreliable there; check the input's units and time stamps and the "
            "noise config",
            file=sys.stderr,
        )
    if not summary.get("absolute_aiding", True):
        print(
            f"msf run: note: {label}no GNSS or pose measurements were fused: dead reckoning, "
            "the position drifts without bound",
            file=sys.stderr,
        )
    stale = summary.get("stale_outputs")
    if stale:
        print(
            f"msf run: note: {label}the output folder still holds files of an earlier run that "
            f"this run did not write: {', '.join(stale)}",
            file=sys.stderr,
        )


def _load_with_one_config(args, who: str, apart: str) -> tuple[list[Any], Any]:
    """Every ``args.sequence`` loaded (``_load``) and the config they share; a ValueError
    naming the keys where one differs from the first (``who`` need one config, "``apart``
    one at a time" is the way out)."""
    loaded = [_load(args, source) for source in args.sequence]
    _, cfg, first = loaded[0]
    for _, other, source in loaded[1:]:
        differ = other.differing_keys(cfg)
        if differ:
            raise ValueError(
                f"{who} need one front-end config, but {source} differs from {first} in "
                f"{', '.join(differ)} (each sequence's metadata can set keys the --config "
                f"file leaves out; {apart} one at a time or set those keys)"
            )
    return loaded, cfg


def _cmd_run_batch(args) -> dict[str, Any]:
    """``msf run A B ...``: one batched front-end run (``runner.run_batch``)."""

    from msf_torch.runner import RunOptions, run_batch

    if args.topics is not None:
        raise ValueError("--topics reads one bag at a time (give one SEQUENCE)")
    loaded, cfg = _load_with_one_config(args, "the sequences of one batch", "run them")
    first = loaded[0][2]
    options = RunOptions(
        out_dir=args.out,
        gnss_outage_s=args.gnss_outage,
        plot=not args.no_plot,
        progress=_progress_factory(args.progress),
        smooth=args.smooth,
        smoother=_smoother_config(args, first),
        learned=_learned(args),
        exports=args.export,
        device=args.device,
    )
    summary = run_batch([seq for seq, _, _ in loaded], cfg, options)
    for name in summary["names"]:
        with open(Path(summary["out"]) / name / "summary.json", encoding="utf-8") as handle:
            _notes(json.load(handle), f"{name}: ")
    print(f"msf run: outputs in {args.out}", file=sys.stderr)
    return summary


def _check_filter_settings(args, source: str | None, learned: Any) -> None:
    """Warn (stderr) when the run's config YAML sets other front-end values than the
    checkpoint's training did: the learned scales multiply those values."""
    from msf_torch.frontend.config import packaged_config, read_config_keys
    from msf_torch.learning.inference import filter_settings_mismatch

    if args.topics is not None:  # a bag: the robot YAML's estimator: section, then --config
        from msf_torch.robot.config import load_robot_config

        settings = {**load_robot_config(args.topics).estimator, **_config_overrides(args.config)}
    else:
        path = args.config
        if path is None and source in NAMED_DATASETS:
            path = packaged_config(source)
        settings = {} if path is None else read_config_keys(path)
    differ = filter_settings_mismatch(learned, settings)
    if differ:
        print(
            f"msf run: warning: {learned.path} was trained with other filter settings than "
            f"this run's ({'; '.join(differ)}); its scales multiply them: pass the training's "
            "eskf_config as --config",
            file=sys.stderr,
        )


def _learned(args) -> Any:
    """The CovNet for ``msf run``: ``--checkpoint``, else the shipped one if present."""
    if args.no_learned:
        return None
    from msf_torch.learning.inference import DEFAULT_CHECKPOINT, load_learned

    path = args.checkpoint
    if path is None:
        if not DEFAULT_CHECKPOINT.is_file():
            return None
        path = DEFAULT_CHECKPOINT
    return load_learned(path)


def _cmd_eval(args) -> dict[str, Any]:
    from msf_torch.eval.metrics import evaluate_files

    return evaluate_files(
        args.estimate,
        args.reference,
        align=args.align,
        max_dt=args.max_dt,
        delta=args.delta,
        delta_unit=args.delta_unit,
        plot=args.plot,
        sort=args.sort,
        reference_stream=args.reference_stream,
        lever_arm=args.lever_arm,
    )


def _cmd_simulate(args) -> dict[str, Any]:
    import dataclasses

    import numpy as np

    from msf_torch.io.native import write_native
    from msf_torch.sim import (
        WeatherSchedule,
        apply_weather,
        default_slip_config,
        simulate_run,
        weather_slip_config,
    )

    slip_episodes = 3 if args.slip_episodes is None else args.slip_episodes
    config = default_slip_config(
        duration_s=args.duration,
        slip_episodes=slip_episodes,
        gnss_outage_count=args.gnss_outages,
    )
    if args.magnetometer_anomalies and not args.magnetometer:
        raise ValueError("--magnetometer-anomalies needs --magnetometer")
    config = dataclasses.replace(
        config,
        gnss_velocity=args.gnss_velocity,
        gnss_heading=args.gnss_heading,
        magnetometer=args.magnetometer,
        magnetometer_anomaly_count=args.magnetometer_anomalies,
    )
    summary: dict[str, Any] = {"out": None, "duration_s": args.duration, "seed": args.seed}
    schedule = None
    if args.weather:
        weather_seed = args.seed if args.weather_seed is None else args.weather_seed
        if weather_seed < 0:
            raise ValueError(f"--weather-seed must be >= 0, got {weather_seed}")
        # three independent seeds: schedule, slip draw, degradation
        seeds = [int(x) for x in np.random.SeedSequence([weather_seed, 1]).generate_state(3)]
        schedule = WeatherSchedule.random(args.duration, seeds[0])
        config = weather_slip_config(config, schedule, seeds[1])
        if args.slip_episodes is not None:
            config = dataclasses.replace(config, slip_episodes=args.slip_episodes)
        summary["weather_seed"] = weather_seed
    try:
        run = simulate_run(config, seed=args.seed)
    except ValueError as err:
        raise ValueError(
            f"{err}; here --slip-episodes {config.slip_episodes}, --gnss-outages "
            f"{args.gnss_outages}, --duration {args.duration}"
        ) from None
    sequence = run.sequence
    if schedule is not None:
        wet = apply_weather(run, schedule, seeds[2], pose_source=None)
        sequence = wet.sequence
        summary["weather"] = [
            [round(s.t_start, 3), round(s.t_end, 3), s.condition] for s in schedule.segments
        ]
        summary["pose_sources"] = {
            name: int(stream.mask.sum()) for name, stream in sorted(wet.pose_sources.items())
        }
    summary["out"] = str(write_native(sequence, args.out))
    summary["imu_samples"] = int(sequence.imu.mask.sum())
    if sequence.gnss_velocity is not None:
        summary["gnss_velocities"] = int(sequence.gnss_velocity.mask.sum())
    if sequence.gnss_heading is not None:
        summary["gnss_headings"] = int(sequence.gnss_heading.mask.sum())
    if sequence.magnetometer is not None:
        summary["magnetometer_readings"] = int(sequence.magnetometer.mask.sum())
    summary["slip_episodes"] = [
        [round(e.t_start, 3), round(e.t_end, 3), e.kind] for e in run.slip_episodes
    ]
    return summary


def _cmd_config(args) -> dict[str, Any]:
    """``msf config check FILE``: a robot config (top-level ``sensors``) or a front-end one."""

    from msf_torch.backend.window import load_smoother_config
    from msf_torch.frontend.config import EskfConfig, load_config
    from msf_torch.robot.config import is_robot_config, load_robot_config

    if is_robot_config(args.file):
        robot = load_robot_config(args.file)
        load_smoother_config(args.file)
        return {"ok": True, "kind": "robot", **robot.summary()}
    cfg = load_config(args.file)
    load_smoother_config(args.file)
    changed = {key: getattr(cfg, key) for key in cfg.differing_keys(EskfConfig())}
    return {"ok": True, "kind": "frontend", "file": str(args.file), "estimator": changed}


def _cmd_posegraph(args) -> dict[str, Any]:
    from msf_torch.backend.posegraph import optimize_pose_graph, pose_graph_config
    from msf_torch.io.errors import DataError
    from msf_torch.io.g2o import (
        GTSAM_POSE3_FILES,
        POSE3_TAGS,
        gtsam_pose_graph_path,
        read_pose_graph,
        write_g2o,
    )
    from msf_torch.io.g2o_2d import (
        GTSAM_LANDMARK2_FILES,
        GTSAM_POSE2_FILES,
        POSE2_TAGS,
        pose_graph_kind,
        read_pose_graph_2d,
        write_g2o_2d,
    )

    source = args.graph
    if not Path(source).exists():
        shipped = GTSAM_POSE3_FILES + GTSAM_POSE2_FILES + GTSAM_LANDMARK2_FILES
        named = [n for n in shipped if source in (n, Path(n).stem)]
        if named:
            source = str(gtsam_pose_graph_path(named[0]))
    for option, path in (("--out", args.out), ("--plot", args.plot)):
        if path is not None and path.is_dir():
            raise ValueError(f"{option} {path} is a folder; give a file name")
    kind = pose_graph_kind(source)
    if kind is None:
        raise DataError(
            source,
            f"no pose-graph records: neither 2-D ({', '.join(sorted(POSE2_TAGS))}) nor 3-D "
            f"({', '.join(sorted(POSE3_TAGS))}) tags (tags are case-sensitive)",
        )
    planar = kind == 2
    if args.start == "incremental" and not planar:
        raise ValueError("--start incremental is for 2-D graphs; this file holds a 3-D graph")
    graph = read_pose_graph_2d(source) if planar else read_pose_graph(source)
    config = pose_graph_config(
        max_iterations=args.max_iterations, relative_tolerance=args.tolerance, planar=planar
    )
    factory = _progress_factory("auto", unit="vertex") if args.start == "incremental" else None
    update, close = factory() if factory is not None else (None, None)
    try:
        result = optimize_pose_graph(
            graph,
            robust=args.robust,
            config=config,
            start=args.start,
            chunk=args.chunk,
            progress=update,
        )
    finally:
        if close is not None:
            close()
    if not math.isfinite(result.initial_cost):
        raise DataError(
            source,
            f"the cost at the initial poses is not finite ({result.initial_cost}): a vertex or "
            "edge value is too large (positions and translations are in metres)",
        )
    summary: dict[str, Any] = {
        "graph": source,
        "dimension": 2 if planar else 3,
        "poses": graph.num_vertices,
        "edges": graph.num_edges,
        **({"landmarks": graph.num_landmarks} if planar and graph.num_landmarks else {}),
        **({"sightings": graph.num_observations} if planar and graph.num_observations else {}),
        "robust": None if args.robust is None else [args.robust.name, args.robust.scale],
        "initial_cost": result.initial_cost,
        **(
            {"start": "incremental", "chunk": args.chunk, "start_cost": result.start_cost}
            if args.start == "incremental"
            else {}
        ),
        "final_cost": result.final_cost,
        "iterations": result.iterations,
        "seconds": result.seconds,
        "status": result.status,
    }
    if args.out is not None:
        summary["out"] = str((write_g2o_2d if planar else write_g2o)(args.out, result.graph))
    if args.plot is not None:
        from msf_torch.eval.plots import pose_graph_figure

        summary["plot"] = str(
            pose_graph_figure(
                args.plot,
                graph.positions,
                result.graph.positions,
                graph.edge_index,
                result.log,
                result.start_cost,
                title=Path(source).name
                + (
                    f" (final LM from the incremental start, chunk {args.chunk}; file's start "
                    f"cost {result.initial_cost:.4g})"
                    if args.start == "incremental"
                    else ""
                ),
                landmarks=(graph.landmark_positions, result.graph.landmark_positions)
                if planar and graph.num_landmarks
                else None,
            )
        )
    return summary


def _cmd_ranges(args) -> dict[str, Any]:
    import torch

    from msf_torch.backend.range2d import OdometryNoise
    from msf_torch.backend.range_smoother import (
        RangeSmootherSettings,
        calibrate_from_truth,
        smooth_ranges,
    )
    from msf_torch.io.plaza import load_plaza
    from msf_torch.io.ranges import read_range_run, write_anchors
    from msf_torch.io.tum import write_tum
    from msf_torch.types import Trajectory

    files = (args.odometry, args.ranges, args.anchors)
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} is a file; give a folder")
    if args.plot is not None and args.plot.is_dir():
        raise ValueError(f"--plot {args.plot} is a folder; give a file name")
    if args.run is not None and any(f is not None for f in (*files, args.truth)):
        raise ValueError("give a shipped run or the CSV files, not both")
    settings = RangeSmootherSettings(
        solve_anchors=args.solve_anchors, range_timing=args.range_timing
    )
    if args.run is not None:
        name = {"plaza1": "Plaza1", "plaza2": "Plaza2"}[args.run]
        other = "Plaza2" if name == "Plaza1" else "Plaza1"
        run = load_plaza(name)
        settings = calibrate_from_truth(load_plaza(other), settings)
        settings.start = run.truth[0]
    elif (
        args.odometry is None
        or args.ranges is None
        or (args.anchors is None and not args.solve_anchors)
    ):
        raise ValueError(
            "give --odometry, --ranges and --anchors (--anchors may be left out with "
            "--solve-anchors), or a shipped run name"
        )
    else:
        run = read_range_run(*files, truth=args.truth)
    if args.range_sigma is not None:
        settings.range_sigma_m = args.range_sigma
    if args.range_bias is not None:
        settings.range_bias_m = args.range_bias
    settings.kernel = args.robust
    if args.odometry_noise is not None:
        forward, lateral, heading = args.odometry_noise
        settings.odometry_noise = OdometryNoise(forward=forward, lateral=lateral, heading=heading)
    if args.start is not None:
        settings.start = torch.tensor(args.start, dtype=torch.float64)
    result = smooth_ranges(run, settings)
    summary: dict[str, Any] = {
        "run": run.name,
        "poses": int(run.pose_t.shape[0]),
        "ranges": int(run.ranges.shape[0]),
        "anchors": int(run.anchors.shape[0]),
        "settings": {
            "range_sigma_m": settings.range_sigma_m,
            "range_bias_m": settings.range_bias_m,
            "robust": None
            if settings.kernel is None
            else [settings.kernel.name, settings.kernel.scale],
            "odometry_noise": [
                settings.odometry_noise.forward,
                settings.odometry_noise.lateral,
                settings.odometry_noise.heading,
            ],
            "solve_anchors": settings.solve_anchors,
            "range_timing": settings.range_timing,
        },
        **result.summary(),
        "meta": run.meta,
    }
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        poses = result.poses
        half = 0.5 * poses[:, 2]
        zero = torch.zeros_like(half)
        trajectory = Trajectory(
            t=run.pose_t[None],
            position=torch.stack((poses[:, 0], poses[:, 1], zero), -1)[None],
            quaternion=torch.stack((torch.cos(half), zero, zero, torch.sin(half)), -1)[None],
            mask=torch.ones(1, poses.shape[0], dtype=torch.bool),
        )
        summary["files"] = {"trajectory": str(write_tum(trajectory, args.out / "trajectory.tum"))}
        if settings.solve_anchors:
            summary["files"]["anchors"] = str(
                write_anchors(args.out / "anchors.csv", run.anchor_ids, result.anchors)
            )
    if args.plot is not None:
        from msf_torch.eval.plots import range_run_figure

        summary["plot"] = str(range_run_figure(args.plot, run, result.poses, result.anchors))
    return summary


def _cmd_nmea(args) -> dict[str, Any]:
    """``msf nmea LOG --out FOLDER/gnss.csv``: GGA fixes, RMC / VTG velocities and HDT / THS
    headings."""
    import numpy as np

    from msf_torch.io.errors import DataError
    from msf_torch.io.nmea import read_nmea

    log = read_nmea(args.log, qualities=args.quality, time=args.time)
    if len(log) == 0:
        raise DataError(args.log, f"no fix kept (counts: {log.counts})")
    unix = log.time_source == "receive" or log.dated
    summary = _write_receiver_folder(
        args, log, log.velocity_t.size > 0, log.heading_t.size > 0, unix
    )
    given = np.isfinite(log.sigma_enu).all(axis=1)
    return {
        "log": str(args.log),
        **summary,
        "fixes": len(log),
        "fixes_with_sigma": int(given.sum()),
        "velocities": int(log.velocity_t.size),
        "headings": int(log.heading_t.size),
        "counts": log.counts,
        "time_source": log.time_source,
        "median_sigma_enu_m": np.median(log.sigma_enu[given], axis=0).tolist()
        if given.any()
        else None,
        "geoid_separation_missing": log.geoid_separation_missing,
    }


def _cmd_ubx(args) -> dict[str, Any]:
    """``msf ubx LOG --out FOLDER/gnss.csv``: NAV-PVT fixes and velocities and NAV-RELPOSNED
    headings, with sigmas."""
    import numpy as np

    from msf_torch.io.errors import DataError
    from msf_torch.io.ubx import read_ubx

    log = read_ubx(args.log, fix_types=args.fix_types)
    if len(log) == 0:
        raise DataError(args.log, f"no NAV-PVT solution kept (counts: {log.counts})")
    summary = _write_receiver_folder(args, log, True, log.heading_t.size > 0, True)
    heading_sigma = log.heading_sigma_rad[np.isfinite(log.heading_sigma_rad)]
    return {
        "log": str(args.log),
        **summary,
        "fixes": len(log),
        "velocities": len(log),
        "headings": int(log.heading_t.size),
        "counts": log.counts,
        "rtk_fixed": int((log.carrier == 2).sum()),
        "rtk_float": int((log.carrier == 1).sum()),
        "median_sigma_enu_m": np.median(log.sigma_enu, axis=0).tolist(),
        "median_speed_sigma_mps": float(np.median(log.velocity_sigma[:, 0])),
        "median_heading_sigma_rad": float(np.median(heading_sigma)) if heading_sigma.size else None,
    }


def _write_receiver_folder(
    args, log, has_velocities: bool, has_headings: bool, unix_times: bool
) -> dict[str, Any]:
    """Write a receiver log's ``gnss.csv`` (``args.out``), ``gnss_velocity.csv`` and
    ``gnss_heading.csv`` beside it, and its ``gnss_origin`` / ``time_origin_ns`` into the
    folder's ``meta.json`` (``msf nmea``, ``msf ubx``). ``log`` has ``to_gnss(origin, t0)``,
    ``to_gnss_velocity(t0)`` and ``to_gnss_heading(t0)``; ``unix_times``: its times are UNIX
    seconds. Returns the summary's entries about what was written."""
    from msf_torch.io.native import (
        store_gnss_origin,
        store_time_origin,
        stored_gnss_origin,
        stored_time_origin,
        write_stream_csv,
    )

    if args.out.is_dir():
        raise ValueError(f"--out {args.out} is a folder; give a file name (FOLDER/gnss.csv)")
    folder = args.out.parent
    stored = stored_gnss_origin(folder)
    wanted = args.origin if args.origin is not None else stored
    origin_from = "--origin" if args.origin is not None else "meta.json" if stored else "first fix"
    gnss, origin = log.to_gnss(origin=wanted, t0=args.t0)
    if stored is not None and list(origin) != stored:
        warnings.warn(
            f"{folder / 'meta.json'}: gnss_origin changed from {stored} to {list(origin)}; "
            "other tables of this folder in the old ENU frame (ground_truth.csv) no longer "
            "match gnss.csv",
            stacklevel=2,
        )
    folder.mkdir(parents=True, exist_ok=True)
    out = write_stream_csv(args.out, "gnss", gnss)
    written: dict[str, str | None] = {}
    for name, wanted, stream in (
        ("velocity", not args.no_velocity and has_velocities, log.to_gnss_velocity),
        ("heading", not args.no_heading and has_headings, log.to_gnss_heading),
    ):
        table = folder / f"gnss_{name}.csv"
        written[name] = None
        if wanted:
            written[name] = str(write_stream_csv(table, f"gnss_{name}", stream(t0=args.t0)))
        elif table.exists():
            warnings.warn(
                f"{table} (not from this conversion) is left as it is: msf run reads it",
                stacklevel=2,
            )
    meta = store_gnss_origin(folder, origin)
    # the folder's t = 0 in UNIX ns, when the fix times are UNIX times (dated UTC, or the
    # logging host's receive stamps): GPX exports get UTC times from it
    time_origin = None
    if unix_times:
        time_origin = round(args.t0 * 1e9)
        stored_origin = stored_time_origin(folder)
        if stored_origin is not None and stored_origin != time_origin:
            warnings.warn(
                f"{meta}: time_origin_ns changed from {stored_origin} to {time_origin}",
                stacklevel=2,
            )
        store_time_origin(folder, time_origin)
    t = gnss.t[0].numpy()
    return {
        "out": str(out),
        "velocity_out": written["velocity"],
        "heading_out": written["heading"],
        "origin": list(origin),
        "origin_from": origin_from,
        "time_origin_ns": time_origin,
        "meta": str(meta),
        "t_range_s": [float(t[0]), float(t[-1])],
    }


def _cmd_encoders(args) -> dict[str, Any]:
    import numpy as np

    from msf_torch.io.encoders import read_encoder_counts, write_wheel_csv

    if args.out.is_dir():
        raise ValueError(f"--out {args.out} is a folder; give a file name (FOLDER/wheel.csv)")
    columns = [name.strip() for name in args.columns.split(",")]
    log = read_encoder_counts(args.log, columns, rollover=args.rollover, sort=args.sort)
    wheel = log.wheel_speeds(args.ticks_per_rev, args.radius)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    out = write_wheel_csv(args.out, wheel)
    step = float(np.median(np.diff(log.t)))
    resolution = [
        2 * math.pi * radius / (count * step)
        for radius, count in zip(args.radius, args.ticks_per_rev, strict=True)
    ]
    return {
        "log": str(args.log),
        "out": str(out),
        "readings": int(log.t.size),
        "samples": int(wheel.t.shape[1]),
        "counts": log.counts,
        "t_range_s": [float(wheel.t[0, 0]), float(wheel.t[0, -1])],
        "median_step_s": step,
        "speed_resolution_mps": resolution,
        "max_abs_speed_mps": [
            float(wheel.left_speed.abs().max()),
            float(wheel.right_speed.abs().max()),
        ],
    }


def _cmd_lidar_map(args) -> dict[str, Any]:
    from msf_torch.io.scans import read_scans, write_scans
    from msf_torch.lidar.grid import GridConfig
    from msf_torch.lidar.mapping import map_from_scans

    if (args.scans is None) == (args.simulate is None):
        raise ValueError("give a scan file or --simulate MAP (one of the two)")
    path = args.scans
    if args.simulate is not None:
        from msf_torch.sim.lidar2d import corridor_map, simulate_lidar_run, warehouse_map

        builder = corridor_map if args.simulate == "corridor" else warehouse_map
        run = simulate_lidar_run(builder(), seed=args.seed, duration_s=args.duration)
        path = write_scans(
            args.out / "scans.npz", run.t, run.angles, run.ranges, run.odometry, run.truth
        )
    summary = map_from_scans(
        read_scans(path),
        args.out,
        GridConfig(resolution_m=args.resolution),
        use_odometry=not args.identity_guess,
    )
    return {"scans_file": str(path), **summary}


def _front_end_tilt(seq: Any, robot: Any, times: Any, source: str) -> tuple[Any, Any]:
    """Roll and pitch (M, 2) rad of the front end run on ``seq`` without its magnetometer
    (``robot``'s config for a bag, else :func:`load_sequence_config`), interpolated at the
    magnetometer times ``times`` (N,) s inside the run's span, and that mask (N,) bool, for
    ``msf magcal --level``. DataError when the sequence has no GNSS or wheels."""
    import dataclasses

    import numpy as np
    import torch

    from msf_torch.frontend.config import load_sequence_config
    from msf_torch.frontend.eskf import run_eskf
    from msf_torch.io.errors import DataError

    if seq.gnss is None and seq.wheel is None:
        raise DataError(
            source,
            "--level needs the front end's roll and pitch: IMU with GNSS and / or wheel "
            "odometry (gnss.csv, wheels.csv), not IMU alone",
        )
    cfg = load_sequence_config(seq.meta) if robot is None else robot.eskf_config(seq.meta, {})
    result = run_eskf(dataclasses.replace(seq, magnetometer=None), cfg)
    t = result.t[0].detach().to(device="cpu", dtype=torch.float64).numpy()
    rotation = result.rotation[0].detach().to(device="cpu", dtype=torch.float64).numpy()
    roll = np.unwrap(np.arctan2(rotation[:, 2, 1], rotation[:, 2, 2]))
    pitch = -np.arcsin(np.clip(rotation[:, 2, 0], -1.0, 1.0))
    inside = (times >= t[0]) & (times <= t[-1])
    if inside.sum() < 10:
        raise DataError(
            source,
            f"only {int(inside.sum())} magnetometer readings lie within the front end's "
            f"run ({t[0]:.3f}-{t[-1]:.3f} s)",
        )
    return np.column_stack(
        (np.interp(times[inside], t, roll), np.interp(times[inside], t, pitch))
    ), inside


def _cmd_magcal(args) -> dict[str, Any]:
    """``msf magcal SEQUENCE``: the magnetometer calibration of a sequence's readings
    (:func:`msf_torch.sensors.magnetometer_calibration.fit_magnetometer`); ``--model auto``
    fits the ellipse to planar readings (a robot that only yaws), else the ellipsoid;
    ``--level`` levels them with the front end's roll and pitch
    (:func:`~msf_torch.sensors.magnetometer_calibration.fit_magnetometer_levelled`)."""
    import re

    import numpy as np
    import torch

    from msf_torch.io import load_sequence
    from msf_torch.io.atomic import atomic_write
    from msf_torch.io.errors import DataError
    from msf_torch.sensors.magnetometer_calibration import (
        PLANAR_THICKNESS_RATIO,
        fit_magnetometer,
        fit_magnetometer_levelled,
        planarity,
    )

    robot = None
    if args.topics is not None:
        if args.fmt is not None:
            raise ValueError("--format does not apply to a ROS bag read with --topics")
        from msf_torch.io.rosbag import read_rosbag
        from msf_torch.robot.config import load_robot_config

        robot = load_robot_config(args.topics)
        seq = read_rosbag(args.sequence, robot.layout)
    else:
        seq = load_sequence(args.sequence, fmt=args.fmt)
    mag = seq.magnetometer
    if mag is None or not bool(mag.mask.any()):
        raise DataError(
            args.sequence, "no magnetometer readings (native: magnetometer.csv or magnetometer/*)"
        )
    field = mag.field[0][mag.mask[0]].detach().to(device="cpu", dtype=torch.float64).numpy()
    model, reason = args.model, f"--model {args.model}"
    if args.level:
        if args.model != "auto":
            raise ValueError("--level fits its own model: leave out --model")
        times = mag.t[0][mag.mask[0]].detach().to(device="cpu", dtype=torch.float64).numpy()
        tilt, inside = _front_end_tilt(seq, robot, times, args.sequence)
        field = field[inside]
        model = "levelled"
        reason = (
            f"--level: {int(inside.sum())} readings levelled with the roll and pitch of the "
            "front end run without the magnetometer"
            + (
                f" ({int((~inside).sum())} outside its time span left out)"
                if not inside.all()
                else ""
            )
        )
    elif model == "auto":
        planar, thickness, noise = planarity(field)
        model = "ellipse" if planar else "ellipsoid"
        reason = (
            f"auto: the readings lie in one plane ({thickness:.3g} uT thick off it, <= "
            f"{PLANAR_THICKNESS_RATIO:g} x their noise {noise:.3g} uT: a robot that only yaws)"
            if planar
            else f"auto: the readings are not planar ({thickness:.3g} uT thick off their "
            f"plane, > {PLANAR_THICKNESS_RATIO:g} x their noise {noise:.3g} uT)"
        )
    try:
        cal = (
            fit_magnetometer_levelled(field, tilt)
            if args.level
            else fit_magnetometer(field, model=model)
        )
    except ValueError as err:  # the library's advice in the command's words
        raise ValueError(
            re.sub(r'model="(\w+)"', r"--model \1", str(err))
            + (
                f" ({reason}, so the {model} was tried)"
                if args.model == "auto" and not args.level
                else ""
            )
        ) from None
    if not 10.0 <= cal.field_uT <= 100.0:
        warnings.warn(
            f"the fitted field {cal.field_uT:.4g} uT is far from the earth's 25-65 uT: are the "
            "readings in microtesla (1 gauss = 100 uT, 1 T = 1e6 uT)?",
            stacklevel=2,
        )
    summary = {
        "sequence": str(args.sequence),
        "model": cal.model,
        "model_reason": reason,
        "hard_iron_uT": cal.hard_iron.tolist(),
        "soft_iron": cal.soft_iron.reshape(-1).tolist(),
        "field_uT": cal.field_uT,
        "residual_rms_uT": cal.residual_rms_uT,
        "raw_norm_std_uT": float(np.linalg.norm(field, axis=1).std()),
        "corrected_norm_std_uT": float(np.linalg.norm(cal.correct(field), axis=1).std()),
        "coverage": cal.coverage,
        "samples": cal.samples,
    }
    if args.out is not None:

        def numbers(values: list[float]) -> str:
            return ", ".join(map(repr, values))

        with atomic_write(args.out) as handle:
            handle.write(
                f"# msf magcal: {cal.model} fit of {cal.samples} magnetometer readings of "
                f"{args.sequence} ({reason})\n# coverage {cal.coverage:.3f}, residual RMS "
                f"{cal.residual_rms_uT:.3f} uT; a front-end config (--config)\n"
                f"magnetometer_hard_iron_uT: [{numbers(summary['hard_iron_uT'])}]\n"
                f"magnetometer_soft_iron: [{numbers(summary['soft_iron'])}]\n"
                f"magnetometer_field_uT: {cal.field_uT!r}\n"
            )
        summary["config_file"] = str(args.out)
    return summary


def _cmd_tune(args) -> dict[str, Any]:
    """``msf tune RUN [RUN ...]``: the noise of the front end fitted to the runs by
    maximum likelihood of its innovations (:func:`msf_torch.frontend.tuning.tune_noise`);
    ``--out`` writes the start config with the tuned values."""
    import time

    import yaml

    from msf_torch.frontend.config import read_config_keys
    from msf_torch.frontend.tuning import tune_noise
    from msf_torch.io.atomic import atomic_write

    args.sort, args.no_slip_detection = False, False
    loaded, cfg = _load_with_one_config(args, "the runs tuned together", "tune them")
    factory = _progress_factory(args.progress, unit="evaluation")
    update, close = factory() if factory is not None else (None, None)
    start = time.perf_counter()
    try:
        result = tune_noise(
            [seq for seq, _, _ in loaded],
            cfg,
            args.params,
            piece_s=args.piece_s,
            burn_in_s=args.burn_in_s,
            max_evaluations=args.max_evaluations,
            progress=update,
        )
    finally:
        if close is not None:
            close()
    wall = time.perf_counter() - start
    if result.at_bound:
        warnings.warn(
            f"{', '.join(result.at_bound)} ended at the bound (x100 or /100 of the start): "
            "the runs want it further, or cannot see it (a sensor that never disagrees, "
            "e.g. a simulated one without that noise); check before using it",
            stacklevel=2,
        )
    if not result.converged:
        warnings.warn(
            f"stopped at --max-evaluations {args.max_evaluations} while still improving: the "
            "values may move further with more",
            stacklevel=2,
        )
    summary: dict[str, Any] = {
        "sequences": list(args.sequence),
        "pieces": result.pieces,
        "piece_s": result.piece_s,
        "burn_in_s": result.burn_in_s,
        "parameters": result.parameters,
        "at_bound": result.at_bound,
        "nll_per_measurement_initial": result.nll_initial,
        "nll_per_measurement_final": result.nll_final,
        "mean_nis": {k: list(v) for k, v in result.mean_nis.items()},
        "accepted": {k: list(v) for k, v in result.accepted.items()},
        "evaluations": result.evaluations,
        "converged": result.converged,
        "wall_s": wall,
    }
    if args.out is not None:
        keys: dict[str, Any] = {} if args.config is None else read_config_keys(args.config)
        for name in result.parameters:
            if name.startswith("pose:"):
                keys["pose_source_variance_scale"] = dict(result.config.pose_source_variance_scale)
            else:
                keys[name] = getattr(result.config, name)
        header = (
            f"# msf tune: noise fitted by maximum likelihood of the innovations of "
            f"{', '.join(map(str, args.sequence))}\n# ({result.evaluations} evaluations; "
            f"negative log-likelihood per measurement {result.nll_initial:.4g} -> "
            f"{result.nll_final:.4g})"
            + (f"; the other keys as in {args.config}" if args.config is not None else "")
            + "\n"
        )
        with atomic_write(args.out) as handle:
            handle.write(header + yaml.safe_dump(keys, sort_keys=False))
        summary["config_file"] = str(args.out)
    return summary


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``msf`` console script; returns the exit status."""
    from msf_torch.io.errors import DataError, MissingExtraError

    args = build_parser().parse_args(argv)
    commands = {
        "run": _cmd_run,
        "eval": _cmd_eval,
        "simulate": _cmd_simulate,
        "posegraph": _cmd_posegraph,
        "lidar-map": _cmd_lidar_map,
        "ranges": _cmd_ranges,
        "nmea": _cmd_nmea,
        "ubx": _cmd_ubx,
        "encoders": _cmd_encoders,
        "config": _cmd_config,
        "magcal": _cmd_magcal,
        "tune": _cmd_tune,
    }
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line(args.command)
            result = commands[args.command](args)
    except (DataError, MissingExtraError, ValueError, FileNotFoundError) as err:
        print(f"msf {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        return _interrupted(args, err)
    print(json.dumps(result, default=float))
    return 0


def _warning_line(command: str):
    """A ``warnings.showwarning`` that prints one ``msf COMMAND: warning: ...`` line on
    stderr (no source location: the message names the file and what was skipped)."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"msf {command}: warning: {message}", file=sys.stderr)

    return show


INTERRUPTED_STATUS = 130
"""Exit status after Ctrl-C (SIGINT), as shells report it (128 + 2)."""


def _interrupted(args, err: KeyboardInterrupt) -> int:
    """Say where an interrupted command stopped (stderr) and print its partial summary, if
    it wrote one (``msf run``: ``runner.RunInterrupted``)."""
    summary = getattr(err, "summary", None)
    if summary is None:
        print(f"msf {args.command}: interrupted (no partial output)", file=sys.stderr)
        return INTERRUPTED_STATUS
    stop = summary["interrupted"]
    print(
        f"msf {args.command}: interrupted in the {stop['stage']} at t = {stop['t_s']:.3f} s "
        f"({stop['t_from_start_s']:.3f} s after the first IMU sample; epoch "
        f"{stop['epochs_done']} of {stop['epochs_total']}); partial outputs in {args.out}",
        file=sys.stderr,
    )
    print(json.dumps(summary, default=float))
    return INTERRUPTED_STATUS


if __name__ == "__main__":
    raise SystemExit(main())
