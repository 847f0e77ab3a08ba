"""Map files of the formats before version 6 (3: RootSIFT, 4: XFeat, 5: both), written from a
loaded map the way those versions stored it: float32 keypoints, a float32 place projection and
descriptors, no keypoint scale. The current writer writes version 6 only, so the tests that
older maps still load need these files."""

from __future__ import annotations

import hashlib
import itertools
import json
import struct
from pathlib import Path

import numpy as np

from service.maps.route_map import (
    MAGIC,
    RouteMap,
    _canonical,
    _image_digest,
    _pad,
)


def _digests(codes: np.ndarray, kps: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    return np.stack([np.frombuffer(_image_digest(codes[a:b], kps[a:b]), np.uint8)
                     for a, b in itertools.pairwise(offsets)])


def write_legacy(m: RouteMap, path: Path, version: int) -> Path:
    """``m`` as a map file of format ``version`` (3, 4 or 5, as fits its feature type)."""
    n = m.n_images
    codes, kps = np.asarray(m.codes), m.keypoints[0: len(m.codes)]
    arrays: dict[str, np.ndarray] = {
        "positions": np.ascontiguousarray(m.positions, "<f8"),
        "offsets": np.ascontiguousarray(m.offsets, "<i8"),
        "image_names": np.frombuffer(json.dumps(m.image_names).encode(), np.uint8),
        "layers": np.ascontiguousarray(m.layers, "<i8")}
    if m.place_index is not None:
        p = m.place_index
        arrays.update({"place_words": np.ascontiguousarray(p.words, "<f4"),
                       "place_mean": np.ascontiguousarray(p.mean, "<f4"),
                       "place_projection": np.ascontiguousarray(p.projection, "<f4"),
                       "place_descriptors": np.ascontiguousarray(p.descriptors, "<f4")})
    arrays.update({"codes": np.ascontiguousarray(codes),
                   "keypoints": np.ascontiguousarray(kps, "<f4"),
                   "image_digests": _digests(codes, kps, np.asarray(m.offsets))})
    if m.second is not None:
        s = m.second
        codes2, kps2 = np.asarray(s.codes), s.keypoints[0: len(s.codes)]
        arrays.update({"offsets2": np.ascontiguousarray(s.offsets, "<i8"),
                       "codes2": np.ascontiguousarray(codes2),
                       "keypoints2": np.ascontiguousarray(kps2, "<f4"),
                       "image_digests2": _digests(codes2, kps2, np.asarray(s.offsets))})
    assert all(len(a) for a in arrays.values()) and n
    layout, off = {}, 0
    for k, a in arrays.items():
        layout[k] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": off,
                     "nbytes": a.nbytes, "sha256": hashlib.sha256(a.tobytes()).hexdigest()}
        off += a.nbytes + _pad(a.nbytes)
    drop = ("arrays", "checksum", "keypoint_scale", "format_version")
    header = {k: v for k, v in m.meta.items() if k not in drop}
    header.update({"name": m.name, "format_version": version, "arrays": layout})
    header["checksum"] = hashlib.sha256(_canonical(header)).hexdigest()
    head = json.dumps(header).encode()
    prefix = MAGIC + struct.pack("<Q", len(head)) + head
    blob = b"".join(a.tobytes() + b"\x00" * _pad(a.nbytes) for a in arrays.values())
    path.write_bytes(prefix + b"\x00" * _pad(len(prefix)) + blob)
    return path
