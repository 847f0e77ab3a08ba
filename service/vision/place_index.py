"""Global place recognition over a map's images: VLAD of its own descriptors, stored in the map.

Each map image gets one compact global descriptor (VLAD, Jegou et al. 2010; with the
intra-normalisation of Arandjelovic & Zisserman 2013): the unit RootSIFT descriptors of the
image are assigned to their nearest of ``K`` visual words (k-means over a sample of the map's
own descriptors), the residuals to the word are summed per word, each word's sum is
L2-normalised, the K x 128 vector signed-square-rooted and L2-normalised, then projected by a
PCA (with damped whitening) fitted on the map's images to ``dims`` dimensions and normalised
again. A frame is described the same way; its candidate places are the map images with the
highest scalar products (NumPy brute force: 40,000 images x 256 dims is a ~10 M
multiply-adds per query, a few milliseconds, so an ANN library would not pay here).

``PlaceSeeder`` uses the index to seed global initialisation and recovery: while an estimator
is not tracking, its random placements (initial particles, scouts) are drawn around the
top-k candidate images of the current frame instead of random map images; the swarm then
confirms a place with its usual comparisons. The index query is no map-image comparison (it
never runs the m(A, B) matcher) and is not counted as one; its time is reported apart.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from service.vision.features import unit_descriptors

WORDS = 32  # visual words K
DIMS = 256  # PCA dimensions of the stored descriptors
TRAIN_DESCRIPTORS = 60_000  # k-means sample
TRAIN_IMAGES = 3_000  # PCA sample
KMEANS_ITERATIONS = 12
WHITEN_POWER = 0.5  # eigenvalue^-(power/2): 0 no whitening, 1 full whitening
_CHUNK = 8_192  # images per scoring block (bounded temporary memory)


@dataclass(frozen=True)
class PlaceIndex:
    """VLAD vocabulary, PCA and one global descriptor per map image."""

    words: np.ndarray  # (K, 128) float32 unit visual words
    mean: np.ndarray  # (K * 128,) float32 PCA centre
    projection: np.ndarray  # (K * 128, dims) float32 PCA (whitened) basis
    # (n_images, dims) float32 unit global descriptors: stored as float16 (format 6) and
    # widened once on load, since a query over float16 rows costs ~10x (35 against 3.6 ms at
    # 40,000 images); a float32 array of an older map stays memory-mapped
    descriptors: np.ndarray

    @property
    def n_images(self) -> int:
        return len(self.descriptors)

    @property
    def dims(self) -> int:
        return int(self.projection.shape[1])

    def describe(self, codes: np.ndarray) -> np.ndarray:
        """The unit global descriptor (dims,) of one frame's descriptor codes."""
        return self._project(vlad(unit_descriptors(codes), self.words)[None, :])[0]

    def _project(self, v: np.ndarray) -> np.ndarray:
        p = (v - self.mean) @ self.projection
        return p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)

    def query(self, codes: np.ndarray, k: int, among: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """(image ids, scores) of the ``k`` map images most like the frame, best first;
        ``among``: only these image ids (None: all)."""
        k = min(k, self.n_images if among is None else len(among))
        if k <= 0 or len(codes) == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        q = self.describe(codes).astype(np.float32)
        if among is None:
            scores = np.concatenate([np.asarray(self.descriptors[i: i + _CHUNK]) @ q
                                     for i in range(0, self.n_images, _CHUNK)])
        else:
            scores = np.asarray(self.descriptors)[among] @ q
        top = np.argpartition(-scores, k - 1)[:k]
        top = top[np.argsort(-scores[top], kind="stable")]
        ids = top if among is None else np.asarray(among)[top]
        return ids.astype(np.int64), scores[top].astype(float)

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays a map file stores (service/maps/route_map.py, format 6): the projection
        as int8 with a scale per column, the descriptors as float16."""
        codes, scale = encode_projection(self.projection)
        return {"place_words": np.ascontiguousarray(self.words, "<f4"),
                "place_mean": np.ascontiguousarray(self.mean, "<f4"),
                "place_projection": codes, "place_projection_scale": scale,
                "place_descriptors": np.ascontiguousarray(self.descriptors, "<f2")}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> PlaceIndex | None:
        """The index of a map file's arrays (format 6, or the float32 ones of formats 3-5)."""
        if "place_descriptors" not in arrays:
            return None
        proj = np.asarray(arrays["place_projection"])
        if "place_projection_scale" in arrays:
            proj = decode_projection(proj, np.asarray(arrays["place_projection_scale"]))
        return cls(np.asarray(arrays["place_words"]), np.asarray(arrays["place_mean"]),
                   proj, np.asarray(arrays["place_descriptors"], np.float32))

    def meta(self) -> dict[str, Any]:
        return {"type": "vlad", "words": len(self.words), "dims": self.dims,
                "whiten_power": WHITEN_POWER}


def vlad(desc: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Intra-normalised, power-normalised VLAD (K * 128,) of unit descriptors (n, 128)."""
    k, d = words.shape
    out = np.zeros((k, d), np.float32)
    if len(desc):
        onehot = _onehot(np.argmax(desc @ words.T, axis=1), k)  # (k, n)
        out = onehot @ desc - onehot.sum(axis=1)[:, None] * words  # residual sums per word
        out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    v = out.ravel()
    v = np.sign(v) * np.sqrt(np.abs(v))
    return (v / max(float(np.linalg.norm(v)), 1e-12)).astype(np.float32)


def _onehot(assign: np.ndarray, k: int) -> np.ndarray:
    out = np.zeros((k, len(assign)), np.float32)
    out[assign, np.arange(len(assign))] = 1.0
    return out


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Spherical k-means (unit centroids, scalar-product assignment), Lloyd iterations."""
    c = x[rng.choice(len(x), k, replace=False)].copy()
    for _ in range(KMEANS_ITERATIONS):
        assign = np.argmax(x @ c.T, axis=1)
        onehot = _onehot(assign, k)
        sums = onehot @ x
        counts = np.bincount(assign, minlength=k)
        empty = counts == 0
        sums[empty] = x[rng.choice(len(x), int(empty.sum()), replace=False)]
        c = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)
    return c.astype(np.float32)


class CodesSource(Protocol):
    """What the index is built from: per-image descriptor codes (a map or its spill)."""

    @property
    def n_images(self) -> int: ...
    def codes_of(self, image_id: int) -> np.ndarray: ...


def build_place_index(source: CodesSource, rng: np.random.Generator, words: int = WORDS,
                      dims: int = DIMS) -> PlaceIndex | None:
    """Train the vocabulary and the PCA on the map's own descriptors, describe every image.
    None when the map is too small or has too few features for a vocabulary."""
    n = source.n_images
    sample_ids = np.sort(rng.choice(n, min(n, TRAIN_IMAGES), replace=False))
    pool = [source.codes_of(int(i)) for i in sample_ids]
    total = sum(len(c) for c in pool)
    dims = min(dims, len(sample_ids) - 1, words * 128)
    if total < 4 * words or dims < 1:
        return None
    allc = np.concatenate(pool)
    take = rng.choice(len(allc), min(len(allc), TRAIN_DESCRIPTORS), replace=False)
    voc = _kmeans(unit_descriptors(allc[take]), words, rng)
    train = np.stack([vlad(unit_descriptors(c), voc) for c in pool])
    mean = train.mean(axis=0)
    # PCA through the Gram matrix of the (fewer) training images: Xc Xc^T = U L U^T, the
    # principal axes are Xc^T U L^-1/2 (cheaper than an SVD of the wide matrix)
    xc = (train - mean).astype(np.float64)
    lam, u = np.linalg.eigh(xc @ xc.T)
    order = np.argsort(lam)[::-1][:dims]
    lam = np.maximum(lam[order], 1e-12)
    axes = (xc.T @ u[:, order]) / np.sqrt(lam)[None, :]
    ev = lam / max(len(train) - 1, 1)
    scale = (ev + 1e-3 * ev[0]) ** (-WHITEN_POWER / 2)
    # rounded as the map file stores it, so that a built map and its saved copy agree
    proj = decode_projection(*encode_projection(axes * scale[None, :]))
    index = PlaceIndex(voc, mean.astype(np.float32), proj, np.zeros((0, dims), np.float32))
    out = np.empty((n, dims), np.float16)
    for a in range(0, n, 1024):
        ids = range(a, min(n, a + 1024))
        out[a: a + len(ids)] = index._project(
            np.stack([vlad(unit_descriptors(source.codes_of(i)), voc) for i in ids]))
    return PlaceIndex(voc, index.mean, proj, out.astype(np.float32))  # as a loaded map's


def encode_projection(proj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(int8 codes, float32 scale per column) of a projection matrix (rows, dims): a quarter
    of its float32 size, each column to 1/127 of its largest entry."""
    proj = np.asarray(proj, np.float32)
    scale = (np.abs(proj).max(axis=0, initial=0.0) / 127.0).astype(np.float32)
    scale[scale == 0] = 1.0
    codes = np.clip(np.rint(proj / scale[None, :]), -127, 127).astype(np.int8)
    return codes, scale


def decode_projection(codes: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The float32 projection of ``encode_projection``'s codes and scales."""
    return np.asarray(codes, np.float32) * np.asarray(scale, np.float32)[None, :]


class Seedable(Protocol):
    """What the seeder needs of an estimator (service/estimators/base.py)."""

    place_candidates: np.ndarray | None
    place_frames: int
    place_disagree: int

    def wants_places(self) -> bool: ...


Verify = Callable[[np.ndarray], np.ndarray]  # learned candidate ids -> mask of those kept


def interleaved(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a[0], b[0], a[1], b[1], ..., then the rest of the longer one."""
    n = min(len(a), len(b))
    out = np.empty(len(a) + len(b), np.int64)
    out[0:2 * n:2], out[1:2 * n:2] = a[:n], b[:n]
    out[2 * n:] = np.concatenate([a[n:], b[n:]])
    return out


class PlaceSeeder:
    """Per frame: the top-k candidate places for an estimator that is searching, else none.

    While the estimator tracks, the index is asked every ``check_every`` frames whether the
    tracked place is among its top ``check_top`` candidates (within ``far_m``). The swarm's
    own lost detection judges a match against the background of the images it compares; on a
    large map a wrong place whose best match is weak but above that background can look like
    a good track (a kidnapped robot then "tracks" the old place for ever). After
    ``disagree_checks`` checks in a row that disagree, this frame's candidates are given to
    the estimator anyway: its scouts are drawn there, and a place that matches better takes
    over. ``last_query_s`` is the time of this frame's index query (0 when none ran) and
    ``queries`` counts them, for the benchmarks' honest accounting. ``among``: the image ids
    it may propose (None: all; a map with experiences: its own images, service/engine/localizer.py).
    ``learned``: the experiences' images, ranked apart: the best half of the ``k`` candidates
    come from ``among``, the other half from ``learned`` (interleaved, best first), and a
    searching estimator gets only the learned ones ``verify`` accepts (the frame clearly
    matches them; a learned image of today's light at a wrong place looks only a little like
    it). ``verify``: per frame, given to ``before_step``; its comparisons count in
    ``last_query_s``. The tracking check ranks both pools without it (no comparisons while
    the swarm tracks): a learned image of today's light near the tracked place agrees with
    it, and the candidates handed over after checks that disagree include learned ones
    unchecked, as scouts' places only.
    """

    def __init__(self, index: PlaceIndex, positions: np.ndarray, k: int, check_every: int = 3,
                 check_top: int = 3, far_m: float = 10.0, disagree_checks: int = 2,
                 among: np.ndarray | None = None, learned: np.ndarray | None = None) -> None:
        self.index = index
        self.among = among
        self.learned = learned if learned is not None and len(learned) else None
        self.positions = np.asarray(positions, float)
        self.k = k
        self.check_every = check_every
        self.check_top = check_top
        self.far_m = far_m
        self.disagree_checks = disagree_checks
        self.last_query_s = 0.0
        self.queries = 0
        self.last_ids = np.zeros(0, np.int64)

    def _query(self, codes: np.ndarray, verify: Verify | None = None) -> np.ndarray:
        t0 = time.perf_counter()
        if self.learned is None:
            ids, _ = self.index.query(codes, self.k, self.among)
        else:
            own, _ = self.index.query(codes, self.k - self.k // 2, self.among)
            learned, _ = self.index.query(codes, self.k // 2, self.learned)
            if verify is not None and len(learned):
                learned = learned[verify(learned)]
            ids = interleaved(own, learned)
        self.last_query_s = time.perf_counter() - t0
        self.queries += 1
        self.last_ids = ids
        return ids

    def before_step(self, estimator: Seedable, codes: np.ndarray,
                    estimate: np.ndarray | None = None, verify: Verify | None = None) -> None:
        """Set ``estimator.place_candidates`` for this frame; ``estimate``: the position
        reported for the previous frame; ``verify``: which learned candidates a searching
        estimator may be given (a mask over their ids; None: all)."""
        self.last_query_s = 0.0
        estimator.place_candidates = None
        if self.k <= 0:
            return
        if estimator.wants_places():
            estimator.place_disagree = 0
            ids = self._query(codes, verify)
            estimator.place_candidates = self.positions[ids] if len(ids) else None
            return
        estimator.place_frames += 1
        if estimate is None or estimator.place_frames % self.check_every:
            return
        ids = self._query(codes)
        if not len(ids):
            return
        near = np.linalg.norm(self.positions[ids[: self.check_top]] - estimate, axis=1)
        estimator.place_disagree = 0 if (near <= self.far_m).any() else \
            estimator.place_disagree + 1
        if estimator.place_disagree >= self.disagree_checks:
            estimator.place_candidates = self.positions[ids]
