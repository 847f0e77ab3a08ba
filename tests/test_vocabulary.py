"""The inverted-file matcher (service/vision/vocabulary.py): exact where every word is probed,
close to the exact matcher with a few, one vocabulary per map and seed."""

from __future__ import annotations

import numpy as np
import pytest

from service.vision.features import extract
from service.vision.matcher import match_batch_u8, match_batch_u8_reference
from service.vision.vocabulary import InvertedFileMatcher, Vocabulary, index_image


@pytest.fixture(scope="module")
def frames(sunny1, sunny2) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Codes of 8 map images (sunny1) and 3 frames of another round (sunny2)."""
    return ([extract(sunny1.load_image(i)).codes for i in range(8)],
            [extract(sunny2.load_image(i)).codes for i in range(3)])


def _matcher(images: list[np.ndarray], k: int, probes: int) -> InvertedFileMatcher:
    return InvertedFileMatcher(lambda i: images[i], np.vstack(images), len(images), k, probes)


def test_every_word_probed_equals_the_exact_matcher(frames) -> None:
    images, queries = frames
    m = _matcher(images, k=16, probes=16)
    for q in queries:
        got = m.match(q, range(len(images)))
        want = match_batch_u8_reference(q, images)
        assert (got.counts == want.counts).all()
        assert (got.matched == want.matched).all()
        assert want.counts.sum() > 20  # the frames do match


def test_few_words_keep_the_counts_and_the_best_image(frames) -> None:
    images, queries = frames
    m = _matcher(images, k=64, probes=3)
    for q in queries:
        exact = match_batch_u8(q, images).counts
        approx = m.match(q, range(len(images))).counts
        assert np.argmax(approx) == np.argmax(exact)
        assert abs(approx.sum() - exact.sum()) <= 0.15 * exact.sum(), (approx, exact)


def test_one_map_and_seed_give_one_vocabulary_and_a_consistent_index(frames) -> None:
    images, _ = frames
    codes = np.vstack(images)
    a, b = Vocabulary.train(codes, 32, seed=1), Vocabulary.train(codes, 32, seed=1)
    assert np.array_equal(a.words.desc, b.words.desc) and a.k == 32
    idx = index_image(images[0], a)
    assert np.array_equal(idx.desc, images[0][idx.perm])
    words = a.nearest(idx.desc)[:, 0]
    assert (np.diff(words) >= 0).all() and idx.starts[-1] == len(images[0])
    assert all((words[idx.starts[q]:idx.starts[q + 1]] == q).all() for q in range(a.k))


def test_geometry_pairs_with_every_word_equal_the_exact_pairs(frames) -> None:
    from service.vision.metric_pose import match_pairs

    images, queries = frames
    m = _matcher(images, k=16, probes=16)
    for q in queries[:2]:
        got = m.pairs(q, 3, 0.9)
        want = match_pairs(q, images[3], 0.9)
        assert len(want[0]) > 10
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
