"""Absolute and relative trajectory error (ATE / RPE), defined as evo defines them.

Conventions (those of evo 1.38, so numbers match ``evo_ape`` / ``evo_rpe`` on the same files):

* Association: :func:`msf_torch.eval.align.associate`, evo's nearest-timestamp rule
  (``sync.associate_trajectories(traj_ref, traj_est, max_diff)``).
* Alignment: the estimate is moved onto the reference, ``p' = s R p + t`` and ``R_i' = R R_i``,
  with Umeyama over all matched positions. ``"se3"`` is ``traj_est.align(traj_ref)``,
  ``"sim3"`` is ``align(traj_ref, correct_scale=True)``, ``"none"`` leaves it as it is.
* ATE: ``metrics.APE(PoseRelation.translation_part)``, the per-pose error
  ``|| p_est,i' - p_ref,i ||``.
* RPE: ``metrics.RPE(PoseRelation.translation_part, delta, delta_unit, all_pairs=False)`` with
  pairs chosen on the (aligned) estimate: ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` for reference
  poses Q and estimated poses P, translation error ``|| trans(E_ij) ||`` (m) and rotation error
  ``angle(rot(E_ij))`` (deg, ``PoseRelation.rotation_angle_deg``).
* Statistics: rmse, mean, median (mean of the two middle values for an even count), std
  (population, ``ddof = 0``), min, max — those of evo's ``PE.get_statistic``.

Everything is float64. Functions taking :class:`~msf_torch.types.Trajectory` work on one
sequence (B = 1); :func:`translation_errors` and :func:`error_statistics` are the batched,
masked cores for already synchronised batches.
"""

from __future__ import annotations

__all__ = [
    "ALIGN_MODES",
    "DELTA_UNITS",
    "error_statistics",
    "translation_errors",
    "position_errors",
    "aligned_estimate",
    "ate",
    "rpe",
    "REFERENCE_STREAMS",
    "load_reference",
    "at_lever_arm",
    "evaluate_files",
]

import dataclasses
import os
from pathlib import Path
from typing import Any

import torch

from msf_torch.eval.align import apply_similarity, associate, umeyama
from msf_torch.geometry import so3
from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.types import Trajectory

ALIGN_MODES = ("se3", "sim3", "none")
"""Alignment modes: rigid (SE(3)), similarity (Sim(3)), none."""

DELTA_UNITS = ("frames", "m", "s")
"""RPE delta units: matched poses, travelled metres, elapsed seconds."""

_STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")

REFERENCE_STREAMS = ("auto", "ground_truth", "gnss")
"""Which stream of a recorded sequence :func:`load_reference` takes: ``"auto"`` (the ground
truth when the sequence has one, else its GNSS fixes), or that one."""


def _check_align(align: str) -> None:
    if align not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {align!r}")


def error_statistics(
    error: torch.Tensor, mask: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """Masked statistics of per-sample errors, per sequence.

    Args:
        error: (B, N) non-negative errors (any unit; the statistics keep it).
        mask: (B, N) bool, True where the sample counts; None means all.

    Returns:
        ``{"rmse", "mean", "median", "std", "min", "max"}`` each (B,) in the unit of
        ``error``, and ``"count"`` (B,) int64. ``std`` is the population standard deviation
        and ``median`` averages the two middle values for an even count (numpy's and evo's
        definitions). A sequence with no samples gets NaN statistics and count 0.
    """
    if error.dim() != 2:
        raise ValueError(f"error must be (B, N), got {tuple(error.shape)}")
    if mask is None:
        mask = torch.ones_like(error, dtype=torch.bool)
    if mask.shape != error.shape:
        raise ValueError(f"mask must be {tuple(error.shape)}, got {tuple(mask.shape)}")
    count = mask.sum(-1)
    n = count.to(error.dtype)
    nan = torch.full_like(n, float("nan"))
    empty = count == 0
    safe_n = n.clamp_min(1.0)
    zero = torch.zeros_like(error)
    masked = torch.where(mask, error, zero)
    mean = masked.sum(-1) / safe_n
    rmse = torch.sqrt((masked * masked).sum(-1) / safe_n)
    centred = torch.where(mask, error - mean[:, None], zero)
    std = torch.sqrt((centred * centred).sum(-1) / safe_n)
    if error.shape[-1] == 0:
        median, minimum, maximum = nan.clone(), nan.clone(), nan.clone()
    else:
        inf = torch.full_like(error, float("inf"))
        ordered = torch.where(mask, error, inf).sort(-1).values
        lo = ((count - 1).clamp_min(0) // 2)[:, None]
        hi = (count // 2).clamp_max(error.shape[-1] - 1)[:, None]
        median = 0.5 * (ordered.gather(-1, lo) + ordered.gather(-1, hi))[:, 0]
        minimum = ordered[:, 0]
        maximum = torch.where(mask, error, -inf).amax(-1)
    out = {
        "rmse": rmse,
        "mean": mean,
        "median": median,
        "std": std,
        "min": minimum,
        "max": maximum,
    }
    out = {k: torch.where(empty, nan, v) for k, v in out.items()}
    out["count"] = count
    return out


def translation_errors(
    est_position: torch.Tensor,
    ref_position: torch.Tensor,
    mask: torch.Tensor | None = None,
    align: str = "se3",
) -> torch.Tensor:
    """Per-pose position error after alignment, batched, for synchronised trajectories.

    Args:
        est_position: (B, N, 3) estimated positions, m, pose i paired with ``ref_position``'s.
        ref_position: (B, N, 3) reference positions, m.
        mask: (B, N) bool, True for real pairs (alignment uses only these); None means all.
        align: ``"se3"``, ``"sim3"`` or ``"none"``, one alignment per sequence.

    Returns:
        (B, N) ``|| s R p_est + t - p_ref ||``, m; 0 where ``mask`` is False.

    Example:
        >>> err = translation_errors(est_xyz, gt_xyz, mask, align="se3")  # doctest: +SKIP
        >>> stats = error_statistics(err, mask)  # doctest: +SKIP
    """
    _check_align(align)
    if est_position.shape != ref_position.shape or est_position.dim() != 3:
        raise ValueError(
            f"est_position and ref_position must both be (B, N, 3); got "
            f"{tuple(est_position.shape)} and {tuple(ref_position.shape)}"
        )
    if mask is None:
        mask = torch.ones(est_position.shape[:2], dtype=torch.bool, device=est_position.device)
    if align != "none":
        rot, trans, scale = umeyama(est_position, ref_position, mask, with_scale=align == "sim3")
        est_position = apply_similarity(est_position, rot, trans, scale)
    err = (est_position - ref_position).norm(dim=-1)
    return torch.where(mask, err, torch.zeros_like(err))


def _matched(est: Trajectory, ref: Trajectory, align: str, max_dt: float) -> dict[str, Any]:
    """Associate, gather and align one sequence; float64, every tensor without a B axis."""
    _check_align(align)
    est = est.to(dtype=torch.float64)
    ref = ref.to(dtype=torch.float64)
    est_idx, ref_idx = associate(est, ref, max_dt)
    p_est = est.position[0, est_idx]
    p_ref = ref.position[0, ref_idx]
    r_est = quat_to_matrix(est.quaternion[0, est_idx])
    r_ref = quat_to_matrix(ref.quaternion[0, ref_idx])
    eye = torch.eye(3, dtype=p_est.dtype, device=p_est.device)
    rot, trans, scale = eye, torch.zeros(3, dtype=p_est.dtype, device=p_est.device), 1.0
    if align != "none":
        r_a, t_a, s_a = umeyama(p_est[None], p_ref[None], with_scale=align == "sim3")
        rot, trans, scale = r_a[0], t_a[0], float(s_a[0])
        p_est = scale * (p_est @ rot.T) + trans
        r_est = rot @ r_est
    return {
        "t": est.t[0, est_idx],
        "p_est": p_est,
        "p_ref": p_ref,
        "r_est": r_est,
        "r_ref": r_ref,
        "rotation": rot,
        "translation": trans,
        "scale": scale,
        "matched": int(est_idx.numel()),
    }


def _floats(stats: dict[str, torch.Tensor]) -> dict[str, float]:
    return {k: float(stats[k][0]) for k in _STAT_KEYS}


def aligned_estimate(
    est: Trajectory, ref: Trajectory, align: str = "se3", max_dt: float = 0.01
) -> Trajectory:
    """The whole estimate moved by the alignment the ATE uses (float64, B = 1).

    ``p' = s R p + t`` and ``R_est' = R R_est`` with ``(R, t, s)`` from
    :func:`~msf_torch.eval.align.umeyama` over the matched poses (``"none"``: unchanged).

    Args:
        est: estimated trajectory, B = 1.
        ref: reference trajectory, B = 1.
        align: ``"se3"``, ``"sim3"`` or ``"none"``.
        max_dt: association tolerance, s.
    """
    m = _matched(est, ref, align, max_dt)
    moved = est.to(dtype=torch.float64)
    position = m["scale"] * moved.position @ m["rotation"].T + m["translation"]
    rotation = m["rotation"] @ quat_to_matrix(moved.quaternion)
    return dataclasses.replace(moved, position=position, quaternion=matrix_to_quat(rotation))


def position_errors(
    est: Trajectory, ref: Trajectory, align: str = "se3", max_dt: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Position error over time after association and alignment, for plotting.

    Args:
        est: estimated trajectory, B = 1.
        ref: reference trajectory, B = 1.
        align: ``"se3"``, ``"sim3"`` or ``"none"``.
        max_dt: association tolerance, s.

    Returns:
        ``(t, err)``: (K,) the estimate's times of the K matched poses, s, and (K,) the
        position error ``|| p_est' - p_ref ||`` there, m (float64).
    """
    m = _matched(est, ref, align, max_dt)
    return m["t"], (m["p_est"] - m["p_ref"]).norm(dim=-1)


def ate(
    est: Trajectory, ref: Trajectory, align: str = "se3", max_dt: float = 0.01
) -> dict[str, float | int]:
    """Absolute trajectory error (translation part), like ``evo_ape tum ref est [-a|-as]``.

    Args:
        est: estimated trajectory, B = 1.
        ref: reference trajectory, B = 1.
        align: ``"se3"`` (Umeyama, rigid), ``"sim3"`` (with scale) or ``"none"``.
        max_dt: association tolerance, s.

    Returns:
        ``{"rmse", "mean", "median", "std", "min", "max"}`` in m, ``"matched"`` (number of
        associated poses) and ``"scale"`` (the Sim(3) scale; 1.0 for ``se3`` / ``none``).

    Raises:
        ValueError: B is not 1, no timestamps match, or alignment is degenerate.
    """
    m = _matched(est, ref, align, max_dt)
    err = (m["p_est"] - m["p_ref"]).norm(dim=-1)
    out: dict[str, float | int] = dict(_floats(error_statistics(err[None])))
    out["matched"] = m["matched"]
    out["scale"] = m["scale"]
    return out


def _pairs_by_path(positions: torch.Tensor, delta: float) -> list[tuple[int, int]]:
    """evo's ``filter_pairs_by_path`` (consecutive pairs): restart the path sum at each pick."""
    steps = (positions[1:] - positions[:-1]).norm(dim=-1).tolist()
    ids = [0]
    path = 0.0
    for i, step in enumerate(steps, start=1):
        path += step
        if path >= delta:
            ids.append(i)
            path = 0.0
    return list(zip(ids[:-1], ids[1:], strict=True))


def _pairs_by_time(times: torch.Tensor, delta: float) -> list[tuple[int, int]]:
    """Consecutive pairs at least ``delta`` seconds apart (evo has no time unit for RPE)."""
    stamps = times.tolist()
    ids = [0]
    for i in range(1, len(stamps)):
        if stamps[i] - stamps[ids[-1]] >= delta:
            ids.append(i)
    return list(zip(ids[:-1], ids[1:], strict=True))


def rpe(
    est: Trajectory,
    ref: Trajectory,
    delta: float = 1,
    delta_unit: str = "frames",
    align: str = "se3",
    max_dt: float = 0.01,
) -> dict[str, Any]:
    """Relative pose error, like ``evo_rpe tum ref est -r trans_part -d delta -u unit [-a|-as]``.

    Pairs ``(i, j)`` of matched poses are consecutive (evo's ``all_pairs=False``) and picked
    on the aligned estimate:

    * ``"frames"``: ``i = 0, delta, 2 delta, ...`` (``delta`` a positive integer);
    * ``"m"``: the next ``j`` once the path travelled since ``i`` (sum of the estimate's
      segment lengths) reaches ``delta`` metres;
    * ``"s"``: the next ``j`` with ``t_j - t_i >= delta`` seconds (an msf_torch extension: evo's
      RPE has no time unit).

    With ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (Q reference, P aligned estimate), the
    translation error is ``|| trans(E_ij) ||`` and the rotation error ``angle(rot(E_ij))``.
    A rigid alignment leaves RPE unchanged; ``"sim3"`` rescales the estimate's translations.

    Args:
        est: estimated trajectory, B = 1.
        ref: reference trajectory, B = 1.
        delta: pair spacing in ``delta_unit``.
        delta_unit: ``"frames"``, ``"m"`` or ``"s"``.
        align: ``"se3"``, ``"sim3"`` or ``"none"``.
        max_dt: association tolerance, s.

    Returns:
        ``{"rmse", "mean", "median", "std", "min", "max"}`` of the translation error in m,
        ``"rotation_deg"``: the same statistics of the rotation error in degrees,
        ``"pairs"`` (number of pose pairs), ``"matched"`` (associated poses), ``"delta"``,
        ``"delta_unit"``.

    Raises:
        ValueError: bad ``delta`` / ``delta_unit``, B is not 1, or no pair fits ``delta``.
    """
    if delta_unit not in DELTA_UNITS:
        raise ValueError(f"delta_unit must be one of {DELTA_UNITS}, got {delta_unit!r}")
    if not delta > 0:
        raise ValueError(f"delta must be positive, got {delta}")
    if delta_unit == "frames" and float(delta) != int(delta):
        raise ValueError(f"delta must be an integer for delta_unit 'frames', got {delta}")
    m = _matched(est, ref, align, max_dt)
    n = m["matched"]
    if delta_unit == "frames":
        ids = list(range(0, n, int(delta)))
        pairs = list(zip(ids[:-1], ids[1:], strict=True))
    elif delta_unit == "m":
        pairs = _pairs_by_path(m["p_est"], float(delta))
    else:
        pairs = _pairs_by_time(m["t"], float(delta))
    if not pairs:
        raise ValueError(
            f"delta = {delta} ({delta_unit}) produced no pose pairs among {n} matched poses; "
            "use a smaller delta"
        )
    device = m["p_est"].device
    i = torch.tensor([p[0] for p in pairs], dtype=torch.long, device=device)
    j = torch.tensor([p[1] for p in pairs], dtype=torch.long, device=device)
    p_est, p_ref, r_est, r_ref = m["p_est"], m["p_ref"], m["r_est"], m["r_ref"]
    # Relative poses P_i^-1 P_j and Q_i^-1 Q_j.
    rp = r_est[i].transpose(-1, -2) @ r_est[j]
    tp = (r_est[i].transpose(-1, -2) @ (p_est[j] - p_est[i])[..., None])[..., 0]
    rq = r_ref[i].transpose(-1, -2) @ r_ref[j]
    tq = (r_ref[i].transpose(-1, -2) @ (p_ref[j] - p_ref[i])[..., None])[..., 0]
    # E = (Q_rel)^-1 P_rel.
    re = rq.transpose(-1, -2) @ rp
    te = (rq.transpose(-1, -2) @ (tp - tq)[..., None])[..., 0]
    trans_err = te.norm(dim=-1)
    rot_err = torch.rad2deg(so3.log(re).norm(dim=-1))
    out: dict[str, Any] = dict(_floats(error_statistics(trans_err[None])))
    out["rotation_deg"] = _floats(error_statistics(rot_err[None]))
    out["pairs"] = len(pairs)
    out["matched"] = n
    out["delta"] = delta
    out["delta_unit"] = delta_unit
    return out


def load_reference(
    path: str | os.PathLike, stream: str = "auto", sort: bool = False
) -> tuple[Trajectory, str]:
    """A reference trajectory from a TUM file or from a recorded sequence.

    A ``.tum`` / ``.txt`` file is read with :func:`msf_torch.io.tum.read_tum`; anything
    else :func:`msf_torch.io.load_sequence` reads (a native folder or ``.npz``, a EuRoC
    folder, ``kitti-gtsam``) gives its ground truth or its GNSS fixes (``stream``, see
    :data:`REFERENCE_STREAMS`). GNSS fixes are positions only: the returned trajectory's
    quaternions are identity and mean nothing (the kind says so).

    Args:
        path: the file, folder or dataset name.
        stream: ``"auto"``, ``"ground_truth"`` or ``"gnss"`` (a sequence only).
        sort: sort poses / samples by time (else time going backwards is an error).

    Returns:
        ``(trajectory (1, N), kind)``, kind ``"tum"``, ``"ground_truth"`` or ``"gnss"``.

    Raises:
        ValueError: an unknown ``stream``, a stream the sequence lacks, or ``stream`` other
            than ``"auto"`` for a TUM file. DataError: unreadable input.
    """
    from msf_torch.io import detect_format, load_sequence
    from msf_torch.io.tum import read_tum

    if stream not in REFERENCE_STREAMS:
        raise ValueError(f"reference stream must be one of {REFERENCE_STREAMS}, got {stream!r}")
    if detect_format(path) == "tum":
        if stream != "auto":
            raise ValueError(f"{path} is a TUM trajectory; it has no {stream} stream to pick")
        return read_tum(path, sort=sort), "tum"
    seq = load_sequence(path, sort=sort)
    truth = seq.ground_truth
    has_truth = truth is not None and bool(truth.mask.any())
    has_gnss = seq.gnss is not None and bool(seq.gnss.mask.any())
    if stream == "ground_truth" or (stream == "auto" and has_truth):
        if not has_truth:
            raise ValueError(f"{path} has no ground truth (try --reference-stream gnss)")
        return truth.compact().to(dtype=torch.float64), "ground_truth"
    if not has_gnss:
        raise ValueError(f"{path} has no {'ground truth or ' * (stream == 'auto')}GNSS fixes")
    fixes = seq.gnss.compact().to(dtype=torch.float64)
    identity = torch.zeros(*fixes.position.shape[:-1], 4, dtype=torch.float64)
    identity[..., 0] = 1.0
    return Trajectory(fixes.t, fixes.position, identity, fixes.mask), "gnss"


def at_lever_arm(trajectory: Trajectory, lever_arm: torch.Tensor) -> Trajectory:
    """The trajectory of a point fixed to the body: ``p + R l`` (orientation unchanged).

    Args:
        trajectory: (B, N) poses (body in world).
        lever_arm: (3,) the point in the body frame, m (e.g. a GNSS antenna).
    """
    rotation = quat_to_matrix(trajectory.quaternion)
    arm = torch.as_tensor(lever_arm, dtype=rotation.dtype, device=rotation.device)
    return dataclasses.replace(
        trajectory, position=trajectory.position + (rotation @ arm[:, None])[..., 0]
    )


def evaluate_files(
    estimate_path: str | os.PathLike,
    reference_path: str | os.PathLike,
    align: str | None = None,
    max_dt: float = 0.01,
    delta: float = 1,
    delta_unit: str = "frames",
    plot: str | os.PathLike | None = None,
    sort: bool = False,
    reference_stream: str = "auto",
    lever_arm: tuple[float, float, float] | None = None,
) -> dict[str, Any]:
    """ATE and RPE of a TUM estimate file against a reference (:func:`load_reference`).

    Reads the estimate with :func:`msf_torch.io.tum.read_tum` (imported here, lazily, so
    that ``msf_torch.eval`` otherwise needs only types and geometry). Against GNSS fixes
    (positions only) there is no RPE (``"rpe"`` is None, ``"rpe_skipped"`` says why), and
    the default alignment is ``"none"``: the fixes are the world frame the estimator kept.

    Args:
        estimate_path: TUM file ``t x y z qx qy qz qw`` of the estimate.
        reference_path: TUM file of the reference, or a recorded sequence.
        align: ``"se3"``, ``"sim3"`` or ``"none"``; None: ``"none"`` against GNSS fixes,
            else ``"se3"``.
        max_dt: association tolerance, s.
        delta, delta_unit: RPE pair spacing (see :func:`rpe`).
        plot: optional PNG path: the estimate moved by the ATE's alignment against the
            reference (top-down) and the position error over time
            (:func:`msf_torch.eval.plots.overview_figure`, no slip panel).
        sort: sort each file's poses by time (else time going backwards is an error).
        reference_stream: a sequence's stream to score against (:data:`REFERENCE_STREAMS`).
        lever_arm: ``(x, y, z)`` m in the body frame: score the estimate at this point
            (``p + R l``, e.g. the GNSS antenna the fixes locate), not at the body origin.

    Returns:
        ``{"ate": ate(...), "rpe": rpe(...) or None, "matched": n, "align": align,
        "estimate": str, "reference": str, "reference_kind": kind}``, ``"rpe_skipped"``
        against GNSS, ``"lever_arm_m"`` with ``lever_arm``, and ``"plot": str`` with
        ``plot``.
    """
    from msf_torch.io.tum import read_tum

    est = read_tum(estimate_path, sort=sort)
    ref, kind = load_reference(reference_path, reference_stream, sort=sort)
    if lever_arm is not None:
        est = at_lever_arm(est, torch.tensor(lever_arm, dtype=torch.float64))
    if align is None:
        align = "none" if kind == "gnss" else "se3"
    ate_out = ate(est, ref, align=align, max_dt=max_dt)
    out: dict[str, Any] = {"ate": ate_out, "rpe": None}
    if kind == "gnss":
        out["rpe_skipped"] = "GNSS fixes are positions only: no relative rotation to compare"
    else:
        out["rpe"] = rpe(est, ref, delta=delta, delta_unit=delta_unit, align=align, max_dt=max_dt)
    out.update(
        {
            "matched": ate_out["matched"],
            "align": align,
            "estimate": os.fspath(estimate_path),
            "reference": os.fspath(reference_path),
            "reference_kind": kind,
        }
    )
    if lever_arm is not None:
        out["lever_arm_m"] = [float(x) for x in lever_arm]
    if plot is not None:
        from msf_torch.eval.plots import overview_figure

        error_t, error = position_errors(est, ref, align, max_dt)
        out["plot"] = str(
            overview_figure(
                plot,
                aligned_estimate(est, ref, align, max_dt),
                ref,
                error_t=error_t,
                error=error,
                title=f"{Path(estimate_path).name} vs {Path(reference_path).name} "
                f"(align {align}, ATE RMSE {ate_out['rmse']:.3f} m)",
                slip_panel=False,
                reference_label={"gnss": "GNSS fixes", "ground_truth": "ground truth"}.get(
                    kind, "reference"
                ),
            )
        )
    return out
