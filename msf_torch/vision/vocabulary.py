"""Bag of binary words: a vocabulary tree over ORB descriptors, tf-idf vectors, L1 scores.

Vocabulary (built offline, :func:`build_vocabulary`)
    Hierarchical k-majority clustering (k-means for binary strings under the Hamming
    distance): the training descriptors are split into ``branching`` clusters, each cluster
    again into ``branching``, down to ``depth`` levels; the leaves are the words. A cluster's
    centre is the bitwise majority of its members (the binary string minimising the summed
    Hamming distance to them, bit by bit); seeds are drawn by k-means++ (probability
    proportional to the squared Hamming distance to the nearest seed so far). A node with
    at most ``branching`` distinct descriptors gets one leaf per descriptor (DBoW2's rule).

Word look-up (:meth:`Vocabulary.words`)
    Descend from the root, at each level to the child with the nearest centre (Hamming,
    ties to the lower index), until a leaf: ``depth`` x ``branching`` distance evaluations
    instead of one per word. Greedy descent is the tree's definition of a word; it equals
    the globally nearest leaf centre when the clusters are well separated (and always for a
    one-level tree).

Weights
    ``idf_w = ln(N / n_w)`` over the N training images, ``n_w`` the number of training
    images in which word ``w`` occurs (looked up with the finished tree; a word no training
    image maps to gets ``ln N``, as if seen once). An image's vector has
    ``v_w = tf_w idf_w`` with ``tf_w`` = (its descriptors in ``w``) / (its descriptors),
    normalised to unit L1 norm (:meth:`Vocabulary.bow`).

Score
    ``s(v, u) = 1 - 0.5 |v - u|_1`` in [0, 1] for unit-L1 non-negative vectors
    (:func:`bow_l1_score`), computed over the shared words only as
    ``0.5 sum_w (v_w + u_w - |v_w - u_w|)``; :class:`BowDatabase` scores a query against every
    stored vector through an inverted file (word -> entries).

Reference: D. Galvez-Lopez and J. D. Tardos, "Bags of Binary Words for Fast Place
Recognition in Image Sequences", IEEE T-RO 28(5), 2012 (DBoW2).

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> descriptors = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    >>> vocabulary = build_vocabulary(descriptors, np.arange(400) // 40, branching=4, depth=2)
    >>> vocabulary.num_words <= 16, vocabulary.words(descriptors[:3]).shape
    (True, (3,))
"""

from __future__ import annotations

__all__ = [
    "BowVector",
    "Vocabulary",
    "BowDatabase",
    "hamming_distance",
    "k_majority",
    "build_vocabulary",
    "bow_l1_score",
]

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse

_POPCOUNT = np.array([bin(value).count("1") for value in range(256)], np.uint8)


def hamming_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between binary descriptors, broadcasting over the leading dims.

    Args:
        a, b: (..., 32) uint8 (any byte length, the same for both).
    Returns:
        (...) int64 numbers of differing bits.
    """
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(-1, dtype=np.int64)


def _majority(descriptors: np.ndarray, assignment: np.ndarray, count: int) -> np.ndarray:
    """Bitwise majority (count, bytes) uint8 of the members of each cluster (a bit is set
    when more than half the members have it; an empty cluster gets zeros)."""
    bits = np.unpackbits(descriptors, axis=1).astype(np.float64)
    members = sparse.csr_matrix(
        (np.ones(len(assignment)), (assignment, np.arange(len(assignment)))),
        shape=(count, len(assignment)),
    )
    ones = np.asarray(members @ bits)
    sizes = np.bincount(assignment, minlength=count)[:, None]
    return np.packbits((2.0 * ones > sizes).astype(np.uint8), axis=1)


def k_majority(
    descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """k-majority clustering of binary descriptors (k-means under the Hamming distance).

    k-means++ seeding, then alternate nearest-centre assignment and bitwise-majority
    centres until the assignment stops changing or ``iterations`` rounds; an emptied
    cluster keeps its previous centre.

    Args:
        descriptors: (N, bytes) uint8, at least ``k`` distinct rows.
        k: clusters.
        rng: seeding stream.
        iterations: most assignment rounds.
    Returns:
        centres (k, bytes) uint8 and the assignment (N,) int64 to the final centres.
    """
    count = len(descriptors)
    first = int(rng.integers(count))
    seeds = [first]
    nearest = hamming_distance(descriptors, descriptors[first]).astype(np.float64)
    for _ in range(1, k):
        weight = nearest**2
        total = float(weight.sum())
        if total <= 0.0:
            raise ValueError(f"k_majority: fewer than k = {k} distinct descriptors")
        pick = int(rng.choice(count, p=weight / total))
        seeds.append(pick)
        nearest = np.minimum(nearest, hamming_distance(descriptors, descriptors[pick]))
    centres = descriptors[seeds].copy()
    assignment = np.full(count, -1, np.int64)
    for _ in range(max(iterations, 1)):
        distance = hamming_distance(descriptors[:, None, :], centres[None, :, :])
        new_assignment = np.argmin(distance, axis=1)
        if np.array_equal(new_assignment, assignment):
            break
        assignment = new_assignment
        updated = _majority(descriptors, assignment, k)
        empty = np.bincount(assignment, minlength=k) == 0
        centres = np.where(empty[:, None], centres, updated)
    distance = hamming_distance(descriptors[:, None, :], centres[None, :, :])
    return centres, np.argmin(distance, axis=1)


@dataclass
class BowVector:
    """A sparse unit-L1 tf-idf vector.

    Attributes:
        words: (n,) int64 word ids, increasing.
        weights: (n,) float64 > 0, summing to 1 (empty when no descriptor had weight).
    """

    words: np.ndarray
    weights: np.ndarray


def bow_l1_score(a: BowVector, b: BowVector) -> float:
    """``1 - 0.5 |a - b|_1`` in [0, 1] of two unit-L1 vectors (0 when either is empty)."""
    common, index_a, index_b = np.intersect1d(
        a.words, b.words, assume_unique=True, return_indices=True
    )
    if common.size == 0:
        return 0.0
    wa, wb = a.weights[index_a], b.weights[index_b]
    return float(0.5 * (wa + wb - np.abs(wa - wb)).sum())


@dataclass
class Vocabulary:
    """A vocabulary tree (see the module docstring).

    Attributes:
        centres: (M, bytes) uint8 node centres (row 0, the root, unused).
        children: (M, branching) int64 child node ids, -1 where absent (leaves: all -1).
        word_of_node: (M,) int64 word id of each leaf, -1 for inner nodes.
        idf: (W,) float64 inverse document frequency of each word.
        branching: children per node. depth: levels below the root.
    """

    centres: np.ndarray
    children: np.ndarray
    word_of_node: np.ndarray
    idf: np.ndarray
    branching: int
    depth: int

    @property
    def num_words(self) -> int:
        """W."""
        return int(self.idf.shape[0])

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id (N,) int64 of each descriptor (N, bytes) uint8 by greedy descent."""
        descriptors = np.ascontiguousarray(descriptors, np.uint8)
        node = np.zeros(len(descriptors), np.int64)
        for _ in range(self.depth):
            options = self.children[node]  # (N, k)
            inner = options[:, 0] >= 0
            if not inner.any():
                break
            rows = np.nonzero(inner)[0]
            options = options[rows]
            distance = hamming_distance(descriptors[rows, None, :], self.centres[options])
            distance = np.where(options >= 0, distance, np.iinfo(np.int64).max)
            node[rows] = options[np.arange(len(rows)), np.argmin(distance, axis=1)]
        return self.word_of_node[node]

    def bow(self, descriptors: np.ndarray) -> BowVector:
        """The unit-L1 tf-idf vector of one image's descriptors (N, bytes) uint8."""
        if len(descriptors) == 0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        words, counts = np.unique(self.words(descriptors), return_counts=True)
        weights = counts / len(descriptors) * self.idf[words]
        keep = weights > 0
        words, weights = words[keep], weights[keep]
        total = float(weights.sum())
        if total <= 0.0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        return BowVector(words.astype(np.int64), weights / total)

    def save(self, path: str | Path) -> None:
        """Write the vocabulary to an ``.npz`` file."""
        np.savez_compressed(
            path,
            centres=self.centres,
            children=self.children,
            word_of_node=self.word_of_node,
            idf=self.idf,
            branching=np.int64(self.branching),
            depth=np.int64(self.depth),
        )

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        """Read a vocabulary written by :meth:`save`.

        Raises:
            ValueError: the file lacks a field or its arrays disagree in shape (names the
                file and the field).
        """
        with np.load(path) as data:
            fields = ("centres", "children", "word_of_node", "idf", "branching", "depth")
            missing = [name for name in fields if name not in data.files]
            if missing:
                raise ValueError(f"{path}: not a vocabulary file, missing {missing}")
            vocabulary = cls(
                centres=data["centres"].astype(np.uint8),
                children=data["children"].astype(np.int64),
                word_of_node=data["word_of_node"].astype(np.int64),
                idf=data["idf"].astype(np.float64),
                branching=int(data["branching"]),
                depth=int(data["depth"]),
            )
        nodes = len(vocabulary.centres)
        if vocabulary.children.shape != (nodes, vocabulary.branching):
            raise ValueError(f"{path}: children must be ({nodes}, branching), field 'children'")
        if vocabulary.word_of_node.shape != (nodes,):
            raise ValueError(f"{path}: word_of_node must be ({nodes},), field 'word_of_node'")
        if int(vocabulary.word_of_node.max()) + 1 != vocabulary.num_words:
            raise ValueError(f"{path}: idf length disagrees with the leaves, field 'idf'")
        return vocabulary


def build_vocabulary(
    descriptors: np.ndarray,
    image_index: np.ndarray,
    branching: int = 10,
    depth: int = 4,
    seed: int = 0,
    iterations: int = 10,
) -> Vocabulary:
    """Build a vocabulary tree from training descriptors (see the module docstring).

    Args:
        descriptors: (N, bytes) uint8 training descriptors.
        image_index: (N,) int training image of each descriptor (for the idf weights).
        branching: children per node (k).
        depth: levels (L); at most ``branching ** depth`` words.
        seed: clustering seed.
        iterations: k-majority rounds per node.
    Returns:
        the :class:`Vocabulary`.
    Raises:
        ValueError: shapes disagree, or ``branching < 2`` or ``depth < 1``.
    """
    descriptors = np.ascontiguousarray(descriptors, np.uint8)
    image_index = np.asarray(image_index, np.int64)
    if descriptors.ndim != 2 or image_index.shape != (len(descriptors),):
        raise ValueError(
            f"build_vocabulary: descriptors (N, bytes) and image_index (N,) expected, got "
            f"{descriptors.shape} and {image_index.shape}"
        )
    if branching < 2 or depth < 1 or len(descriptors) == 0:
        raise ValueError("build_vocabulary: branching >= 2, depth >= 1 and descriptors needed")
    rng = np.random.default_rng(seed)
    centres = [np.zeros(descriptors.shape[1], np.uint8)]
    children: list[list[int]] = [[]]
    frontier = [(0, np.arange(len(descriptors)))]
    for _ in range(depth):
        next_frontier = []
        for node, members in frontier:
            distinct = np.unique(descriptors[members], axis=0)
            if len(distinct) <= branching:
                groups = [(row, np.zeros(0, np.int64)) for row in distinct]
            else:
                node_centres, assignment = k_majority(
                    descriptors[members], branching, rng, iterations
                )
                groups = [(node_centres[c], members[assignment == c]) for c in range(branching)]
            for centre, child_members in groups:
                children[node].append(len(centres))
                centres.append(centre)
                children.append([])
                if len(child_members) > 1:
                    next_frontier.append((len(centres) - 1, child_members))
        frontier = next_frontier
    table = np.full((len(centres), branching), -1, np.int64)
    for node, kids in enumerate(children):
        table[node, : len(kids)] = kids
    leaves = table[:, 0] < 0
    leaves[0] = False
    word_of_node = np.full(len(centres), -1, np.int64)
    word_of_node[leaves] = np.arange(int(leaves.sum()))
    vocabulary = Vocabulary(
        centres=np.stack(centres),
        children=table,
        word_of_node=word_of_node,
        idf=np.zeros(int(leaves.sum())),
        branching=branching,
        depth=depth,
    )
    words = vocabulary.words(descriptors)
    images = np.unique(image_index)
    pairs = np.unique(np.stack((image_index, words), -1), axis=0)
    documents = np.bincount(pairs[:, 1], minlength=vocabulary.num_words)
    vocabulary.idf = np.log(len(images) / np.maximum(documents, 1)).astype(np.float64)
    return vocabulary


class BowDatabase:
    """Stored bag-of-words vectors with an inverted file (word -> entries) for scoring.

    Entries are numbered in insertion order from 0.
    """

    def __init__(self) -> None:
        self._entries: dict[int, list[int]] = {}
        self._weights: dict[int, list[float]] = {}
        self.vectors: list[BowVector] = []

    def __len__(self) -> int:
        return len(self.vectors)

    def add(self, vector: BowVector) -> int:
        """Store a vector; returns its entry number."""
        entry = len(self.vectors)
        self.vectors.append(vector)
        for word, weight in zip(vector.words.tolist(), vector.weights.tolist(), strict=True):
            self._entries.setdefault(word, []).append(entry)
            self._weights.setdefault(word, []).append(weight)
        return entry

    def scores(self, query: BowVector) -> np.ndarray:
        """L1 scores (E,) float64 of ``query`` against every entry (:func:`bow_l1_score`)."""
        total = np.zeros(len(self.vectors))
        for word, weight in zip(query.words.tolist(), query.weights.tolist(), strict=True):
            entries = self._entries.get(word)
            if entries is None:
                continue
            stored = np.asarray(self._weights[word])
            total[np.asarray(entries)] += weight + stored - np.abs(weight - stored)
        return 0.5 * total
