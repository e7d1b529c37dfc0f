"""Batched Levenberg-Marquardt over a :class:`~msf_torch.backend.problem.Problem`.

Each iteration solves ``(H + lambda D) dx = -g`` for all B problems at once, where ``H`` is
the Gauss-Newton Hessian, ``g`` the gradient and ``D`` the damping matrix (``diag(H)``
clamped below, Marquardt's scaling, or the identity). A step is accepted per problem when
the gain ratio ``rho = (cost - cost_new) / predicted_decrease`` is positive; the damping is
then updated by Nielsen's rule (``lambda *= max(1/3, 1 - (2 rho - 1)^3)``) and otherwise
multiplied by a growing factor. Damping, acceptance and convergence are kept per problem,
so a batch is B independent solves. Problems that have finished are dropped from the batch
once at most ``compact_below`` of it is still running (dense and chain paths, when every
factor type declares its batched data), so a few slow problems do not carry the whole
batch through their last iterations; the results are unchanged.

Linear solvers:

* ``dense``: batched Cholesky of the (B, n, n) system (windows, training); when the
  Hessian is block-tridiagonal (one kind of variable, factors only between neighbours:
  keyframe chains) a block Cholesky in O(n d^2), on blocks assembled straight from the
  factor Jacobians (``chain=True``, the default: no dense (B, n, n) matrix is formed, see
  :meth:`~msf_torch.backend.problem.Problem.linearize_chain`). Differentiable:
  gradients flow through every iteration (unrolled) to factor noise and measurements.
  With ``eliminate=GROUP`` the block-diagonal part of that group (landmarks) is removed by
  the Schur complement first and back-substituted after.
* ``sparse``: the B systems are stacked block-diagonally into one sparse matrix and
  factorised with a fill-reducing ordering, by MKL PARDISO through ``pypardiso`` when it is
  installed (extra ``[fast]``; CPU, symbolic analysis reused across iterations) or else by
  CHOLMOD's supernodal Cholesky through ``cholespy`` (CPU and CUDA; its wheel bundles
  reference BLAS, about 5x slower on 15k-unknown pose graphs). Not differentiable.

Gradients: the unrolled derivative of the iterates converges to the implicit-function
derivative of the optimum more slowly than the iterates converge. ``gradient_steps``
Gauss-Newton steps taken after convergence (value no-ops at the optimum, dense path) let
the derivative catch up; use about 10 when training through the solve.

Convergence (per problem): a step is accepted and the relative decrease of the cost is
below ``relative_tolerance``, or the cost is below ``absolute_tolerance``, or the step is
shorter than ``step_tolerance`` (relative to the variables), or the damping exceeds
``max_damping`` (no descent found: status ``"stalled"``).
"""

from __future__ import annotations

__all__ = ["LMConfig", "LMResult", "solve", "sparse_backend_available"]

import functools
from dataclasses import dataclass, field

import torch

from msf_torch.backend.problem import Linearization, Problem


@dataclass
class LMConfig:
    """Settings of :func:`solve` (defaults suit windows and pose graphs)."""

    max_iterations: int = 50
    initial_damping: float = 1e-5
    damping: str = "marquardt"  # or "identity"
    min_diagonal: float = 1e-6
    max_damping: float = 1e10
    relative_tolerance: float = 1e-10
    absolute_tolerance: float = 1e-12
    step_tolerance: float = 1e-12
    damping_update: str = "nielsen"  # or "multiplicative" (divide / multiply by damping_factor)
    damping_factor: float = 10.0
    linear_solver: str = "auto"  # "dense", "sparse" or "auto" (dense up to 1500 unknowns)
    eliminate: str | None = None
    gradient_steps: int = 0
    sparse_backend: str = "auto"  # "pardiso" (MKL, CPU), "cholespy" (CPU/CUDA) or "auto"
    chain: bool = True  # block-tridiagonal problems: assemble blocks, never the dense matrix
    compact_below: float = 0.75  # drop finished problems once at most this share is active


@dataclass
class LMResult:
    """Outcome of :func:`solve` for B problems.

    Attributes:
        values: optimised variable values ``{group: (B, N, S)}``.
        initial_cost, cost: (B,) cost before and after (0.5 * sum of robust losses).
        iterations: (B,) accepted-or-rejected iterations run while the problem was active.
        converged: (B,) bool.
        status: list of B strings: "converged", "stalled" or "max_iterations".
        log: one dict per iteration with (B,) tensors ``cost``, ``step_norm``, ``damping``,
            ``accepted``.
    """

    values: dict[str, torch.Tensor]
    initial_cost: torch.Tensor
    cost: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    status: list[str]
    log: list[dict[str, torch.Tensor]] = field(default_factory=list)


def _damping_diagonal(diagonal: torch.Tensor, config: LMConfig) -> torch.Tensor:
    if config.damping == "identity":
        return torch.ones_like(diagonal)
    return diagonal.clamp_min(config.min_diagonal)


def _solve_dense(
    problem: Problem, lin: Linearization, damping: torch.Tensor, config: LMConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step (B, n) and success flags (B,) of the damped dense system."""
    hessian = lin.hessian
    diag = torch.diagonal(hessian, dim1=-2, dim2=-1)
    damped = hessian.clone()
    damped.diagonal(dim1=-2, dim2=-1).add_(damping[:, None] * _damping_diagonal(diag, config))
    rhs = -lin.gradient
    if config.eliminate is not None:
        return _solve_schur(problem, damped, rhs, config.eliminate)
    block = problem.block_tridiagonal_size()
    if block is not None and problem.dim // block >= 3:
        return _solve_block_tridiagonal(damped, rhs, block)
    chol, info = torch.linalg.cholesky_ex(damped)
    ok = info == 0
    if bool(ok.all()):
        return torch.cholesky_solve(rhs[..., None], chol).squeeze(-1), ok
    chol = torch.where(
        ok[:, None, None], chol, torch.eye(problem.dim, dtype=chol.dtype, device=chol.device)
    )
    step = torch.cholesky_solve(rhs[..., None], chol).squeeze(-1)
    return torch.where(ok[:, None], step, torch.zeros_like(step)), ok


def _solve_block_tridiagonal(
    damped: torch.Tensor, rhs: torch.Tensor, block: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Block Cholesky of a dense block-tridiagonal system (B, n, n) with blocks of
    ``block``: its blocks are taken out and passed to :func:`_solve_blocks`."""
    batch, count = damped.shape[0], damped.shape[-1] // block
    grid = damped.reshape(batch, count, block, count, block)
    diagonal = torch.diagonal(grid, dim1=1, dim2=3).permute(0, 3, 1, 2)
    lower = torch.diagonal(grid[:, 1:, :, :-1], dim1=1, dim2=3).permute(0, 3, 1, 2)
    return _solve_blocks(diagonal, lower, rhs)


def _solve_blocks(
    diagonal: torch.Tensor,
    lower: torch.Tensor,
    rhs: torch.Tensor,
    added_diagonal: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step (B, K d) and success flags (B,) of the block-tridiagonal system with diagonal
    blocks (B, K, d, d) (plus ``added_diagonal`` (B, K, d) on their diagonals, the damping)
    and sub-diagonal blocks ``A_{i+1,i}`` (B, K - 1, d, d): block Cholesky
    ``L_i L_i^T = A_ii - C_i C_i^T``, ``C_i = A_{i,i-1} L_{i-1}^-T``, then the two block
    substitutions. O(K d^3) instead of O(K^3 d^3)."""
    batch, count, block = diagonal.shape[0], diagonal.shape[1], diagonal.shape[-1]
    # each diagonal block carries its right-hand side as an extra column, so one triangular
    # solve gives both C_i = A_{i,i-1} L_{i-1}^-T and y_{i-1}^T = b_{i-1}^T L_{i-1}^-T (solved
    # from the right: the blocks are taken row-major as they are, faster than C_i^T from the
    # left), and one product updates [A_ii | b_i] by C_i [C_i^T | y_{i-1}]
    augmented = torch.cat((diagonal, rhs.reshape(batch, count, block, 1)), -1)
    if added_diagonal is not None:
        augmented[..., :block].diagonal(dim1=-2, dim2=-1).add_(added_diagonal)
    eye = torch.eye(block, dtype=diagonal.dtype, device=diagonal.device)
    factors, couplings, forward = [], [None], []
    ok = torch.ones(batch, dtype=torch.bool, device=diagonal.device)
    current = augmented[:, 0]
    for i in range(count):
        if i > 0:
            solved = torch.linalg.solve_triangular(
                factors[-1].mT,
                torch.cat((lower[:, i - 1], current[..., block:].mT), -2),
                upper=True,
                left=False,
            )  # (B, d + 1, d): [C_i; y_{i-1}^T]
            coupling = solved[..., :block, :]
            couplings.append(coupling)
            forward.append(solved[..., block:, :].mT)
            current = augmented[:, i] - coupling @ solved.mT
        chol, info = torch.linalg.cholesky_ex(current[..., :block])
        if bool(info.any()):
            failed = info != 0
            ok = ok & ~failed
            chol = torch.where(failed[:, None, None], eye, chol)
        factors.append(chol)
    forward.append(torch.linalg.solve_triangular(factors[-1], current[..., block:], upper=False))
    backward = [None] * count
    for i in reversed(range(count)):
        y = forward[i]
        if i + 1 < count:
            y = y - couplings[i + 1].mT @ backward[i + 1]
        backward[i] = torch.linalg.solve_triangular(factors[i].mT, y, upper=True)
    step = torch.cat(backward, 1).reshape(rhs.shape)
    return torch.where(ok[:, None], step, torch.zeros_like(step)), ok


def _solve_chain(
    lin: Linearization, damping: torch.Tensor, config: LMConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step (B, n) and success flags (B,) of the damped block-tridiagonal system."""
    diag = torch.diagonal(lin.diagonal, dim1=-2, dim2=-1)  # (B, K, d)
    added = damping[:, None, None] * _damping_diagonal(diag, config)
    return _solve_blocks(lin.diagonal, lin.lower, -lin.gradient, added)


def _solve_schur(
    problem: Problem, damped: torch.Tensor, rhs: torch.Tensor, group: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eliminate ``group`` (3x3 diagonal blocks, e.g. landmarks) by the Schur complement."""
    cols = problem.group_columns[group]
    dim = problem.kinds[group].tangent_dim
    free_cols = cols[cols >= 0]
    if free_cols.numel() == 0:
        return _solve_dense_plain(damped, rhs)
    start = int(free_cols.min())
    stop = int(free_cols.max()) + dim
    if stop != problem.dim:
        raise ValueError(f"eliminated group {group!r} must be the last variable group")
    count = (stop - start) // dim
    batch = damped.shape[0]
    a = damped[:, :start, :start]
    b = damped[:, :start, start:]
    c_blocks = damped[:, start:, start:].reshape(batch, count, dim, count, dim)
    c_blocks = torch.diagonal(c_blocks, dim1=1, dim2=3).permute(0, 3, 1, 2)  # (B, M, d, d)
    c_inv = torch.linalg.inv(c_blocks)
    b_split = b.reshape(batch, start, count, dim)
    b_cinv = torch.einsum("bpmi,bmij->bpmj", b_split, c_inv).reshape(batch, start, count * dim)
    schur = a - b_cinv @ b.mT
    rhs_p, rhs_l = rhs[:, :start], rhs[:, start:]
    reduced = rhs_p - (b_cinv @ rhs_l[..., None]).squeeze(-1)
    chol, info = torch.linalg.cholesky_ex(schur)
    ok = info == 0
    chol = torch.where(
        ok[:, None, None], chol, torch.eye(start, dtype=chol.dtype, device=chol.device)
    )
    step_p = torch.cholesky_solve(reduced[..., None], chol).squeeze(-1)
    back = (rhs_l - (b.mT @ step_p[..., None]).squeeze(-1)).reshape(batch, count, dim)
    step_l = (c_inv @ back[..., None]).squeeze(-1).reshape(batch, count * dim)
    step = torch.cat((step_p, step_l), -1)
    return torch.where(ok[:, None], step, torch.zeros_like(step)), ok


def _solve_dense_plain(
    damped: torch.Tensor, rhs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    chol, info = torch.linalg.cholesky_ex(damped)
    ok = info == 0
    step = torch.cholesky_solve(rhs[..., None], chol).squeeze(-1)
    return torch.where(ok[:, None], step, torch.zeros_like(step)), ok


def sparse_backend_available(name: str) -> bool:
    """Whether a sparse factorisation backend (``"pardiso"`` or ``"cholespy"``) is installed."""
    import importlib.util

    module = {"pardiso": "pypardiso", "cholespy": "cholespy"}[name]
    return importlib.util.find_spec(module) is not None


def _sparse_backend(config: LMConfig, device: torch.device) -> str:
    if config.sparse_backend != "auto":
        return config.sparse_backend
    if device.type == "cpu" and sparse_backend_available("pardiso"):
        return "pardiso"
    return "cholespy"


@functools.lru_cache(maxsize=1)
def _pardiso_solver():
    """One shared PARDISO handle (creating one searches the MKL install, ~0.3 s)."""
    import pypardiso

    return pypardiso.PyPardisoSolver(mtype=2)


class _PardisoSystem:
    """Upper triangle of the stacked sparse system in CSR order, factorised by MKL PARDISO
    (symmetric positive definite, ``mtype=2``, nested-dissection ordering).

    The pattern is the same at every iteration, so its symbolic analysis (ordering and
    elimination tree, PARDISO phase 11) is done once and each solve runs the numerical
    factorisation and the solve only (phase 23): on w10000 (30,000 unknowns) 0.036 s per
    solve instead of 0.087 s, the same steps bit for bit. The handle is shared (making one
    costs ~0.3 s), so the analysis is redone when another system used it in between."""

    def __init__(self, problem: Problem) -> None:
        import numpy as np

        rows, cols = problem.sparse_pattern()
        upper = torch.nonzero(rows <= cols).squeeze(-1)
        order = torch.argsort(rows[upper] * (problem.batch_size * problem.dim) + cols[upper])
        self.select = upper[order].cpu()
        csr_rows = rows[self.select].cpu().numpy()
        self.indices = cols[self.select].cpu().numpy().astype(np.int32)
        size = problem.batch_size * problem.dim
        self.indptr = np.searchsorted(csr_rows, np.arange(size + 1)).astype(np.int32)
        self.size = size
        self.solver = _pardiso_solver()

    def solve(self, values: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """Step (n,) float64; NaN where PARDISO refuses the system (non-finite or
        overflowing entries), which the LM treats as a failed solve (more damping)."""
        import numpy as np
        import scipy.sparse
        from pypardiso.pardiso_wrapper import PyPardisoError

        data = values.cpu().to(torch.float64)[self.select].numpy()  # PARDISO: float64 only
        matrix = scipy.sparse.csr_matrix(
            (data, self.indices, self.indptr), shape=(self.size, self.size)
        )
        right = rhs.cpu().to(torch.float64).numpy().reshape(-1, 1)
        solver = self.solver
        try:
            if getattr(solver, "msf_analysed", None) is not self:
                solver.msf_analysed = None
                solver.set_phase(11)
                solver._call_pardiso(matrix, np.zeros_like(right))
                solver.msf_analysed = self
            solver.set_phase(23)
            return torch.from_numpy(np.ravel(solver._call_pardiso(matrix, right)))
        except PyPardisoError:
            solver.msf_analysed = None
            return torch.full((self.size,), torch.nan, dtype=torch.float64)


def _solve_sparse(
    problem: Problem, lin: Linearization, damping: torch.Tensor, config: LMConfig, cache: dict
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step (B, n) from one sparse Cholesky of the block-diagonal stack of the B systems."""
    rows, cols = problem.sparse_pattern()
    diag_pos = problem.sparse_diagonal_positions()
    values = lin.sparse_values.detach().clone()
    diag = values[diag_pos].reshape(problem.batch_size, problem.dim)
    values[diag_pos] += (damping[:, None] * _damping_diagonal(diag, config)).reshape(-1)
    total = problem.batch_size * problem.dim
    device = values.device
    rhs = (-lin.gradient.detach()).reshape(total, 1).contiguous()
    if _sparse_backend(config, device) == "pardiso":
        if "pardiso" not in cache:
            cache["pardiso"] = _PardisoSystem(problem)
        step = cache["pardiso"].solve(values, rhs).to(device=device, dtype=values.dtype)
    else:
        import cholespy

        solver = cholespy.CholeskySolverD(  # double precision only
            total,
            rows.to(torch.int32).contiguous(),
            cols.to(torch.int32).contiguous(),
            values.to(torch.float64).contiguous(),
            cholespy.MatrixType.COO,
        )
        right = rhs.to(torch.float64).contiguous()
        step = torch.zeros_like(right)
        solver.solve(right, step)
        step = step.to(values.dtype)
    step = step.reshape(problem.batch_size, problem.dim)
    ok = torch.isfinite(step).all(-1)
    step = torch.where(ok[:, None], step, torch.zeros_like(step))
    return step, ok


def solve(problem: Problem, config: LMConfig | None = None) -> LMResult:
    """Minimise the B problems' costs by Levenberg-Marquardt.

    Args:
        problem: the problems; its ``values`` are the initial estimate (not modified).
        config: :class:`LMConfig`.
    Returns:
        :class:`LMResult`.
    """
    config = config or LMConfig()
    solver = config.linear_solver
    if solver == "auto":
        solver = "dense" if problem.dim <= 1500 or config.eliminate is not None else "sparse"
    if solver not in ("dense", "sparse"):
        raise ValueError(f"linear_solver must be 'dense', 'sparse' or 'auto', got {solver!r}")
    sparse = solver == "sparse"
    block = None if sparse or config.eliminate is not None else problem.block_tridiagonal_size()
    chain = config.chain and block is not None and problem.dim // block >= 3
    compact = not sparse and config.compact_below > 0.0 and problem.selectable
    batch = problem.batch_size
    dtype, device = problem.dtype, problem.device
    sparse_cache: dict = {}

    def linearize(current: Problem, at: dict[str, torch.Tensor]) -> Linearization:
        if chain:
            return current.linearize_chain(at)
        return current.linearize(at, sparse=sparse)

    def linear_step(
        current: Problem, lin: Linearization, damping: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if chain:
            return _solve_chain(lin, damping, config)
        if sparse:
            return _solve_sparse(current, lin, damping, config, sparse_cache)
        return _solve_dense(current, lin, damping, config)

    values = dict(problem.values)
    lin = linearize(problem, values)
    initial_cost = lin.cost.detach().clone()
    damping = torch.full((batch,), config.initial_damping, dtype=dtype, device=device)
    growth = torch.full((batch,), 2.0, dtype=dtype, device=device)
    # nothing free (e.g. a pose graph of its one fixed vertex): converged as it stands
    converged = torch.full((batch,), problem.dim == 0, dtype=torch.bool, device=device)
    active = ~converged
    stalled = torch.zeros(batch, dtype=torch.bool, device=device)
    iterations = torch.zeros(batch, dtype=torch.long, device=device)
    log: list[dict[str, torch.Tensor]] = []
    # the problems still carried: all of them, or (after dropping finished ones) ``rows``
    current, rows = problem, None
    final_values, final_cost, final_damping = values, lin.cost, damping

    def widen(part: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """Per-problem values of the carried problems placed into the full batch ``base``."""
        return part if rows is None else base.index_copy(0, rows, part)

    for _ in range(config.max_iterations):
        if not bool(active.any()):
            break
        carried = active.shape[0]
        running = int(active.sum())
        if compact and running < carried and running <= config.compact_below * carried:
            final_values = {k: widen(v, final_values[k]) for k, v in values.items()}
            final_cost, final_damping = widen(lin.cost, final_cost), widen(damping, final_damping)
            keep = torch.nonzero(active).squeeze(-1)
            rows = keep if rows is None else rows[keep]
            current = current.select(keep)
            values = {k: v[keep] for k, v in values.items()}
            lin = _select(lin, keep)
            damping, growth, active = damping[keep], growth[keep], active[keep]
        step, ok = linear_step(current, lin, damping)
        step = step * active[:, None].to(dtype)
        candidate = current.retract(values, step)
        new_lin = linearize(current, candidate)
        predicted = -(lin.gradient * step).sum(-1) - 0.5 * _quadratic(current, lin, step, sparse)
        actual = lin.cost - new_lin.cost
        gain = actual / predicted.clamp_min(torch.finfo(dtype).tiny)
        accept = active & ok & (actual > 0) & torch.isfinite(new_lin.cost)
        step_norm = step.detach().norm(dim=-1)
        near_gauss_newton = damping <= config.initial_damping
        iterations = iterations + widen(active.long(), torch.zeros_like(iterations))
        log.append(
            {
                "cost": widen(torch.where(accept, new_lin.cost, lin.cost), final_cost).detach(),
                "step_norm": widen(step_norm, torch.zeros_like(final_cost.detach())),
                "damping": widen(damping, final_damping).detach().clone(),
                "accepted": widen(accept, torch.zeros_like(converged)).clone(),
            }
        )
        if config.damping_update == "multiplicative":
            damping = torch.where(
                accept, damping / config.damping_factor, damping * config.damping_factor
            )
        else:
            scale = torch.clamp(1.0 - (2.0 * gain.detach() - 1.0) ** 3, min=1.0 / 3.0)
            damping = torch.where(accept, damping * scale, damping * growth)
            growth = torch.where(accept, torch.full_like(growth, 2.0), growth * 2.0)
        small_change = actual.detach().abs() <= config.relative_tolerance * lin.cost.detach().abs()
        tiny_cost = new_lin.cost.detach() <= config.absolute_tolerance
        x_norm = torch.cat(
            [v.detach().reshape(active.shape[0], -1) for v in values.values()], -1
        ).norm(dim=-1)
        # a failed solve gives a zero step: that is no convergence (more damping, retry)
        tiny_step = ok & (step_norm <= config.step_tolerance * (x_norm + config.step_tolerance))
        # the Gauss-Newton model itself promises no relative decrease worth taking
        flat_model = predicted.detach() <= config.relative_tolerance * lin.cost.detach().abs()
        done = active & (
            (accept & (small_change | tiny_cost))
            | tiny_step
            | (ok & flat_model & near_gauss_newton)
        )
        stall = active & ~accept & (damping > config.max_damping)
        if bool(accept.all()):
            values = candidate
        elif bool(accept.any()):
            values = {k: _where_batch(accept, candidate[k], v) for k, v in values.items()}
        lin = _merge(accept, new_lin, lin)
        converged = converged | widen(done, torch.zeros_like(converged))
        stalled = stalled | widen(stall, torch.zeros_like(stalled))
        active = active & ~done & ~stall
    if rows is not None:
        values = {k: widen(v, final_values[k]) for k, v in values.items()}
        cost = widen(lin.cost, final_cost)
        damping = widen(damping, final_damping)
        lin = linearize(problem, values) if config.gradient_steps and not sparse else None
    else:
        cost = lin.cost
    for _ in range(config.gradient_steps if not sparse else 0):
        step, ok = linear_step(problem, lin, torch.full_like(damping, 1e-12))
        values = problem.retract(values, step * ok[:, None].to(dtype))
        lin = linearize(problem, values)
        cost = lin.cost
    status = [
        "converged" if c else ("stalled" if s else "max_iterations")
        for c, s in zip(converged.tolist(), stalled.tolist(), strict=True)
    ]
    return LMResult(values, initial_cost, cost, iterations, converged, status, log)


def _quadratic(
    problem: Problem, lin: Linearization, step: torch.Tensor, sparse: bool
) -> torch.Tensor:
    """``step^T H step`` (B,) for the undamped Gauss-Newton Hessian."""
    if lin.diagonal is not None:
        count, block = lin.diagonal.shape[1], lin.diagonal.shape[-1]
        pieces = step.reshape(step.shape[0], count, block)
        # one matrix-vector product per block, then dot products
        on_diagonal = ((lin.diagonal @ pieces[..., None]).squeeze(-1) * pieces).sum((1, 2))
        coupled = ((lin.lower @ pieces[:, :-1, :, None]).squeeze(-1) * pieces[:, 1:]).sum((1, 2))
        return on_diagonal + 2.0 * coupled
    if not sparse:
        return (step[:, None, :] @ lin.hessian @ step[..., None]).reshape(-1)
    rows, cols = problem.sparse_pattern()
    flat = step.detach().reshape(-1)
    product = torch.zeros_like(flat).index_add(0, rows, lin.sparse_values.detach() * flat[cols])
    return (flat * product).reshape(problem.batch_size, problem.dim).sum(-1)


def _where_batch(mask: torch.Tensor, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
    return torch.where(mask.reshape(-1, *([1] * (new.dim() - 1))), new, old)


def _select(lin: Linearization, index: torch.Tensor) -> Linearization:
    """The linearisation of problems ``index`` (dense and chain layouts)."""

    def pick(x: torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None else x[index]

    return Linearization(
        cost=lin.cost[index],
        gradient=lin.gradient[index],
        hessian=pick(lin.hessian),
        diagonal=pick(lin.diagonal),
        lower=pick(lin.lower),
    )


def _merge(accept: torch.Tensor, new: Linearization, old: Linearization) -> Linearization:
    """Per problem, the new linearisation where the step was accepted, else the old one: the
    rejected problems' rows of ``old`` are copied into ``new`` in place (usually a few)."""
    if bool(accept.all()):
        return new
    if not bool(accept.any()):
        return old
    reject = torch.nonzero(~accept).squeeze(-1)

    def keep_old(part: torch.Tensor | None, previous: torch.Tensor | None) -> torch.Tensor | None:
        if part is not None:
            part[reject] = previous[reject]
        return part

    sparse_values = None
    if new.sparse_values is not None:
        batch = accept.shape[0]
        mask = accept.repeat_interleave(new.sparse_values.numel() // batch)
        sparse_values = torch.where(mask, new.sparse_values, old.sparse_values)
    return Linearization(
        cost=torch.where(accept, new.cost, old.cost),
        gradient=keep_old(new.gradient, old.gradient),
        hessian=keep_old(new.hessian, old.hessian),
        sparse_values=sparse_values,
        diagonal=keep_old(new.diagonal, old.diagonal),
        lower=keep_old(new.lower, old.lower),
    )
