"""Least-squares problems: variable tables, factor types and the normal equations.

A :class:`Problem` holds B independent problems of the same structure. Its variables are
named groups (``"state"``, ``"landmark"``, ...), each a :class:`VariableKind` with values
(B, N, S); its factors are :class:`Factor` objects, each a *type* of F factors stored as a
struct of arrays: per slot an index tensor (F,) into one variable group, a square-root
information (whitening) matrix and an optional robust kernel. The cost of one problem is

    0.5 * sum_f rho_f(|W_f r_f(x)|^2)        (GTSAM's convention; rho(s) = s without kernel)

Linearising gives the Gauss-Newton system ``H dx = -g`` on the stacked tangent vector of the
free variables (variables can be held fixed). It is assembled either dense and batched
(B, n, n) for small windows, straight into its block-tridiagonal blocks for chains of
keyframes (:meth:`Problem.linearize_chain`: no dense matrix), or as one sparse COO matrix
for large problems, B problems placed block-diagonally; the index structure is computed
once per problem and reused.
"""

from __future__ import annotations

__all__ = ["Factor", "Problem", "Linearization", "whiten"]

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any

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
    batched: tuple[str, ...] | None = None
    """Names of the attributes besides ``sqrt_information`` whose tensors lead with the batch
    dimension (B|1, F, ...) (tensors, dataclasses or lists of tensors); None when unknown,
    and then the type cannot be cut down to a subset of the B problems (:meth:`select`)."""

    def select(self, index: torch.Tensor, batch: int) -> Factor:
        """A copy holding only problems ``index`` (B',) of the ``batch`` problems: every
        batch-leading tensor of :attr:`batched` (and ``sqrt_information``) indexed along its
        first dimension; shared ones (leading 1) are kept."""
        if self.batched is None:
            raise NotImplementedError(f"{type(self).__name__} does not declare its batched data")
        out = copy.copy(self)
        for name in self.batched:
            setattr(out, name, _select_batch(getattr(self, name), index, batch, self.size))
        sqrt_info = self.sqrt_information
        if batch > 1 and sqrt_info.dim() == 4 and sqrt_info.shape[0] == batch:
            out.sqrt_information = sqrt_info[index]
        return out

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

    def normal_blocks(
        self, values: list[torch.Tensor], kinds: list[VariableKind], pairs: list[tuple[int, int]]
    ) -> tuple[torch.Tensor, list[torch.Tensor], list[list[tuple[slice, slice, torch.Tensor]]]]:
        """This type's share of the Gauss-Newton system, per factor.

        Args:
            values: one (B, F, S_slot) per slot. kinds: the slots' variable kinds.
            pairs: slot pairs ``(a, b)`` whose blocks ``J_a^T J_b`` are wanted (whitened,
                robust-reweighted Jacobians).
        Returns:
            robust loss (B, F); gradient ``J_a^T W r`` (B, F, D_a) per slot; per pair a list
            of pieces ``(rows, cols, block (B, F, r, c))`` that add up to the (D_a, D_b) block,
            or ``(rows, rows, diagonal (B, F, r))`` for a diagonal piece (the default gives
            one piece over the span of columns where the Jacobians are nonzero; factors with
            known zero structure may override with smaller pieces).
        """
        residual, jacobians = self.residual_and_jacobians(values, kinds)
        # whitening mixes rows only: columns zero before it stay zero, so only the span of
        # nonzero columns is whitened and multiplied
        spans = [_nonzero_columns(jac) for jac in jacobians]
        used = [jac[..., span] for jac, span in zip(jacobians, spans, strict=True)]
        white, jacs, loss = whiten(self, residual, used)
        grads = [
            torch.nn.functional.pad(
                (jac.mT @ white[..., None]).squeeze(-1), (span.start, full.shape[-1] - span.stop)
            )
            for jac, span, full in zip(jacs, spans, jacobians, strict=True)
        ]
        pieces = [[(spans[a], spans[b], jacs[a].mT @ jacs[b])] for a, b in pairs]
        return loss, grads, pieces


def _select_batch(data: Any, index: torch.Tensor, batch: int, size: int) -> Any:
    """``data`` (tensor (B|1, F, ...), dataclass or list of them, or None) restricted to the
    problems ``index``; tensors that do not lead with (B, F) (shared ones with a leading 1,
    or per-type constants such as a (3,) lever arm) are kept."""
    if data is None:
        return None
    if isinstance(data, torch.Tensor):
        if batch > 1 and data.dim() >= 2 and data.shape[0] == batch and data.shape[1] == size:
            return data[index]
        return data
    if isinstance(data, list | tuple):
        return type(data)(_select_batch(x, index, batch, size) for x in data)
    if dataclasses.is_dataclass(data):
        fields = {
            f.name: _select_batch(getattr(data, f.name), index, batch, size)
            for f in dataclasses.fields(data)
        }
        return dataclasses.replace(data, **fields)
    raise TypeError(f"cannot select problems from a {type(data).__name__}")


def _nonzero_columns(jacobian: torch.Tensor) -> slice:
    """The span of columns (..., R, D) -> slice of D where any entry is nonzero (columns
    outside it contribute exact zeros to ``J^T J``)."""
    counts = torch.count_nonzero(jacobian, tuple(range(jacobian.dim() - 1)))  # (D,)
    used = torch.nonzero(counts).squeeze(-1)
    if used.numel() == 0:
        return slice(0, 0)
    return slice(int(used[0]), int(used[-1]) + 1)


def whiten(
    factor: Factor, residual: torch.Tensor, jacobians: list[torch.Tensor] | None
) -> tuple[torch.Tensor, list[torch.Tensor] | None, torch.Tensor]:
    """Robust-reweighted whitened residual (B, F, R), Jacobians (B, F, R, D) (None when not
    given) and the robust loss per factor (B, F) of ``factor``'s residual (B, F, R) and
    Jacobians."""
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
    jacs = None
    if jacobians is not None:
        jacs = [sqrt_info @ j for j in jacobians]
        if scale is not None:
            jacs = [j * scale[..., None, None] for j in jacs]
    return white, jacs, loss


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
        diagonal: (B, K, d, d) diagonal blocks ``H_kk`` of a block-tridiagonal Hessian
            (chain path) or None.
        lower: (B, K - 1, d, d) sub-diagonal blocks ``H_{k+1,k}`` (chain path) or None.
    """

    cost: torch.Tensor
    gradient: torch.Tensor
    hessian: torch.Tensor | None = None
    sparse_values: torch.Tensor | None = None
    diagonal: torch.Tensor | None = None
    lower: torch.Tensor | None = None


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
        self._group_spans: dict[str, slice] = {}  # groups with every variable free
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
            if count > 0 and bool(free.all()):
                self._group_spans[name] = slice(start, start + count * dim)
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
        self._chain_index: list | None = None
        self._sparse_pattern: tuple[torch.Tensor, torch.Tensor, list] | None = None

    @property
    def selectable(self) -> bool:
        """Whether every factor type declares its batched data (:meth:`select` works)."""
        return all(f.batched is not None for f in self.factors)

    def select(self, index: torch.Tensor) -> Problem:
        """The problems ``index`` (B',) of this batch as a new Problem of batch size B' (same
        structure; index tables are shared with this one)."""
        out = copy.copy(self)
        out.values = {name: value[index] for name, value in self.values.items()}
        out.variables = {
            name: (kind, out.values[name]) for name, (kind, _) in self.variables.items()
        }
        out.factors = [f.select(index, self.batch_size) for f in self.factors]
        out.batch_size = int(index.shape[0])
        out._sparse_pattern = None
        return out

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
            out.append(whiten(factor, residual, jacs))
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
            dim = self.kinds[name].tangent_dim
            span = self._group_spans.get(name)
            if span is not None:  # all free: the group's columns follow one another
                local = step[:, span].reshape(step.shape[0], -1, dim)
                moved[name] = self.kinds[name].retract(value, local)
                continue
            cols = self.group_columns[name]
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

    def _chain_indices(
        self,
    ) -> list[tuple[list[torch.Tensor], list[tuple[int, int, torch.Tensor]]]]:
        """Per factor type: the block (F,) each slot's gradient goes to (K = spill), and the
        slot pairs ``(a, b)`` whose product ``J_a^T J_b`` lands in a stored block, with the
        block (F,) of each factor: ``k`` for ``H_kk``, ``K + k`` for ``H_{k+1,k}``, ``2K - 1``
        (spill) for fixed variables and upper blocks (the transpose of a stored one)."""
        if self._chain_index is None:
            d = self.block_tridiagonal_size()
            if d is None:
                raise ValueError("the Hessian is not block-tridiagonal")
            count = self.dim // d
            spill = 2 * count - 1
            out = []
            for layouts in self.slot_layouts:
                blocks = [
                    torch.where(
                        lay.columns >= 0, lay.columns // d, torch.full_like(lay.columns, -1)
                    )
                    for lay in layouts
                ]
                grad_targets = [torch.where(k >= 0, k, torch.full_like(k, count)) for k in blocks]
                pairs = []
                for a, ka in enumerate(blocks):
                    for b, kb in enumerate(blocks):
                        free = (ka >= 0) & (kb >= 0)
                        target = torch.full_like(ka, spill)
                        target = torch.where(free & (ka == kb), ka, target)
                        target = torch.where(free & (ka == kb + 1), count + kb, target)
                        if bool((target != spill).any()):
                            pairs.append((a, b, target))
                out.append((grad_targets, pairs))
            self._chain_index = out
        return self._chain_index

    def linearize_chain(self, values: dict[str, torch.Tensor]) -> Linearization:
        """Cost, gradient and the Gauss-Newton Hessian as its block-tridiagonal blocks
        (``diagonal`` (B, K, d, d), ``lower`` (B, K - 1, d, d)), assembled per factor from the
        slot Jacobians without forming the dense (B, n, n) matrix. Only for problems with
        :meth:`block_tridiagonal_size` (keyframe chains)."""
        d = self.block_tridiagonal_size()
        indices = self._chain_indices()
        count = self.dim // d
        batch = self.batch_size
        grad = torch.zeros(batch, count + 1, d, dtype=self.dtype, device=self.device)
        blocks = torch.zeros(batch, 2 * count, d, d, dtype=self.dtype, device=self.device)
        cost = torch.zeros(batch, dtype=self.dtype, device=self.device)
        for factor, (grad_targets, pairs) in zip(self.factors, indices, strict=True):
            loss, grads, pieces = factor.normal_blocks(
                self.gathered(factor, values), factor.kinds, [(a, b) for a, b, _ in pairs]
            )
            cost = cost + loss.sum(-1)
            for part, target in zip(grads, grad_targets, strict=True):
                grad.index_add_(1, target, part)
            for (_, _, target), parts in zip(pairs, pieces, strict=True):
                for rows, cols, block in parts:
                    into = blocks[:, :, rows, cols]
                    if block.dim() == 3:
                        into = into.diagonal(dim1=-2, dim2=-1)
                        block = block.expand(batch, *block.shape[1:])
                    into.index_add_(1, target, block)
        return Linearization(
            cost,
            grad[:, :count].reshape(batch, self.dim),
            diagonal=blocks[:, :count],
            lower=blocks[:, count : 2 * count - 1],
        )

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
        entry once, both triangles), in the order of :attr:`Linearization.sparse_values`.
        The whole diagonal is in the pattern, also where no factor touches a variable (its
        entries are 0, so the damping keeps the system definite there)."""
        if self._sparse_pattern is None:
            n = self.dim
            flats, pieces = [], []
            for fi, factor in enumerate(self.factors):
                for a in range(len(factor.slots)):
                    for b in range(len(factor.slots)):
                        rows, cols, keep = self._block_entries(fi, a, b)
                        flats.append((rows * n + cols).reshape(-1))
                        pieces.append((fi, a, b, keep))
            touched = sum(f.numel() for f in flats)
            flats.append(torch.arange(n, device=self.device) * (n + 1))
            flat = torch.cat(flats)
            unique, inverse = torch.unique(flat, return_inverse=True)
            inverse = inverse[:touched]
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
        if blocks:
            values = values.index_add(1, inverse, torch.cat(blocks, 1))
        return values.reshape(-1)

    def sparse_diagonal_positions(self) -> torch.Tensor:
        """Positions (B * n,) of the diagonal entries in the sparse values, in row order."""
        rows, cols = self.sparse_pattern()
        on_diag = torch.nonzero(rows == cols).squeeze(-1)
        order = torch.argsort(rows[on_diag])
        return on_diag[order]
