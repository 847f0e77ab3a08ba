"""CLAHE + RootSIFT features quantised to uint8, for the matcher's tests and benchmarks.

The map's own extraction lives in ``service.features`` (its feature type is the lead's choice);
this is the recipe the matcher is measured on: CLAHE (clip 2, 8x8 tiles) on the working-size
grey image, all OpenCV SIFT features, RootSIFT ``sqrt(d / sum d)``, quantised as
``round(255 * r)`` to uint8.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.features import SiftParams, to_working_size


def rootsift_u8(image: np.ndarray, params: SiftParams | None = None) -> np.ndarray:
    """(N, 128) uint8 quantised RootSIFT descriptors of a frame (all features, CLAHE first)."""
    gray = to_working_size(image, params or SiftParams())
    gray = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(gray)
    _, d = cv2.SIFT_create().detectAndCompute(gray, None)
    if d is None:
        return np.zeros((0, 128), np.uint8)
    s = d.sum(axis=1, keepdims=True)
    d = d[s[:, 0] > 0]
    r = np.sqrt(d / d.sum(axis=1, keepdims=True))
    return np.round(255 * r).astype(np.uint8)


def unit_float(q: np.ndarray) -> np.ndarray:
    """The float path's input: uint8 descriptors L2-normalised to float32 unit vectors."""
    f = q.astype(np.float32)
    return f / np.linalg.norm(f, axis=1, keepdims=True)
