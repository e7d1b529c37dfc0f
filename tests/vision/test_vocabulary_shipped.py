"""The shipped ORB vocabulary (checkpoints/orb_vocabulary.npz): it loads, it is written in
the format Vocabulary.save writes, its tree is well formed, and it describes rendered
frames; the slow test rebuilds it with the benchmark's recipe and compares every array."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from msf_torch.vision.loop import describe_place
from msf_torch.vision.vocabulary import Vocabulary, bow_l1_score, build_vocabulary

SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "orb_vocabulary.npz"
TRAINING_IMAGES = 363  # every fifth frame of three 60 s runs (benchmarks/loop_closure.py)


def test_shipped_vocabulary_is_in_the_saved_format(tmp_path):
    shipped = Vocabulary.load(SHIPPED)
    descriptors = np.random.default_rng(0).integers(0, 256, (400, 32), dtype=np.uint8)
    build_vocabulary(descriptors, np.arange(400) // 40, 4, 2).save(tmp_path / "small.npz")
    with np.load(SHIPPED) as ours, np.load(tmp_path / "small.npz") as fresh:
        assert sorted(ours.files) == sorted(fresh.files)
        for name in fresh.files:
            assert ours[name].dtype == fresh[name].dtype, name
            assert ours[name].ndim == fresh[name].ndim, name
    assert SHIPPED.stat().st_size < 2_000_000
    assert (shipped.branching, shipped.depth) == (10, 4)
    assert 5_000 < shipped.num_words <= 10**4
    # a tree: every node but the root is the child of exactly one node, leaves are words
    children = shipped.children[shipped.children >= 0]
    assert np.array_equal(np.sort(children), np.arange(1, len(shipped.centres)))
    leaves = shipped.children[:, 0] < 0
    leaves[0] = False
    assert np.array_equal(np.sort(shipped.word_of_node[leaves]), np.arange(shipped.num_words))
    assert (shipped.word_of_node[~leaves] == -1).all()
    assert shipped.idf.min() >= 0.0 and shipped.idf.max() <= math.log(TRAINING_IMAGES) + 1e-12


def test_shipped_vocabulary_describes_rendered_frames(rendered):
    _, renderer, frames = rendered
    vocabulary = Vocabulary.load(SHIPPED)
    places = [describe_place(f.left, f.right, renderer.rig) for f in (frames[0], frames[2])]
    words = vocabulary.words(places[0].descriptors)
    assert len(np.unique(words)) > 0.5 * len(words)  # spread over the vocabulary
    vectors = [vocabulary.bow(p.descriptors) for p in places]
    assert bow_l1_score(vectors[0], vectors[0]) == pytest.approx(1.0)
    assert 0.0 < bow_l1_score(vectors[0], vectors[1]) < 1.0


@pytest.mark.slow
def test_shipped_vocabulary_equals_a_rebuild(tmp_path):
    """The benchmark's recipe (seeds 301-303, about 3 min) gives the shipped file."""
    from benchmarks.loop_closure import train_vocabulary

    train_vocabulary(tmp_path / "rebuilt.npz")
    with np.load(SHIPPED) as ours, np.load(tmp_path / "rebuilt.npz") as rebuilt:
        assert sorted(ours.files) == sorted(rebuilt.files)
        for name in ours.files:
            np.testing.assert_array_equal(ours[name], rebuilt[name], err_msg=name)
