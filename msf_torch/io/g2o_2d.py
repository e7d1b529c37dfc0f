"""2-D pose graphs: g2o (``VERTEX_SE2`` / ``EDGE_SE2``) and TORO (``VERTEX2`` / ``EDGE2``)
files, read into a :class:`PoseGraph2D` and written back as g2o.

Planar graphs are what a wheeled robot with a 2-D LiDAR or wheel odometry and loop closures
produces (the classic benchmarks ``intel``, ``M3500``, ``w10000`` are in these formats).

Formats
    One record per line, space separated; ``#`` starts a comment; blank lines are ignored.
    Ids are non-negative integers, lengths in m, angles in rad.

    * ``VERTEX_SE2 id x y theta`` / ``VERTEX2 id x y theta`` -- the pose of vertex ``id``:
      position ``[x, y]`` and heading ``theta`` (body -> world rotation ``R(theta)``).
    * ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` -- the measured relative pose
      ``T_ij = T_i^-1 T_j`` and the upper triangle, row by row, of its 3x3 information
      matrix in ``[x, y, theta]`` order (g2o's and GTSAM's ``readG2o`` layout).
    * ``EDGE2 i j dx dy dtheta I_xx I_xy I_yy I_tt I_xt I_yt`` -- TORO's edge: the same
      pose, the information matrix in TORO's order (``inf_ff inf_fs inf_ss inf_rr inf_fr
      inf_sr``: forward, sideways, rotation), GTSAM's ``load2D(..., NoiseFormatTORO)``.
    * ``ODOMETRY i j dx dy dtheta C11 C12 C13 C22 C23 C33`` -- the same pose, with the
      upper triangle of its *covariance* (GTSAM's ``NoiseFormatCOV``, the layout its
      ``load2D`` finds in ``victoria_park.txt``); stored inverted, as information.
    * ``VERTEX_XY id x y`` -- the position of landmark ``id`` (landmarks have their own id
      space, GTSAM's ``L(id)`` keys).
    * ``BR i l bearing range bearing_sigma range_sigma`` -- landmark ``l`` seen from vertex
      ``i``: bearing (rad, from the vertex's x axis, counter-clockwise) and range (m), with
      their standard deviations.
    * ``LANDMARK i l x y v_xx v_xy v_yy`` -- landmark ``l`` at ``(x, y)`` in vertex ``i``'s
      frame, read as GTSAM's ``load2D`` reads it: bearing ``atan2(y, x)`` and range
      ``|(x, y)|``; when ``|v_xx - v_yy| < 1e-4`` the variance is taken to describe the
      uncertainty at 10 m, bearing sigma ``sqrt(v_xx / 10)`` rad and range sigma
      ``sqrt(v_xx)`` m, else both sigmas 1 (with a warning).
    * ``FIX id [id ...]`` -- vertices held fixed by the optimiser (``PoseGraph2D.fixed_ids``).

    A landmark without a ``VERTEX_XY`` line is placed where its first sighting (file order)
    puts it from that vertex's initial pose, as ``load2D`` places it.

    A file with edges and no vertices (``cityTrees_reduced_1k.g2o``, ``victoria_park.txt``)
    is read with ``has_vertices=False`` and GTSAM's ``load2D`` rule for the initial poses:
    record by record in file order, a vertex i not yet placed goes to the origin, then a
    vertex j not yet placed goes to ``T_i T_ij`` (for an odometry chain: ``T_{k+1} = T_k
    T_{k,k+1}`` from the first vertex at the origin); a sighting's vertex not yet placed
    goes to the origin.

Cost (the reference is GTSAM 4.3's ``BetweenFactor<Pose2>`` as the gtsam wheel builds it)
    The error of edge ``ij`` is the SE(2) logarithm of the error pose
    ``E = Z_ij^-1 T_i^-1 T_j`` (``Pose2.Logmap``: ``[V(theta)^-1 t, theta]``, theta wrapped
    to (-pi, pi]), and the cost is ``0.5 * sum e^T I e`` with the file's information ``I``
    (:mod:`msf_torch.backend.posegraph2d`). g2o's ``EdgeSE2`` uses ``[t, theta]`` of the same
    error pose; the two agree to first order. A sighting adds GTSAM's
    ``BearingRangeFactor<Pose2, Point2>`` error ``[wrap(bearing - b), range - r]``.

Rules
    Malformed records raise :class:`DataError` naming file, 1-based line and field (``id``,
    ``i``, ``j``, ``x``, ``y``, ``theta``; ``info[r,c]`` for ``EDGE_SE2``, TORO's own names
    ``inf_ff`` ... ``inf_sr`` for ``EDGE2``): a wrong number
    of values, a value that is not a finite number, a bad id, a duplicate vertex id, an edge
    from a vertex to itself, an information matrix that is not positive definite, an edge
    naming an undefined vertex (when the file defines any), a ``FIX`` naming no vertex of
    the graph, and any 3-D pose tag (read those with
    :func:`~msf_torch.io.g2o.read_pose_graph`); for landmarks a duplicate ``VERTEX_XY``
    id, a sighting from a vertex no vertex line defines, a zero or negative range and a
    sigma that is not positive. Other tags (``EQUIV``,
    ``LANDMARK2``, ``EDGE_SE2_XY``, ...) are skipped,
    counted in ``PoseGraph2D.skipped`` and reported by one ``UserWarning`` (GTSAM's
    ``readG2o`` skips them too); ``unknown_tags="error"`` raises instead.
"""

from __future__ import annotations

__all__ = [
    "GTSAM_LANDMARK2_FILES",
    "GTSAM_POSE2_FILES",
    "LANDMARK_VARIANCE_RANGE_M",
    "PoseGraph2D",
    "is_pose_graph_2d",
    "pose_graph_kind",
    "read_pose_graph_2d",
    "write_g2o_2d",
]

import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from msf_torch.io import _tables
from msf_torch.io.atomic import atomic_write
from msf_torch.io.errors import DataError
from msf_torch.io.g2o import (
    FIX_TAG,
    POSE3_TAGS,
    GraphSizes,
    RecordBook,
    check_graph_fields,
    edge_rows,
    parse_float_fields,
    parse_id,
)

G2O_VERTEX_TAG = "VERTEX_SE2"
G2O_EDGE_TAG = "EDGE_SE2"
TORO_VERTEX_TAG = "VERTEX2"
TORO_EDGE_TAG = "EDGE2"
ODOMETRY_TAG = "ODOMETRY"
LANDMARK_TAG = "LANDMARK"
BEARING_RANGE_TAG = "BR"
POINT_VERTEX_TAG = "VERTEX_XY"
EDGE_TAGS = frozenset({G2O_EDGE_TAG, TORO_EDGE_TAG, ODOMETRY_TAG})
POSE2_TAGS = frozenset({G2O_VERTEX_TAG, TORO_VERTEX_TAG, *EDGE_TAGS})
LANDMARK_TAGS = frozenset({LANDMARK_TAG, BEARING_RANGE_TAG, POINT_VERTEX_TAG})

GTSAM_POSE2_FILES = (
    "cityTrees_reduced_1k.g2o",
    "noisyToyGraph.txt",
    "optimizedNoisyToyGraph.txt",
    "orientationsNoisyToyGraph.txt",
    "pose2example.txt",
    "victoriaPark_reduced_1k.g2o",
    "w100.graph",
    "w10000.graph",
)
"""2-D pose graphs shipped in the gtsam wheel's ``Data`` folder that
:func:`read_pose_graph_2d` reads as GTSAM's ``load2D`` does (``.g2o`` / ``.txt`` files with
``NoiseFormatG2O``, the TORO ``.graph`` files with ``NoiseFormatTORO``). Their ``EQUIV`` and
``LANDMARK2`` lines are skipped by both."""

GTSAM_LANDMARK2_FILES = ("example.graph", "victoria_park.txt")
"""2-D graphs with landmark sightings shipped with gtsam that :func:`read_pose_graph_2d` reads
as GTSAM's ``load2D`` (default noise format) does: ``example.graph`` (TORO poses and edges,
``BR`` sightings) and ``victoria_park.txt`` (the Victoria Park drive, Sydney: a utility car
with wheel odometry and a laser detecting tree trunks; 6,969 poses, ``ODOMETRY`` and 3,640
``LANDMARK`` sightings of 151 trees)."""

_TAGS = (
    f"{G2O_VERTEX_TAG}, {G2O_EDGE_TAG}, {TORO_VERTEX_TAG}, {TORO_EDGE_TAG}, {ODOMETRY_TAG}, "
    f"{POINT_VERTEX_TAG}, {LANDMARK_TAG}, {BEARING_RANGE_TAG}, {FIX_TAG}"
)
_POSE_FIELDS = ("x", "y", "theta")
_G2O_INFO = ("info[0,0]", "info[0,1]", "info[0,2]", "info[1,1]", "info[1,2]", "info[2,2]")
_ODOMETRY_COV = ("cov[0,0]", "cov[0,1]", "cov[0,2]", "cov[1,1]", "cov[1,2]", "cov[2,2]")
_LANDMARK_FIELDS = {
    POINT_VERTEX_TAG: (("id",), ("x", "y")),
    LANDMARK_TAG: (("i", "l"), ("x", "y", "cov[0,0]", "cov[0,1]", "cov[1,1]")),
    BEARING_RANGE_TAG: (("i", "l"), ("bearing", "range", "bearing_sigma", "range_sigma")),
}
LANDMARK_VARIANCE_RANGE_M = 10.0
"""Range (m) at which GTSAM's ``load2D`` takes a ``LANDMARK`` line's x-y variance ``v`` to
hold: bearing sigma ``sqrt(v / 10)`` rad, range sigma ``sqrt(v)`` m."""
_TORO_INFO = ("inf_ff", "inf_fs", "inf_ss", "inf_rr", "inf_fr", "inf_sr")
_EDGE_MATRIX = {G2O_EDGE_TAG: _G2O_INFO, TORO_EDGE_TAG: _TORO_INFO, ODOMETRY_TAG: _ODOMETRY_COV}
# file position k of the six numbers -> (row, col) of the information in [x, y, theta]
_G2O_CELLS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_TORO_CELLS = ((0, 0), (0, 1), (1, 1), (2, 2), (0, 2), (1, 2))
_EDGE_CELLS = {G2O_EDGE_TAG: _G2O_CELLS, TORO_EDGE_TAG: _TORO_CELLS, ODOMETRY_TAG: _G2O_CELLS}


def _empty(*shape: int, integral: bool = False) -> torch.Tensor:
    """An empty float64 (or int64) CPU tensor of ``shape``."""
    return torch.zeros(shape, dtype=torch.int64 if integral else torch.float64)


@dataclass
class PoseGraph2D(GraphSizes):
    """A planar pose graph: vertices (x, y, heading) and relative-pose edges.

    All tensors are float64 (int64 for ids and indices) on one device; N vertices, E edges.

    Attributes:
        vertex_ids: (N,) int64, the file's vertex ids, strictly increasing.
        positions: (N, 2) m, position of each vertex in the world frame.
        headings: (N,) rad, heading of each vertex (body -> world rotation ``R(theta)``).
        edge_index: (E, 2) int64 ``[i, j]`` row indices into the vertex arrays, file order.
        edge_translations: (E, 2) m, measured translation of ``T_ij = T_i^-1 T_j``.
        edge_headings: (E,) rad, measured rotation angle of ``T_ij``.
        edge_information: (E, 3, 3) symmetric positive definite information in
            ``[x, y, theta]`` order (1/m^2, 1/(m rad), 1/rad^2).
        has_vertices: False when the file held edges only (poses chained from the origin).
        edge_lines: (E,) int64 1-based line of each edge in the source file, or None.
        skipped: tag -> number of lines skipped.
        source: the file read, or None.
        fixed_ids: file ids of the vertices the file holds fixed (``FIX``), sorted.
        landmark_ids: (L,) int64 ids of the landmarks (their own id space), increasing.
        landmark_positions: (L, 2) m, landmark positions in the world frame.
        observation_index: (O, 2) int64 ``[vertex row, landmark row]`` of each sighting.
        observation_bearings: (O,) rad, bearing of the landmark in the vertex's frame
            (from its x axis, counter-clockwise).
        observation_ranges: (O,) m, distance from the vertex to the landmark.
        observation_sigmas: (O, 2) ``[bearing rad, range m]`` standard deviations.
        observation_lines: (O,) int64 1-based line of each sighting, or None.
    """

    vertex_ids: torch.Tensor
    positions: torch.Tensor
    headings: torch.Tensor
    edge_index: torch.Tensor
    edge_translations: torch.Tensor
    edge_headings: torch.Tensor
    edge_information: torch.Tensor
    has_vertices: bool = True
    edge_lines: torch.Tensor | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    source: str | None = None
    fixed_ids: tuple[int, ...] = ()
    landmark_ids: torch.Tensor = field(default_factory=lambda: _empty(0, integral=True))
    landmark_positions: torch.Tensor = field(default_factory=lambda: _empty(0, 2))
    observation_index: torch.Tensor = field(default_factory=lambda: _empty(0, 2, integral=True))
    observation_bearings: torch.Tensor = field(default_factory=lambda: _empty(0))
    observation_ranges: torch.Tensor = field(default_factory=lambda: _empty(0))
    observation_sigmas: torch.Tensor = field(default_factory=lambda: _empty(0, 2))
    observation_lines: torch.Tensor | None = None

    @property
    def num_landmarks(self) -> int:
        """L, the number of landmarks."""
        return int(self.landmark_ids.shape[0])

    @property
    def num_observations(self) -> int:
        """O, the number of landmark sightings."""
        return int(self.observation_index.shape[0])

    def check(self) -> None:
        """Check shapes, dtypes and index ranges.

        Raises:
            ValueError: naming the first field that is wrong.
        """
        n, e = self.num_vertices, self.num_edges
        shapes = {
            "vertex_ids": (n,),
            "positions": (n, 2),
            "headings": (n,),
            "edge_index": (e, 2),
            "edge_translations": (e, 2),
            "edge_headings": (e,),
            "edge_information": (e, 3, 3),
        }
        check_graph_fields(self, "PoseGraph2D", shapes)
        m, o = self.num_landmarks, self.num_observations
        shapes = {
            "landmark_ids": (m,),
            "landmark_positions": (m, 2),
            "observation_index": (o, 2),
            "observation_bearings": (o,),
            "observation_ranges": (o,),
            "observation_sigmas": (o, 2),
        }
        if self.observation_lines is not None:
            shapes["observation_lines"] = (o,)
        for name, shape in shapes.items():
            value = getattr(self, name)
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"PoseGraph2D.{name}: shape {tuple(value.shape)}, expected {shape}"
                )
            integral = name in ("landmark_ids", "observation_index", "observation_lines")
            if integral != (value.dtype == torch.int64) or not (
                integral or value.is_floating_point()
            ):
                expected = "torch.int64" if integral else "floating"
                raise ValueError(f"PoseGraph2D.{name}: dtype {value.dtype}, expected {expected}")
        if m > 1 and not bool((self.landmark_ids.diff() > 0).all()):
            raise ValueError("PoseGraph2D.landmark_ids: not strictly increasing")
        if o:
            rows, cols = self.observation_index[:, 0], self.observation_index[:, 1]
            if (
                int(rows.min()) < 0
                or int(rows.max()) >= n
                or int(cols.min()) < 0
                or int(cols.max()) >= m
            ):
                raise ValueError(f"PoseGraph2D.observation_index: rows outside [0, {n}) x [0, {m})")
            if not bool((self.observation_sigmas > 0).all()):
                raise ValueError("PoseGraph2D.observation_sigmas: not all positive")


def _chain_2d(
    path: str,
    ids: np.ndarray,
    pairs: np.ndarray,
    edges: np.ndarray,
    lines: np.ndarray,
    sightings: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and headings (N,) of a graph without vertex records, GTSAM's
    ``load2D`` rule: in file order, an edge's vertex i not yet placed goes to the origin,
    then its vertex j not yet placed goes to ``T_i T_ij``; a landmark sighting's vertex not
    yet placed goes to the origin. ``edges`` (E, 3) are the measured ``[dx, dy, dtheta]``;
    ``sightings`` the sighting vertex ids (O,) and their lines (O,)."""
    row = {int(v): k for k, v in enumerate(ids.tolist())}
    positions = np.zeros((ids.shape[0], 2))
    headings = np.zeros(ids.shape[0])
    placed = np.zeros(ids.shape[0], dtype=bool)
    seen_ids, seen_lines = sightings
    events = sorted(
        [(int(line), 1, e) for e, line in enumerate(lines.tolist())]
        + [(int(line), 0, k) for k, line in enumerate(seen_lines.tolist())]
    )
    for _, is_edge, e in events:
        if not is_edge:
            placed[row[int(seen_ids[e])]] = True
            continue
        i, j = (int(v) for v in pairs[e])
        a, b = row[i], row[j]
        placed[a] = True
        if placed[b]:
            continue
        c, s = math.cos(headings[a]), math.sin(headings[a])
        dx, dy, dtheta = edges[e]
        with np.errstate(over="ignore", invalid="ignore"):
            positions[b] = positions[a] + (c * dx - s * dy, s * dx + c * dy)
        if not np.isfinite(positions[b]).all():
            raise DataError(
                path,
                f"the initial position of vertex {j}, chained along the edges, overflows (the "
                "translations are too large)",
                line=int(lines[e]),
                field="x",
            )
        headings[b] = math.remainder(headings[a] + dtheta, 2 * math.pi)
        placed[b] = True
    return positions, headings


def pose_graph_kind(path: str | os.PathLike[str]) -> int | None:
    """2 or 3: the kind of the first pose tag (vertex or edge) in the pose-graph file
    ``path`` (2-D: ``VERTEX_SE2``, ``EDGE_SE2``, ``VERTEX2``, ``EDGE2``; 3-D:
    ``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``, ``VERTEX3``, ``EDGE3``); None when it holds
    neither.

    Raises:
        DataError: the file cannot be read.
    """
    for raw in _tables.split_lines(_tables.read_text(os.fspath(path))):
        tokens = raw.split("#", 1)[0].split(maxsplit=1)
        if tokens and tokens[0] in POSE2_TAGS:
            return 2
        if tokens and tokens[0] in POSE3_TAGS:
            return 3
    return None


def is_pose_graph_2d(path: str | os.PathLike[str]) -> bool:
    """Whether the pose-graph file ``path`` is planar (:func:`pose_graph_kind` is 2); False
    when it holds 3-D or no pose tags (the 3-D reader then says what is wrong).

    Raises:
        DataError: the file cannot be read.
    """
    return pose_graph_kind(path) == 2


def _check_count(path: str, tag: str, tokens: list[str], names: tuple[str, ...], line: int) -> None:
    """A DataError unless the record ``tokens`` (tag first) holds one value per field."""
    given = len(tokens) - 1
    if given != len(names):
        problem = (
            f"wrong number of values for {tag} ({tag} {' '.join(names)}): "
            f"expected {len(names)}, got {given}"
        )
        missing = names[given] if given < len(names) else None
        if missing is not None:
            problem += f"; '{missing}' and later fields are missing"
        raise DataError(path, problem, line=line, field=missing)


def _check_sigma(path: str, sigma: float, line: int, name: str) -> None:
    """A DataError unless ``sigma`` is a positive standard deviation whose information
    ``1 / sigma^2`` is finite."""
    if not sigma > 0.0 or sigma * sigma == 0.0 or not math.isfinite(1.0 / (sigma * sigma)):
        raise DataError(
            path,
            f"the standard deviation {sigma!r} this gives is not positive (or its information "
            "1/sigma^2 is not finite)",
            line=line,
            field=name,
        )


@dataclass
class _LandmarkRecords:
    """The landmark records of a 2-D file, in file order: ``VERTEX_XY`` positions and the
    ``LANDMARK`` / ``BR`` sightings as bearing, range and their sigmas (GTSAM's reading)."""

    points: dict[int, tuple[float, float]] = field(default_factory=dict)
    point_lines: dict[int, int] = field(default_factory=dict)
    pairs: list[tuple[int, int]] = field(default_factory=list)
    measured: list[tuple[float, float, float, float]] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)
    unit_sigma_lines: list[int] = field(default_factory=list)

    def read(self, path: str, tokens: list[str], line: int) -> None:
        """Parse one ``VERTEX_XY``, ``LANDMARK`` or ``BR`` record; a DataError when bad."""
        tag = tokens[0]
        id_names, value_names = _LANDMARK_FIELDS[tag]
        names = (*id_names, *value_names)
        _check_count(path, tag, tokens, names, line)
        ids = [parse_id(path, tokens[1 + k], line, n) for k, n in enumerate(id_names)]
        values = parse_float_fields(path, tokens[1 + len(id_names) :], line, value_names)
        if tag == POINT_VERTEX_TAG:
            if ids[0] in self.points:
                raise DataError(
                    path,
                    f"duplicate landmark id {ids[0]} (first defined on line "
                    f"{self.point_lines[ids[0]]})",
                    line=line,
                    field="id",
                )
            self.points[ids[0]] = (values[0], values[1])
            self.point_lines[ids[0]] = line
            return
        if tag == LANDMARK_TAG:
            x, y, var_xx, _, var_yy = values
            distance = math.hypot(x, y)
            if distance == 0.0 or not math.isfinite(distance):
                raise DataError(
                    path,
                    f"the landmark's offset ({x!r}, {y!r}) has no bearing and range "
                    "(zero or overflowing distance)",
                    line=line,
                    field="x",
                )
            bearing = math.atan2(y, x)
            if abs(var_xx - var_yy) < 1e-4:
                sigmas = (
                    math.sqrt(max(var_xx, 0.0) / LANDMARK_VARIANCE_RANGE_M),
                    math.sqrt(max(var_xx, 0.0)),
                )
                for sigma, name in zip(sigmas, ("cov[0,0]", "cov[0,0]"), strict=True):
                    _check_sigma(path, sigma, line, name)
            else:
                sigmas = (1.0, 1.0)
                self.unit_sigma_lines.append(line)
        else:
            bearing, distance, bearing_sigma, range_sigma = values
            if not distance > 0.0:
                raise DataError(
                    path, f"range must be positive, got {distance!r}", line=line, field="range"
                )
            _check_sigma(path, bearing_sigma, line, "bearing_sigma")
            _check_sigma(path, range_sigma, line, "range_sigma")
            bearing = math.remainder(bearing, 2.0 * math.pi)
            sigmas = (bearing_sigma, range_sigma)
        self.pairs.append((ids[0], ids[1]))
        self.measured.append((bearing, distance, *sigmas))
        self.lines.append(line)

    def finish(
        self, path: str, vertex_ids: np.ndarray, positions: np.ndarray, headings: np.ndarray
    ) -> dict[str, torch.Tensor]:
        """The landmark fields of :class:`PoseGraph2D`: landmarks sorted by id, each placed
        at its ``VERTEX_XY`` position or else, as GTSAM's ``load2D`` places it, where its
        first sighting (file order) puts it from that vertex's pose."""
        if not self.points and not self.pairs:
            return {}
        if self.unit_sigma_lines:
            warnings.warn(
                f"{path}: {len(self.unit_sigma_lines)} LANDMARK lines (first on line "
                f"{self.unit_sigma_lines[0]}) give unequal x and y variances; read with bearing "
                "and range sigma 1, as GTSAM's load2D reads them",
                stacklevel=3,
            )
        pairs = np.array(self.pairs, dtype=np.int64).reshape(-1, 2)
        lines = np.array(self.lines, dtype=np.int64)
        measured = np.array(self.measured, dtype=np.float64).reshape(-1, 4)
        rows = np.searchsorted(vertex_ids, pairs[:, 0])
        known = vertex_ids[np.minimum(rows, max(vertex_ids.size - 1, 0))] == pairs[:, 0]
        if vertex_ids.size == 0 or not known.all():
            k = int(np.argmin(known)) if vertex_ids.size else 0
            raise DataError(
                path,
                f"landmark sighting names vertex {int(pairs[k, 0])}, which no vertex line defines",
                line=int(lines[k]),
                field="i",
            )
        landmark_ids = np.array(
            sorted(set(self.points) | set(pairs[:, 1].tolist())), dtype=np.int64
        )
        columns = np.searchsorted(landmark_ids, pairs[:, 1])
        placed = np.zeros((landmark_ids.size, 2))
        given = np.isin(landmark_ids, np.array(list(self.points), dtype=np.int64))
        for k, lid in enumerate(landmark_ids.tolist()):
            if given[k]:
                placed[k] = self.points[lid]
        # each landmark's first sighting in file order (np.unique returns first indices)
        seen_cols, first = np.unique(columns, return_index=True)
        todo = np.isin(seen_cols, np.flatnonzero(~given))
        cols, first = seen_cols[todo], first[todo]
        if cols.size:
            angle = headings[rows[first]] + measured[first, 0]
            with np.errstate(over="ignore", invalid="ignore"):
                placed[cols] = positions[rows[first]] + measured[first, 1:2] * np.stack(
                    (np.cos(angle), np.sin(angle)), 1
                )
            bad = np.flatnonzero(~np.isfinite(placed[cols]).all(axis=1))
            if bad.size:
                k = int(first[bad[0]])
                raise DataError(
                    path,
                    f"the initial position of landmark {landmark_ids[cols[bad[0]]]} from its "
                    "first sighting overflows",
                    line=int(lines[k]),
                    field="range",
                )

        def f64(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

        return {
            "landmark_ids": torch.as_tensor(landmark_ids, dtype=torch.int64),
            "landmark_positions": f64(placed),
            "observation_index": torch.as_tensor(
                np.stack((rows, columns), 1), dtype=torch.int64
            ).reshape(-1, 2),
            "observation_bearings": f64(measured[:, 0]),
            "observation_ranges": f64(measured[:, 1]),
            "observation_sigmas": f64(measured[:, 2:4]),
            "observation_lines": torch.as_tensor(lines, dtype=torch.int64),
        }


def read_pose_graph_2d(
    path: str | os.PathLike[str], *, unknown_tags: Literal["skip", "error"] = "skip"
) -> PoseGraph2D:
    """Read a 2-D pose graph from a g2o or TORO file (tags may be mixed).

    Args:
        path: the file.
        unknown_tags: ``"skip"`` (default) skips and counts lines whose tag is not a 2-D pose
            tag or ``FIX`` and warns once; ``"error"`` raises DataError on them. 3-D pose tags
            always raise.

    Returns:
        a :class:`PoseGraph2D` in float64 on the CPU: vertices sorted by id, edges in file
        order, information in ``[x, y, theta]`` order (module docstring).

    Raises:
        DataError: naming file, line and field of the first bad record; also a missing file,
            one without vertices and edges, and one with skipped tags but no pose edge.
        ValueError: an unknown ``unknown_tags``.

    Warns:
        UserWarning: once per file when lines were skipped (each tag's count, first line).
    """
    if unknown_tags not in ("skip", "error"):
        raise ValueError(f"unknown_tags must be 'skip' or 'error', got {unknown_tags!r}")
    path_str = os.fspath(path)
    vertex_line: dict[int, int] = {}
    vertices: list[list[float]] = []
    edge_pairs: list[tuple[int, int]] = []
    edge_values: list[list[float]] = []
    edge_lines: list[int] = []
    edge_tags: list[str] = []
    marks = _LandmarkRecords()
    book = RecordBook(path_str)
    for line_no, raw in enumerate(_tables.split_lines(_tables.read_text(path_str)), start=1):
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        tag = tokens[0]
        if tag == FIX_TAG:
            book.read_fix(tokens, line_no)
            continue
        if tag in LANDMARK_TAGS:
            marks.read(path_str, tokens, line_no)
            continue
        if tag not in POSE2_TAGS:
            if tag in POSE3_TAGS:
                first_2d = min([*vertex_line.values(), *edge_lines[:1]], default=None)
                advice = (
                    "read 3-D graphs with msf_torch.io.read_pose_graph"
                    if first_2d is None
                    else f"the file mixes it with 2-D records (the first on line {first_2d}); "
                    "keep one kind per file"
                )
                raise DataError(
                    path_str,
                    f"3-D pose-graph tag {_tables.shown(tag)}; this reader reads 2-D graphs "
                    f"({_TAGS}); {advice}",
                    line=line_no,
                    field="tag",
                )
            book.other_tag(tag, line_no, unknown_tags, _TAGS)
            continue
        edge = tag in EDGE_TAGS
        id_names = ("i", "j") if edge else ("id",)
        names = (*id_names, *_POSE_FIELDS, *(_EDGE_MATRIX[tag] if edge else ()))
        _check_count(path_str, tag, tokens, names, line_no)
        ids = [parse_id(path_str, tokens[1 + k], line_no, n) for k, n in enumerate(id_names)]
        values = parse_float_fields(
            path_str, tokens[1 + len(id_names) :], line_no, names[len(id_names) :]
        )
        if not edge:
            if ids[0] in vertex_line:
                raise DataError(
                    path_str,
                    f"duplicate vertex id {ids[0]} (first defined on line {vertex_line[ids[0]]})",
                    line=line_no,
                    field="id",
                )
            vertex_line[ids[0]] = line_no
            vertices.append([float(ids[0]), *values])
            continue
        if ids[0] == ids[1]:
            raise DataError(
                path_str, f"edge from vertex {ids[0]} to itself", line=line_no, field="j"
            )
        matrix = np.zeros((3, 3))
        for (row, col), value in zip(_EDGE_CELLS[tag], values[3:], strict=True):
            matrix[row, col] = matrix[col, row] = value
        edge_pairs.append((ids[0], ids[1]))
        edge_values.append([*values[:3], *matrix.ravel()])
        edge_lines.append(line_no)
        edge_tags.append(tag)
    if edge_values:
        # Cholesky, not the smallest eigenvalue: rounding can make a singular matrix's
        # positive, and a PD diagonal's with entries 1e-308 and 1e308 zero; one batched
        # factorisation for all edges (ODOMETRY gives covariances, the rest information)
        matrices = torch.tensor([v[3:] for v in edge_values], dtype=torch.float64)
        chol, info = torch.linalg.cholesky_ex(matrices.reshape(-1, 3, 3))
        failed = torch.nonzero(info)
        if failed.numel():
            k = int(failed[0, 0])
            matrix = matrices[k].reshape(3, 3).numpy()
            what = "covariance" if edge_tags[k] == ODOMETRY_TAG else "information"
            raise DataError(
                path_str,
                f"{what} matrix is not positive definite (eigenvalues "
                f"{np.array2string(np.linalg.eigvalsh(matrix), precision=4)}; {edge_tags[k]} "
                f"gives it as {' '.join(_EDGE_MATRIX[edge_tags[k]])})",
                line=edge_lines[k],
                field="covariance" if what == "covariance" else "information",
            )
        odometry = torch.tensor([t == ODOMETRY_TAG for t in edge_tags])
        if bool(odometry.any()):
            inverse = torch.cholesky_inverse(chol[odometry])
            if not bool(torch.isfinite(inverse).all()):
                k = int(torch.nonzero(odometry)[0, 0])
                raise DataError(
                    path_str,
                    "covariance matrix too close to singular to invert",
                    line=edge_lines[k],
                    field="covariance",
                )
            for k, row in zip(torch.nonzero(odometry)[:, 0].tolist(), inverse, strict=True):
                edge_values[k][3:] = row.reshape(-1).tolist()

    if not edge_lines and not marks.lines:
        if book.skipped:
            raise DataError(
                path_str,
                f"no 2-D pose edges ({G2O_EDGE_TAG}, {TORO_EDGE_TAG} or {ODOMETRY_TAG}) or "
                f"landmark sightings, only tags this reader does not read: {book.tally()} "
                f"(tags read: {_TAGS})",
            )
        if not vertices:
            raise DataError(path_str, f"no vertices or edges (tags read: {_TAGS})")
    pairs = np.array(edge_pairs, dtype=np.int64).reshape(-1, 2)
    edges = np.array(edge_values, dtype=np.float64).reshape(-1, 12)
    lines = np.array(edge_lines, dtype=np.int64)
    seen = np.array(marks.pairs, dtype=np.int64).reshape(-1, 2)
    seen_lines = np.array(marks.lines, dtype=np.int64)
    if vertices:
        table = np.array(vertices, dtype=np.float64)
        order = np.argsort(table[:, 0], kind="stable")
        vertex_ids = np.array(sorted(vertex_line), dtype=np.int64)
        positions, headings = table[order, 1:3], table[order, 3]
        rows = edge_rows(path_str, vertex_ids, pairs, lines)
    else:
        vertex_ids = np.unique(np.concatenate((pairs.reshape(-1), seen[:, 0])))
        rows = np.searchsorted(vertex_ids, pairs)
        positions, headings = _chain_2d(
            path_str, vertex_ids, pairs, edges[:, :3], lines, (seen[:, 0], seen_lines)
        )
    book.check_fixes(vertex_ids, bool(vertices))
    landmarks = marks.finish(path_str, vertex_ids, positions, headings)
    book.warn_skipped(_TAGS)

    def f64(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float64)

    graph = PoseGraph2D(
        vertex_ids=torch.as_tensor(vertex_ids, dtype=torch.int64),
        positions=f64(positions),
        headings=f64(headings),
        edge_index=torch.as_tensor(rows.reshape(-1, 2), dtype=torch.int64),
        edge_translations=f64(edges[:, 0:2]),
        edge_headings=f64(edges[:, 2]),
        edge_information=f64(edges[:, 3:].reshape(-1, 3, 3)),
        has_vertices=bool(vertices),
        edge_lines=torch.as_tensor(lines, dtype=torch.int64),
        skipped=book.skipped,
        source=path_str,
        fixed_ids=tuple(sorted(book.fixes)),
        **landmarks,
    )
    graph.check()
    return graph


def write_g2o_2d(path: str | os.PathLike[str], graph: PoseGraph2D) -> Path:
    """Write a 2-D pose graph as a g2o file (``VERTEX_SE2``, ``FIX``, ``EDGE_SE2``),
    atomically; the layout of GTSAM's ``writeG2o`` for ``Pose2`` graphs. Landmarks follow as
    ``VERTEX_XY id x y`` and their sightings as ``BR i l bearing range bearing_sigma
    range_sigma`` (both read by GTSAM's ``load2D`` / ``readG2o``).

    Numbers are written as Python's shortest round-trip decimal, so
    ``read_pose_graph_2d(write_g2o_2d(p, g))`` gives back ``g`` exactly (an edge-only
    graph is written with its chained poses as vertices; ``ODOMETRY`` covariances as their
    inverses, in ``EDGE_SE2`` information form).

    Args:
        path: the output file; missing parent folders are created.
        graph: the graph; any device and floating dtype (written as float64).

    Returns:
        the path written.

    Raises:
        ValueError: a malformed graph, no vertices, a non-finite value or an information
            matrix that is not symmetric (named by vertex id or edge index).
    """
    graph.check()
    if graph.num_vertices == 0:
        raise ValueError("a pose graph without vertices cannot be written")

    def host(x: torch.Tensor) -> np.ndarray:
        return x.detach().to(device="cpu", dtype=torch.float64).numpy()

    ids = graph.vertex_ids.detach().cpu().numpy()
    pairs = ids[graph.edge_index.detach().cpu().numpy()].reshape(-1, 2)
    poses = np.concatenate((host(graph.positions), host(graph.headings)[:, None]), 1)
    edges = np.concatenate((host(graph.edge_translations), host(graph.edge_headings)[:, None]), 1)
    info = host(graph.edge_information)
    for what, array, labels in (
        ("vertex", poses, ids.tolist()),
        ("edge", np.concatenate((edges, info.reshape(-1, 9)), 1), range(len(pairs))),
    ):
        bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
        if bad.size:
            raise ValueError(f"{what} {list(labels)[int(bad[0])]}: not finite")
    if info.shape[0]:
        asym = np.abs(info - np.swapaxes(info, 1, 2)).max(axis=(1, 2))
        bad = np.flatnonzero(asym > 1e-9 * np.maximum(np.abs(info).max(axis=(1, 2)), 1.0))
        if bad.size:
            k = int(bad[0])
            raise ValueError(
                f"edge {k} ({pairs[k, 0]} -> {pairs[k, 1]}): information matrix is not "
                f"symmetric (max asymmetry {asym[k]:.3g})"
            )
    landmark_ids = graph.landmark_ids.detach().cpu().numpy()
    points = host(graph.landmark_positions)
    index = graph.observation_index.detach().cpu().numpy()
    seen = np.stack((ids[index[:, 0]], landmark_ids[index[:, 1]]), 1).reshape(-1, 2)
    sightings = np.concatenate(
        (
            host(graph.observation_bearings)[:, None],
            host(graph.observation_ranges)[:, None],
            host(graph.observation_sigmas),
        ),
        1,
    )
    for what, array, labels in (
        ("landmark", points, landmark_ids.tolist()),
        ("sighting", sightings, range(len(seen))),
    ):
        bad = np.flatnonzero(~np.isfinite(array).all(axis=1))
        if bad.size:
            raise ValueError(f"{what} {list(labels)[int(bad[0])]}: not finite")
    upper = info[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    target = Path(path)
    with atomic_write(target, newline="") as handle:
        for vid, pose in zip(ids.tolist(), poses.tolist(), strict=True):
            handle.write(f"{G2O_VERTEX_TAG} {vid} " + " ".join(map(repr, pose)) + "\n")
        for vid in graph.fixed_ids:
            handle.write(f"{FIX_TAG} {vid}\n")
        for (i, j), edge, u in zip(pairs.tolist(), edges.tolist(), upper.tolist(), strict=True):
            handle.write(f"{G2O_EDGE_TAG} {i} {j} " + " ".join(map(repr, edge + u)) + "\n")
        for lid, point in zip(landmark_ids.tolist(), points.tolist(), strict=True):
            handle.write(f"{POINT_VERTEX_TAG} {lid} " + " ".join(map(repr, point)) + "\n")
        for (i, lid), sighting in zip(seen.tolist(), sightings.tolist(), strict=True):
            handle.write(f"{BEARING_RANGE_TAG} {i} {lid} " + " ".join(map(repr, sighting)) + "\n")
    return target
