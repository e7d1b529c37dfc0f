"""Bag-of-words vocabulary: tree look-up against brute force, k-majority centres, tf-idf and
L1 scores against hand computation, the inverted file against pairwise scores, save/load."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msf_torch.vision.vocabulary import (
    BowDatabase,
    BowVector,
    Vocabulary,
    bow_l1_score,
    build_vocabulary,
    hamming_distance,
    k_majority,
)


def _random_descriptors(count: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (count, 32), dtype=np.uint8)


def _bits(descriptors: np.ndarray) -> np.ndarray:
    return np.unpackbits(descriptors, axis=-1).astype(np.int64)


def test_hamming_distance_counts_differing_bits():
    a, b = _random_descriptors(50, 0), _random_descriptors(50, 1)
    expected = np.abs(_bits(a) - _bits(b)).sum(-1)
    np.testing.assert_array_equal(hamming_distance(a, b), expected)
    assert hamming_distance(a[:, None], b[None]).shape == (50, 50)


def test_k_majority_centres_are_bitwise_majorities_of_nearest_members():
    descriptors = _random_descriptors(300, 2)
    centres, assignment = k_majority(descriptors, 5, np.random.default_rng(0), iterations=50)
    distance = hamming_distance(descriptors[:, None], centres[None])
    np.testing.assert_array_equal(assignment, np.argmin(distance, axis=1))
    for c in range(5):
        members = _bits(descriptors[assignment == c])
        if len(members):
            majority = (2 * members.sum(0) > len(members)).astype(np.uint8)
            np.testing.assert_array_equal(_bits(centres[c]), majority)


def test_one_level_tree_lookup_is_the_nearest_word():
    descriptors = _random_descriptors(2000, 3)
    vocabulary = build_vocabulary(descriptors, np.arange(2000) // 100, branching=16, depth=1)
    queries = _random_descriptors(500, 4)
    leaves = np.nonzero(vocabulary.word_of_node >= 0)[0]
    distance = hamming_distance(queries[:, None], vocabulary.centres[leaves][None])
    nearest = vocabulary.word_of_node[leaves][np.argmin(distance, axis=1)]
    np.testing.assert_array_equal(vocabulary.words(queries), nearest)


def _descend(vocabulary: Vocabulary, descriptor: np.ndarray) -> int:
    """Reference look-up: one descriptor, one node at a time."""
    node = 0
    while vocabulary.children[node, 0] >= 0:
        kids = [int(c) for c in vocabulary.children[node] if c >= 0]
        distances = [int(hamming_distance(descriptor, vocabulary.centres[c])) for c in kids]
        node = kids[int(np.argmin(distances))]
    return int(vocabulary.word_of_node[node])


def test_deep_tree_lookup_equals_node_by_node_descent():
    descriptors = _random_descriptors(3000, 5)
    vocabulary = build_vocabulary(descriptors, np.arange(3000) // 50, branching=6, depth=3)
    assert 6 < vocabulary.num_words <= 6**3
    queries = np.concatenate((_random_descriptors(200, 6), descriptors[:100]))
    expected = [_descend(vocabulary, q) for q in queries]
    np.testing.assert_array_equal(vocabulary.words(queries), expected)


def test_separated_clusters_tree_lookup_equals_brute_force_nearest_word():
    """Descriptors around 4 x 4 hierarchical centres (flip 40 bits for the first level, 12
    for the second, 3 for the samples): greedy descent finds the globally nearest word."""
    rng = np.random.default_rng(7)

    def flip(base: np.ndarray, count: int) -> np.ndarray:
        bits = np.unpackbits(base)
        bits[rng.choice(256, count, replace=False)] ^= 1
        return np.packbits(bits)

    root = _random_descriptors(1, 8)[0]
    samples = []
    for _ in range(4):
        top = flip(root, 100)
        for _ in range(4):
            leaf = flip(top, 30)
            samples += [flip(leaf, 3) for _ in range(40)]
    descriptors = np.stack(samples)
    vocabulary = build_vocabulary(
        descriptors, np.arange(len(descriptors)) // 10, branching=4, depth=2, seed=1
    )
    leaves = np.nonzero(vocabulary.word_of_node >= 0)[0]
    assert len(leaves) == 16
    distance = hamming_distance(descriptors[:, None], vocabulary.centres[leaves][None])
    nearest = vocabulary.word_of_node[leaves][np.argmin(distance, axis=1)]
    np.testing.assert_array_equal(vocabulary.words(descriptors), nearest)
    # each generated leaf cluster is one word
    labels = np.arange(len(descriptors)) // 40
    words = vocabulary.words(descriptors)
    for label in range(16):
        assert len(np.unique(words[labels == label])) == 1


def _hand_vocabulary() -> tuple[Vocabulary, np.ndarray]:
    """A flat vocabulary of 4 words (centres 0x00, 0x0f, 0xf0, 0xff in every byte)."""
    centres = np.stack([np.full(32, v, np.uint8) for v in (0, 0x0F, 0xF0, 0xFF)])
    descriptors = np.concatenate(
        [np.repeat(centres[w : w + 1], n, 0) for w, n in enumerate((3, 2, 2, 1))]
    )
    # images: 0 -> words {0, 0, 1}, 1 -> {0, 2, 2}, 2 -> {1, 3}
    image = np.array([0, 0, 1, 0, 2, 1, 1, 2])
    return build_vocabulary(descriptors, image, branching=4, depth=1), descriptors


def test_idf_and_tf_idf_vectors_match_hand_computation():
    vocabulary, _ = _hand_vocabulary()
    assert vocabulary.num_words == 4
    word_of = {
        int(v): int(vocabulary.words(np.full((1, 32), v, np.uint8))[0]) for v in (0, 15, 240, 255)
    }
    # documents containing each word: 0 -> 2 images, 0x0f -> 2, 0xf0 -> 1, 0xff -> 1
    expected_idf = {0: math.log(3 / 2), 15: math.log(3 / 2), 240: math.log(3), 255: math.log(3)}
    for value, idf in expected_idf.items():
        assert vocabulary.idf[word_of[value]] == pytest.approx(idf)
    # an image with descriptors 0, 0, 0xf0, 0xff: tf 1/2, 1/4, 1/4
    image = np.stack([np.full(32, v, np.uint8) for v in (0, 0, 240, 255)])
    bow = vocabulary.bow(image)
    raw = {0: 0.5 * math.log(1.5), 240: 0.25 * math.log(3), 255: 0.25 * math.log(3)}
    total = sum(raw.values())
    got = dict(zip(bow.words.tolist(), bow.weights.tolist(), strict=True))
    assert set(got) == {word_of[v] for v in raw}
    for value, weight in raw.items():
        assert got[word_of[value]] == pytest.approx(weight / total)
    assert bow.weights.sum() == pytest.approx(1.0)


def _dense(vector: BowVector, size: int) -> np.ndarray:
    out = np.zeros(size)
    out[vector.words] = vector.weights
    return out


def test_l1_score_and_inverted_file_match_dense_vectors():
    descriptors = _random_descriptors(4000, 9)
    image = np.arange(4000) // 100
    vocabulary = build_vocabulary(descriptors, image, branching=8, depth=2)
    vectors = [vocabulary.bow(descriptors[image == k]) for k in range(40)]
    database = BowDatabase()
    for vector in vectors[:30]:
        database.add(vector)
    for query in vectors[30:]:
        expected = [
            1.0
            - 0.5
            * np.abs(_dense(query, vocabulary.num_words) - _dense(v, vocabulary.num_words)).sum()
            for v in vectors[:30]
        ]
        np.testing.assert_allclose(
            [bow_l1_score(query, v) for v in vectors[:30]], expected, atol=1e-12
        )
        np.testing.assert_allclose(database.scores(query), expected, atol=1e-12)
    assert bow_l1_score(vectors[0], vectors[0]) == pytest.approx(1.0)


def test_save_load_round_trip(tmp_path):
    vocabulary = build_vocabulary(_random_descriptors(500, 10), np.arange(500) // 25, 5, 2)
    path = tmp_path / "vocabulary.npz"
    vocabulary.save(path)
    loaded = Vocabulary.load(path)
    queries = _random_descriptors(100, 11)
    np.testing.assert_array_equal(loaded.words(queries), vocabulary.words(queries))
    np.testing.assert_array_equal(loaded.idf, vocabulary.idf)
    np.savez(tmp_path / "bad.npz", centres=vocabulary.centres)
    with pytest.raises(ValueError, match="missing"):
        Vocabulary.load(tmp_path / "bad.npz")
