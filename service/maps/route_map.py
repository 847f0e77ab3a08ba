"""Route maps: build from a round, save atomically, load memory-mapped and verified.

File layout (``NAME.swmap``), all little-endian:

    MAGIC (8 bytes) | header length (uint64) | header JSON (utf-8) | padding to 64 | arrays

Format version 3 (version 2 plus the place index and per-image digests) stores descriptors
as uint8 codes (SIFT is integer-valued; RootSIFT is quantised, see service/vision/features.py), the
layer (traversal) of every image, for maps merged from several traversals, and the global
place-recognition index (service/vision/place_index.py: VLAD vocabulary, PCA, one descriptor per
image). The header holds the format version, the metadata (feature type and parameters, delta,
working image size, geodetic origin, build date, pruning statistics, source, place index) and,
for every array, its dtype, shape, byte offset and SHA-256. ``checksum`` is the SHA-256 of the
header without that field (canonical JSON), so it covers every array through their digests.
``image_digests`` holds a BLAKE2b-64 of each image's codes and of its keypoints.

Loading verifies the header and every array (``verify=True``), or, for a server start-up whose
time and memory must not grow with the map (``verify="lazy"``), the header and every array
except the descriptors and keypoints, whose images are checked against their digests when
first used: a flipped bit anywhere is still caught before it is used, and a 40,000-image map
opens without reading its gigabytes. Arrays are 64-byte aligned and opened with
``numpy.memmap``: a map opens without copying its descriptors into memory.

Format version 6 (every map written now) stores the keypoints and the place index compactly
(service/maps/compact.py); versions 3-5 still load.

Version 2 maps (no index, one checksum over everything) still load, fully verified; their
place index is absent, so global initialisation falls back to random map images (rebuild the
map with 'swarmloc map build' to get the index).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
import struct
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Literal, Protocol

import numpy as np
from scipy.spatial import cKDTree

from service.api.geo import LocalFrame
from service.api.models import COORD_LIMIT_M, MATCHERS
from service.maps.compact import (
    KEYPOINT_DTYPE,
    FixedPointKeypoints,
    KeypointRangeError,
    Keypoints,
    decode_keypoints,
    encode_keypoints,
    keypoint_scale,
    valid_keypoint_scale,
)
from service.maps.positions import FUSED_SIGMA_M, PositionsRule, round_positions
from service.vision.features import (
    DEFAULT_DELTA,
    DUAL,
    DualParams,
    Features,
    SiftParams,
    feature_params,
    match_batch,
)
from service.vision.fusion import Fusion, fusion_levels
from service.vision.image_cache import ImageCache
from service.vision.map_geometry import FramePairs, MapGeometry
from service.vision.matcher import (
    Pairs,
    PreparedSet,
    match_batch_u8,
    match_batch_u8_pairs,
    prepare,
)
from service.vision.metric_pose import Camera, match_pairs
from service.vision.mnn_matcher import (
    PreparedCodes,
    mnn_batch,
    mnn_pairs,
    mnn_scores,
    prepare_codes,
)
from service.vision.place_index import PlaceIndex, build_place_index
from service.vision.vocabulary import DEFAULT_PROBES, InvertedFileMatcher
from service.vision.xfeat import DIMS as XFEAT_DIMS
from service.vision.xfeat import (
    FeatureModelError,
    XFeatParams,
    check_map_model,
)

if TYPE_CHECKING:
    from service.vision.features import FeatureParams

MAGIC = b"SWMAP\x00\r\n"
# the dtype of every stored array, as save_map writes them (anything else is refused)
_DTYPES: dict[str, np.dtype] = {
    "positions": np.dtype("<f8"), "offsets": np.dtype("<i8"), "codes": np.dtype(np.uint8),
    "keypoints": np.dtype("<f4"), "image_names": np.dtype(np.uint8), "layers": np.dtype("<i8")}
# version 3: small arrays first, then the descriptors, keypoints and their per-image digests;
# the place index arrays are optional (a map too small for a vocabulary has none)
_DTYPES_V3: dict[str, np.dtype] = {
    "positions": np.dtype("<f8"), "offsets": np.dtype("<i8"), "image_names": np.dtype(np.uint8),
    "layers": np.dtype("<i8"), "place_words": np.dtype("<f4"), "place_mean": np.dtype("<f4"),
    "place_projection": np.dtype("<f4"), "place_descriptors": np.dtype("<f4"),
    "codes": np.dtype(np.uint8), "keypoints": np.dtype("<f4"),
    "image_digests": np.dtype(np.uint8)}
_OPTIONAL = ("place_words", "place_mean", "place_projection", "place_descriptors")
_LAZY = ("codes", "keypoints", "codes2", "keypoints2")  # checked per image on first use
#                                                        with verify="lazy"
_DIGEST = 8  # bytes of each BLAKE2b image digest (codes, then keypoints)
# version 4: version 3 with learned (XFeat) features: int8 codes of 64 dimensions and the
# model's digest in the metadata.
# version 5: version 3 (RootSIFT) with a second feature set per image, XFeat: its own offsets,
# int8 codes, keypoints and per-image digests (the ``_SECOND`` arrays, the codes and
# keypoints checked lazily like the first), and the fusion's levels in the metadata
# (``fusion``, service/vision/fusion.py). Single-type maps were written as version 3
# (RootSIFT) or 4 (XFeat) then.
# version 6: any of the three feature types (``feature.type`` in the metadata, as in 4 and 5)
# stored compactly (service/maps/compact.py): keypoints as uint16 fixed point at
# ``keypoint_scale`` (header), the place projection as int8 with a float32 scale per column
# (``place_projection_scale``), the place descriptors as float16. The image digests are those
# of the decoded float32 keypoints, as before. Every map is written as version 6; versions
# 2-5 still load.
FORMAT_VERSION = 6
READABLE_VERSIONS = (2, 3, 4, 5, 6)
_CODE_DTYPES = {"sift": np.dtype(np.uint8), "xfeat": np.dtype(np.int8), DUAL: np.dtype(np.uint8)}
_CODE_DIMS = {"sift": 128, "xfeat": XFEAT_DIMS, DUAL: 128}
_SECOND: dict[str, np.dtype] = {
    "offsets2": np.dtype("<i8"), "codes2": np.dtype(np.int8), "keypoints2": np.dtype("<f4"),
    "image_digests2": np.dtype(np.uint8)}
_COMPACT: dict[str, np.dtype] = {  # version 6's dtypes where they differ from version 3-5's
    "keypoints": KEYPOINT_DTYPE, "keypoints2": KEYPOINT_DTYPE,
    "place_projection": np.dtype(np.int8), "place_projection_scale": np.dtype("<f4"),
    "place_descriptors": np.dtype("<f2")}
_OPTIONAL_V6 = (*_OPTIONAL[:3], "place_projection_scale", _OPTIONAL[3])
REBUILD_DUAL = "rebuild it with 'swarmloc map build --features clahe-rootsift+xfeat'"


def _dtypes_v6(kind: str) -> dict[str, np.dtype]:
    """Every array of a version 6 map of feature type ``kind``, in file order."""
    out: dict[str, np.dtype] = {}
    for key, dtype in _DTYPES_V3.items():
        if key == "place_descriptors":
            out["place_projection_scale"] = _COMPACT["place_projection_scale"]
        out[key] = _COMPACT.get(key, dtype)
    out["codes"] = _CODE_DTYPES[kind]
    if kind == DUAL:
        out.update({k: _COMPACT.get(k, v) for k, v in _SECOND.items()})
    return out


Verify = bool | Literal["lazy"]
SUFFIX = ".swmap"
WRITE_TEMPS = f".*{SUFFIX}.tmp-*"  # the temporary files of ``write_map`` (a crash leaves one)
#: the ``auto`` matcher compares through the inverted file on maps whose median image holds
#: more RootSIFT features than this: a frame's default cap, so every map built with the
#: defaults keeps the exact matcher (docs/research/performance.md, "Rich maps")
RICH_FEATURES = SiftParams().n_features
_ALIGN = 64


class MapError(ValueError):
    """A map file is missing, corrupted, of another format version, or inconsistent."""


@dataclass(frozen=True)
class PruneStats:
    features_before: int
    features_after: int

    @property
    def removed_fraction(self) -> float:
        return 1.0 - self.features_after / max(self.features_before, 1)


def prune(features: list[Features], delta: float = DEFAULT_DELTA
          ) -> tuple[list[Features], PruneStats]:
    """Keep only features with a symmetric match in a neighbouring image of the round.

    As in the papers (Sec. 6): image i is compared with i-1 and i+1 (the first and last image
    with their one neighbour); features found in neither are noise and are dropped.
    """
    kept: list[Features] = []
    for i, f in enumerate(features):
        neighbours = [features[j].descriptors for j in (i - 1, i + 1) if 0 <= j < len(features)]
        if len(f) == 0 or not neighbours:
            kept.append(f)
            continue
        mask = match_batch(f.descriptors, neighbours, delta).matched.any(axis=0)
        kept.append(Features(f.keypoints[mask], f.codes[mask]))
    before = sum(len(f) for f in features)
    return kept, PruneStats(before, sum(len(f) for f in kept))


@dataclass
class SecondSet:
    """A map's second feature set (XFeat beside RootSIFT, format 5): int8 codes (total, 64),
    memory-mapped, keypoints (total, 2), row offsets (n + 1,) of each image and, when the map
    was opened with verify="lazy", the (n, 16) digests of each image's codes and keypoints."""

    codes: np.ndarray
    keypoints: Keypoints
    offsets: np.ndarray
    lazy_digests: np.ndarray | None = None

    def rows(self, image_id: int) -> slice:
        return slice(int(self.offsets[image_id]), int(self.offsets[image_id + 1]))


@dataclass
class RouteMap:
    """A loaded map: image positions, descriptor codes (memory-mapped) and KD-trees.

    A map merged from several traversals of one route (conditions) has one *layer* per
    traversal; ``nearest_per_layer`` answers the nearest image of every layer, so a particle
    is compared with its place's image from each condition.
    """

    name: str
    meta: dict
    positions: np.ndarray  # (n, 2) metres east/north
    image_names: list[str]
    codes: np.ndarray  # (total, D) uint8 descriptor codes, memory-mapped
    offsets: np.ndarray  # (n + 1,) row offsets of each image's descriptors
    keypoints: Keypoints  # (total, 2) float32 (format 6: decoded from uint16 fixed point)
    path: Path | None = None
    layers: np.ndarray | None = None  # (n,) traversal index of each image; None: one
    place_index: PlaceIndex | None = None  # global place recognition (None: not built)
    # (n, 16) BLAKE2b-64 digests of each image's codes and keypoints, checked on first use
    # of an image when the map was opened with verify="lazy" (None: nothing left to check)
    lazy_digests: np.ndarray | None = None
    second: SecondSet | None = None  # XFeat beside RootSIFT (feature type sift+xfeat)
    # how a frame's RootSIFT codes are compared with the map's (MATCHERS): "exact" every
    # pair, "words" the pairs that share a visual word (service/vision/vocabulary.py),
    # "auto" words where the map's images are rich (``rich_images``), else exact
    matcher: str = "auto"
    # the words matcher: the best ``exact_top`` images of each comparison (by their words
    # score) are compared again with the exact matcher (0: none)
    exact_top: int = 0

    def __post_init__(self) -> None:
        check_matcher(self.matcher)
        n = len(self.positions)
        if self.layers is None:
            self.layers = np.zeros(n, np.int64)
        self._tree = cKDTree(self.positions)
        self._layer_ids = [np.flatnonzero(self.layers == k) for k in range(self.n_layers)]
        self._layer_trees = ([self._tree] if self.n_layers == 1 else
                             [cKDTree(self.positions[ids]) for ids in self._layer_ids])
        # each image's descriptors as the matchers take them, within a byte budget
        self.image_cache = ImageCache()
        self._checked = np.zeros(n if self.lazy_digests is not None else 0, bool)
        self._checked2 = np.zeros(n if self.second is not None and
                                  self.second.lazy_digests is not None else 0, bool)
        self._words_lock = threading.Lock()
        self._words: InvertedFileMatcher | None = None
        self._median_features = float(np.median(np.diff(self.offsets))) if n else 0.0

    def _check_image(self, image_id: int) -> None:
        """With lazy verification: the image's codes and keypoints against their digests,
        once (a corrupted image raises MapError instead of being matched)."""
        a, b = int(self.offsets[image_id]), int(self.offsets[image_id + 1])
        self._verify(image_id, self.lazy_digests, self._checked, self.codes[a:b],
                     self.keypoints[a:b], "does not match its digest", "rebuild the map")

    def _check_second(self, image_id: int) -> None:
        """``_check_image`` for the second feature set."""
        s = self.second
        assert s is not None
        rows = s.rows(image_id)
        self._verify(image_id, s.lazy_digests, self._checked2, s.codes[rows], s.keypoints[rows],
                     "has XFeat features that do not match their digest", REBUILD_DUAL)

    def _verify(self, image_id: int, digests: np.ndarray | None, checked: np.ndarray,
                codes: np.ndarray, keypoints: np.ndarray, defect: str, remedy: str) -> None:
        if digests is None or checked[image_id]:
            return
        if _image_digest(codes, keypoints) != bytes(digests[image_id]):
            raise MapError(f"{self.path}: image {image_id} ('{self.image_names[image_id]}') "
                           f"{defect}, the file is corrupted; {remedy}")
        checked[image_id] = True

    @property
    def position_sigma_m(self) -> float | None:
        """The per-axis error of the map's positions where the map knows it (every round's
        positions fused with its odometry: ``FUSED_SIGMA_M``); None: as recorded."""
        how = self.meta.get("source", {}).get("positions")
        fused = isinstance(how, list) and bool(how) and all(
            isinstance(h, str) and h.startswith("fused") for h in how)
        return FUSED_SIGMA_M if fused else None

    @property
    def n_layers(self) -> int:
        return int(self.layers.max()) + 1 if self.layers is not None and len(self.layers) else 1

    @property
    def n_images(self) -> int:
        return len(self.positions)

    @property
    def delta(self) -> float:
        return float(self.meta["delta"])

    @cached_property
    def feature_params(self) -> FeatureParams:
        """The map's feature type and its settings (every frame is extracted with them)."""
        return feature_params(self.meta["feature"])

    @property
    def first_params(self) -> SiftParams | XFeatParams:
        """The feature type of the map's codes and keypoints (RootSIFT for a map of two: the
        two-view geometry and the place index use it)."""
        p = self.feature_params
        return p.sift if isinstance(p, DualParams) else p

    @cached_property
    def fusion(self) -> Fusion | None:
        """How a map of two feature types fuses their similarities (metadata ``fusion``);
        None for a map of one."""
        return Fusion.from_dict(self.meta["fusion"]) if self.second is not None else None

    @cached_property
    def frame(self) -> LocalFrame | None:
        """The geodetic frame (built once: a pyproj transformer is not cheap)."""
        o = self.meta.get("origin")
        return LocalFrame(o["lat"], o["lon"]) if o else None

    @cached_property
    def camera(self) -> Camera | None:
        """The camera's intrinsics (metadata ``camera``), None when the map was built without
        them: its frames are then placed at map images, never located between them."""
        c = self.meta.get("camera")
        return Camera.from_dict(c) if c else None

    @cached_property
    def geometry(self) -> MapGeometry | None:
        """Two-view geometry against this map's images (service/vision/map_geometry.py), None
        without a camera."""
        cam = self.camera
        if cam is None:
            return None
        return MapGeometry(self, cam, self.feature_params.width, self.feature_params.height)

    @cached_property
    def second_geometry(self) -> MapGeometry | None:
        """On a map of two feature types with the camera: two-view geometry on its second set
        (XFeat), which matches where RootSIFT finds little (dusk); None otherwise. The
        localizer locates a frame with it where RootSIFT's geometry does not
        (service/engine/localizer.py), and so does a learning session's located gate
        (service/engine/learning.py)."""
        cam = self.camera
        if cam is None or self.second is None:
            return None
        return MapGeometry(SecondImages(self), cam, self.feature_params.width,
                           self.feature_params.height)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the map positions."""
        return self.positions.min(axis=0), self.positions.max(axis=0)

    @property
    def spacing(self) -> float:
        """Median distance between consecutive map images (metres)."""
        if self.n_images < 2:
            return 1.0
        return float(np.median(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def features_of(self, image_id: int) -> PreparedCodes:
        """One XFeat map image's codes prepared for the matcher (kept after the first use)."""
        def make() -> PreparedCodes:
            self._check_image(image_id)
            return prepare_codes(np.asarray(self.codes[self.offsets[image_id]:
                                                       self.offsets[image_id + 1]]))
        return self.image_cache.get(("codes", int(image_id)), make)

    def second_features_of(self, image_id: int) -> PreparedCodes:
        """One map image's second feature set (XFeat) prepared for the matcher (kept after the
        first use)."""
        s = self.second
        if s is None:
            raise ValueError(f"map '{self.name}' has one feature type")
        def make() -> PreparedCodes:
            self._check_second(image_id)
            return prepare_codes(np.asarray(s.codes[s.rows(image_id)]))
        return self.image_cache.get(("codes2", int(image_id)), make)

    def image_features(self, image_id: int) -> Features:
        """One map image as a frame's ``Features`` (both sets on a map of two types)."""
        second = None
        if self.second is not None:
            self._check_second(image_id)
            rows = self.second.rows(image_id)
            second = Features(np.asarray(self.second.keypoints[rows]),
                              np.asarray(self.second.codes[rows]))
        return Features(np.asarray(self.keypoints_of(image_id)),
                        np.asarray(self.codes_of(image_id)), second)

    def nearest(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest map image id and its distance for each of many positions, in one call."""
        dist, idx = self._tree.query(np.asarray(positions, float).reshape(-1, 2))
        return idx.astype(np.int64), dist

    def nearest_per_layer(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids, distances), each (n, layers): the nearest image of every layer."""
        pts = np.asarray(positions, float).reshape(-1, 2)
        if self.n_layers == 1:
            ids, dist = self.nearest(pts)
            return ids[:, None], dist[:, None]
        out_i = np.empty((len(pts), self.n_layers), np.int64)
        out_d = np.empty((len(pts), self.n_layers))
        for k, (tree, ids) in enumerate(zip(self._layer_trees, self._layer_ids, strict=True)):
            out_d[:, k], local = tree.query(pts)
            out_i[:, k] = ids[local]
        return out_i, out_d

    def nearest_in_layer(self, positions: np.ndarray, layer: int
                         ) -> tuple[np.ndarray, np.ndarray]:
        """(ids, distances), each (n,): the nearest image of one layer."""
        pts = np.asarray(positions, float).reshape(-1, 2)
        if self.n_layers == 1:
            return self.nearest(pts)
        dist, local = self._layer_trees[layer].query(pts)
        return self._layer_ids[layer][local].astype(np.int64), dist

    def prepared(self, image_id: int) -> PreparedSet:
        """One map image's codes prepared for the exact uint8 matcher (kept after first use;
        the codes stay memory-mapped)."""
        def make() -> PreparedSet:
            self._check_image(image_id)
            return prepare(np.asarray(
                self.codes[self.offsets[image_id]: self.offsets[image_id + 1]]))
        return self.image_cache.get(("prepared", int(image_id)), make)

    @property
    def rich_images(self) -> bool:
        """The median map image holds more features than a frame keeps by default
        (``RICH_FEATURES``: the map was built with a higher cap), so that comparing every
        pair would grow with the square of the features."""
        return self._median_features > RICH_FEATURES

    @property
    def uses_words(self) -> bool:
        """The similarity (and the geometry's matches) go through the inverted file: the
        ``words`` matcher on a map of SIFT codes, or ``auto`` on a RootSIFT map of rich
        images (XFeat keeps its own matcher)."""
        p = self.first_params
        if isinstance(p, XFeatParams):
            return False
        # ``auto`` leaves the papers' plain SIFT on the papers' similarity
        return self.matcher == "words" or (self.matcher == "auto" and p.root
                                           and self.rich_images)

    @property
    def inverted_file(self) -> InvertedFileMatcher:
        """The map's inverted file (service/vision/vocabulary.py), trained on first use from a
        seeded sample of the map's codes, k from its images' median feature count; one map
        always gives one vocabulary. ``load_map(matcher="words")`` trains it at load."""
        with self._words_lock:
            if self._words is None:
                self._words = self._train_words(None, DEFAULT_PROBES)
            return self._words

    def _train_words(self, k: int | None, probes: int) -> InvertedFileMatcher:
        return InvertedFileMatcher(self.codes_of, self.codes, self.n_images, k, probes,
                                   features_per_image=self._median_features,
                                   cache=self.image_cache)

    def with_matcher(self, matcher: str) -> RouteMap:
        """This map (the same arrays) compared with ``matcher`` (MATCHERS); a vocabulary the
        words matcher needs is trained on first use."""
        return replace(self, matcher=check_matcher(matcher))

    def with_words(self, k: int | None = None, probes: int = DEFAULT_PROBES,
                   exact_top: int = 0) -> RouteMap:
        """This map (the same arrays) with the ``words`` matcher and its own vocabulary of
        ``k`` words (None: the map's own choice) probed ``probes`` at a time, the best
        ``exact_top`` images of each comparison matched again exactly (the lab's knobs;
        ``matcher="words"`` gives the defaults)."""
        m = replace(self, matcher="words", exact_top=exact_top)
        m._words = self._train_words(k, probes)
        return m

    def similarity(self, frame: Features | np.ndarray, image_ids: Iterable[int],
                   keep: FramePairs | None = None,
                   keep_second: FramePairs | None = None,
                   first: Callable[[np.ndarray, np.ndarray], object] | None = None
                   ) -> np.ndarray:
        """m(frame, map image) for each id on the frame's ``Features`` (or, on a map of one
        feature type, its descriptor codes ``Features.codes``): the exact uint8 matcher
        (service/vision/matcher.py) for RootSIFT, mutual nearest neighbours for XFeat
        (service/vision/xfeat.py), both fused (service/vision/fusion.py) on a map of two.
        ``keep`` (RootSIFT): the same pass also keeps the frame's matches at ``keep.delta``
        with each image, for the two-view geometry (XFeat: its matches, whatever the delta;
        a map of two: RootSIFT's, and XFeat's in ``keep_second``). ``first(ids, m)``, on a
        map of two: told the first type's own m (the lost detection's, ``TypeScores``)."""
        ids = [int(i) for i in image_ids]
        if self.second is None:
            codes = frame.codes if isinstance(frame, Features) else frame
            return self._first_similarity(codes, ids, keep)
        assert self.fusion is not None
        own, other = self.type_similarities(frame, ids, keep, keep_second)
        if first is not None:
            first(np.asarray(ids, np.int64), own)
        return self.fusion.fuse(own, other)

    def type_similarities(self, frame: Features | np.ndarray, image_ids: Iterable[int],
                          keep: FramePairs | None = None,
                          keep_second: FramePairs | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
        """On a map of two feature types: each type's m(frame, map image) for each id,
        RootSIFT's (which ``keep`` keeps the matches of) and XFeat's (``keep_second``)."""
        p = self.feature_params
        second = frame.second if isinstance(frame, Features) else None
        if not isinstance(p, DualParams) or second is None:
            raise ValueError(f"map '{self.name}' holds two feature types: compare a frame's "
                             "Features from extract(image, map.feature_params), not its codes"
                             if isinstance(p, DualParams) else
                             f"map '{self.name}' holds one feature type")
        assert isinstance(frame, Features)
        ids = [int(i) for i in image_ids]
        first = self._first_similarity(frame.codes, ids, keep)
        other, pairs = mnn_batch(second.codes, [self.second_features_of(i) for i in ids],
                                 p.xfeat.min_cos, p.xfeat.max_ratio)
        if keep_second is not None:  # XFeat's geometry takes them as they are (any delta)
            keep_second.keep(ids, pairs)
        return first, other

    def _first_similarity(self, frame_codes: np.ndarray, ids: list[int],
                          keep: FramePairs | None) -> np.ndarray:
        p = self.first_params
        if isinstance(p, XFeatParams):
            feats = [self.features_of(i) for i in ids]
            if keep is None:
                return mnn_scores(frame_codes, feats, p.min_cos, p.max_ratio)
            scores, kept = mnn_batch(frame_codes, feats, p.min_cos, p.max_ratio)
            keep.keep(ids, kept)  # the geometry's matches are the similarity's (any delta)
            return scores
        if self.uses_words:
            r, kept_pairs = self.inverted_file.match_pairs(
                frame_codes, ids, self.delta, None if keep is None else keep.delta)
            scores = r.scores
            if self.exact_top > 0 and len(ids):
                scores, kept_pairs = self._exact_again(frame_codes, ids, scores, kept_pairs,
                                                       keep)
            if keep is not None and kept_pairs is not None:
                keep.keep(ids, kept_pairs)
            return scores
        sets = [self.prepared(i) for i in ids]
        if keep is None:
            return match_batch_u8(frame_codes, sets, self.delta).scores
        r, pairs = match_batch_u8_pairs(frame_codes, sets, self.delta, keep.delta)
        keep.keep(ids, pairs)
        return r.scores

    def _exact_again(self, frame_codes: np.ndarray, ids: list[int], scores: np.ndarray,
                     kept_pairs: list[Pairs] | None, keep: FramePairs | None
                     ) -> tuple[np.ndarray, list[Pairs] | None]:
        """The words matcher's scores (and kept pairs) with the ``exact_top`` best images
        compared again by the exact matcher."""
        top = np.argsort(-scores, kind="stable")[: self.exact_top]
        top = top[scores[top] > 0]
        if not len(top):
            return scores, kept_pairs
        sets = [self.prepared(ids[j]) for j in top]
        scores = scores.copy()
        if keep is None:
            scores[top] = match_batch_u8(frame_codes, sets, self.delta).scores
            return scores, kept_pairs
        r, pairs = match_batch_u8_pairs(frame_codes, sets, self.delta, keep.delta)
        scores[top] = r.scores
        if kept_pairs is not None:
            kept_pairs = list(kept_pairs)
            for j, pr in zip(top, pairs, strict=True):
                kept_pairs[int(j)] = pr
        return scores, kept_pairs

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """Matched feature indices (in ``codes``, in the image) for the two-view geometry:
        the symmetric ratio test at ``delta`` (RootSIFT) or the map's mutual nearest
        neighbours (XFeat). A map of two feature types: RootSIFT's. The ``words`` matcher:
        among the pairs sharing a visual word."""
        p = self.first_params
        if isinstance(p, XFeatParams):
            return mnn_pairs(codes, self.features_of(image_id), p.min_cos, p.max_ratio)
        if self.uses_words and not self.exact_top:  # else the best images' pairs: exact
            return self.inverted_file.pairs(codes, image_id, delta)
        return match_pairs(codes, self.prepared(image_id), delta)

    def frame_pairs(self, a: np.ndarray, b: np.ndarray, delta: float, second: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Matched feature indices of two frames' codes of the map's first feature type
        (``second``: of its second, XFeat) for the two-view geometry: the symmetric ratio
        test at ``delta`` (RootSIFT) or mutual nearest neighbours (XFeat)."""
        p = self.feature_params
        if second:
            if not isinstance(p, DualParams):
                raise ValueError(f"map '{self.name}' has one feature type")
            return mnn_pairs(a, b, p.xfeat.min_cos, p.xfeat.max_ratio)
        first = self.first_params
        if isinstance(first, XFeatParams):
            return mnn_pairs(a, b, first.min_cos, first.max_ratio)
        return match_pairs(a, b, delta)

    def image_pairs(self, image_id: int, other: int, delta: float
                    ) -> tuple[np.ndarray, np.ndarray]:
        """``pairs`` of map image ``image_id``'s codes with map image ``other`` (a structure's
        matches; the words matcher keeps each image's own words)."""
        if self.uses_words:
            return self.inverted_file.image_pairs(image_id, other, delta)
        return self.pairs(self.codes_of(image_id), other, delta)

    def codes_of(self, image_id: int) -> np.ndarray:
        """One image's descriptor codes (a memory-mapped view; verified with lazy loading)."""
        self._check_image(image_id)
        return self.codes[self.offsets[image_id]: self.offsets[image_id + 1]]

    def keypoints_of(self, image_id: int) -> np.ndarray:
        """One image's keypoints (working-size pixels; verified with lazy loading)."""
        self._check_image(image_id)
        return self.keypoints[self.offsets[image_id]: self.offsets[image_id + 1]]

    def summary(self) -> dict:
        return {
            "name": self.name,
            "n_images": self.n_images,
            "n_features": int(self.offsets[-1]),
            "n_layers": self.n_layers,
            "bounds": [self.bounds[0].tolist(), self.bounds[1].tolist()],
            "spacing_m": self.spacing,
            **{k: v for k, v in self.meta.items() if k not in ("arrays", "checksum")},
            "place_index": self.place_index.meta() if self.place_index is not None else None,
            "matcher": "words" if self.uses_words else "exact",
            **self._file_size(),
        }

    def _file_size(self) -> dict[str, float]:
        """The map file's bytes, and per stored feature of either type (none in memory)."""
        try:
            size = self.path.stat().st_size if self.path is not None else None
        except OSError:
            size = None
        if size is None:
            return {}
        features = int(self.offsets[-1]) + (len(self.second.codes) if self.second else 0)
        return {"file_bytes": size, "bytes_per_feature": round(size / max(features, 1), 1)}


class SecondImages:
    """A map of two feature types seen through its second set (XFeat): what MapGeometry
    needs of a map (positions, layers, codes, keypoints, matched pairs by mutual nearest
    neighbours)."""

    def __init__(self, m: RouteMap) -> None:
        if m.second is None or not isinstance(m.feature_params, DualParams):
            raise ValueError(f"map '{m.name}' has one feature type")
        self.map, self.set, self.params = m, m.second, m.feature_params.xfeat
        self.positions, self.layers = m.positions, m.layers

    def codes_of(self, image_id: int) -> np.ndarray:
        self.map._check_second(image_id)
        return self.set.codes[self.set.rows(image_id)]

    def keypoints_of(self, image_id: int) -> np.ndarray:
        self.map._check_second(image_id)
        return self.set.keypoints[self.set.rows(image_id)]

    def pairs(self, codes: np.ndarray, image_id: int, delta: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """Mutual nearest neighbours of ``codes`` with the image's second set (any delta)."""
        return mnn_pairs(codes, self.map.second_features_of(image_id), self.params.min_cos,
                         self.params.max_ratio)

    def image_pairs(self, image_id: int, other: int, delta: float
                    ) -> tuple[np.ndarray, np.ndarray]:
        return self.pairs(self.codes_of(image_id), other, delta)


def position_problem(positions: np.ndarray) -> str | None:
    """What makes map positions unusable (NaN, inf, beyond the pose bound), or None."""
    if not np.isfinite(positions).all():
        return "are not all finite numbers (NaN or inf)"
    if positions.size and float(np.abs(positions).max()) > COORD_LIMIT_M:
        return f"lie beyond +-{COORD_LIMIT_M:g} m (the bound of every pose)"
    return None


def build_map(
    name: str,
    images: Iterable[np.ndarray],
    positions: np.ndarray,
    image_names: list[str],
    *,
    params: FeatureParams | None = None,
    delta: float = DEFAULT_DELTA,
    origin: tuple[float, float] | None = None,
    source: dict | None = None,
    extract: Callable[[np.ndarray, FeatureParams], Features] | None = None,
    prune_features: bool = False,
    layers: np.ndarray | None = None,
    place_index: bool = True,
    camera: Camera | None = None,
) -> RouteMap:
    """Extract, (optionally) prune and assemble a map in memory (``save_map`` writes it).

    ``prune_features``: the papers' neighbour pruning (Sec. 6), off by default: it throws
    away the features that survive a change of light (README, "Features across lighting").
    ``layers``: traversal index per image for a map merged from several traversals; pruning
    compares neighbours within a traversal. ``place_index``: build the global
    place-recognition index (service/vision/place_index.py; seeded, so a build is reproducible).
    ``camera``: the intrinsics, kept in the metadata, with which frames are located between
    map images (service/vision/map_geometry.py); None: they are placed at map images only.
    """
    from service.vision.features import extract as sift_extract

    params = params or SiftParams()
    extract = extract or sift_extract
    feats = [extract(img, params) for img in images]
    positions = np.asarray(positions, float)
    if problem := position_problem(positions):
        raise MapError(f"image positions {problem}")
    if len(feats) != len(positions) or len(feats) != len(image_names):
        raise MapError("images, positions and names must have the same length")
    if len(feats) == 0:
        raise MapError("a map needs at least one image")
    layer_arr = (np.zeros(len(feats), np.int64) if layers is None
                 else np.asarray(layers, np.int64))
    if len(layer_arr) != len(feats) or layer_arr.min() < 0:
        raise MapError("layers must give a non-negative traversal index per image")
    dual = isinstance(params, DualParams)
    if dual and any(f.second is None for f in feats):
        raise MapError("a map of two feature types needs both per image (extract each with "
                       "the map's DualParams)")
    kept = feats
    stats = PruneStats(sum(len(f) for f in feats), sum(len(f) for f in feats))
    if prune_features:
        kept = list(feats)
        before = after = 0
        for k in np.unique(layer_arr):
            idx = np.flatnonzero(layer_arr == k)
            part, st = prune([feats[i] for i in idx], delta)
            if dual:  # each type among its own kind (the second's counts are not reported)
                part2, _ = prune([feats[i].second for i in idx], delta)  # type: ignore[misc]
                part = [replace(f, second=g) for f, g in zip(part, part2, strict=True)]
            for i, f in zip(idx, part, strict=True):
                kept[i] = f
            before, after = before + st.features_before, after + st.features_after
        stats = PruneStats(before, after)
    kind = DUAL if dual else "xfeat" if isinstance(params, XFeatParams) else "sift"
    scale = keypoint_scale(params.width, params.height)
    codes, kps, offsets = _stack(kept, _CODE_DTYPES[kind], _CODE_DIMS[kind], scale)
    second = None
    if dual:
        second = SecondSet(*_stack([f.second for f in kept],  # type: ignore[misc]
                                   _SECOND["codes2"], XFEAT_DIMS, scale))
    meta = {
        "format_version": FORMAT_VERSION,
        "feature": params.as_dict(),
        "delta": delta,
        "image_size": [params.width, params.height],
        "keypoint_scale": scale,
        "origin": {"lat": origin[0], "lon": origin[1]} if origin else None,
        "build_date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "pruning": {
            "enabled": prune_features,
            "features_before": stats.features_before,
            "features_after": stats.features_after,
            "removed_fraction": round(stats.removed_fraction, 4),
        },
        "source": source or {},
        "camera": camera.as_dict() if camera is not None else None,
    }
    m = RouteMap(name, meta, positions, list(image_names), codes, offsets, kps,
                 layers=layer_arr, second=second)
    if dual:
        m.meta["fusion"] = fusion_levels(
            positions, layer_arr,
            lambda i, ids: m.type_similarities(m.image_features(i), ids)).as_dict()
    if place_index:
        m.place_index = build_place_index(m, np.random.default_rng(0))
    return m


def _stack(feats: Sequence[Features], dtype: np.dtype, dims: int, scale: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(codes, keypoints, offsets) of the images' features, one after the other; the
    keypoints as the map file stores them (fixed point at ``scale``)."""
    counts = np.array([len(f) for f in feats], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    codes = (np.concatenate([f.codes for f in feats]) if offsets[-1]
             else np.zeros((0, dims), dtype)).astype(dtype)
    kps = (np.concatenate([f.keypoints for f in feats]) if offsets[-1]
           else np.zeros((0, 2), np.float32))
    return codes, decode_keypoints(_stored_keypoints(kps, scale), scale), offsets


def _stored_keypoints(kps: np.ndarray, scale: int) -> np.ndarray:
    """The uint16 fixed-point keypoints a map file stores; MapError where they cannot be."""
    try:
        return encode_keypoints(kps, scale)
    except KeypointRangeError as exc:
        raise MapError(str(exc)) from None


class RoundLike(Protocol):
    """What a map is built from: a traversal's images and positions (the client's ``Round``,
    the service's ``UploadedRound``)."""

    @property
    def name(self) -> str: ...
    @property
    def images(self) -> Sequence[str]: ...
    @property
    def xy(self) -> np.ndarray: ...
    @property
    def origin(self) -> tuple[float, float] | None: ...
    @property
    def camera(self) -> dict[str, float] | None: ...
    def __len__(self) -> int: ...
    def load_image(self, i: int) -> np.ndarray: ...


def build_map_from_rounds(
    rounds: Sequence[RoundLike],
    *,
    name: str | None = None,
    params: FeatureParams | None = None,
    delta: float = DEFAULT_DELTA,
    prune_features: bool = False,
    source: dict[str, Any] | None = None,
    images: Iterable[np.ndarray] | None = None,
    wrap: Callable[[Iterator[np.ndarray]], Iterable[np.ndarray]] | None = None,
    camera: Camera | None = None,
    positions: PositionsRule = "fused",
) -> RouteMap:
    """The map of one round, or of several traversals of one route (one layer each).

    ``name`` defaults to the rounds' names joined by '+'. Image names are the round's, or
    ``ROUND/IMAGE`` for several rounds. ``images`` replaces the rounds' own images (e.g. paced
    for a background build); ``wrap`` wraps the image iterator (e.g. a progress bar);
    ``camera``: the intrinsics kept in the map (see ``build_map``); by default the rounds'
    own (all must have the same). ``positions``: ``fused`` (the default) aligns a round's
    wheel odometry, where it has one, to its recorded positions (service/maps/positions.py);
    ``recorded`` keeps ``poses.csv`` as it is (exact positions, the papers' protocol). The
    map's ``source`` says which each round got.
    """
    if not rounds:
        raise MapError("a map needs at least one round")
    origin = rounds[0].origin
    if any(r.origin != origin for r in rounds[1:]):
        raise MapError("the rounds have different geodetic origins: give them one "
                       "dataset.json origin")
    if camera is None and rounds[0].camera is not None:
        if any(r.camera != rounds[0].camera for r in rounds[1:]):
            raise MapError("the rounds were recorded with different cameras (dataset.json "
                           "'camera' or calib.txt); build one map per camera")
        try:
            camera = Camera.from_dict(rounds[0].camera)
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"the round's camera intrinsics are invalid ({exc})") from None
    it: Iterable[np.ndarray] = (images if images is not None else
                                (r.load_image(i) for r in rounds for i in range(len(r))))
    if wrap is not None:
        it = wrap(iter(it))
    multi = len(rounds) > 1
    placed = [round_positions(r, positions) for r in rounds]
    source = dict(source) if source is not None else {"rounds": [r.name for r in rounds]}
    source["positions"] = [how for _, how in placed]
    return build_map(
        name or "+".join(r.name for r in rounds), it, np.concatenate([xy for xy, _ in placed]),
        [f"{r.name}/{n}" if multi else n for r in rounds for n in r.images],
        params=params, delta=delta, origin=origin,
        source=source, prune_features=prune_features,
        layers=np.concatenate([np.full(len(r), k) for k, r in enumerate(rounds)]),
        camera=camera,
    )


Chunk = tuple[np.ndarray, np.ndarray, np.ndarray]  # (codes, keypoints, counts) of whole images


def _image_digest(codes: np.ndarray, keypoints: np.ndarray) -> bytes:
    return (hashlib.blake2b(_raw(np.ascontiguousarray(codes).view(np.uint8)),
                            digest_size=_DIGEST).digest()
            + hashlib.blake2b(_raw(np.ascontiguousarray(keypoints, "<f4")),
                              digest_size=_DIGEST).digest())


def _keypoint_scale_of(meta: dict) -> int:
    """The fixed-point scale of a map's keypoints: its own, or the one its image size gives
    (a map of an older format being written again)."""
    have = meta.get("keypoint_scale")
    if isinstance(have, int) and valid_keypoint_scale(have):
        return have
    try:
        width, height = (int(v) for v in meta["image_size"])
    except (KeyError, TypeError, ValueError):
        raise MapError("the map's metadata lacks its working image size ('image_size')"
                       ) from None
    return keypoint_scale(width, height)


def _small_arrays(positions: np.ndarray, offsets: np.ndarray, image_names: list[str],
                  layers: np.ndarray, place_index: PlaceIndex | None) -> dict[str, np.ndarray]:
    out = {
        "positions": np.ascontiguousarray(positions, "<f8"),
        "offsets": np.ascontiguousarray(offsets, "<i8"),
        "image_names": np.frombuffer(json.dumps(image_names).encode(), np.uint8),
        "layers": np.ascontiguousarray(layers, "<i8"),
    }
    if place_index is not None:
        out.update(place_index.arrays())
    return out


def _canonical(header: dict) -> bytes:
    return json.dumps({k: v for k, v in header.items() if k != "checksum"},
                      sort_keys=True, separators=(",", ":")).encode()


def _raw(arr: np.ndarray) -> memoryview | bytes:
    """The array's bytes without copying a (memory-mapped) contiguous array."""
    if arr.nbytes == 0:
        return b""
    return np.ascontiguousarray(arr).data.cast("B")


def _pad(n: int) -> int:
    return (-n) % _ALIGN


def _sha256(arr: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in range(0, max(len(arr), 1), 1 << 16):  # bounded memory for a memmap
        h.update(_raw(arr[a: a + (1 << 16)]))
    return h.hexdigest()


def save_map(m: RouteMap, path: str | Path) -> Path:
    """Write the map atomically: a crash leaves the old file or none, never half of one.
    Returns the file written; load it (``load_map``) for a map backed by that file."""
    n = m.n_images
    counts = np.diff(m.offsets)

    def chunks() -> Iterator[Chunk]:
        for a in range(0, n, 512):  # whole images, bounded memory for a memory-mapped map
            b = min(n, a + 512)
            lo, hi = int(m.offsets[a]), int(m.offsets[b])
            yield m.codes[lo:hi], m.keypoints[lo:hi], counts[a:b]

    second = None
    if m.second is not None:
        s2 = m.second
        counts2 = np.diff(s2.offsets)

        def chunks2() -> Iterator[Chunk]:
            for a in range(0, n, 512):
                b = min(n, a + 512)
                rows = slice(int(s2.offsets[a]), int(s2.offsets[b]))
                yield s2.codes[rows], s2.keypoints[rows], counts2[a:b]

        second = (counts2, chunks2())
    assert m.layers is not None
    out = write_map(path, m.name, m.meta, m.positions, m.image_names, m.layers, counts,
                    chunks(), m.place_index, second)
    return out  # ``m`` is untouched: its ``path`` still names the file it was loaded from


def write_map(path: str | Path, name: str, meta: dict, positions: np.ndarray,
              image_names: list[str], layers: np.ndarray, counts: np.ndarray,
              chunks: Iterable[Chunk], place_index: PlaceIndex | None = None,
              second: tuple[np.ndarray, Iterable[Chunk]] | None = None) -> Path:
    """Stream a map into ``path`` atomically (temp + fsync + rename), chunk by chunk of whole
    images, so a map of any size is written without holding its descriptors in memory.

    ``counts``: features per image (the chunks' counts, in order, must repeat them).
    ``second``: (counts, chunks) of the second feature set, which a map of two feature types
    (metadata ``feature`` type sift+xfeat, format 5) needs and no other map has.
    """
    path = Path(path)
    if path.suffix != SUFFIX:
        path = path.with_name(path.name + SUFFIX)
    counts = np.asarray(counts, np.int64)
    n, total = len(counts), int(counts.sum())
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    small = _small_arrays(positions, offsets, list(image_names), layers, place_index)
    kind = str(meta.get("feature", {}).get("type", "sift"))
    if kind not in _CODE_DTYPES:
        raise MapError(f"unknown feature type '{kind}'")
    if (second is not None) != (kind == DUAL):
        raise MapError(f"a map of feature type '{kind}' "
                       f"{'needs' if kind == DUAL else 'has no'} a second feature set")
    code_dtype, dims = _CODE_DTYPES[kind], _CODE_DIMS[kind]
    dtypes = _dtypes_v6(kind)
    scale = _keypoint_scale_of(meta)
    shapes = {**{k: v.shape for k, v in small.items()}, "codes": (total, dims),
              "keypoints": (total, 2), "image_digests": (n, 2 * _DIGEST)}
    counts2 = np.zeros(0, np.int64)
    if second is not None:
        counts2 = np.asarray(second[0], np.int64)
        if len(counts2) != n:
            raise MapError(f"the second feature set counts {len(counts2)} images, expected {n}")
        small["offsets2"] = np.concatenate([[0], np.cumsum(counts2)]).astype("<i8")
        total2 = int(counts2.sum())
        shapes.update({"offsets2": (n + 1,), "codes2": (total2, XFEAT_DIMS),
                       "keypoints2": (total2, 2), "image_digests2": (n, 2 * _DIGEST)})
    layout: dict[str, dict[str, Any]] = {}
    offset = 0
    for key, dtype in dtypes.items():
        if key not in shapes:
            continue
        nbytes = math.prod(shapes[key]) * dtype.itemsize
        layout[key] = {"dtype": dtype.str, "shape": list(shapes[key]), "offset": offset,
                       "nbytes": int(nbytes), "sha256": "0" * 64}
        offset += nbytes + _pad(nbytes)
    header = {k: v for k, v in meta.items() if k not in ("arrays", "checksum", "name")}
    header.update({"name": name, "format_version": FORMAT_VERSION, "keypoint_scale": scale,
                   "arrays": layout,
                   "place_index": place_index.meta() if place_index is not None else None,
                   "checksum": "0" * 64})
    head_len = len(json.dumps(header).encode())
    start = len(MAGIC) + 8 + head_len
    data_start = start + _pad(start)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")  # WRITE_TEMPS
    try:
        with tmp.open("wb") as fh:
            fh.truncate(data_start + offset)
            fd = fh.fileno()

            def put(key: str, at: int, arr: np.ndarray) -> None:
                if arr.nbytes:
                    os.pwrite(fd, _raw(arr), data_start + layout[key]["offset"] + at)

            for key, arr in small.items():
                put(key, 0, arr)
                layout[key]["sha256"] = _sha256(arr)
            _stream_set(put, layout, chunks, counts, code_dtype, dims, scale, "")
            if second is not None:
                _stream_set(put, layout, second[1], counts2, _SECOND["codes2"], XFEAT_DIMS,
                            scale, "2")
            header["checksum"] = hashlib.sha256(_canonical(header)).hexdigest()
            head = json.dumps(header).encode()
            assert len(head) == head_len  # digests are fixed-length hex: same header size
            prefix = MAGIC + struct.pack("<Q", len(head)) + head
            os.pwrite(fd, prefix + b"\x00" * _pad(len(prefix)), 0)
            fh.flush()
            os.fsync(fd)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return path


def _stream_set(put: Callable[[str, int, np.ndarray], None], layout: dict[str, dict[str, Any]],
                chunks: Iterable[Chunk], counts: np.ndarray, code_dtype: np.dtype, dims: int,
                scale: int, suffix: str) -> None:
    """Write one feature set's chunks (arrays ``codes``, ``keypoints`` and ``image_digests``
    with ``suffix``; the keypoints as uint16 fixed point at ``scale``) and record their
    SHA-256 in ``layout``. The image digests are of the decoded (float32) keypoints."""
    n = len(counts)
    h_codes, h_kps = hashlib.sha256(), hashlib.sha256()
    digests = np.zeros((n, 2 * _DIGEST), np.uint8)
    img = row = 0
    for codes, kps, cnt in chunks:
        codes = np.ascontiguousarray(codes, code_dtype)
        cnt = np.asarray(cnt, np.int64)
        if not np.array_equal(cnt, counts[img: img + len(cnt)]) or \
                len(codes) != int(cnt.sum()) or len(kps) != len(codes):
            raise MapError("map chunks do not add up to the images' feature counts")
        stored = _stored_keypoints(kps, scale)
        kps = decode_keypoints(stored, scale)
        put("codes" + suffix, row * dims * code_dtype.itemsize, codes)
        put("keypoints" + suffix, row * 2 * KEYPOINT_DTYPE.itemsize, stored)
        h_codes.update(_raw(codes))
        h_kps.update(_raw(stored))
        local = np.concatenate([[0], np.cumsum(cnt)])
        for j in range(len(cnt)):
            a, b = int(local[j]), int(local[j + 1])
            digests[img + j] = np.frombuffer(_image_digest(codes[a:b], kps[a:b]), np.uint8)
        img += len(cnt)
        row += len(codes)
    if img != n:
        raise MapError(f"map chunks hold {img} images, expected {n}")
    put("image_digests" + suffix, 0, digests)
    layout["codes" + suffix]["sha256"] = h_codes.hexdigest()
    layout["keypoints" + suffix]["sha256"] = h_kps.hexdigest()
    layout["image_digests" + suffix]["sha256"] = _sha256(digests)


def _read_header(path: Path, fh: BinaryIO | None = None) -> tuple[dict, int]:
    """The header and where the arrays start, from the open file ``fh`` (the file at
    ``path`` opened here where None)."""
    try:
        if fh is None:
            with path.open("rb") as own:
                return _read_header(path, own)
        fh.seek(0)
        magic = fh.read(len(MAGIC))
        if magic != MAGIC:
            raise MapError(f"{path}: not a swarmloc map (bad magic bytes)")
        raw_len = fh.read(8)
        if len(raw_len) != 8:
            raise MapError(f"{path}: truncated header")
        (n,) = struct.unpack("<Q", raw_len)
        if n > 64 * 1024 * 1024:
            raise MapError(f"{path}: header length {n} is implausible (corrupted file)")
        raw = fh.read(n)
    except OSError as exc:
        raise MapError(f"{path}: cannot read ({exc})") from None
    if len(raw) != n:
        raise MapError(f"{path}: truncated header")
    try:
        header = json.loads(raw.decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise MapError(f"{path}: header is not valid JSON (corrupted file)") from None
    if not isinstance(header, dict):
        raise MapError(f"{path}: header is not a JSON object (corrupted file)")
    start = len(MAGIC) + 8 + n
    return header, start + _pad(start)


def file_version(path: str | Path) -> str | None:
    """The checksum (version) in a map file's header, read without opening its arrays; None
    when the file is missing or unreadable (``load_map`` then says why)."""
    try:
        header, _ = _read_header(Path(path))
    except MapError:
        return None
    v = header.get("checksum")
    return v if isinstance(v, str) else None


def _open_arrays(path: Path, fh: BinaryIO, header: dict, data_start: int,
                 dtypes: dict[str, np.dtype], optional: tuple[str, ...]
                 ) -> dict[str, np.ndarray]:
    """The arrays memory-mapped from the open file ``fh``: the file the header was read from,
    even where ``path`` is replaced meanwhile (another writer's new version)."""
    size = os.fstat(fh.fileno()).st_size
    arrays: dict[str, np.ndarray] = {}
    try:
        layout = header["arrays"]
        for key, want in dtypes.items():
            if key not in layout and key in optional:
                continue
            spec = layout[key]
            dtype = np.dtype(spec["dtype"])
            offset, nbytes = int(spec["offset"]), int(spec["nbytes"])
            shape = tuple(int(x) for x in spec["shape"])
            if dtype != want or offset < 0 or any(d < 0 for d in shape) or \
                    nbytes != math.prod(shape) * dtype.itemsize:
                raise MapError(f"{path}: array '{key}' is described inconsistently (dtype "
                               f"{spec['dtype']}, shape {spec['shape']}, {nbytes} bytes)")
            begin = data_start + offset
            if begin + nbytes > size:
                raise MapError(f"{path}: truncated file (array '{key}' runs past the end)")
            arrays[key] = (np.memmap(fh, dtype=dtype, mode="r", offset=begin, shape=shape)
                           if nbytes else np.zeros(shape, dtype))
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, MapError):
            raise
        raise MapError(f"{path}: header does not describe the arrays ({exc})") from None
    return arrays


def _check_no_trailing_bytes(path: Path, fh: BinaryIO, header: dict, data_start: int,
                             arrays: dict[str, np.ndarray]) -> None:
    """A version 3 file ends with its last (padded) array: anything after it was appended."""
    layout = header["arrays"]
    end = data_start + max((int(layout[k]["offset"]) + int(layout[k]["nbytes"]) +
                            _pad(int(layout[k]["nbytes"])) for k in arrays), default=0)
    size = os.fstat(fh.fileno()).st_size
    if size > end:
        raise MapError(f"{path}: {size - end} bytes follow the map's last array (something was "
                       "appended to the file); rebuild or download the map again")


def _verify_v2(path: Path, header: dict, arrays: dict[str, np.ndarray]) -> None:
    digest = hashlib.sha256(_canonical(header))
    for arr in arrays.values():
        digest.update(_raw(arr))
    if digest.hexdigest() != header.get("checksum"):
        raise MapError(f"{path}: checksum mismatch, the file is corrupted; rebuild the map")


def _verify_v3(path: Path, header: dict, arrays: dict[str, np.ndarray], lazy: bool) -> None:
    if hashlib.sha256(_canonical(header)).hexdigest() != header.get("checksum"):
        raise MapError(f"{path}: checksum mismatch (header), the file is corrupted; rebuild "
                       "the map")
    for key, arr in arrays.items():
        if lazy and key in _LAZY:
            continue
        if _sha256(arr) != header["arrays"][key].get("sha256"):
            fix = REBUILD_DUAL if key in _SECOND else "rebuild the map"
            raise MapError(f"{path}: checksum mismatch (array '{key}'), the file is "
                           f"corrupted; {fix}")


def check_matcher(matcher: str) -> str:
    """``matcher`` if it is one of MATCHERS, else a ValueError naming them."""
    if matcher not in MATCHERS:
        raise ValueError(f"unknown matcher {matcher!r}: use one of {', '.join(MATCHERS)} "
                         "('exact' compares every pair of features, 'words' only the pairs "
                         "sharing a visual word)")
    return matcher


def load_map(path: str | Path, verify: Verify = True, matcher: str = "auto") -> RouteMap:
    """Open a map memory-mapped; check version, layout and (by default) every checksum.

    ``verify="lazy"``: check the header and every array but the descriptors and keypoints
    now, each image's descriptors and keypoints against its digest when first used; start-up
    time and memory then do not grow with the map (service start-up uses it).
    """
    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such map file")
    # one open file for the header and every array: another writer's new version renamed
    # onto ``path`` meanwhile is not mixed into this one
    try:
        fh = path.open("rb")
    except OSError as exc:
        raise MapError(f"{path}: cannot read ({exc})") from None
    with fh:
        return _load_open(path, fh, verify, matcher)


def _load_open(path: Path, fh: BinaryIO, verify: Verify, matcher: str) -> RouteMap:
    header, data_start = _read_header(path, fh)
    version = header.get("format_version")
    if version not in READABLE_VERSIONS:
        raise MapError(
            f"{path}: map format version {version} is not supported (this swarmloc reads "
            f"versions {', '.join(map(str, READABLE_VERSIONS))}); rebuild it with "
            "'swarmloc map build'"
        )
    if version == 2:
        arrays = _open_arrays(path, fh, header, data_start, _DTYPES, ())
        if verify:
            _verify_v2(path, header, arrays)
    else:
        feature = header.get("feature")
        kind = (feature.get("type", "sift")
                if isinstance(feature, dict) and version in (4, 5, 6) else "sift")
        if kind not in _CODE_DTYPES:
            raise MapError(f"{path}: unknown feature type '{kind}' (this swarmloc knows "
                           f"{', '.join(_CODE_DTYPES)}); rebuild it with 'swarmloc map build'")
        dual = version == 5 or (version == 6 and kind == DUAL)
        optional: tuple[str, ...]
        if version == 6:
            dtypes, optional = _dtypes_v6(kind), _OPTIONAL_V6
            if not valid_keypoint_scale(header.get("keypoint_scale")):
                raise MapError(f"{path}: the keypoints' fixed-point scale "
                               f"{header.get('keypoint_scale')!r} is not a power of two from 1 "
                               "to 32 (corrupted file); rebuild the map")
        else:
            dtypes, optional = {**_DTYPES_V3, "codes": _CODE_DTYPES[kind]}, _OPTIONAL
            if dual:
                dtypes.update(_SECOND)
        if dual:
            layout = header.get("arrays")
            missing = [k for k in _SECOND if not isinstance(layout, dict) or k not in layout]
            if missing:
                raise MapError(f"{path}: the map of two feature types lacks its XFeat arrays "
                               f"({', '.join(missing)}); {REBUILD_DUAL}")
        arrays = _open_arrays(path, fh, header, data_start, dtypes, optional)
        _check_no_trailing_bytes(path, fh, header, data_start, arrays)
        if verify:
            _verify_v3(path, header, arrays, lazy=verify == "lazy")
    positions = np.asarray(arrays["positions"])
    offsets = np.asarray(arrays["offsets"])
    n = len(positions)
    layers = np.asarray(arrays["layers"])
    if positions.ndim != 2 or positions.shape[1] != 2 or len(offsets) != n + 1 or \
            offsets[-1] != len(arrays["codes"]) or np.any(np.diff(offsets) < 0) or \
            len(layers) != n or (n and layers.min() < 0):
        raise MapError(f"{path}: inconsistent arrays (positions/offsets/codes/layers)")
    if problem := position_problem(positions):
        raise MapError(f"{path}: image positions {problem}; the estimators cannot use them")
    if n and len(np.unique(layers)) != int(layers.max()) + 1:
        # traversal ids are 0 .. L-1, each with images (a stray huge id would otherwise
        # make a per-layer index of that many entries)
        raise MapError(f"{path}: layer ids are not 0..L-1 with images in each (largest "
                       f"{int(layers.max())}, {len(np.unique(layers))} distinct)")
    try:
        names = json.loads(bytes(arrays["image_names"]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise MapError(f"{path}: image names are corrupted") from None
    if not isinstance(names, list) or len(names) != n or \
            not all(isinstance(x, str) for x in names):
        got = len(names) if isinstance(names, list) else type(names).__name__
        raise MapError(f"{path}: {got} image names for {n} image positions; every image "
                       "needs one name")
    codes, kps = arrays["codes"], arrays["keypoints"]
    dims = _CODE_DIMS["xfeat" if codes.dtype == np.int8 else "sift"]
    if codes.ndim != 2 or codes.shape[1] != dims or kps.shape != (len(codes), 2):
        raise MapError(f"{path}: descriptor codes {codes.shape} / keypoints {kps.shape} do "
                       f"not have the shapes (n, {dims}) / (n, 2)")
    second = _check_second(path, arrays, n) if "codes2" in arrays else None
    place_index = None
    if version >= 3:
        place_index = _check_place_index(path, arrays, n, dims, version)
        if arrays["image_digests"].shape != (n, 2 * _DIGEST):
            raise MapError(f"{path}: image digests {arrays['image_digests'].shape} do not "
                           f"have the shape ({n}, {2 * _DIGEST})")
    delta, feature = header.get("delta"), header.get("feature")
    if not isinstance(delta, int | float) or not 0 < delta <= 1 or \
            not isinstance(feature, dict):
        raise MapError(f"{path}: header lacks valid matching parameters (delta, feature)")
    try:
        fp = feature_params(feature)
    except (TypeError, ValueError) as exc:
        raise MapError(f"{path}: feature parameters are invalid ({exc})") from None
    if not isinstance(fp, _PARAMS_OF_VERSION[version]):
        raise MapError(f"{path}: feature type '{feature.get('type')}' does not fit map format "
                       f"version {version}")
    dual = isinstance(fp, DualParams)
    for part in (fp.sift, fp.xfeat) if isinstance(fp, DualParams) else (fp,):
        _check_feature_params(path, part, feature,
                              "clahe-rootsift+xfeat" if dual else "xfeat")
    if dual and not isinstance(header.get("fusion"), dict):
        raise MapError(f"{path}: the map of two feature types lacks its fusion levels "
                       f"('fusion'); {REBUILD_DUAL}")
    cam = header.get("camera")
    if cam is not None:
        try:
            Camera.from_dict(cam)
        except (TypeError, ValueError, KeyError) as exc:
            raise MapError(f"{path}: camera intrinsics are invalid ({exc}); rebuild the map "
                           "with a valid --hfov, or without one") from None
    meta = {k: v for k, v in header.items() if k not in ("name",)}
    name = str(header.get("name", path.stem))
    lazy = (np.asarray(arrays["image_digests"]) if version >= 3 and verify == "lazy"
            else None)
    if second is not None and verify == "lazy":
        second.lazy_digests = np.asarray(arrays["image_digests2"])
    keypoints: Keypoints = arrays["keypoints"]
    if version == 6:
        scale = int(header["keypoint_scale"])
        keypoints = FixedPointKeypoints(arrays["keypoints"], scale)
        if second is not None:
            second.keypoints = FixedPointKeypoints(arrays["keypoints2"], scale)
    m = RouteMap(name, meta, positions, names, arrays["codes"], offsets,
                 keypoints, path, layers, place_index, lazy, second,
                 check_matcher(matcher))
    if m.uses_words:
        m.inverted_file  # noqa: B018 - trained now, so that no frame waits for it
    if m.second is not None:
        try:
            m.fusion  # noqa: B018 - parsed now: a bad header fails at load, not on a frame
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"{path}: the fusion levels are invalid ({exc}); {REBUILD_DUAL}"
                           ) from None
    return m


_PARAMS_OF_VERSION: dict[int, type | tuple[type, ...]] = {
    2: SiftParams, 3: SiftParams, 4: XFeatParams, 5: DualParams,
    6: (SiftParams, XFeatParams, DualParams)}


def _check_feature_params(path: Path, fp: SiftParams | XFeatParams, feature: dict,
                          name: str) -> None:
    """Sizes within bounds and, for XFeat, this service's model (``name``: the map's feature
    type name, for the rebuild command)."""
    sizes = ((fp.width, fp.height, fp.clahe_tile, fp.n_features) if isinstance(fp, SiftParams)
             else (fp.width, fp.height, fp.top_k))
    if not all(type(v) is int for v in sizes) or not (
            8 <= fp.width <= 8192 and 8 <= fp.height <= 8192 and min(sizes[2:]) >= 0
            and (not isinstance(fp, SiftParams) or 1 <= fp.clahe_tile <= 64)):
        raise MapError(f"{path}: feature parameters are invalid ({feature})")
    if isinstance(fp, XFeatParams):
        try:
            check_map_model(fp, name)
        except FeatureModelError as exc:
            raise MapError(f"{path}: {exc}") from None


def _check_second(path: Path, arrays: dict[str, np.ndarray], n: int) -> SecondSet:
    """The second feature set's arrays fit together and the map's n images."""
    offsets, codes = np.asarray(arrays["offsets2"]), arrays["codes2"]
    kps, digests = arrays["keypoints2"], arrays["image_digests2"]
    if offsets.shape != (n + 1,) or (n and (offsets[0] != 0 or np.any(np.diff(offsets) < 0))) \
            or offsets[-1] != len(codes) or codes.ndim != 2 or codes.shape[1] != XFEAT_DIMS \
            or kps.shape != (len(codes), 2) or digests.shape != (n, 2 * _DIGEST):
        raise MapError(f"{path}: the XFeat arrays do not fit together (offsets "
                       f"{offsets.shape}, codes {codes.shape}, keypoints {kps.shape}, digests "
                       f"{digests.shape} for {n} images); {REBUILD_DUAL}")
    return SecondSet(codes, kps, offsets)


def _check_place_index(path: Path, arrays: dict[str, np.ndarray], n: int, dims: int,
                       version: int) -> PlaceIndex | None:
    keys = _OPTIONAL_V6 if version == 6 else _OPTIONAL
    present = [k for k in keys if k in arrays]
    if not present:
        return None
    if len(present) != len(keys):
        raise MapError(f"{path}: the place index is incomplete (has {present})")
    w, mu, proj, desc = (arrays[k] for k in _OPTIONAL)
    scale = arrays.get("place_projection_scale")
    if w.ndim != 2 or w.shape[1] != dims or mu.shape != (w.shape[0] * dims,) or \
            proj.ndim != 2 or proj.shape[0] != len(mu) or desc.shape != (n, proj.shape[1]) or \
            (scale is not None and (scale.shape != (proj.shape[1],) or
                                    not np.isfinite(scale).all())):
        raise MapError(f"{path}: the place index arrays do not fit together (words "
                       f"{w.shape}, projection {proj.shape}, descriptors {desc.shape})")
    return PlaceIndex.from_arrays(arrays)


def list_maps(directory: str | Path) -> list[Path]:
    directory = Path(directory)
    return sorted(p for p in directory.glob(f"*{SUFFIX}") if p.is_file())
