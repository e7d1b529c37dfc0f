"""Theseus peer for batched nav-state windows: one ``th.Objective`` over the B problems of a
:class:`~msf_torch.backend.problem.Problem`, solved by ``th.LevenbergMarquardt``.

The factor graph is the one a Theseus user would write:

* per keyframe k a ``th.SE3`` pose ``pose_k`` (tensor (B, 3, 4) = ``[R | p]``) and a
  ``th.Vector(9)`` ``vel_bias_k`` = ``[v, b_g, b_a]`` (m/s, rad/s, m/s^2);
* one ``th.AutoDiffCostFunction`` per factor (per row of each of our factor types). Its
  error function packs the Theseus variables into our nav-state layout
  (:func:`~msf_torch.backend.variables.pack_nav_state`) and returns OUR factor's whitened
  residual ``W r`` for that one factor, so the cost ``0.5 sum |W r|^2`` is the Problem's
  cost exactly. The factor's data at that row (measurements, increments, whitening) are
  the cost function's auxiliary variables and the error function is shared by all rows of
  a factor type, so Theseus's vectoriser batches the rows of a type into one call;
* Jacobians by Theseus's autodiff (``vmap(jacrev)``) projected onto its own tangent
  spaces, steps retracted with its own retractions (SE3: ``X Exp([v, w])``, translation
  part first; ours moves ``p`` in the world frame and ``R Exp(dtheta)``): the same cost
  and optimum, a different path.

What is compared is Theseus's machinery (autodiff linearisation, dense Cholesky of the
(B, n, n) normal equations, its LM loop), not the problem.

Install (theseus-ai 0.2.3 is an sdist whose build needs torch; its declared dependency
scikit-sparse has no wheel and needs SuiteSparse headers, and the dense solver used here
does not need it, hence ``--no-deps`` and no entry in the ``[peers]`` extra)::

    .venv/bin/pip install --no-build-isolation --no-deps theseus-ai==0.2.3 \\
        torchlie==0.1.0 torchkin==0.1.1 urdf_parser_py==0.0.4 semantic-version==2.10.0
"""

from __future__ import annotations

__all__ = ["INSTALL", "import_theseus", "TheseusWindows", "build_theseus", "solve_theseus"]

import copy
import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import torch

from msf_torch.backend.problem import Factor, Problem
from msf_torch.backend.variables import pack_nav_state, unpack_nav_state

INSTALL = (
    ".venv/bin/pip install --no-build-isolation --no-deps theseus-ai==0.2.3 torchlie==0.1.0 "
    "torchkin==0.1.1 urdf_parser_py==0.0.4 semantic-version==2.10.0"
)
"""The command that installs Theseus into the project venv (see the module docstring)."""


def import_theseus() -> Any:
    """``theseus`` (raises ImportError when not installed); its warning that the CHOLMOD
    sparse solver is missing (scikit-sparse not installed, not used here) is silenced."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*skparse.cholmod.*")
        import theseus

    return theseus


@dataclass
class TheseusWindows:
    """A Theseus objective built from a Problem, with the layer that solves it.

    Attributes:
        layer: ``th.TheseusLayer`` around ``th.LevenbergMarquardt``.
        initial: initial tensors by variable name (``pose_k`` (B, 3, 4), ``vel_bias_k``
            (B, 9)), passed to every solve so that repeats start from the same point.
        keyframes: K, variables per problem.
        cost_functions: number of cost functions in the objective.
        damping: initial LM damping (``lambda I``, then adapted per problem).
    """

    layer: Any
    initial: dict[str, torch.Tensor]
    keyframes: int
    cost_functions: int
    damping: float


def _leaves(data: Any) -> list[torch.Tensor]:
    """Tensors of a factor attribute (tensor, dataclass of tensors or list of them) in order."""
    if isinstance(data, torch.Tensor):
        return [data]
    if isinstance(data, list | tuple):
        return [t for item in data for t in _leaves(item)]
    if dataclasses.is_dataclass(data):
        return [t for f in dataclasses.fields(data) for t in _leaves(getattr(data, f.name))]
    raise TypeError(f"cannot map factor data of type {type(data).__name__} to Theseus")


def _rebuild(data: Any, leaves: list[torch.Tensor]) -> Any:
    """``data`` with its tensors replaced, in :func:`_leaves` order, by ``leaves`` (consumed)."""
    if isinstance(data, torch.Tensor):
        return leaves.pop(0)
    if isinstance(data, list | tuple):
        return type(data)(_rebuild(item, leaves) for item in data)
    fields = {f.name: _rebuild(getattr(data, f.name), leaves) for f in dataclasses.fields(data)}
    return dataclasses.replace(data, **fields)


def _per_factor(leaf: torch.Tensor, batch: int, size: int) -> bool:
    """Whether ``leaf`` leads with (B|1, F) (one entry per factor) rather than being shared."""
    return leaf.dim() >= 2 and leaf.shape[0] in (1, batch) and leaf.shape[1] == size


class _FactorType:
    """One of our factor types seen as Theseus cost functions: per row f the auxiliary data
    (each per-factor tensor at row f, flattened to (B|1, numel)) and one error function
    shared by all rows."""

    def __init__(self, factor: Factor, batch: int) -> None:
        if factor.kernel is not None:
            raise ValueError(f"{type(factor).__name__}: robust kernels are not mapped to Theseus")
        if any(kind.name != "nav_state" for kind in factor.kinds):
            raise ValueError(f"{type(factor).__name__}: only nav_state variables are mapped")
        self.factor = factor
        self.names = list(factor.batched or ()) + ["sqrt_information"]
        leaves = [leaf for name in self.names for leaf in _leaves(getattr(factor, name))]
        self.mask = [_per_factor(leaf, batch, factor.size) for leaf in leaves]
        self.shapes = [leaf.shape[2:] for leaf, m in zip(leaves, self.mask, strict=True) if m]
        self.leaves = leaves
        self.dim = int(factor.sqrt_information.shape[-2])

    def aux_tensors(self, row: int) -> list[torch.Tensor]:
        """The per-factor tensors of factor ``row``, each (B|1, numel)."""
        return [
            leaf[:, row].reshape(leaf.shape[0], -1)
            for leaf, m in zip(self.leaves, self.mask, strict=True)
            if m
        ]

    def error(self, optim_vars: tuple[Any, ...], aux_vars: tuple[Any, ...]) -> torch.Tensor:
        """Whitened residual (N, R) of one factor per batch entry; ``optim_vars`` alternate
        (SE3, Vector(9)) per slot, ``aux_vars`` as :meth:`aux_tensors`."""
        values = []
        for pose, rest in zip(optim_vars[0::2], optim_vars[1::2], strict=True):
            matrix = pose.tensor
            v, bg, ba = rest.tensor[:, 0:3], rest.tensor[:, 3:6], rest.tensor[:, 6:9]
            values.append(pack_nav_state(matrix[:, :, 3], v, matrix[:, :, :3], bg, ba)[:, None])
        given = iter(
            aux.tensor.reshape(aux.tensor.shape[0], 1, *shape)
            for aux, shape in zip(aux_vars, self.shapes, strict=True)
        )
        leaves = [
            next(given) if m else leaf for leaf, m in zip(self.leaves, self.mask, strict=True)
        ]
        factor = copy.copy(self.factor)
        for name in self.names:
            setattr(factor, name, _rebuild(getattr(self.factor, name), leaves))
        residual = factor.residual(values)
        return (factor.sqrt_information @ residual[..., None])[:, 0, :, 0]


def build_theseus(
    problem: Problem,
    relative_tolerance: float,
    max_iterations: int,
    damping: float,
) -> TheseusWindows:
    """Theseus objective (batch B) of a Problem with one ``nav_state`` group, and its LM layer.

    Args:
        problem: B problems, one variable group of K ``nav_state`` variables (none fixed),
            factors without robust kernels.
        relative_tolerance: stop a problem when its cost changes by less than this fraction
            (``rel_err_tolerance``; ``abs_err_tolerance`` is 0).
        max_iterations: LM iterations at most.
        damping: initial LM damping (adaptive per problem, ``lambda I``).
    """
    th = import_theseus()
    if len(problem.values) != 1 or problem.fixed:
        raise ValueError("the Theseus peer maps problems with one free variable group")
    ((group, values),) = problem.values.items()
    if problem.kinds[group].name != "nav_state":
        raise ValueError(f"the Theseus peer maps nav_state variables, not {group!r}")
    p, v, r, bg, ba = unpack_nav_state(values)
    keyframes = values.shape[1]
    initial: dict[str, torch.Tensor] = {}
    poses, rests = [], []
    for k in range(keyframes):
        initial[f"pose_{k}"] = torch.cat((r[:, k], p[:, k, :, None]), -1).contiguous()
        initial[f"vel_bias_{k}"] = torch.cat((v[:, k], bg[:, k], ba[:, k]), -1)
        poses.append(th.SE3(tensor=initial[f"pose_{k}"].clone(), name=f"pose_{k}"))
        rests.append(th.Vector(tensor=initial[f"vel_bias_{k}"].clone(), name=f"vel_bias_{k}"))
    objective = th.Objective(dtype=values.dtype)
    unit = th.ScaleCostWeight(torch.ones(1, 1, dtype=values.dtype), name="unit_weight")
    count = 0
    for t, factor in enumerate(problem.factors):
        if any(g != group for g, _ in factor.slots):
            raise ValueError(f"{type(factor).__name__} joins another variable group")
        ftype = _FactorType(factor, problem.batch_size)
        # one function object for all rows: Theseus vectorises cost functions whose error
        # function is the same object (a bound method is a new object at each access)
        error = ftype.error
        for row in range(factor.size):
            optim = []
            for _, index in factor.slots:
                k = int(index[row])
                optim += [poses[k], rests[k]]
            aux = [
                th.Variable(tensor, name=f"f{t}_{row}_a{i}")
                for i, tensor in enumerate(ftype.aux_tensors(row))
            ]
            objective.add(
                th.AutoDiffCostFunction(
                    optim, error, ftype.dim, unit, aux_vars=aux, name=f"f{t}_{row}"
                )
            )
            count += 1
    objective.to(device=values.device)
    optimizer = th.LevenbergMarquardt(
        objective,
        th.CholeskyDenseSolver,
        max_iterations=max_iterations,
        rel_err_tolerance=relative_tolerance,
        abs_err_tolerance=0.0,
        vectorize=True,
    )
    return TheseusWindows(th.TheseusLayer(optimizer), initial, keyframes, count, damping)


def solve_theseus(peer: TheseusWindows) -> tuple[torch.Tensor, Any]:
    """One LM solve from the initial values, under ``torch.no_grad``.

    Returns:
        nav-state values (B, K, 21) in our layout, and Theseus's ``NonlinearOptimizerInfo``
        (``status``, ``converged_iter`` per problem: -1 where it hit the iteration limit).
    """
    with torch.no_grad():
        out, info = peer.layer.forward(
            dict(peer.initial),
            optimizer_kwargs={"adaptive_damping": True, "damping": peer.damping},
        )
    poses = torch.stack([out[f"pose_{k}"] for k in range(peer.keyframes)], 1)
    rests = torch.stack([out[f"vel_bias_{k}"] for k in range(peer.keyframes)], 1)
    values = pack_nav_state(
        poses[..., 3], rests[..., 0:3], poses[..., :3], rests[..., 3:6], rests[..., 6:9]
    )
    return values, info
