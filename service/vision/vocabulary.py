"""An approximate m(A, B) that does less work: a visual vocabulary (inverted file), the
service's ``words`` matcher (``SWARMLOC_MATCHER=words``, ``RouteMap.inverted_file``).

The exact matcher (service/vision/matcher.py) computes every dot product between a frame's
descriptors and each compared map image's, about 18 times per frame. Here the descriptors
of a map are clustered once into ``k`` visual words (spherical k-means on a sample of the
map's unit descriptors, seeded: one map always gives one vocabulary; k from the map's
features per image, ``words_for``; the centroids quantised to uint8, so that a descriptor's
words come from the exact uint8 GEMM). Each map image's
features are sorted by their nearest word, once per image (``WordIndex``); a frame's
features are assigned to their ``w`` nearest words once per frame (``FrameWords``), shared
by all the comparisons of its step. A comparison then scores only the pairs (a, b) where b's
word is one of a's ``w`` words, exactly (integer dot products, float64 cosines), and applies
the papers' symmetric ratio test to the best and second-best neighbours *among those
candidates* (``matcher.match_batch_ivf``). A feature with fewer than two candidates on a
side matches nothing.

What is approximate: a true nearest neighbour in another word is missed, and a second-best
neighbour in another word is not seen (the ratio test then compares with a farther one).
``swarmloc bench approx`` measures match counts, the best image per frame and the
localization error against the exact matcher, side by side. With ``w == k`` every pair is a
candidate and the result equals the exact matcher's.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from service.vision.features import DEFAULT_DELTA, BatchMatch, unit_descriptors
from service.vision.image_cache import ImageCache
from service.vision.matcher import (
    Pairs,
    PreparedSet,
    match_batch_ivf,
    norms_u8,
    pairs_ivf,
    prepare,
    top_columns,
)

DEFAULT_PROBES = 3  # w: nearest words a frame feature is compared in
FEATURES_PER_WORD = 2.5  # k = a map image's median features / this (``words_for``)
MIN_WORDS, MAX_WORDS = 16, 4096
_SAMPLE = 20_000  # descriptors the vocabulary is trained on (at least _PER_WORD per word)
_PER_WORD = 8
_ITERATIONS = 10
_WORK = _ITERATIONS * _SAMPLE * 256  # rows x words x iterations of a k = 256 training


def words_for(features_per_image: float) -> int:
    """k for a map whose images hold ``features_per_image`` features: a word then holds
    about ``FEATURES_PER_WORD`` of an image's features whatever their number, so the
    candidate pairs of a comparison grow linearly with the features, not with their square
    (a fixed k grew 6.2x from 1,000 to 4,000 features)."""
    return int(np.clip(round(features_per_image / FEATURES_PER_WORD), MIN_WORDS, MAX_WORDS))


@dataclass(frozen=True)
class Vocabulary:
    """``k`` visual words: unit centroids quantised to uint8 (k, D) and prepared for the
    exact uint8 GEMM; a descriptor's word is the centroid of the largest cosine."""

    words: PreparedSet

    @property
    def k(self) -> int:
        return len(self.words)

    @classmethod
    def train(cls, codes: np.ndarray, k: int, seed: int = 0, sample: int | None = None,
              iterations: int | None = None) -> Vocabulary:
        """Spherical k-means on up to ``sample`` rows of uint8 ``codes`` (seeded; default:
        max(20,000, 8 k) rows, as many iterations (2 to 10) as fit in the work of 10 at
        k = 256 on 20,000 rows, so that start-up stays short for a large k)."""
        rng = np.random.default_rng(seed)
        sample = max(_SAMPLE, _PER_WORD * k) if sample is None else sample
        rows = rng.choice(len(codes), min(sample, len(codes)), replace=False)
        x = unit_descriptors(np.asarray(codes)[np.sort(rows)])
        k = min(k, len(x))
        if k < 1:
            raise ValueError("a vocabulary needs at least one descriptor")
        if iterations is None:
            iterations = int(np.clip(_WORK // (len(x) * k), 2, _ITERATIONS))
        c = x[rng.choice(len(x), k, replace=False)].copy()
        at = np.arange(len(x))
        for _ in range(iterations):
            label = (x @ c.T).argmax(axis=1)
            sums = csr_matrix((np.ones(len(x), np.float32), (label, at)), shape=(k, len(x))) @ x
            norms = np.linalg.norm(sums, axis=1, keepdims=True)
            c = np.where(norms > 0, sums / np.maximum(norms, 1e-12), c)  # empty: kept
        q = np.round(255 * c / np.maximum(c.max(axis=1, keepdims=True), 1e-12))
        return cls(prepare(np.maximum(q, 0).astype(np.uint8)))

    def nearest(self, codes: np.ndarray, w: int = 1) -> np.ndarray:
        """(n, w) int64: the ``w`` nearest words of each row of uint8 ``codes`` (integer dot
        products over the words' norms; a row's own norm does not change its order)."""
        return top_columns(codes, self.words, w)


@dataclass(frozen=True)
class WordIndex:
    """One map image's features sorted by word: ``desc[starts[q]:starts[q + 1]]`` are the
    features of word q; ``perm[r]`` is row r's index in the image."""

    desc: np.ndarray  # (n, D) uint8
    norms: np.ndarray  # (n,) float64
    perm: np.ndarray  # (n,) int64
    starts: np.ndarray  # (k + 1,) int64

    def __len__(self) -> int:
        return len(self.desc)


def index_image(codes: np.ndarray, vocabulary: Vocabulary, word: np.ndarray | None = None
                ) -> WordIndex:
    """``codes`` sorted by their nearest word (``word``, when known)."""
    codes = np.ascontiguousarray(codes, np.uint8)
    word = vocabulary.nearest(codes)[:, 0] if word is None else word
    perm = np.argsort(word, kind="stable")
    desc = np.ascontiguousarray(codes[perm])
    starts = np.searchsorted(word[perm], np.arange(vocabulary.k + 1)).astype(np.int64)
    return WordIndex(desc, norms_u8(desc) if len(desc) else np.zeros(0), perm, starts)


@dataclass(frozen=True)
class FrameWords:
    """A frame's codes with their norms and ``w`` nearest words (once per frame)."""

    codes: np.ndarray
    norms: np.ndarray
    words: np.ndarray  # (n, w) int64


class InvertedFileMatcher:
    """m(frame, image) through a map's vocabulary; thread-safe. ``codes_of(i)`` gives map
    image i's uint8 codes; the vocabulary is trained on a sample of all of them. ``k`` None:
    ``words_for`` the images' median feature count (the cost then grows linearly with the
    features per frame)."""

    def __init__(self, codes_of: Callable[[int], np.ndarray], all_codes: np.ndarray,
                 n_images: int, k: int | None = None, probes: int = DEFAULT_PROBES,
                 seed: int = 0, features_per_image: float | None = None,
                 cache: ImageCache | None = None) -> None:
        if k is None:
            per_image = features_per_image if features_per_image is not None else \
                len(all_codes) / max(n_images, 1)
            k = words_for(per_image)
        if k < 1 or probes < 1:
            raise ValueError(f"an inverted file needs k >= 1 words and probes >= 1 "
                             f"(got k={k}, probes={probes})")
        self.vocabulary = Vocabulary.train(all_codes, k, seed)
        self.probes = probes
        self._codes_of = codes_of
        # each image's words and word-sorted features, within the map's byte budget
        self.cache = cache if cache is not None else ImageCache()
        self._frame: FrameWords | None = None
        self._lock = threading.Lock()

    def index(self, image_id: int) -> WordIndex:
        """Map image ``image_id`` sorted by word (kept after first use)."""
        def make() -> WordIndex:
            words = self._words_of(image_id)
            return index_image(words.codes, self.vocabulary,
                               words.words[:, 0] if len(words.codes) else None)
        return self.cache.get(("word-index", int(image_id)), make)

    def indexed(self) -> list[int]:
        """The images whose word index is kept now."""
        return sorted(int(k[1]) for k in self.cache.keys()
                      if isinstance(k, tuple) and k[0] == "word-index")

    def _words_of(self, image_id: int) -> FrameWords:
        """Map image ``image_id``'s words as a frame's (kept after first use: its index and
        the structures' matches use them)."""
        return self.cache.get(("words", int(image_id)), lambda: self.frame_words(
            np.asarray(self._codes_of(image_id)), keep=False))

    def frame_words(self, codes: np.ndarray, keep: bool = True) -> FrameWords:
        """The frame's words, computed once for the frame (the last frame's are kept;
        ``keep=False``: codes of a map image, not kept)."""
        with self._lock:
            last = self._frame
        if last is not None and last.codes is codes:
            return last
        c = np.ascontiguousarray(codes, np.uint8)
        fw = FrameWords(codes, norms_u8(c) if len(c) else np.zeros(0),
                        self.vocabulary.nearest(c, self.probes) if len(c) else
                        np.zeros((0, min(self.probes, self.vocabulary.k)), np.int64))
        if keep:
            with self._lock:
                self._frame = fw
        return fw

    def match(self, codes: np.ndarray, image_ids: Sequence[int] | np.ndarray,
              delta: float = DEFAULT_DELTA) -> BatchMatch:
        return self.match_pairs(codes, image_ids, delta)[0]

    def match_pairs(self, codes: np.ndarray, image_ids: Sequence[int] | np.ndarray,
                    delta: float = DEFAULT_DELTA, pairs_delta: float | None = None
                    ) -> tuple[BatchMatch, list[Pairs] | None]:
        """``match`` and, with ``pairs_delta``, each image's matched pairs (rows of
        ``codes``, rows in the image) at that delta from the same scan (the two-view
        geometry's, as ``match_batch_u8_pairs`` gives them)."""
        fw = self.frame_words(codes)
        idx = [self.index(int(i)) for i in image_ids]
        r, pairs = match_batch_ivf(np.ascontiguousarray(codes, np.uint8), fw.norms, fw.words,
                                   idx, delta, pairs_delta)
        if pairs is not None:
            pairs = [(rows, s.perm[cols]) for (rows, cols), s in zip(pairs, idx, strict=True)]
        return r, pairs

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """Matched feature indices (in ``codes``, in the image) for the two-view geometry,
        through the vocabulary as the similarity's."""
        return self._pairs(self.frame_words(codes, keep=False), image_id, delta)

    def image_pairs(self, image_id: int, other: int, delta: float
                    ) -> tuple[np.ndarray, np.ndarray]:
        """``pairs`` of map image ``image_id`` (its words kept after first use) with
        ``other``."""
        return self._pairs(self._words_of(image_id), other, delta)

    def _pairs(self, fw: FrameWords, image_id: int, delta: float
               ) -> tuple[np.ndarray, np.ndarray]:
        idx = self.index(image_id)
        rows, cols = pairs_ivf(np.ascontiguousarray(fw.codes, np.uint8), fw.norms, fw.words,
                               idx, delta)
        return rows, idx.perm[cols]

    def similarity(self, codes: np.ndarray, image_ids: Sequence[int] | np.ndarray,
                   delta: float = DEFAULT_DELTA) -> np.ndarray:
        return self.match(codes, image_ids, delta).scores
