"""Feature-map sparsification: which map points to keep, as a binary quadratic programme.

Problem (:class:`SparsificationProblem`)
    n map points, m keyframes, ``A`` (m, n) with ``A_ki = 1`` when keyframe k observes point
    i. Keep ``x in {0, 1}^n`` minimising

        f(x) = 1/2 x^T Q x + q^T x      subject to   A x >= b

    with ``b_k = min(min_points, sum_i A_ki)`` (every keyframe keeps ``min_points`` points,
    or all it has), the cost of keeping a point ``q_i = 1 - track_discount n_i / max_j n_j``
    (``n_i`` keyframes observe it: long tracks are cheaper, ``q_i`` in
    ``[1 - track_discount, 1]``), and the pair penalty

        Q_ij = pair_weight sum_k A_ki A_kj exp(-|u_ki - u_kj|^2 / (2 r^2))   (i != j), Q_ii = 0

    for points ``i, j`` seen ``|u_ki - u_kj|`` px apart in keyframe k (``r =
    neighbourhood_px``): two points that project close together constrain a pose much as
    one does, so keeping both is penalised and the kept points spread over the image.
    ``Q >= 0`` elementwise but is indefinite, so ``f`` is not convex over ``[0, 1]^n``.

Solvers
    * :func:`sparsify_greedy` (default): the greedy rule for weighted set multicover, with
      the quadratic cost's marginal: repeatedly keep the point with the largest
      ``(uncovered demand it meets) / (q_i + (Q x)_i)`` until every keyframe has its ``b_k``;
      then drop kept points, costliest marginal first, while every keyframe keeps ``b_k``
      (each drop lowers ``f`` by ``q_i + (Q x)_i > 0``). For linear costs this greedy is
      within ``H(max_i n_i)`` of the optimum (Dobson 1982); the pair penalty only raises the
      marginal of points near kept ones. Incremental: O(nnz(A) + picks x n). A 1-swap local
      search follows (replace a kept point by an unkept one that covers the keyframes it
      would leave short, when that lowers ``f``), then the drop pass again.
    * :func:`sparsify_relaxation`: the linear-programming relaxation of the exact
      linearisation (``y_ij >= x_i + x_j - 1``, ``y_ij >= 0`` replaces ``x_i x_j``; exact for
      binary x because ``Q >= 0``; McCormick), solved by HiGHS (``scipy.optimize.linprog``);
      its optimum is a lower bound on ``f``; points with ``x_i >= 1/2`` are kept, the greedy
      completes the cover and the drop pass follows.
    * :func:`sparsify_exact`: the same linearisation as a mixed-integer programme
      (``scipy.optimize.milp``, HiGHS branch and bound), with a time limit: the reference
      on small and medium instances.

Reference: M. Dymczyk, S. Lynen, T. Cieslewski, M. Bosse, R. Siegwart and P. Furgale, "The
Gist of Maps - Summarizing Experience for Lifelong Localization", ICRA 2015 (keyframe
coverage constraints, an ILP over landmarks).
"""

from __future__ import annotations

__all__ = [
    "SparsifyConfig",
    "SparsificationProblem",
    "SparsifyResult",
    "sparsification_problem",
    "vo_sparsification_problem",
    "sparsify_greedy",
    "sparsify_relaxation",
    "sparsify_exact",
]

import time
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, linprog, milp

from msf_torch.vision.odometry import VoResult


@dataclass(frozen=True)
class SparsifyConfig:
    """Terms of the programme (module docstring).

    Attributes:
        min_points: ``b``, points every keyframe keeps (or all it has).
        neighbourhood_px: ``r``, image distance scale of the pair penalty, px.
        pair_weight: scale of ``Q``.
        track_discount: ``q_i = 1 - track_discount n_i / max n`` (in [0, 1)).
        cutoff: pairs farther than ``cutoff r`` apart in a keyframe add nothing to ``Q``.
    """

    min_points: int = 40
    neighbourhood_px: float = 20.0
    pair_weight: float = 1.0
    track_discount: float = 0.5
    cutoff: float = 3.0


@dataclass
class SparsificationProblem:
    """``min 1/2 x^T Q x + q^T x  s.t.  A x >= b, x binary``.

    Attributes:
        coverage: ``A`` (m, n) CSR, 0/1 float64.
        required: ``b`` (m,) int64.
        linear: ``q`` (n,) float64 > 0.
        quadratic: ``Q`` (n, n) CSR, symmetric, zero diagonal, >= 0.
    """

    coverage: sparse.csr_matrix
    required: np.ndarray
    linear: np.ndarray
    quadratic: sparse.csr_matrix

    @property
    def num_points(self) -> int:
        """n."""
        return int(self.coverage.shape[1])

    def cost(self, keep: np.ndarray) -> float:
        """``f(x)`` of a selection (n,) bool or 0/1."""
        x = np.asarray(keep, np.float64)
        return float(0.5 * x @ (self.quadratic @ x) + self.linear @ x)

    def feasible(self, keep: np.ndarray) -> bool:
        """Every keyframe keeps at least ``b_k`` points."""
        return bool(np.all(self.coverage @ np.asarray(keep, np.float64) >= self.required))


@dataclass
class SparsifyResult:
    """A selection and how it was found.

    Attributes:
        keep: (n,) bool, the points kept.
        cost: ``f(keep)``.
        lower_bound: a proven lower bound on the optimal ``f`` (``-inf`` when none).
        seconds: solve time (wall), s.
        method: ``"greedy"``, ``"relaxation"`` or ``"exact"``.
        status: solver message (``"ok"`` for the greedy).
    """

    keep: np.ndarray
    cost: float
    lower_bound: float
    seconds: float
    method: str
    status: str


def sparsification_problem(
    keyframe_points: list[np.ndarray],
    keyframe_pixels: list[np.ndarray],
    num_points: int,
    config: SparsifyConfig | None = None,
) -> SparsificationProblem:
    """Build the programme from the keyframes' observations.

    Args:
        keyframe_points: per keyframe, (K_k,) int64 point indices it observes (unique).
        keyframe_pixels: per keyframe, (K_k, 2) px where it sees them.
        num_points: n.
        config: terms.
    Returns:
        the :class:`SparsificationProblem`.
    Raises:
        ValueError: lengths disagree or an index lies outside ``[0, n)``.
    """
    config = config or SparsifyConfig()
    if len(keyframe_points) != len(keyframe_pixels):
        raise ValueError("sparsification_problem: one pixel array per keyframe needed")
    rows, cols, pair_i, pair_j, pair_w = [], [], [], [], []
    radius = config.neighbourhood_px
    for k, (points, pixels) in enumerate(zip(keyframe_points, keyframe_pixels, strict=True)):
        points = np.asarray(points, np.int64)
        pixels = np.asarray(pixels, np.float64)
        if points.size and (points.min() < 0 or points.max() >= num_points):
            raise ValueError(f"sparsification_problem: keyframe {k} names a point outside [0, n)")
        if pixels.shape != (len(points), 2):
            raise ValueError(f"sparsification_problem: keyframe {k} pixels must be (K, 2)")
        rows.append(np.full(len(points), k))
        cols.append(points)
        gap2 = ((pixels[:, None, :] - pixels[None, :, :]) ** 2).sum(-1)
        a, b = np.nonzero(np.triu(gap2 <= (config.cutoff * radius) ** 2, 1))
        pair_i.append(points[a])
        pair_j.append(points[b])
        pair_w.append(np.exp(-gap2[a, b] / (2.0 * radius**2)))
    count = len(keyframe_points)
    none = [np.zeros(0, np.int64)]  # no keyframe or no point: an empty programme
    coverage = sparse.csr_matrix(
        (
            np.ones(sum(len(c) for c in cols)),
            (np.concatenate(none + rows), np.concatenate(none + cols)),
        ),
        shape=(count, num_points),
    )
    coverage.data[:] = 1.0
    observed = np.asarray(coverage.sum(1)).reshape(-1).astype(np.int64)
    required = np.minimum(observed, config.min_points)
    track = np.asarray(coverage.sum(0)).reshape(-1)
    linear = 1.0 - config.track_discount * track / max(float(track.max(initial=0.0)), 1.0)
    i, j = np.concatenate(none + pair_i), np.concatenate(none + pair_j)
    w = np.concatenate([np.zeros(0), *pair_w])
    upper = sparse.coo_matrix((config.pair_weight * w, (i, j)), shape=(num_points, num_points))
    quadratic = (upper + upper.T).tocsr()
    quadratic.sum_duplicates()
    return SparsificationProblem(coverage, required, linear, quadratic)


def vo_sparsification_problem(
    result: VoResult, config: SparsifyConfig | None = None
) -> SparsificationProblem:
    """The programme over the map points of a visual-odometry run (point i = landmark row i
    of ``result.landmarks``), from the keyframes' features that have map points."""
    points, pixels = [], []
    landmark_ids = result.landmark_ids
    for keyframe in result.keyframes:
        ids = keyframe.feature_ids[keyframe.landmark]
        where = np.searchsorted(landmark_ids, ids)
        found = where < len(landmark_ids)
        found[found] = landmark_ids[where[found]] == ids[found]
        points.append(where[found])
        pixels.append(keyframe.pixels[keyframe.landmark][found])
    return sparsification_problem(points, pixels, len(result.landmarks), config)


def _greedy_complete(problem: SparsificationProblem, keep: np.ndarray) -> np.ndarray:
    """Add points by the greedy ratio until ``A x >= b``; then the drop pass."""
    coverage_csc = problem.coverage.tocsc()
    coverage_csr = problem.coverage
    quadratic = problem.quadratic.tocsc()
    keep = keep.copy()
    x = keep.astype(np.float64)
    deficit = problem.required - (coverage_csr @ x).astype(np.int64)
    needy = (deficit > 0).astype(np.float64)
    gain = np.asarray(coverage_csc.T @ needy).reshape(-1)
    marginal = problem.linear + quadratic @ x
    gain[keep] = 0.0
    while (deficit > 0).any():
        best = int(np.argmax(gain / marginal))
        if gain[best] <= 0.0:
            raise ValueError("sparsify: the coverage constraints cannot be met")
        keep[best] = True
        gain[best] = 0.0
        start, end = coverage_csc.indptr[best], coverage_csc.indptr[best + 1]
        frames = coverage_csc.indices[start:end]
        deficit[frames] -= 1
        for frame in frames[deficit[frames] == 0]:
            members = coverage_csr.indices[
                coverage_csr.indptr[frame] : coverage_csr.indptr[frame + 1]
            ]
            gain[members] -= 1.0
        gain[keep] = 0.0
        q_start, q_end = quadratic.indptr[best], quadratic.indptr[best + 1]
        marginal[quadratic.indices[q_start:q_end]] += quadratic.data[q_start:q_end]
    return _swap_pass(problem, _drop_pass(problem, keep))


def _drop_pass(problem: SparsificationProblem, keep: np.ndarray) -> np.ndarray:
    """Drop kept points, costliest marginal first, while every keyframe keeps ``b_k``."""
    coverage_csc = problem.coverage.tocsc()
    keep = keep.copy()
    x = keep.astype(np.float64)
    slack = (problem.coverage @ x).astype(np.int64) - problem.required
    marginal = problem.linear + problem.quadratic @ x
    quadratic = problem.quadratic.tocsc()
    for point in np.nonzero(keep)[0][np.argsort(-marginal[keep], kind="stable")]:
        frames = coverage_csc.indices[coverage_csc.indptr[point] : coverage_csc.indptr[point + 1]]
        if np.all(slack[frames] >= 1):
            keep[point] = False
            slack[frames] -= 1
            start, end = quadratic.indptr[point], quadratic.indptr[point + 1]
            marginal[quadratic.indices[start:end]] -= quadratic.data[start:end]
    return keep


def _swap_pass(problem: SparsificationProblem, keep: np.ndarray, max_rounds: int = 5) -> np.ndarray:
    """1-swap local search: replace a kept point ``i`` by an unkept ``j`` that is seen in
    every keyframe ``i`` leaves short, when that lowers ``f`` (by ``q_i + (Q x)_i - q_j -
    (Q x)_j + Q_ij``); rounds over all kept points until none improves."""
    coverage_csc = problem.coverage.tocsc()
    coverage_csr = problem.coverage
    quadratic = problem.quadratic.tocsr()
    keep = keep.copy()
    for _ in range(max_rounds):
        x = keep.astype(np.float64)
        slack = (coverage_csr @ x).astype(np.int64) - problem.required
        marginal = problem.linear + quadratic @ x
        improved = False
        for point in np.nonzero(keep)[0]:
            frames = coverage_csc.indices[
                coverage_csc.indptr[point] : coverage_csc.indptr[point + 1]
            ]
            tight = frames[slack[frames] == 0]
            if tight.size == 0:
                continue
            rows = coverage_csr[tight]
            candidates = np.nonzero(np.asarray(rows.sum(0)).reshape(-1) == tight.size)[0]
            candidates = candidates[~keep[candidates]]
            if candidates.size == 0:
                continue
            row = quadratic.getrow(point)
            pair = np.zeros(candidates.size)
            where = np.searchsorted(candidates, row.indices)
            inside = where < candidates.size
            inside[inside] = candidates[where[inside]] == row.indices[inside]
            pair[where[inside]] = row.data[inside]
            change = marginal[candidates] - pair - marginal[point]
            best = int(np.argmin(change))
            if change[best] >= -1e-12:
                continue
            other = int(candidates[best])
            keep[point], keep[other] = False, True
            frames_other = coverage_csc.indices[
                coverage_csc.indptr[other] : coverage_csc.indptr[other + 1]
            ]
            slack[frames] -= 1
            slack[frames_other] += 1
            marginal -= quadratic.getcol(point).toarray().reshape(-1)
            marginal += quadratic.getcol(other).toarray().reshape(-1)
            improved = True
        if not improved:
            break
    return _drop_pass(problem, keep)


def sparsify_greedy(problem: SparsificationProblem) -> SparsifyResult:
    """Greedy cover by cost-effectiveness, then the drop pass (module docstring).

    Raises:
        ValueError: the constraints cannot be met (never for ``b_k <= sum_i A_ki``).
    """
    start = time.perf_counter()
    keep = _greedy_complete(problem, np.zeros(problem.num_points, bool))
    seconds = time.perf_counter() - start
    return SparsifyResult(keep, problem.cost(keep), -np.inf, seconds, "greedy", "ok")


def _linearisation(
    problem: SparsificationProblem,
) -> tuple[np.ndarray, sparse.csr_matrix, np.ndarray, np.ndarray, int]:
    """Objective (n + p,), constraint matrix, lower and upper bounds of ``A x >= b`` and
    ``x_i + x_j - y_ij <= 1`` over ``[x, y]``, and p (the pairs ``i < j`` with
    ``Q_ij > 0``)."""
    n = problem.num_points
    upper = sparse.triu(problem.quadratic, 1).tocoo()
    pairs = len(upper.data)
    objective = np.concatenate((problem.linear, upper.data))
    m = problem.coverage.shape[0]
    cover = sparse.hstack((problem.coverage, sparse.csr_matrix((m, pairs))))
    index = np.arange(pairs)
    link = sparse.coo_matrix(
        (
            np.concatenate((np.ones(pairs), np.ones(pairs), -np.ones(pairs))),
            (
                np.concatenate((index, index, index)),
                np.concatenate((upper.row, upper.col, n + index)),
            ),
        ),
        shape=(pairs, n + pairs),
    )
    matrix = sparse.vstack((cover, link)).tocsr()
    lower = np.concatenate((problem.required.astype(np.float64), np.full(pairs, -np.inf)))
    upper_bound = np.concatenate((np.full(m, np.inf), np.ones(pairs)))
    return objective, matrix, lower, upper_bound, pairs


def sparsify_relaxation(problem: SparsificationProblem) -> SparsifyResult:
    """LP relaxation of the linearised programme (HiGHS), threshold 1/2, greedy repair and
    the drop pass (module docstring); ``lower_bound`` is the LP optimum."""
    start = time.perf_counter()
    if problem.num_points == 0:
        return SparsifyResult(np.zeros(0, bool), 0.0, 0.0, 0.0, "relaxation", "no points")
    objective, matrix, lower, upper, _ = _linearisation(problem)
    split = problem.coverage.shape[0]
    cover_rows, link_rows = matrix[:split], matrix[split:]
    a_ub = sparse.vstack((-cover_rows, link_rows)).tocsr()
    b_ub = np.concatenate((-lower[:split], upper[split:]))
    solution = linprog(objective, A_ub=a_ub, b_ub=b_ub, bounds=(0.0, 1.0), method="highs")
    if solution.status != 0:
        raise ValueError(f"sparsify_relaxation: the LP failed: {solution.message}")
    fractional = solution.x[: problem.num_points]
    keep = _greedy_complete(problem, fractional >= 0.5)
    seconds = time.perf_counter() - start
    return SparsifyResult(
        keep, problem.cost(keep), float(solution.fun), seconds, "relaxation", solution.message
    )


def sparsify_exact(problem: SparsificationProblem, time_limit_s: float = 60.0) -> SparsifyResult:
    """The linearised programme as a MILP (HiGHS branch and bound, x binary, y continuous),
    stopped after ``time_limit_s``: ``keep`` is the best selection found and
    ``lower_bound`` the proven bound (equal to ``cost`` when solved to optimality)."""
    start = time.perf_counter()
    if problem.num_points == 0:
        return SparsifyResult(np.zeros(0, bool), 0.0, 0.0, 0.0, "exact", "no points")
    objective, matrix, lower, upper, pairs = _linearisation(problem)
    integrality = np.concatenate((np.ones(problem.num_points), np.zeros(pairs)))
    solution = milp(
        objective,
        constraints=LinearConstraint(matrix, lower, upper),
        integrality=integrality,
        bounds=Bounds(0.0, 1.0),
        options={"time_limit": float(time_limit_s)},
    )
    if solution.x is None:
        raise ValueError(f"sparsify_exact: no feasible selection found: {solution.message}")
    keep = solution.x[: problem.num_points] > 0.5
    bound = getattr(solution, "mip_dual_bound", None)
    seconds = time.perf_counter() - start
    return SparsifyResult(
        keep,
        problem.cost(keep),
        float(bound) if bound is not None else -np.inf,
        seconds,
        "exact",
        solution.message,
    )
