"""3-D pose graphs: g2o (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) and TORO (``VERTEX3`` /
``EDGE3``) files, read into a :class:`PoseGraph` and written back as g2o.

Formats
    One record per line, space separated; ``#`` starts a comment (to the end of the line);
    blank lines are ignored. Ids are non-negative integers, lengths are in m, angles in rad.

    * ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` -- the pose of vertex ``id`` (body -> world):
      position ``[x, y, z]``, unit quaternion in ``[x, y, z, w]`` order (normalised on read,
      as GTSAM and g2o do).
    * ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + 21 numbers -- the measured relative pose
      ``T_ij = T_i^-1 T_j`` and the upper triangle (row by row) of its 6x6 information
      matrix in g2o's order ``[x y z qx qy qz]``.
    * ``VERTEX3 id x y z roll pitch yaw`` -- TORO 3-D vertex; ``R = Rz(yaw) Ry(pitch)
      Rx(roll)`` (GTSAM's ``Rot3.Ypr(yaw, pitch, roll)``).
    * ``EDGE3 i j x y z roll pitch yaw`` + 21 numbers -- TORO 3-D edge, same rotation rule,
      upper triangle of the information matrix (order: see below).
    * ``FIX id [id ...]`` -- g2o's gauge record: these vertices are held fixed by the
      optimiser (``PoseGraph.fixed_ids``; :func:`~msf_torch.backend.posegraph.optimize_pose_graph`
      holds them instead of the first vertex).

    A file may mix these tags. A file with edges and no vertices (``sphere2500.txt``) is
    read with ``has_vertices=False``: the initial poses are chained from the lowest id
    (identity) along the odometry edges ``k -> k+1`` (the first such edge in the file; the
    ids must be consecutive), ``T_{k+1} = T_k T_{k,k+1}``.

Information matrices (the reference is GTSAM 4.3's ``readG2o(path, True)`` = ``load3D``)
    GTSAM builds ``BetweenFactorPose3(i, j, T_ij, Gaussian.Information(M))`` whose error is
    ``Pose3.Logmap(T_ij^-1 T_i^-1 T_j)`` = ``[omega, rho]``, rotation first (the full SE(3)
    logarithm: ``omega = Log(R_e)``, ``rho = V(omega)^-1 t_e`` for the error pose
    ``(R_e, t_e)``, ``V`` the left Jacobian of SO(3)). The whitened cost is
    ``0.5 [omega, rho]^T M [omega, rho]``. msf_torch orders the tangent translation first,
    ``[rho, omega]``, and stores ``edge_information = P M P^T`` with ``P`` the block swap,
    so ``0.5 [rho, omega]^T edge_information [rho, omega]`` is GTSAM's cost exactly.

    * ``EDGE_SE3:QUAT``: the file matrix ``F`` is in g2o's ``[x y z qx qy qz]`` order and
      GTSAM permutes it to ``M = P F P^T``; hence ``edge_information = F`` as written in the
      file. (g2o's own EDGE_SE3 error uses the quaternion's vector part, about half the
      rotation angle; GTSAM, and so msf_torch, applies the rotation block to the rotation
      vector unchanged.)
    * ``EDGE3``: GTSAM takes the file matrix ``F`` as ``M = F`` directly, i.e. in its own
      ``[rot, trans]`` order, so ``edge_information = P F P^T``. For ``sphere2500.txt``
      (``10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25``) this gives
      ``diag(100, 100, 25, 10, 10, 10)`` in ``[dp, dtheta]``: translation 100, 100, 25 /m^2,
      rotation 10 /rad^2. (Read in TORO's pose order ``x y z roll pitch yaw`` the same
      line would mean translation 10 and rotation 100, 100, 25; msf_torch follows GTSAM so
      that costs agree with the peer.)

    To first order at a zero residual, ``rho`` equals the translation of the error pose
    ``R_ij^T (R_i^T (p_j - p_i) - t_ij)`` and ``omega`` its rotation ``Log(R_ij^T R_i^T
    R_j)``, i.e. the right perturbation ``T = T_hat (Exp(dtheta), dp)``; a residual in that
    product chart has the same information matrix but differs from GTSAM's cost at second
    order in the residual.

Rules
    Malformed records raise :class:`DataError` naming file, 1-based line and field (``id``,
    ``i``, ``j``, ``x`` ... ``qw``, ``roll`` ... ``yaw``, ``info[r,c]`` for row ``r`` and
    column ``c`` (0-based) of the file's 6x6 matrix): a wrong number of values, a value that
    is not a number or not finite, an id that is not a non-negative integer, a zero
    quaternion, a duplicate vertex id, an edge from a vertex to itself, an information
    matrix that is not positive definite, an edge naming a vertex the file does not define
    (when it defines any), a broken odometry chain (edge-only files), and any 2-D tag
    (``VERTEX_SE2``, ``EDGE2``, ...: this reader is for 3-D graphs), and a ``FIX`` naming a
    vertex the graph does not have. Other tags (``VERTEX_TRACKXYZ``,
    ``EDGE_SE3_TRACKXYZ``, ``PARAMS_SE3OFFSET``, ``EDGE_SE3_PRIOR``, ...) are skipped, as
    GTSAM's pose-graph loader skips them, counted per tag in ``PoseGraph.skipped`` and
    reported by one ``UserWarning`` (each tag's count and first line); pass
    ``unknown_tags="error"`` to raise instead. A file whose only edges carry skipped tags (no
    pose edge at all) is a DataError naming those tags: there is no pose graph to solve.
"""

from __future__ import annotations

__all__ = [
    "G2O_EDGE_TAG",
    "G2O_VERTEX_TAG",
    "GTSAM_POSE3_FILES",
    "PoseGraph",
    "TORO_EDGE_TAG",
    "TORO_VERTEX_TAG",
    "gtsam_pose_graph_path",
    "read_pose_graph",
    "write_g2o",
]

import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pytorch_kinematics.transforms import euler_angles_to_matrix

from msf_torch.geometry.quaternion import matrix_to_quat, quat_to_matrix
from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_write
from msf_torch.io.errors import DataError
from msf_torch.io.kitti_gtsam import gtsam_data_path

G2O_VERTEX_TAG = "VERTEX_SE3:QUAT"
G2O_EDGE_TAG = "EDGE_SE3:QUAT"
TORO_VERTEX_TAG = "VERTEX3"
TORO_EDGE_TAG = "EDGE3"

GTSAM_POSE3_FILES = (
    "Klaus3.g2o",
    "known_landmark_localization_20.g2o",
    "known_landmark_localization_3.g2o",
    "pose3Localizationexample.txt",
    "pose3example-grid.txt",
    "pose3example-offdiagonal-rewritten.txt",
    "pose3example-offdiagonal.txt",
    "pose3example.txt",
    "simpleGraph10gradIter.txt",
    "sphere2500.txt",
    "sphere2500_groundtruth.txt",
    "toyExample.g2o",
)
"""3-D pose graphs shipped in the gtsam wheel's ``Data`` folder that :func:`read_pose_graph`
reads and GTSAM's ``readG2o(path, True)`` reads identically (the two
``known_landmark_localization_*`` files also hold landmark records, which are skipped).
``sphere_smallnoise.graph`` is not listed: its ``EDGE3`` lines carry no information matrix
(a DataError here; GTSAM stops reading after the first edge)."""

_INFO_ROWS, _INFO_COLS = np.triu_indices(6)
_INFO_FIELDS = tuple(f"info[{r},{c}]" for r, c in zip(_INFO_ROWS, _INFO_COLS, strict=True))
_TAGS_2D = frozenset(
    {"VERTEX", "VERTEX2", "EDGE", "EDGE2", "ODOMETRY", "LANDMARK", "LANDMARK2", "BR", "EQUIV"}
)
POSE3_TAGS = frozenset({G2O_VERTEX_TAG, G2O_EDGE_TAG, TORO_VERTEX_TAG, TORO_EDGE_TAG})
_ID = re.compile(r"[0-9]+")
FIX_TAG = "FIX"
_TAGS = f"{G2O_VERTEX_TAG}, {G2O_EDGE_TAG}, {TORO_VERTEX_TAG}, {TORO_EDGE_TAG}, {FIX_TAG}"


@dataclass(frozen=True)
class _Spec:
    """One record type: its tag, whether it is an edge, its rotation encoding, fields."""

    tag: str
    edge: bool
    quat: bool
    fields: tuple[str, ...]

    @property
    def n_ids(self) -> int:
        return 2 if self.edge else 1


_POSE_QUAT = ("x", "y", "z", "qx", "qy", "qz", "qw")
_POSE_RPY = ("x", "y", "z", "roll", "pitch", "yaw")
_SPECS = {
    G2O_VERTEX_TAG: _Spec(G2O_VERTEX_TAG, False, True, ("id", *_POSE_QUAT)),
    G2O_EDGE_TAG: _Spec(G2O_EDGE_TAG, True, True, ("i", "j", *_POSE_QUAT, *_INFO_FIELDS)),
    TORO_VERTEX_TAG: _Spec(TORO_VERTEX_TAG, False, False, ("id", *_POSE_RPY)),
    TORO_EDGE_TAG: _Spec(TORO_EDGE_TAG, True, False, ("i", "j", *_POSE_RPY, *_INFO_FIELDS)),
}


class GraphSizes:
    """What 3-D and 2-D pose graphs share: sizes and the rows of the fixed vertices (needs
    ``vertex_ids``, ``edge_index`` and ``fixed_ids``)."""

    vertex_ids: torch.Tensor
    edge_index: torch.Tensor
    fixed_ids: tuple[int, ...]

    @property
    def num_vertices(self) -> int:
        """N, the number of vertices."""
        return int(self.vertex_ids.shape[0])

    @property
    def num_edges(self) -> int:
        """E, the number of edges."""
        return int(self.edge_index.shape[0])

    def fixed_rows(self) -> torch.Tensor:
        """(F,) int64 row indices (into the vertex arrays) of :attr:`fixed_ids`.

        Raises:
            ValueError: a fixed id that is not a vertex id.
        """
        return fixed_rows_of(self.vertex_ids, self.fixed_ids, type(self).__name__)


@dataclass
class PoseGraph(GraphSizes):
    """A 3-D pose graph: vertices (poses) and relative-pose edges with information matrices.

    All tensors are float64 (int64 for ids and indices) on one device; N vertices, E edges.

    Attributes:
        vertex_ids: (N,) int64, the file's vertex ids, strictly increasing.
        rotations: (N, 3, 3) body -> world rotation of each vertex (``x_world = R x_body``).
        positions: (N, 3) m, position of each vertex in the world frame.
        edge_index: (E, 2) int64, ``[i, j]`` row indices into the vertex arrays (not file
            ids; ``vertex_ids[edge_index]`` gives those), in file order.
        edge_rotations: (E, 3, 3) measured ``R_ij`` of ``T_ij = T_i^-1 T_j``.
        edge_translations: (E, 3) m, measured ``t_ij`` of ``T_ij``.
        edge_information: (E, 6, 6) symmetric positive definite information matrix in the
            tangent order ``[dp, dtheta]`` (1/m^2, 1/(m rad), 1/rad^2); see the module
            docstring for the exact chart and the conversion from each file format.
        has_vertices: False when the file held edges only; the poses are then the chained
            odometry initial guess (lowest id = identity).
        edge_lines: (E,) int64 1-based line of each edge in the source file, or None (a
            graph built in memory).
        skipped: tag -> number of lines skipped (tags this reader does not use).
        source: the file read, or None.
        fixed_ids: file ids of the vertices the file holds fixed (``FIX`` records), sorted;
            empty when it names none (the optimiser then holds the first vertex).
    """

    vertex_ids: torch.Tensor
    rotations: torch.Tensor
    positions: torch.Tensor
    edge_index: torch.Tensor
    edge_rotations: torch.Tensor
    edge_translations: torch.Tensor
    edge_information: torch.Tensor
    has_vertices: bool = True
    edge_lines: torch.Tensor | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    source: str | None = None
    fixed_ids: tuple[int, ...] = ()

    def edge_ids(self) -> torch.Tensor:
        """(E, 2) int64 file ids ``[id_i, id_j]`` of every edge."""
        return self.vertex_ids[self.edge_index]

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> PoseGraph:
        """A copy on ``device``; floating tensors cast to ``dtype`` when given."""

        def move(x: torch.Tensor) -> torch.Tensor:
            if dtype is not None and x.is_floating_point():
                return x.to(device=device, dtype=dtype)
            return x.to(device=device)

        return PoseGraph(
            vertex_ids=move(self.vertex_ids),
            rotations=move(self.rotations),
            positions=move(self.positions),
            edge_index=move(self.edge_index),
            edge_rotations=move(self.edge_rotations),
            edge_translations=move(self.edge_translations),
            edge_information=move(self.edge_information),
            has_vertices=self.has_vertices,
            edge_lines=None if self.edge_lines is None else move(self.edge_lines),
            skipped=dict(self.skipped),
            source=self.source,
            fixed_ids=self.fixed_ids,
        )

    def check(self) -> None:
        """Check shapes, dtypes and index ranges.

        Raises:
            ValueError: naming the first field that is wrong.
        """
        n, e = self.num_vertices, self.num_edges
        shapes = {
            "vertex_ids": (n,),
            "rotations": (n, 3, 3),
            "positions": (n, 3),
            "edge_index": (e, 2),
            "edge_rotations": (e, 3, 3),
            "edge_translations": (e, 3),
            "edge_information": (e, 6, 6),
        }
        check_graph_fields(self, "PoseGraph", shapes)


def fixed_rows_of(vertex_ids: torch.Tensor, fixed_ids: tuple[int, ...], owner: str) -> torch.Tensor:
    """(F,) int64 rows of the sorted ``vertex_ids`` (N,) that hold ``fixed_ids``.

    Raises:
        ValueError: a fixed id that is not a vertex id (``owner`` names the graph class).
    """
    fixed = torch.as_tensor(fixed_ids, dtype=torch.int64, device=vertex_ids.device)
    n = int(vertex_ids.shape[0])
    rows = torch.searchsorted(vertex_ids, fixed)
    known = rows < n
    if n:
        known &= vertex_ids[rows.clamp(max=n - 1)] == fixed
    if not bool(known.all()):
        raise ValueError(f"{owner}.fixed_ids: {fixed[~known].tolist()} are not vertex ids")
    return rows


def check_graph_fields(graph, owner: str, shapes: dict[str, tuple[int, ...]]) -> None:
    """Shapes, dtypes and index ranges of a pose graph (``PoseGraph`` or ``PoseGraph2D``):
    every field in ``shapes`` has that shape (and ``edge_lines`` (E,) when set), ids and
    indices are int64, the rest floating; ids strictly increase; edges index vertices;
    ``fixed_ids`` are vertex ids.

    Raises:
        ValueError: naming ``owner`` and the first field that is wrong.
    """
    n, e = graph.num_vertices, graph.num_edges
    if graph.edge_lines is not None:
        shapes = {**shapes, "edge_lines": (e,)}
    for name, shape in shapes.items():
        value = getattr(graph, name)
        if tuple(value.shape) != shape:
            raise ValueError(f"{owner}.{name}: shape {tuple(value.shape)}, expected {shape}")
        integral = name in ("vertex_ids", "edge_index", "edge_lines")
        if integral and value.dtype != torch.int64:
            raise ValueError(f"{owner}.{name}: dtype {value.dtype}, expected torch.int64")
        if not integral and not value.is_floating_point():
            raise ValueError(f"{owner}.{name}: dtype {value.dtype}, expected floating")
    if n > 1 and not bool((graph.vertex_ids.diff() > 0).all()):
        raise ValueError(f"{owner}.vertex_ids: not strictly increasing")
    if e and (int(graph.edge_index.min()) < 0 or int(graph.edge_index.max()) >= n):
        raise ValueError(f"{owner}.edge_index: row indices outside [0, {n})")
    graph.fixed_rows()


@dataclass
class RecordBook:
    """What a pose-graph reader notes besides its pose records: the ``FIX`` ids and the
    lines it skipped (shared by the 2-D and 3-D readers).

    Attributes:
        path: the file, for errors. fixes: fixed id -> line of its first ``FIX``.
        skipped: tag -> lines skipped. first: tag -> first line skipped.
    """

    path: str
    fixes: dict[int, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    first: dict[str, int] = field(default_factory=dict)

    def read_fix(self, tokens: list[str], line: int) -> None:
        """Note a ``FIX id [id ...]`` record; a DataError when it names no id."""
        if len(tokens) < 2:
            raise DataError(self.path, "FIX names no vertex id", line=line, field="id")
        for token in tokens[1:]:
            self.fixes.setdefault(parse_id(self.path, token, line, "id"), line)

    def other_tag(self, tag: str, line: int, mode: str, tags_read: str) -> None:
        """A line whose tag the reader does not read: counted (``mode`` ``"skip"``) or a
        DataError (``"error"``)."""
        if mode == "error":
            raise DataError(
                self.path,
                f"unknown tag {_tables.shown(tag)} (known: {tags_read})",
                line=line,
                field="tag",
            )
        self.skipped[tag] = self.skipped.get(tag, 0) + 1
        self.first.setdefault(tag, line)

    def tally(self) -> str:
        """Each skipped tag with its count and first line, for messages."""
        return ", ".join(
            f"{_tables.shown(tag)} x{count} (first on line {self.first[tag]})"
            for tag, count in self.skipped.items()
        )

    def check_fixes(self, vertex_ids: np.ndarray, has_vertices: bool) -> None:
        """A DataError when a ``FIX`` names an id that is not a vertex of the graph."""
        unknown = sorted(set(self.fixes) - set(vertex_ids.tolist()), key=self.fixes.__getitem__)
        if unknown:
            vid = unknown[0]
            defined = "vertex line defines" if has_vertices else "edge names"
            raise DataError(
                self.path,
                f"FIX names vertex {vid}, which no {defined}",
                line=self.fixes[vid],
                field="id",
            )

    def warn_skipped(self, tags_read: str) -> None:
        """One UserWarning with the tally, when lines were skipped."""
        if self.skipped:
            warnings.warn(
                f"{self.path}: skipped {sum(self.skipped.values())} lines with tags this "
                f"reader does not read: {self.tally()} (tags read: {tags_read})",
                stacklevel=3,
            )


def edge_rows(path: str, vertex_ids: np.ndarray, pairs: np.ndarray, lines: np.ndarray):
    """(E, 2) rows of the sorted ``vertex_ids`` (N,) that the edges' id ``pairs`` (E, 2)
    name; a DataError naming the edge's ``lines`` (E,) entry and field when one is not a
    vertex."""
    rows = np.searchsorted(vertex_ids, pairs)
    known = vertex_ids[np.minimum(rows, vertex_ids.size - 1)] == pairs
    if not known.all():
        k, side = (int(x) for x in np.argwhere(~known)[0])
        raise DataError(
            path,
            f"edge names vertex {int(pairs[k, side])}, which no vertex line defines",
            line=int(lines[k]),
            field="ij"[side],
        )
    return rows


# ----------------------------------------------------------------------------- reading


@dataclass
class _Records:
    """Parsed records of one tag, in file order."""

    lines: list[int] = field(default_factory=list)
    ids: list[tuple[int, ...]] = field(default_factory=list)
    values: list[list[float]] = field(default_factory=list)


def parse_id(path: str, token: str, line: int, name: str) -> int:
    """A vertex id: a non-negative integer below 2^63, else a DataError naming the field."""
    if not _ID.fullmatch(token) or len(token.lstrip("0")) > 19 or int(token) >= 2**63:
        raise DataError(
            path,
            f"not a non-negative integer id: {_tables.shown(token)} (ids lie below 2^63)",
            line=line,
            field=name,
        )
    return int(token)


def parse_float_fields(
    path: str, tokens: list[str], line: int, names: tuple[str, ...]
) -> list[float]:
    """Finite floats of ``tokens``, else a DataError naming the field (``names``, one per
    token) of the first bad one."""
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        for token, name in zip(tokens, names, strict=True):
            try:
                float(token)
            except ValueError:
                raise DataError(
                    path, f"not a number: {_tables.shown(token)}", line=line, field=name
                ) from None
        raise  # pragma: no cover - float() failed above, so the loop raised
    if not all(map(math.isfinite, values)):
        k = next(k for k, v in enumerate(values) if not math.isfinite(v))
        raise DataError(path, f"not finite: {_tables.shown(tokens[k])}", line=line, field=names[k])
    return values


def _parse_line(path: str, spec: _Spec, tokens: list[str], line: int, records: _Records) -> None:
    given = len(tokens) - 1
    expected = len(spec.fields)
    if given != expected:
        layout = " ".join(spec.fields[: spec.n_ids + (7 if spec.quat else 6)])
        more = " + 21 information entries" if spec.edge else ""
        problem = (
            f"wrong number of values for {spec.tag} ({spec.tag} {layout}{more}): "
            f"expected {expected}, got {given}"
        )
        missing = spec.fields[given] if given < expected else None
        if missing is not None:
            problem += f"; '{missing}' and later fields are missing"
        raise DataError(path, problem, line=line, field=missing)
    ids = tuple(parse_id(path, tokens[1 + k], line, spec.fields[k]) for k in range(spec.n_ids))
    values = parse_float_fields(path, tokens[1 + spec.n_ids :], line, spec.fields[spec.n_ids :])
    if spec.quat:
        q = values[3:7]
        if math.sqrt(sum(x * x for x in q)) < 1e-6:
            raise DataError(path, f"quaternion {q} has (near) zero norm", line=line, field="qw")
    if spec.edge and ids[0] == ids[1]:
        raise DataError(path, f"edge from vertex {ids[0]} to itself", line=line, field="j")
    records.lines.append(line)
    records.ids.append(ids)
    records.values.append(values)


def _is_2d_tag(tag: str) -> bool:
    return tag in _TAGS_2D or "SE2" in tag or tag.endswith("_XY")


def _rotations(values: np.ndarray, quat: bool) -> np.ndarray:
    """(K, 6 or 7) pose values -> (K, 3, 3) rotations (quaternion xyzw or roll pitch yaw)."""
    if values.shape[0] == 0:
        return np.zeros((0, 3, 3))
    if quat:
        wxyz = _tables.normalise_quaternions(values[:, [6, 3, 4, 5]])
        return quat_to_matrix(torch.as_tensor(wxyz, dtype=torch.float64)).numpy()
    ypr = torch.as_tensor(values[:, [5, 4, 3]], dtype=torch.float64)
    return euler_angles_to_matrix(ypr, "ZYX").numpy()


def _information(values: np.ndarray, quat: bool) -> np.ndarray:
    """(K, 21) upper triangles -> (K, 6, 6) information in ``[dp, dtheta]`` order."""
    info = np.zeros((values.shape[0], 6, 6))
    info[:, _INFO_ROWS, _INFO_COLS] = values
    info[:, _INFO_COLS, _INFO_ROWS] = values
    if not quat:  # EDGE3: GTSAM reads the file matrix in its [rot, trans] order
        info = info[:, [3, 4, 5, 0, 1, 2]][:, :, [3, 4, 5, 0, 1, 2]]
    return info


def _chain(
    path: str,
    ids: np.ndarray,
    pairs: np.ndarray,
    rot: np.ndarray,
    trans: np.ndarray,
    lines: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses of an edge-only graph along the odometry edges ``k -> k+1``; a position
    that overflows to inf on the way is a DataError naming the edge that pushed it over."""
    first: dict[tuple[int, int], int] = {}
    for e, (i, j) in enumerate(pairs.tolist()):
        first.setdefault((i, j), e)
    n = ids.shape[0]
    rotations = np.empty((n, 3, 3))
    positions = np.empty((n, 3))
    rotations[0] = np.eye(3)
    positions[0] = 0.0
    for k in range(n - 1):
        a = int(ids[k])
        e = first.get((a, a + 1))
        if e is None:
            raise DataError(
                path,
                f"the file has edges only, so the initial poses are chained from vertex "
                f"{int(ids[0])} (identity) along the odometry edges k -> k+1, but there is no "
                f"edge {a} -> {a + 1}",
            )
        with np.errstate(over="ignore", invalid="ignore"):
            positions[k + 1] = positions[k] + rotations[k] @ trans[e]
        if not np.isfinite(positions[k + 1]).all():
            raise DataError(
                path,
                f"the initial position of vertex {a + 1}, chained along the odometry edges, "
                "overflows (the translations are too large)",
                line=int(lines[e]),
                field="x",
            )
        rotations[k + 1] = rotations[k] @ rot[e]
    return rotations, positions


def read_pose_graph(
    path: str | os.PathLike[str], *, unknown_tags: Literal["skip", "error"] = "skip"
) -> PoseGraph:
    """Read a 3-D pose graph from a g2o or TORO file (the tags decide; they may be mixed).

    Args:
        path: the file.
        unknown_tags: ``"skip"`` (default) skips and counts lines whose tag is not a 3-D pose
            tag or ``FIX`` (landmark records, priors, ...) and warns once about them;
            ``"error"`` raises DataError on them. 2-D pose-graph tags always raise.

    Returns:
        a :class:`PoseGraph` in float64 on the CPU: vertices sorted by id, edges in file
        order, information matrices in ``[dp, dtheta]`` order such that the whitened cost
        equals GTSAM's (module docstring); ``has_vertices=False`` and chained poses for a
        file with edges only; ``fixed_ids`` from the ``FIX`` records.

    Raises:
        DataError: naming file, line and field of the first bad record (module docstring
            lists the rules); also a missing file, one without vertices and edges, and one
            with skipped tags but no pose edge (the message names the skipped tags).
        ValueError: an unknown ``unknown_tags``.

    Warns:
        UserWarning: once per file when lines were skipped, with each skipped tag's count
            and first line.
    """
    if unknown_tags not in ("skip", "error"):
        raise ValueError(f"unknown_tags must be 'skip' or 'error', got {unknown_tags!r}")
    path_str = os.fspath(path)
    records = {tag: _Records() for tag in _SPECS}
    book = RecordBook(path_str)
    vertex_line: dict[int, int] = {}
    for line_no, raw in enumerate(_tables.split_lines(_tables.read_text(path_str)), start=1):
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        tag = tokens[0]
        spec = _SPECS.get(tag)
        if tag == FIX_TAG:
            book.read_fix(tokens, line_no)
            continue
        if spec is None:
            if _is_2d_tag(tag):
                first_3d = min((r.lines[0] for r in records.values() if r.lines), default=None)
                advice = (
                    "read 2-D graphs with msf_torch.io.read_pose_graph_2d"
                    if first_3d is None
                    else f"the file mixes it with 3-D records (the first on line {first_3d}); "
                    "keep one kind per file"
                )
                raise DataError(
                    path_str,
                    f"2-D pose-graph tag {_tables.shown(tag)}; this reader reads 3-D graphs "
                    f"({_TAGS}); {advice}",
                    line=line_no,
                    field="tag",
                )
            book.other_tag(tag, line_no, unknown_tags, _TAGS)
            continue
        _parse_line(path_str, spec, tokens, line_no, records[tag])
        if not spec.edge:
            vid = records[tag].ids[-1][0]
            if vid in vertex_line:
                raise DataError(
                    path_str,
                    f"duplicate vertex id {vid} (first defined on line {vertex_line[vid]})",
                    line=line_no,
                    field="id",
                )
            vertex_line[vid] = line_no

    # edges, in file order
    edge_tags = [t for t, s in _SPECS.items() if s.edge]
    e_lines = np.array([ln for t in edge_tags for ln in records[t].lines], dtype=np.int64)
    order = np.argsort(e_lines, kind="stable")
    e_lines = e_lines[order]
    e_pairs = np.array([ids for t in edge_tags for ids in records[t].ids], dtype=np.int64)
    e_pairs = e_pairs.reshape(-1, 2)[order]
    e_rot, e_trans, e_info = [], [], []
    for t in edge_tags:
        vals = np.array(records[t].values, dtype=np.float64).reshape(
            len(records[t].values), len(_SPECS[t].fields) - 2
        )
        pose = vals[:, :-21]
        e_rot.append(_rotations(pose, _SPECS[t].quat))
        e_trans.append(pose[:, :3])
        e_info.append(_information(vals[:, -21:], _SPECS[t].quat))
    edge_rotations = np.concatenate(e_rot)[order]
    edge_translations = np.concatenate(e_trans)[order]
    edge_information = np.concatenate(e_info)[order]
    if e_lines.size:
        chol = torch.linalg.cholesky_ex(torch.as_tensor(edge_information))
        bad = torch.nonzero(chol.info).flatten()
        if bad.numel():
            k = int(bad[0])
            eig = np.linalg.eigvalsh(edge_information[k])
            raise DataError(
                path_str,
                f"information matrix is not positive definite (eigenvalues "
                f"{np.array2string(eig, precision=4)})",
                line=int(e_lines[k]),
                field="information",
            )

    # vertices, sorted by id
    vertex_tags = [t for t, s in _SPECS.items() if not s.edge]
    v_ids = np.array([ids[0] for t in vertex_tags for ids in records[t].ids], dtype=np.int64)
    v_rot, v_pos = [], []
    for t in vertex_tags:
        vals = np.array(records[t].values, dtype=np.float64).reshape(
            len(records[t].values), len(_SPECS[t].fields) - 1
        )
        v_rot.append(_rotations(vals, _SPECS[t].quat))
        v_pos.append(vals[:, :3])
    has_vertices = v_ids.size > 0
    if book.skipped and not e_lines.size:
        raise DataError(
            path_str,
            f"no pose edges ({G2O_EDGE_TAG} or {TORO_EDGE_TAG}), only tags this reader does "
            f"not read: {book.tally()} (tags read: {_TAGS})",
        )
    if not has_vertices and not e_lines.size:
        raise DataError(path_str, f"no vertices or edges (tags read: {_TAGS})")

    if has_vertices:
        vorder = np.argsort(v_ids, kind="stable")
        vertex_ids = v_ids[vorder]
        rotations = np.concatenate(v_rot)[vorder]
        positions = np.concatenate(v_pos)[vorder]
        rows = edge_rows(path_str, vertex_ids, e_pairs, e_lines)
    else:
        vertex_ids = np.unique(e_pairs)
        rows = np.searchsorted(vertex_ids, e_pairs)
        rotations, positions = _chain(
            path_str, vertex_ids, e_pairs, edge_rotations, edge_translations, e_lines
        )
    book.check_fixes(vertex_ids, has_vertices)
    book.warn_skipped(_TAGS)

    def f64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    def i64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.int64)

    graph = PoseGraph(
        vertex_ids=i64(vertex_ids),
        rotations=f64(rotations),
        positions=f64(positions),
        edge_index=i64(rows.reshape(-1, 2)),
        edge_rotations=f64(edge_rotations),
        edge_translations=f64(edge_translations),
        edge_information=f64(edge_information),
        has_vertices=has_vertices,
        edge_lines=i64(e_lines),
        skipped=book.skipped,
        source=path_str,
        fixed_ids=tuple(sorted(book.fixes)),
    )
    graph.check()
    return graph


# ----------------------------------------------------------------------------- writing


def _check_rotations(rot: np.ndarray, what: str, labels: np.ndarray) -> None:
    if rot.shape[0] == 0:
        return
    err = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bad = np.flatnonzero((err > 1e-6) | (det <= 0))
    if bad.size:
        k = int(bad[0])
        raise ValueError(
            f"{what} {labels[k]}: rotation is not a proper orthonormal matrix "
            f"(max |R^T R - I| = {err[k]:.3g}, det = {det[k]:.6g})"
        )


def write_g2o(path: str | os.PathLike[str], graph: PoseGraph) -> Path:
    """Write a pose graph as a g2o file (``VERTEX_SE3:QUAT``, ``FIX``, ``EDGE_SE3:QUAT``),
    atomically.

    Vertices are written by id, then one ``FIX id`` line per fixed vertex, then edges in
    order, each number as Python's shortest
    round-trip decimal (``repr``), so ``read_pose_graph(write_g2o(p, g))`` gives back ``g``
    to about 1e-15 (rotations pass through a unit quaternion ``[x, y, z, w]``, ``w >= 0``).
    The information matrix is written as its upper triangle in ``[dp, dtheta]`` order,
    which is g2o's ``[x y z qx qy qz]`` order, the layout GTSAM's ``writeG2o`` produces; an
    edge-only graph is written with its chained poses as vertices.

    Args:
        path: the output file; missing parent folders are created.
        graph: the graph; any device and floating dtype (written as float64).

    Returns:
        the path written.

    Raises:
        ValueError: a malformed graph (:meth:`PoseGraph.check`), no vertices, a non-finite
            value, a rotation that is not orthonormal, or an information matrix that is not
            symmetric (each named by vertex id or edge index).
    """
    graph.check()
    if graph.num_vertices == 0:
        raise ValueError("a pose graph without vertices cannot be written")

    def host(x: torch.Tensor) -> np.ndarray:
        return x.detach().to(device="cpu", dtype=torch.float64).numpy()

    ids = graph.vertex_ids.detach().cpu().numpy()
    pairs = ids[graph.edge_index.detach().cpu().numpy()].reshape(-1, 2)
    rot, pos = host(graph.rotations), host(graph.positions)
    e_rot, e_trans = host(graph.edge_rotations), host(graph.edge_translations)
    info = host(graph.edge_information)
    edge_labels = np.array([f"{k} ({i} -> {j})" for k, (i, j) in enumerate(pairs.tolist())])
    for what, arrays, labels in (
        ("vertex", (rot, pos), ids),
        ("edge", (e_rot, e_trans, info), edge_labels),
    ):
        finite = np.ones(arrays[0].shape[0], dtype=bool)
        for a in arrays:
            finite &= np.isfinite(a.reshape(a.shape[0], math.prod(a.shape[1:]))).all(axis=1)
        if not finite.all():
            raise ValueError(f"{what} {labels[int(np.flatnonzero(~finite)[0])]}: not finite")
    _check_rotations(rot, "vertex", ids)
    _check_rotations(e_rot, "edge", edge_labels)
    if info.shape[0]:
        asym = np.abs(info - np.swapaxes(info, 1, 2)).max(axis=(1, 2))
        scale = np.maximum(np.abs(info).max(axis=(1, 2)), 1.0)
        bad = np.flatnonzero(asym > 1e-9 * scale)
        if bad.size:
            k = int(bad[0])
            raise ValueError(
                f"edge {edge_labels[k]}: information matrix is not symmetric "
                f"(max asymmetry {asym[k]:.3g})"
            )

    def quats(r: np.ndarray) -> np.ndarray:
        if r.shape[0] == 0:
            return np.zeros((0, 4))
        return matrix_to_quat(torch.as_tensor(r)).numpy()[:, [1, 2, 3, 0]]

    q, e_q = quats(rot), quats(e_rot)
    upper = info[:, _INFO_ROWS, _INFO_COLS]
    target = Path(path)
    with atomic_write(target, newline="") as handle:
        for vid, p, qv in zip(ids.tolist(), pos.tolist(), q.tolist(), strict=True):
            handle.write(f"{G2O_VERTEX_TAG} {vid} " + " ".join(map(repr, p + qv)) + "\n")
        for vid in graph.fixed_ids:
            handle.write(f"{FIX_TAG} {vid}\n")
        for (i, j), t, qv, u in zip(
            pairs.tolist(), e_trans.tolist(), e_q.tolist(), upper.tolist(), strict=True
        ):
            handle.write(f"{G2O_EDGE_TAG} {i} {j} " + " ".join(map(repr, t + qv + u)) + "\n")
    return target


def gtsam_pose_graph_path(name: str) -> Path:
    """Path of a pose-graph file shipped with gtsam, e.g. ``"sphere2500.txt"``.

    Args:
        name: a file name inside the installed gtsam wheel's ``Data`` folder; the 3-D graphs
            this module reads are listed in :data:`GTSAM_POSE3_FILES`.

    Returns:
        the absolute path of an existing file (read it with :func:`read_pose_graph`).

    Raises:
        MissingExtraError: gtsam is not installed (``pip install 'msf_torch[peers]'``).
        DataError: no such file in the installed gtsam's Data folder.
    """
    return gtsam_data_path(name)
