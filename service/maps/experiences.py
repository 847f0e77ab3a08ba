"""Experiences: layers of a map that the fleet learned, and the layer each frame is matched with.

An *experience* (Churchill and Newman, "Practice makes perfect", 2012) is a layer appended to a
route map: frames a robot saw where it was confidently localized, stored like map images (their
descriptor codes, keypoints and estimated positions) with one image per place. The map header's
``experiences`` lists them (id, layer, created, updated, condition, robot, images, bytes, uses,
last used); the map's own traversals are its *base* layers. A map without the list is a map
without experiences: older files load unchanged, and an older service reads experiences as
ordinary traversals. Every change is a new file written atomically with its checksums
(service/maps/route_map.py ``write_map``): a new version and ETag. Versions that differ only by
experiences keep the base images' ids; ``compatible_versions`` lists the earlier versions a
stored session may continue from without a reset.

Localization does not compare a particle with every layer: ``LayerChoice`` keeps, per session,
an exponential average of how well each layer matched at the estimate, and the particles are
compared with the *active* layer's image at their place (the base images where the active
experience has none). After each frame the active layer, and every second frame one other in
turn, are compared at the estimate (``probe``: at most two comparisons, mostly one already
made), so a session moves to the layer of today's light without multiplying comparisons by
the number of layers. An experience rarely covers the whole route: in its gaps, and while the
swarm searches, the particles use the base images (``nearest``), and where particles compared
with different layers meet, an experience's similarities are put on the base layer's scale
(``scaled``).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.estimators.along_track import path_tangents
from service.maps.compact import KEYPOINT_DTYPE, Keypoints
from service.maps.route_map import Chunk, MapError, RouteMap, load_map, write_map
from service.vision.features import Features
from service.vision.place_index import PlaceIndex

KEY = "experiences"
COMPATIBLE = "compatible_versions"
MAX_COMPATIBLE = 64  # earlier versions a stored session may continue from
BASE = "base"  # the LayerChoice key of the map's own traversals
EMA_ALPHA = 0.3  # weight of the newest probe in a layer's score
SWITCH_RATIO = 1.1  # another layer becomes active when its score beats the active one's by this
GAP_SPACINGS = 2.0  # a particle farther than this many spacings from an experience image uses
#                     the base images there
PLACE_SPACINGS = 0.5  # one image per place and experience: this many spacings apart at least

LEVEL_SAMPLE = 40  # consecutive image pairs of a map whose median similarity is its level
SEED_SHARE = 0.2  # a learned image proposed to a searching swarm matches the frame at least
#                   this share of the map's same-light level

Usage = dict[str, tuple[int, float]]  # experience id -> (frames matched, last use, unix s)


def now_iso(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="seconds")


def _layers(m: RouteMap) -> np.ndarray:
    assert m.layers is not None  # set by RouteMap.__post_init__
    return m.layers


def experience_list(m: RouteMap) -> list[dict]:
    """The map's experiences as stored in its header (empty for a map without)."""
    return [dict(e) for e in m.meta.get(KEY) or []]


def experience_layers(m: RouteMap) -> dict[str, int]:
    """Experience id -> its layer."""
    return {str(e["id"]): int(e["layer"]) for e in m.meta.get(KEY) or []}


def base_layers(m: RouteMap) -> list[int]:
    learned = set(experience_layers(m).values())
    return [k for k in range(m.n_layers) if k not in learned]


def base_images(m: RouteMap) -> np.ndarray:
    """Ids of the map's own images (its traversals, not its experiences)."""
    return np.flatnonzero(np.isin(_layers(m), base_layers(m)))


def base_spacing(m: RouteMap) -> float:
    """Median spacing of the map's own images (the experiences' are not counted)."""
    pos = m.positions[base_images(m)]
    if len(pos) < 2:
        return 1.0
    return float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1)))


def base_identity(m: RouteMap) -> str:
    """What its versions that differ only by experiences share, and a map rebuilt or replaced
    under the same name does not: a digest of its feature type and its own images' names,
    positions and numbers of features. Images learned on one version are written only into
    a version of the same identity (their positions are in its frame)."""
    ids = base_images(m)
    h = hashlib.blake2b(digest_size=16)
    h.update(str((m.meta.get("feature") or {}).get("type")).encode())
    h.update(np.ascontiguousarray(m.positions[ids], "<f8").tobytes())
    h.update(np.ascontiguousarray(np.diff(m.offsets)[ids], "<i8").tobytes())
    h.update("\0".join(m.image_names[int(i)] for i in ids).encode())
    return h.hexdigest()


def same_light_level(m: RouteMap) -> float:
    """How well a frame in the map's own light matches it: the median similarity of up to
    ``LEVEL_SAMPLE`` map images with their successor in the same traversal (within two
    spacings)."""
    layers = np.asarray(m.layers)
    base = np.flatnonzero(np.isin(layers, base_layers(m)))[:-1]
    spacing = base_spacing(m)
    ok = base[(layers[base] == layers[base + 1]) &
              (np.linalg.norm(m.positions[base + 1] - m.positions[base], axis=1)
               <= 2 * spacing)]
    if not len(ok):
        return 1.0
    pick = ok[np.linspace(0, len(ok) - 1, min(LEVEL_SAMPLE, len(ok))).astype(int)]
    return float(np.median([m.similarity(m.image_features(int(i)), [int(i) + 1])[0]
                            for i in pick]))


def image_bytes(m: RouteMap, ids: np.ndarray) -> int:
    """Bytes the images ``ids`` take in the map file (codes, keypoints, position, layer, offset,
    digest, place descriptor and name)."""
    ids = np.asarray(ids, np.int64)
    feats = int(np.sum(m.offsets[ids + 1] - m.offsets[ids]))
    per_feature = _per_feature(m.codes)
    place = _place_bytes(m)
    names = sum(len(m.image_names[int(i)].encode()) + 4 for i in ids)
    second = 0
    if m.second is not None:  # its codes, keypoints, offset and digest
        feats2 = int(np.sum(m.second.offsets[ids + 1] - m.second.offsets[ids]))
        second = feats2 * _per_feature(m.second.codes) + len(ids) * (8 + 16)
    return feats * per_feature + len(ids) * (16 + 8 + 8 + 16 + place) + names + second


def _per_feature(codes: np.ndarray) -> int:
    """Bytes per feature of a feature set as the map file stores it (format 6: its code and
    a uint16 fixed-point keypoint)."""
    return codes.shape[1] * codes.dtype.itemsize + 2 * KEYPOINT_DTYPE.itemsize


def _place_bytes(m: RouteMap) -> int:
    """Bytes of one image's place descriptor in the map file (float16)."""
    return m.place_index.dims * 2 if m.place_index is not None else 0


@dataclass(frozen=True)
class NewImage:
    """A frame to learn: its descriptor codes and keypoints (the map's feature type) and its
    estimated position; on a map of two feature types also the second set's (XFeat)."""

    codes: np.ndarray
    keypoints: np.ndarray
    xy: np.ndarray
    name: str
    codes2: np.ndarray | None = None
    keypoints2: np.ndarray | None = None

    @classmethod
    def of(cls, features: Features, xy: np.ndarray, name: str, second: bool) -> NewImage:
        """A frame's features as an image to learn at ``xy`` (copies: the frame's buffers are
        not kept); ``second``: with its second set (a map of two feature types)."""
        two = features.second if second else None
        return cls(np.array(features.codes), np.array(features.keypoints, np.float32),
                   np.asarray(xy, float), name,
                   None if two is None else np.array(two.codes),
                   None if two is None else np.array(two.keypoints, np.float32))

    @property
    def features(self) -> Features:
        """The image's features as a frame's (its second set where it has one)."""
        second = None if self.codes2 is None or self.keypoints2 is None else \
            Features(self.keypoints2, self.codes2)
        return Features(self.keypoints, self.codes, second)


def _rewrite(m: RouteMap, path: Path, keep: np.ndarray, new: Sequence[NewImage],
             new_layer: int, layer_map: np.ndarray, meta: dict) -> RouteMap:
    """Write the map's kept images (``keep``, with layers renumbered by ``layer_map``) and
    ``new`` images of layer ``new_layer`` atomically to ``path``; load it back (verified)."""
    kept = np.flatnonzero(keep)
    counts_old = np.diff(m.offsets)[kept]
    counts = np.concatenate([counts_old, [len(f.codes) for f in new]]).astype(np.int64)
    positions = np.concatenate([m.positions[kept], np.array([f.xy for f in new],
                                                             float).reshape(-1, 2)])
    names = [m.image_names[int(i)] for i in kept] + [f.name for f in new]
    layers = np.concatenate([layer_map[_layers(m)[kept]],
                             np.full(len(new), new_layer, np.int64)]).astype(np.int64)
    place = m.place_index
    if place is not None:
        extra = np.array([place.describe(f.codes) for f in new], np.float32).reshape(
            -1, place.dims)
        place = PlaceIndex(place.words, place.mean, place.projection,
                           np.concatenate([np.asarray(place.descriptors)[kept], extra]))

    second: tuple[np.ndarray, Iterator[Chunk]] | None = None
    if m.second is not None:
        missing = [f.name for f in new if f.codes2 is None or f.keypoints2 is None]
        if missing:
            raise MapError(f"map '{m.name}' holds two feature types: the learned images "
                           f"{missing[:3]} lack the second set (XFeat)")
        s2 = m.second
        new2 = [(np.asarray(f.codes2), np.asarray(f.keypoints2)) for f in new]
        counts2 = np.concatenate([np.diff(s2.offsets)[kept], [len(c) for c, _ in new2]]
                                 ).astype(np.int64)
        second = (counts2, _chunks(s2.codes, s2.keypoints, s2.offsets, kept, new2))
    new1 = [(f.codes, f.keypoints) for f in new]
    out = write_map(path, m.name, meta, positions, names, layers, counts,
                    _chunks(m.codes, m.keypoints, m.offsets, kept, new1), place, second)
    return load_map(out, verify=True, matcher=m.matcher)  # a new version, the same matcher


def _chunks(codes: np.ndarray, keypoints: Keypoints, offsets: np.ndarray, kept: np.ndarray,
            new: Sequence[tuple[np.ndarray, np.ndarray]]) -> Iterator[Chunk]:
    """One feature set's chunks for ``write_map``: the kept images' rows (whole images, 512 at
    a time, bounded memory), then the new images' (codes, keypoints)."""
    for a in range(0, len(kept), 512):
        ids = kept[a: a + 512]
        parts = [slice(int(offsets[i]), int(offsets[i + 1])) for i in ids]
        yield (np.concatenate([codes[s] for s in parts]),
               np.concatenate([keypoints[s] for s in parts]),
               np.diff(offsets)[ids].astype(np.int64))
    if new:
        yield (np.concatenate([c for c, _ in new]),
               np.concatenate([k for _, k in new]).astype(np.float32),
               np.array([len(c) for c, _ in new], np.int64))


def _history(m: RouteMap) -> list[str]:
    old = [str(c) for c in m.meta.get(COMPATIBLE) or []]
    have = m.meta.get("checksum")
    return ([*old, have] if have else old)[-MAX_COMPATIBLE:]


def _with_usage(entries: list[dict], usage: Usage) -> list[dict]:
    for e in entries:
        frames, last = usage.get(str(e["id"]), (0, 0.0))
        if frames:
            e["uses"] = int(e.get("uses", 0)) + frames
            e["last_used"] = now_iso(last)
    return entries


def add_experience(m: RouteMap, path: Path, exp_id: str, images: Sequence[NewImage], *,
                   condition: str | None, robot: str | None, now: float, budget_bytes: int,
                   usage: Usage | None = None) -> tuple[RouteMap, list[str]]:
    """A new version of ``m`` at ``path`` with ``images`` added to experience ``exp_id``
    (created when new): one image per place and experience (an image closer than
    ``PLACE_SPACINGS`` spacings to one the experience has, or to an earlier new one, is left
    out). The experiences then take at most ``budget_bytes``: the least used others are retired
    first (fewest uses, then the oldest last use), and what still does not fit of the new images
    is left out. Returns (the new map, the ids of retired experiences); ``m`` unchanged when
    no image is added."""
    entries = _with_usage(experience_list(m), usage or {})
    layers = experience_layers(m)
    layer = layers.get(exp_id, m.n_layers)
    radius = PLACE_SPACINGS * base_spacing(m)
    have = m.positions[_layers(m) == layer] if exp_id in layers else np.zeros((0, 2))
    chosen: list[NewImage] = []
    for f in images:
        xy = np.asarray(f.xy, float)
        placed = np.concatenate([have, [g.xy for g in chosen]]) if chosen else have
        if len(placed) and float(np.min(np.linalg.norm(placed - xy, axis=1))) < radius:
            continue
        chosen.append(f)
    if not chosen:
        return m, []
    per_new = [_new_bytes(m, f) for f in chosen]
    sizes = {str(e["id"]): int(e.get("bytes", 0)) for e in entries}
    mine = sizes.get(exp_id, 0)
    fit = int(np.searchsorted(np.cumsum(per_new), max(budget_bytes - mine, 0), side="right"))
    chosen, per_new = chosen[:fit], per_new[:fit]
    if not chosen:
        return m, []
    need = mine + sum(per_new)
    others = sorted((e for e in entries if str(e["id"]) != exp_id),
                    key=lambda e: (int(e.get("uses", 0)), str(e.get("last_used") or
                                                                e.get("created"))))
    retired: list[str] = []
    total = need + sum(sizes[str(e["id"])] for e in others)
    for e in others:
        if total <= budget_bytes:
            break
        retired.append(str(e["id"]))
        total -= sizes[str(e["id"])]
    gone_layers = {layers[r] for r in retired}
    keep = ~np.isin(_layers(m), list(gone_layers))
    layer_map = np.cumsum([k not in gone_layers for k in range(m.n_layers)]) - 1
    new_layer = int(layer_map[layer]) if exp_id in layers else \
        m.n_layers - len(gone_layers)
    stamp = now_iso(now)
    kept_entries = [e for e in entries if str(e["id"]) not in retired]
    for e in kept_entries:
        e["layer"] = int(layer_map[int(e["layer"])])
    mine_entry = next((e for e in kept_entries if str(e["id"]) == exp_id), None)
    if mine_entry is None:
        mine_entry = {"id": exp_id, "layer": new_layer, "created": stamp, "condition": condition,
                      "robot": robot, "images": 0, "bytes": 0, "uses": 0, "last_used": None}
        kept_entries.append(mine_entry)
    mine_entry.update(updated=stamp, images=int(mine_entry["images"]) + len(chosen),
                      bytes=need)
    meta = {**m.meta, KEY: kept_entries, COMPATIBLE: _history(m)}
    return _rewrite(m, path, keep, chosen, new_layer, layer_map, meta), retired


def _new_bytes(m: RouteMap, f: NewImage) -> int:
    second = 0
    if m.second is not None and f.codes2 is not None:
        second = len(f.codes2) * _per_feature(m.second.codes) + 8 + 16
    return (len(f.codes) * _per_feature(m.codes)
            + 16 + 8 + 8 + 16 + _place_bytes(m) + len(f.name.encode()) + 4 + second)


def remove_experience(m: RouteMap, path: Path, exp_id: str, usage: Usage | None = None
                      ) -> RouteMap:
    """A new version of ``m`` at ``path`` without experience ``exp_id`` (KeyError: none)."""
    layers = experience_layers(m)
    gone = layers[exp_id]
    entries = [e for e in _with_usage(experience_list(m), usage or {}) if str(e["id"]) != exp_id]
    layer_map = np.cumsum([k != gone for k in range(m.n_layers)]) - 1
    for e in entries:
        e["layer"] = int(layer_map[int(e["layer"])])
    meta = {**m.meta, KEY: entries, COMPATIBLE: _history(m)}
    return _rewrite(m, path, _layers(m) != gone, [], 0, layer_map, meta)


def with_usage(m: RouteMap, usage: Usage) -> list[dict]:
    """The map's experiences with the uses counted since its last write added."""
    return _with_usage(experience_list(m), usage)


def same_images(old: RouteMap, new: RouteMap) -> np.ndarray:
    """For each image of ``old``, its id in ``new`` (another version of the same map) where
    ``new`` holds it unchanged, else -1: the same name, position, number of features and
    layer (the same experience, or the same traversal of the map's own)."""
    def keys(m: RouteMap) -> list[tuple]:
        names = {k: f"experience:{e}" for e, k in experience_layers(m).items()}
        counts = np.diff(m.offsets)
        return [(names.get(int(layer), f"own:{int(layer)}"), m.image_names[i],
                 float(m.positions[i, 0]), float(m.positions[i, 1]), int(counts[i]))
                for i, layer in enumerate(_layers(m))]
    where: dict[tuple, int] = {}
    for i, key in enumerate(keys(new)):
        where.setdefault(key, i)
    return np.array([where.get(key, -1) for key in keys(old)], np.int64)


def carry_geometry(old: RouteMap, new: RouteMap) -> int:
    """Give ``new``, a version of ``old`` that differs only by experiences, the two-view
    structures ``old`` has built for the images both hold unchanged (both feature types'), so
    that the sessions moving onto it do not build them again; returns how many."""
    if not compatible(new, old.meta.get("checksum")):
        return 0
    ids: np.ndarray | None = None
    n = 0
    for attr in ("geometry", "second_geometry"):
        was = vars(old).get(attr)  # built only where a frame or the warmer used it
        now = getattr(new, attr) if was is not None else None
        if was is not None and now is not None:
            ids = same_images(old, new) if ids is None else ids
            n += now.carry(was, ids)
    return n


def compatible(m: RouteMap, checksum: str | None) -> bool:
    """Whether a session stored on version ``checksum`` may continue on ``m`` (the same
    version, or an earlier one that differs only by experiences)."""
    return checksum == m.meta.get("checksum") or checksum in (m.meta.get(COMPATIBLE) or [])


# ---- which layer each frame is matched with -------------------------------------------------
SimilarityFn = Callable[[np.ndarray], np.ndarray]


def nearest_base(m: RouteMap, positions: np.ndarray, base: list[int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(ids, distances) of each position's nearest image in every base layer ``base`` (one
    column per layer)."""
    cols = [m.nearest_in_layer(positions, k) for k in base]
    return np.column_stack([c[0] for c in cols]), np.column_stack([c[1] for c in cols])


@dataclass
class LayerChoice:
    """A session's choice of layer (kept with its state): the score of each layer (``BASE``
    or an experience id) and the active one."""

    scores: dict[str, float] = field(default_factory=dict)
    active: str = BASE
    turn: int = 0  # round-robin over the other layers for the probe

    def nearest(self, m: RouteMap, at: np.ndarray | None = None
                ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """For the fitness: each particle's base images (one column per base layer), replaced
        by the active experience's image of the same place where it has one: the experience
        image nearest to the particle's first base image, within ``GAP_SPACINGS`` of that
        image or, where it lies beside it (a lane beside the map's: ``_beside``), of a
        particle sharing it.

        ``at`` (the previous estimate while the session tracks; None while the swarm searches:
        no estimate yet, or it was not ``tracking``): where the active experience has no image
        within ``GAP_SPACINGS`` of it, or while the swarm searches, every particle uses the
        base images (the gap rule). Otherwise the particles at the true place (base images,
        another light) would compete with particles at the experience's images elsewhere
        (today's light, higher similarity to any frame), and the swarm would leave the gap, or
        a global search would settle, on the part of the route the experience covers."""
        base = base_layers(m)
        spacing = base_spacing(m)
        gap = GAP_SPACINGS * spacing
        layer = self.layer_at(m, at, gap)

        def nearest(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            ids, dist = nearest_base(m, positions, base)
            if layer is None:
                return ids, dist
            # each particle's first base image stands in for its place: the experience image
            # nearest to that image replaces it, so a frame compares no more distinct images
            # than it would on the base layer alone
            own, inverse = np.unique(ids[:, 0], return_inverse=True)
            e_own, e_gap = m.nearest_in_layer(m.positions[own], layer)
            e_ids = e_own[inverse]
            e_dist = np.linalg.norm(np.asarray(positions, float).reshape(-1, 2)
                                    - m.positions[e_ids], axis=1)
            near = e_gap <= gap
            reached = np.zeros(len(own), bool)  # a particle sharing the base image is near
            np.logical_or.at(reached, inverse, e_dist <= gap)  # its experience image
            check = ~near & reached
            if check.any():
                near[check] = self._beside(m, own[check], e_own[check], spacing, gap)
            near = near[inverse]
            return (np.where(near[:, None], e_ids[:, None], ids),
                    np.where(near[:, None], e_dist[:, None], dist))

        return nearest

    @staticmethod
    def _beside(m: RouteMap, own: np.ndarray, e_own: np.ndarray, spacing: float, gap: float
                ) -> np.ndarray:
        """Whether each experience image ``e_own`` shows the place of base image ``own`` from
        beside it: less than ``gap`` ahead or behind it along the map's path, at any distance
        across (not a place beyond a gap of the experience). A robot driving a lane beside
        the one the map was recorded in learns images on its own lane, farther than the gap
        from the map's images of the same place."""
        tangent = path_tangents(m.positions, own, spacing)
        along = np.abs(np.sum((m.positions[e_own] - m.positions[own]) * tangent, axis=1))
        return np.any(tangent != 0, axis=1) & (along <= gap)

    def layer_at(self, m: RouteMap, at: np.ndarray | None, gap: float) -> int | None:
        """The active experience's layer, None where the particles use the base images: no
        experience active, the swarm searching (``at`` None) or ``at`` in a gap of it (no
        image of it within ``gap``, ``GAP_SPACINGS`` map spacings)."""
        layer = experience_layers(m).get(self.active)
        if layer is not None and (at is None or float(
                m.nearest_in_layer(np.asarray(at, float)[None, :], layer)[1][0]) > gap):
            return None
        return layer

    def scaled(self, m: RouteMap, similarity: SimilarityFn) -> SimilarityFn:
        """``similarity`` with each experience image's m put on the base layer's scale: times
        the base layer's running score over the experience's (both from ``probe``, at the
        estimate), where the experience scores higher. Particles compared with different
        layers then compete fairly: a learned image of today's light that matches the frame
        about as well as any of its images matches any frame of that light (a wrong place)
        no longer beats the base images at the true place. Unchanged where nothing is
        scored yet."""
        factors = np.ones(m.n_layers)
        base = self.scores.get(BASE)
        for key, k in experience_layers(m).items():
            score = self.scores.get(key)
            if base is not None and score is not None and score > base:
                factors[k] = base / score
        if np.all(factors == 1.0):
            return similarity
        layers = _layers(m)
        return lambda ids: similarity(ids) * factors[layers[ids]]

    def probe(self, m: RouteMap, similarity: SimilarityFn, position: np.ndarray) -> None:
        """Compare the frame at ``position`` with the active layer and one other (in turn);
        update their scores and switch to a layer that matches clearly better."""
        layers = experience_layers(m)
        gap = GAP_SPACINGS * base_spacing(m)
        here: dict[str, int] = {}
        for key, k in layers.items():
            i, d = m.nearest_in_layer(position[None, :], k)
            if float(d[0]) <= gap:
                here[key] = int(i[0])
        if not here:
            return
        if self.active != BASE and self.active not in layers:
            self.active = BASE  # its experience was removed
        keys = [BASE, *sorted(here)]
        others = [k for k in keys if k != self.active]
        probed = [self.active] if self.active in keys else []
        self.turn += 1
        if others and (self.turn % 2 == 0 or not probed):  # another layer every 2nd frame
            probed.append(others[(self.turn // 2) % len(others)])
        for key in probed:
            if key == BASE:
                ids = np.array([int(m.nearest_in_layer(position[None, :], k)[0][0])
                                for k in base_layers(m)], np.int64)
            else:
                ids = np.array([here[key]], np.int64)
            score = float(np.max(similarity(ids)))
            old = self.scores.get(key)
            self.scores[key] = score if old is None else \
                (1 - EMA_ALPHA) * old + EMA_ALPHA * score
        for key in list(self.scores):
            if key != BASE and key not in layers:
                del self.scores[key]
        best = max(self.scores, key=lambda k: self.scores[k])
        if best != self.active and self.scores[best] > SWITCH_RATIO * self.scores.get(
                self.active, 0.0):
            self.active = best

    def experience(self) -> str | None:
        return None if self.active == BASE else self.active


def check_experience_id(exp_id: str) -> None:
    if not (0 < len(exp_id) <= 64 and all(c.isalnum() or c in "-_." for c in exp_id)):
        raise MapError(f"experience id '{exp_id}' must be 1-64 letters, digits, '-', '_' or '.'")


def budget_bytes(megabytes: float) -> int:
    return math.floor(megabytes * 1024 * 1024)
