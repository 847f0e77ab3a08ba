"""Route maps: build from a round, save atomically, load memory-mapped and verified.

File layout (``NAME.swmap``), all little-endian:

    MAGIC (8 bytes) | header length (uint64) | header JSON (utf-8) | padding to 64 | arrays

Format version 2 stores descriptors as uint8 codes (SIFT is integer-valued; RootSIFT is
quantised, see service/features.py) and the layer (traversal) of every image, for maps merged
from several traversals. The header holds the format version, the metadata (feature type and
parameters, delta, working image size, geodetic origin, build date, pruning statistics,
source) and, for every array, its dtype, shape and byte offset. ``checksum`` is the SHA-256
of the header without that field (canonical JSON) followed by every data byte, so a flipped
bit anywhere is caught on load. Arrays are 64-byte aligned and opened with ``numpy.memmap``:
a map opens without copying its descriptors into memory.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from scipy.spatial import cKDTree

from service.features import (
    DEFAULT_DELTA,
    Features,
    SiftParams,
    match_batch,
    unit_descriptors,
)
from service.geo import LocalFrame
from service.matcher import PreparedSet, match_batch_u8, prepare

MAGIC = b"SWMAP\x00\r\n"
# the dtype of every stored array, as save_map writes them (anything else is refused)
_DTYPES = {"positions": np.dtype("<f8"), "offsets": np.dtype("<i8"), "codes": np.dtype(np.uint8),
           "keypoints": np.dtype("<f4"), "image_names": np.dtype(np.uint8),
           "layers": np.dtype("<i8")}
FORMAT_VERSION = 2
SUFFIX = ".swmap"
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
    keypoints: np.ndarray  # (total, 2) float32
    path: Path | None = None
    layers: np.ndarray | None = None  # (n,) traversal index of each image; None: one

    def __post_init__(self) -> None:
        n = len(self.positions)
        if self.layers is None:
            self.layers = np.zeros(n, np.int64)
        self._tree = cKDTree(self.positions)
        self._layer_ids = [np.flatnonzero(self.layers == k) for k in range(self.n_layers)]
        self._layer_trees = ([self._tree] if self.n_layers == 1 else
                             [cKDTree(self.positions[ids]) for ids in self._layer_ids])
        self._sets: list[np.ndarray | None] = [None] * n
        self._prepared: list[PreparedSet | None] = [None] * n

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
    def sift_params(self) -> SiftParams:
        p = {k: v for k, v in self.meta["feature"].items() if k != "type"}
        return SiftParams(**p)

    @cached_property
    def frame(self) -> LocalFrame | None:
        """The geodetic frame (built once: a pyproj transformer is not cheap)."""
        o = self.meta.get("origin")
        return LocalFrame(o["lat"], o["lon"]) if o else None

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

    def features_of(self, image_id: int) -> np.ndarray:
        """Unit descriptors of one map image (from its codes; kept after the first use)."""
        cached = self._sets[image_id]
        if cached is None:
            cached = unit_descriptors(self.codes[self.offsets[image_id]:
                                                 self.offsets[image_id + 1]])
            self._sets[image_id] = cached
        return cached

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

    def prepared(self, image_id: int) -> PreparedSet:
        """One map image's codes prepared for the exact uint8 matcher (kept after first use;
        the codes stay memory-mapped)."""
        cached = self._prepared[image_id]
        if cached is None:
            cached = prepare(np.asarray(
                self.codes[self.offsets[image_id]: self.offsets[image_id + 1]]))
            self._prepared[image_id] = cached
        return cached

    def similarity(self, frame_codes: np.ndarray, image_ids: Iterable[int]) -> np.ndarray:
        """m(frame, map image) for each id: the exact uint8 matcher (service/matcher.py) on
        the frame's descriptor codes (``Features.codes``)."""
        sets = [self.prepared(int(i)) for i in image_ids]
        return match_batch_u8(frame_codes, sets, self.delta).scores

    def summary(self) -> dict:
        return {
            "name": self.name,
            "n_images": self.n_images,
            "n_features": int(self.offsets[-1]),
            "n_layers": self.n_layers,
            "bounds": [self.bounds[0].tolist(), self.bounds[1].tolist()],
            "spacing_m": self.spacing,
            **{k: v for k, v in self.meta.items() if k not in ("arrays", "checksum")},
        }


def build_map(
    name: str,
    images: Iterable[np.ndarray],
    positions: np.ndarray,
    image_names: list[str],
    *,
    params: SiftParams | None = None,
    delta: float = DEFAULT_DELTA,
    origin: tuple[float, float] | None = None,
    source: dict | None = None,
    extract: Callable[[np.ndarray, SiftParams], Features] | None = None,
    prune_features: bool = False,
    layers: np.ndarray | None = None,
) -> RouteMap:
    """Extract, (optionally) prune and assemble a map in memory (``save_map`` writes it).

    ``prune_features``: the papers' neighbour pruning (Sec. 6), off by default: it throws
    away the features that survive a change of light (README, "Features across lighting").
    ``layers``: traversal index per image for a map merged from several traversals; pruning
    compares neighbours within a traversal.
    """
    from service.features import extract as sift_extract

    params = params or SiftParams()
    extract = extract or sift_extract
    feats = [extract(img, params) for img in images]
    positions = np.asarray(positions, float)
    if len(feats) != len(positions) or len(feats) != len(image_names):
        raise MapError("images, positions and names must have the same length")
    if len(feats) == 0:
        raise MapError("a map needs at least one image")
    layer_arr = (np.zeros(len(feats), np.int64) if layers is None
                 else np.asarray(layers, np.int64))
    if len(layer_arr) != len(feats) or layer_arr.min() < 0:
        raise MapError("layers must give a non-negative traversal index per image")
    kept = feats
    stats = PruneStats(sum(len(f) for f in feats), sum(len(f) for f in feats))
    if prune_features:
        kept = list(feats)
        before = after = 0
        for k in np.unique(layer_arr):
            idx = np.flatnonzero(layer_arr == k)
            part, st = prune([feats[i] for i in idx], delta)
            for i, f in zip(idx, part, strict=True):
                kept[i] = f
            before, after = before + st.features_before, after + st.features_after
        stats = PruneStats(before, after)
    counts = np.array([len(f) for f in kept], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    codes = (np.concatenate([f.codes for f in kept]) if offsets[-1]
             else np.zeros((0, 128), np.uint8)).astype(np.uint8)
    kps = (np.concatenate([f.keypoints for f in kept]) if offsets[-1]
           else np.zeros((0, 2), np.float32)).astype(np.float32)
    meta = {
        "format_version": FORMAT_VERSION,
        "feature": params.as_dict(),
        "delta": delta,
        "image_size": [params.width, params.height],
        "origin": {"lat": origin[0], "lon": origin[1]} if origin else None,
        "build_date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "pruning": {
            "enabled": prune_features,
            "features_before": stats.features_before,
            "features_after": stats.features_after,
            "removed_fraction": round(stats.removed_fraction, 4),
        },
        "source": source or {},
    }
    return RouteMap(name, meta, positions, list(image_names), codes, offsets, kps,
                    layers=layer_arr)


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
    def __len__(self) -> int: ...
    def load_image(self, i: int) -> np.ndarray: ...


def build_map_from_rounds(
    rounds: Sequence[RoundLike],
    *,
    name: str | None = None,
    params: SiftParams | None = None,
    delta: float = DEFAULT_DELTA,
    prune_features: bool = False,
    source: dict[str, Any] | None = None,
    images: Iterable[np.ndarray] | None = None,
    wrap: Callable[[Iterator[np.ndarray]], Iterable[np.ndarray]] | None = None,
) -> RouteMap:
    """The map of one round, or of several traversals of one route (one layer each).

    ``name`` defaults to the rounds' names joined by '+'. Image names are the round's, or
    ``ROUND/IMAGE`` for several rounds. ``images`` replaces the rounds' own images (e.g. paced
    for a background build); ``wrap`` wraps the image iterator (e.g. a progress bar).
    """
    if not rounds:
        raise MapError("a map needs at least one round")
    origin = rounds[0].origin
    if any(r.origin != origin for r in rounds[1:]):
        raise MapError("the rounds have different geodetic origins: give them one "
                       "dataset.json origin")
    it: Iterable[np.ndarray] = (images if images is not None else
                                (r.load_image(i) for r in rounds for i in range(len(r))))
    if wrap is not None:
        it = wrap(iter(it))
    multi = len(rounds) > 1
    return build_map(
        name or "+".join(r.name for r in rounds), it,
        np.concatenate([np.asarray(r.xy, float) for r in rounds]),
        [f"{r.name}/{n}" if multi else n for r in rounds for n in r.images],
        params=params, delta=delta, origin=origin,
        source=source if source is not None else {"rounds": [r.name for r in rounds]},
        prune_features=prune_features,
        layers=np.concatenate([np.full(len(r), k) for k, r in enumerate(rounds)]),
    )


def _arrays(m: RouteMap) -> dict[str, np.ndarray]:
    names = np.frombuffer(json.dumps(m.image_names).encode(), np.uint8)
    return {
        "positions": np.ascontiguousarray(m.positions, "<f8"),
        "offsets": np.ascontiguousarray(m.offsets, "<i8"),
        "codes": np.ascontiguousarray(m.codes, np.uint8),
        "keypoints": np.ascontiguousarray(m.keypoints, "<f4"),
        "image_names": names,
        "layers": np.ascontiguousarray(m.layers, "<i8"),
    }


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


def save_map(m: RouteMap, path: str | Path) -> Path:
    """Write the map atomically: a crash leaves the old file or none, never half of one."""
    path = Path(path)
    if path.suffix != SUFFIX:
        path = path.with_name(path.name + SUFFIX)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = _arrays(m)
    layout, offset = {}, 0
    for key, arr in arrays.items():
        layout[key] = {"dtype": arr.dtype.str, "shape": list(arr.shape), "offset": offset,
                       "nbytes": int(arr.nbytes)}
        offset += arr.nbytes + _pad(arr.nbytes)
    header = {**m.meta, "name": m.name, "format_version": FORMAT_VERSION, "arrays": layout}
    digest = hashlib.sha256(_canonical(header))
    for arr in arrays.values():
        digest.update(_raw(arr))
    header["checksum"] = digest.hexdigest()
    head = json.dumps(header).encode()
    prefix = MAGIC + struct.pack("<Q", len(head)) + head
    prefix += b"\x00" * _pad(len(prefix))
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with tmp.open("wb") as fh:
            fh.write(prefix)
            for arr in arrays.values():
                fh.write(arr.tobytes())
                fh.write(b"\x00" * _pad(arr.nbytes))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    m.path = path
    return path


def _read_header(path: Path) -> tuple[dict, int]:
    try:
        with path.open("rb") as fh:
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


def load_map(path: str | Path, verify: bool = True) -> RouteMap:
    """Open a map memory-mapped; check version, layout and (by default) the checksum."""
    path = Path(path)
    if not path.is_file():
        raise MapError(f"{path}: no such map file")
    header, data_start = _read_header(path)
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise MapError(
            f"{path}: map format version {version} is not supported (this swarmloc reads "
            f"version {FORMAT_VERSION}); rebuild it with 'swarmloc map build'"
        )
    size = path.stat().st_size
    arrays: dict[str, np.ndarray] = {}
    try:
        layout = header["arrays"]
        for key, want in _DTYPES.items():
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
            arrays[key] = (np.memmap(path, dtype=dtype, mode="r", offset=begin, shape=shape)
                           if nbytes else np.zeros(shape, dtype))
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        if isinstance(exc, MapError):
            raise
        raise MapError(f"{path}: header does not describe the arrays ({exc})") from None
    if verify:
        digest = hashlib.sha256(_canonical(header))
        for arr in arrays.values():
            digest.update(_raw(arr))
        if digest.hexdigest() != header.get("checksum"):
            raise MapError(f"{path}: checksum mismatch, the file is corrupted; rebuild the map")
    positions = np.asarray(arrays["positions"])
    offsets = np.asarray(arrays["offsets"])
    n = len(positions)
    layers = np.asarray(arrays["layers"])
    if positions.ndim != 2 or positions.shape[1] != 2 or len(offsets) != n + 1 or \
            offsets[-1] != len(arrays["codes"]) or np.any(np.diff(offsets) < 0) or \
            len(layers) != n or (n and layers.min() < 0):
        raise MapError(f"{path}: inconsistent arrays (positions/offsets/codes/layers)")
    if not np.isfinite(positions).all():
        raise MapError(f"{path}: image positions are not all finite numbers (NaN or inf)")
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
    if codes.ndim != 2 or codes.shape[1] != 128 or kps.shape != (len(codes), 2):
        raise MapError(f"{path}: descriptor codes {codes.shape} / keypoints {kps.shape} do "
                       "not have the shapes (n, 128) / (n, 2)")
    delta, feature = header.get("delta"), header.get("feature")
    if not isinstance(delta, int | float) or not 0 < delta <= 1 or \
            not isinstance(feature, dict):
        raise MapError(f"{path}: header lacks valid matching parameters (delta, feature)")
    try:
        sp = SiftParams(**{k: v for k, v in feature.items() if k != "type"})
    except (TypeError, ValueError) as exc:
        raise MapError(f"{path}: feature parameters are invalid ({exc})") from None
    sizes = (sp.width, sp.height, sp.clahe_tile, sp.n_features)
    if not all(type(v) is int for v in sizes) or not (
            8 <= sp.width <= 8192 and 8 <= sp.height <= 8192 and 1 <= sp.clahe_tile <= 64
            and sp.n_features >= 0):
        raise MapError(f"{path}: feature parameters are invalid ({feature})")
    meta = {k: v for k, v in header.items() if k not in ("name",)}
    name = str(header.get("name", path.stem))
    return RouteMap(name, meta, positions, names, arrays["codes"], offsets,
                    arrays["keypoints"], path, layers)


def list_maps(directory: str | Path) -> list[Path]:
    directory = Path(directory)
    return sorted(p for p in directory.glob(f"*{SUFFIX}") if p.is_file())
