"""Least-squares problems: variable tables, factor types and the normal equations.

A :class:`Problem` holds B independent problems of the same structure. Its variables are
named groups (``"state"``, ``"landmark"``, ...), each a :class:`VariableKind` with values
(B, N, S); its factors are :class:`Factor` objects, each a *type* of F factors stored as a
struct of arrays: per slot an index tensor (F,) into one variable group, a square-root
information (whitening) matrix and an optional robust kernel. The cost of one problem is

    0.5 * sum_f rho_f(|W_f r_f(x)|^2)        (GTSAM's convention; rho(s) = s without kernel)

Linearising gives the Gauss-Newton system ``H dx = -g`` on the stacked tangent vector of the
free variables (variables can be held fixed). It is assembled either dense and batched
(B, n, n) for small windows, or as one sparse COO matrix for large problems, B problems
placed block-diagonally; the index structure is computed once per problem and reused.
"""

from __future__ import annotations

__all__ = ["Factor", "Problem", "Linearization"]

from dataclasses import dataclass, field

import torch

from msf_torch.backend.robust import RobustKernel
from msf_torch.backend.variables import KINDS, VariableKind


class Factor:
    """A type of factor: F residuals of size R, each joining one variable per slot.

    Subclasses set ``slots``, ``sqrt_information`` and ``kernel`` and implement
    :meth:`residual`; they may override :meth:`residual_and_jacobians` with analytic
    Jacobians (the default differentiates :meth:`residual` by forward-mode autodiff on the
    tangent space, exact to round-off).

    Attributes:
        slots: ``((group name, index (F,) int64), ...)``, one per connected variable.
        sqrt_information: ``W`` broadcastable to (B, F, R, R); whitened residual ``W r``.
        kernel: robust kernel, or None for plain least squares.
    """

    slots: tuple[tuple[str, torch.Tensor], ...]
    sqrt_information: torch.Tensor
    kernel: RobustKernel | None = None
    kinds: list[VariableKind]  # set by the Problem: the kind of each slot

    @property
    def size(self) -> int:
        """F, the number of factors of this type."""
        return int(self.slots[0][1].shape[0])

    def residual(self, values: list[torch.Tensor]) -> torch.Tensor:
        """Residuals (B, F, R) from the connected values, one (B, F, S_slot) per slot."""
        raise NotImplementedError

    def residual_and_jacobians(
        self, values: list[torch.Tensor], kinds: list[VariableKind]
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Residuals (B, F, R) and per-slot Jacobians (B, F, R, D_slot) w.r.t. the tangent
        step ``x <- retract(x, dx)`` at ``dx = 0``."""
        zeros = [
            torch.zeros(*v.shape[:-1], k.tangent_dim, dtype=v.dtype, device=v.device)
            for v, k in zip(values, kinds, strict=True)
        ]

        def moved(*steps: torch.Tensor) -> torch.Tensor:
            return self.residual(
                [k.retract(v, s) for v, s, k in zip(values, steps, kinds, strict=True)]
            )

        basis = []
        for slot, kind in enumerate(kinds):
            for dim in range(kind.tangent_dim):
                basis.append([_one_hot(z, dim) if i == slot else z for i, z in enumerate(zeros)])
        stacked = [torch.stack([b[i] for b in basis]) for i in range(len(kinds))]
        residual = self.residual(values)

        def directional(*tangents: torch.Tensor) -> torch.Tensor:
            return torch.func.jvp(moved, tuple(zeros), tangents)[1]

        columns = torch.func.vmap(directional)(*stacked)  # (sum D, B, F, R)
        jacobians = []
        start = 0
        for kind in kinds:
            block = columns[start : start + kind.tangent_dim]
            jacobians.append(block.permute(1, 2, 3, 0))
            start += kind.tangent_dim
        return residual, jacobians


def _one_hot(like: torch.Tensor, dim: int) -> torch.Tensor:
    out = torch.zeros_like(like)
    out[..., dim] = 1.0
    return out


@dataclass
class Linearization:
    """One linearisation of B problems.

    Attributes:
        cost: (B,) 0.5 * sum of robust losses.
        hessian: dense (B, n, n) or None (sparse path).
        gradient: (B, n) ``J^T W^T W r`` (robust-weighted).
        sparse_values: (nnz,) values of the sparse pattern (sparse path) or None.
    """

    cost: torch.Tensor
    gradient: torch.Tensor
    hessian: torch.Tensor | None = None
    sparse_values: torch.Tensor | None = None


@dataclass
class _SlotLayout:
    columns: torch.Tensor  # (F,) first column of each connected variable, -1 when fixed
    dim: int


@dataclass
class Problem:
    """B least-squares problems sharing one structure.

    Args:
        variables: ``{group: (kind name or VariableKind, values (B, N, S))}``.
        factors: factor types (see :class:`Factor`).
        fixed: ``{group: (N,) bool}`` variables held constant (gauge, known poses).
    """

    variables: dict[str, tuple[VariableKind | str, torch.Tensor]]
    factors: list[Factor]
    fixed: dict[str, torch.Tensor] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.kinds: dict[str, VariableKind] = {}
        self.values: dict[str, torch.Tensor] = {}
        for name, (kind, value) in self.variables.items():
            kind = KINDS[kind] if isinstance(kind, str) else kind
            if value.dim() != 3 or value.shape[-1] != kind.storage_dim:
                raise ValueError(
                    f"variable group {name!r}: values must be (B, N, {kind.storage_dim}), "
                    f"got {tuple(value.shape)}"
                )
            self.kinds[name] = kind
            self.values[name] = value
        first = next(iter(self.values.values()))
        for factor in self.factors:
            factor.kinds = [self.kinds[g] for g, _ in factor.slots]
        self.batch_size = first.shape[0]
        self.dtype, self.device = first.dtype, first.device
        self._build_layout()

    def _build_layout(self) -> None:
        """Column of every free variable in the stacked tangent vector; -1 for fixed."""
        self.group_columns: dict[str, torch.Tensor] = {}
        start = 0
        for name, value in self.values.items():
            count = value.shape[1]
            dim = self.kinds[name].tangent_dim
            free = torch.ones(count, dtype=torch.bool, device=self.device)
            if name in self.fixed:
                free = ~self.fixed[name].to(device=self.device, dtype=torch.bool)
            rank = torch.cumsum(free.long(), 0) - 1
            cols = torch.where(free, start + rank * dim, torch.full_like(rank, -1))
            self.group_columns[name] = cols
            start += int(free.sum()) * dim
        self.dim = start
        self.slot_layouts = [
            [
                _SlotLayout(self.group_columns[g][idx], self.kinds[g].tangent_dim)
                for g, idx in f.slots
            ]
            for f in self.factors
        ]
        self._dense_index: tuple[torch.Tensor, torch.Tensor] | None = None
        self._block_size: int | None = None
        self._sparse_pattern: tuple[torch.Tensor, torch.Tensor, list] | None = None

    # -- evaluation ---------------------------------------------------------------------

    def gathered(self, factor: Factor, values: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """Values of each slot of ``factor``: list of (B, F, S)."""
        return [values[g][:, idx] for g, idx in factor.slots]

    def whitened(
        self, values: dict[str, torch.Tensor], jacobians: bool = True
    ) -> list[tuple[torch.Tensor, list[torch.Tensor] | None, torch.Tensor]]:
        """Per factor type: robust-reweighted whitened residual (B, F, R), Jacobians
        (B, F, R, D) or None, and the robust loss per factor (B, F)."""
        out = []
        for factor in self.factors:
            slot_values = self.gathered(factor, values)
            kinds = [self.kinds[g] for g, _ in factor.slots]
            if jacobians:
                residual, jacs = factor.residual_and_jacobians(slot_values, kinds)
            else:
                residual, jacs = factor.residual(slot_values), None
            sqrt_info = factor.sqrt_information
            white = (sqrt_info @ residual[..., None]).squeeze(-1)
            squared = (white * white).sum(-1)
            if factor.kernel is None:
                loss = 0.5 * squared
                scale = None
            else:
                loss = factor.kernel.loss(squared)
                scale = torch.sqrt(factor.kernel.weight(squared))
                white = white * scale[..., None]
            if jacs is not None:
                jacs = [sqrt_info @ j for j in jacs]
                if scale is not None:
                    jacs = [j * scale[..., None, None] for j in jacs]
            out.append((white, jacs, loss))
        return out

    def cost(self, values: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) total cost 0.5 * sum rho(|W r|^2)."""
        total = torch.zeros(self.batch_size, dtype=self.dtype, device=self.device)
        for _, _, loss in self.whitened(values, jacobians=False):
            total = total + loss.sum(-1)
        return total

    def retract(
        self, values: dict[str, torch.Tensor], step: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Move every free variable by its part of ``step`` (B, n); fixed ones stay."""
        moved = {}
        for name, value in values.items():
            cols = self.group_columns[name]
            dim = self.kinds[name].tangent_dim
            free = cols >= 0
            if not bool(free.any()):
                moved[name] = value
                continue
            index = (cols.clamp_min(0)[:, None] + torch.arange(dim, device=self.device)).reshape(-1)
            local = step[:, index].reshape(step.shape[0], -1, dim)
            local = local * free[None, :, None].to(step.dtype)
            moved[name] = self.kinds[name].retract(value, local)
        return moved

    # -- assembly -----------------------------------------------------------------------

    def _block_entries(
        self, factor_index: int, a: int, b: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rows, columns (F', Da, Db) and factor selection (F',) of block (a, b)."""
        la, lb = self.slot_layouts[factor_index][a], self.slot_layouts[factor_index][b]
        keep = torch.nonzero((la.columns >= 0) & (lb.columns >= 0)).squeeze(-1)
        ra = (
            la.columns[keep][:, None, None]
            + torch.arange(la.dim, device=self.device)[None, :, None]
        )
        cb = (
            lb.columns[keep][:, None, None]
            + torch.arange(lb.dim, device=self.device)[None, None, :]
        )
        rows, cols = torch.broadcast_tensors(ra, cb)
        return rows, cols, keep

    def _factor_columns(self, factor_index: int) -> torch.Tensor:
        """Columns (F, sum D) of every tangent entry of each factor's variables; -1 where the
        variable is fixed."""
        pieces = []
        for layout in self.slot_layouts[factor_index]:
            offsets = torch.arange(layout.dim, device=self.device)
            cols = layout.columns[:, None] + offsets
            pieces.append(
                torch.where(layout.columns[:, None] >= 0, cols, torch.full_like(cols, -1))
            )
        return torch.cat(pieces, -1)

    def _dense_indices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat scatter indices of all gradient entries and all Hessian blocks, every factor
        type concatenated; entries of fixed variables go to a spill slot past the end."""
        if self._dense_index is None:
            n = self.dim
            grad_index, hess_index = [], []
            for fi in range(len(self.factors)):
                cols = self._factor_columns(fi)
                free = cols >= 0
                grad_index.append(torch.where(free, cols, torch.full_like(cols, n)).reshape(-1))
                pair = cols[:, :, None] * n + cols[:, None, :]
                pair_free = free[:, :, None] & free[:, None, :]
                hess_index.append(
                    torch.where(pair_free, pair, torch.full_like(pair, n * n)).reshape(-1)
                )
            self._dense_index = (torch.cat(grad_index), torch.cat(hess_index))
        return self._dense_index

    def block_tridiagonal_size(self) -> int | None:
        """Block size ``d`` when every variable has tangent size ``d`` and the Hessian only
        couples neighbouring variables in column order (chains of keyframes: IMU windows),
        else None. Such systems are solved in O(n d^2) instead of O(n^3)."""
        if self._block_size is None:
            dims = {self.kinds[g].tangent_dim for g in self.values}
            size = 0
            if len(dims) == 1 and self.dim > 0:
                d = dims.pop()
                _, hess_index = self._dense_indices()
                used = hess_index[hess_index < self.dim * self.dim]
                rows, cols = used // self.dim // d, used % self.dim // d
                if used.numel() == 0 or int((rows - cols).abs().max()) <= 1:
                    size = d
            self._block_size = size
        return self._block_size or None

    def _stacked(self, lin: list) -> list[torch.Tensor]:
        """Per factor type, all slot Jacobians side by side: (B, F, R, sum D)."""
        return [torch.cat(jacs, -1) for _, jacs, _ in lin]

    def _gradient(self, lin: list, stacked: list[torch.Tensor]) -> torch.Tensor:
        grad_index, _ = self._dense_indices()
        contrib = torch.cat(
            [
                (jac.mT @ white[..., None]).reshape(self.batch_size, -1)
                for jac, (white, _, _) in zip(stacked, lin, strict=True)
            ],
            1,
        )
        grad = torch.zeros(self.batch_size, self.dim + 1, dtype=self.dtype, device=self.device)
        grad.index_add_(1, grad_index, contrib)
        return grad[:, : self.dim]

    def linearize(self, values: dict[str, torch.Tensor], sparse: bool = False) -> Linearization:
        """Cost, gradient and Gauss-Newton Hessian ``J^T J`` (dense or sparse) at ``values``."""
        lin = self.whitened(values)
        cost = sum(loss.sum(-1) for _, _, loss in lin)
        stacked = self._stacked(lin)
        grad = self._gradient(lin, stacked)
        if sparse:
            return Linearization(cost, grad, sparse_values=self._sparse_values(lin))
        return Linearization(cost, grad, hessian=self._dense_hessian(stacked))

    def _dense_hessian(self, stacked: list[torch.Tensor]) -> torch.Tensor:
        n = self.dim
        _, hess_index = self._dense_indices()
        blocks = torch.cat([(jac.mT @ jac).reshape(self.batch_size, -1) for jac in stacked], 1)
        hessian = torch.zeros(self.batch_size, n * n + 1, dtype=self.dtype, device=self.device)
        hessian.index_add_(1, hess_index, blocks)
        return hessian[:, : n * n].reshape(self.batch_size, n, n)

    def sparse_pattern(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows and columns (nnz,) of the block-diagonal stack of the B Hessians (each
        entry once, both triangles), in the order of :attr:`Linearization.sparse_values`."""
        if self._sparse_pattern is None:
            n = self.dim
            flats, pieces = [], []
            for fi, factor in enumerate(self.factors):
                for a in range(len(factor.slots)):
                    for b in range(len(factor.slots)):
                        rows, cols, keep = self._block_entries(fi, a, b)
                        flats.append((rows * n + cols).reshape(-1))
                        pieces.append((fi, a, b, keep))
            flat = torch.cat(flats)
            unique, inverse = torch.unique(flat, return_inverse=True)
            shift = torch.arange(self.batch_size, device=self.device)[:, None] * n
            rows = (unique // n)[None] + shift
            cols = (unique % n)[None] + shift
            self._sparse_pattern = (
                rows.reshape(-1),
                cols.reshape(-1),
                [inverse, pieces, unique.numel()],
            )
        return self._sparse_pattern[0], self._sparse_pattern[1]

    def _sparse_values(self, lin: list) -> torch.Tensor:
        self.sparse_pattern()
        inverse, pieces, nnz = self._sparse_pattern[2]
        blocks = []
        for fi, a, b, keep in pieces:
            jacs = lin[fi][1]
            blocks.append((jacs[a][:, keep].mT @ jacs[b][:, keep]).reshape(self.batch_size, -1))
        values = torch.zeros(self.batch_size, nnz, dtype=self.dtype, device=self.device)
        values = values.index_add(1, inverse, torch.cat(blocks, 1))
        return values.reshape(-1)

    def sparse_diagonal_positions(self) -> torch.Tensor:
        """Positions (B * n,) of the diagonal entries in the sparse values, in row order."""
        rows, cols = self.sparse_pattern()
        on_diag = torch.nonzero(rows == cols).squeeze(-1)
        order = torch.argsort(rows[on_diag])
        return on_diag[order]
