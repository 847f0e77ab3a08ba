"""An approximate m(A, B) that does less work: a visual vocabulary (inverted file).

The exact matcher (service/vision/matcher.py) computes every dot product between a frame's
descriptors and each compared map image's, about 18 times per frame. Here the descriptors
of a map are clustered once into ``k`` visual words (spherical k-means on a sample of the
map's unit descriptors, seeded: one map always gives one vocabulary). Each map image's
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

from service.vision.features import DEFAULT_DELTA, BatchMatch, unit_descriptors
from service.vision.matcher import match_batch_ivf, norms_u8, pairs_ivf

DEFAULT_WORDS = 256  # k: visual words of a map
DEFAULT_PROBES = 3  # w: nearest words a frame feature is compared in
_SAMPLE = 20_000  # descriptors the vocabulary is trained on
_ITERATIONS = 10


@dataclass(frozen=True)
class Vocabulary:
    """``k`` unit centroids (k, D) float32."""

    centroids: np.ndarray

    @property
    def k(self) -> int:
        return len(self.centroids)

    @classmethod
    def train(cls, codes: np.ndarray, k: int = DEFAULT_WORDS, seed: int = 0,
              sample: int = _SAMPLE, iterations: int = _ITERATIONS) -> Vocabulary:
        """Spherical k-means on up to ``sample`` rows of uint8 ``codes`` (seeded)."""
        rng = np.random.default_rng(seed)
        rows = rng.choice(len(codes), min(sample, len(codes)), replace=False)
        x = unit_descriptors(np.asarray(codes)[np.sort(rows)])
        k = min(k, len(x))
        if k < 1:
            raise ValueError("a vocabulary needs at least one descriptor")
        c = x[rng.choice(len(x), k, replace=False)].copy()
        for _ in range(iterations):
            label = (x @ c.T).argmax(axis=1)
            sums = np.zeros_like(c)
            np.add.at(sums, label, x)
            norms = np.linalg.norm(sums, axis=1, keepdims=True)
            c = np.where(norms > 0, sums / np.maximum(norms, 1e-12), c)  # empty: kept
        return cls(c.astype(np.float32))

    def nearest(self, codes: np.ndarray, w: int = 1) -> np.ndarray:
        """(n, w) int64: the ``w`` nearest words of each row of uint8 ``codes``."""
        s = unit_descriptors(codes) @ self.centroids.T
        out = np.empty((len(s), min(w, self.k)), np.int64)
        rows = np.arange(len(s))
        for q in range(out.shape[1]):  # w argmax passes: far cheaper than argpartition
            out[:, q] = s.argmax(axis=1)
            s[rows, out[:, q]] = -np.inf
        return out


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


def index_image(codes: np.ndarray, vocabulary: Vocabulary) -> WordIndex:
    codes = np.ascontiguousarray(codes, np.uint8)
    word = vocabulary.nearest(codes)[:, 0]
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
    image i's uint8 codes; the vocabulary is trained on a sample of all of them."""

    def __init__(self, codes_of: Callable[[int], np.ndarray], all_codes: np.ndarray,
                 n_images: int, k: int = DEFAULT_WORDS, probes: int = DEFAULT_PROBES,
                 seed: int = 0) -> None:
        self.vocabulary = Vocabulary.train(all_codes, k, seed)
        self.probes = probes
        self._codes_of = codes_of
        self._indexes: list[WordIndex | None] = [None] * n_images
        self._frame: FrameWords | None = None
        self._lock = threading.Lock()

    def index(self, image_id: int) -> WordIndex:
        """Map image ``image_id`` sorted by word (kept after first use)."""
        found = self._indexes[image_id]
        if found is None:
            found = index_image(self._codes_of(image_id), self.vocabulary)
            self._indexes[image_id] = found
        return found

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
                        np.zeros((0, self.probes), np.int64))
        if keep:
            with self._lock:
                self._frame = fw
        return fw

    def match(self, codes: np.ndarray, image_ids: Sequence[int] | np.ndarray,
              delta: float = DEFAULT_DELTA) -> BatchMatch:
        fw = self.frame_words(codes)
        return match_batch_ivf(np.ascontiguousarray(codes, np.uint8), fw.norms, fw.words,
                               [self.index(int(i)) for i in image_ids], delta)

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """Matched feature indices (in ``codes``, in the image) for the two-view geometry,
        through the vocabulary as the similarity's."""
        c = np.ascontiguousarray(codes, np.uint8)
        idx = self.index(image_id)
        fw = self.frame_words(codes, keep=False)
        rows, cols = pairs_ivf(c, fw.norms, fw.words, idx, delta)
        return rows, idx.perm[cols]

    def similarity(self, codes: np.ndarray, image_ids: Sequence[int] | np.ndarray,
                   delta: float = DEFAULT_DELTA) -> np.ndarray:
        return self.match(codes, image_ids, delta).scores
