"""GNSS outage experiments: withhold the fixes of a time window and score the estimate there.

Drift is the largest horizontal-and-vertical position error against the withheld fixes
divided by the distance travelled inside the window (sum of consecutive fix
displacements), in percent. A real outage labelled in the data (``labels["gnss_outage"]``)
has no fixes to withhold; :func:`labelled_outage_metrics` scores it the same way against the
ground truth's positions inside it.
"""

from __future__ import annotations

__all__ = [
    "split_gnss_outage",
    "outage_metrics",
    "labelled_outage_metrics",
    "interpolate_positions",
]

import dataclasses

import torch

from msf_torch.types import GnssFixes, Sequence, Trajectory


def split_gnss_outage(seq: Sequence, start_s: float, end_s: float) -> tuple[Sequence, GnssFixes]:
    """Withhold GNSS fixes with ``start_s <= t - t_first <= end_s`` (B = 1); the GNSS
    velocities and dual-antenna headings of that window go too (an outage takes the
    receiver's whole output).

    Args:
        seq: one sequence with GNSS.
        start_s, end_s: window in seconds from the sequence's first IMU sample.
    Returns:
        (sequence without those fixes, the withheld fixes as their own stream).
    Raises:
        ValueError: B != 1, no GNSS, end <= start, or fewer than 2 fixes inside the window.
    """
    if seq.batch_size != 1:
        raise ValueError(f"split_gnss_outage needs B = 1, got B = {seq.batch_size}")
    if seq.gnss is None or not bool(seq.gnss.mask.any()):
        raise ValueError(f"sequence '{seq.names[0]}' has no GNSS fixes to withhold")
    if not end_s > start_s:
        raise ValueError(f"outage window must have end > start, got {start_s}:{end_s}")
    rel = seq.gnss.t[0] - seq.start_time[0]
    inside = (rel >= start_s) & (rel <= end_s) & seq.gnss.mask[0]
    held = int(inside.sum())
    if held < 2:
        raise ValueError(
            f"the outage window {start_s}:{end_s} s holds {held} GNSS fix(es); drift needs at "
            "least 2 (a distance travelled inside the window)"
        )
    kept = seq.gnss.map(lambda x: x[:, ~inside])
    withheld = seq.gnss.map(lambda x: x[:, inside])
    receiver = {}
    for name in ("gnss_velocity", "gnss_heading"):
        stream = getattr(seq, name)
        if stream is not None:
            rel = stream.t[0] - seq.start_time[0]
            outside = ~((rel >= start_s) & (rel <= end_s))
            receiver[name] = stream.map(lambda x, k=outside: x[:, k])
    return dataclasses.replace(seq, gnss=kept, **receiver), withheld


def interpolate_positions(estimate: Trajectory, times: torch.Tensor) -> torch.Tensor:
    """Estimated positions linearly interpolated at ``times`` (N,), s -> (N, 3), m (B = 1).

    Times outside the estimate's span take its first / last position.
    """
    keep = estimate.mask[0]
    t_est = estimate.t[0, keep]
    p_est = estimate.position[0, keep]
    idx = torch.searchsorted(t_est, times).clamp(1, t_est.numel() - 1)
    t_lo, t_hi = t_est[idx - 1], t_est[idx]
    w = ((times - t_lo) / (t_hi - t_lo).clamp_min(1e-12)).clamp(0.0, 1.0)[:, None]
    return p_est[idx - 1] * (1.0 - w) + p_est[idx] * w


def outage_metrics(estimate: Trajectory, withheld: GnssFixes) -> dict[str, float]:
    """Score an estimate against withheld fixes (B = 1).

    The estimate is linearly interpolated in position at each fix time (no alignment: the
    outage is judged in the world frame the estimator kept).

    Returns:
        ``outage_rmse_m``, ``outage_max_error_m``, ``outage_distance_m``,
        ``outage_drift_pct`` (= max error / distance * 100), ``outage_duration_s``,
        ``outage_fixes``.
    Raises:
        ValueError: when ``withheld`` holds no fix (nothing to score against).
    """
    if not bool(withheld.mask[0].any()):
        raise ValueError("outage_metrics: no withheld GNSS fix to score the estimate against")
    t_ref = withheld.t[0, withheld.mask[0]]
    p_ref = withheld.position[0, withheld.mask[0]]
    metrics = _position_errors(estimate, t_ref, p_ref)
    metrics["outage_fixes"] = int(t_ref.numel())
    return metrics


def labelled_outage_metrics(
    estimate: Trajectory, ground_truth: Trajectory, start_t: float, end_t: float
) -> dict[str, float]:
    """Score an estimate over a labelled GNSS outage ``[start_t, end_t]`` (s, the sequence's
    clock) against the ground truth's positions inside it (B = 1), as
    :func:`outage_metrics` does against withheld fixes (no alignment).

    Returns:
        ``outage_rmse_m``, ``outage_max_error_m``, ``outage_distance_m`` (along the truth),
        ``outage_drift_pct``, ``outage_duration_s``, ``outage_truth_samples``.
    Raises:
        ValueError: fewer than 2 ground-truth samples inside the outage.
    """
    keep = ground_truth.mask[0] & (ground_truth.t[0] >= start_t) & (ground_truth.t[0] <= end_t)
    if int(keep.sum()) < 2:
        raise ValueError(
            f"labelled_outage_metrics: {int(keep.sum())} ground-truth sample(s) inside the "
            f"outage {start_t}:{end_t} s; need at least 2"
        )
    t_ref = ground_truth.t[0, keep]
    metrics = _position_errors(estimate, t_ref, ground_truth.position[0, keep])
    metrics["outage_truth_samples"] = int(t_ref.numel())
    return metrics


def _position_errors(
    estimate: Trajectory, t_ref: torch.Tensor, p_ref: torch.Tensor
) -> dict[str, float]:
    """RMSE, max error, reference path length, drift % and duration of an estimate against
    reference positions ``p_ref`` (N, 3) m at ``t_ref`` (N,) s."""
    err = (interpolate_positions(estimate, t_ref) - p_ref).norm(dim=-1)
    distance = (p_ref[1:] - p_ref[:-1]).norm(dim=-1).sum()
    return {
        "outage_rmse_m": float(err.pow(2).mean().sqrt()),
        "outage_max_error_m": float(err.max()),
        "outage_distance_m": float(distance),
        "outage_drift_pct": float(100.0 * err.max() / distance.clamp_min(1e-9)),
        "outage_duration_s": float(t_ref[-1] - t_ref[0]),
    }
