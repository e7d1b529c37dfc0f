"""ESKF consistency: NEES of the 15-dim error over Monte-Carlo runs (acceptance).

20 simulated runs (seeds 100..119, 40 s, IMU + wheel + GNSS) with the simulator's
unmodelled effects switched off (no wheel scale error, ideal tachometer, no slip) and the
filter's noise set to the simulator's (IMU densities from the run's metadata, wheel sigmas =
``wheel_speed_noise_mps``, GNSS sigmas from the fixes). The average NEES over runs must lie
inside the two-sided 95% chi-square interval at >= 90% of the epochs after a 5 s transient
(the initial yaw, roll/pitch and position come from the first seconds of data).

The error is measured in the filter's own coordinates, the right-invariant error of
``geometry.invariant`` against the invariant covariance (``eval.nees.navigation_errors``).
The conventional additive error agrees to first order only: the wheels pin the body
velocity to millimetres per second, and a heading error ``psi`` puts ``|v| psi^2 / 2`` (about
2 mm/s at 1.5 m/s and 0.05 rad) into the conventional velocity error, which no linear map of
the covariance holds. Over 800 runs (seeds 100-899) random 20-run sets pass the
epoch-fraction test 67 % of the time in invariant coordinates (``per_run_nees``,
``subset_pass_rate``; 65 % with the former constant 0.05-rad initial yaw sigma, recorded
then as 63 %, and 34 % in conventional ones; an ideal consistent filter with errors as
correlated in time: 83 %).

``nees_consistency`` is importable for longer studies, e.g.::

    import sys; sys.path.insert(0, "tests/frontend")
    from test_eskf_nees import nees_consistency
    report = nees_consistency(seeds=range(100, 200), duration_s=120.0)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np
import torch

from msf_torch.eval.nees import average_nees, chi2_interval, navigation_errors, nees
from msf_torch.frontend.config import EskfConfig, config_for_sequence
from msf_torch.frontend.eskf import run_eskf
from msf_torch.frontend.init import initial_state
from msf_torch.geometry import so3
from msf_torch.sim.wheeled import SimConfig, simulate_run
from msf_torch.types import NavState, batch_sequences

COMPONENTS = {"position": 0, "velocity": 3, "attitude": 6, "gyro_bias": 9, "accel_bias": 12}


def consistent_sim_config(duration_s: float = 40.0, **overrides) -> SimConfig:
    """A simulator setting without effects the filter does not model."""
    return SimConfig(
        duration_s=duration_s,
        wheel_scale_sigma=0.0,
        encoder_ticks_per_rev=None,
        slip_episodes=0,
        gnss_outage_count=0,
        **overrides,
    )


def matched_filter_config(sim: SimConfig, meta: dict) -> EskfConfig:
    """The filter configuration whose noise equals the simulator's."""
    base = EskfConfig(
        # the forward speed is the mean of two wheels with independent noise
        wheel_speed_sigma_mps=sim.wheel_speed_noise_mps / 2**0.5,
        # the simulated robot never slides sideways or lifts: the lateral / vertical rows
        # are exact, so their matched sigma is (nearly) zero
        wheel_lateral_sigma_mps=1e-3,
        wheel_track_m=sim.wheel_track_m,
        gnss_lever_arm_m=list(sim.gnss_lever_arm_m),
        init_gyro_bias_sigma_radps=sim.imu_noise.gyro_bias_sigma0,
        init_accel_bias_sigma_mps2=sim.imu_noise.accel_bias_sigma0,
        slip_detection=False,
        gate_probability=1.0,
    )
    return config_for_sequence(base, meta, explicit=set())


@dataclasses.dataclass
class NeesReport:
    """Average NEES over runs per epoch and its test against the chi-square interval.

    Attributes:
        t: (E,) epoch times, s (common to all runs).
        anees: (E,) average 15-dim NEES over runs.
        components: name -> (E,) average 3-dim NEES of one block (its own marginal).
        bounds: two-sided interval of the 15-dim average, (low, high).
        fraction_inside: fraction of epochs after ``skip_s`` inside ``bounds``.
        fraction_below, fraction_above: the same for below / above.
        component_fraction: name -> fraction of epochs of the block's 3-dim ANEES inside its
            own interval ``chi2_interval(3, n_runs)``.
        n_runs, skip_s.
    """

    t: np.ndarray
    anees: np.ndarray
    components: dict[str, np.ndarray]
    bounds: tuple[float, float]
    fraction_inside: float
    fraction_below: float
    fraction_above: float
    component_fraction: dict[str, float]
    n_runs: int
    skip_s: float

    def summary(self) -> str:
        after = self.t >= self.t[0] + self.skip_s
        lines = [
            f"{self.n_runs} runs, epochs after {self.skip_s} s: {int(after.sum())}; "
            f"15-dim ANEES inside [{self.bounds[0]:.2f}, {self.bounds[1]:.2f}] at "
            f"{100 * self.fraction_inside:.1f}% (below {100 * self.fraction_below:.1f}%, "
            f"above {100 * self.fraction_above:.1f}%); median {np.median(self.anees[after]):.2f}"
        ]
        low3, high3 = chi2_interval(3, self.n_runs)
        for name, values in self.components.items():
            lines.append(
                f"  {name:10s} 3-dim ANEES median {np.median(values[after]):7.2f} "
                f"(interval [{low3:.2f}, {high3:.2f}], inside "
                f"{100 * self.component_fraction[name]:.1f}%)"
            )
        return "\n".join(lines)


def nees_consistency(
    seeds: Iterable[int] = range(100, 120),
    duration_s: float = 40.0,
    skip_s: float = 5.0,
    prob: float = 0.95,
    sim_overrides: dict | None = None,
    cfg_overrides: dict | None = None,
    start_from_truth: bool = False,
    coordinates: str = "invariant",
) -> NeesReport:
    """Simulate one run per seed, filter them as one batch, and score the NEES.

    The error is truth against estimate at the epoch times (IMU sample times), in
    ``coordinates`` (``eval.nees.navigation_errors``): ``"invariant"``, the right-invariant
    error the filter keeps its covariance in, or ``"conventional"`` (``p_t - p``,
    ``v_t - v``, ``Log(R^T R_t)``, ``b_t - b`` against the reported covariance).
    """
    seeds = list(seeds)
    fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
    sim = consistent_sim_config(duration_s, **(sim_overrides or {}))
    runs = [simulate_run(sim, seed=s) for s in seeds]
    cfg = matched_filter_config(sim, runs[0].sequence.meta)
    if cfg_overrides:
        cfg = cfg.replace(**cfg_overrides)
    batch = batch_sequences([r.sequence for r in runs])
    initial = None
    if start_from_truth:
        # the classic Monte-Carlo consistency check: the filter starts at the truth with the
        # covariance the initialiser would use, which isolates propagation and updates
        # from the initialiser's own (non-Gaussian) errors
        start = NavState(*(torch.cat([getattr(r.truth, n)[:, 0] for r in runs]) for n in fields))
        initial = (start, initial_state(batch, cfg)[1])
    res = run_eskf(batch, cfg, initial=initial)
    if not bool(res.mask.all()):
        raise AssertionError("runs of equal length should give equal epoch grids")
    t = res.t[0]
    if float((res.t - t).abs().max()) > 1e-9:
        raise AssertionError("epoch times differ between runs")
    idx = torch.round(t * sim.imu_rate_hz).long()
    if float((runs[0].truth.t[0, idx] - t).abs().max()) > 1e-9:
        raise AssertionError("epoch times are not IMU sample times")

    def truth(name):
        return torch.stack([getattr(r.truth, name)[0, idx] for r in runs])

    error, cov = navigation_errors(
        NavState(*(truth(n) for n in fields)),
        NavState(*(getattr(res, n) for n in fields)),
        res.covariance,
        coordinates,
    )
    anees = average_nees(nees(error, cov)).numpy()
    components = {}
    for name, start in COMPONENTS.items():
        blk = slice(start, start + 3)
        components[name] = average_nees(nees(error[..., blk], cov[..., blk, blk])).numpy()
    t_np = t.numpy()
    after = t_np >= t_np[0] + skip_s
    low, high = chi2_interval(15, len(seeds), prob)
    low3, high3 = chi2_interval(3, len(seeds), prob)
    vals = anees[after]
    return NeesReport(
        t=t_np,
        anees=anees,
        components=components,
        bounds=(low, high),
        fraction_inside=float(np.mean((vals >= low) & (vals <= high))),
        fraction_below=float(np.mean(vals < low)),
        fraction_above=float(np.mean(vals > high)),
        component_fraction={
            k: float(np.mean((v[after] >= low3) & (v[after] <= high3)))
            for k, v in components.items()
        },
        n_runs=len(seeds),
        skip_s=skip_s,
    )


def per_run_nees(
    seeds: Iterable[int], duration_s: float = 40.0, chunk: int = 40
) -> dict[str, np.ndarray]:
    """Per-run NEES series in invariant coordinates, filtering ``chunk`` runs per batch.

    Returns ``t`` (E,) s; ``nees`` (R, E) 15-dim; one (R, E) 3-dim series per block of
    ``COMPONENTS``; ``yaw_z`` (R,) the initial yaw error over its reported sigma (z
    component of the invariant attitude error at the first epoch), N(0, 1) if honest.
    """
    seeds = list(seeds)
    fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
    sim = consistent_sim_config(duration_s)
    parts: dict[str, list[np.ndarray]] = {"nees": [], "yaw_z": [], **{k: [] for k in COMPONENTS}}
    for first in range(0, len(seeds), chunk):
        runs = [simulate_run(sim, seed=s) for s in seeds[first : first + chunk]]
        cfg = matched_filter_config(sim, runs[0].sequence.meta)
        res = run_eskf(batch_sequences([r.sequence for r in runs]), cfg)
        idx = torch.round(res.t[0] * sim.imu_rate_hz).long()
        truth = NavState(
            *(torch.stack([getattr(r.truth, n)[0, idx] for r in runs]) for n in fields)
        )
        estimate = NavState(*(getattr(res, n) for n in fields))
        error, cov = navigation_errors(truth, estimate, res.covariance)
        parts["nees"].append(nees(error, cov).numpy())
        for name, start in COMPONENTS.items():
            blk = slice(start, start + 3)
            parts[name].append(nees(error[..., blk], cov[..., blk, blk]).numpy())
        parts["yaw_z"].append((error[:, 0, 8] / cov[:, 0, 8, 8].sqrt()).numpy())
    return {"t": res.t[0].numpy(), **{k: np.concatenate(v) for k, v in parts.items()}}


def subset_pass_rate(
    t: np.ndarray,
    values: np.ndarray,
    size: int = 20,
    draws: int = 4000,
    skip_s: float = 5.0,
    prob: float = 0.95,
    need: float = 0.90,
    seed: int = 0,
) -> float:
    """Fraction of ``draws`` random ``size``-run subsets of ``values`` (R, E) per-run 15-dim
    NEES at times ``t`` (E,) s whose average NEES lies inside the two-sided ``prob``
    chi-square interval at >= ``need`` of the epochs after ``skip_s`` (the acceptance test's
    rule applied to other 20-run sets), e.g.::

        runs = per_run_nees(range(100, 900))
        subset_pass_rate(runs["t"], runs["nees"])
    """
    low, high = chi2_interval(15, size, prob)
    after = values[:, t >= t[0] + skip_s]
    rng = np.random.default_rng(seed)
    passed = 0
    for _ in range(draws):
        mean = after[rng.choice(len(after), size, replace=False)].mean(0)
        passed += np.mean((mean >= low) & (mean <= high)) >= need
    return passed / draws


def test_average_nees_inside_chi_square_bounds():
    """Acceptance: 20 runs, >= 90% of epochs inside (measured 92.6% on seeds 100-119, the rest
    below the interval; other 20-run sets 98.9% (300-319, 1.1% above) and 83.2% (400-419, all
    below); with the former constant initial yaw sigma 91.6%, 99.7%, 78.4%)."""
    report = nees_consistency(seeds=range(100, 120), duration_s=40.0, skip_s=5.0)
    assert report.fraction_inside >= 0.90, (
        "ESKF inconsistent: 15-dim average NEES over 20 runs inside the 95% chi-square "
        f"interval at only {100 * report.fraction_inside:.1f}% of epochs (need >= 90%)\n"
        + report.summary()
    )


def test_average_nees_conventional_coordinates():
    """The same runs scored with the conventional additive error against the reported
    covariance: 97.8% inside (300-319: 91.9%, 8.1% above; 400-419: 79.7%, 6.1% above;
    with the former constant initial yaw sigma 97.9%, 94.4%, 69.7%)."""
    report = nees_consistency(
        seeds=range(100, 120), duration_s=40.0, skip_s=5.0, coordinates="conventional"
    )
    assert report.fraction_inside >= 0.90, report.summary()


def test_average_nees_pooled_over_sixty_runs():
    """Pooled over three 20-run seed sets the tighter 60-run interval holds at 92.2% of epochs,
    none above it (conventional coordinates: 93.2%, 0.9% above; with the former constant
    initial yaw sigma 89.3% and 84.7%, 6.7% above); guard at 85% and 2%."""
    seeds = [*range(100, 120), *range(300, 320), *range(400, 420)]
    report = nees_consistency(seeds=seeds, duration_s=40.0, skip_s=5.0)
    assert report.fraction_inside >= 0.85, report.summary()
    assert report.fraction_above <= 0.02, report.summary()


def test_nees_typical_epoch_consistent_on_long_runs():
    """Over 120 s runs the median average NEES lies inside the 95% interval and the filter is
    overconfident (above the interval) at under a quarter of the epochs (measured: median
    13.09 in [12.7, 17.5], none above, 31.7% below: conservative)."""
    report = nees_consistency(seeds=range(100, 120), duration_s=120.0, skip_s=5.0)
    low, high = report.bounds
    median = float(np.median(report.anees[report.t >= report.skip_s]))
    assert low <= median <= high, report.summary()
    assert report.fraction_above <= 0.25, report.summary()


if __name__ == "__main__":
    print(nees_consistency().summary())


def near_linear_monte_carlo(
    seeds: Iterable[int], skip_s: float = 5.0
) -> tuple[float, float, np.ndarray]:
    """The classic Monte-Carlo check of the filter's Q and R, where a first-order filter is exact.

    Each run starts at the truth minus an error drawn from the filter's own initial covariance
    P0, with small initial uncertainty (navigation block x 0.1 in sigma, turn-on biases x 0.1)
    so the problem is nearly linear, and the wheel's lateral / vertical rows are left out
    (sigma 100 m/s): the simulated robot satisfies them exactly, which no finite sigma
    describes. Returns the mean 15-dim NEES over runs and epochs after ``skip_s``, its
    standard error (runs as the independent units), and the eigenvalues of the second moment
    of the whitened error (all 1 for a consistent filter).
    """
    seeds = list(seeds)
    base = consistent_sim_config(40.0)
    noise = dataclasses.replace(
        base.imu_noise,
        gyro_bias_sigma0=0.1 * base.imu_noise.gyro_bias_sigma0,
        accel_bias_sigma0=0.1 * base.imu_noise.accel_bias_sigma0,
    )
    sim = dataclasses.replace(base, imu_noise=noise)
    runs = [simulate_run(sim, seed=s) for s in seeds]
    cfg = matched_filter_config(sim, runs[0].sequence.meta).replace(wheel_lateral_sigma_mps=100.0)
    batch = batch_sequences([r.sequence for r in runs])
    scale = torch.ones(15, dtype=torch.float64)
    scale[:9] = 0.1
    p0 = scale[:, None] * initial_state(batch, cfg)[1] * scale[None, :]
    draw = torch.Generator().manual_seed(seeds[0])
    dx = (
        torch.linalg.cholesky(p0)
        @ torch.randn(len(seeds), 15, 1, generator=draw, dtype=torch.float64)
    )[..., 0]
    fields = ("position", "velocity", "rotation", "gyro_bias", "accel_bias")
    truth0 = {n: torch.cat([getattr(r.truth, n)[:, 0] for r in runs]) for n in fields}
    start = NavState(
        truth0["position"] - dx[:, 0:3],
        truth0["velocity"] - dx[:, 3:6],
        truth0["rotation"] @ so3.exp(-dx[:, 6:9]),
        truth0["gyro_bias"] - dx[:, 9:12],
        truth0["accel_bias"] - dx[:, 12:15],
    )
    res = run_eskf(batch, cfg, initial=(start, p0))
    t = res.t[0]
    idx = torch.round(t * sim.imu_rate_hz).long()

    def truth(name):
        return torch.stack([getattr(r.truth, name)[0, idx] for r in runs])

    error, _ = navigation_errors(
        NavState(*(truth(n) for n in fields)),
        NavState(*(getattr(res, n) for n in fields)),
        res.covariance,
        "conventional",
    )
    after = t >= t[0] + skip_s
    per_run = nees(error, res.covariance)[:, after].mean(-1)
    white = torch.linalg.solve_triangular(
        torch.linalg.cholesky(res.covariance[:, after]), error[:, after, :, None], upper=False
    )[..., 0]
    moment = torch.einsum("bei,bej->ij", white, white) / (white.shape[0] * white.shape[1])
    return (
        float(per_run.mean()),
        float(per_run.std() / len(seeds) ** 0.5),
        torch.linalg.eigvalsh(moment).numpy(),
    )


def test_nees_near_linear_monte_carlo_matches_the_state_dimension():
    """Q and R match the simulator: with a P0-sampled start, small initial uncertainty and no
    exact-constraint rows, the mean NEES over 100 runs is 15 within 3 standard errors
    (measured 15.13 / 15.24 / 15.09 +- 0.42 on seeds 2000, 2100, 3000 + 0..99) and the
    whitened error's second moment has every eigenvalue near 1. The 20-run epoch-fraction
    test above is a weaker statistic: errors stay correlated for many seconds
    (autocorrelation 0.43 at 8 s), so a 20-run set holds few independent draws, and random
    20-run subsets of 800 runs pass it 67 % of the time (invariant coordinates; 65 % with the
    former constant initial yaw sigma) although their pooled NEES is 14.81 after 5 s (14.77
    before)."""
    mean, stderr, eig = near_linear_monte_carlo(range(2000, 2100))
    assert abs(mean - 15.0) <= 3.0 * stderr + 0.3, (mean, stderr)
    # measured 0.66-1.48 on three 100-run sets; the exact-constraint rows at 1e-3 m/s give 0.34
    assert eig.min() > 0.5 and eig.max() < 1.7, eig


def test_initial_yaw_error_matches_its_reported_sigma():
    """The initial yaw error over its reported sigma is N(0, 1) over 80 runs: mean square
    inside the two-sided 99 % interval of chi2(80) / 80, [0.64, 1.45] (measured 0.773 on
    seeds 100-179; the former constant 0.05 rad gave 0.374; over seeds 100-899 std 0.973 vs
    0.680). ``frontend.init.alignment_yaw_variance`` gives the sigma."""
    runs = per_run_nees(range(100, 180))
    low, high = chi2_interval(1, len(runs["yaw_z"]), 0.99)
    square = float(np.mean(runs["yaw_z"] ** 2))
    assert low <= square <= high, (square, low, high)
