"""How a map file of format version 6 stores keypoints and the place index compactly.

A RootSIFT map feature is its 128-byte code; what else is stored per feature should stay
small (issue 29: at most 140 B per map feature). Version 6 stores

- **keypoints as fixed point**: uint16 holding ``round(x * scale)``, ``scale`` a power of two
  chosen from the working image size (1/32 px up to 2047 px, 1/4 px at 8192 px), 4 bytes
  instead of float32's 8. Decoding (``stored / scale``) is exact in float32, so a map's
  keypoints survive any number of save/load cycles unchanged;
- **the place index** compactly: its PCA projection, the map's largest fixed cost (4 MiB for
  RootSIFT), as int8 with a float32 scale per output dimension, and its descriptors as
  float16 (service/vision/place_index.py ``PlaceIndex.arrays``).

Built maps are rounded to the stored values in memory (route_map's ``_stack``, and the place
index as it is built), so a map behaves the same before and after it is saved.
"""

from __future__ import annotations

import math

import numpy as np

KEYPOINT_DTYPE = np.dtype("<u2")
MAX_KEYPOINT_SCALE = 32
_LIMIT = int(np.iinfo(np.uint16).max)


def keypoint_scale(width: int, height: int) -> int:
    """The power-of-two fixed-point scale for keypoints of an image of this working size: the
    finest (at most 1/32 px) whose largest coordinate still fits a uint16."""
    side = max(int(width), int(height), 1)
    return int(min(MAX_KEYPOINT_SCALE, 2 ** math.floor(math.log2(_LIMIT / side))))


def valid_keypoint_scale(scale: object) -> bool:
    return type(scale) is int and 1 <= scale <= MAX_KEYPOINT_SCALE and scale & (scale - 1) == 0


class KeypointRangeError(ValueError):
    """Keypoints outside the image cannot be stored at the map's fixed-point scale."""


def encode_keypoints(kps: np.ndarray, scale: int) -> np.ndarray:
    """(n, 2) float keypoints as uint16 fixed point. Coordinates down to half a pixel below
    zero are clamped to 0; below that, beyond the largest coordinate the scale stores, or
    not finite: KeypointRangeError."""
    q = np.rint(np.asarray(kps, np.float64) * scale)
    if q.size and not np.isfinite(q).all():
        raise KeypointRangeError("keypoints are not finite numbers")
    if q.size and (q.min() < -scale / 2 or q.max() > _LIMIT):
        raise KeypointRangeError(
            f"keypoints span {float(np.min(kps)):.1f}..{float(np.max(kps)):.1f} px, outside "
            f"0..{_LIMIT / scale:.0f} px that the map stores at 1/{scale} px")
    return np.clip(q, 0, _LIMIT).astype(KEYPOINT_DTYPE)


def decode_keypoints(raw: np.ndarray, scale: int) -> np.ndarray:
    """Float32 keypoints of uint16 fixed point (exact: a power-of-two scale)."""
    return np.asarray(raw, np.float32) * np.float32(1.0 / scale)


class FixedPointKeypoints:
    """A map's (total, 2) keypoints stored as uint16 fixed point (memory-mapped), decoded to
    float32 slice by slice: ``kps[a:b]`` is what the rest of the service reads."""

    def __init__(self, raw: np.ndarray, scale: int) -> None:
        self.raw = raw
        self.scale = scale

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.raw.shape)

    def __len__(self) -> int:
        return len(self.raw)

    def __getitem__(self, key: slice) -> np.ndarray:
        return decode_keypoints(self.raw[key], self.scale)


Keypoints = np.ndarray | FixedPointKeypoints  # how a map holds its (total, 2) keypoints
