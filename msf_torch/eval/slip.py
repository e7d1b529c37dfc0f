"""Slip-detection scores against labelled slip intervals.

Step level: every wheel epoch is a sample; it is *positive* when its time lies inside a
labelled slip interval (widened by ``tolerance_s`` on each side for the truth used by
precision, so onset and offset ramps do not count as false alarms) and *detected* when the
estimator flagged it. Episode level: an episode is found when at least one flagged epoch
falls inside it; a false episode is a run of flagged epochs touching no interval.
"""

from __future__ import annotations

__all__ = ["slip_scores"]

import torch


def _inside(t: torch.Tensor, intervals: torch.Tensor, pad: float) -> torch.Tensor:
    """(N,) bool: ``t`` inside any ``[t0 - pad, t1 + pad]`` of intervals (K, 2)."""
    if intervals.numel() == 0:
        return torch.zeros_like(t, dtype=torch.bool)
    lo = intervals[:, 0] - pad
    hi = intervals[:, 1] + pad
    return ((t[:, None] >= lo) & (t[:, None] <= hi)).any(-1)


def slip_scores(
    t: torch.Tensor, flagged: torch.Tensor, intervals: torch.Tensor, tolerance_s: float = 0.5
) -> dict[str, float]:
    """Precision, recall and F1 of slip flags, step- and episode-level (one sequence).

    Args:
        t: (N,) wheel epoch times, s.
        flagged: (N,) bool, epochs the estimator called slipping.
        intervals: (K, 2) labelled slip intervals ``[t_start, t_end]``, s (NaN rows ignored).
        tolerance_s: widening of the intervals when judging false alarms, s.
    Returns:
        dict with ``precision``, ``recall``, ``f1`` (step level), ``episode_recall``,
        ``false_episodes``, ``episodes``.
    """
    intervals = intervals[torch.isfinite(intervals).all(-1)]
    truth_strict = _inside(t, intervals, 0.0)
    truth_loose = _inside(t, intervals, tolerance_s)
    tp_recall = (flagged & truth_strict).sum().item()
    positives = truth_strict.sum().item()
    detections = flagged.sum().item()
    true_detections = (flagged & truth_loose).sum().item()
    precision = true_detections / detections if detections else 1.0
    recall = tp_recall / positives if positives else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    found = 0
    for t0, t1 in intervals.tolist():
        found += int((flagged & (t >= t0) & (t <= t1)).any().item())
    # runs of consecutive flagged epochs that touch no (widened) interval
    false_runs = 0
    run_touches = False
    in_run = False
    for f, ok in zip(flagged.tolist(), truth_loose.tolist(), strict=True):
        if f:
            run_touches = run_touches or ok
            in_run = True
        elif in_run:
            false_runs += int(not run_touches)
            in_run, run_touches = False, False
    if in_run:
        false_runs += int(not run_touches)
    episodes = intervals.shape[0]
    return {
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "episode_recall": found / episodes if episodes else 1.0,
        "false_episodes": false_runs,
        "episodes": episodes,
    }
